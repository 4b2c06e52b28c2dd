"""The constraint slot of a scene: the protocol the Maggi layer plugs into.

A constraint does not add a force: it replaces the unconstrained solve ``M a = f`` of the
scene by a projected one and reports the reactions it needed. A constraint object provides

* ``accelerations(ctx, mass_matrix, force) -> (a, reactions)``: the accelerations ``(nv,)``
  that satisfy the constraints and the reactions ``(s,)``, one per constraint row, with
  ``M a = force + Gᵀ·reactions`` (``G`` the Jacobian of the constraint rows with respect to
  ``v``);
* ``drift(ctx) -> (position (s,), velocity (s,))``: the current violation of the constraints,
  at position level (zero on rows that have none) and at velocity level, which the simulator
  records along the solution (``Solution.constraint_drift``).

:class:`jaxbody.maggi.ConstrainedSystem` implements it: build one with
``jaxbody.maggi.constrain(model, [...], q_ref=...)`` from the ready constraints of
:mod:`jaxbody.constraints` (or pass the list of constraints to ``jb.scene`` directly).
"""

from typing import Protocol, runtime_checkable

from .._types import Array, Float
from ._base import EffectContext

__all__ = ["Constraint"]


@runtime_checkable
class Constraint(Protocol):
    """What a scene's ``constraints`` slot needs (structural: no base class required)."""

    def accelerations(
        self, ctx: EffectContext, mass_matrix: Float[Array, "nv nv"], force: Float[Array, " nv"]
    ) -> tuple[Float[Array, " nv"], Float[Array, " s"]]: ...

    def drift(self, ctx: EffectContext) -> tuple[Float[Array, " s"], Float[Array, " s"]]: ...
