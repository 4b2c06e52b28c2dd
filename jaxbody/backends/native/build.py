"""Building and loading the native kernel: its XLA FFI target and the batched call of one compiled
program (the compiler and the on-disk cache of the libraries: :mod:`jaxbody.cxx`)."""

import concurrent.futures
import ctypes
import functools
import hashlib
import os
import threading
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ...compilation_cache import cache_root
from ...cxx import (COMPILER_FLAGS, OPTIMISATION_LEVELS, build_library, compiler, compiler_flags,  # noqa: F401  (re-exported)
                    cpu_signature, ffi_unavailable_reason, library_path)
from ...ffi_targets import note_program, note_target
from ...model import Model
from ...tiered_compilation import BACKGROUND_NICENESS, QUICK_NATIVE_LEVEL, native_enabled
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
    return ffi_unavailable_reason()


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
def generator_fingerprint() -> str:
    """A hash of jaxbody's own source files (the code generator, its C++ templates and everything
    they call): a changed generator changes every library's identity (:meth:`Kernel.identity`)."""
    root = Path(__file__).resolve().parents[2]
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        if path.suffix in (".py", ".cc", ".h") and path.is_file():
            digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def handler_library(dtype) -> Path:
    """The (tree-independent) handler library for ``dtype``, built where the cache lacks it."""
    scalar, ffi_type = SCALAR_TYPES[np.dtype(dtype)]
    source = (HANDLER_TEMPLATE.replace("@COMMON@", COMMON_TEMPLATE.replace("@T@", scalar)).replace("@DT@", ffi_type)
              .replace("@SPIN_NS@", str(int(os.environ.get("JAXBODY_NATIVE_SPIN_NS", SPIN_NS)))))
    return build_library(source, f"handler_{scalar}")


@functools.cache
def _handler(dtype) -> str:
    """The FFI target name of the (tree-independent) handler for ``dtype``; built and registered once."""
    _await_prefetch(("handler", np.dtype(dtype)))
    path = handler_library(dtype)
    lib = ctypes.cdll.LoadLibrary(str(path))
    name = f"jaxbody_native_{path.stem}"
    jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(lib.jaxbody_fd), platform="cpu")
    lib.jaxbody_register.argtypes = (ctypes.c_int64, ctypes.c_void_p)
    _handlers[name] = lib
    _loaded.append(lib)
    note_target(name, __name__, "handler_target", np.dtype(dtype).str)
    return name


def handler_target(dtype) -> str:
    """The FFI target name of the handler for ``dtype`` (a dtype or its string), built and
    registered in this process where it is not yet."""
    return _handler(np.dtype(dtype))


_handlers: dict = {}  # FFI target name -> its handler library (where programs are registered)


def _program_key(library: Path) -> int:
    """The key a traced call names a program by (:func:`_handler`'s registry): 60 bits of the
    hash of its library's name, which holds the hash of its source, compiler and CPU — the same
    in every process, unlike the program's address."""
    return int(hashlib.sha256(library.stem.encode()).hexdigest()[:15], 16) or 1


_loaded: list = []  # libraries stay loaded for the life of the process (XLA holds their addresses)
_registered: dict = {}  # program key -> the library registered under it (its quick build, or itself)


def register_program(library: str, dtype: str) -> int:
    """Load a kernel's built ``library`` (a path) and register its program with the handler of
    ``dtype`` (a NumPy dtype string); returns the key traced calls name it by. Idempotent. A
    stored program (:mod:`jaxbody.program_store`) replays this in a process that never traced it.

    Raises :class:`FileNotFoundError` where ``library`` is neither registered in this process
    (its quick build stands in for it while it builds: :meth:`Kernel.address`) nor built (removed
    from the cache, or an optimised build an earlier process did not finish): a stored program
    is then traced again, which builds it."""
    key = _program_key(Path(library))
    with _lock:
        if key in _registered:
            return key
    if not Path(library).is_file():
        raise FileNotFoundError(f"the native program {library} is not built")
    return _register(library, dtype, library)


