"""The outputs of a stored program: its arrays, and the structure around them (tuples, lists,
dicts, dataclasses, plain values) as data that can be pickled beside the program and rebuilt
in a later process without tracing (:mod:`jaxbody.program_store`)."""

import dataclasses
import importlib

import jax
import numpy as np

from .program_fingerprint import Undescribable

__all__ = ["arrays_in", "rebuild", "skeleton"]


def skeleton(x, leaves: list):
    """``x`` as plain data that can be stored, with its arrays appended to ``leaves``."""
    if isinstance(x, jax.Array | np.ndarray):
        leaves.append(x)
        return ("array",)
    if x is None or isinstance(x, (bool, int, float, str)):
        return ("value", x)
    if isinstance(x, type):
        return ("class", x.__module__, x.__qualname__)
    if isinstance(x, (tuple, list)) and not hasattr(x, "_fields"):
        return (type(x).__name__, [skeleton(v, leaves) for v in x])
    if isinstance(x, dict):
        return ("dict", [(k, skeleton(v, leaves)) for k, v in x.items()])
    if dataclasses.is_dataclass(x):
        fields = [(f.name, skeleton(getattr(x, f.name), leaves)) for f in dataclasses.fields(x) if hasattr(x, f.name)]
        return ("dataclass", type(x).__module__, type(x).__qualname__, fields)
    raise Undescribable(f"an output of type {type(x).__qualname__}")


def _resolve(module: str, qualname: str):
    obj = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def rebuild(skeleton, leaves):
    """The inverse of :func:`skeleton`: ``leaves`` an iterator over the arrays."""
    kind = skeleton[0]
    if kind == "array":
        return next(leaves)
    if kind == "value":
        return skeleton[1]
    if kind == "class":
        return _resolve(skeleton[1], skeleton[2])
    if kind in ("tuple", "list"):
        items = [rebuild(v, leaves) for v in skeleton[1]]
        return tuple(items) if kind == "tuple" else items
    if kind == "dict":
        return {k: rebuild(v, leaves) for k, v in skeleton[1]}
    cls = _resolve(skeleton[1], skeleton[2])
    # the fields as they were (their converters already ran when the output was made)
    obj = object.__new__(cls)
    for name, value in skeleton[3]:
        object.__setattr__(obj, name, rebuild(value, leaves))
    return obj


def arrays_in(skeleton) -> int:
    """How many arrays the outputs of ``skeleton`` (:func:`skeleton`) hold."""
    kind = skeleton[0]
    if kind == "array":
        return 1
    if kind in ("tuple", "list"):
        return sum(map(arrays_in, skeleton[1]))
    if kind == "dict":
        return sum(arrays_in(v) for _, v in skeleton[1])
    if kind == "dataclass":
        return sum(arrays_in(v) for _, v in skeleton[3])
    return 0
