
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <unordered_map>
#include <vector>
#include <string.h>
// XLA's C API alone: its C++ binding (ffi.h) takes about a second and a half to compile, this
// whole file a fraction of that, and the handler is built on a new user's first call
#include "xla/ffi/api/c_api.h"
@COMMON@
constexpr XLA_FFI_DataType DT = @DT@;

// A persistent pool: a batch is cut into as many slices as threads; the calling thread runs
// the first, the workers the others (starting threads on every call would cost as much as a
// few hundred states). Between calls the workers spin (yielding the core to any other
// runnable thread) for up to SPIN_NS before they sleep on a condition variable, and so does the
// caller waiting for them: the next call of a simulation comes a few tens of microseconds after
// the last (the integrator's own work on the batch), and waking a sleeping thread costs as much
// on a virtual machine. Every worker acknowledges every call, so a call's fields stay valid
// until all of them have read them.
class Pool {
 public:
  void run(Range range, const Inputs* in, int64_t batch, int64_t threads) {
    std::lock_guard<std::mutex> call(call_);  // one batch at a time (XLA may call from several devices)
    grow(threads - 1);
    const int64_t chunk = (batch + threads - 1) / threads;
    range_ = range, in_ = in, batch_ = batch, chunk_ = chunk, slices_ = threads;
    pending_.store(int64_t(workers_.size()), std::memory_order_relaxed);
    {
      std::lock_guard<std::mutex> lock(m_);
      generation_.fetch_add(1, std::memory_order_release);  // publishes the fields above
    }
    cv_.notify_all();  // no system call when every worker is spinning
    range(in, 0, chunk < batch ? chunk : batch);
    if (!spin([&] { return pending_.load(std::memory_order_acquire) == 0; })) {
      std::unique_lock<std::mutex> lock(m_);
      done_.wait(lock, [&] { return pending_.load(std::memory_order_acquire) == 0; });
    }
  }

 private:
  static constexpr int64_t SPIN_NS = @SPIN_NS@;
  template <class Ready>
  static bool spin(Ready ready) {
    if (ready()) return true;
    const auto until = std::chrono::steady_clock::now() + std::chrono::nanoseconds(SPIN_NS);
    for (;;) {
      for (int k = 0; k < 16; ++k) {
        if (ready()) return true;
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#endif
      }
      if (std::chrono::steady_clock::now() > until) return ready();
      std::this_thread::yield();  // a core shared with other work gets it back at once
    }
  }
  void grow(int64_t n) {
    while (int64_t(workers_.size()) < n) {
      const int64_t slot = int64_t(workers_.size()) + 1;
      // a new worker starts at the calls made so far: the next one is its first
      const uint64_t seen = generation_.load(std::memory_order_relaxed);
      workers_.emplace_back([this, slot, seen] { work(slot, seen); });
      workers_.back().detach();
    }
  }
  void work(int64_t slot, uint64_t seen) {
    for (;;) {
      auto fresh = [&] { return generation_.load(std::memory_order_acquire) != seen; };
      if (!spin(fresh)) {
        std::unique_lock<std::mutex> lock(m_);
        cv_.wait(lock, fresh);
      }
      seen = generation_.load(std::memory_order_acquire);
      if (slot < slices_) {
        const int64_t b0 = slot * chunk_, b1 = b0 + chunk_ < batch_ ? b0 + chunk_ : batch_;
        if (b0 < b1) range_(in_, b0, b1);
      }
      if (pending_.fetch_sub(1, std::memory_order_acq_rel) == 1) {
        std::lock_guard<std::mutex> lock(m_);  // the caller checks pending_ under m_ before it sleeps
        done_.notify_one();
      }
    }
  }
  std::mutex call_, m_;
  std::condition_variable cv_, done_;
  std::vector<std::thread> workers_;
  Range range_ = nullptr;
  const Inputs* in_ = nullptr;
  int64_t batch_ = 0, chunk_ = 0, slices_ = 0;
  std::atomic<int64_t> pending_{0};
  std::atomic<uint64_t> generation_{0};
};

static Pool* pool() {
  static Pool* p = new Pool();  // never destroyed: workers outlive static destruction
  return p;
}

// The compiled programs loaded in this process, by a key derived from their source's hash.
// A traced call names its program by that key, not by its address: the address changes from
// one process to the next, and a program in JAX's persistent compilation cache, made in
// another process, must find this process's copy of the same program (and never another's).
// A key is registered again when a program's optimised build replaces its quick first one:
// the generation counts registrations, so that a thread's remembered program is looked up anew.
static std::mutex registry_m;
static std::atomic<uint64_t> registry_generation{0};
static std::unordered_map<int64_t, Range>& registry() {
  static auto* r = new std::unordered_map<int64_t, Range>();
  return *r;
}

