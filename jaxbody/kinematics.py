"""Kinematics of a :class:`~jaxbody.model.Model`: frames, base points, DoF motions, velocities.

Frames are composed from the root down by pointer jumping over the static frame tree of
:class:`~jaxbody.joints.JointLayout` (one node for each body's fixed offset, one per joint),
so the trace does not grow with the number of bodies. MuJoCo's conventions are reproduced
exactly (``mj_kinematics``): hinge and slide joints act relative to ``qpos0``, the joint
anchor is fixed in the frame that precedes the joint, a ball or free joint's angular
velocity is expressed in the body frame.

Points attached to each body ``k`` (docs/mathematics.md, "Points and kinematic quantities"):

* base point ``O_0k`` — fixed in the parent: the anchor of the body's first joint (MuJoCo
  ``xanchor``); for a body without joints its origin; for a free body its origin, treated as
  the origin of a translating carrier frame (spec Cor. 1);
* pole ``O_k`` — fixed in body ``k``, coinciding with ``O_0k`` in the reference pose of the
  body's own joints. ``rho_k = O_k - O_0k`` is non-zero only for sliding or off-centre
  relative motion.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Float
from ._util import check_shape, index, quat_multiply, quat_to_matrix, skew
from .joints import BALL, FREE, HINGE, SLIDE
from .model import Model
from .shared_evaluation import shared

__all__ = [
    "Kinematics",
    "BodyMotion",
    "quat_to_matrix",
    "quat_multiply",
    "axis_angle_matrix",
    "forward_kinematics",
    "dof_motion_at",
    "body_velocities",
    "reference_point",
    "dof_motion_plucker",
    "body_accelerations",
    "point_velocity",
    "point_acceleration",
    "rigid_body_kinetic_energy",
    "qpos_rate",
    "integrate_qpos",
    "normalize_qpos",
]


def cross(a, b):
    return jnp.cross(a, b)


def axis_angle_matrix(axis: Float[ArrayLike, "*b 3"], angle: Float[ArrayLike, "*b"]) -> Float[Array, "*b 3 3"]:
    """Rodrigues' rotation about a unit ``axis`` by ``angle``."""
    c, s = jnp.cos(angle)[..., None, None], jnp.sin(angle)[..., None, None]
    k = skew(axis)
    eye = jnp.eye(3, dtype=axis.dtype)
    return eye + s * k + (1 - c) * (k @ k)


class Kinematics(eqx.Module):
    """Positions and orientations at one configuration (all world frame).

    Attributes:
        body_rotation: rotation matrix of each body frame.
        body_position: origin of each body frame (MuJoCo ``xpos``).
        base_point: ``O_0k`` (see module docstring).
        pole: ``O_k``.
        com: centre of mass ``C_k`` (MuJoCo ``xipos``).
        central_inertia: ``I_Ck`` about the CM in world axes.
        dof_angular, dof_linear, dof_anchor: DoF ``d`` moves its body with angular velocity
            ``dof_angular[d]`` and gives the point ``X`` the velocity
            ``dof_linear[d] + dof_angular[d] × (X - dof_anchor[d])`` per unit rate.
    """

    body_rotation: Float[Array, "n_body 3 3"]
    body_position: Float[Array, "n_body 3"]
    base_point: Float[Array, "n_body 3"]
    pole: Float[Array, "n_body 3"]
    com: Float[Array, "n_body 3"]
    central_inertia: Float[Array, "n_body 3 3"]
    dof_angular: Float[Array, "nv 3"]
    dof_linear: Float[Array, "nv 3"]
    dof_anchor: Float[Array, "nv 3"]


