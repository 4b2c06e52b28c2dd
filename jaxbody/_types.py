"""Shared jaxtyping aliases (named dimensions on every public function, defined once).

Dimension names: ``n_body`` bodies, ``nq``/``nv`` generalized coordinates/velocities,
``n_joint`` joints, ``n_pair`` (ancestor, descendant) pairs.
"""

from jaxtyping import Array, ArrayLike, Bool, Float, Int, PyTree, Scalar

__all__ = ["Array", "ArrayLike", "Bool", "Float", "Int", "PyTree", "Scalar"]

from collections.abc import Sequence as _Sequence

#: a small vector given as an array or a plain sequence of numbers (builder inputs)
VectorLike = ArrayLike | _Sequence[float | int] | _Sequence[_Sequence[float | int]]
__all__ += ["VectorLike"]
#: a real number given as a Python/NumPy scalar or a 0-d array
ScalarLike = ArrayLike
__all__ += ["ScalarLike"]
