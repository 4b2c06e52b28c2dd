"""Absolute-form equations of spatial body trees (docs/mathematics.md, "Statement 1" to "Corollary 4").

Quantities are world-frame vectors per body ``k`` (leading axis = body):

* ``m_0k`` body mass, ``m_k`` subsystem mass, ``m̄_k`` augmented static moment (eq. 5) and
  ``I_k`` augmented inertia (eq. 6), both about the base point ``O_0k``;
* ``R_k`` the link ``O_0,p(k) -> O_0k`` (unused for roots);
* ``ω_k``, ``ε_k`` absolute angular velocity/acceleration;
* ``V_rk``, ``W_rk`` relative velocity/acceleration of the pole ``O_k`` with respect to
  ``O_0k``, derivatives taken in body-``k`` axes (docs/mathematics.md, "Points and kinematic quantities" remark);
* ``W_0`` the acceleration of the frame carrying a root's base point (zero for the fixed
  ground, the carrier acceleration for a free base, spec Cor. 1).

Every sum over a carrier chain or a subsystem is a ``segment_sum`` over static index pairs
(:class:`~jaxbody.tree.BodyTree`), so the trace has the same size for any tree.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Float
from ._util import skew
from .tree import BodyTree

__all__ = [
    "ForceFactors",
    "base_point_acceleration",
    "relative_inertial_force",
    "relative_force_factors",
    "absolute_mass_matrix",
    "absolute_bias",
    "skew",
]


def _cross(a, b):
    return jnp.cross(a, b)


class ForceFactors(eqx.Module):
    """Output of Statement 1 (docs/mathematics.md, "Statement 1").

    Attributes:
        force: ``F_k``, force the base exerts on body ``k`` (constraint reaction + drive).
        moment: ``M_k``, its moment about ``O_0k``.
        base_point_acceleration: ``W_0k`` (eq. 3).
        inertial_force: ``F_ek`` (eq. 4).
    """

    force: Float[Array, "n_body 3"]
    moment: Float[Array, "n_body 3"]
    base_point_acceleration: Float[Array, "n_body 3"]
    inertial_force: Float[Array, "n_body 3"]


def base_point_acceleration(
    tree: BodyTree,
    link: Float[ArrayLike, "n_body 3"],
    angular_velocity: Float[ArrayLike, "n_body 3"],
    angular_acceleration: Float[ArrayLike, "n_body 3"],
    relative_velocity: Float[ArrayLike, "n_body 3"] | None,
    relative_acceleration: Float[ArrayLike, "n_body 3"] | None,
    root_acceleration: Float[ArrayLike, "n_body 3"] | None,
) -> Float[Array, "n_body 3"]:
    """Acceleration of every base point, eq. (3).

    ``W_0k = W_0 + sum_{i in C(k)} [W_ri + 2 ω_i×V_ri + ε_i×R_c(i,k) + ω_i×(ω_i×R_c(i,k))]``.
    Each carrier term belongs to the pair (parent ``i``, child ``c``), so the carrier sum is a
    path sum of per-child terms. ``root_acceleration[k]`` is used for roots only.
    """
    par = tree.parent_array
    p = np.maximum(par, 0)
    w, e = angular_velocity[p], angular_acceleration[p]
    term = _cross(e, link) + _cross(w, _cross(w, link))
    # None = identically zero, known when the model is built (no slide joints: poles stay
    # on their base points; no free joint: every root hangs on the fixed ground), so the
    # terms are left out of the program instead of being multiplied by zero.
    if relative_velocity is not None:
        term = term + relative_acceleration[p] + 2.0 * _cross(w, relative_velocity[p])
    term = jnp.where(jnp.asarray(par >= 0)[:, None], term, 0.0)
    W0 = tree.path_sum(term)
    if root_acceleration is not None:
        W0 = W0 + root_acceleration[np.asarray(tree.root, dtype=np.int32)]
    return W0


def relative_inertial_force(
    tree: BodyTree,
    subtree_mass: Float[ArrayLike, " n_body"],
    static_moment: Float[ArrayLike, "n_body 3"],
    angular_velocity: Float[ArrayLike, "n_body 3"],
    angular_acceleration: Float[ArrayLike, "n_body 3"],
    relative_velocity: Float[ArrayLike, "n_body 3"] | None,
    relative_acceleration: Float[ArrayLike, "n_body 3"] | None,
) -> Float[Array, "n_body 3"]:
    """Inertial force of subsystem ``k`` due to motion relative to ``O_0k``, eq. (4)."""
    w = angular_velocity
    per_body = _cross(angular_acceleration, static_moment) + _cross(w, _cross(w, static_moment))
    if relative_velocity is not None:  # None: no relative motion (see base_point_acceleration)
        per_body = per_body + subtree_mass[:, None] * (relative_acceleration + 2.0 * _cross(w, relative_velocity))
    return tree.subtree_sum(per_body)


def relative_force_factors(
    tree: BodyTree,
    subtree_mass: Float[ArrayLike, " n_body"],
    static_moment: Float[ArrayLike, "n_body 3"],
    augmented_inertia: Float[ArrayLike, "n_body 3 3"],
    link: Float[ArrayLike, "n_body 3"],
    angular_velocity: Float[ArrayLike, "n_body 3"],
    angular_acceleration: Float[ArrayLike, "n_body 3"],
    relative_velocity: Float[ArrayLike, "n_body 3"] | None,
    relative_acceleration: Float[ArrayLike, "n_body 3"] | None,
    root_acceleration: Float[ArrayLike, "n_body 3"] | None,
    gravity: Float[ArrayLike, "3"] | None,
    external_force: Float[ArrayLike, "n_body 3"] | None = None,
    external_moment: Float[ArrayLike, "n_body 3"] | None = None,
) -> ForceFactors:
    """Relative force factors ``F_k``, ``M_k`` of every body: Statement 1, eqs (1)–(4).

    Force equation (1): ``F_k = m_k W_0k + F_ek - m_k g - sum_{i in S(k)} F_ri``.
    Moment equation (2) written as ``M_k - sum_{j in A(k)} M_j = X_k`` with

    ``X_k = m̄_k×(W_0k + W_rk + 2ω_k×V_rk) + I_k ε_k + ω_k×I_k ω_k + sum_{j in A(k)} R_j×F_ej
    - m̄_k×g - M_rk - sum_{j in A(k)} R_j×sum_{i in S(j)} F_ri``,

    so ``M_k = sum_{i in S(k)} X_i`` (subtree sum instead of a leaves-first recursion).

    Args:
        relative_velocity, relative_acceleration: ``V_rk``, ``W_rk``; ``None`` when no body
            moves relative to its base point (no slide joints).
        root_acceleration: ``W_0`` of each root's carrier; ``None`` for the fixed ground.
        gravity: ``g``; ``None`` leaves gravity out.
        external_force, external_moment: ``F_rk`` and ``M_rk`` (moment about ``O_0k``) of
            loads other than gravity; ``None`` when there are none.
    """
    w, e = angular_velocity, angular_acceleration
    Vr, Wr = relative_velocity, relative_acceleration
    W0 = base_point_acceleration(tree, link, w, e, Vr, Wr, root_acceleration)
    Fe = relative_inertial_force(tree, subtree_mass, static_moment, w, e, Vr, Wr)
    # Every optional term (relative motion, gravity, loads) that is None is absent from the
    # program, not multiplied by zero: a scene that declares no gravity or no loads pays nothing.
    lin = W0 if gravity is None else W0 - jnp.asarray(gravity, static_moment.dtype)
    F = subtree_mass[:, None] * lin + Fe
    Fs = Fe
    if external_force is not None:
        Fr_sub = tree.subtree_sum(external_force)
        F, Fs = F - Fr_sub, Fe - Fr_sub
    lever = lin if Vr is None else lin + Wr + 2.0 * _cross(w, Vr)
    Iw = jnp.einsum("nij,nj->ni", augmented_inertia, w)
    X = (
        _cross(static_moment, lever)
        + jnp.einsum("nij,nj->ni", augmented_inertia, e)
        + _cross(w, Iw)
        + tree.children_sum(_cross(link, Fs))
    )
    if external_moment is not None:
        X = X - external_moment
    M = tree.subtree_sum(X)
    return ForceFactors(force=F, moment=M, base_point_acceleration=W0, inertial_force=Fe)


def absolute_mass_matrix(
    tree: BodyTree,
    static_moment: Float[ArrayLike, "n_body 3"],
    augmented_inertia: Float[ArrayLike, "n_body 3 3"],
    link: Float[ArrayLike, "n_body 3"],
    total_mass: Float[ArrayLike, ""] | None = None,
) -> Float[Array, "n n"]:
    """Block matrix ``D`` of the absolute equations (docs/mathematics.md, "Corollary 4", Cor. 4; with Cor. 1 rows).

    Unknowns ``(ε_1, …, ε_n)`` (3 each) for a tree of ball-type joints whose poles are the
    base points; ``D_kk = I_k``, ``D_ki = -[m̄_k]×[R_c(i,k)]×`` for ``i in C(k)`` and its
    transpose above the diagonal. With ``total_mass`` given (a translating free base, Cor. 1)
    the first three unknowns are the base acceleration ``W``: ``D_WW = M E``,
    ``D_W,i = -[m̄_i]×`` and ``D_k,W = [m̄_k]×``. ``½ xᵀ D x`` is the kinetic energy in the
    quasi-velocities ``x = (V, ω_1, …, ω_n)``.
    """
    n = tree.n_body
    dtype = static_moment.dtype
    off = 0 if total_mass is None else 3
    D = jnp.zeros((off + 3 * n, off + 3 * n), dtype)
    blk = np.arange(3)
    rows = off + 3 * np.arange(n)[:, None] + blk  # (n, 3)
    D = D.at[rows[:, :, None], rows[:, None, :]].set(augmented_inertia)
    anc = np.asarray(tree.carrier_pair_ancestor, dtype=np.int64)
    if anc.size:
        body = np.asarray(tree.carrier_pair_body, dtype=np.int64)
        child = np.asarray(tree.carrier_pair_child, dtype=np.int64)
        Dki = -skew(static_moment[body]) @ skew(link[child])
        D = D.at[rows[body][:, :, None], rows[anc][:, None, :]].set(Dki)
        D = D.at[rows[anc][:, :, None], rows[body][:, None, :]].set(jnp.swapaxes(Dki, -1, -2))
    if total_mass is not None:
        D = D.at[blk[:, None], blk[None, :]].set(total_mass * jnp.eye(3, dtype=dtype))
        S = skew(static_moment)  # (n, 3, 3)
        D = D.at[blk[None, :, None], rows[:, None, :]].set(-S)
        D = D.at[rows[:, :, None], blk[None, None, :]].set(S)
    return D


def absolute_bias(
    tree: BodyTree,
    static_moment: Float[ArrayLike, "n_body 3"],
    augmented_inertia: Float[ArrayLike, "n_body 3 3"],
    link: Float[ArrayLike, "n_body 3"],
    angular_velocity: Float[ArrayLike, "n_body 3"],
    gravity: Float[ArrayLike, "3"],
) -> Float[Array, "n_body 3"]:
    """Velocity-product and gravity vector ``b`` of the absolute equations (docs/mathematics.md, "Corollary 4", Cor. 4).

    ``b_k = m̄_k × sum_{i in C(k)} ω_i×(ω_i×R_c(i,k)) + ω_k×I_k ω_k
    + sum_{j in A(k)} R_j × sum_{i in S(j)} ω_i×(ω_i×m̄_i) - m̄_k×g``.
    """
    w = angular_velocity
    W0 = base_point_acceleration(tree, link, w, jnp.zeros_like(static_moment), None, None, None)
    cen = tree.subtree_sum(_cross(w, _cross(w, static_moment)))
    Iw = jnp.einsum("nij,nj->ni", augmented_inertia, w)
    return (
        _cross(static_moment, W0 - jnp.asarray(gravity, static_moment.dtype))
        + _cross(w, Iw)
        + tree.children_sum(_cross(link, cen))
    )