def _local_frames(model: Model, q):
    """Local rotation/translation of every frame-tree node (offset nodes and joint nodes)."""
    joints = model.joints
    dtype = model.body_pos.dtype
    n_node = joints.frame_tree.n_body
    R = jnp.zeros((n_node, 3, 3), dtype)
    t = jnp.zeros((n_node, 3), dtype)
    free_body = np.asarray(joints.body_is_free, dtype=bool)
    off = index(joints.body_offset_node)
    # a free body's pose is all in q: MuJoCo ignores body_pos/body_quat there
    Roff = quat_to_matrix(model.body_quat)
    Roff = jnp.where(free_body[:, None, None], jnp.eye(3, dtype=dtype), Roff)
    toff = jnp.where(free_body[:, None], 0.0, model.body_pos)
    R = R.at[off].set(Roff)
    t = t.at[off].set(toff)
    jnode = np.asarray(joints.joint_node, dtype=np.int64)
    for kind, js, a, _ in joints.kind_groups():
        p = model.joint_pos[js]
        if kind.code == HINGE:
            # hinge and slide act relative to qpos0, as MuJoCo's mj_kinematics
            Rj = axis_angle_matrix(model.joint_axis[js], q[a] - model.qpos0[a])
            tj = p - jnp.einsum("nij,nj->ni", Rj, p)
        elif kind.code == SLIDE:
            Rj = jnp.broadcast_to(jnp.eye(3, dtype=dtype), (js.size, 3, 3))
            tj = model.joint_axis[js] * (q[a] - model.qpos0[a])[:, None]
        elif kind.code == BALL:
            Rj = quat_to_matrix(q[a[:, None] + kind.quaternion + np.arange(4)])
            tj = p - jnp.einsum("nij,nj->ni", Rj, p)
        else:
            Rj = quat_to_matrix(q[a[:, None] + kind.quaternion + np.arange(4)])
            tj = q[a[:, None] + np.arange(3)]
        R = R.at[jnode[js]].set(Rj)
        t = t.at[jnode[js]].set(tj)
    return R, t


def _compose(outer, inner):
    Ro, to = outer
    Ri, ti = inner
    return Ro @ Ri, jnp.einsum("nij,nj->ni", Ro, ti) + to


@shared
def forward_kinematics(model: Model, q: Float[ArrayLike, " nq"]) -> Kinematics:
    """World frames, base points, poles, CMs and DoF motions at configuration ``q``.

    Follows MuJoCo's ``mj_kinematics`` and ``mj_comPos`` conventions (DESIGN.md).

    The frames are traced once per model structure and shape of ``q`` and reused (a nested
    ``jit``): constraint residuals, their Jacobians and rates call this again and again, and
    re-tracing it each time was most of the trace of a constrained simulation. XLA inlines the
    call, so the compiled program is unchanged. Within
    :func:`jaxbody.shared_evaluation.shared_evaluations` (a vector field's body), a second call
    with the same ``model`` and ``q`` objects returns the first call's frames.
    """
    q = check_shape(q, (model.nq,), "q", dtype=model.body_pos.dtype)
    return _forward_kinematics(model, q)


