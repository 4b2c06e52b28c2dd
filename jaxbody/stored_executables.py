"""Optimised executables kept beside the stored programs, loaded without lowering them again.

A later process runs a stored program (:mod:`jaxbody.program_store`) without tracing it, and
JAX's persistent compilation cache spares it XLA's compile. To find the compiled program in that
cache, JAX still lowers the program again and hashes the result, a large part of a warm first
call for the largest programs (a constrained solve and its saved states). The optimised
executable XLA compiled is therefore serialised beside the stored program
(``PROGRAM.pickle.MACHINE.xla``) and a later process loads it directly: with the initial
constraint check stored too, the Cassie-like biped's first simulation in a warm process went
from 1.2 to 0.9 s (``benchmarks/first_call.py --cases cassie --cassie jaxbody/models/cassie_like.xml
--baseline DIR``, a 2-core machine).

An executable is machine code for one processor, one XLA and one set of flags: its file name
holds a hash of the JAX and jaxlib versions, the backend and its version, the processor's
instruction set (:func:`jaxbody.cxx.cpu_signature`) and ``$XLA_FLAGS``, so a cache directory
shared between different machines keeps one executable per kind of machine. The program's own
key (everything its trace is a function of) is the stored program's file name. Only on the CPU:
executables compiled for accelerators are left to JAX's cache, where they were measured. Not
for programs that call jaxbody's native kernel or other FFI targets either: with jaxlib 0.10.2
such an executable, serialised so and loaded in another process, crashed the process when it
ran (JAX's own cache, which deserialises with the compile options, loads them correctly), so
the program store keeps executables of programs without FFI calls only: the vectorised and
unrolled kernels' solves (the Cassie-like biped's among them) and their checks.

Only an executable XLA compiled in this process is kept: one JAX loaded from its own cache
cannot be serialised again (what JAX's serialiser writes of it lacks its machine code, and the
loaded copy fails when it runs), so :func:`compile_fresh` tells the two apart by JAX's
cache-hit events. A process that loaded the optimised program from JAX's cache keeps nothing;
the first process that compiles it does.

A file that cannot be read or loaded is ignored (the program is compiled, or loaded from JAX's
cache, as before). ``JAXBODY_PROGRAM_STORE=0`` turns this off with the store itself.
"""

import functools
import hashlib
import os
import pickle
import threading
from collections.abc import Callable
from pathlib import Path

import jax
import jaxlib
from jax.experimental import serialize_executable

from .cxx import cpu_signature

__all__ = ["SUFFIX", "compile_fresh", "executable_path", "load_executable", "store_executable"]

#: The ending of an executable's file name.
SUFFIX = ".xla"

# JAX's event of a program loaded from its persistent cache, recorded in the compiling thread
_CACHE_HIT = "/jax/compilation_cache/cache_hits"
_local = threading.local()


def _note_cache_hit(event: str, **_) -> None:
    if event == _CACHE_HIT:
        _local.hits = getattr(_local, "hits", 0) + 1


jax.monitoring.register_event_listener(_note_cache_hit)


def compile_fresh(compile: Callable[[], object]) -> tuple[object, bool]:
    """``(executable, fresh)``: ``compile()``'s executable and whether XLA compiled it here
    (``False``: JAX loaded it from its persistent cache, and it cannot be kept)."""
    before = getattr(_local, "hits", 0)
    executable = compile()
    return executable, getattr(_local, "hits", 0) == before


@functools.cache
def _machine() -> str:
    """What an executable compiled here is a function of, besides its program (a short hash)."""
    backend = jax.devices()[0].client
    parts = (jax.__version__, jaxlib.__version__, backend.platform, backend.platform_version, cpu_signature(),
             os.environ.get("XLA_FLAGS", ""))
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


def executable_path(program: Path | None, variant: str = "") -> Path | None:
    """Where the executable of the program stored at ``program`` is kept on this machine
    (``None``: the program is not stored, or the backend is not the CPU); ``variant`` names
    executables compiled with other options (``"quick"``)."""
    if program is None or jax.default_backend() != "cpu":
        return None
    return program.with_name(f"{program.name}.{_machine()}{'.' + variant if variant else ''}{SUFFIX}")


def load_executable(path: Path | None):
    """The executable stored at ``path`` (a :class:`jax.stages.Compiled`), ``None`` where there
    is none or it cannot be loaded. The FFI targets it calls must be registered first."""
    if path is None:
        return None
    try:
        data = path.read_bytes()
    except OSError:
        return None
    try:
        serialized, in_tree, out_tree = pickle.loads(data)
        compiled = serialize_executable.deserialize_and_load(serialized, in_tree, out_tree)
    except Exception:  # noqa: BLE001 (a damaged or foreign file: compiled as before)
        return None
    try:
        os.utime(path)  # used now: the last to be removed when the store is full
    except OSError:
        pass
    return compiled


def store_executable(path: Path | None, compiled) -> bool:
    """Serialise ``compiled`` (an optimised :class:`jax.stages.Compiled` that XLA compiled in this
    process: :func:`compile_fresh`) to ``path``; whether it was written (not where XLA cannot
    serialise it, or the cache is read-only)."""
    if path is None:
        return False
    try:
        data = pickle.dumps(serialize_executable.serialize(compiled))
    except Exception:  # noqa: BLE001 (an executable XLA cannot serialise: left to JAX's cache)
        return False
    try:
        # written whole, then renamed: a reader never sees half a file
        tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError:
        return False
    return True
