"""The scene protocol: what :func:`jaxbody.simulate` asks of every scene, and what scenes share.

A scene is the adapter between a mechanism and the simulator: whatever its path (spatial tree,
planar absolute angles, or an object of the simulation protocol), it provides ``nq``, ``nv``,
``qdot``, ``acceleration``, ``total_energy`` and :meth:`Scene.evaluate`, so the simulator never
asks which path it runs on. :class:`Scene` is abstract; each path is one final class
(:class:`jaxbody.scene.SpatialScene`, :class:`jaxbody.scene.PlanarScene`,
:class:`jaxbody.scene.SystemScene`). Effects ask the scene for the generalized force of a
uniform field or of body wrenches (:meth:`Scene.uniform_field_force`,
:meth:`Scene.body_wrench_force`), which is how one effect serves every path.
"""

import abc
import dataclasses
from typing import Any

import equinox as eqx
import jax.numpy as jnp

from .._types import Array, Float
from .._util import compiled_when_eager
from ..effects import EffectContext, Gravity
from ..joints import BALL, FREE
from ..kinematics import qpos_rate
from ..model import Model
from .chart import CoordinateChart, chart_of

__all__ = ["Scene", "ModelScene"]


class Scene(eqx.Module):
    """A system plus the effects it declares (see :mod:`jaxbody.scene`). Build it with
    :func:`jaxbody.scene`; every scene is an instance of this class.

    Implements the simulation protocol (``nq``, ``nv``, ``qdot``, ``acceleration``,
    ``total_energy``) and :meth:`evaluate`, which also returns the power of each
    non-conservative effect and the constraint reaction.

    Attributes:
        system: the mechanism (:class:`jaxbody.Model`, planar system or protocol object).
        effects: declared effects, in the order given.
        constraints: an object with the :class:`jaxbody.effects.Constraint` protocol (a
            :class:`jaxbody.maggi.ConstrainedSystem`), or ``None``. On the ``"system"`` path it
            is the system itself when that is a ``ConstrainedSystem``.
        path: ``"spatial"``, ``"planar"`` or ``"system"`` (read-only: the scene's class).
    """

    system: Any
    # a tuple, not a list: the effects are part of the pytree structure, and equal scenes share
    # one compilation only if the structure is hashable and ordered
    effects: tuple
    constraints: Any = None

    # ------------------------------------------------------------------ structure
    @property
    @abc.abstractmethod
    def path(self) -> str:
        """``"spatial"``, ``"planar"`` or ``"system"``."""

    @property
    def model(self):
        """The system (alias used by effects)."""
        return self.system

    @property
    def nq(self) -> int:
        return self.system.nq

    @property
    def nv(self) -> int:
        return self.system.nv

    @property
    def has_quaternions(self) -> bool:
        """Ball or free joints present (their quaternions are kept on the unit sphere)."""
        # a protocol system integrates its own coordinates: the scene keeps nothing on a sphere
        if not isinstance(self.system, Model):
            return False
        # decided from the joint kinds (static), so a hinge-only model traces no projection
        return any(int(k) in (BALL, FREE) for k in self.system.joints.type)

    @property
    def effect_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects)

    @property
    @abc.abstractmethod
    def work_names(self) -> tuple[str, ...]:
        """Names of the non-conservative effects whose work the simulator integrates."""

    @property
    @abc.abstractmethod
    def has_energy(self) -> bool:
        """Whether the scene has an energy function (:meth:`total_energy`)."""

    def gravity_vector(self, dtype) -> Float[Array, " 3"] | None:
        """The sum of the declared uniform gravity fields (``None`` without any): the ground's
        acceleration the straight-line kernels take."""
        # several Gravity effects add up (a field and a tilt correction, say): the kernels take one
        gravity = None
        for e in self.effects:
            if isinstance(e, Gravity):
                g = jnp.asarray(e.vector, dtype)
                gravity = g if gravity is None else gravity + g
        return gravity

    @abc.abstractmethod
    def is_direct(self) -> bool:
        """Whether the vector field runs :func:`jaxbody.backends.acceleration` directly, with no
        kinematics of the scene's own (see :meth:`jaxbody.scene.SpatialScene.is_direct`)."""

    @abc.abstractmethod
    def direct_kernel(self) -> str | None:
        """The forward-dynamics kernel a direct vector field runs (``"native"``, ``"unrolled"`` or
        ``"vectorised"``, resolved for the model), or ``None`` when the field is not direct."""

    @abc.abstractmethod
    def with_constraints(self, constraints) -> "Scene":
        """The scene with its constraint system replaced (e.g. re-partitioned at a switch)."""

    # ------------------------------------------------------------------ per-state terms
    @abc.abstractmethod
    def context(self, t, q, v) -> EffectContext:
        """Kinematics of one state, computed once for every effect."""

    @abc.abstractmethod
    def uniform_field_force(self, ctx: EffectContext, field) -> Float[Array, " nv"]:
        """Generalized force of the uniform field ``field`` (an acceleration, world axes) on all masses."""

    @abc.abstractmethod
    def uniform_field_potential(self, ctx: EffectContext, field) -> Float[Array, ""]:
        """Potential ``−Σ m_k field·C_k`` of the uniform field ``field``."""

    @abc.abstractmethod
    def body_wrench_force(self, ctx: EffectContext, wrenches: Float[Array, "n_body 6"]) -> Float[Array, " nv"]:
        """Generalized force of world forces/torques applied at the bodies' centres of mass
        (``wrenches``: force then torque per body, MuJoCo's ``xfrc_applied`` layout)."""

    # ------------------------------------------------------------------ protocol
    @abc.abstractmethod
    def qdot(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nq"]:
        """Coordinate rates."""

    @abc.abstractmethod
    def evaluate(self, t, q, v, tau=None):
        """``(a, powers, reactions)``: accelerations, the power ``f_e·v`` of every effect named in
        :attr:`work_names`, and the constraint reactions ``Λ`` (one per constraint row, ``M a =
        f + GᵀΛ``; ``None`` without constraints).

        ``tau`` is an extra generalized force (counted in the actuation work when present).
        """

    @compiled_when_eager
    def acceleration(
        self, t, q: Float[Array, " nq"], v: Float[Array, " nv"], tau: Float[Array, " nv"] | None = None
    ) -> Float[Array, " nv"]:
        """Forward dynamics with every declared effect (plus an optional extra ``tau``)."""
        return self.evaluate(t, q, v, tau)[0]

    @abc.abstractmethod
    def kinetic_energy(self, q, v) -> Float[Array, ""]:
        """Kinetic energy of the state."""

    @compiled_when_eager
    def potential_energy(self, q) -> Float[Array, ""]:
        """Sum of the potentials of the conservative effects."""
        # potentials depend on q alone: the context is built at rest and t = 0
        ctx = self.context(jnp.zeros((), q.dtype), q, jnp.zeros((self.nv,), q.dtype))
        e = jnp.zeros((), q.dtype)
        for eff in self.effects:
            if eff.conservative:
                e = e + eff.potential_energy(ctx)
        return e

    @abc.abstractmethod
    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        """Kinetic energy plus the potentials of the declared conservative effects."""

    @compiled_when_eager
    def constraint_drift(self, t, q, v):
        """``(position, velocity)`` residuals of the constraints at ``(t, q, v)`` (``None`` without)."""
        if self.constraints is None:
            return None
        # the constraints see the same context as the vector field (rheonomic rows need t)
        return self.constraints.drift(self.context(jnp.asarray(t, v.dtype), q, v))

    def coordinate_chart(self) -> CoordinateChart | None:
        """The chart the system declares (``coordinate_chart()``, optional in the protocol):
        where its coordinates are regular. The step guard of :func:`jaxbody.simulate` stops a
        solve that leaves it; ``None`` for coordinates that are regular everywhere."""
        return chart_of(self.system)

    @property
    def runs(self) -> str:
        """What computes the vector field: the kernel's name on the spatial path (``"native"``,
        ``"unrolled"``, ``"vectorised"``), ``"jax"`` for the planar path's and protocol
        systems' own JAX code."""
        return "jax"

    def __repr__(self):
        return (f"Scene({type(self.system).__name__}, path={self.path!r}, kernel={self.runs!r}, "
                f"effects={list(self.effect_names)})")


class ModelScene(Scene):
    """What the scenes of a :class:`jaxbody.Model` share (spatial and planar path): the model's
    coordinates, and a right-hand side that is the sum of the effects' forces.

    Abstract; the final classes are :class:`jaxbody.scene.SpatialScene` and
    :class:`jaxbody.scene.PlanarScene`.
    """

    @property
    def work_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects if not e.conservative)

    @property
    def has_energy(self) -> bool:
        return True

    def with_constraints(self, constraints) -> "ModelScene":
        return dataclasses.replace(self, constraints=constraints)

    @compiled_when_eager
    def qdot(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nq"]:
        """Coordinate rates; ``v`` itself when there are no quaternions."""
        # hinge and slide coordinates are their own rates: the quaternion kinematics (and its
        # equations in the traced program) are left out unless a ball or free joint needs them
        if not self.has_quaternions:
            return v
        return qpos_rate(self.system, q, v)

    def effect_forces(self, ctx: EffectContext, tau) -> tuple[Float[Array, " nv"], list]:
        """``(f, powers)``: the sum ``f`` of every effect's generalized force plus ``tau``, and the
        power of each non-conservative effect (the actuation's includes ``tau·v``)."""
        # the powers come in the order of work_names, which is how the simulator's work vector
        # is laid out; an extra tau is booked as actuation work when the scene has actuation
        v = ctx.v
        forces = [e.generalized_force(ctx) for e in self.effects]
        powers = [jnp.dot(f, v) for e, f in zip(self.effects, forces) if not e.conservative]
        if tau is not None and "actuation" in self.work_names:
            i = self.work_names.index("actuation")
            powers[i] = powers[i] + jnp.dot(tau, v)
        total = jnp.zeros_like(v)
        for f in forces:
            total = total + f
        if tau is not None:
            total = total + tau
        return total, powers
