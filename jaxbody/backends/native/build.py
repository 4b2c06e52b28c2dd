"""Building and loading the native kernel: its XLA FFI target and the batched call of one compiled
program (the compiler and the on-disk cache of the libraries: :mod:`jaxbody.cxx`)."""

import ctypes
import functools
import hashlib
import os
import threading
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ...cxx import COMPILER_FLAGS, OPTIMISATION_LEVELS, build_library, compiler, compiler_flags, cpu_signature  # noqa: F401  (re-exported)
from ...model import Model
from .codegen import (COMMON_TEMPLATE, generate, generate_adaptive, generate_adaptive_vjp, generate_run, generate_run_vjp,
                      HANDLER_TEMPLATE, result_widths, SCALAR_TYPES)
from .tableaux import tableau

#: Largest tree ``kernel="auto"`` gives the native kernel, counted in entries of the tree-sparse
#: mass matrix (:func:`mass_matrix_entries`: for each DoF, the DoFs on its path to the root,
#: itself included). The generated code grows with these entries and their factorisation, not
#: with the number of DoFs: a 24-link chain has 300, a 25-DoF humanoid (floating base, two legs
#: of five hinges, a torso hinge, two arms of four) 194 — its forward dynamics compiles in about
#: 10 s, once, cached on disk (docs/performance.md, "Choosing a kernel"). Above this the vectorised
#: kernel (whose program does not grow with the tree) serves.
MAX_MASS_ENTRIES = 300

_lock = threading.RLock()


# ----------------------------------------------------------------------------- build and load
@functools.cache
def unavailable_reason() -> str | None:
    """Why the native kernel cannot be built here (``None`` where it can): no C++ compiler, no
    XLA FFI headers, or a backend other than the CPU."""
    if jax.default_backend() != "cpu":
        return f"the native kernel runs on the CPU and JAX's default backend is {jax.default_backend()}"
    if compiler() is None:
        return f"no C++ compiler found ({os.environ.get('CXX', 'g++')}; set $CXX to one)"
    include = Path(jax.ffi.include_dir()) / "xla" / "ffi" / "api" / "ffi.h"
    if not include.is_file():
        return f"jaxlib ships no XLA FFI headers ({include} is missing)"
    return None


def available() -> bool:
    """Whether the native kernel can be built here: a C++ compiler, XLA's FFI headers, a CPU."""
    return unavailable_reason() is None


