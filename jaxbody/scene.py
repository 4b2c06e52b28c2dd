"""Scenes: a mechanism plus the effects it declares, and nothing else.

A :class:`Scene` is what :func:`jaxbody.simulate` integrates. It holds a system (a spatial
:class:`jaxbody.Model`, a planar system, or any object with the simulation protocol) and a
tuple of effect modules (:mod:`jaxbody.effects`); its vector field is

    q̇ = qdot(q, v),     M(q) a = Σ_effects f_e(t, q, v) − c(q, v)     (+ constraints)

where ``c`` holds only the velocity-product terms of the tree (Statement 1 with no gravity and
no loads): gravity, springs, dampers, actuation, loads and a moving support are effects, so an
undeclared one is absent from the traced program. Choices made once, when the scene is built:

* **path**: ``"planar"`` when every joint is a hinge (one per body, fixed base, no armature),
  all hinge axes are parallel and gravity lies in their plane — the dynamics then run on the
  absolute-angle equations of planar trees (a mass matrix of augmented-body constants rotated
  by the link angles) in place of the spatial tree; ``"spatial"`` otherwise;
  ``"system"`` for planar systems and other objects with the simulation protocol;
* **no quaternions**: ``q̇ = v`` without the per-kind quaternion kinematics when the model has
  no ball or free joint;
* effects whose parameters are all zero (the model's springs or dampers) are not declared.

Coordinates are always the system's own (for a :class:`Model`, MuJoCo's ``qpos``/``qvel``);
on the planar path the absolute angles are an internal change of variables.
"""

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Float
from .effects import (
    Actuation,
    BodyLoads,
    Effect,
    EffectContext,
    Gravity,
    JointDampers,
    JointSprings,
    SupportMotion,
)
from .joints import BALL, FREE, HINGE
from .linalg import solve_spd
from .model import Model

__all__ = ["Scene", "scene", "Phases", "Event"]


def _concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(xs))


# ----------------------------------------------------------------------------- spatial terms
# Gravity is an effect of the scene, so the tree's own bias is taken with gravity off; the
# kernels of jaxbody.kernels check nothing, so they are safe inside a vmapped solver loop.
def _spatial_mass_and_bias(model: Model, data, v):
    from .kernels import bias_forces, mass_matrix

    return mass_matrix(model, data), bias_forces(model, data, gravity=False)


def _planar_from_model(model: Model, gravity=None, tol: float = 1e-9):
    """The planar system of a model whose hinges are parallel, or ``None``.

    Body axes of the planar system coincide with the plane basis ``(e1, e2)`` at the reference
    configuration ``qpos0``, so the absolute angle of body ``k`` is
    ``θ_k = Σ_{j on the path to k} s_j (q_j − q0_j)`` with ``s_j = ±1`` the sense of hinge ``j``
    about the plane normal ``n``. Returns ``(system, plane (2, 3), signs, normal)``.
    """
    from . import planar
    from .kinematics import forward_kinematics

    joints = model.joints
    if model.n_body == 0 or model.n_joint != model.n_body:
        return None
    if any(int(k) != HINGE for k in joints.type) or list(joints.body) != list(range(model.n_body)):
        return None
    if not _concrete(model):
        return None
    if np.any(np.asarray(model.dof_armature) != 0):
        return None
    # concrete model: evaluate now even when the scene is built inside a jit trace
    with jax.ensure_compile_time_eval():
        return _planar_conversion(model, gravity, tol)