extern "C" void jaxbody_register(int64_t key, void* range) {
  std::lock_guard<std::mutex> lock(registry_m);
  registry()[key] = reinterpret_cast<Range>(range);
  registry_generation.fetch_add(1, std::memory_order_release);
}

static Range lookup(int64_t key) {
  // the thread's last program first: a solver loop calls one program many times
  thread_local int64_t last_key = 0;
  thread_local Range last = nullptr;
  thread_local uint64_t seen = 0;
  const uint64_t generation = registry_generation.load(std::memory_order_acquire);
  if (key == last_key && last && generation == seen) return last;
  std::lock_guard<std::mutex> lock(registry_m);
  auto it = registry().find(key);
  if (it == registry().end()) return nullptr;
  last_key = key, last = it->second, seen = generation;
  return last;
}

static XLA_FFI_Error* fail(const XLA_FFI_Api* api, const char* message) {
  XLA_FFI_Error_Create_Args args = {XLA_FFI_Error_Create_Args_STRUCT_SIZE, nullptr, message,
                                    XLA_FFI_Error_Code_INVALID_ARGUMENT};
  return api->XLA_FFI_Error_Create(&args);
}

// The int64 scalar attribute `name` of the call (nullptr where there is none).
static const int64_t* attribute(const XLA_FFI_CallFrame* frame, const char* name) {
  const size_t len = strlen(name);
  for (int64_t k = 0; k < frame->attrs.size; ++k) {
    const XLA_FFI_ByteSpan* key = frame->attrs.names[k];
    if (frame->attrs.types[k] != XLA_FFI_AttrType_SCALAR || key->len != len || memcmp(key->ptr, name, len) != 0) continue;
    const XLA_FFI_Scalar* value = static_cast<const XLA_FFI_Scalar*>(frame->attrs.attrs[k]);
    return value->dtype == XLA_FFI_DataType_S64 ? static_cast<const int64_t*>(value->value) : nullptr;
  }
  return nullptr;
}

// The call: operands (B_k, n_k) and results (B, n_j) of the kernel's dtype, attributes "kernel"
// (the program's key) and "threads".
extern "C" XLA_FFI_Error* jaxbody_fd(XLA_FFI_CallFrame* frame) {
  const XLA_FFI_Api* api = frame->api;
  // XLA asks a handler for the API version it was built against before calling it
  if (frame->extension_start && frame->extension_start->type == XLA_FFI_Extension_Metadata) {
    auto* ext = reinterpret_cast<XLA_FFI_Metadata_Extension*>(frame->extension_start);
    ext->metadata->api_version = XLA_FFI_Api_Version{XLA_FFI_Api_Version_STRUCT_SIZE, nullptr, XLA_FFI_API_MAJOR,
                                                     XLA_FFI_API_MINOR};
    ext->metadata->traits = 0;
    return nullptr;
  }
  if (frame->stage != XLA_FFI_ExecutionStage_EXECUTE) return nullptr;
  const int64_t* kernel = attribute(frame, "kernel");
  const int64_t* threads = attribute(frame, "threads");
  if (!kernel || !threads) return fail(api, "jaxbody native kernel: int64 attributes 'kernel' and 'threads' expected");
  const Range range = lookup(*kernel);
  if (!range) return fail(api, "jaxbody native kernel: program not loaded in this process");
  if (frame->args.size > MAX_IN || frame->rets.size > MAX_OUT || frame->rets.size == 0)
    return fail(api, "jaxbody native kernel: too many operands");
  Inputs in{};
  for (int64_t k = 0; k < frame->args.size; ++k) {
    const auto* x = static_cast<const XLA_FFI_Buffer*>(frame->args.args[k]);
    if (frame->args.types[k] != XLA_FFI_ArgType_BUFFER || x->dtype != DT || x->rank != 2)
      return fail(api, "jaxbody native kernel: operands are 2-D, of the kernel's dtype");
    in.x[k] = static_cast<const T*>(x->data);
    in.s[k] = x->dims[0] == 1 ? 0 : x->dims[1];
  }
  int64_t batch = 0;
  for (int64_t j = 0; j < frame->rets.size; ++j) {
    const auto* y = static_cast<const XLA_FFI_Buffer*>(frame->rets.rets[j]);
    if (frame->rets.types[j] != XLA_FFI_RetType_BUFFER || y->dtype != DT || y->rank != 2)
      return fail(api, "jaxbody native kernel: results are 2-D, of the kernel's dtype");
    in.y[j] = static_cast<T*>(y->data);
    batch = y->dims[0];
    in.n[j] = y->dims[1];
  }
  // one slice per thread for batches worth it (at least 64 states a slice)
  int64_t n = *threads < batch / 64 ? *threads : batch / 64;
  if (n <= 1) range(&in, 0, batch);
  else pool()->run(range, &in, batch, n);
  return nullptr;
}
