"""Building and loading the native kernel: the compiler, the on-disk cache, the XLA FFI target
and the batched call of one compiled program."""

import contextlib
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

try:  # POSIX: builders of the same library in several processes take turns (build_library)
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

import jax
import jax.numpy as jnp
import numpy as np

from ...model import Model
from .codegen import (COMMON_TEMPLATE, generate, generate_adaptive, generate_adaptive_vjp, generate_run, generate_run_vjp,
                      HANDLER_TEMPLATE, result_widths, SCALAR_TYPES)
from .tableaux import tableau

#: Largest number of DoFs ``kernel="auto"`` gives the native kernel. The generated code grows
#: with the mass-matrix entries on each DoF's ancestor chain and their factorisation (for a
#: chain, quadratically and cubically): the 7-DoF Panda arm compiles in about 4 s, a 20-link
#: chain in about 25 s (once; cached on disk). Above this the vectorised kernel (whose program
#: does not grow with the tree) serves.
MAX_DOFS = 24

_lock = threading.RLock()


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


#: Nanoseconds the pool's threads spin waiting for the next call (or for each other) before
#: they sleep; ``$JAXBODY_NATIVE_SPIN_NS`` overrides it (0: sleep at once).
SPIN_NS = 100_000


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


#: The compiler flags of every build but the optimisation level (:func:`compiler_flags`).
#: -ffp-contract=fast: fused multiply-adds; -fno-math-errno: sin/cos/sqrt without errno.
COMPILER_FLAGS = ("-march=native", "-std=gnu++17", "-ffp-contract=fast", "-fno-math-errno", "-shared", "-fPIC", "-pthread", "-w")

#: The optimisation levels ``$JAXBODY_NATIVE_OPTIMISATION`` may choose.
OPTIMISATION_LEVELS = ("-O0", "-O1", "-O2", "-O3")


def compiler_flags() -> tuple[str, ...]:
    """The flags of a build: ``$JAXBODY_NATIVE_OPTIMISATION`` (default ``-O2``) and :data:`COMPILER_FLAGS`.

    ``-O0`` builds the whole-solve programs of a 7-DoF arm about 10x faster than ``-O2`` (8 s
    against 86 s for Panda's reverse sweep) and runs them several times slower: the test suite,
    which builds many programs and runs each briefly, uses it; users keep ``-O2``."""
    level = os.environ.get("JAXBODY_NATIVE_OPTIMISATION", "-O2")
    if level not in OPTIMISATION_LEVELS:
        raise ValueError(f"JAXBODY_NATIVE_OPTIMISATION must be one of {', '.join(OPTIMISATION_LEVELS)}, got {level!r}")
    return (level, *COMPILER_FLAGS)


def build_library(source: str, stem: str) -> Path:
    """Compile ``source`` to a shared library in the cache (once per source, compiler and CPU)."""
    compiler = _compiler()
    if compiler is None:
        raise RuntimeError("the native kernel needs a C++ compiler (g++ or $CXX); use kernel='vectorised'")
    flags = compiler_flags()
    key = hashlib.sha256("\n".join((source, compiler, *flags, _cpu_signature(), jax.__version__)).encode()).hexdigest()[:24]
    target = _cache_dir() / f"{stem}_{key}.so"
    if target.is_file():
        return target
    # one builder of a library at a time across processes (test workers, a batch job's
    # processes): the others wait on the lock and load what it built
    with open(target.with_suffix(".lock"), "a") as lock, _exclusive(lock):
        if target.is_file():
            return target
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            src = Path(tmp) / "src.cc"
            src.write_text(source)
            out = Path(tmp) / "lib.so"
            cmd = [compiler, *flags, f"-I{jax.ffi.include_dir()}", str(src), "-o", str(out)]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"building the native kernel failed ({' '.join(cmd)}):\n{proc.stderr[-4000:]}")
            os.replace(out, target)  # atomic: a process that does not take the lock never sees half a file
    return target


@contextlib.contextmanager
def _exclusive(fh):
    """Hold an exclusive advisory lock on the open file ``fh`` (POSIX ``flock``; no lock where the
    platform has none)."""
    if fcntl is None:
        yield
        return
    fcntl.flock(fh, fcntl.LOCK_EX)
    try:
        yield
    finally:
        fcntl.flock(fh, fcntl.LOCK_UN)


@functools.cache
def _handler(dtype) -> str:
    """The FFI target name of the (tree-independent) handler for ``dtype``; built and registered once."""
    scalar, ffi_type = SCALAR_TYPES[np.dtype(dtype)]
    source = (HANDLER_TEMPLATE.replace("@COMMON@", COMMON_TEMPLATE.replace("@T@", scalar)).replace("@DT@", ffi_type)
              .replace("@SPIN_NS@", str(int(os.environ.get("JAXBODY_NATIVE_SPIN_NS", SPIN_NS)))))
    path = build_library(source, f"handler_{scalar}")
    lib = ctypes.cdll.LoadLibrary(str(path))
    name = f"jaxbody_native_{path.stem}"
    jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(lib.jaxbody_fd), platform="cpu")
    _loaded.append(lib)
    return name


_loaded: list = []  # libraries stay loaded for the life of the process (XLA holds their addresses)