def _planar_conversion(model, gravity, tol):
    """:func:`jaxbody.planar.from_model` of the same mechanism with every hinge turned to
    point along the plane normal ``n`` (``s_j`` records the turn), without its springs and
    dampers (they are effects of the scene) and without gravity (an effect too)."""
    from . import planar
    from .kinematics import forward_kinematics

    kin = forward_kinematics(model, model.qpos0)
    axes = np.asarray(kin.dof_angular)
    axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    n = axes[0]
    if np.any(np.linalg.norm(np.cross(axes, n), axis=-1) > tol):
        return None
    signs = np.sign(axes @ n)
    if gravity is not None and not _concrete(gravity):
        return None
    g = np.zeros(3) if gravity is None else np.asarray(gravity, dtype=float)
    gn = np.linalg.norm(g)
    if gn > 0 and abs(g @ n) > tol * gn:
        return None
    dtype = model.body_pos.dtype
    aligned = eqx.tree_at(
        lambda m: (m.joint_axis, m.dof_damping, m.joint_stiffness, m.gravity),
        model,
        (
            model.joint_axis * jnp.asarray(signs, dtype)[:, None],
            jnp.zeros_like(model.dof_damping),
            jnp.zeros_like(model.joint_stiffness),
            jnp.asarray(g, dtype),
        ),
    )
    try:
        converted = planar.from_model(aligned, atol=tol)
    except ValueError:
        # not a valid planar system (e.g. bad parameters): the spatial path and the boundary
        # checks of simulate report what is wrong, in the model's own terms
        return None
    system = eqx.tree_at(lambda s: s.gravity, converted, jnp.zeros(2, dtype))
    plane = jnp.asarray(planar.plane_basis(n, g), dtype)
    return system, plane, tuple(float(s) for s in signs)


