"""Ready constraints on any spatial :class:`jaxbody.Model` (the second Maggi layer).

Each class is a :class:`jaxbody.maggi.Constraint` on the model's joint velocities ``v``
(quasi-velocities of the :class:`jaxbody.maggi.ModelBase`): rows ``f*(t, q, v) = 0``
linear in ``v``, and for holonomic ones the position residual ``φ(t, q)`` with
``dφ/dt = f*``. The reactions ``Λ`` that :meth:`jaxbody.maggi.ConstrainedSystem.solve`
returns for them are forces in newtons (point constraints: the force that the constraint
exerts on the constrained point along each constrained direction) or, for prescribed
coordinates, the generalized force on that coordinate.

| class | rows | holonomic | reaction |
|---|---|---|---|
| :class:`PointOnPlane` | 1 | yes | force along the plane normal |
| :class:`PointOnLine` | 2 | yes | force across the line (two normals) |
| :class:`LoopClosure` | 1–3 | yes | force on the point of body ``a`` along each axis |
| :class:`PlaneContact` | 1 | yes | normal force of a wheel on a plane |
| :class:`RollingContact` | 2 | no | friction force at the contact point |
| :class:`KnifeEdge` | 1 | no | lateral force on the edge |
| :class:`PrescribedCoordinate` | 1 | yes (in ``t``) | generalized force driving it |

Bodies are given by name or index (``-1`` = the world). Point coordinates are in the body
frame; directions of planes and lines are in the world frame.
"""

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, Float
from .joints import HINGE, SLIDE
from .kinematics import forward_kinematics, integrate_qpos, qpos_rate
from .loop_directions import (CLOSED_ATOL, close_loops, gap_and_jacobian, gap_jacobians, gap_velocity_bias, loop_frame,
                              loop_rows, point_gap, point_gap_velocity)
from .maggi.constrained import ConstrainedSystem
from .maggi.constraint import Constraint
from .maggi.projections import constrain

__all__ = [
    "PointOnPlane",
    "PointOnLine",
    "LoopClosure",
    "PlaneContact",
    "RollingContact",
    "rolling_wheel",
    "KnifeEdge",
    "PrescribedCoordinate",
    "body_point",
    "body_point_velocity",
    "body_angular_velocity",
    "connect_constraints",
    "loop_closures",
    "loop_system",
    "loop_reference",
]


def _model(base):
    # the model is read from the base at each call, not stored in the constraint: a scene that
    # rebinds the base to its own model is then the one evaluated and differentiated
    model = getattr(base, "model", None)
    if model is None:
        raise ValueError(
            f"these constraints act on a jaxbody.Model base system, got {type(base).__name__}"
        )
    return model


def _body(model, body) -> int:
    if isinstance(body, str):
        return model.body_index(body)
    body = int(body)
    # checked at build time: -1 means the world, and any other negative index would silently
    # pick a body counted from the end
    if not -1 <= body < model.n_body:
        raise ValueError(f"body index {body} out of range for a model with {model.n_body} bodies")
    return body


def _vec(v, n=3, what="vector"):
    v = jnp.asarray(v)
    # integer input such as (0, 0, 1) is promoted so that the field can carry gradients
    if not jnp.issubdtype(v.dtype, jnp.inexact):
        v = v.astype(jnp.result_type(float))
    if v.shape != (n,):
        raise ValueError(f"{what} must have shape ({n},), got {v.shape}")
    return v


def _unit(v, what):
    """A direction argument as a unit vector (shape checked, naming ``what``)."""
    v = _vec(v, what=what)
    return v / jnp.linalg.norm(v)


def _point_fields(model, body, point, origin, label, on):
    """``(body, point, origin, label)`` of a point constraint, checked (body name or index,
    3-vectors); the default label is ``point of '<body>' on <on>``."""
    body = _body(model, body)
    label = label or f"point of {model.body_names[body]!r} on {on}"
    return body, _vec(point, what="point"), _vec(origin, what="origin"), label


