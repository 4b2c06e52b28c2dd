"""Counterweights and link extensions folded into the bodies' mass, centre of mass and inertia."""

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .. import identify
from .bodies import check_system, dimension, is_planar

__all__ = ["fold_counterweights", "fold_point_masses", "extension_rod", "fold_with_extensions"]


def fold_counterweights(system, bodies: Sequence[int], mass, position, gyration: float = 0.0):
    """The system with point counterweights folded into the bodies.

    Args:
        system: planar system or :class:`Model`.
        bodies: the bodies that carry a counterweight (static).
        mass: ``(n_cw,)`` counterweight masses.
        position: ``(n_cw, dim)`` positions in the body's frame (planar: body axes from the
            hinge, like ``body_com``; models: body frame, like ``body_com``).
        gyration: radius of gyration of each counterweight about its own centre (``0``: point).

    Returns:
        The system with ``m' = m + μ``, ``c' = (m c + μ p) / m'`` and the inertia about the new
        centre of mass by the parallel-axis theorem (traceable: ``grad`` reaches ``mass`` and
        ``position``).
    """
    check_system(system)
    idx = tuple(int(b) for b in np.asarray(bodies, dtype=np.int64).reshape(-1))
    mu = jnp.asarray(mass)
    p = jnp.asarray(position)
    if p.shape != (len(idx), dimension(system)) or mu.shape != (len(idx),):
        raise ValueError(
            f"counterweights: mass has shape {mu.shape} and position {p.shape}, expected "
            f"({len(idx)},) and ({len(idx)}, {dimension(system)}) for bodies {idx}"
        )
    g2 = float(gyration) ** 2
    if is_planar(system):
        extra = mu * g2
    else:  # a homogeneous ball of radius of gyration g: (2/3) g² μ about each axis
        extra = mu[:, None, None] * (2.0 / 3.0 * g2) * jnp.eye(3, dtype=p.dtype)
    return fold_point_masses(system, idx, mu, p, extra)


@eqx.filter_jit
def fold_point_masses(system, bodies, mass, position, extra):
    """Fold point masses ``mass`` at ``position`` plus their own central inertia ``extra``
    (planar ``(n_cw,)``, spatial ``(n_cw, 3, 3)``) into ``bodies`` (repeats allowed)."""
    idx = np.asarray(bodies, dtype=np.int64)
    mu, p = mass, position
    if is_planar(system):
        m = system.body_mass
        c = system.body_com
        J = system.body_inertia + m * jnp.sum(c * c, axis=-1)  # about the hinge
        m2 = m.at[idx].add(mu)
        h2 = (m[:, None] * c).at[idx].add(mu[:, None] * p)
        J2 = J.at[idx].add(mu * jnp.sum(p * p, axis=-1) + extra)
        c2 = h2 / m2[:, None]
        I2 = J2 - m2 * jnp.sum(c2 * c2, axis=-1)
        return eqx.tree_at(lambda s: (s.body_mass, s.body_com, s.body_inertia), system, (m2, c2, I2))
    pi = identify.parameters(system).reshape(system.n_body, 10)
    eye = jnp.eye(3, dtype=p.dtype)
    Ip = mu[:, None, None] * (jnp.sum(p * p, axis=-1)[:, None, None] * eye - p[:, :, None] * p[:, None, :]) + extra
    add = jnp.concatenate(
        [mu[:, None], mu[:, None] * p, jnp.stack([Ip[:, i, j] for i, j in identify.SYMMETRIC_INDEX], axis=-1)], axis=-1
    )
    pi = pi.at[idx].add(add)
    return identify.with_parameters(system, pi.reshape(-1))


def extension_rod(system, direction, length, density):
    """A straight uniform rod from the base point along ``direction`` (unit, ``(n, dim)``):
    mass ``density · length``, centre at ``length/2 · direction``, central inertia
    ``m ℓ²/12`` about the hinge axis (planar) or ``m ℓ²/12 (1 − d dᵀ)`` (spatial)."""
    mass = density * length
    centre = 0.5 * length[:, None] * direction
    i_perp = mass * length**2 / 12.0
    if is_planar(system):
        return mass, centre, i_perp
    eye = jnp.eye(3, dtype=direction.dtype)
    return mass, centre, i_perp[:, None, None] * (eye - direction[:, :, None] * direction[:, None, :])




def fold_with_extensions(system, cw, mu, p, e, anchor, direction, density, gyration):
    """Counterweights at the ends of the extensions, and the extension rods, folded in."""
    rm, rc, ri = extension_rod(system, direction, e, density)
    g2 = float(gyration) ** 2
    if is_planar(system):
        extra = jnp.concatenate([mu * g2, ri])
    else:
        extra = jnp.concatenate([mu[:, None, None] * (2.0 / 3.0 * g2) * jnp.eye(3, dtype=p.dtype), ri])
    return fold_point_masses(system, tuple(cw) + tuple(cw), jnp.concatenate([mu, rm]),
                 jnp.concatenate([p, anchor + rc]), extra)
