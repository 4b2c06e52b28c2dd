"""First calls compiled quickly, their optimised programs compiled in the background.

About half of XLA's CPU compile of a solve is LLVM optimising the machine code, and a first
simulation waits for all of it (a rolling disk's first ``simulate`` in a fresh process took
4.75 s with every program compiled quickly, 7.14 s optimised:
``benchmarks/tiered_compilation.py``). Where this machine has not compiled a stored program
(:mod:`jaxbody.program_store`) optimised before, :func:`compile_tiered` compiles it with the
optimiser off (:data:`QUICK_OPTIONS`: XLA's backend optimisation level 0, one code-generation
part) and runs that; a background thread at low priority compiles the optimised program,
which replaces the quick one for every later call and goes into JAX's persistent compilation
cache. A marker file beside the stored program then tells later processes to load the
optimised program at once. The quick programs ran 1.5-2x slower than the optimised ones on the
same benchmark's cases: they serve the first calls only.

The native kernel's C++ is tiered alike (:func:`native_enabled`): a program whose ``-O2``
library is not in the cache is built at ``-O0`` first (about 10x faster to build, several times
slower to run) and registered under the key of the ``-O2`` library, which a compiler process at
low priority builds in the background and which is registered under the same key when done.
The XLA program that calls the key does not change, and later processes find the ``-O2``
library in the cache.

A process that ends while an optimised compile or build runs waits for it at exit: that work
is what makes the next process's first call fast (a first gradient's optimised compiles can
make that wait longer than the gradient itself: the `process` column of
``benchmarks/first_call.py``).

The two programs compute the same operations; only the machine code differs, so their results
can differ in the last bits (the optimiser fuses multiplies and adds): a chaotic trajectory
from the first call and from a later one can part after many steps. The switch
``JAXBODY_TIERED_COMPILE=0`` (or ``off``, ``false``, ``no``) compiles and builds optimised from
the first call. XLA's tiering is off where its optimisation level is the caller's own
(``--xla_backend_optimization_level`` in ``$XLA_FLAGS``) and off accelerators, whose compiles
it was not measured on; the native kernel's where ``$JAXBODY_NATIVE_OPTIMISATION`` sets its level.
"""

import os
import threading
from collections.abc import Callable
from pathlib import Path

import jax

from .cxx import LEVEL_SWITCH
from .stored_executables import compile_fresh

__all__ = ["BACKGROUND_NICENESS", "ENV_SWITCH", "MARK_SUFFIX", "OPTIMISED_OPTIONS", "QUICK_NATIVE_LEVEL",
           "QUICK_OPTIONS", "compile_once", "compile_tiered", "enabled", "native_enabled"]

#: The environment variable that turns tiered compilation off (``0``, ``off``, ``false``, ``no``).
ENV_SWITCH = "JAXBODY_TIERED_COMPILE"

#: XLA's options of a quick compile: no LLVM optimisation, and the machine code in one part
#: (split into parts, it is compiled on parallel threads, which costs more work in all and
#: competes with the optimised compile running beside it).
QUICK_OPTIONS = {"xla_backend_optimization_level": 0, "xla_cpu_parallel_codegen_split_count": 1}

#: XLA's options of the optimised compile: the default optimisation, the machine code in one
#: part too, so that all of the compile runs on the background thread at its low priority
#: (XLA compiles the parts on a pool of threads of its own, at the caller's priority).
OPTIMISED_OPTIONS = {"xla_cpu_parallel_codegen_split_count": 1}

#: The suffix of the file beside a stored program that marks it compiled optimised.
MARK_SUFFIX = ".optimised"

#: Niceness of the optimised compiles (XLA's thread, the native kernel's compiler processes): the
#: quick programs' runs and the caller's other compiles go first on a machine with few cores.
BACKGROUND_NICENESS = 10

