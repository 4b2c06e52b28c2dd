"""Augmented bodies: subtree masses, augmented static moments and inertia tensors (docs/mathematics.md, "The augmented body").

Augmented body ``k`` is body ``k`` plus, for every adjacent (child) body ``j``, a point mass
``m_j`` — the whole mass of subsystem ``j`` — placed at the child's base point ``O_0j``.

All functions take the tree (static) and per-body arrays with a leading body axis; they are
sums over children or subtrees done with ``segment_sum`` over static index pairs, so the
trace is the same for any number of bodies. Vectors may be 3-D (spatial trees) or 2-D
(planar trees); :func:`static_moment` works for both.
"""

import equinox as eqx
import jax.numpy as jnp

from ._types import Array, ArrayLike, Float
from .tree import BodyTree

__all__ = [
    "AugmentedBodies",
    "subtree_mass",
    "static_moment",
    "augmented_inertia",
    "augmented_moment_of_inertia",
    "subtree_static_moment",
]


class AugmentedBodies(eqx.Module):
    """Augmented quantities of every body, in one frame (world for spatial trees).

    Attributes:
        subtree_mass: ``m_k``, mass of subsystem ``k`` (docs/mathematics.md, "The augmented body").
        static_moment: ``m̄_k`` about the base point ``O_0k`` (eq. 5).
        augmented_inertia: ``I_k`` about ``O_0k`` (eq. 6); ``(n_body, 3, 3)`` for spatial
            trees, ``(n_body,)`` (the planar ``J_k``) for planar ones.
    """

    subtree_mass: Float[Array, " n_body"]
    static_moment: Float[Array, "n_body dim"]
    augmented_inertia: Float[Array, "n_body *inertia"]


def subtree_mass(tree: BodyTree, body_mass: Float[ArrayLike, " n_body"]) -> Float[Array, " n_body"]:
    """Mass of subsystem ``k``: ``m_k = sum_{i in S(k)} m_0i`` (docs/mathematics.md, "The augmented body")."""
    return tree.subtree_sum(jnp.asarray(body_mass))


def static_moment(
    tree: BodyTree,
    body_mass: Float[ArrayLike, " n_body"],
    com_offset: Float[ArrayLike, "n_body dim"],
    link: Float[ArrayLike, "n_body dim"],
) -> Float[Array, "n_body dim"]:
    """Static moment of augmented body ``k`` about its base point, eq. (5).

    ``m̄_k = m_0k r_k + sum_{j in A(k)} m_j R_j``.

    Args:
        tree: body tree.
        body_mass: ``m_0k``.
        com_offset: ``r_k`` = vector ``O_0k -> C_k`` (base point to the body's CM).
        link: ``R_k`` = vector ``O_0,p(k) -> O_0k`` from the parent's base point to this
            body's base point (ignored for bodies without a parent).

    Returns:
        ``m̄_k`` in the frame of the inputs, 2-D or 3-D.
    """
    body_mass = jnp.asarray(body_mass)
    m = subtree_mass(tree, body_mass)
    return body_mass[:, None] * com_offset + tree.children_sum(m[:, None] * link)


def _point_inertia(mass, r):
    """``mass * (r·r E - r rᵀ)`` for stacked ``r`` of shape (n, 3)."""
    r2 = jnp.sum(r * r, axis=-1)
    eye = jnp.eye(3, dtype=r.dtype)
    return mass[:, None, None] * (r2[:, None, None] * eye - r[:, :, None] * r[:, None, :])


def augmented_inertia(
    tree: BodyTree,
    body_mass: Float[ArrayLike, " n_body"],
    central_inertia: Float[ArrayLike, "n_body 3 3"],
    com_offset: Float[ArrayLike, "n_body 3"],
    link: Float[ArrayLike, "n_body 3"],
) -> Float[Array, "n_body 3 3"]:
    """Inertia tensor of augmented body ``k`` about its base point ``O_0k``, eq. (6).

    ``I_k = I_Ck + m_0k (r_k² E - r_k r_kᵀ) + sum_{j in A(k)} m_j (R_j² E - R_j R_jᵀ)``.

    Args: as :func:`static_moment`, plus ``central_inertia`` = ``I_Ck`` about the CM, in the
    same frame as the vectors.
    """
    body_mass = jnp.asarray(body_mass)
    m = subtree_mass(tree, body_mass)
    return (
        central_inertia
        + _point_inertia(body_mass, com_offset)
        + tree.children_sum(_point_inertia(m, link))
    )


def augmented_moment_of_inertia(
    tree: BodyTree,
    body_mass: Float[ArrayLike, " n_body"],
    central_inertia: Float[ArrayLike, " n_body"],
    com_offset: Float[ArrayLike, "n_body 2"],
    link: Float[ArrayLike, "n_body 2"],
) -> Float[Array, " n_body"]:
    """Planar reduction of eq. (6): ``J_k = k·I_k k`` about the hinge axis of body ``k``.

    ``J_k = I_Ck + m_0k |r_k|² + sum_{j in A(k)} m_j |R_j|²`` (docs/mathematics.md, "Planar systems in absolute angles"), with
    ``central_inertia`` the moment of inertia about the axis through the CM normal to the plane.
    """
    body_mass = jnp.asarray(body_mass)
    m = subtree_mass(tree, body_mass)
    return (
        central_inertia
        + body_mass * jnp.sum(com_offset**2, axis=-1)
        + tree.children_sum(m * jnp.sum(link**2, axis=-1))
    )


def subtree_static_moment(
    tree: BodyTree, static_moment: Float[ArrayLike, "n_body dim"]
) -> Float[Array, "n_body dim"]:
    """Static moment of the whole subsystem ``k`` about ``O_0k``: ``sum_{i in S(k)} m̄_i`` (docs/mathematics.md, "The augmented body")."""
    return tree.subtree_sum(static_moment)
