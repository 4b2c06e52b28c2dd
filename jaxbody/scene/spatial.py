"""The spatial path: a :class:`jaxbody.Model` on the spatial tree (any joints, constraints, loads).

Gravity is an effect of the scene, so the tree's own bias is taken with gravity off; the
kernels of :mod:`jaxbody.kernels` check nothing, so they are safe inside a vmapped solver loop.
"""

from typing import final

import equinox as eqx
import jax.numpy as jnp

from ..backends import native, unrolled
from .._types import Array, Float
from ..data import compute_data
from ..effects import Actuation, EffectContext, FourierTorque, Gravity, JointDampers, JointSprings
from ..backends import acceleration, resolve_kernel
from ..kernels import bias_forces, body_wrench_force, kinetic_energy, mass_matrix, uniform_field_force
from ..linalg import solve_spd
from ..shared_evaluation import shared_evaluations
from .base import ModelScene, compiled_when_eager

__all__ = ["SpatialScene"]


@final
class SpatialScene(ModelScene):
    """A :class:`jaxbody.Model` on the spatial path (see :class:`jaxbody.Scene`).

    Attributes:
        kernel: forward-dynamics kernel (:func:`jaxbody.backends.acceleration`); ``None`` for
            :func:`jaxbody.backends.default_kernel` (``"auto"`` unless ``$JAXBODY_KERNEL`` says
            otherwise). :attr:`runs` names the one that runs.
    """

    kernel: str | None = eqx.field(static=True, default=None)

    @property
    def path(self) -> str:
        return "spatial"

    def is_direct(self) -> bool:
        """Whether the vector field can run :func:`jaxbody.backends.acceleration` directly.

        True without constraints when every effect is a uniform gravity field or a joint-space
        force (springs, dampers, actuation, a Fourier-series torque): those need no kinematics of their own, gravity
        enters the kernel as the ground's acceleration, and nothing is computed twice. Body
        loads, support motion, constraints and effects of unknown kind go through the shared
        kinematics of :meth:`context`.
        """
        return self.constraints is None and all(
            isinstance(e, (Gravity, JointSprings, JointDampers, Actuation, FourierTorque)) for e in self.effects
        )

    @property
    def runs(self) -> str:
        # a field that is not direct runs the vectorised kinematics and mass matrix of the scene
        return self.direct_kernel() or "vectorised"

    def direct_kernel(self) -> str | None:
        if not self.is_direct():
            return None
        return resolve_kernel(self.system, self.kernel)

    # ------------------------------------------------------------------ kinematics
    def context(self, t, q, v) -> EffectContext:
        return EffectContext(self, t, q, v, kinematics=compute_data(self.system, q, v))

    def uniform_field_force(self, ctx: EffectContext, field):
        return uniform_field_force(self.system, ctx.kinematics, jnp.asarray(field, ctx.v.dtype))

    def uniform_field_potential(self, ctx: EffectContext, field):
        field = jnp.asarray(field, ctx.q.dtype)
        return -jnp.sum(self.system.body_mass * (ctx.kinematics.com @ field))

    def body_wrench_force(self, ctx: EffectContext, wrenches):
        return body_wrench_force(self.system, ctx.kinematics, wrenches)

    # ------------------------------------------------------------------ protocol
    @compiled_when_eager
    def evaluate(self, t, q, v, tau=None):
        # the mass matrix, the velocity terms and every constraint row ask for the frames of the
        # same q: one computation of them in the traced evaluation
        with shared_evaluations():
            return self._evaluate(t, q, v, tau)

    def _evaluate(self, t, q, v, tau):
        if self.is_direct():
            return self._evaluate_direct(t, q, v, tau)
        ctx = self.context(t, q, v)
        total, powers = self.effect_forces(ctx, tau)
        M = mass_matrix(self.system, ctx.kinematics)
        # gravity is one of the scene's effects and already in ``total``: the tree's own gravity
        # would count it twice
        bias = bias_forces(self.system, ctx.kinematics, gravity=False)
        if self.constraints is None:
            return solve_spd(M, total - bias), tuple(powers), None
        # the constraint set receives D = M and the force side, solves Maggi's reduced system and
        # returns Λ: one constrained path for every entry point
        a, reaction = self.constraints.accelerations(ctx, M, total - bias)
        return a, tuple(powers), reaction

    def _evaluate_direct(self, t, q, v, tau):
        # no kinematics here: the effects are joint-space forces (their context needs only the
        # state) and gravity goes to the kernel, which computes the kinematics it needs itself
        ctx = EffectContext(self, t, q, v)
        gravity = self.gravity_vector(v.dtype)
        total = None
        powers = []
        for e in self.effects:
            if isinstance(e, Gravity):
                continue
            f = e.generalized_force(ctx)
            total = f if total is None else total + f
            if not e.conservative:
                powers.append(jnp.dot(f, v))
        if tau is not None:
            total = tau if total is None else total + tau
            if "actuation" in self.work_names:
                i = self.work_names.index("actuation")
                # the run-time control input's power joins the actuation effect's work, so the energy
                # balance closes with the tau actually applied
                powers[i] = powers[i] + jnp.dot(tau, v)
        a = acceleration(self.system, q, v, total, gravity=gravity, kernel=self.kernel)
        return a, tuple(powers), None

    def _kernel_energies(self, q, v) -> tuple | None:
        """``(kinetic, potential)`` from the forward-dynamics kernel's own straight-line program
        (one native call per batch, or the unrolled scalar code), where the scene runs the
        native or unrolled kernel and its conservative effects are gravity and at most one set
        of joint springs; else ``None`` (the vectorised kinematics serve)."""
        kernel = resolve_kernel(self.system, self.kernel)
        conservative = [e for e in self.effects if e.conservative]
        springs = [e for e in conservative if isinstance(e, JointSprings)]
        # these straight-line energies cover gravity and at most one set of joint springs; any
        # other conservative effect needs the general kinematics
        if kernel not in ("native", "unrolled") or len(springs) > 1:
            return None
        if not all(isinstance(e, (Gravity, JointSprings)) for e in conservative):
            return None
        gravity = self.gravity_vector(v.dtype)
        if kernel == "native":
            spring = dict(stiffness=springs[0].stiffness, reference=springs[0].reference) if springs else {}
            kinetic, potential, elastic = native.energies(self.system, q, v, gravity=gravity, **spring)
            return kinetic, potential + elastic
        kinetic, potential = unrolled.energies(self.system, q, v, gravity=gravity)
        if springs:
            potential = potential + springs[0].potential_energy(EffectContext(self, jnp.zeros((), v.dtype), q, v))
        return kinetic, potential

    @compiled_when_eager
    def kinetic_energy(self, q, v) -> Float[Array, ""]:
        fast = self._kernel_energies(q, v)
        if fast is not None:
            return fast[0]
        return kinetic_energy(self.system, compute_data(self.system, q, v))

    @compiled_when_eager
    @shared_evaluations()  # the kinetic and the potential energy from one computation of the frames
    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        # the energies of a straight-line kernel come from the same program as its dynamics,
        # so a batch of them is one native call instead of the vectorised kinematics
        fast = self._kernel_energies(q, v)
        if fast is not None:
            return fast[0] + fast[1]
        return self.kinetic_energy(q, v) + self.potential_energy(q)
