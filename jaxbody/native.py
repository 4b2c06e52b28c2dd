"""The native kernel: forward dynamics of a tree compiled to machine code, called from XLA.

XLA's CPU backend runs a traced program as a sequence of fused loops, each writing its
outputs to memory; for multibody dynamics — thousands of scalar operations along short
chains of bodies — that is dominated by memory traffic and per-loop overhead, not by
arithmetic (docs/performance.md). The native kernel removes both: the same algorithm as
the unrolled kernel (:mod:`jaxbody.unrolled`: kinematics root to leaves, composite
(augmented) inertias and subtree forces leaves to root, the tree-sparse ``LᵀDL``
factorisation), written out at build time for the model's static tree, is emitted as C++
and compiled once per tree with the system's C++ compiler. Every intermediate stays in
registers; one call evaluates a whole batch of states, split over the CPU cores.

How it plugs into JAX:

* **Code generation.** :func:`jaxbody.unrolled._bias_and_mass` and ``_ltdl_solve`` run on
  *symbolic* scalars (:class:`_Sym`) instead of arrays; every operation appends one line
  of C++. Structural zeros and ones are folded as in the unrolled kernel and repeated
  expressions are shared. The model's parameters (offsets, axes, masses, centres of mass,
  inertias, armature, ``qpos0``) are *inputs* of the compiled function, not constants, so
  one compilation serves every parameter value, batches over parameters and gradients
  with respect to them.
* **XLA FFI.** The compiled function is registered as an XLA foreign-function target
  (:func:`jax.ffi.ffi_call`); XLA calls it inside jitted programs and solver loops.
* **Batches.** A :func:`jax.custom_batching.custom_vmap` rule turns ``vmap`` (nested or
  not) into one call over the stacked states; inputs that are not batched (the model under
  a ``vmap`` over states) are passed once and read with stride zero.
* **Derivatives.** A :func:`jax.custom_jvp` rule takes the value from the native call and
  the tangent from the vectorised JAX kernel (:mod:`jaxbody.kernels`), which computes the
  same function: ``jvp``, ``grad`` (any adjoint) and higher derivatives work, with respect
  to the state and to every model parameter.

It needs a C++17 compiler (``g++``, or ``$CXX``) when a tree is first used; compiled
kernels are cached in ``$JAXBODY_CACHE_DIR`` (default ``~/.cache/jaxbody``) under a hash of
their source. :func:`available` says whether the kernel can be used here; with
``kernel="auto"`` jaxbody falls back to the vectorised kernel where it cannot.
"""

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from . import unrolled
from ._types import Array, ArrayLike, Float
from .model import Model

__all__ = ["MAX_DOFS", "applies", "available", "forward_dynamics", "parameter_vector", "threads"]

#: Largest number of DoFs ``kernel="auto"`` gives the native kernel. The generated code grows
#: with the mass-matrix entries on each DoF's ancestor chain and their factorisation (for a
#: chain, quadratically and cubically): the 7-DoF Panda arm compiles in about 4 s, a 20-link
#: chain in about 25 s (once; cached on disk). Above this the vectorised kernel (whose program
#: does not grow with the tree) serves.
MAX_DOFS = 24

_lock = threading.Lock()


# ----------------------------------------------------------------------------- symbolic scalars
class _Emitter:
    """Collects the lines of one generated function and shares repeated expressions."""

    def __init__(self):
        self.lines: list[str] = []
        self.memo: dict[str, "_Sym"] = {}

    def emit(self, expr: str) -> "_Sym":
        sym = self.memo.get(expr)
        if sym is None:
            name = f"t{len(self.lines)}"
            self.lines.append(f"const U {name} = {expr};")
            sym = self.memo[expr] = _Sym(name, self)
        return sym


def _sincos(em, x):
    key = f"sincos({x.name})"
    pair = em.memo.get(key)
    if pair is None:
        n = len(em.lines)
        em.lines.append(f"U s{n}, c{n}; sc({x.name}, s{n}, c{n});")
        pair = em.memo[key] = (_Sym(f"s{n}", em), _Sym(f"c{n}", em))
    return pair


_Emitter.sincos = _sincos


def _lit(x) -> str:
    if isinstance(x, _Sym):
        return x.name
    return f"T({float(x)!r})"