def _wheel_fields(model, body, radius, centre, axis, normal):
    """``(body, centre, axis, radius, normal)`` of a wheel constraint, checked (unit axis and
    normal, radius in the centre's dtype)."""
    centre = _vec(centre, what="centre")
    return _body(model, body), centre, _unit(axis, "axis"), jnp.asarray(radius, centre.dtype), _unit(normal, "normal")


def body_point(model, q, body: int, point) -> Float[Array, " 3"]:
    """World position of a point fixed in ``body`` (``-1``: the world, point as given)."""
    if body < 0:
        return jnp.asarray(point, q.dtype)
    kin = forward_kinematics(model, q)
    return kin.body_position[body] + kin.body_rotation[body] @ point


def body_point_velocity(model, q, v, body: int, point) -> Float[Array, " 3"]:
    """World velocity of a point fixed in ``body`` (``d/dt`` of :func:`body_point` along ``q̇ = qpos_rate(q, v)``)."""
    if body < 0:
        return jnp.zeros((3,), jnp.asarray(v).dtype)
    # v holds quasi-velocities (a ball joint's angular velocity, not quaternion rates): the
    # point's velocity is the derivative along q̇ = qpos_rate(q, v), so the rows are linear in v
    return jax.jvp(lambda qq: body_point(model, qq, body, point), (q,), (qpos_rate(model, q, v),))[1]


def body_angular_velocity(model, q, v, body: int) -> Float[Array, " 3"]:
    """World angular velocity of ``body`` (from ``Ṙ Rᵀ``)."""
    rot = lambda qq: forward_kinematics(model, qq).body_rotation[body]
    R, Rd = jax.jvp(rot, (q,), (qpos_rate(model, q, v),))
    return _angular_velocity(R, Rd)


class _OneRow(Constraint):
    """A constraint of one row, named by its ``label``."""

    @property
    def size(self):
        return 1

    @property
    def names(self):
        return (self.label,)


class _PointOffset(Constraint):
    """A body point's offset from ``origin`` vanishes along fixed world ``directions``
    (``φ = D·(p(q) − p₀)``, one row per direction): the shared form of the point constraints."""

    body: int = eqx.field(static=True)
    point: Array
    origin: Array
    directions: Array
    label: str = eqx.field(static=True)

    def __init__(self, model, body, point, directions, origin, label, on):
        self.body, self.point, self.origin, self.label = _point_fields(model, body, point, origin, label, on)
        # directions are array leaves, not static: a plane's normal or a line's direction can be
        # fitted like any other parameter
        self.directions = jnp.asarray(directions, self.point.dtype)

    @property
    def size(self):
        return int(self.directions.shape[0])

    def position(self, base, t, q):
        # fixed world directions, so dφ/dt = D·ṗ exactly: the velocity rows below are the time
        # derivative of these, as the Baumgarte term ω²φ + 2ωf* requires
        return self.directions @ (body_point(_model(base), q, self.body, self.point) - self.origin)

    def velocity(self, base, t, q, x):
        return self.directions @ body_point_velocity(_model(base), q, x, self.body, self.point)


class PointOnPlane(_PointOffset):
    """A body point stays on a plane: ``φ = n·(p(q) − p₀) = 0`` (unit ``n``, world frame)."""

    def __init__(self, model, body, point, normal, origin=(0.0, 0.0, 0.0), label=None):
        super().__init__(model, body, point, _unit(normal, "normal")[None], origin, label, "plane")

    @property
    def normal(self):
        """The plane's unit normal (world frame)."""
        return self.directions[0]

    @property
    def names(self):
        return (self.label,)


def _normals(direction):
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    # the world axis least aligned with d keeps the cross product far from zero
    a = np.eye(3)[np.argmin(np.abs(d))]
    n1 = np.cross(d, a)
    n1 /= np.linalg.norm(n1)
    # orthonormal and both orthogonal to d: two independent rows, never redundant
    return np.stack([n1, np.cross(d, n1)])


