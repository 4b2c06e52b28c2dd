"""The FFI targets and native programs registered in this process, and how to register them again.

jaxbody's native code reaches XLA through FFI targets that a process registers when it first
traces a call to them (:mod:`jaxbody.runtime_check`, :mod:`jaxbody.backends.native`, whose one
handler target runs many programs, each named by a ``kernel`` key in the call). A program stored
on disk and run in a later process (:mod:`jaxbody.program_store`) is not traced there, so
nothing would register what it calls. Each registration is therefore noted here with the call
that repeats it (a module, a function of it and its arguments: plain data that can be stored),
and :func:`needed` reads from a lowered program which of them it calls.

Why the program's text and not a record kept while it is traced: JAX reuses the traces of inner
``jit`` functions, so a call traced earlier in the process runs no Python the second time.
"""

import importlib
import re

__all__ = ["needed", "note_program", "note_target", "register", "targets"]

_targets: dict = {}  # FFI target name -> (module, function, args) that registers it
_programs: dict = {}  # native program key -> (module, function, args) that registers it

# a custom call in StableHLO's text, and the native handler's program key among its attributes
_CUSTOM_CALL = re.compile(r"custom_call\s*@([A-Za-z0-9_.$-]+)")
_KERNEL = re.compile(r"\bkernel\s*=\s*(-?\d+)\s*:\s*i64")


def note_target(target: str, module: str, function: str, *args) -> None:
    """``target`` is registered in this process; ``module.function(*args)`` registers it."""
    _targets[target] = (module, function, tuple(args))


def note_program(key: int, module: str, function: str, *args) -> None:
    """The native program ``key`` is registered; ``module.function(*args)`` registers it."""
    _programs[int(key)] = (module, function, tuple(args))


def targets() -> tuple[str, ...]:
    """Every FFI target registered through this module in this process."""
    return tuple(_targets)


def needed(module_text: str) -> tuple:
    """The registrations a lowered program (StableHLO text) needs: ``(module, function, args)``
    each. Raises ``KeyError`` naming a custom call or program this process cannot register
    again (one of JAX's own custom calls needs nothing)."""
    calls = []
    called = set(_CUSTOM_CALL.findall(module_text))
    for target in sorted(called & set(_targets)):
        calls.append(_targets[target])
    if any(_targets[t][0].startswith("jaxbody.backends.native") for t in called & set(_targets)):
        for key in sorted({int(k) for k in _KERNEL.findall(module_text)}):
            if key not in _programs:
                raise KeyError(f"native program {key} has no registration noted")
            calls.append(_programs[key])
    return tuple(calls)


def register(calls) -> None:
    """Repeat the registrations ``calls`` (from :func:`needed`) in this process (each idempotent)."""
    for module, function, args in calls:
        getattr(importlib.import_module(module), function)(*args)