class _Sym:
    """A scalar of the generated program: a C++ name; arithmetic emits code.

    Python floats mixed in are constants known at generation time (the unrolled kernel's
    structural ``0.0``/``1.0``); they fold as in :func:`jaxbody.unrolled._add` and friends.
    """

    symbolic = True
    __slots__ = ("name", "em")

    def __init__(self, name: str, em: _Emitter):
        self.name, self.em = name, em

    def _bin(self, op: str, a, b, commutative: bool):
        x, y = _lit(a), _lit(b)
        if commutative and y < x:
            x, y = y, x
        return self.em.emit(f"{x} {op} {y}")

    def __add__(self, o):
        if isinstance(o, float | int) and o == 0:
            return self
        return self._bin("+", self, o, True)

    __radd__ = __add__

    def __sub__(self, o):
        if isinstance(o, float | int) and o == 0:
            return self
        return self._bin("-", self, o, False)

    def __rsub__(self, o):
        if isinstance(o, float | int) and o == 0:
            return -self
        return self._bin("-", o, self, False)

    def __mul__(self, o):
        if isinstance(o, float | int):
            if o == 0:
                return 0.0
            if o == 1:
                return self
        return self._bin("*", self, o, True)

    __rmul__ = __mul__

    def __truediv__(self, o):
        if isinstance(o, float | int) and o == 1:
            return self
        return self._bin("/", self, o, False)

    def __rtruediv__(self, o):
        return self._bin("/", o, self, False)

    def __neg__(self):
        return self.em.emit(f"-{self.name}")

    def cos(self):
        return self.em.sincos(self)[1]

    def sin(self):
        return self.em.sincos(self)[0]


class _SymbolicModel:
    """What the unrolled passes read of a model, with every parameter a symbol ``p[i]``."""

    FIELDS = ("body_pos", "body_quat", "body_mass", "body_com", "body_inertia", "joint_pos", "joint_axis", "dof_armature", "qpos0")

    def __init__(self, tree, joints, em: _Emitter):
        self.tree, self.joints = tree, joints
        self.n_body, self.nv, self.nq = tree.n_body, joints.nv, joints.nq
        sizes = [int(np.prod(shape)) for shape in _field_shapes(tree, joints)]
        p = _inputs(em, "p", sum(sizes))
        offset = 0
        for name, shape, size in zip(self.FIELDS, _field_shapes(tree, joints), sizes):
            syms = np.empty(size, dtype=object)
            syms[:] = p[offset : offset + size]
            setattr(self, name, syms.reshape(shape))
            offset += size


def _inputs(em: _Emitter, name: str, n: int) -> list:
    """``n`` scalars of input ``name``, loaded (one lane per state) at the top of the block."""
    out = []
    for i in range(n):
        em.lines.append(f"const U {name}_{i} = ld(in.{name}, in.s{name[0]}, {i});")
        out.append(_Sym(f"{name}_{i}", em))
    return out


def _field_shapes(tree, joints):
    nb, nj = tree.n_body, joints.n_joint
    return ((nb, 3), (nb, 4), (nb,), (nb, 3), (nb, 3, 3), (nj, 3), (nj, 3), (joints.nv,), (joints.nq,))


def parameter_vector(model: Model) -> Float[Array, " n_param"]:
    """The model's parameters flattened in the order the native kernel reads them."""
    return jnp.concatenate([jnp.ravel(getattr(model, name)) for name in _SymbolicModel.FIELDS])


# ----------------------------------------------------------------------------- code generation
# Two translation units: the per-tree kernel (plain C++, quick to compile) and, once per dtype,
# the XLA FFI handler (XLA's FFI headers take longer to parse than a small tree takes to
# optimise). The handler receives the kernel's address as a call attribute.
_COMMON = r"""
#include <cstdint>
using T = @T@;
// input x of state b: x + b * stride (rows of a (batch, n) array); stride 0 = shared by all states
struct Inputs {
  const T *q, *v, *f, *p, *g, *ext;
  int64_t sq, sv, sf, sp, sg, se;
};
typedef void (*Range)(const Inputs*, int64_t, int64_t, T*);
"""