def mass_matrix_entries(model: Model) -> int:
    """Entries of the tree-sparse mass matrix's lower triangle: for each DoF, the DoFs on its
    path to the root (itself included) — what the native kernel's generated code grows with."""
    parent, dof_body = model.tree.parent_array, model.joints.dof_body
    dofs_on_body = np.bincount(np.asarray(dof_body, dtype=np.int64), minlength=model.n_body)
    # bodies come after their parents: DoFs on the path from the root to each body, in one pass
    above = np.zeros(model.n_body, dtype=np.int64)
    for b in range(model.n_body):
        above[b] = dofs_on_body[b] + (above[parent[b]] if parent[b] >= 0 else 0)
    # the k-th DoF of a body sees the body's ancestors' DoFs and the k first of its own
    entries = 0
    for b in range(model.n_body):
        base = above[b] - dofs_on_body[b]
        entries += int(dofs_on_body[b] * base + dofs_on_body[b] * (dofs_on_body[b] + 1) // 2)
    return entries


def too_large_reason(model: Model) -> str | None:
    """Why ``kernel="auto"`` leaves ``model`` to another kernel for its size (``None``: it does not)."""
    entries = mass_matrix_entries(model)
    if entries <= MAX_MASS_ENTRIES:
        return None
    return (f"the tree ({model.nv} DoFs) has {entries} mass-matrix entries, above the native kernel's "
            f"limit of {MAX_MASS_ENTRIES} (jaxbody.backends.native.MAX_MASS_ENTRIES); kernel='native' builds it anyway")


def applies(model: Model) -> bool:
    """Whether ``kernel="auto"`` gives ``model`` the native kernel (within :data:`MAX_MASS_ENTRIES`, buildable)."""
    return model.nv > 0 and available() and too_large_reason(model) is None


#: Nanoseconds the pool's threads spin waiting for the next call (or for each other) before
#: they sleep; ``$JAXBODY_NATIVE_SPIN_NS`` overrides it (0: sleep at once).
SPIN_NS = 100_000


def threads() -> int:
    """Threads one call splits a batch over: ``$JAXBODY_NATIVE_THREADS``, else the CPU count."""
    return int(os.environ.get("JAXBODY_NATIVE_THREADS", os.cpu_count() or 1))


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
    lib.jaxbody_register.argtypes = (ctypes.c_int64, ctypes.c_void_p)
    _handlers[name] = lib
    _loaded.append(lib)
    return name


_handlers: dict = {}  # FFI target name -> its handler library (where programs are registered)


def _program_key(library: Path) -> int:
    """The key a traced call names a program by (:func:`_handler`'s registry): 60 bits of the
    hash of its library's name, which holds the hash of its source, compiler and CPU — the same
    in every process, unlike the program's address."""
    return int(hashlib.sha256(library.stem.encode()).hexdigest()[:15], 16) or 1


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

    def __init__(self, tree, joints, with_external: bool, dtype, mode: str = "fd", harmonics: int | None = None):
        self.tree, self.joints, self.with_external = tree, joints, with_external
        self.nv, self.nq, self.dtype, self.mode = joints.nv, joints.nq, np.dtype(dtype), mode
        # a whole solve's Fourier-series joint torque: its number of harmonics shapes the program
        self.harmonics = harmonics
        self.widths = result_widths(joints, mode, harmonics)
        if harmonics is not None and not (mode in ("rk4", "rk4_run", "rk4_run_vjp") or mode.startswith("adaptive")):
            raise ValueError(f"a Fourier-series joint torque is evaluated by the RK4 step and the whole solves, not {mode!r}")
        self.target = _handler(self.dtype)
        if mode == "rk4_run":
            self.source = generate_run(tree, joints, self.dtype, harmonics)
        elif mode == "rk4_run_vjp":
            self.source = generate_run_vjp(tree, joints, self.dtype, harmonics)
        elif mode.startswith("adaptive:"):
            self.source = generate_adaptive(tree, joints, self.dtype, tableau(mode.split(":")[1]), harmonics)
        elif mode.startswith("adaptive_vjp:"):
            self.source = generate_adaptive_vjp(tree, joints, self.dtype, tableau(mode.split(":")[1]), harmonics)
        else:
            self.source = generate(tree, joints, with_external, self.dtype, mode, harmonics)
        self._addresses = {}  # built on the first call (traced), where a build error then shows
        self._batched = {}
        if mode in ("fd", "rk4", "energy", "rk4_run", "rk4_run_vjp") or mode.startswith("adaptive_vjp:"):
            self.batched = self.batched_with(self.widths)

    def address(self, build: str) -> int:
        """The key of the compiled program of one of :data:`BUILDS` (built and registered with the
        handler on its first call); the traced call passes this key, not an address, so that
        the compiled XLA program is the same in every process (JAX's persistent cache)."""
        with _lock:  # two threads tracing the same kernel build it once
            if build not in self._addresses:
                source = self.source.replace("@VECTOR_BYTES@", BUILDS[build])
                stem = self.mode.replace(":", "_") + ("" if self.harmonics is None else f"_fourier{self.harmonics}")
                library = build_library(source, f"{stem}_{build}")
                lib = ctypes.cdll.LoadLibrary(str(library))
                _loaded.append(lib)
                key = _program_key(library)
                _handlers[self.target].jaxbody_register(key, ctypes.cast(lib.jaxbody_range, ctypes.c_void_p).value)
                self._addresses[build] = key
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
    return " avx512f" in cpu_signature()


@functools.lru_cache(maxsize=256)
def compiled_kernel(tree, joints, with_external: bool, dtype, mode: str = "fd", harmonics: int | None = None) -> Kernel:
    """The :class:`Kernel` of a tree, dtype and mode (and a whole solve's Fourier-series joint
    torque of ``harmonics`` harmonics), made once per process (its builds on first call)."""
    with _lock:
        return Kernel(tree, joints, with_external, dtype, mode, harmonics)