# optimised compiles running at once: one per two cores, so that they leave the caller's own
# work (a trace, the next quick compile) a core on the smallest machines
_running = threading.BoundedSemaphore(max(1, (os.cpu_count() or 2) // 2))


def enabled() -> bool:
    """Whether :func:`compile_tiered` compiles quickly first: switched on
    (``$JAXBODY_TIERED_COMPILE``), on the CPU, and XLA's optimisation level not set by the caller."""
    if os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "off", "false", "no"):
        return False
    if "--xla_backend_optimization_level" in os.environ.get("XLA_FLAGS", ""):
        return False
    return jax.default_backend() == "cpu"


#: The C++ optimisation level of the native kernel's quick first build of a program.
QUICK_NATIVE_LEVEL = "-O0"


def native_enabled() -> bool:
    """Whether the native kernel builds a program at :data:`QUICK_NATIVE_LEVEL` first, runs that,
    and swaps in its optimised build made in the background: switched on
    (``$JAXBODY_TIERED_COMPILE``) and the optimisation level not set by the caller
    (``$JAXBODY_NATIVE_OPTIMISATION``)."""
    if os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "off", "false", "no"):
        return False
    return not os.environ.get(LEVEL_SWITCH)


def _marker(path: Path | None) -> Path | None:
    """The file saying the program stored at ``path`` was compiled optimised into JAX's
    persistent cache (``None``: no such cache, so nothing to find there)."""
    if path is None or jax.config.jax_compilation_cache_dir is None:
        return None
    return path.with_name(path.name + MARK_SUFFIX)


def compile_tiered(lowered, path: Path | None, install: Callable, start: Callable, keep: Callable | None = None):
    """The executable of ``lowered`` (a :class:`jax.stages.Lowered`) to run now.

    ``path``: the file the program is stored in (its marker goes beside it); ``install``: called
    from the background thread with the optimised executable once compiled; ``start``: runs a
    function in a background thread (``start(work, name)``) that the interpreter joins at exit;
    ``keep``: called with every optimised executable XLA compiles, here or in the background (not
    one loaded from JAX's cache): the program store keeps it (:mod:`jaxbody.stored_executables`).
    Where tiering is off (XLA's default options), or the marker says the optimised program is in
    JAX's cache, the optimised program is compiled (loaded) here and ``install`` is not called."""

    def optimised(**options):
        return _compiled_and_kept(lowered, keep, **options)

    if not enabled():
        return optimised()
    marker = _marker(path)
    if marker is not None and marker.exists():
        return optimised(compiler_options=OPTIMISED_OPTIONS)  # as the earlier process compiled it
    quick = lowered.compile(compiler_options=QUICK_OPTIONS)

    def work():
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), BACKGROUND_NICENESS)
        except (AttributeError, OSError):  # not Linux: the thread keeps the caller's priority
            pass
        try:
            with _running:
                executable = optimised(compiler_options=OPTIMISED_OPTIONS)
        except Exception:  # noqa: BLE001 (the quick program keeps running; it is the same program)
            return
        install(executable)
        if marker is not None:
            try:
                marker.touch()
            except OSError:  # a read-only cache: the next process compiles quickly first again
                pass

    start(work, "jaxbody-optimised-compile")
    return quick


def compile_once(lowered, keep: Callable | None = None):
    """The executable of ``lowered`` for a program that runs about once per system (a check of
    its inputs): compiled quickly where tiering is on, with no optimised compile after it (there
    are no later calls for the optimiser to speed up), with XLA's defaults where it is off.
    ``keep``: as :func:`compile_tiered`'s, called with the executable where XLA compiled it."""
    return _compiled_and_kept(lowered, keep, **({"compiler_options": QUICK_OPTIONS} if enabled() else {}))


def _compiled_and_kept(lowered, keep: Callable | None, **options):
    """``lowered`` compiled with ``options``; ``keep`` called with the executable where XLA
    compiled it here (not where JAX loaded it from its cache: such a copy cannot be kept)."""
    executable, fresh = compile_fresh(lambda: lowered.compile(**options))
    if fresh and keep is not None:
        keep(executable)
    return executable