@eqx.filter_jit
def _forward_kinematics(model: Model, q: Float[Array, " nq"]) -> Kinematics:
    joints = model.joints
    R_loc, t_loc = _local_frames(model, q)
    R_w, t_w = joints.frame_tree.accumulate_from_root((R_loc, t_loc), _compose)
    last = index(joints.body_last_node)
    body_R, body_x = R_w[last], t_w[last]
    com = body_x + jnp.einsum("nij,nj->ni", body_R, model.body_com)
    I_c = body_R @ model.body_inertia @ jnp.swapaxes(body_R, -1, -2)

    nj = model.n_joint
    dtype = body_x.dtype
    if nj:
        pre = index(joints.joint_pre_node)
        jbody = index(joints.body)
        types = np.asarray(joints.type)
        is_free = types == FREE
        anchor = jnp.einsum("nij,nj->ni", R_w[pre], model.joint_pos) + t_w[pre]
        # a free joint turns about the body origin (MuJoCo), not about joint_pos
        anchor = jnp.where(is_free[:, None], body_x[jbody], anchor)
        axis = jnp.einsum("nij,nj->ni", R_w[pre], model.joint_axis)
    else:
        anchor = jnp.zeros((0, 3), dtype)
        axis = jnp.zeros((0, 3), dtype)

    # DoF motions: (angular part, pure linear part, anchor point)
    dof_joint = index(joints.dof_joint)
    dof_body = index(joints.dof_body)
    comp = np.asarray(joints.dof_component)
    rot = np.asarray(joints.dof_is_rotation, dtype=bool)
    dtypes = np.asarray(joints.type)[dof_joint] if joints.nv else np.zeros(0, int)
    nv = joints.nv
    if nv:
        # Ball and free-rotation rates are angular velocities in *body* axes (MuJoCo qvel), so
        # their unit motions are the body's axes in world (columns of R_body); free translation
        # rates are world-frame velocities, so those motions are the world unit vectors.
        body_cols = jnp.swapaxes(body_R, -1, -2)[dof_body, comp]  # column `comp` of R_body
        unit = jnp.eye(3, dtype=dtype)[comp]
        jaxis = axis[dof_joint]
        ang = jnp.where((dtypes == HINGE)[:, None], jaxis, 0.0)
        ang = jnp.where(((dtypes == BALL) | ((dtypes == FREE) & rot))[:, None], body_cols, ang)
        lin = jnp.where((dtypes == SLIDE)[:, None], jaxis, 0.0)
        lin = jnp.where(((dtypes == FREE) & ~rot)[:, None], unit, lin)
        dof_anchor = anchor[dof_joint]
    else:
        ang = lin = dof_anchor = jnp.zeros((0, 3), dtype)

    # base points and poles
    first = np.asarray(joints.body_first_joint)
    has_joint = first >= 0
    free_body = np.asarray(joints.body_is_free, dtype=bool)
    use_anchor = has_joint & ~free_body
    if nj:
        fj = np.where(use_anchor, first, 0)
        base = jnp.where(use_anchor[:, None], anchor[fj], body_x)
        sigma = jnp.where(use_anchor[:, None], model.joint_pos[fj], 0.0)
    else:
        base = body_x
        sigma = jnp.zeros_like(body_x)
    # The pole O_k is fixed in body k where O_0k is at the joint reference; the two differ only
    # when a slide or an off-anchor joint of the same body has moved (docs/mathematics.md, "Points and kinematic quantities").
    pole = body_x + jnp.einsum("nij,nj->ni", body_R, sigma)
    return Kinematics(
        body_rotation=body_R,
        body_position=body_x,
        base_point=base,
        pole=pole,
        com=com,
        central_inertia=I_c,
        dof_angular=ang,
        dof_linear=lin,
        dof_anchor=dof_anchor,
    )


def dof_motion_at(kin: Kinematics, dofs, points):
    """Unit motion of DoFs ``dofs`` evaluated at ``points``: (angular, point velocity)."""
    ang = kin.dof_angular[dofs]
    return ang, kin.dof_linear[dofs] + cross(ang, points - kin.dof_anchor[dofs])


class BodyMotion(eqx.Module):
    """Angular velocity/acceleration of each body and the motion of one reference point.

    ``velocity`` is the velocity and ``acceleration`` the *spatial* acceleration (time
    derivative of the velocity field at the fixed point) of each body's material point located
    at ``reference_point`` (Plücker coordinates about that point; one point for all bodies keeps
    every sum over DoFs a dense product). :func:`point_velocity` and
    :func:`point_acceleration` give the classical motion of any point of a body.
    """

    angular_velocity: Float[Array, "n_body 3"]
    velocity: Float[Array, "n_body 3"]
    angular_acceleration: Float[Array, "n_body 3"]
    acceleration: Float[Array, "n_body 3"]
    reference_point: Float[Array, "n_body 3"]


def rigid_body_kinetic_energy(
    mass: Float[ArrayLike, " n_body"],
    com_velocity: Float[ArrayLike, "n_body 3"],
    angular_velocity: Float[ArrayLike, "n_body 3"],
    central_inertia: Float[ArrayLike, "n_body 3 3"],
) -> Float[Array, ""]:
    """``T = sum_k ½ m_k |v_Ck|² + ½ ω_k·I_Ck ω_k`` body by body (König's theorem).

    The one kinetic-energy formula of the package: planar systems call it with ``ω`` along
    ``k`` and ``I_Ck`` acting on that axis.
    """
    t = 0.5 * jnp.sum(mass * jnp.sum(com_velocity * com_velocity, axis=-1))
    return t + 0.5 * jnp.sum(angular_velocity * jnp.einsum("nij,nj->ni", central_inertia, angular_velocity))


