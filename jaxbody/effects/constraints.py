"""The constraint slot of a scene: the protocol the Maggi layer plugs into.

A constraint does not add a force: it replaces the unconstrained solve ``M a = f`` of the
scene by a projected one and reports the reaction it needed. A constraint object provides

* ``accelerations(ctx, mass_matrix, force) -> (a, reactions)``: the accelerations ``(nv,)``
  that satisfy the constraints and the generalized reaction forces ``(nv,)`` with
  ``M a = force + reactions``;
* ``drift(ctx) -> (m,)``: the current violation of the constraints (position level), which the
  simulator records along the solution.

The Maggi constraints of the constraint layer implement the same two members. :class:`HolonomicConstraint` is a ready one for coordinates with ``q̇ = v``
(hinge and slide joints): ``φ(q) = 0`` enforced at the acceleration level with Lagrange
multipliers and Baumgarte stabilisation.
"""

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import equinox as eqx
import jax
import jax.numpy as jnp

from .._types import Array, Float
from ..linalg import solve_spd
from ._base import EffectContext

__all__ = ["Constraint", "HolonomicConstraint"]


@runtime_checkable
class Constraint(Protocol):
    """What a scene's ``constraints`` slot needs (structural: no base class required)."""

    def accelerations(
        self, ctx: EffectContext, mass_matrix: Float[Array, "nv nv"], force: Float[Array, " nv"]
    ) -> tuple[Float[Array, " nv"], Float[Array, " nv"]]: ...

    def drift(self, ctx: EffectContext) -> Float[Array, " m"]: ...


class HolonomicConstraint(eqx.Module):
    """``φ(q) = 0`` (``m`` equations) on a model whose coordinates satisfy ``q̇ = v``.

    With ``G = ∂φ/∂q``: ``M a = f + Gᵀλ`` and ``G a = −Ġ v − 2ζω G v − ω² φ`` (Baumgarte:
    ``ζ``, ``ω`` damp drift; ``ω = 0`` is the exact index-reduced form). The reaction reported is
    ``Gᵀλ``.

    Attributes:
        phi: ``φ(q) -> (m,)``; an ``equinox.Module`` for differentiable parameters.
        stabilization: Baumgarte ``ω`` (1/s); ``0`` disables it.
        damping_ratio: Baumgarte ``ζ``.
    """

    phi: Callable
    stabilization: float = eqx.field(static=True, default=0.0)
    damping_ratio: float = eqx.field(static=True, default=1.0)

    def accelerations(self, ctx, mass_matrix, force):
        q, v = ctx.q, ctx.v
        G = jax.jacfwd(self.phi)(q)
        G_v, Gdot_v = jax.jvp(lambda qq: jax.jacfwd(self.phi)(qq) @ v, (q,), (v,))
        rhs = -Gdot_v
        if self.stabilization:
            w = self.stabilization
            rhs = rhs - 2.0 * self.damping_ratio * w * G_v - w * w * self.phi(q)
        Minv_f = solve_spd(mass_matrix, force)
        Minv_Gt = jax.vmap(lambda g: solve_spd(mass_matrix, g))(G).T
        lam = solve_spd(G @ Minv_Gt, rhs - G @ Minv_f)
        return Minv_f + Minv_Gt @ lam, G.T @ lam

    def drift(self, ctx):
        return jnp.atleast_1d(self.phi(ctx.q))