class PointOnLine(_PointOffset):
    """A body point stays on a line through ``origin`` along ``direction`` (world): two rows,
    the offsets along two unit normals of the line (the reaction is the force across it)."""

    def __init__(self, model, body, point, direction, origin=(0.0, 0.0, 0.0), label=None):
        super().__init__(model, body, point, _normals(_vec(direction, what="direction")), origin, label, "line")

    @property
    def normals(self):
        """Two unit normals of the line (world frame), one per row."""
        return self.directions

    @property
    def names(self):
        return (f"{self.label}[n1]", f"{self.label}[n2]")


class LoopClosure(Constraint):
    """Point-to-point loop closure: the gap ``R_fᵀ (p_a(q) − p_b(q))`` vanishes along ``axes``
    (unit vectors in the frame of body ``frame``; ``-1``, the default: world axes; default all
    three). Give only the independent directions (a planar loop: the two in-plane axes),
    otherwise the constraints are redundant; :func:`loop_closures` finds them. The reaction is
    the force on the point of body ``a`` along each axis (body ``b`` feels the opposite)."""

    body_a: int = eqx.field(static=True)
    body_b: int = eqx.field(static=True)
    point_a: Array
    point_b: Array
    axes: Array
    label: str = eqx.field(static=True)
    frame: int = eqx.field(static=True, default=-1)

    def __init__(self, model, body_a, point_a, body_b, point_b, axes=None, label=None, frame=-1):
        self.body_a, self.body_b = _body(model, body_a), _body(model, body_b)
        self.frame = _body(model, frame)
        self.point_a = _vec(point_a, what="point_a")
        self.point_b = _vec(point_b, what="point_b")
        ax = np.eye(3) if axes is None else np.asarray(axes, dtype=np.float64).reshape(-1, 3)
        # unit axes, so that each reaction is a force along its axis (a row scaled by k would
        # report its reaction divided by k)
        ax = ax / np.linalg.norm(ax, axis=1, keepdims=True)
        self.axes = jnp.asarray(ax, self.point_a.dtype)
        name = lambda b: "world" if b < 0 else model.body_names[b]
        self.label = label or f"loop {name(self.body_a)}-{name(self.body_b)}"

    @property
    def size(self):
        return int(self.axes.shape[0])

    @property
    def names(self):
        return tuple(f"{self.label}[{i}]" for i in range(self.size))

    # both points from one evaluation of the frames: a solve differentiates these several
    # times, and each evaluation is a copy of forward kinematics in the compiled program
    def position(self, base, t, q):
        return self.axes @ point_gap(_model(base), q, self.body_a, self.point_a, self.body_b, self.point_b, self.frame)

    def velocity(self, base, t, q, x):
        return self.axes @ point_gap_velocity(_model(base), q, x, self.body_a, self.point_a, self.body_b,
                                              self.point_b, self.frame)

    def velocity_jacobian(self, base, t, q, x):
        return self.axes @ gap_and_jacobian(_model(base), q, self.body_a, self.point_a, self.body_b, self.point_b,
                                            self.frame)[1]

    def velocity_bias(self, base, t, q, x):
        return self.axes @ gap_velocity_bias(_model(base), q, x, self.body_a, self.point_a, self.body_b,
                                             self.point_b, self.frame)


def _body_frame_rate(model, q, v, body: int):
    """``(R, x, Ṙ, ẋ)``: rotation and origin of ``body`` and their rates along
    ``q̇ = qpos_rate(q, v)``, from one (differentiated) evaluation of the frames."""
    def frame(qq):
        kin = forward_kinematics(model, qq)
        return kin.body_rotation[body], kin.body_position[body]

    (R, x), (Rd, xd) = jax.jvp(frame, (q,), (qpos_rate(model, q, v),))
    return R, x, Rd, xd