# ----------------------------------------------------------------------------- Scene
class Scene(eqx.Module):
    """A system plus the effects it declares (see the module docstring). Build it with :func:`scene`.

    Implements the simulation protocol (``nq``, ``nv``, ``qdot``, ``acceleration``,
    ``total_energy``) and :meth:`evaluate`, which also returns the power of each
    non-conservative effect and the constraint reaction.

    Attributes:
        system: the mechanism (:class:`jaxbody.Model`, planar system or protocol object).
        effects: declared effects, in the order given.
        constraints: an object with the :class:`jaxbody.effects.Constraint` protocol (a
            :class:`jaxbody.maggi.ConstrainedSystem`), or ``None``. On the ``"system"`` path it
            is the system itself when that is a ``ConstrainedSystem``.
        planar: the absolute-angle system of the planar path (``None`` on other paths).
        plane: rows ``(e1, e2)`` of the plane of motion in world axes (planar path).
        axis_sign: sense ``±1`` of each hinge about the plane normal (planar path).
        path: ``"spatial"``, ``"planar"`` or ``"system"``.
    """

    system: Any
    effects: tuple
    constraints: Any = None
    planar: Any = None
    plane: Float[Array, "2 3"] | None = None
    axis_sign: tuple[float, ...] = eqx.field(static=True, default=())
    path: str = eqx.field(static=True, default="system")
    kernel: str | None = eqx.field(static=True, default=None)

    # ------------------------------------------------------------------ structure
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
        if not isinstance(self.system, Model):
            return False
        return any(int(k) in (BALL, FREE) for k in self.system.joints.type)

    @property
    def effect_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects)

    @property
    def work_names(self) -> tuple[str, ...]:
        """Names of the non-conservative effects whose work the simulator integrates."""
        if self.path == "system":
            if hasattr(self.system, "power"):
                return ("power",)
            return tuple(e.name for e in self.effects if not e.conservative)
        return tuple(e.name for e in self.effects if not e.conservative)

    def __check_init__(self):
        if self.path not in ("spatial", "planar", "system"):
            raise ValueError(f"scene: unknown path {self.path!r}")

    # ------------------------------------------------------------------ kinematics
    def _signs(self, dtype):
        return jnp.asarray(self.axis_sign, dtype)

    def context(self, t, q, v) -> EffectContext:
        """Kinematics of one state, computed once for every effect."""
        if self.path == "spatial":
            from .data import compute_data

            return EffectContext(self, t, q, v, kinematics=compute_data(self.system, q, v))
        if self.path == "planar":
            tree = self.system.tree
            s = self._signs(q.dtype)
            theta = tree.path_sum(s * (q - self.system.qpos0))
            omega = tree.path_sum(s * v)
            return EffectContext(self, t, q, v, angles=(theta, omega))
        return EffectContext(self, t, q, v)

    def _to_joint(self, force_abs):
        """Forces conjugate to absolute angles → joint forces (``τ_j = s_j Σ_{S(j)} Q_k``)."""
        return self._signs(force_abs.dtype) * self.system.tree.subtree_sum(force_abs)

    def _uniform_field_force(self, ctx: EffectContext, field):
        """Generalized force of the uniform field ``field`` (acceleration, world) on all masses."""
        model = self.system
        field = jnp.asarray(field, ctx.v.dtype)
        if self.path == "planar":
            from . import planar

            g2 = self.plane @ field
            mbar = planar.augmented_bodies(self.planar, ctx.angles[0]).static_moment
            q_abs = mbar[:, 0] * g2[1] - mbar[:, 1] * g2[0]
            return self._to_joint(q_abs)
        kin = ctx.kinematics
        m = model.body_mass
        tree = model.tree
        m_sub = tree.subtree_sum(m)
        h_sub = tree.subtree_sum(m[:, None] * kin.com)
        b = np.asarray(model.joints.dof_body, dtype=np.int32)
        lever = h_sub[b] - m_sub[b][:, None] * kin.dof_anchor
        return m_sub[b] * (kin.dof_linear @ field) + jnp.sum(kin.dof_angular * jnp.cross(lever, field), axis=-1)

    def _uniform_field_potential(self, ctx: EffectContext, field):
        field = jnp.asarray(field, ctx.q.dtype)
        if self.path == "planar":
            from . import planar

            _, com = planar.body_positions(self.planar, ctx.angles[0])
            return -jnp.sum(self.planar.body_mass * (com @ (self.plane @ field)))
        return -jnp.sum(self.system.body_mass * (ctx.kinematics.com @ field))

    def _body_wrench_force(self, ctx: EffectContext, force, torque):
        """Generalized force of world forces/torques applied at the bodies' centres of mass."""
        if self.path != "spatial":
            raise ValueError("body loads need the spatial path")
        kin = ctx.kinematics
        tree = self.system.tree
        f_sub = tree.subtree_sum(force)
        m_sub = tree.subtree_sum(torque + jnp.cross(kin.com, force))
        b = np.asarray(self.system.joints.dof_body, dtype=np.int32)
        moment = m_sub[b] - jnp.cross(kin.dof_anchor, f_sub[b])
        return jnp.sum(kin.dof_linear * f_sub[b], axis=-1) + jnp.sum(kin.dof_angular * moment, axis=-1)

    # ------------------------------------------------------------------ protocol
    def qdot(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nq"]:
        """Coordinate rates; ``v`` itself when there are no quaternions."""
        if self.path == "system":
            return self.system.qdot(q, v)
        if not self.has_quaternions:
            return v
        from .kinematics import qpos_rate

        return qpos_rate(self.system, q, v)

    def evaluate(self, t, q, v, tau=None):
        """``(a, powers, reactions)``: accelerations, the power ``f_e·v`` of every effect named in
        :attr:`work_names`, and the constraint reactions ``Λ`` (one per constraint row, ``M a =
        f + GᵀΛ``; ``None`` without constraints).

        ``tau`` is an extra generalized force (counted in the actuation work when present).
        """
        if self._direct():
            return self._evaluate_direct(t, q, v, tau)
        ctx = self.context(t, q, v)
        forces = [e.generalized_force(ctx) for e in self.effects]
        if self.path == "system":
            total = None
            for f in forces + ([] if tau is None else [tau]):
                total = f if total is None else total + f
            if self.constraints is not None:  # a constrained system: reactions come with a
                r = self.system.solve(t, q, v, total, stabilise=True)
                a, reaction = r.xdot, r.reactions
            else:
                a, reaction = self.system.acceleration(t, q, v, total), None
            if hasattr(self.system, "power"):
                powers = (self.system.power(t, q, v, total),)
            else:
                powers = tuple(jnp.dot(f, v) for e, f in zip(self.effects, forces) if not e.conservative)
            return a, powers, reaction
        powers = [jnp.dot(f, v) for e, f in zip(self.effects, forces) if not e.conservative]
        if tau is not None and "actuation" in self.work_names:
            i = self.work_names.index("actuation")
            powers[i] = powers[i] + jnp.dot(tau, v)
        total = jnp.zeros_like(v)
        for f in forces:
            total = total + f
        if tau is not None:
            total = total + tau
        reaction = None
        if self.path == "planar":
            from . import planar

            theta, omega = ctx.angles
            rhs_abs = self._signs(v.dtype) * total
            rhs_abs = rhs_abs - self.system.tree.children_sum(rhs_abs)
            rhs_abs = rhs_abs - planar.bias_forces(self.planar, theta, omega)
            acc_abs = solve_spd(planar.mass_matrix(self.planar, theta), rhs_abs)
            par = np.asarray(self.system.tree.parent_array)
            acc_parent = jnp.where(jnp.asarray(par >= 0), acc_abs[np.maximum(par, 0)], 0.0)
            a = self._signs(v.dtype) * (acc_abs - acc_parent)
        else:
            M, bias = _spatial_mass_and_bias(self.system, ctx.kinematics, v)
            if self.constraints is None:
                a = solve_spd(M, total - bias)
            else:
                a, reaction = self.constraints.accelerations(ctx, M, total - bias)
        return a, tuple(powers), reaction

    def _direct(self) -> bool:
        """Whether the vector field can run :func:`jaxbody.kernels.acceleration` directly.

        True on the unconstrained spatial path when every effect is a uniform gravity field or
        a joint-space force (springs, dampers, actuation): those need no kinematics of their
        own, gravity enters the kernel as the ground's acceleration, and nothing is computed
        twice. Body loads, support motion, constraints and effects of unknown kind go through
        the shared kinematics of :meth:`context`.
        """
        return (
            self.path == "spatial"
            and self.constraints is None
            and all(isinstance(e, (Gravity, JointSprings, JointDampers, Actuation)) for e in self.effects)
        )

    def _gravity(self, dtype):
        """The sum of the declared uniform gravity fields (``None`` without any): the ground's
        acceleration the straight-line kernels take."""
        gravity = None
        for e in self.effects:
            if isinstance(e, Gravity):
                g = jnp.asarray(e.vector, dtype)
                gravity = g if gravity is None else gravity + g
        return gravity

    def _evaluate_direct(self, t, q, v, tau):
        from .backends import acceleration

        ctx = EffectContext(self, t, q, v)
        gravity = self._gravity(v.dtype)
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
                powers[i] = powers[i] + jnp.dot(tau, v)
        a = acceleration(self.system, q, v, total, gravity=gravity, kernel=self.kernel)
        return a, tuple(powers), None

    def acceleration(
        self, t, q: Float[Array, " nq"], v: Float[Array, " nv"], tau: Float[Array, " nv"] | None = None
    ) -> Float[Array, " nv"]:
        """Forward dynamics with every declared effect (plus an optional extra ``tau``)."""
        return self.evaluate(t, q, v, tau)[0]

    def _kernel_energies(self, q, v) -> tuple | None:
        """``(kinetic, potential)`` from the forward-dynamics kernel's own straight-line program
        (one native call per batch, or the unrolled scalar code), where the scene runs the
        native or unrolled kernel and its conservative effects are gravity and at most one set
        of joint springs; else ``None`` (the vectorised kinematics serve)."""
        if self.path != "spatial":
            return None
        from .backends import resolve_kernel

        kernel = resolve_kernel(self.system, self.kernel)
        conservative = [e for e in self.effects if e.conservative]
        springs = [e for e in conservative if isinstance(e, JointSprings)]
        if kernel not in ("native", "unrolled") or len(springs) > 1:
            return None
        if not all(isinstance(e, (Gravity, JointSprings)) for e in conservative):
            return None
        gravity = self._gravity(v.dtype)
        if kernel == "native":
            from .backends import native

            spring = dict(stiffness=springs[0].stiffness, reference=springs[0].reference) if springs else {}
            kinetic, potential, elastic = native.energies(self.system, q, v, gravity=gravity, **spring)
            return kinetic, potential + elastic
        from .backends import unrolled

        kinetic, potential = unrolled.energies(self.system, q, v, gravity=gravity)
        if springs:
            potential = potential + springs[0].potential_energy(EffectContext(self, jnp.zeros((), v.dtype), q, v))
        return kinetic, potential

    def kinetic_energy(self, q, v) -> Float[Array, ""]:
        fast = self._kernel_energies(q, v)
        if fast is not None:
            return fast[0]
        if self.path == "spatial":
            from .data import compute_data
            from .kernels import kinetic_energy

            return kinetic_energy(self.system, compute_data(self.system, q, v))
        if self.path == "planar":
            from . import planar

            theta, omega = self.context(0.0, q, v).angles
            return planar.kinetic_energy(self.planar, theta, omega)
        raise ValueError("kinetic_energy: this system has no separate kinetic energy")

    def potential_energy(self, q) -> Float[Array, ""]:
        """Sum of the potentials of the conservative effects."""
        ctx = self.context(jnp.zeros((), q.dtype), q, jnp.zeros((self.nv,), q.dtype))
        e = jnp.zeros((), q.dtype)
        for eff in self.effects:
            if eff.conservative:
                e = e + eff.potential_energy(ctx)
        return e

    @property
    def has_energy(self) -> bool:
        return self.path != "system" or hasattr(self.system, "total_energy")

    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        """Kinetic energy plus the potentials of the declared conservative effects."""
        if self.path == "system":
            return self.system.total_energy(q, v)
        fast = self._kernel_energies(q, v)
        if fast is not None:
            return fast[0] + fast[1]
        return self.kinetic_energy(q, v) + self.potential_energy(q)

    def constraint_drift(self, t, q, v):
        """``(position, velocity)`` residuals of the constraints at ``(t, q, v)`` (``None`` without)."""
        if self.constraints is None:
            return None
        return self.constraints.drift(self.context(jnp.asarray(t, v.dtype), q, v))

    def __repr__(self):
        return f"Scene({type(self.system).__name__}, path={self.path!r}, effects={list(self.effect_names)})"


def _model_flag(value, default):
    return default if isinstance(value, str) and value == "model" else value


def scene(
    system,
    *,
    gravity: bool | str | ArrayLike | None = "model",
    springs: bool | str | ArrayLike | JointSprings | None = "model",
    dampers: bool | str | ArrayLike | JointDampers | None = "model",
    actuation: Callable | Actuation | tuple | None = None,
    loads: Callable | BodyLoads | None = None,
    support: Callable | SupportMotion | None = None,
    constraints: Any = "model",
    effects: Sequence[Effect] = (),
    planar: bool | None = None,
    kernel: str | None = None,
) -> Scene:
    """Build a :class:`Scene`: ``system`` plus the effects declared here, nothing else.

    Args:
        system: a :class:`jaxbody.Model`, a planar system (``jb.planar``, ``jb.examples``) or
            any object with ``nq``, ``nv``, ``qdot``, ``acceleration``.
        gravity: ``"model"`` (the model's gravity; undeclared when it is zero), ``True`` (same),
            ``False``/``None`` (off), or a world vector ``(3,)``. Planar systems: ``"model"``/
            ``True`` keep theirs, ``False`` switches it off.
        springs: joint springs: ``"model"`` (declared when a stiffness is non-zero), ``False``
            (off), a stiffness array ``(n_joint,)`` (reference: the model's ``qpos_spring``) or
            a :class:`~jaxbody.effects.JointSprings`.
        dampers: joint dampers: ``"model"``, ``False``, a damping array ``(nv,)`` or a
            :class:`~jaxbody.effects.JointDampers`.
        actuation: generalized forces: a callable ``tau(t, q, v)`` (an ``equinox.Module`` for
            differentiable parameters, e.g. a :class:`~jaxbody.effects.ControlSignal`), a pair
            ``(tau, params)`` called as ``tau(t, q, v, params)``, or an
            :class:`~jaxbody.effects.Actuation`.
        loads: body loads ``wrench(t, q, v) -> (n_body, 6)`` (``xfrc_applied`` layout) or a
            :class:`~jaxbody.effects.BodyLoads`.
        support: prescribed support translation ``s(t) -> (3,)`` or a
            :class:`~jaxbody.effects.SupportMotion`; the state is then relative to the support.
        constraints: the Maggi layer: ``"model"`` (the model's loop closures, ``model.loops``
            from MJCF ``<connect>``, with their independent directions,
            :func:`jaxbody.constraints.loop_closures`; none when it has none), ``None``/``False``
            (none, loops left open), a :class:`jaxbody.maggi.ConstrainedSystem` built on this
            model (``jaxbody.maggi.constrain(model, [...], q_ref=...)``), or a sequence of
            :class:`jaxbody.maggi.Constraint` (e.g. from :mod:`jaxbody.constraints`), then
            built at ``q_ref = model.qpos0``; or any object with the
            :class:`~jaxbody.effects.Constraint` protocol. Given constraints replace the model's
            loops; keep both with ``[*jaxbody.constraints.loop_closures(model), ...]``. A
            ``ConstrainedSystem`` passed as ``system`` brings its own constraints.
        effects: further effect modules (contact, limits, ...), appended in order.
        planar: ``None`` chooses the planar absolute-angle path when the model allows it;
            ``False`` forces the spatial path; ``True`` requires the planar path.
        kernel: forward-dynamics kernel of the spatial path (:func:`jaxbody.kernels.acceleration`):
            ``None`` (:data:`jaxbody.kernels.DEFAULT_KERNEL`, the vectorised kernel unless
            ``$JAXBODY_KERNEL`` says otherwise), ``"auto"`` (the native kernel where it can be
            built, :func:`jaxbody.kernels.resolve_kernel`), ``"native"``, ``"unrolled"`` or
            ``"vectorised"``. docs/performance.md says when each is faster.

    Returns:
        The scene.

    Raises:
        ValueError: an effect the system cannot take, a wrong shape (naming the argument), or
            ``planar=True`` on a model that is not planar.
    """
    if isinstance(system, Scene):
        raise ValueError("scene: system is already a Scene")
    from .backends import KERNELS

    if kernel is not None and kernel not in KERNELS:
        raise ValueError(f"scene: kernel must be one of {KERNELS}, got {kernel!r}")
    declared: list[Effect] = []
    if not isinstance(system, Model):
        for name, val in (("springs", springs), ("dampers", dampers), ("loads", loads), ("support", support), ("constraints", constraints)):
            if val is not None and val is not False and not (isinstance(val, str) and val == "model"):
                raise ValueError(
                    f"scene: {name} needs a spatial jaxbody.Model; {type(system).__name__} takes gravity and actuation only"
                )
        if gravity is False or gravity is None:
            if not hasattr(system, "gravity"):
                raise ValueError(f"scene: gravity cannot be switched off on {type(system).__name__}")
            system = eqx.tree_at(lambda s: s.gravity, system, jnp.zeros_like(system.gravity))
        elif not (gravity is True or (isinstance(gravity, str) and gravity == "model")):
            raise ValueError("scene: a gravity vector needs a spatial jaxbody.Model; pass True or False")
        if actuation is not None:
            declared.append(_actuation(actuation))
        declared.extend(effects)
        out = Scene(system=system, effects=tuple(declared), constraints=_own_constraints(system), path="system")
        for e in out.effects:
            e.check(out)
        return out

    model = system
    dtype = model.body_pos.dtype
    if isinstance(constraints, str) and constraints == "model":
        from .constraints import loop_closures

        constraints = loop_closures(model) if model.loops else None
    constraints = _constraint_slot(model, constraints)
    # gravity
    if gravity is True or (isinstance(gravity, str) and gravity == "model"):
        if not _concrete(model.gravity) or np.any(np.asarray(model.gravity) != 0) or gravity is True:
            declared.append(Gravity(model.gravity))
    elif gravity is not None and gravity is not False:
        g = jnp.asarray(gravity, dtype)
        if g.shape != (3,):
            raise ValueError(f"scene: gravity must be a bool or a (3,) vector, got shape {g.shape}")
        declared.append(Gravity(g))
    # springs and dampers
    if isinstance(springs, JointSprings):
        declared.append(springs)
    elif isinstance(springs, str) and springs == "model":
        if not _concrete(model.joint_stiffness) or np.any(np.asarray(model.joint_stiffness) != 0):
            declared.append(JointSprings(model.joint_stiffness, model.qpos_spring))
    elif springs is True:
        declared.append(JointSprings(model.joint_stiffness, model.qpos_spring))
    elif springs is not None and springs is not False:
        declared.append(JointSprings(jnp.asarray(springs, dtype), model.qpos_spring))
    if isinstance(dampers, JointDampers):
        declared.append(dampers)
    elif isinstance(dampers, str) and dampers == "model":
        if not _concrete(model.dof_damping) or np.any(np.asarray(model.dof_damping) != 0):
            declared.append(JointDampers(model.dof_damping))
    elif dampers is True:
        declared.append(JointDampers(model.dof_damping))
    elif dampers is not None and dampers is not False:
        declared.append(JointDampers(jnp.asarray(dampers, dtype)))
    if actuation is not None:
        declared.append(_actuation(actuation))
    if loads is not None:
        declared.append(loads if isinstance(loads, BodyLoads) else BodyLoads(loads))
    if support is not None:
        declared.append(support if isinstance(support, SupportMotion) else SupportMotion(support))
    declared.extend(effects)

    planar_ok = planar is not False and loads is None and constraints is None
    grav = [e.vector for e in declared if isinstance(e, Gravity)]
    converted = _planar_from_model(model, grav[0] if grav else None) if planar_ok else None
    if planar is True and converted is None:
        raise ValueError(
            "scene: planar=True needs hinge joints only (one per body, no armature), parallel axes, "
            "gravity in their plane, and no loads or constraints"
        )
    if converted is not None:
        psys, plane, signs = converted
        out = Scene(system=model, effects=tuple(declared), planar=psys, plane=plane, axis_sign=signs, path="planar")
    else:
        out = Scene(system=model, effects=tuple(declared), constraints=constraints, path="spatial", kernel=kernel)
    for e in out.effects:
        e.check(out)
    return out


def _own_constraints(system):
    """A :class:`jaxbody.maggi.ConstrainedSystem` is its own constraint slot (``"system"`` path)."""
    from .maggi import ConstrainedSystem

    return system if isinstance(system, ConstrainedSystem) else None


def _constraint_slot(model: Model, constraints):
    """Validate the ``constraints`` argument of :func:`scene` (a sequence of Maggi constraints
    is built into a ``ConstrainedSystem`` at ``model.qpos0``)."""
    from . import maggi

    if constraints is None or constraints is False:
        return None
    if isinstance(constraints, maggi.Constraint):
        constraints = (constraints,)
    if isinstance(constraints, (tuple, list)):
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(model)):
            raise ValueError(
                "scene: constraints are checked and their coordinate partition chosen when the scene is "
                "built, from concrete values; this model's parameters are traced (inside jit, vmap or grad). "
                "Build the scene outside and change its parameters inside with "
                "equinox.tree_at(lambda s: s.system.<field>, scene, value)"
            )
        try:
            constraints = maggi.constrain(model, constraints, q_ref=model.qpos0)
        except ValueError as err:
            raise ValueError(
                f"scene: constraints: {err} (they were checked at model.qpos0; pass "
                "jaxbody.maggi.constrain(model, [...], q_ref=<an admissible q>) instead)"
            ) from None
    missing = [n for n in ("accelerations", "drift") if not callable(getattr(constraints, n, None))]
    if missing:
        raise ValueError(
            f"scene: constraints must be a jaxbody.maggi.ConstrainedSystem, a sequence of "
            f"jaxbody.maggi.Constraint or an object with accelerations and drift; "
            f"{type(constraints).__name__} lacks {', '.join(missing)}"
        )
    if isinstance(constraints, maggi.ConstrainedSystem):
        if not isinstance(constraints.base, maggi.ModelBase):
            raise ValueError(
                f"scene: constraints are built on a {type(constraints.base).__name__}, not on a "
                "jaxbody.Model; simulate that ConstrainedSystem directly"
            )
        if (constraints.nq, constraints.nv) != (model.nq, model.nv):
            raise ValueError(
                f"scene: constraints are built on a model with (nq, nv) = ({constraints.nq}, "
                f"{constraints.nv}), the scene's has ({model.nq}, {model.nv})"
            )
    return constraints


