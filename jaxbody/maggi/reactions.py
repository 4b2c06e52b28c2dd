"""Outputs along a solution of a constrained system: the reactions ``Λ`` (M.12) and the
constraint residuals (position and velocity) at each saved state."""

import equinox as eqx
import jax
import jax.numpy as jnp

from .._types import Array
from .constrained import ConstrainedSystem

__all__ = ["reactions", "constraint_residuals"]


def reactions(system: ConstrainedSystem, t, q, x, tau=None) -> Array:
    """Constraint reactions ``Λ`` (M.12) along a trajectory: ``t`` (N,), ``q`` (N, nq),
    ``x`` (N, nv) (e.g. ``sol.t, sol.q, sol.v`` of :func:`jaxbody.simulate`). Returns (N, s)."""
    return _reactions(system, jnp.asarray(t), jnp.asarray(q), jnp.asarray(x), tau)


@eqx.filter_jit
def _reactions(system, t, q, x, tau):
    # Λ does not depend on the partition: evaluate each state with its best-conditioned one
    return jax.vmap(lambda tt, qq, xx: system.with_best_partition(tt, qq, xx).solve_inline(tt, qq, xx, tau, False).reactions)(t, q, x)


def constraint_residuals(system: ConstrainedSystem, t, q, x) -> tuple[Array, Array]:
    """``(position, velocity)`` residuals along a trajectory, each (N, s): ``φ(t, q)`` on the
    holonomic rows (zero elsewhere) and ``f*(t, q, x)``."""
    return _residuals(system, jnp.asarray(t), jnp.asarray(q), jnp.asarray(x))


@eqx.filter_jit
def _residuals(system, t, q, x):
    # on the states as integrated, nothing projected first: these measure the drift that the
    # Baumgarte terms keep bounded
    pos = jax.vmap(system.position_residual)(t, q)
    vel = jax.vmap(system.constraint_residual)(t, q, x)
    return pos, vel