def _angular_velocity(R, Rd):
    """World angular velocity from a rotation and its rate (``Ṙ Rᵀ`` is its cross-product matrix)."""
    W = Rd @ R.T
    return jnp.stack([W[2, 1], W[0, 2], W[1, 0]])


def _unit_or_zero(u):
    """``u / |u|`` with a gradient-safe norm (zero stays zero)."""
    # the floor keeps value and gradient finite at u = 0, where the gradient of
    # jnp.linalg.norm is NaN (0/0)
    return u / jnp.sqrt(jnp.maximum(u @ u, jnp.finfo(u.dtype).tiny))


def _wheel_contact(model, q, body, centre, axis, radius, normal):
    """Contact point of a wheel (disk of ``radius`` about ``centre`` with symmetry ``axis``,
    body frame) with a plane of normal ``normal``: the lowest point of the rim."""
    kin = forward_kinematics(model, q)
    return _wheel_contact_in(kin.body_rotation[body], kin.body_position[body], centre, axis, radius, normal)


def _wheel_contact_in(R, x, centre, axis, radius, normal):
    """:func:`_wheel_contact` from the wheel body's rotation ``R`` and origin ``x``: ``(centre, contact)``."""
    c = x + R @ centre
    a = R @ axis
    # gradient-safe normalisation (a wheel lying flat has no single contact point)
    s = _unit_or_zero(normal - (normal @ a) * a)
    # s is the unit vector in the wheel's plane closest to the plane normal: the lowest point
    # of the rim lies one radius from the centre against it
    return c, c - radius * s


class PlaneContact(_OneRow):
    """Holonomic contact of a wheel with the plane ``n·X = height``: ``φ = n·D(q) − height``."""

    body: int = eqx.field(static=True)
    centre: Array
    axis: Array
    radius: Array
    normal: Array
    height: Array
    label: ClassVar[str] = "wheel on plane"

    def __init__(self, model, body, radius, centre=(0.0, 0.0, 0.0), axis=(0.0, 0.0, 1.0), normal=(0.0, 0.0, 1.0), height=0.0):
        self.body, self.centre, self.axis, self.radius, self.normal = _wheel_fields(model, body, radius, centre, axis, normal)
        self.height = jnp.asarray(height, self.centre.dtype)

    def position(self, base, t, q):
        _, d = _wheel_contact(_model(base), q, self.body, self.centre, self.axis, self.radius, self.normal)
        return (self.normal @ d - self.height)[None]

    def velocity(self, base, t, q, x):
        m = _model(base)
        # the exact time derivative of φ along q̇: f* = dφ/dt by construction, so the position
        # and velocity residuals of this row stay consistent under stabilisation
        return jax.jvp(lambda qq: self.position(base, t, qq), (q,), (qpos_rate(m, q, x),))[1]


class RollingContact(Constraint):
    """Rolling without slip of a wheel on a plane: the material point of the wheel at the
    contact has no velocity along the plane (two rows: along the wheel's heading
    ``t₁ = a × n / |a × n|`` and across it, ``t₂ = n × t₁``). The reactions are the friction
    force components along ``t₁`` and ``t₂``."""

    body: int = eqx.field(static=True)
    centre: Array
    axis: Array
    radius: Array
    normal: Array

    def __init__(self, model, body, radius, centre=(0.0, 0.0, 0.0), axis=(0.0, 0.0, 1.0), normal=(0.0, 0.0, 1.0)):
        self.body, self.centre, self.axis, self.radius, self.normal = _wheel_fields(model, body, radius, centre, axis, normal)

    @property
    def size(self):
        return 2

    @property
    def names(self):
        return ("rolling (heading)", "rolling (lateral)")

    def tangents(self, model, q):
        return self._tangents_in(forward_kinematics(model, q).body_rotation[self.body])

    def _tangents_in(self, R):
        # t₁ along the heading (axis × normal), t₂ across it; a wheel lying flat has no heading,
        # and the gradient-safe normalisation keeps that state finite
        t1 = _unit_or_zero(jnp.cross(R @ self.axis, self.normal))
        return jnp.stack([t1, jnp.cross(self.normal, t1)])

    def velocity(self, base, t, q, x):
        # the wheel's frame and its rate from one differentiated evaluation of the frames
        R, o, Rd, od = _body_frame_rate(_model(base), q, x, self.body)
        c, d = _wheel_contact_in(R, o, self.centre, self.axis, self.radius, self.normal)
        # the velocity of the material point at the contact (centre velocity plus ω × (d − c)):
        # the geometric contact point slides along the rim, so its own velocity is not constrained
        vc = od + Rd @ self.centre
        return self._tangents_in(R) @ (vc + jnp.cross(_angular_velocity(R, Rd), d - c))