def _register(library: str, dtype: str, loaded: str) -> int:
    """Register the program ``loaded`` (``library`` itself, or its quick build standing in for it
    while ``library`` builds: :meth:`Kernel.address`) under ``library``'s key; an optimised
    program is never replaced by a quick one."""
    target = handler_target(dtype)
    key = _program_key(Path(library))
    with _lock:
        if _registered.get(key) not in (loaded, library):
            lib = ctypes.cdll.LoadLibrary(loaded)
            _loaded.append(lib)
            _handlers[target].jaxbody_register(key, ctypes.cast(lib.jaxbody_range, ctypes.c_void_p).value)
            _registered[key] = loaded
        # a stored program that calls it registers it again in a later process
        note_program(key, __name__, "register_program", library, np.dtype(dtype).str)
    return key


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
        self._source = None  # generated on first need: a library in the cache is found without it
        self._addresses = {}  # built on the first call (traced), where a build error then shows
        self._batched = {}
        # this kernel's builds take turns; other kernels build beside them (see prefetch)
        self._build_lock = threading.Lock()
        self._source_lock = threading.Lock()
        if mode in ("fd", "rk4", "energy", "rk4_run", "rk4_run_vjp") or mode.startswith("adaptive_vjp:"):
            self.batched = self.batched_with(self.widths)

    @property
    def source(self) -> str:
        """The program's C++ source (generated once, on first need)."""
        with self._source_lock:
            if self._source is None:
                tree, joints, dtype, mode, harmonics = self.tree, self.joints, self.dtype, self.mode, self.harmonics
                if mode == "rk4_run":
                    self._source = generate_run(tree, joints, dtype, harmonics)
                elif mode == "rk4_run_vjp":
                    self._source = generate_run_vjp(tree, joints, dtype, harmonics)
                elif mode.startswith("adaptive:"):
                    self._source = generate_adaptive(tree, joints, dtype, tableau(mode.split(":")[1]), harmonics)
                elif mode.startswith("adaptive_vjp:"):
                    self._source = generate_adaptive_vjp(tree, joints, dtype, tableau(mode.split(":")[1]), harmonics)
                else:
                    self._source = generate(tree, joints, self.with_external, dtype, mode, harmonics)
            return self._source

    def identity(self, build: str) -> str:
        """What one build's source is a function of: the generator's own code
        (:func:`generator_fingerprint`), the tree and joint layout (what makes them equal), the
        mode, dtype, loads and harmonics, and the build. The library is looked up by it, so a
        process whose library is cached generates no code (a second or so of Python for a
        7-DoF arm's derivative programs)."""
        tree, joints = self.tree, self.joints
        structure = (tree.parent, tree.names, tree.traversal, joints.type, joints.body, joints.names)
        return "\n".join((generator_fingerprint(), repr(structure), str(self.with_external), self.dtype.str, self.mode,
                          repr(self.harmonics), build))

    @property
    def target(self) -> str:
        """The FFI target of the handler this kernel's programs are registered with (built on
        first use, not with the kernel: a kernel's code is generated while the handler builds)."""
        return _handler(self.dtype)

    def address(self, build: str) -> int:
        """The key of the compiled program of one of :data:`BUILDS` (built and registered with the
        handler on its first call); the traced call passes this key, not an address, so that
        the compiled XLA program is the same in every process (JAX's persistent cache).

        Where the optimised library is not built yet and tiering is on
        (:func:`jaxbody.tiered_compilation.native_enabled`), the quick build is registered under
        the optimised one's key and runs until the optimised build, started in the background,
        replaces it: the XLA program that calls the key does not change."""
        with self._build_lock:  # two threads tracing the same kernel build it once
            if build not in self._addresses:
                # a build started ahead of use (prefetch) is waited for, not raced
                _await_prefetch((self.key, build))
                final = self.library_path(build)
                if self._tiered(build):
                    quick = str(self.library(build, QUICK_NATIVE_LEVEL))
                    key = _register(str(final), self.dtype.str, quick)
                    future = _builders().submit(self._optimise, build)
                    with _lock:
                        _optimising.append(future)
                else:
                    key = register_program(str(self.library(build)), self.dtype.str)
                self._addresses[build] = (key, str(final))
            return self._addresses[build][0]

    def _tiered(self, build: str) -> bool:
        """Whether ``build`` is built quickly first: tiering on, its optimised library not built."""
        if not native_enabled():
            return False
        final = self.library_path(build)
        return final is not None and not final.is_file()

    def _optimise(self, build: str) -> None:
        """The optimised build, in the background (at a low priority): registered in place of the
        quick one when done; where it fails, the quick one keeps serving."""
        try:
            library = self.library(build, niceness=BACKGROUND_NICENESS)
        except Exception:  # noqa: BLE001
            return
        register_program(str(library), self.dtype.str)

    def prepare(self, build: str) -> None:
        """Build (not load) what :meth:`address` will first register: the quick build where the
        program is tiered, else the optimised one (:func:`prefetch`)."""
        self.library(build, QUICK_NATIVE_LEVEL if self._tiered(build) else None)

    def _stem(self, build: str) -> str:
        return self.mode.replace(":", "_") + ("" if self.harmonics is None else f"_fourier{self.harmonics}") + f"_{build}"

    def library_path(self, build: str, level: str | None = None) -> Path | None:
        """Where the shared library of one of :data:`BUILDS` at optimisation ``level`` (default
        :func:`jaxbody.cxx.compiler_flags`'s) is kept, built or not (``None``: no compiler)."""
        return library_path(None, self._stem(build), compiler_flags(level), self.identity(build))

    def library(self, build: str, level: str | None = None, niceness: int = 0) -> Path:
        """The shared library of one of :data:`BUILDS` at optimisation ``level``, built where the
        cache lacks it (not loaded)."""
        return build_library(lambda: self.source.replace("@VECTOR_BYTES@", BUILDS[build]), self._stem(build),
                             flags=compiler_flags(level), identity=self.identity(build), niceness=niceness)

    def build_for(self, batch: int) -> str:
        """Which of :data:`BUILDS` runs a call over ``batch`` states (:func:`build_for`), except
        that an energy program has one build for every batch: it runs off the solve's hot path
        (the energies of the saved states and of the initial one), where its scalar build would
        cost a second compilation on first use for microseconds per call."""
        return _build_of(self.mode, batch)

    def call(self, *args, widths=None) -> list:
        """``args``: ``(B_i, n_i)`` arrays with ``B_i`` 1 or the batch size; returns ``(B, width)``
        arrays (``widths``: the results', default the program's)."""
        batch = max(a.shape[0] for a in args)
        out = [jax.ShapeDtypeStruct((batch, w), self.dtype) for w in (widths or self.widths)]
        fn = jax.ffi.ffi_call(self.target, out, vmap_method="sequential")
        # every lane of a SIMD register is one state: the kernel gathers W states' inputs; the
        # batch size is static here, so the build is chosen (and built) when the call is traced
        address = self.address(self.build_for(batch))
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


