"""Joint-space kernels of a :class:`~jaxbody.Model` on a state :class:`~jaxbody.Data`.

Every function takes ``(model, data, ...)`` with ``data = jb.compute_data(model, q, v)``,
reads the kinematics and augmented bodies stored there, and checks no values (they are meant
for vector fields, solver loops and ``vmap`` batches; validate once with
:func:`jaxbody.check_inputs`). The convenience functions ``jb.mass_matrix(model, q)`` ...
of :mod:`jaxbody.dynamics` are these kernels behind that check.

Joints are the first Maggi layer (docs/maggi.md, "Maggi's equations and the reactions"): the joint rates ``v`` map linearly to the
quasi-velocities of the absolute equations (absolute angular velocities ``ω_k``, relative
pole velocities ``V_rk`` and the free-base velocity), and every joint-space equation is the
projection of the absolute equations on a DoF's motion:

* :func:`force_factors` evaluates Statement 1 (:func:`jaxbody.spatial.relative_force_factors`);
  projecting the factors of body ``k`` on the unit motion ``S_d`` of each DoF ``d`` of that
  body gives ``τ_d = F_k · v_d(O_0k) + M_k · ω_d`` (:func:`inverse_dynamics`); the factors
  themselves are the joint reactions (:func:`joint_reactions`).
* :func:`mass_matrix` is ``Aᵀ D A`` evaluated through subtree sums of augmented quantities:
  for DoFs ``a`` (on a carrier of, or the same body as) ``b`` on body ``k``,
  ``M_ab = S_a · 𝕀_k S_b`` where subsystem ``k`` is described by its mass ``m_k``, static
  moment ``h_k = sum_{i in S(k)} m̄_i`` and inertia
  ``K_k = sum_{l in S(k)} (I_l - [d_kl]×[m̄_l]× - [m̄_l]×[d_kl]×)``, ``d_kl = O_0l - O_0k``.

Conventions (docs/conventions.md):

* ``M(q) a + bias(q, v) = tau + passive + Jᵀ external``: ``bias`` = Coriolis, centrifugal
  and gravity terms (MuJoCo ``qfrc_bias``); ``passive`` = joint springs and dampers (MuJoCo
  ``qfrc_passive``), included only with ``include_passive=True``.
* ``external``: loads per body ``(n_body, 6)`` = world force and torque at the body's centre
  of mass (MuJoCo ``xfrc_applied``).
* Reactions: ``(force, moment)`` the parent exerts on body ``k``, moment about ``O_0k``.
"""


import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Float
from ._util import check_shape, index
from .augmented import subtree_static_moment
from .data import Data
from .kinematics import (
    Kinematics,
    body_accelerations,
    dof_motion_at,
    dof_motion_plucker,
    point_acceleration,
    point_velocity,
    quat_multiply,
    reference_point,
    rigid_body_kinetic_energy,
)
from .joints import SLIDE
from .linalg import solve_spd
from .model import Model
from .spatial import ForceFactors, relative_force_factors

__all__ = [
    "mass_matrix",
    "bias_forces",
    "force_factors",
    "inverse_dynamics",
    "forward_dynamics",
    "joint_reactions",
    "kinetic_energy",
    "potential_energy",
    "passive_forces",
    "passive_forces_at",
    "project_force_factors",
    "spring_displacements",
    "spring_dofs",
    "uniform_field_force",
    "body_wrench_force",
]


def _composite_about(model: Model, data: Data, point):
    """Mass, static moment and inertia of every subsystem about one ``point``.

    From the augmented bodies (docs/mathematics.md, "The augmented body"): the subsystem static moment about ``O_0k`` is
    ``h_k = sum_{i in S(k)} m̄_i`` and its inertia ``K_k = sum_{l in S(k)} (I_l - [d_kl]×[m̄_l]×
    - [m̄_l]×[d_kl]×)`` with ``d_kl = O_0l - O_0k``; moved to ``point`` (``x_l = O_0l - point``)
    this is ``sum_{l in S(k)} (I_l - sym(x_l, m̄_l)) - m_k [x_k]×²`` and ``h_k + m_k x_k``.
    """
    tree, aug = model.tree, data.augmented
    x = data.base_point - point
    mbar, m = aug.static_moment, aug.subtree_mass
    eye = jnp.eye(3, dtype=x.dtype)
    xm = jnp.sum(x * mbar, axis=-1)[:, None, None]
    term = aug.augmented_inertia + 2.0 * xm * eye - mbar[:, :, None] * x[:, None, :] - x[:, :, None] * mbar[:, None, :]
    x2 = jnp.sum(x * x, axis=-1)[:, None, None]
    K = tree.subtree_sum(term) + m[:, None, None] * (x2 * eye - x[:, :, None] * x[:, None, :])
    h = subtree_static_moment(tree, mbar) + m[:, None] * x
    return m, h, K