_KERNEL = r"""
#include <cmath>
#include <type_traits>
@COMMON@
constexpr int NV = @NV@;
constexpr int W = 32 / sizeof(T);  // states per block: one AVX register of lanes
typedef T V __attribute__((vector_size(sizeof(T) * W)));
typedef std::conditional<sizeof(T) == 8, int64_t, int32_t>::type IntT;
typedef IntT I __attribute__((vector_size(sizeof(T) * W)));

// sine and cosine of every lane: Cody-Waite reduction by pi/2 (two-part constant, fused
// multiply-adds) and Cephes' minimax polynomials on [-pi/4, pi/4], about 1 ulp for the angles
// of joints (|x| < 1e5); larger angles (and NaN) go lane by lane through libm
static inline void sincos_(double x, double* s, double* c) { sincos(x, s, c); }
static inline void sincos_(float x, float* s, float* c) { sincosf(x, s, c); }

static inline void sincos_lanes(V x, V& s, V& c, int n) {
  T sl = 0, cl = 0;
  for (int l = 0; l < W; ++l) {
    if (l < n) {
      sincos_(x[l], &sl, &cl);
    }
    s[l] = sl;
    c[l] = cl;
  }
}

static inline void vsincos(V x, V& s, V& c, int n) {
  {
    bool small = true;
    for (int l = 0; l < W; ++l) small &= std::fabs(x[l]) < T(1e5);  // false for NaN: libm's NaN
    if (small) {
      // 1.5 * 2^(mantissa bits): adding it rounds to an integer, held in the low bits
      const T magic = sizeof(T) == 8 ? T(6755399441055744.0) : T(12582912.0f);
      const T pio2_hi = sizeof(T) == 8 ? T(1.5707963267948966) : T(1.57079637f);
      const T pio2_lo = sizeof(T) == 8 ? T(6.123233995736766e-17) : T(-4.37113883e-8f);
      const V shifted = x * T(0.63661977236758134308) + magic;
      const V k = shifted - magic;
      I quadrant;
      __builtin_memcpy(&quadrant, &shifted, sizeof(V));
      quadrant &= 3;
      V r = x - k * pio2_hi;  // contracted to a fused multiply-add
      r = r - k * pio2_lo;
      const V z = r * r;
      V ps = V{} + T(1.58962301576546568060e-10);
      ps = ps * z + T(-2.50507477628578072866e-8);
      ps = ps * z + T(2.75573136213857245213e-6);
      ps = ps * z + T(-1.98412698295895385996e-4);
      ps = ps * z + T(8.33333333332211858878e-3);
      ps = ps * z + T(-1.66666666666666307295e-1);
      V pc = V{} + T(-1.13585365213876817300e-11);
      pc = pc * z + T(2.08757008419747316778e-9);
      pc = pc * z + T(-2.75573141792967388112e-7);
      pc = pc * z + T(2.48015872888517045348e-5);
      pc = pc * z + T(-1.38888888888730564116e-3);
      pc = pc * z + T(4.16666666666665929218e-2);
      const V sr = r + r * z * ps;
      const V cr = T(1.0) - T(0.5) * z + z * z * pc;
      const I swap = (quadrant & 1) != 0;
      const V s0 = swap ? cr : sr, c0 = swap ? sr : cr;
      s = ((quadrant & 2) != 0) ? -s0 : s0;
      c = (((quadrant + 1) & 2) != 0) ? -c0 : c0;
      return;
    }
  }
  sincos_lanes(x, s, c, n);
}

// forward dynamics of the states b0 .. b0 + n - 1 (n <= W); lane l is state b0 + min(l, n - 1)
static void fd_block(const Inputs& in, int64_t b0, int n, T* __restrict out) {
  typedef V U;
  int64_t idx[W];
  for (int l = 0; l < W; ++l) idx[l] = b0 + (l < n ? l : n - 1);
  auto ld = [&](const T* x, int64_t stride, int i) {
    U r;
    for (int l = 0; l < W; ++l) r[l] = x[idx[l] * stride + i];
    return r;
  };
  auto st = [&](int i, U x) {
    for (int l = 0; l < n; ++l) out[(b0 + l) * NV + i] = x[l];
  };
  auto sc = [n](U x, U& s, U& c) { vsincos(x, s, c, n); };
@BODY@
}

extern "C" void jaxbody_fd_range(const Inputs* in, int64_t b0, int64_t b1, T* out) {
  for (int64_t b = b0; b < b1; b += W) fd_block(*in, b, b1 - b < W ? int(b1 - b) : W, out);
}
"""

