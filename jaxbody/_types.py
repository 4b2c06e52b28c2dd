"""Shared jaxtyping aliases (STYLE rule 8).

Dimension names: ``n_body`` bodies, ``nq``/``nv`` generalized coordinates/velocities,
``n_joint`` joints, ``n_pair`` (ancestor, descendant) pairs.
"""

from jaxtyping import Array, ArrayLike, Bool, Float, Int, PyTree, Scalar

__all__ = ["Array", "ArrayLike", "Bool", "Float", "Int", "PyTree", "Scalar"]