def mass_matrix(model: Model, data: Data) -> Float[Array, "nv nv"]:
    """Joint-space mass matrix ``M(q)`` in the coordinates of ``v`` (armature included).

    ``M_ab = S_a · 𝕀_k S_b`` for DoF ``a`` supporting DoF ``b`` on body ``k`` (module
    docstring), all in Plücker coordinates about one point.
    """
    # One common point (the base point of body 0) keeps every lever arm short and every sum
    # over DoFs a single dense product.
    c0 = reference_point(data)
    m, h, K = _composite_about(model, data, c0)
    k = index(model.joints.dof_body)
    ang, lin0 = dof_motion_plucker(data, c0)
    # wrench of subsystem k moving with the unit motion of DoF b, about c0
    p = m[k][:, None] * lin0 + jnp.cross(ang, h[k])
    L = jnp.cross(h[k], lin0) + jnp.einsum("nij,nj->ni", K[k], ang)
    P = lin0 @ p.T + ang @ L.T  # P[a, b] = S_a · 𝕀_k(b) S_b
    # P is only right where a supports b (then body(b)'s subsystem is the one that both DoFs
    # move); keep that upper triangle and mirror it, so M is exactly symmetric in floating point.
    U = model.joints.mass_mask(P.dtype) * P
    return U + U.T - jnp.diag(jnp.diag(U)) + jnp.diag(model.dof_armature)


def _external_loads(model: Model, data: Data, external):
    """``(F_r, M_r about O_0k)`` from MuJoCo-style ``xfrc_applied`` (force, torque at the CM)."""
    if external is None:
        return None, None
    external = check_shape(external, (model.n_body, 6), "external", dtype=data.com.dtype)
    f, t = external[:, :3], external[:, 3:]
    return f, t + jnp.cross(data.com - data.base_point, f)


def uniform_field_force(
    model: Model, data: Kinematics, field: Float[ArrayLike, "3"]
) -> Float[Array, " nv"]:
    """Generalized force of a uniform acceleration field ``g`` (gravity; world) on every mass.

    The field acts on body ``l`` as the force ``m_l g`` at its centre of mass ``C_l``; DoF ``d``
    of body ``k``, whose unit motion gives the point ``X`` the velocity ``s_d + ω_d × (X − a_d)``
    (``a_d`` its anchor), receives the power of the forces on the subtree ``S(k)`` it moves:
    ``Q_d = m_k (s_d · g) + ω_d · ((h_k − m_k a_d) × g)`` with the subtree mass
    ``m_k = Σ_{S(k)} m_l`` and static moment ``h_k = Σ_{S(k)} m_l C_l`` about the origin (the
    augmented bodies' subsystem mass and static moment, docs/mathematics.md, "The augmented body", eq. 5, moved to the origin).
    """
    field = jnp.asarray(field, data.com.dtype)
    m = model.body_mass
    tree = model.tree
    m_sub = tree.subtree_sum(m)
    h_sub = tree.subtree_sum(m[:, None] * data.com)
    b = np.asarray(model.joints.dof_body, dtype=np.int32)
    lever = h_sub[b] - m_sub[b][:, None] * data.dof_anchor
    return m_sub[b] * (data.dof_linear @ field) + jnp.sum(data.dof_angular * jnp.cross(lever, field), axis=-1)


