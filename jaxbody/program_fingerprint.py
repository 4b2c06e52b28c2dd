"""What a traced program is a function of, as a fingerprint: the key of a stored program.

A program traced from a function of some arguments is reused in a later process only when that
process would trace the same program (:mod:`jaxbody.program_store`). :func:`fingerprint` hashes
everything the trace is a function of except the values of the input arrays:

* the input arrays by shape, dtype and weak type; every other argument by value (numbers,
  strings, the static fields of modules, arrays held as constants);
* the functions among the arguments by their code, the values they close over and the globals
  their code names, recursively: a module of one of the trusted packages (:data:`TRUSTED`) by its
  name, any other module by the attributes the code names, a user's class by its body;
* jaxbody's own source (a hash of its files), the versions of the packages it traces through,
  JAX's settings that change a trace, jaxbody's environment variables and the CPU count.

:func:`describe` raises :class:`Undescribable` where some part of an argument cannot be
described this way (an object of a class that is neither a dataclass nor a module of the kinds
above): such a program is traced, never reused.
"""

import dataclasses
import enum
import functools
import hashlib
import importlib
import os
import sys
import types
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

__all__ = ["TRUSTED", "Undescribable", "describe", "fingerprint", "input_aval", "is_input", "jax_settings"]

#: Packages whose functions and classes are fingerprinted by name: their code is fixed by the
#: versions in the fingerprint (jaxbody's by the hash of its source files).
TRUSTED = frozenset({
    "jaxbody", "jax", "jaxlib", "numpy", "diffrax", "equinox", "optimistix", "lineax", "jaxtyping", "builtins",
    "math", "cmath", "operator", "functools", "itertools", "typing", "collections", "dataclasses", "enum", "abc",
    "types",
})

# the packages a solve is traced through: their versions key every program
_VERSIONED = ("jax", "jaxlib", "numpy", "diffrax", "equinox", "optimistix", "lineax")


class Undescribable(TypeError):
    """An argument the fingerprint cannot describe (the program is traced instead of stored)."""


def _trusted(module: str | None) -> bool:
    return module is not None and module.split(".", 1)[0] in TRUSTED


def _code_names(code: types.CodeType) -> set:
    """The global and attribute names ``code`` and the code nested in it refer to."""
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _code_names(const)
    return names


def _code(code: types.CodeType) -> tuple:
    """A code object by what it executes (not where it was written: moving a function in its
    file changes no program)."""
    consts = tuple(_code(c) if isinstance(c, types.CodeType) else ("const", type(c).__name__, repr(c))
                   for c in code.co_consts)
    return ("code", code.co_code, consts, code.co_names, code.co_varnames, code.co_freevars, code.co_cellvars,
            code.co_argcount, code.co_kwonlyargcount, code.co_flags)


class _Describer:
    """One fingerprint: :meth:`__call__` describes a value as nested tuples of plain data."""

    def __init__(self):
        self._seen: dict = {}  # (id, how described) -> its index

    def __call__(self, x, static: bool = True, names: frozenset = frozenset()):
        # `static`: arrays are described by value (constants of the program) rather than by
        # shape (inputs); `names`: the attribute names of the code that reached a module
        if x is None or isinstance(x, (bool, int, float, complex, str, bytes, type(Ellipsis))):
            return (type(x).__name__, repr(x))
        if isinstance(x, jax.ShapeDtypeStruct) and not static:
            return ("input",) + input_aval(x)
        if isinstance(x, (np.ndarray, np.generic, jax.Array)):
            if not static and not isinstance(x, np.generic):
                return ("input",) + input_aval(x)
            if isinstance(x, jax.core.Tracer):
                raise Undescribable("a traced value held as a constant")
            value = np.asarray(x)
            return ("value", value.shape, str(value.dtype), hashlib.sha256(value.tobytes()).hexdigest())
        if isinstance(x, np.dtype):
            return ("dtype", str(x))
        # a value met again is a reference to its first description, if it was described the
        # same way: as a constant or an input, and a module with the same attribute names
        key = (id(x), static, names if isinstance(x, types.ModuleType) else None)
        if key in self._seen:
            return ("ref", self._seen[key])
        self._seen[key] = len(self._seen)
        # keep the object alive while its id stands for it
        self._seen[("keep",) + key] = x
        if isinstance(x, (tuple, list)) and not hasattr(x, "_fields"):
            return (type(x).__name__, tuple(self(v, static, names) for v in x))
        if isinstance(x, tuple):  # a named tuple
            return ("namedtuple", self._class(type(x)), tuple(self(v, static, names) for v in x))
        if isinstance(x, dict):
            items = sorted(((self(k), self(v, static, names)) for k, v in x.items()), key=repr)
            return ("dict", tuple(items))
        if isinstance(x, (set, frozenset)):
            return (type(x).__name__, tuple(sorted((self(v) for v in x), key=repr)))
        if isinstance(x, type):
            return self._class(x)
        if isinstance(x, enum.Enum):
            return ("enum", self._class(type(x)), x.name)
        if isinstance(x, types.ModuleType):
            return self._module(x, names)
        if isinstance(x, types.FunctionType):
            return self._function(x)
        if isinstance(x, types.MethodType):
            return ("method", self(x.__self__), self(x.__func__))
        if isinstance(x, functools.partial):
            return ("partial", self(x.func), self(x.args), self(x.keywords))
        if isinstance(x, types.BuiltinFunctionType):
            if not _trusted(getattr(x, "__module__", None) or "builtins"):
                raise Undescribable(f"the built-in function {x!r}")
            return ("builtin", getattr(x, "__module__", None), x.__qualname__)
        if dataclasses.is_dataclass(x):  # equinox modules among them
            fields = []
            for f in dataclasses.fields(x):
                if not hasattr(x, f.name):
                    continue
                fields.append((f.name, self(getattr(x, f.name), static or bool(f.metadata.get("static")))))
            return ("dataclass", self._class(type(x)), tuple(fields))
        if _trusted(type(x).__module__) and type(x).__repr__ is not object.__repr__:
            # a value of jaxbody's or a trusted package's own class that says what it is (a
            # PyTreeDef, a dtype-like): its repr, unless that is just its address
            text = repr(x)
            if " at 0x" not in text:
                return ("repr", self._class(type(x)), text)
        raise Undescribable(f"a {type(x).__module__}.{type(x).__qualname__}")

    def _class(self, cls: type):
        name = (cls.__module__, cls.__qualname__)
        if _trusted(cls.__module__):
            return ("class",) + name
        # a user's class: what its own body defines (methods by code, class-level values)
        body = []
        for attr, value in sorted(vars(cls).items()):
            if attr.startswith("__") and attr.endswith("__") or attr == "_abc_impl":
                if not (isinstance(value, types.FunctionType) and value.__qualname__.startswith(cls.__qualname__ + ".")):
                    continue  # written by Python, dataclasses or equinox, not by the user
            if isinstance(value, (staticmethod, classmethod)):
                value = value.__func__
            if isinstance(value, property):
                value = (value.fget, value.fset)
            body.append((attr, self(value)))
        return ("class",) + name + (tuple(body), tuple(self._class(b) for b in cls.__bases__ if b is not object))

    def _module(self, module: types.ModuleType, names: frozenset):
        if _trusted(module.__name__):
            return ("module", module.__name__)
        # a user's module: the attributes the code that reached it names
        attrs = tuple((n, self(getattr(module, n), True, names)) for n in sorted(names) if hasattr(module, n))
        return ("module", module.__name__, attrs)

    def _function(self, fn: types.FunctionType):
        qualname = fn.__qualname__
        if _trusted(fn.__module__) and "<locals>" not in qualname and not fn.__closure__:
            return ("function", fn.__module__, qualname)
        names = frozenset(_code_names(fn.__code__))
        cells = tuple(self(c.cell_contents, True, names) if _filled(c) else ("empty",) for c in fn.__closure__ or ())
        globals_ = tuple((n, self(fn.__globals__[n], True, names)) for n in sorted(names) if n in fn.__globals__)
        return ("function", fn.__module__, qualname, _code(fn.__code__), cells, globals_,
                self(fn.__defaults__), self(fn.__kwdefaults__))