_HANDLER = r"""
#include <atomic>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <vector>
#include "xla/ffi/api/ffi.h"
@COMMON@
namespace ffi = xla::ffi;
constexpr ffi::DataType DT = @DT@;

// A persistent pool: a batch is cut into as many slices as threads; the calling thread runs
// the first, the workers the others (starting threads on every call would cost as much as a
// few hundred states).
class Pool {
 public:
  void run(Range range, const Inputs* in, int64_t batch, T* out, int64_t threads) {
    std::lock_guard<std::mutex> call(call_);  // one batch at a time (XLA may call from several devices)
    grow(threads - 1);
    const int64_t chunk = (batch + threads - 1) / threads;
    {
      std::lock_guard<std::mutex> lock(m_);
      range_ = range, in_ = in, out_ = out, batch_ = batch, chunk_ = chunk, slices_ = threads;
      pending_ = threads - 1;
      ++generation_;
    }
    cv_.notify_all();
    range(in, 0, chunk < batch ? chunk : batch, out);
    std::unique_lock<std::mutex> lock(m_);
    done_.wait(lock, [&] { return pending_ == 0; });
  }

 private:
  void grow(int64_t n) {
    while (int64_t(workers_.size()) < n) {
      const int64_t slot = int64_t(workers_.size()) + 1;
      workers_.emplace_back([this, slot] { work(slot); });
      workers_.back().detach();
    }
  }
  void work(int64_t slot) {
    uint64_t seen = 0;
    for (;;) {
      std::unique_lock<std::mutex> lock(m_);
      cv_.wait(lock, [&] { return generation_ != seen; });
      seen = generation_;
      if (slot >= slices_) continue;
      const int64_t b0 = slot * chunk_, b1 = b0 + chunk_ < batch_ ? b0 + chunk_ : batch_;
      Range range = range_;
      const Inputs* in = in_;
      T* out = out_;
      lock.unlock();
      if (b0 < b1) range(in, b0, b1, out);
      lock.lock();
      if (--pending_ == 0) done_.notify_one();
    }
  }
  std::mutex call_, m_;
  std::condition_variable cv_, done_;
  std::vector<std::thread> workers_;
  Range range_ = nullptr;
  const Inputs* in_ = nullptr;
  T* out_ = nullptr;
  int64_t batch_ = 0, chunk_ = 0, slices_ = 0, pending_ = 0;
  uint64_t generation_ = 0;
};

static Pool* pool() {
  static Pool* p = new Pool();  // never destroyed: workers outlive static destruction
  return p;
}

template <typename B>
static int64_t stride(const B& x) {
  auto d = x.dimensions();
  return d[0] == 1 ? 0 : d[1];
}

static ffi::Error fd_impl(ffi::Buffer<DT> q, ffi::Buffer<DT> v, ffi::Buffer<DT> f, ffi::Buffer<DT> p,
                          ffi::Buffer<DT> g, ffi::Buffer<DT> ext, ffi::ResultBuffer<DT> out,
                          int64_t kernel, int64_t threads) {
  const Range range = reinterpret_cast<Range>(kernel);
  const int64_t batch = out->dimensions()[0];
  const Inputs in{q.typed_data(), v.typed_data(), f.typed_data(), p.typed_data(), g.typed_data(),
                  ext.typed_data(), stride(q), stride(v), stride(f), stride(p), stride(g), stride(ext)};
  // one slice per thread for batches worth it (at least 64 states a slice)
  int64_t n = threads < batch / 64 ? threads : batch / 64;
  if (n <= 1) range(&in, 0, batch, out->typed_data());
  else pool()->run(range, &in, batch, out->typed_data(), n);
  return ffi::Error::Success();
}

XLA_FFI_DEFINE_HANDLER_SYMBOL(jaxbody_fd, fd_impl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<DT>>()
                                  .Arg<ffi::Buffer<DT>>()
                                  .Arg<ffi::Buffer<DT>>()
                                  .Arg<ffi::Buffer<DT>>()
                                  .Arg<ffi::Buffer<DT>>()
                                  .Arg<ffi::Buffer<DT>>()
                                  .Ret<ffi::Buffer<DT>>()
                                  .Attr<int64_t>("kernel")
                                  .Attr<int64_t>("threads"));
"""

_SCALAR = {np.dtype(np.float64): ("double", "ffi::F64"), np.dtype(np.float32): ("float", "ffi::F32")}