def body_wrench_force(
    model: Model, data: Kinematics, wrenches: Float[ArrayLike, "n_body 6"]
) -> Float[Array, " nv"]:
    """Generalized force of world forces and torques at the bodies' centres of mass.

    ``wrenches`` is MuJoCo's ``xfrc_applied`` layout: ``(force, torque)`` per body. DoF ``d`` of
    body ``k`` (unit motion ``s_d + ω_d × (X − a_d)``) receives ``Q_d = s_d · F_k + ω_d · (M_k −
    a_d × F_k)`` with the subtree sums ``F_k = Σ_{S(k)} f_l`` and ``M_k = Σ_{S(k)} (t_l + C_l ×
    f_l)`` about the origin: ``Jᵀ external`` of the equations of motion (docs/conventions.md;
    the body loads ``F_r``, ``M_r`` of Statement 1, spec eqs 1–2, projected on the DoFs).
    """
    wrenches = jnp.asarray(wrenches, data.com.dtype)
    force, torque = wrenches[:, :3], wrenches[:, 3:]
    tree = model.tree
    f_sub = tree.subtree_sum(force)
    m_sub = tree.subtree_sum(torque + jnp.cross(data.com, force))
    b = np.asarray(model.joints.dof_body, dtype=np.int32)
    moment = m_sub[b] - jnp.cross(data.dof_anchor, f_sub[b])
    return jnp.sum(data.dof_linear * f_sub[b], axis=-1) + jnp.sum(data.dof_angular * moment, axis=-1)


def force_factors(
    model: Model,
    data: Data,
    a: Float[ArrayLike, " nv"],
    *,
    external: Float[ArrayLike, "n_body 6"] | None = None,
    gravity=True,
) -> ForceFactors:
    """Statement 1 at ``(q, v, a)``: relative force factors of every body (spec eqs 1–4).

    ``force``/``moment`` are what the parent (ground for roots) exerts on body ``k`` at
    ``O_0k``: constraint reaction plus drive. ``gravity=False`` (or ``None``) leaves the
    model's gravity out of the program (scenes declare gravity as an effect of their own); a
    vector replaces the model's gravity. Terms that the
    model's joints make identically zero are left out when the program is traced: the
    relative motion of poles without slides or bodies with several joints, the carrier
    acceleration without a free joint.
    """
    tree = model.tree
    a = check_shape(a, (model.nv,), "a", dtype=data.com.dtype)
    aug = data.augmented
    motion = body_accelerations(model, data, data.v, a)
    w, e = motion.angular_velocity, motion.angular_acceleration
    joints = model.joints
    Vr = Wr = W_root = None
    # Only slides, or a second joint of a body turning it about another anchor, move a pole
    # off its base point; otherwise V_r = W_r = 0 identically and the terms are left out.
    if SLIDE in joints.type or max(joints.body_joint_count, default=0) > 1:
        par = tree.parent_array
        has_parent = jnp.asarray(par >= 0)[:, None]
        # motion of the parent's material point at O_0k (ground: at rest)
        parent_motion = jax.tree.map(lambda x: x[np.maximum(par, 0)], motion)
        vp = jnp.where(has_parent, point_velocity(parent_motion, data.base_point), 0.0)
        ap = jnp.where(has_parent, point_acceleration(parent_motion, data.base_point), 0.0)
        # Relative motion of the pole O_k with respect to O_0k, derivatives taken in body-k
        # axes (docs/mathematics.md, "Points and kinematic quantities" remark): remove the rigid-body part ω×ρ from the world-frame
        # derivatives.
        rho = data.pole - data.base_point
        rho_dot = point_velocity(motion, data.pole) - vp
        rho_ddot = point_acceleration(motion, data.pole) - ap
        Vr = rho_dot - jnp.cross(w, rho)
        Wr = rho_ddot - jnp.cross(e, rho) - jnp.cross(w, rho_dot) - jnp.cross(w, Vr)
    if any(joints.body_is_free):
        # A free body's base point is the origin of a translating carrier frame (Cor. 1): its
        # motion enters as the root acceleration W_0, not as a relative motion.
        free = np.asarray(joints.body_is_free, dtype=bool)[:, None]
        if Vr is not None:
            Vr = jnp.where(free, 0.0, Vr)
            Wr = jnp.where(free, 0.0, Wr)
        W_root = jnp.where(free, point_acceleration(motion, data.base_point), 0.0)
    Fr, Mr = _external_loads(model, data, external)
    if gravity is True:
        g = model.gravity
    elif gravity is None or gravity is False:
        g = None
    else:
        g = jnp.asarray(gravity, data.com.dtype)
    return relative_force_factors(
        tree, aug.subtree_mass, aug.static_moment, aug.augmented_inertia, data.link,
        w, e, Vr, Wr, W_root, g, Fr, Mr,
    )