def input_aval(x) -> tuple:
    """An input array's shape, dtype and weak type (a traced one's too, or a
    :class:`jax.ShapeDtypeStruct` standing for an array not yet computed)."""
    aval = x if isinstance(x, jax.ShapeDtypeStruct) else jax.typeof(x)
    return (tuple(aval.shape), str(aval.dtype), bool(getattr(aval, "weak_type", False)))


def is_input(x) -> bool:
    """An input of a program: an array, or the shape of one (a program prepared for outputs
    that are not computed yet: :func:`jaxbody.program_store.call_then`)."""
    return eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)


def _filled(cell) -> bool:
    try:
        cell.cell_contents
    except ValueError:
        return False
    return True


def describe(x, static: bool = False):
    """``x`` described as nested tuples of plain data, the input arrays by shape and dtype (all
    arrays by value with ``static=True``); raises :class:`Undescribable` where some part of it
    cannot be described."""
    return _Describer()(x, static)


@functools.cache
def _source_hash() -> str:
    """A hash of jaxbody's own source files."""
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        if path.suffix in (".py", ".cc", ".h") and path.is_file():
            digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def _environment(unkeyed: tuple) -> tuple:
    """What a trace depends on besides its arguments: package versions, JAX's configuration,
    jaxbody's environment variables (the cache's place and ``unkeyed`` aside) and the CPU count
    (the native kernel's default threads)."""
    versions = tuple((name, getattr(importlib.import_module(name), "__version__", "?")) for name in _VERSIONED)
    config = jax_settings()
    env = tuple(sorted((k, v) for k, v in os.environ.items()
                       if (k.startswith("JAXBODY_") and k != "JAXBODY_CACHE_DIR" and k not in unkeyed) or k == "CXX"))
    return (_source_hash(), versions, config, env, os.cpu_count(), sys.version_info[:2], jax.default_backend())


def jax_settings() -> tuple:
    """JAX's settings that change a trace, as this thread sees them (a context manager's are
    its thread's own)."""
    return tuple((name, str(getattr(jax.config, name))) for name in (
        "jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion", "jax_numpy_rank_promotion",
        "jax_default_prng_impl", "jax_platforms"))


def fingerprint(name: str, args, differentiated: tuple = (), *, context: tuple = (), unkeyed: tuple = ()) -> str:
    """The key of the program ``name`` of ``args`` (see the module docstring) or, where
    ``differentiated`` marks input arrays, of its derivative with respect to those; ``context``:
    plain data keyed in too (a store's format), ``unkeyed``: environment variables left out
    (a store's own switch). Raises :class:`Undescribable` where the arguments cannot be
    fingerprinted."""
    text = repr((name, tuple(differentiated), tuple(context), _environment(tuple(unkeyed)), describe(args)))
    return hashlib.sha256(text.encode()).hexdigest()