def point_velocity(motion: BodyMotion, points):
    """Velocity of the material points of each body located at ``points`` (n_body, 3)."""
    return motion.velocity + cross(motion.angular_velocity, points - motion.reference_point)


def point_acceleration(motion: BodyMotion, points):
    """Classical acceleration of the material points of each body located at ``points``."""
    d = points - motion.reference_point
    w = motion.angular_velocity
    return (
        motion.acceleration
        + cross(motion.angular_acceleration, d)
        + cross(w, motion.velocity + cross(w, d))
    )


def reference_point(kin: Kinematics) -> Float[Array, "3"]:
    """Common point for Plücker coordinates: the base point of body 0 (keeps lever arms short)."""
    return kin.base_point[0]


def dof_motion_plucker(kin: Kinematics, c0):
    """Unit motion of every DoF about the point ``c0``: (angular part, velocity of ``c0``)."""
    return kin.dof_angular, kin.dof_linear + cross(kin.dof_angular, c0 - kin.dof_anchor)


def body_velocities(model: Model, kin: Kinematics, v: Float[ArrayLike, " nv"]):
    """Angular velocity of every body and the velocity of its base point.

    Sums over the supporting DoFs: ``ω_k = sum_d S[k, d] ω_d v_d``
    (:meth:`~jaxbody.joints.JointLayout.support_sum`).
    """
    nb = model.n_body
    if model.nv == 0:
        z = jnp.zeros((nb, 3), kin.base_point.dtype)
        return z, z
    c0 = reference_point(kin)
    ang, lin0 = dof_motion_plucker(kin, c0)
    w = model.joints.support_sum(ang * v[:, None])
    u0 = model.joints.support_sum(lin0 * v[:, None])
    return w, u0 + cross(w, kin.base_point - c0)


def body_accelerations(
    model: Model, kin: Kinematics, v: Float[ArrayLike, " nv"], a: Float[ArrayLike, " nv"]
) -> BodyMotion:
    """Velocities and accelerations of every body for joint rates ``v`` and accelerations ``a``.

    ``A_k = sum_d (S_d a_d + Ṡ_d v_d)`` over the DoFs that support body ``k``, where the
    derivative of a DoF's motion ``Ṡ_d`` is the motion of the frame just before the joint
    crossed with ``S_d`` (MuJoCo's ``cdof_dot``). All in Plücker coordinates about one point.
    """
    joints = model.joints
    nb = model.n_body
    dtype = kin.base_point.dtype
    c0 = reference_point(kin)
    ref = jnp.broadcast_to(c0, (nb, 3))
    if model.nv == 0:
        z = jnp.zeros((nb, 3), dtype)
        return BodyMotion(z, z, z, z, ref)
    ang, lin0 = dof_motion_plucker(kin, c0)
    sv_ang, sv_lin = ang * v[:, None], lin0 * v[:, None]
    w = joints.support_sum(sv_ang)
    u0 = joints.support_sum(sv_lin)
    # Motion (Ω, V) of the frame just before each DoF; the DoF's axis moves with that frame, so
    # Ṡ_d = (Ω×ω_d, Ω×s_d + V×ω_d): the spatial cross product at c0 (MuJoCo's cdof_dot).
    Om = joints.before_sum(sv_ang)
    V0 = joints.before_sum(sv_lin)
    ang_dot = cross(Om, ang)
    lin_dot = cross(Om, lin0) + cross(V0, ang)
    eps = joints.support_sum(ang * a[:, None] + ang_dot * v[:, None])
    acc = joints.support_sum(lin0 * a[:, None] + lin_dot * v[:, None])
    return BodyMotion(w, u0, eps, acc, ref)