def rolling_wheel(model, body, radius, centre=(0.0, 0.0, 0.0), axis=(0.0, 0.0, 1.0), normal=(0.0, 0.0, 1.0), height=0.0):
    """Both constraints of a wheel rolling on a plane: ``(PlaneContact, RollingContact)``
    (contact kept, no slip); the reactions are the normal force and the two friction components."""
    return (
        PlaneContact(model, body, radius, centre, axis, normal, height),
        RollingContact(model, body, radius, centre, axis, normal),
    )


class KnifeEdge(_OneRow):
    """A knife edge (skate): the point ``point`` of ``body`` has no velocity across the edge
    direction ``edge`` (body frame) within the plane of normal ``normal``:
    ``v_p · (n × e)/|n × e| = 0``. The reaction is the lateral force on the edge."""

    body: int = eqx.field(static=True)
    point: Array
    edge: Array
    normal: Array
    label: ClassVar[str] = "knife edge"

    def __init__(self, model, body, point, edge, normal=(0.0, 0.0, 1.0)):
        self.body = _body(model, body)
        self.point = _vec(point, what="point")
        self.edge, self.normal = _unit(edge, "edge"), _unit(normal, "normal")

    def velocity(self, base, t, q, x):
        R, _, Rd, od = _body_frame_rate(_model(base), q, x, self.body)
        # only the in-plane direction across the edge is constrained: the skate moves freely along it
        lateral = _unit_or_zero(jnp.cross(self.normal, R @ self.edge))
        return (lateral @ (od + Rd @ self.point))[None]


class PrescribedCoordinate(_OneRow):
    """Prescribed relative motion of a hinge or slide joint: ``q_j = g(t)``.

    ``motion(t, params)`` returns the prescribed coordinate; its rate comes from automatic
    differentiation. The reaction is the generalized force (torque or force) the joint
    needs to follow the motion.
    """

    qpos: int = eqx.field(static=True)
    dof: int = eqx.field(static=True)
    motion: Callable = eqx.field(static=True)
    params: object
    label: str = eqx.field(static=True)

    def __init__(self, model, joint, motion, params=None):
        j = model.joint_index(joint) if isinstance(joint, str) else int(joint)
        if model.joints.type[j] not in (HINGE, SLIDE):
            raise ValueError(f"PrescribedCoordinate: joint {model.joint_names[j]!r} is not a hinge or slide")
        # a hinge or slide has one coordinate and one velocity with v_j = q̇_j, so φ = q_j − g(t)
        # and f* = v_j − ġ(t) match (a ball joint's quaternion would not)
        self.qpos, self.dof = model.joints.qposadr[j], model.joints.dofadr[j]
        self.motion, self.params = motion, params
        self.label = f"prescribed {model.joint_names[j]!r}"

    def position(self, base, t, q):
        return (q[self.qpos] - self.motion(t, self.params))[None]

    def velocity(self, base, t, q, x):
        t = jnp.asarray(t, jnp.asarray(x).dtype)
        # ġ by forward-mode differentiation of the user's motion: f* stays affine in v, with the
        # prescribed rate as its affine part
        rate = jax.jvp(lambda tt: self.motion(tt, self.params), (t,), (jnp.ones_like(t),))[1]
        return (x[self.dof] - rate)[None]


