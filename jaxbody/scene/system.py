"""The system path: a planar system, a :class:`jaxbody.maggi.ConstrainedSystem` or any other
object with the simulation protocol (:class:`jaxbody.simulation.DynamicalSystem`).

Such a system brings its own dynamics (and gravity, when it has one); the scene adds only
effects of its own coordinates (actuation), which it hands to the system's ``acceleration`` as
the extra generalized force.
"""

import dataclasses
from typing import final

import jax.numpy as jnp

from .._types import Array, Float
from ..effects import EffectContext
from ..maggi import ConstrainedSystem
from .base import Scene, compiled_when_eager

__all__ = ["SystemScene", "own_constraints"]


def own_constraints(system):
    """The constraint slot of a scene of ``system``: the system itself when it is a
    :class:`jaxbody.maggi.ConstrainedSystem` (its constraints are part of its dynamics), else ``None``."""
    return system if isinstance(system, ConstrainedSystem) else None


@final
class SystemScene(Scene):
    """A system with the simulation protocol on the ``"system"`` path (see :class:`jaxbody.Scene`)."""

    @property
    def path(self) -> str:
        return "system"

    @property
    def work_names(self) -> tuple[str, ...]:
        # a system that reports the power of its own non-conservative forces (e.g. a planar
        # system's joint damping) has one work entry for all of them
        if hasattr(self.system, "power"):
            return ("power",)
        return tuple(e.name for e in self.effects if not e.conservative)

    @property
    def has_energy(self) -> bool:
        # total_energy is optional in the protocol: without it there is no energy balance
        return hasattr(self.system, "total_energy")

    def is_direct(self) -> bool:
        return False

    def direct_kernel(self) -> str | None:
        return None

    def with_constraints(self, constraints) -> "SystemScene":
        # a ConstrainedSystem is both the system and its constraints: replace it in both places
        if self.system is self.constraints:
            return dataclasses.replace(self, system=constraints, constraints=constraints)
        return dataclasses.replace(self, constraints=constraints)

    def context(self, t, q, v) -> EffectContext:
        return EffectContext(self, t, q, v)

    def uniform_field_force(self, ctx: EffectContext, field):
        raise ValueError(f"uniform fields need a jaxbody.Model; {type(self.system).__name__} brings its own gravity")

    def uniform_field_potential(self, ctx: EffectContext, field):
        raise ValueError(f"uniform fields need a jaxbody.Model; {type(self.system).__name__} brings its own gravity")

    def body_wrench_force(self, ctx: EffectContext, wrenches):
        raise ValueError("body loads need the spatial path")

    @compiled_when_eager
    def qdot(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nq"]:
        return self.system.qdot(q, v)

    @compiled_when_eager
    def evaluate(self, t, q, v, tau=None):
        ctx = self.context(t, q, v)
        forces = [e.generalized_force(ctx) for e in self.effects]
        # None when nothing pushes: the protocol's acceleration takes tau=None
        total = None
        for f in forces + ([] if tau is None else [tau]):
            total = f if total is None else total + f
        if self.constraints is not None:
            # a constrained system: its solve returns the reactions with the accelerations
            r = self.system.solve(t, q, v, total, stabilise=True)
            a, reaction = r.xdot, r.reactions
        else:
            a, reaction = self.system.acceleration(t, q, v, total), None
        if hasattr(self.system, "power"):
            powers = (self.system.power(t, q, v, total),)
        else:
            powers = tuple(jnp.dot(f, v) for e, f in zip(self.effects, forces) if not e.conservative)
        return a, powers, reaction

    @compiled_when_eager
    def kinetic_energy(self, q, v) -> Float[Array, ""]:
        raise ValueError("kinetic_energy: this system has no separate kinetic energy")

    @compiled_when_eager
    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        return self.system.total_energy(q, v)