def merge_batch(axis_size: int, args, batched) -> tuple[list, int]:
    """A new batch axis (leading where ``batched``) over ``(B_i, n_i)`` operands, merged with the
    inner one: ``(axis_size * B, n_i)`` operands (or ``(1, n_i)``, read with stride zero), and B."""
    inner = max(a.shape[1] if b else a.shape[0] for a, b in zip(args, batched))
    merged = []
    for a, b in zip(args, batched):
        n = a.shape[-1]
        if b:
            a = jnp.broadcast_to(a, (axis_size, inner, n)).reshape(axis_size * inner, n)
        elif a.shape[0] != 1:
            a = jnp.broadcast_to(a[None], (axis_size, inner, n)).reshape(axis_size * inner, n)
        merged.append(a)
    return merged, inner


class Kernel:
    """One compiled tree, dtype and mode (:func:`generate`): its address and the call."""

    def __init__(self, tree, joints, with_external: bool, dtype, mode: str = "fd"):
        self.tree, self.joints, self.with_external = tree, joints, with_external
        self.nv, self.nq, self.dtype, self.mode = joints.nv, joints.nq, np.dtype(dtype), mode
        self.widths = result_widths(joints, mode)
        self.target = _handler(self.dtype)
        if mode == "rk4_run":
            self.source = generate_run(tree, joints, self.dtype)
        elif mode == "rk4_run_vjp":
            self.source = generate_run_vjp(tree, joints, self.dtype)
        elif mode.startswith("adaptive:"):
            self.source = generate_adaptive(tree, joints, self.dtype, tableau(mode.split(":")[1]))
        elif mode.startswith("adaptive_vjp:"):
            self.source = generate_adaptive_vjp(tree, joints, self.dtype, tableau(mode.split(":")[1]))
        else:
            self.source = generate(tree, joints, with_external, self.dtype, mode)
        self._addresses = {}  # built on the first call (traced), where a build error then shows
        self._batched = {}
        if mode in ("fd", "rk4", "energy", "rk4_run", "rk4_run_vjp") or mode.startswith("adaptive_vjp:"):
            self.batched = self.batched_with(self.widths)

    def address(self, build: str) -> int:
        """The compiled program of one of :data:`BUILDS`, built on its first call."""
        with _lock:  # two threads tracing the same kernel build it once
            if build not in self._addresses:
                source = self.source.replace("@VECTOR_BYTES@", BUILDS[build])
                stem = self.mode.replace(":", "_")
                lib = ctypes.cdll.LoadLibrary(str(build_library(source, f"{stem}_{build}")))
                _loaded.append(lib)
                self._addresses[build] = ctypes.cast(lib.jaxbody_range, ctypes.c_void_p).value
            return self._addresses[build]

    def call(self, *args, widths=None) -> list:
        """``args``: ``(B_i, n_i)`` arrays with ``B_i`` 1 or the batch size; returns ``(B, width)``
        arrays (``widths``: the results', default the program's)."""
        batch = max(a.shape[0] for a in args)
        out = [jax.ShapeDtypeStruct((batch, w), self.dtype) for w in (widths or self.widths)]
        fn = jax.ffi.ffi_call(self.target, out, vmap_method="sequential")
        # every lane of a SIMD register is one state: the kernel gathers W states' inputs; the
        # batch size is static here, so the build is chosen (and built) when the call is traced
        address = self.address(build_for(batch))
        return fn(*args, kernel=np.int64(address), threads=np.int64(threads()))

    def batched_with(self, widths: tuple):
        """The call with results of ``widths``, ``vmap`` batches merged into one call."""
        if widths not in self._batched:
            self._batched[widths] = self._batched_call(widths)
        return self._batched[widths]

    def _batched_call(self, widths):
        @jax.custom_batching.custom_vmap
        def batched(*args):
            return tuple(self.call(*args, widths=widths))

        @batched.def_vmap
        def rule(axis_size, in_batched, *args):
            merged, inner = merge_batch(axis_size, args, in_batched)
            outs = batched(*merged)
            return tuple(o.reshape(axis_size, inner, o.shape[-1]) for o in outs), tuple(True for _ in outs)

        return batched


#: The builds of every program, by the bytes of one block of states (:func:`build_for`):
#: ``"one"`` (``0``: one scalar) scalar code for a single state; ``"narrow"`` 256-bit lanes (4
#: float64 or 8 float32 states) for batches below :data:`WIDE_BATCH`, and for all batches without
#: AVX-512; ``"wide"`` 512-bit lanes (8 or 16 states) for larger batches where the processor has
#: AVX-512, which read the states with gather and write the results with scatter instructions. On an AMD
#: EPYC, whose 512-bit operations cost two 256-bit ones, a batch runs about 1.4x (float64) and
#: 1.6x (float32) faster in 512-bit lanes, but a few states would fill only part of them.
BUILDS = {"one": "0", "narrow": "32", "wide": "64"}

#: Smallest batch a call runs in 512-bit lanes (where the processor has AVX-512).
WIDE_BATCH = 16


def build_for(batch: int) -> str:
    """Which of :data:`BUILDS` a call over ``batch`` states runs."""
    if batch == 1:
        return "one"
    return "wide" if batch >= WIDE_BATCH and _has_avx512() else "narrow"


@functools.cache
def _has_avx512() -> bool:
    return " avx512f" in _cpu_signature()


@functools.lru_cache(maxsize=256)
def compiled_kernel(tree, joints, with_external: bool, dtype, mode: str = "fd") -> Kernel:
    """The :class:`Kernel` of a tree, dtype and mode, made once per process (its builds on first call)."""
    with _lock:
        return Kernel(tree, joints, with_external, dtype, mode)