def _actuation(actuation) -> Actuation:
    if isinstance(actuation, Actuation):
        return actuation
    if isinstance(actuation, tuple) and len(actuation) == 2 and callable(actuation[0]):
        return Actuation(actuation[0], actuation[1])
    if callable(actuation):
        return Actuation(actuation)
    raise ValueError(f"scene: actuation must be callable, a (callable, params) pair or an Actuation, got {type(actuation).__name__}")


# ----------------------------------------------------------------------------- events, phases
class Event(eqx.Module):
    """A condition ``g(t, q, v)`` whose zero crossing stops a solve (located by root finding).

    Attributes:
        condition: ``g(t, q, v) -> scalar`` (or a boolean, which triggers without root finding).
        direction: ``None`` (either way), ``True`` (upward crossing ``−→+``) or ``False`` (downward).
    """

    condition: Callable
    direction: bool | None = eqx.field(static=True, default=None)

    def __call__(self, t, q, v):
        return self.condition(t, q, v)


class Phases(eqx.Module):
    """An ordered list of scenes switched by events: phase ``i`` runs until ``events[i]``
    triggers, then phase ``i + 1`` starts from that state (mapped by ``transitions[i]``
    ``(t, q, v) -> (q, v)`` when given). The last phase runs to ``t1``.

    When the scene of phase ``i + 1`` has Maggi constraints (``jb.scene(model, constraints=...)``
    or a :class:`jaxbody.maggi.ConstrainedSystem`), the velocities entering it are projected onto
    them as an impulsive constraint in the kinetic metric, ``x⁺ = A(AᵀDA)⁻¹AᵀD·x⁻``
    (:func:`jaxbody.maggi.switch_constraints`); a looser constraint set keeps the velocity.
    ``jb.simulate(phases, q0, v0, t1)`` checks ``v0`` against the first phase's constraints
    and returns one :class:`jaxbody.Solution` for the whole run: the work of the
    non-conservative effects carried across the switches, the energy change at each switch in
    ``stats["switch_energy_jump"]`` and ``work["switches"]`` (so the energy balance closes),
    the energy lost by each projection in ``stats["switch_energy_lost"]``, the phase of each
    saved time in ``stats["phase"]``, and reactions and constraint residuals padded with NaN to
    the largest number of constraint rows over the phases.

    Attributes:
        scenes: the phases' scenes (same ``nq`` and ``nv``).
        events: ``len(scenes) − 1`` :class:`Event` (or callables ``g(t, q, v)``); ``events[i]``
            ends phase ``i``.
        transitions: optional maps ``(t, q, v) -> (q, v)`` applied at each switch, before the
            projection onto the next constraints.
    """

    scenes: tuple
    events: tuple
    transitions: tuple = ()

    def __check_init__(self):
        if len(self.scenes) < 1 or len(self.events) != len(self.scenes) - 1:
            raise ValueError(
                f"phases: need n scenes and n - 1 events, got {len(self.scenes)} scenes and {len(self.events)} events"
            )
        if self.transitions and len(self.transitions) != len(self.events):
            raise ValueError("phases: give one transition per event (or none)")
        shapes = {(s.nq, s.nv) for s in self.scenes}
        if len(shapes) != 1:
            raise ValueError(f"phases: every scene needs the same (nq, nv), got {sorted(shapes)}")

    @property
    def nq(self) -> int:
        return self.scenes[0].nq

    @property
    def nv(self) -> int:
        return self.scenes[0].nv