def project_force_factors(model: Model, data: Data, factors: ForceFactors) -> Float[Array, " nv"]:
    """Generalized forces of the DoFs from the force factors of their bodies: projecting the
    factors ``(F_k, M_k)`` of body ``k`` on the unit motion of each of its DoFs gives
    ``τ_d = F_k · v_d(O_0k) + M_k · ω_d`` (spec Statement 1, eqs 1–4)."""
    if model.nv == 0:
        return jnp.zeros((0,), data.com.dtype)
    k = index(model.joints.dof_body)
    ang, vel = dof_motion_at(data, np.arange(model.nv), data.base_point[k])
    return jnp.sum(factors.force[k] * vel, axis=-1) + jnp.sum(factors.moment[k] * ang, axis=-1)


def bias_forces(model: Model, data: Data, *, gravity: bool = True) -> Float[Array, " nv"]:
    """Coriolis, centrifugal and gravity forces (MuJoCo ``qfrc_bias``): ``tau`` at ``a = 0``.

    ``gravity=False``: the velocity-product terms alone (gravity left out of the program).
    """
    return project_force_factors(model, data, force_factors(model, data, jnp.zeros_like(data.v), gravity=gravity))


def inverse_dynamics(
    model: Model,
    data: Data,
    a: Float[ArrayLike, " nv"],
    *,
    external: Float[ArrayLike, "n_body 6"] | None = None,
    include_passive: bool = False,
) -> Float[Array, " nv"]:
    """Joint forces ``tau`` that give accelerations ``a``, via Statement 1.

    ``tau = M a + bias - Jᵀ external`` and, with ``include_passive=True``, minus the passive
    forces (``tau`` is then what the actuators add to the springs and dampers).

    MuJoCo's ``mj_inverse`` returns ``M a + qfrc_bias - qfrc_passive``: it equals
    ``include_passive=True``. The default (``False``) leaves springs and dampers out, so a
    computed-torque law on a damped model does not cancel the damping twice.
    """
    a = check_shape(a, (model.nv,), "a", dtype=data.com.dtype)
    tau = project_force_factors(model, data, force_factors(model, data, a, external=external))
    tau = tau + model.dof_armature * a
    if include_passive:
        tau = tau - passive_forces(model, data)
    return tau


def forward_dynamics(
    model: Model,
    data: Data,
    tau: Float[ArrayLike, " nv"] | None = None,
    *,
    external: Float[ArrayLike, "n_body 6"] | None = None,
    include_passive: bool = False,
) -> Float[Array, " nv"]:
    """Accelerations ``a = M⁻¹ (tau - bias + Jᵀ external [+ passive])`` by a Cholesky solve.

    ``include_passive=True`` adds the joint springs and dampers (MuJoCo's ``mj_forward``
    with ``qfrc_passive``; what the scene of a model (:func:`jaxbody.scene`) and ``jb.simulate`` use).
    The solve is :func:`jaxbody.linalg.solve_spd` (no LAPACK call, safe under large ``vmap``
    batches on CPU, no explicit inverse).
    """
    rhs = -project_force_factors(model, data, force_factors(model, data, jnp.zeros_like(data.v), external=external))
    if tau is not None:
        rhs = rhs + check_shape(tau, (model.nv,), "tau", dtype=rhs.dtype)
    if include_passive:
        rhs = rhs + passive_forces(model, data)
    return solve_spd(mass_matrix(model, data), rhs)


def joint_reactions(
    model: Model,
    data: Data,
    a: Float[ArrayLike, " nv"],
    *,
    external: Float[ArrayLike, "n_body 6"] | None = None,
) -> tuple[Float[Array, "n_body 3"], Float[Array, "n_body 3"]]:
    """``(force, moment)`` the parent exerts on each body at its base point ``O_0k`` (world).

    The relative force factors ``F_k``, ``M_k`` of Statement 1 (spec eqs 1–2): constraint
    reaction plus drive; the moment is about ``O_0k`` (the anchor of the body's first joint,
    the body origin for welded and free bodies).
    """
    f = force_factors(model, data, a, external=external)
    return f.force, f.moment


def kinetic_energy(model: Model, data: Data) -> Float[Array, ""]:
    """``T = sum_k ½ m_0k |v_Ck|² + ½ ω_k·I_Ck ω_k`` from body velocities (armature adds ½ a v²)."""
    w, u = data.angular_velocity, data.base_point_velocity
    vc = u + jnp.cross(w, data.com - data.base_point)
    t = rigid_body_kinetic_energy(model.body_mass, vc, w, data.central_inertia)
    return t + 0.5 * jnp.sum(model.dof_armature * data.v * data.v)