def _frame_name(model, f: int) -> str:
    return "the world" if f < 0 else f"body {model.body_names[f]!r}"


def _traced(model) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(model))


def loop_reference(model, q=None, *, what: str | None = None) -> np.ndarray:
    """A configuration that closes every loop of ``model`` (``model.loops``), near ``q``
    (default ``model.qpos0``): ``q`` itself when it closes them, else its projection by
    :func:`jaxbody.loop_directions.close_loops` (Newton's method, minimum-norm steps, on the
    rotation group for quaternions). NumPy float64, shape ``(nq,)``.

    Raises:
        ValueError: the loops cannot be closed near ``q`` (naming the loops still open).
    """
    q = np.asarray(model.qpos0 if q is None else q, np.float64)
    if not model.loops:
        return q
    specs = _with_frames(model)
    dtype = model.body_pos.dtype
    # the kinematics run in the model's dtype: a float32 model closes its loops to its own rounding
    atol = max(CLOSED_ATOL, 100 * float(jnp.finfo(dtype).eps) * max(1.0, float(np.abs(np.asarray(model.body_pos)).max())))
    return close_loops(
        q, lambda qq: gap_jacobians(model, specs, jnp.asarray(qq, dtype))[:2],
        lambda qq, dv: integrate_qpos(model, jnp.asarray(qq, dtype), jnp.asarray(dv, dtype), 1.0),
        atol=atol, what=what or ("qpos0" if q is None else "the given configuration"), labels=[s.label for s in specs],
    )


def _with_frames(model):
    return [s._replace(frame=loop_frame(model.tree.parent, s.body_a, s.body_b) if s.frame is None else s.frame)
            for s in model.loops]


def loop_closures(model, *, axes="auto", q=None) -> tuple[LoopClosure, ...]:
    """The loop closures a model carries (``model.loops``, from MJCF ``<connect>``) as
    :class:`LoopClosure` constraints, in order and named after them.

    ``axes="auto"`` keeps, for each loop, only the directions in which the loop can open at
    all, in the frame of the lowest common ancestor of its two bodies
    (:mod:`jaxbody.loop_directions`): found at a configuration that closes the loops, by a
    singular-value decomposition of each loop's gap Jacobian there and a rank-revealing test
    across loops that drops rows repeating earlier ones. A loop of a planar linkage thus keeps
    its two in-plane rows (the row across the plane vanishes identically and would make the set
    redundant), even on a floating base; a spatial loop keeps all three. The directions stored
    on the model (``LoopSpec.axes``, found once by the MJCF importer at ``qpos0``) are used as
    they are, so scenes of a model whose parameters are traced (fitting, ``vmap`` over
    parameters) reuse them; ``q`` finds them anew at the configuration that closes the loops
    nearest to ``q`` (a keyframe). ``axes=None`` keeps all three world directions; an array
    ``(k, 3)`` gives world directions for every loop. This is what :func:`jaxbody.scene`
    applies by default (:func:`loop_system`).

    Raises:
        ValueError: the directions must be found and the model's parameters are traced, the
            loops cannot be closed near ``q``, or a loop constrains nothing.
    """
    auto = isinstance(axes, str) and axes == "auto"
    specs = list(model.loops)
    if auto and (q is not None or any(s.axes is None for s in specs)):
        if _traced(model):
            raise ValueError(
                f"loops {[s.label for s in specs]}: their constrained directions are found from a concrete model; "
                "give them (LoopSpec.axes, or loop_closures(model, axes=...)) when the model's parameters are traced"
            )
        specs = _with_frames(model)
        qc = loop_reference(model, q, what=None if q is None else "the given configuration")
        _, J, R = gap_jacobians(model, specs, jnp.asarray(qc, model.body_pos.dtype))
        rows = loop_rows(np.einsum("lji,ljn->lin", R, J), [s.label for s in specs],
                         [_frame_name(model, s.frame) for s in specs])
        specs = [s._replace(axes=tuple(map(tuple, a.tolist())), dropped=d)
                 for s, a, d in zip(specs, rows.axes, rows.dropped)]
    out = []
    for spec in specs:
        if auto and spec.axes is not None and len(spec.axes) == 0:
            continue  # every row repeats other loops' rows (LoopSpec.dropped says which)
        if auto:
            ax = spec.axes
            frame = spec.frame if spec.frame is not None else loop_frame(model.tree.parent, spec.body_a, spec.body_b)
        else:
            ax, frame = axes, -1
        out.append(LoopClosure(model, spec.body_a, spec.point_a, spec.body_b, spec.point_b, axes=ax,
                               label=spec.label, frame=frame))
    return tuple(out)


