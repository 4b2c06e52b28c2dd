"""The coupling measure: the largest normalised off-diagonal entry of the mass matrix in
absolute angles over configurations."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import planar, spatial
from ..sampling import random_states
from ..dynamics import augmented_bodies
from ..kinematics import forward_kinematics
from ..model import Model
from .bodies import check_system, is_planar, moving_bodies

__all__ = ["coupling", "absolute_mass_matrix"]


def _random_configs(system, n, seed):
    rng = np.random.default_rng(seed)
    if is_planar(system):
        cfg = np.zeros((n, system.nq))
        cfg[:, system.n_base :] = rng.uniform(-np.pi, np.pi, size=(n, system.n_body))
        return cfg
    q, _, _ = random_states(system, n, seed)
    return q


def _normalised_offdiag(M, blocks):
    """max over i≠j of |M_ij| / sqrt(M_ii M_jj) (blocks: Frobenius norms of blocks)."""
    if blocks == 1:
        d = jnp.sqrt(jnp.abs(jnp.diagonal(M, axis1=-2, axis2=-1)))
        dd = d[..., :, None] * d[..., None, :]
        R = jnp.where(dd > 0, jnp.abs(M) / jnp.where(dd > 0, dd, 1.0), 0.0)
        n = M.shape[-1]
    else:
        n = M.shape[-1] // blocks
        B = M.reshape(M.shape[:-2] + (n, blocks, n, blocks))
        F = jnp.sqrt(jnp.sum(B * B, axis=(-3, -1)))
        d = jnp.sqrt(jnp.diagonal(F, axis1=-2, axis2=-1))
        dd = d[..., :, None] * d[..., None, :]
        R = jnp.where(dd > 0, F / jnp.where(dd > 0, dd, 1.0), 0.0)
    # massless bodies (zero diagonal) neither couple nor count (handled by the where above)
    return jnp.max(jnp.where(jnp.eye(n, dtype=bool), 0.0, R))


def absolute_mass_matrix(model: Model, q):
    """The absolute block mass matrix ``D`` of a model at ``q``: ``3×3`` blocks in the absolute
    angular velocities of the bodies (:func:`jaxbody.spatial.absolute_mass_matrix`)."""
    kin = forward_kinematics(model, q)
    aug = augmented_bodies(model, q)
    par = np.asarray(model.tree.parent)
    link = kin.base_point - kin.base_point[np.maximum(par, 0)]
    link = jnp.where(jnp.asarray(par >= 0)[:, None], link, 0.0)
    return spatial.absolute_mass_matrix(model.tree, aug.static_moment, aug.augmented_inertia, link)


@jax.jit
def _planar_coupling(system, cfg):
    return _normalised_offdiag(jax.vmap(planar.mass_matrix, in_axes=(None, 0))(system, cfg), 1)


@eqx.filter_jit
def _spatial_coupling(system, cfg, rows):
    Ds = jax.vmap(absolute_mass_matrix, in_axes=(None, 0))(system, cfg)[:, rows][:, :, rows]
    return _normalised_offdiag(Ds, 3)


def coupling(system, configurations=None, n_samples: int = 32, seed: int = 0) -> float:
    """Largest normalised off-diagonal coupling over configurations.

    Planar: ``max |ℳ_ij| / sqrt(ℳ_ii ℳ_jj)`` of the absolute-angle mass matrix
    (:func:`jaxbody.planar.mass_matrix`). Models (fixed base): the same with the Frobenius
    norms of the 3×3 blocks of the absolute block matrix ``D`` in the absolute angular
    velocities (:func:`jaxbody.spatial.absolute_mass_matrix`), over the moving bodies.
    ``0`` means decoupled; ``1`` is the largest possible value.
    """
    check_system(system)
    cfg = _random_configs(system, n_samples, seed) if configurations is None else np.asarray(configurations)
    cfg = jnp.asarray(cfg, system.body_mass.dtype)
    if is_planar(system):
        return float(_planar_coupling(system, cfg))
    if any(system.joints.body_is_free):
        raise ValueError("coupling: models with a free-floating body are not supported; use a fixed base")
    keep = np.nonzero(moving_bodies(system))[0]
    rows = (3 * keep[:, None] + np.arange(3)).reshape(-1)
    return float(_spatial_coupling(system, cfg, rows))
