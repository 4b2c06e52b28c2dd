"""Switching kinematic structure: the impulsive change to a new constraint set (docs/maggi.md §6, M.14).

Phases of constraint sets with switches are run by ``jb.simulate(jb.Phases(...))``, which
projects the velocities at each switch with :func:`switch_constraints`.
"""

import equinox as eqx
import jax.numpy as jnp

from .. import linalg
from .._types import Array
from .constrained import ConstrainedSystem
from .projections import project_velocities

__all__ = ["SwitchReport", "switch_constraints"]


class SwitchReport(eqx.Module):
    """What happened at a change of constraint set (docs/maggi.md §6).

    Attributes:
        t: switch time.
        x_before, x_after: quasi-velocities ``x⁻``, ``x⁺``.
        impulse: constraint impulses ``Π = Kᵀ·D·(x⁺ − x⁻)`` of the new constraints (s_new,).
        generalized_impulse: ``D·(x⁺ − x⁻)`` (n,).
        energy_lost: ``½(x⁻ − x⁺)ᵀD(x⁻ − x⁺)`` (≥ 0).
        energy_before, energy_after: total energy just before and after.
    """

    t: Array
    x_before: Array
    x_after: Array
    impulse: Array
    generalized_impulse: Array
    energy_lost: Array
    energy_before: Array
    energy_after: Array


def switch_constraints(new: ConstrainedSystem, t, q, x_before) -> SwitchReport:
    """Impulsive change to the constraint set of ``new`` (M.14).

    ``x⁺ = A(AᵀDA)⁻¹AᵀD·(x⁻ + K c) − K c`` where ``c = f*(t, q, 0)`` for affine constraints
    (``x⁺ = A(AᵀDA)⁻¹AᵀD·x⁻`` for homogeneous ones); a looser set (``x⁻`` already admissible)
    keeps the velocity.
    """
    x_before = jnp.asarray(x_before)
    return _switch(new, jnp.asarray(t, x_before.dtype), jnp.asarray(q), x_before)


@eqx.filter_jit
def _switch(new, t, q, x_before):
    # the impulse is instantaneous: q does not move, so D, A and K are all taken at the switch
    # state with the velocity before it
    D = new.kinetic_metric(t, q, x_before)
    if new.n_constraint == 0:
        x_after = x_before
        K = jnp.zeros((new.nv, 0), D.dtype)
    else:
        A, K, _ = new.parametrisation(t, q, x_before)
        # affine part c = f*(t, q, 0) of linear rows (f* = Gx + c): the shift −Kc meets Gx⁺ + c = 0
        c = new.constraint_residual(t, q, jnp.zeros_like(x_before))
        target = x_before + K @ c
        # D-orthogonal projection onto the admissible velocities: the impulse D(x⁺ − x⁻) = GᵀΠ lies
        # in the span of Gᵀ and is eliminated with AᵀGᵀ = 0 (M.14)
        alpha = linalg.solve_spd(A.T @ D @ A, A.T @ (D @ target))
        x_after = A @ alpha - K @ c
        # M.14 treats the rows as affine (G taken at x⁻, c at x = 0); for nonlinear rows Newton
        # steps of the kinetic-metric projection finish the job
        if not all(cn.linear for cn in new.constraints):
            x_after = project_velocities(new, q, x_after, t)
    dx = x_after - x_before
    P = D @ dx
    return SwitchReport(
        t=jnp.asarray(t, D.dtype),
        x_before=x_before,
        x_after=x_after,
        # GK = I recovers each row's impulse Π from the generalized impulse GᵀΠ
        impulse=K.T @ P,
        generalized_impulse=P,
        energy_lost=0.5 * dx @ D @ dx,
        energy_before=new.total_energy(q, x_before),
        energy_after=new.total_energy(q, x_after),
    )
