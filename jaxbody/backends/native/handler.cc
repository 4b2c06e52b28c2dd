
#include <atomic>
#include <pthread.h>
#include <sched.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
// POSIX threads, mutexes and condition variables rather than <thread>, <mutex>,
// <condition_variable> and <unordered_map>: those headers were more than half of this file's
// build, which a new user's first call waits for
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
// a held mutex, released at the end of its scope
struct Locked {
  pthread_mutex_t* m;
  explicit Locked(pthread_mutex_t* m) : m(m) { pthread_mutex_lock(m); }
  ~Locked() { pthread_mutex_unlock(m); }
  Locked(const Locked&) = delete;
  Locked& operator=(const Locked&) = delete;
};

static inline int64_t monotonic_ns() {
  timespec now;
  clock_gettime(CLOCK_MONOTONIC, &now);
  return int64_t(now.tv_sec) * 1000000000 + now.tv_nsec;
}

class Pool {
 public:
  void run(Range range, const Inputs* in, int64_t batch, int64_t threads) {
    Locked call(&call_);  // one batch at a time (XLA may call from several devices)
    grow(threads - 1);
    if (threads > workers_ + 1) threads = workers_ + 1;  // a worker could not be started
    const int64_t chunk = (batch + threads - 1) / threads;
    range_ = range, in_ = in, batch_ = batch, chunk_ = chunk, slices_ = threads;
    pending_.store(workers_, std::memory_order_relaxed);
    {
      Locked lock(&m_);
      generation_.fetch_add(1, std::memory_order_release);  // publishes the fields above
    }
    pthread_cond_broadcast(&cv_);  // no system call when every worker is spinning
    range(in, 0, chunk < batch ? chunk : batch);
    auto done = [&] { return pending_.load(std::memory_order_acquire) == 0; };
    if (!spin(done)) {
      Locked lock(&m_);
      while (!done()) pthread_cond_wait(&done_, &m_);
    }
  }

 private:
  static constexpr int64_t SPIN_NS = @SPIN_NS@;
  template <class Ready>
  static bool spin(Ready ready) {
    if (ready()) return true;
    const int64_t until = monotonic_ns() + SPIN_NS;
    for (;;) {
      for (int k = 0; k < 16; ++k) {
        if (ready()) return true;
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#endif
      }
      if (monotonic_ns() > until) return ready();
      sched_yield();  // a core shared with other work gets it back at once
    }
  }
  struct Start {
    Pool* pool;
    int64_t slot;
    uint64_t seen;
  };
  static void* start(void* arg) {
    const Start s = *static_cast<Start*>(arg);
    delete static_cast<Start*>(arg);
    s.pool->work(s.slot, s.seen);
    return nullptr;
  }
  void grow(int64_t n) {
    while (workers_ < n) {
      // a new worker starts at the calls made so far: the next one is its first
      Start* s = new Start{this, workers_ + 1, generation_.load(std::memory_order_relaxed)};
      pthread_t thread;
      if (pthread_create(&thread, nullptr, start, s) != 0) {
        delete s;
        return;  // fewer workers: run() cuts the batch into fewer slices
      }
      pthread_detach(thread);
      ++workers_;
    }
  }
  void work(int64_t slot, uint64_t seen) {
    for (;;) {
      auto fresh = [&] { return generation_.load(std::memory_order_acquire) != seen; };
      if (!spin(fresh)) {
        Locked lock(&m_);
        while (!fresh()) pthread_cond_wait(&cv_, &m_);
      }
      seen = generation_.load(std::memory_order_acquire);
      if (slot < slices_) {
        const int64_t b0 = slot * chunk_, b1 = b0 + chunk_ < batch_ ? b0 + chunk_ : batch_;
        if (b0 < b1) range_(in_, b0, b1);
      }
      if (pending_.fetch_sub(1, std::memory_order_acq_rel) == 1) {
        Locked lock(&m_);  // the caller checks pending_ under m_ before it sleeps
        pthread_cond_signal(&done_);
      }
    }
  }
  pthread_mutex_t call_ = PTHREAD_MUTEX_INITIALIZER, m_ = PTHREAD_MUTEX_INITIALIZER;
  pthread_cond_t cv_ = PTHREAD_COND_INITIALIZER, done_ = PTHREAD_COND_INITIALIZER;
  int64_t workers_ = 0;  // detached worker threads started (they run until the process ends)
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
// A process registers tens of programs: a list searched under the lock (a thread's last
// program is looked up without it) serves as well as a hash map.
struct Registered {
  int64_t key;
  Range range;
};
static pthread_mutex_t registry_m = PTHREAD_MUTEX_INITIALIZER;
static std::atomic<uint64_t> registry_generation{0};
static Registered* registry = nullptr;  // never freed: threads may look up until the process ends
static int64_t registry_size = 0, registry_capacity = 0;

static Registered* find(int64_t key) {  // under registry_m
  for (int64_t i = 0; i < registry_size; ++i)
    if (registry[i].key == key) return &registry[i];
  return nullptr;
}

extern "C" void jaxbody_register(int64_t key, void* range) {
  Locked lock(&registry_m);
  Registered* entry = find(key);
  if (!entry) {
    if (registry_size == registry_capacity) {
      const int64_t capacity = registry_capacity ? 2 * registry_capacity : 64;
      auto* grown = static_cast<Registered*>(realloc(registry, sizeof(Registered) * capacity));
      if (!grown) return;  // out of memory: the program stays unregistered (its call reports so)
      registry = grown, registry_capacity = capacity;
    }
    entry = &registry[registry_size++];
    entry->key = key;
  }
  entry->range = reinterpret_cast<Range>(range);
  registry_generation.fetch_add(1, std::memory_order_release);
}

static Range lookup(int64_t key) {
  // the thread's last program first: a solver loop calls one program many times
  thread_local int64_t last_key = 0;
  thread_local Range last = nullptr;
  thread_local uint64_t seen = 0;
  const uint64_t generation = registry_generation.load(std::memory_order_acquire);
  if (key == last_key && last && generation == seen) return last;
  Locked lock(&registry_m);
  const Registered* entry = find(key);
  if (!entry) return nullptr;
  last_key = key, last = entry->range, seen = generation;
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