def _generate(tree, joints, with_external: bool, dtype) -> str:
    """C++ source of forward dynamics for this tree (parameters, gravity, loads as inputs)."""
    em = _Emitter()
    model = _SymbolicModel(tree, joints, em)
    q = _inputs(em, "q", joints.nq)
    v = _inputs(em, "v", joints.nv)
    f = _inputs(em, "f", joints.nv)
    g = tuple(_inputs(em, "g", 3))
    ext = None
    if with_external:
        flat = _inputs(em, "ext", 6 * tree.n_body)
        ext = [tuple(flat[6 * b : 6 * b + 6]) for b in range(tree.n_body)]
    M, bias, lam = unrolled._bias_and_mass(model, q, v, g, ext)
    a = unrolled._ltdl_solve(M, lam, [fi - b for fi, b in zip(f, bias)])
    body = ["  " + line for line in em.lines]
    body += [f"  st({i}, {ai.name if isinstance(ai, _Sym) else f'U{{}} + T({float(ai)!r})'});" for i, ai in enumerate(a)]
    return (
        _KERNEL.replace("@COMMON@", _COMMON.replace("@T@", _SCALAR[np.dtype(dtype)][0]))
        .replace("@BODY@", "\n".join(body))
        .replace("@NV@", str(joints.nv))
    )


# ----------------------------------------------------------------------------- build and load
def _compiler() -> str | None:
    return shutil.which(os.environ.get("CXX", "g++"))


@functools.cache
def available() -> bool:
    """Whether the native kernel can be built here: a C++ compiler, XLA's FFI headers, a CPU."""
    include = Path(jax.ffi.include_dir()) / "xla" / "ffi" / "api" / "ffi.h"
    return _compiler() is not None and include.is_file() and jax.default_backend() == "cpu"


def applies(model: Model) -> bool:
    """Whether ``kernel="auto"`` gives ``model`` the native kernel (small enough, buildable)."""
    return 0 < model.nv <= MAX_DOFS and available()


def threads() -> int:
    """Threads one call splits a batch over: ``$JAXBODY_NATIVE_THREADS``, else the CPU count."""
    return int(os.environ.get("JAXBODY_NATIVE_THREADS", os.cpu_count() or 1))


def _cache_dir() -> Path:
    root = os.environ.get("JAXBODY_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "jaxbody")
    path = Path(root) / "native"
    path.mkdir(parents=True, exist_ok=True)
    return path


def _cpu_signature() -> str:
    # the library is built with -march=native: key it by the processor's instruction set too
    try:
        with open("/proc/cpuinfo") as fh:
            flags = next((line for line in fh if line.startswith("flags")), "")
    except OSError:
        flags = ""
    return platform.machine() + flags


# -ffp-contract=fast: fused multiply-adds; -fno-math-errno: sin/cos/sqrt without errno
_FLAGS = ("-O2", "-march=native", "-std=gnu++17", "-ffp-contract=fast", "-fno-math-errno", "-shared", "-fPIC", "-pthread", "-w")


def _build(source: str, stem: str) -> Path:
    """Compile ``source`` to a shared library in the cache (once per source, compiler and CPU)."""
    compiler = _compiler()
    if compiler is None:
        raise RuntimeError("the native kernel needs a C++ compiler (g++ or $CXX); use kernel='vectorised'")
    key = hashlib.sha256("\n".join((source, compiler, *_FLAGS, _cpu_signature(), jax.__version__)).encode()).hexdigest()[:24]
    target = _cache_dir() / f"{stem}_{key}.so"
    if target.is_file():
        return target
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        src = Path(tmp) / "src.cc"
        src.write_text(source)
        out = Path(tmp) / "lib.so"
        cmd = [compiler, *_FLAGS, f"-I{jax.ffi.include_dir()}", str(src), "-o", str(out)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"building the native kernel failed ({' '.join(cmd)}):\n{proc.stderr[-4000:]}")
        os.replace(out, target)  # atomic: concurrent builders of the same library agree
    return target


@functools.cache
def _handler(dtype) -> str:
    """The FFI target name of the (tree-independent) handler for ``dtype``; built and registered once."""
    scalar, ffi_type = _SCALAR[np.dtype(dtype)]
    source = _HANDLER.replace("@COMMON@", _COMMON.replace("@T@", scalar)).replace("@DT@", ffi_type)
    path = _build(source, f"handler_{scalar}")
    lib = ctypes.cdll.LoadLibrary(str(path))
    name = f"jaxbody_native_{path.stem}"
    jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(lib.jaxbody_fd), platform="cpu")
    _loaded.append(lib)
    return name


_loaded: list = []  # libraries stay loaded for the life of the process (XLA holds their addresses)


