// The run-time check of jaxbody's inputs: an XLA FFI handler that fails the running program with
// INVALID_ARGUMENT and the message of the first check that failed, so that the error's first
// line is jaxbody's message (a host callback's error reaches the user as INTERNAL, with the
// message many lines down).
//
// Written against XLA's C API alone (xla/ffi/api/c_api.h): the C++ binding (ffi.h) takes about
// 1 s to compile, this file a few hundredths, and the library is built on a user's first call.
//
// Call: arguments (flags, x), result x (aliased to the argument), string attribute "messages".
// flags: booleans (..., n), one per check, the leading axes a vmap batch; messages: n lines.
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "xla/ffi/api/c_api.h"

static XLA_FFI_Error* make_error(const XLA_FFI_Api* api, XLA_FFI_Error_Code code, const char* message) {
  XLA_FFI_Error_Create_Args args = {XLA_FFI_Error_Create_Args_STRUCT_SIZE, nullptr, message, code};
  return api->XLA_FFI_Error_Create(&args);
}

// bytes of one element of the result (the dtypes a checked array may have)
static int64_t item_bytes(XLA_FFI_DataType dtype) {
  switch (dtype) {
    case XLA_FFI_DataType_PRED: case XLA_FFI_DataType_S8: case XLA_FFI_DataType_U8: return 1;
    case XLA_FFI_DataType_S16: case XLA_FFI_DataType_U16: case XLA_FFI_DataType_F16: case XLA_FFI_DataType_BF16: return 2;
    case XLA_FFI_DataType_S32: case XLA_FFI_DataType_U32: case XLA_FFI_DataType_F32: return 4;
    case XLA_FFI_DataType_S64: case XLA_FFI_DataType_U64: case XLA_FFI_DataType_F64: case XLA_FFI_DataType_C64: return 8;
    case XLA_FFI_DataType_C128: return 16;
    default: return 0;
  }
}

extern "C" XLA_FFI_Error* jaxbody_check(XLA_FFI_CallFrame* frame) {
  const XLA_FFI_Api* api = frame->api;
  // XLA asks a handler for the API version it was built against before calling it
  if (frame->extension_start && frame->extension_start->type == XLA_FFI_Extension_Metadata) {
    XLA_FFI_Metadata_Extension* ext = (XLA_FFI_Metadata_Extension*)frame->extension_start;
    ext->metadata->api_version = XLA_FFI_Api_Version{XLA_FFI_Api_Version_STRUCT_SIZE, nullptr, XLA_FFI_API_MAJOR,
                                                     XLA_FFI_API_MINOR};
    ext->metadata->traits = 0;
    return nullptr;
  }
  if (frame->stage != XLA_FFI_ExecutionStage_EXECUTE) return nullptr;
  if (frame->args.size != 2 || frame->rets.size != 1 || frame->attrs.size != 1 ||
      frame->attrs.types[0] != XLA_FFI_AttrType_STRING)
    return make_error(api, XLA_FFI_Error_Code_INTERNAL,
                      "jaxbody's run-time check was called with other than 2 arguments, 1 result and 1 string attribute");
  const XLA_FFI_Buffer* flags = (const XLA_FFI_Buffer*)frame->args.args[0];
  const XLA_FFI_Buffer* x = (const XLA_FFI_Buffer*)frame->args.args[1];
  const XLA_FFI_Buffer* out = (const XLA_FFI_Buffer*)frame->rets.rets[0];
  const XLA_FFI_ByteSpan* messages = (const XLA_FFI_ByteSpan*)frame->attrs.attrs[0];
  const int64_t n = flags->rank ? flags->dims[flags->rank - 1] : 1;
  int64_t total = 1;
  for (int64_t d = 0; d < flags->rank; ++d) total *= flags->dims[d];
  const int64_t members = n ? total / n : 0;
  const bool* f = (const bool*)flags->data;
  // the first member (in row-major order over the batch axes) that failed, and its first check
  for (int64_t i = 0; i < members; ++i)
    for (int64_t j = 0; j < n; ++j) {
      if (!f[i * n + j]) continue;
      const char *m = messages->ptr, *end = messages->ptr + messages->len;
      for (int64_t k = 0; k < j && m && m < end; ++k) {
        m = (const char*)memchr(m, '\n', end - m);
        if (m) ++m;
      }
      if (!m) m = end;
      const char* stop = (const char*)memchr(m, '\n', end - m);
      const int len = (int)((stop ? stop : end) - m);
      // the message and its member, whatever their length (XLA copies the text into its status)
      const size_t size = (size_t)len + 80;
      char* text = (char*)malloc(size);
      if (!text) return make_error(api, XLA_FFI_Error_Code_INVALID_ARGUMENT, "jaxbody: an input check failed");
      if (flags->rank > 1)
        snprintf(text, size, "%.*s (batch member %lld of %lld)", len, m, (long long)i, (long long)members);
      else
        snprintf(text, size, "%.*s", len, m);
      XLA_FFI_Error* err = make_error(api, XLA_FFI_Error_Code_INVALID_ARGUMENT, text);
      free(text);
      return err;
    }
  // the result is aliased to x; should XLA give it a buffer of its own, copy
  if (out->data != x->data) {
    int64_t bytes = item_bytes(x->dtype);
    if (!bytes) return make_error(api, XLA_FFI_Error_Code_INTERNAL, "jaxbody's run-time check: unsupported dtype");
    for (int64_t d = 0; d < x->rank; ++d) bytes *= x->dims[d];
    memcpy(out->data, x->data, (size_t)bytes);
  }
  return nullptr;
}