def loop_system(model, q_ref=None, **constrain_options) -> ConstrainedSystem:
    """The model's loops as a :class:`jaxbody.maggi.ConstrainedSystem` (what :func:`jaxbody.scene`
    imposes by default), checked and partitioned at a configuration that closes them: ``q_ref``
    (a keyframe) or ``model.qpos0``, projected onto the loops when it does not close them
    (:func:`loop_reference`). The rows are the stored ones (:func:`loop_closures`); when they
    are redundant at that configuration they are found anew there.

    Raises:
        ValueError: the loops cannot be closed near the reference, or are redundant or
            inconsistent there even with their directions found anew (naming the rows).
    """
    q = loop_reference(model, q_ref, what="qpos0" if q_ref is None else "the reference configuration")
    closures = loop_closures(model)
    try:
        return constrain(model, closures, q_ref=jnp.asarray(q, model.body_pos.dtype), **constrain_options)
    except ValueError:
        # the stored rows were chosen at qpos0; a singular reference needs its own
        closures = loop_closures(model, q=q)
        return constrain(model, closures, q_ref=jnp.asarray(q, model.body_pos.dtype), **constrain_options)


def connect_constraints(mj_model, model, *, axes=None, active_only: bool = True) -> tuple[LoopClosure, ...]:
    """Loop closures from the MJCF ``<equality><connect>`` constraints of a compiled model.

    :func:`jaxbody.from_mujoco` already stores the active ones in ``model.loops`` and scenes
    apply them (:func:`loop_closures`); this reads them again from the compiled model, for
    connects inactive at start (``active_only=False``) or a model built another way.

    MuJoCo's connect constraint keeps an anchor point of ``body1`` on a point of ``body2``
    (ball-joint loop closure). Each becomes a :class:`LoopClosure` (``body1`` = body ``a``,
    so the reaction is the force on ``body1``). Site-based connects are converted to their
    bodies' frames.

    Args:
        mj_model: the compiled ``mujoco.MjModel`` (as passed to :func:`jaxbody.from_mujoco`)
            or an MJCF path / XML string.
        model: the :class:`jaxbody.Model` imported from it.
        axes: world directions kept in every closure (a planar loop: the two in-plane axes;
            default all three).
        active_only: skip constraints that are inactive at start (``eq_active0 = 0``).

    Returns:
        A tuple of :class:`LoopClosure`, in MuJoCo's order.
    """
    import mujoco  # optional dependency, needed only to read MJCF

    # io sits above constraints (it turns files into models); this MJCF reader is the one
    # constraint builder that needs it, and io does not import constraints, so no cycle forms
    from .io.mujoco import compile_source, connect_loops

    m = mj_model
    if not isinstance(m, mujoco.MjModel):
        m = compile_source(m, "connect_constraints", "MJCF")
    return tuple(
        LoopClosure(model, s.body_a, s.point_a, s.body_b, s.point_b, axes=axes, label=s.label)
        for s in connect_loops(m, active_only=active_only)
    )