# ----------------------------------------------------------------------------- q integration
def qpos_rate(model: Model, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]) -> Float[Array, " nq"]:
    """``dq/dt`` for joint rates ``v`` (MuJoCo layout): quaternions follow ``q̇ = ½ q ⊗ (0, ω)``."""
    qd = jnp.zeros_like(q)
    for kind, _, qa, da in model.joints.kind_groups():
        if kind.quaternion is None:
            qd = qd.at[qa].set(v[da])
            continue
        n = kind.translation
        if n:
            qd = qd.at[qa[:, None] + np.arange(n)].set(v[da[:, None] + np.arange(n)])
        iq = qa[:, None] + kind.quaternion + np.arange(4)
        w = v[da[:, None] + n + np.arange(3)]
        w4 = jnp.concatenate([jnp.zeros_like(w[:, :1]), w], axis=-1)
        qd = qd.at[iq].set(0.5 * quat_multiply(q[iq], w4))
    return qd


def _quat_exp(w, h):
    """Quaternion of the rotation by angle |w| h about w (gradient-safe at w = 0)."""
    n2 = jnp.sum(w * w, axis=-1, keepdims=True)
    # double where: sqrt and sin(x)/x have infinite or NaN derivatives at w = 0
    safe = jnp.where(n2 > 0, n2, 1.0)
    n = jnp.sqrt(safe)
    half = 0.5 * n * h
    small = n2 < 1e-30
    s = jnp.where(small, 0.5 * h, jnp.sin(half) / n)
    c = jnp.where(small, 1.0, jnp.cos(half))
    return jnp.concatenate([c, s * w], axis=-1)


def integrate_qpos(model: Model, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"], dt) -> Float[Array, " nq"]:
    """Advance ``q`` by ``v`` for time ``dt`` exactly on the rotation group (MuJoCo ``mj_integratePos``)."""
    out = q
    for kind, _, qa, da in model.joints.kind_groups():
        if kind.quaternion is None:
            out = out.at[qa].add(dt * v[da])
            continue
        n = kind.translation
        if n:
            out = out.at[qa[:, None] + np.arange(n)].add(dt * v[da[:, None] + np.arange(n)])
        iq = qa[:, None] + kind.quaternion + np.arange(4)
        quat = quat_multiply(q[iq], _quat_exp(v[da[:, None] + n + np.arange(3)], dt))
        out = out.at[iq].set(quat / jnp.linalg.norm(quat, axis=-1, keepdims=True))
    return out


def normalize_qpos(model: Model, q: Float[ArrayLike, " nq"]) -> Float[Array, " nq"]:
    """Normalise the quaternions of ball and free joints.

    Written without an indexed update: the squared norms are a product of ``q²`` (the
    quaternions' coordinates only) with a static 0/1 matrix ``P`` (``nq × quaternions``), each
    coordinate takes its quaternion's inverse norm by a static index, and a select keeps every
    other coordinate as it was. An indexed update compiles on XLA's CPU backend to a scatter
    that loops over a ``vmap`` batch, and a solver renormalises after every step. As before, a
    non-finite or zero quaternion makes only its own coordinates non-finite.
    """
    q = jnp.asarray(q)
    blocks = [qa[:, None] + kind.quaternion + np.arange(4) for kind, _, qa, _ in model.joints.kind_groups()
              if kind.quaternion is not None]
    if not blocks:
        return q
    iq = np.concatenate(blocks)  # (quaternions, 4) coordinates
    member = np.zeros((q.shape[-1], iq.shape[0]))
    member[iq, np.arange(iq.shape[0])[:, None]] = 1.0
    owner = np.zeros(q.shape[-1], np.int32)  # each coordinate's quaternion (0 for the others)
    owner[iq] = np.arange(iq.shape[0])[:, None]
    in_quaternion = jnp.asarray(member.any(axis=1))
    squares = jnp.where(in_quaternion, q * q, 0.0)  # an inf elsewhere stays out of the norms
    inverse_norm = 1.0 / jnp.sqrt(jnp.dot(squares, jnp.asarray(member, q.dtype)))
    return jnp.where(in_quaternion, q * inverse_norm[owner], q)
