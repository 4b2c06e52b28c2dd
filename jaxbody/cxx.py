"""C++ shared libraries built on the user's machine: the compiler, its flags and the on-disk cache.

The native kernel (:mod:`jaxbody.backends.native`) and the run-time check of inputs
(:mod:`jaxbody.runtime_check`) are C++ compiled when first needed, with the system's compiler
(``g++``, or ``$CXX``), into ``<cache>/native`` (:func:`jaxbody.compilation_cache.cache_root`).
A library is keyed by a hash of its source, the compiler, the flags, the processor's
instruction set and JAX's version, and built once: processes that need the same library at the
same time take turns on a lock, and the others load what the first built.
"""

import contextlib
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

try:  # POSIX: builders of the same library in several processes take turns (build_library)
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

import jax

from .compilation_cache import cache_root

__all__ = ["COMPILER_FLAGS", "LEVEL_SWITCH", "OPTIMISATION_LEVELS", "build_library", "cache_dir", "compiler",
           "compiler_flags", "cpu_signature", "ffi_unavailable_reason", "library_path"]


def compiler() -> str | None:
    """The path of the C++ compiler (``$CXX``, default ``g++``), or ``None`` where there is none."""
    return shutil.which(os.environ.get("CXX", "g++"))


def cache_dir() -> Path:
    """Where built libraries are kept: ``<cache>/native`` (created)."""
    path = cache_root() / "native"
    path.mkdir(parents=True, exist_ok=True)
    return path


def cpu_signature() -> str:
    """The processor's architecture and instruction-set flags: libraries are built with
    ``-march=native``, so they are keyed by it too."""
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


#: The environment variable that sets the optimisation level of every build.
LEVEL_SWITCH = "JAXBODY_NATIVE_OPTIMISATION"


def compiler_flags(level: str | None = None) -> tuple[str, ...]:
    """The flags of a build: the optimisation ``level``, default ``$JAXBODY_NATIVE_OPTIMISATION``,
    else ``-O2``, and :data:`COMPILER_FLAGS`.

    ``-O0`` builds the whole-solve programs of a 7-DoF arm about 10x faster than ``-O2`` (8 s
    against 86 s for Panda's reverse sweep) and runs them several times slower: the test suite,
    which builds many programs and runs each briefly, uses it; the native kernel's first builds
    use it while their ``-O2`` builds run in the background (:mod:`jaxbody.tiered_compilation`)."""
    level = level or os.environ.get(LEVEL_SWITCH, "-O2")
    if level not in OPTIMISATION_LEVELS:
        raise ValueError(f"{LEVEL_SWITCH} must be one of {', '.join(OPTIMISATION_LEVELS)}, got {level!r}")
    return (level, *COMPILER_FLAGS)


def ffi_unavailable_reason() -> str | None:
    """Why an XLA FFI handler cannot be built here (``None`` where it can): no C++ compiler, or no
    XLA FFI C header in jaxlib (the handlers are written against it alone)."""
    if compiler() is None:
        return f"no C++ compiler found ({os.environ.get('CXX', 'g++')}; set $CXX to one)"
    header = Path(jax.ffi.include_dir()) / "xla" / "ffi" / "api" / "c_api.h"
    if not header.is_file():
        return f"jaxlib ships no XLA FFI headers ({header} is missing)"
    return None


def library_path(source, stem: str, flags: tuple[str, ...] | None = None, identity: str | None = None) -> Path | None:
    """Where :func:`build_library` keeps the library of these arguments (built or not); ``None``
    where there is no compiler."""
    cxx = compiler()
    if cxx is None:
        return None
    flags = compiler_flags() if flags is None else tuple(flags)
    text = identity if identity is not None else source
    key = hashlib.sha256("\n".join((text, cxx, *flags, cpu_signature(), jax.__version__)).encode()).hexdigest()[:24]
    return cache_dir() / f"{stem}_{key}.so"


def build_library(source, stem: str, what: str = "the native kernel", flags: tuple[str, ...] | None = None,
                  identity: str | None = None, niceness: int = 0) -> Path:
    """Compile ``source`` to a shared library in the cache (once per source, compiler, flags and CPU).

    ``what`` names the library in errors; ``flags`` default to :func:`compiler_flags`. With an
    ``identity`` (a text the source is a function of) the library is keyed by it instead of the
    source, and ``source`` may be a function that makes it, called only when the library is built.
    ``niceness``: the compiler process's (a build in the background gives way to the caller's work)."""
    target = library_path(source, stem, flags, identity)
    if target is None:
        raise RuntimeError(f"{what} needs a C++ compiler (g++ or $CXX); use kernel='vectorised'"
                           if what == "the native kernel" else f"{what} needs a C++ compiler (g++ or $CXX)")
    if target.is_file():
        return target
    flags = compiler_flags() if flags is None else tuple(flags)
    # one builder of a library at a time across processes (test workers, a batch job's
    # processes): the others wait on the lock and load what it built
    with open(target.with_suffix(".lock"), "a") as lock, _exclusive(lock):
        if target.is_file():
            return target
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            src = Path(tmp) / "src.cc"
            src.write_text(source() if callable(source) else source)
            out = Path(tmp) / "lib.so"
            cmd = [compiler(), *flags, f"-I{jax.ffi.include_dir()}", str(src), "-o", str(out)]
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            if niceness:
                try:
                    os.setpriority(os.PRIO_PROCESS, proc.pid, niceness)
                except (AttributeError, OSError):  # not POSIX, or already done
                    pass
            _, stderr = proc.communicate()
            if proc.returncode != 0:
                raise RuntimeError(f"building {what} failed ({' '.join(cmd)}):\n{stderr[-4000:]}")
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