#: Modes with one build for every batch size (:meth:`Kernel.build_for`).
SINGLE_BUILD_MODES = ("energy",)


def _build_of(mode: str, batch: int) -> str:
    return build_for(max(batch, WIDE_BATCH) if mode in SINGLE_BUILD_MODES else batch)


_kernels: dict = {}
_kernel_locks: dict = {}


def compiled_kernel(tree, joints, with_external: bool, dtype, mode: str = "fd", harmonics: int | None = None) -> Kernel:
    """The :class:`Kernel` of a tree, dtype and mode (and a whole solve's Fourier-series joint
    torque of ``harmonics`` harmonics), made once per process (its builds on first call)."""
    key = (tree, joints, with_external, np.dtype(dtype), mode, harmonics)
    kernel = _kernels.get(key)
    if kernel is not None:
        return kernel
    # one lock per kernel: generating one kernel's code does not hold up another's (a build
    # ahead of use generates in a background thread while the trace asks for other kernels)
    with _lock:
        lock = _kernel_locks.setdefault(key, threading.Lock())
    with lock:
        if key not in _kernels:
            kernel = Kernel(tree, joints, with_external, dtype, mode, harmonics)
            kernel.key = key
            _kernels[key] = kernel
        return _kernels[key]


_optimising: list = []  # the futures of the optimised builds started in the background (Kernel.address)


def wait_for_optimised_builds() -> None:
    """Wait for the optimised builds running in the background (the interpreter waits for them
    at exit anyway): from then on every program runs its optimised build."""
    with _lock:
        futures = list(_optimising)
    concurrent.futures.wait(futures)


# ----------------------------------------------------------------------------- builds ahead of use
_pool: concurrent.futures.ThreadPoolExecutor | None = None


def _builders() -> concurrent.futures.ThreadPoolExecutor:
    global _pool
    with _lock:
        if _pool is None:
            # more threads than cores: a solve's few builds all start at once (the compilers
            # share the cores; a build queued behind another would start only when it ends)
            _pool = concurrent.futures.ThreadPoolExecutor(max_workers=max(4, os.cpu_count() or 1),
                                                          thread_name_prefix="jaxbody-build")
        return _pool


def _build_quietly(build):
    try:
        build()
    except Exception:  # noqa: BLE001 (the traced call builds again and raises with the compiler's message)
        pass


def prefetch(model: Model, modes: tuple[str, ...], harmonics: int | None = None,
             batch: int = 1) -> list[concurrent.futures.Future]:
    """Start building, in background threads, the handler and the programs ``modes`` of
    ``model``'s tree for calls over ``batch`` states, where the cache lacks them.

    A solve traces its native calls one after another, and each call's first use waits for the
    C++ compiler: with an empty cache those builds are most of a first simulation. Started
    together before the trace they run beside one another (one compiler process per core) and
    beside the tracing, and each traced call then finds its library built, or waits for that
    build to end (a library is built once, by the thread that asked first). Nothing is loaded or
    registered here, and a failed build is left for the traced call to report. Returns the
    builds' futures."""
    if not available():
        return []
    dtype = np.dtype(model.body_pos.dtype)
    futures = [_ahead(("handler", dtype), lambda: handler_library(dtype))]
    for mode in modes:
        key, build = (model.tree, model.joints, False, dtype, mode, harmonics), _build_of(mode, batch)

        def run(key=key, build=build):
            # the code is generated here too, beside the caller's own work
            compiled_kernel(*key).prepare(build)
        futures.append(_ahead((key, build), run))
    return futures


_ahead_of_use: dict = {}  # (cache, kernel key or "handler", build or dtype) -> the future of its build


def _ahead(key, build) -> concurrent.futures.Future:
    """The future of a build started ahead of use (one per library, cache directory and process)."""
    key = (str(cache_root()), *key)
    with _lock:
        if key not in _ahead_of_use:
            _ahead_of_use[key] = _builders().submit(_build_quietly, build)
        return _ahead_of_use[key]


def _await_prefetch(key) -> None:
    """Wait for the build of ``key`` where one was started ahead of use (a library a traced call
    is about to load is then built once, by the thread that started first)."""
    with _lock:
        future = _ahead_of_use.get((str(cache_root()), *key))
    if future is not None:
        future.result()
