"""Joint-space view of planar systems: relative angles and Lagrange's equations in them (docs/mathematics.md, "Corollary 7").

``α = T q`` maps joint (relative) angles to absolute ones; ``Tᵀ ℳ T`` and ``Tᵀ h`` are the mass
matrix and bias of the joint-angle equations (the coordinates of a spatial model with the same
hinges, see :func:`jaxbody.planar.from_model`).
"""

import jax.numpy as jnp
import numpy as np

from .._types import Array, Float
from .._util import check_shape, index
from .dynamics import bias_forces, mass_matrix, split_base
from .parameters import PlanarParameters

__all__ = ["absolute_to_relative", "relative_to_absolute", "joint_mass_matrix", "joint_bias_forces"]


def absolute_to_relative(system: PlanarParameters, q: Float[Array, " nq"]) -> Float[Array, " nq"]:
    """Joint (relative) angles ``q_k = θ_k − θ_{p(k)}`` (docs/mathematics.md, "Corollary 7", ``α = T q``).

    Roots keep their angle (relative to the ground/base, in the system's angle convention); base
    coordinates pass through. Linear, so it converts rates and accelerations alike.
    """
    q = check_shape(q, (system.nq,), "q", "planar system")
    qb, a = split_base(system, q)
    parent = np.asarray(system.tree.parent)
    ap = jnp.where(jnp.asarray(parent >= 0), a[index(np.maximum(parent, 0))], 0.0)
    return jnp.concatenate([qb, a - ap])


def relative_to_absolute(system: PlanarParameters, q_rel: Float[Array, " nq"]) -> Float[Array, " nq"]:
    """Absolute angles ``α = T q`` from joint angles: ``α_k = Σ_{i∈C(k)∪{k}} q_i`` (docs/mathematics.md, "Corollary 7")."""
    q_rel = check_shape(q_rel, (system.nq,), "q_rel", "planar system")
    qb, r = split_base(system, q_rel)
    return jnp.concatenate([qb, system.tree.path_sum(r)])


def _transpose_path(system, x):
    """``Tᵀ x`` over the leading (angle) axis: ``(Tᵀx)_i = Σ_{k∈S(i)} x_k``."""
    return system.tree.subtree_sum(x)


def joint_mass_matrix(system: PlanarParameters, q: Float[Array, " nq"]) -> Float[Array, "nv nv"]:
    """Joint-space mass matrix ``Tᵀ ℳ T`` (docs/mathematics.md, "Corollary 7"; identity on the base block)."""
    M = mass_matrix(system, q)
    nb = system.n_base
    Mbb, Mbt, Mtt = M[:nb, :nb], M[:nb, nb:], M[nb:, nb:]
    Mtt_q = _transpose_path(system, _transpose_path(system, Mtt).T).T
    if nb == 0:
        return Mtt_q
    Mbt_q = _transpose_path(system, Mbt.T).T
    return jnp.block([[Mbb, Mbt_q], [Mbt_q.T, Mtt_q]])


def joint_bias_forces(
    system: PlanarParameters, q: Float[Array, " nq"], v: Float[Array, " nv"]
) -> Float[Array, " nv"]:
    """``Tᵀ h``: velocity and gravity terms of Lagrange's equations in joint angles (docs/mathematics.md, "Corollary 7").

    ``v`` are the absolute rates (convert joint rates with :func:`relative_to_absolute`).
    """
    hb, ht = split_base(system, bias_forces(system, q, v))
    return jnp.concatenate([hb, _transpose_path(system, ht)])