def _quat_log_diff(qa, qb):
    """Rotation vector of ``qb⁻¹ ⊗ qa`` (MuJoCo ``mju_subQuat``), gradient-safe at zero."""
    conj = qb * jnp.asarray([1.0, -1.0, -1.0, -1.0], qb.dtype)
    d = quat_multiply(conj, qa)
    # q and -q are the same rotation: take the short way round (angle in [0, π])
    d = d * jnp.where(d[..., :1] < 0, -1.0, 1.0)
    s2 = jnp.sum(d[..., 1:] ** 2, axis=-1, keepdims=True)
    # double where: sqrt and angle/s have infinite derivatives at the identity
    safe = jnp.where(s2 > 0, s2, 1.0)
    s = jnp.sqrt(safe)
    angle = 2.0 * jnp.arctan2(s, d[..., :1])
    # angle/s -> 2 as s -> 0 (d_w -> 1)
    scale = jnp.where(s2 > 1e-30, angle / s, 2.0)
    return d[..., 1:] * scale


def spring_dofs(model: Model) -> list[tuple[np.ndarray, ArrayLike]]:
    """The DoFs each group of joint springs acts on and the stiffness of its joints, in the order
    of :func:`spring_displacements`: ``(dofs, stiffness)`` with ``dofs`` ``(n, m)`` DoF indices
    (``m`` = 1 for a hinge or slide, 3 for a translation or a rotation) of ``n`` joints. No
    configuration is needed (a stiffness estimate reads the layout alone)."""
    out = []
    for kind, js, _, da in model.joints.kind_groups():
        k = model.joint_stiffness[js]
        if kind.quaternion is None:
            out.append((da[:, None], k))
            continue
        if kind.translation:
            out.append((da[:, None] + np.arange(kind.translation), k))
        out.append((da[:, None] + kind.translation + np.arange(3), k))
    return out


def spring_displacements(model: Model, q: Float[Array, " nq"]) -> list[tuple[np.ndarray, Array, Array]]:
    """Joint-spring displacements ``q ⊖ q_spring`` from the spring reference, per joint kind.

    A list of ``(dofs, displacement, stiffness)``: the DoF indices ``(n, m)`` the displacement
    acts on, the displacements ``(n, m)`` (a coordinate's difference; for the rotation of a
    ball or free joint the rotation vector of ``q_spring⁻¹ ⊗ q/|q|``, MuJoCo ``mju_subQuat``)
    and the stiffness of each of the ``n`` joints (:func:`spring_dofs`). The springs'
    generalized force is ``τ[dofs] = −k · displacement`` and their energy ``½ k |displacement|²``
    (:func:`passive_forces_at`, :func:`potential_energy`, :class:`jaxbody.JointSprings`).
    """
    out = []  # (dof indices, displacement, stiffness per dof)
    layout = iter(spring_dofs(model))
    for kind, _, qa, _ in model.joints.kind_groups():
        if kind.quaternion is None:
            dofs, k = next(layout)
            out.append((dofs, (q[qa] - model.qpos_spring[qa])[:, None], k))
            continue
        n = kind.translation
        if n:
            dofs, k = next(layout)
            idx = qa[:, None] + np.arange(n)
            out.append((dofs, q[idx] - model.qpos_spring[idx], k))
        dofs, k = next(layout)
        idx = qa[:, None] + kind.quaternion + np.arange(4)
        qn = q[idx] / jnp.linalg.norm(q[idx], axis=-1, keepdims=True)
        out.append((dofs, _quat_log_diff(qn, model.qpos_spring[idx]), k))
    return out


def potential_energy(model: Model, data: Data) -> Float[Array, ""]:
    """Gravity plus joint-spring potential energy (as MuJoCo ``mj_energyPos``)."""
    e = -jnp.sum(model.body_mass * (data.com @ model.gravity))
    for _, disp, k in spring_displacements(model, data.q):
        e = e + 0.5 * jnp.sum(k * jnp.sum(disp * disp, axis=-1))
    return e


def passive_forces(model: Model, data: Data) -> Float[Array, " nv"]:
    """Joint springs towards ``qpos_spring`` and viscous damping (MuJoCo ``qfrc_passive``)."""
    return passive_forces_at(model, data.q, data.v)


def passive_forces_at(model: Model, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nv"]:
    """:func:`passive_forces` from the coordinates alone (springs and dampers need no kinematics)."""
    f = -model.dof_damping * v
    for dofs, disp, k in spring_displacements(model, q):
        f = f.at[dofs].add(-k[:, None] * disp)
    return f