class _Kernel:
    """One compiled tree and dtype: the kernel's address and the batching wrapper around the call."""

    def __init__(self, tree, joints, with_external: bool, dtype):
        self.nv, self.dtype = joints.nv, np.dtype(dtype)
        self.target = _handler(self.dtype)
        lib = ctypes.cdll.LoadLibrary(str(_build(_generate(tree, joints, with_external, self.dtype), "fd")))
        _loaded.append(lib)
        self.address = ctypes.cast(lib.jaxbody_fd_range, ctypes.c_void_p).value
        self.batched = self._batched_call()

    def call(self, *args):
        """``args``: ``(B_i, n_i)`` arrays with ``B_i`` 1 or the batch size; returns ``(B, nv)``."""
        batch = max(a.shape[0] for a in args)
        out = jax.ShapeDtypeStruct((batch, self.nv), self.dtype)
        fn = jax.ffi.ffi_call(self.target, out, vmap_method="sequential")
        # every lane of a SIMD register is one state: the kernel gathers W states' inputs
        return fn(*args, kernel=np.int64(self.address), threads=np.int64(threads()))

    def _batched_call(self):
        @jax.custom_batching.custom_vmap
        def batched(*args):
            return self.call(*args)

        @batched.def_vmap
        def rule(axis_size, in_batched, *args):
            # a new batch axis over (B_i, n_i) inputs: merge it with the inner one
            inner = max(a.shape[1] if b else a.shape[0] for a, b in zip(args, in_batched))
            merged = []
            for a, b in zip(args, in_batched):
                n = a.shape[-1]
                if b:
                    a = jnp.broadcast_to(a, (axis_size, inner, n)).reshape(axis_size * inner, n)
                elif a.shape[0] != 1:
                    a = jnp.broadcast_to(a[None], (axis_size, inner, n)).reshape(axis_size * inner, n)
                merged.append(a)
            return batched(*merged).reshape(axis_size, inner, self.nv), True

        return batched


@functools.lru_cache(maxsize=128)
def _kernel(tree, joints, with_external: bool, dtype) -> _Kernel:
    with _lock:
        return _Kernel(tree, joints, with_external, dtype)


# ----------------------------------------------------------------------------- the JAX function
def _reference(model, q, v, force, gravity, external):
    from .kernels import _vectorised_acceleration

    return _vectorised_acceleration(model, q, v, force, gravity, external)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _forward_dynamics(kernel, model, q, v, force, gravity, external):
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    ext = row(external) if external is not None else jnp.zeros((1, 1), q.dtype)
    args = (row(q), row(v), row(force), row(parameter_vector(model)), row(gravity), ext)
    return kernel.batched(*args)[0]


def _forward_dynamics_jvp(kernel, primals, tangents):
    # value: the native call; tangent: the vectorised kernel's, which is the same function
    # (a linear map of the tangents written in JAX, so reverse mode can transpose it). Only
    # the inputs that carry a tangent are differentiated: a rollout's gradient perturbs the
    # state, not the model's parameters, whose derivative terms would otherwise cost a third
    # of the tangent (benchmarks/gradient_profile.py).
    out = _forward_dynamics(kernel, *primals)
    leaves, treedef = jax.tree_util.tree_flatten(primals)
    dleaves = treedef.flatten_up_to(tangents)
    live = [i for i, d in enumerate(dleaves) if not isinstance(d, SymbolicZero)]
    if not live:
        return out, jnp.zeros_like(out)

    def of_live(*xs):
        full = list(leaves)
        for i, x in zip(live, xs):
            full[i] = x
        return _reference(*jax.tree_util.tree_unflatten(treedef, full))

    _, tangent = jax.jvp(of_live, tuple(leaves[i] for i in live), tuple(dleaves[i] for i in live))
    return out, tangent


_forward_dynamics.defjvp(_forward_dynamics_jvp, symbolic_zeros=True)


def forward_dynamics(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    external: Float[ArrayLike, "n_body 6"] | None = None,
) -> Float[Array, " nv"]:
    """``a = M⁻¹ (force − bias + Jᵀ external)`` by the native kernel (no checks).

    Same arguments and result as :func:`jaxbody.unrolled.forward_dynamics`; ``jit``, ``vmap``
    (one call over the whole batch) and differentiation (tangents from the vectorised kernel)
    pass through. Builds and caches the tree's kernel on first use.
    """
    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    force = jnp.zeros(model.nv, dtype) if force is None else jnp.asarray(force, dtype)
    gravity = jnp.zeros(3, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    if external is not None:
        external = jnp.asarray(external, dtype)
    kernel = _kernel(model.tree, model.joints, external is not None, np.dtype(dtype))
    return _forward_dynamics(kernel, model, q, v, force, gravity, external)
