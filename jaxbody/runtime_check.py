"""The run-time check of inputs inside a compiled program: an error status whose text is ours.

Inside a user's ``jax.jit``, an input can only be checked while the program runs. A host
callback that raises reaches the user as ``INTERNAL: CpuCallback error calling callback`` with
the message many lines down; this check is instead an XLA foreign-function call
(:func:`jax.ffi.ffi_call`) whose handler, a few lines of C++ (``runtime_check.cc``), fails the
program with the status ``INVALID_ARGUMENT`` and jaxbody's message, so the error's first line
reads ``INVALID_ARGUMENT: simulate: q0 contains NaN or inf (batch member 1 of 2)``.

* The messages are static: they travel as one string attribute of the call; the flags (one per
  check) are the call's argument, batched under ``vmap`` (the handler sees every member and
  names the first that failed, counting members in row-major order over nested batches).
* The checked array passes through the call (its result, aliased to it), so the check runs
  before whatever uses the array.
* The library is model-independent, built once per machine with the system's C++ compiler
  (:mod:`jaxbody.cxx`: a few hundredths of a second, against about 1 s for the same handler
  written with XLA's C++ binding) and registered with XLA once per process.
* A program holding the check has no host callback, so JAX's persistent compilation cache
  (:mod:`jaxbody.compilation_cache`) stores it; a process that loads it traces the program
  first, which registers the handler.

Where the library cannot be built (no C++ compiler, no XLA FFI headers) :func:`target` is
``None`` and :func:`jaxbody.validation.raise_if_any` raises through a host callback instead.
"""

import ctypes
import threading
import warnings
from importlib import resources

import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Bool
from .cxx import build_library, ffi_unavailable_reason
from .ffi_targets import note_target

__all__ = ["FLAGS", "TARGET", "check", "target", "unavailable_reason"]

#: The name of the FFI target (registered for the CPU).
TARGET = "jaxbody_runtime_check"

_loaded: list = []  # the library stays loaded for the life of the process (XLA holds its address)

#: Flags of the check's build: its few lines need no optimisation, and -O0 builds fastest.
FLAGS = ("-O0", "-std=gnu++17", "-shared", "-fPIC", "-w")


def unavailable_reason() -> str | None:
    """Why the check's library cannot be built here (``None`` where it can): no C++ compiler, or
    no XLA FFI C header in jaxlib."""
    return ffi_unavailable_reason()


def target() -> str | None:
    """:data:`TARGET`, registered with XLA (its library built on the first call: once per
    machine, then loaded from the on-disk cache once per process), or ``None`` where it cannot
    be built (:func:`unavailable_reason`; a compiler that fails warns once with its message)."""
    if _loaded:
        return TARGET
    if unavailable_reason() is not None:
        return None
    source = resources.files(__package__).joinpath("runtime_check.cc").read_text()
    try:
        path = build_library(source, "runtime_check", "jaxbody's run-time check", FLAGS)
    except RuntimeError as err:
        if str(err) not in _warned:
            _warned.add(str(err))
            warnings.warn(f"{err}\ninputs are checked through a host callback instead", RuntimeWarning, stacklevel=2)
        return None
    with _lock:  # two threads tracing at once register it once
        if not _loaded:
            lib = ctypes.cdll.LoadLibrary(str(path))
            jax.ffi.register_ffi_target(TARGET, jax.ffi.pycapsule(lib.jaxbody_check), platform="cpu")
            _loaded.append(lib)
            note_target(TARGET, __name__, "target")
    return TARGET


_warned: set = set()
_lock = threading.Lock()


def check(x: Array, flags: Bool[ArrayLike, " n"], messages: tuple[str, ...]) -> Array:
    """``x``, unchanged, once the program has checked ``flags``: booleans ``(n,)``, ``True`` where
    check ``i`` failed, whose message is ``messages[i]`` (one line each). A failed check stops
    the program with ``INVALID_ARGUMENT: <message>``, and under ``vmap`` with
    ``" (batch member i of n)"`` after it. Runs on the CPU (the caller picks another way on
    other platforms); no derivative rule (the caller passes tangents around it)."""
    if any("\n" in m for m in messages):
        raise ValueError("runtime_check.check: a message must be one line")
    if np.shape(flags) != (len(messages),):
        raise ValueError(f"runtime_check.check: flags have shape {np.shape(flags)}, expected ({len(messages)},)")
    name = target()
    if name is None:
        raise RuntimeError(f"jaxbody's run-time check cannot be built here: {unavailable_reason()}")
    call = jax.ffi.ffi_call(name, jax.ShapeDtypeStruct(np.shape(x), x.dtype), vmap_method="broadcast_all",
                            input_output_aliases={1: 0})
    return call(jnp.asarray(flags, bool), x, messages="\n".join(messages))
