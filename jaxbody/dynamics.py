"""Joint-space dynamics of a :class:`~jaxbody.model.Model` (DESIGN.md public API).

Joints are the first Maggi layer (spec §15): the joint rates ``v`` map linearly to the
quasi-velocities of the absolute equations (absolute angular velocities ``ω_k``, relative
pole velocities ``V_rk`` and the free-base velocity), and every joint-space equation is the
projection of the absolute equations on a DoF's motion. Concretely:

* ``inverse_dynamics`` evaluates Statement 1 (:func:`jaxbody.spatial.relative_force_factors`)
  and projects the relative force factors of body ``k`` on the unit motion ``S_d`` of each
  DoF ``d`` of that body: ``τ_d = F_k · v_d(O_0k) + M_k · ω_d``. The factors are the joint
  reactions (``joint_reactions``).
* ``mass_matrix`` is ``Aᵀ D A`` evaluated through subtree sums of augmented quantities: for
  DoFs ``a`` (on a carrier of, or the same body as) ``b`` on body ``k``,
  ``M_ab = S_a · 𝕀_k S_b`` where the subsystem ``k`` is described at ``O_0k`` by its mass
  ``m_k``, static moment ``h_k = sum_{i in S(k)} m̄_i`` and inertia
  ``K_k = sum_{l in S(k)} (I_l - [d_kl]×[m̄_l]× - [m̄_l]×[d_kl]×)``, ``d_kl = O_0l - O_0k``.
  (The planar analogue: "joint equation k = sum of the absolute equations of subsystem k",
  spec §9.4.)

``M(q) a + bias(q, v) = tau`` with ``bias`` = Coriolis, centrifugal and gravity terms, as
MuJoCo's ``qfrc_bias``; passive joint forces are separate (:func:`passive_forces`).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Float
from .augmented import (
    AugmentedBodies,
    augmented_inertia,
    static_moment,
    subtree_mass,
    subtree_static_moment,
)
from .joints import BALL, FREE, HINGE, SLIDE
from .kinematics import (
    Kinematics,
    body_accelerations,
    body_velocities,
    dof_motion_at,
    dof_motion_plucker,
    forward_kinematics,
    point_acceleration,
    point_velocity,
    reference_point,
    quat_multiply,
)
from .linalg import solve_spd
from .model import Model
from .spatial import relative_force_factors

__all__ = [
    "augmented_bodies",
    "mass_matrix",
    "bias_forces",
    "inverse_dynamics",
    "forward_dynamics",
    "joint_reactions",
    "kinetic_energy",
    "potential_energy",
    "passive_forces",
    "check_state",
]


def _i32(seq):
    return np.asarray(seq, dtype=np.int32)


def check_state(model: Model, q, v=None):
    """Shape checks at trace time and a NaN/inf check inside jit (``eqx.error_if``)."""
    q = jnp.asarray(q)
    if q.shape != (model.nq,):
        raise ValueError(f"q has shape {q.shape}, expected ({model.nq},) for {model!r}")
    q = eqx.error_if(q, ~jnp.all(jnp.isfinite(q)), "state q contains NaN or inf")
    if v is None:
        return q
    v = jnp.asarray(v)
    if v.shape != (model.nv,):
        raise ValueError(f"v has shape {v.shape}, expected ({model.nv},) for {model!r}")
    v = eqx.error_if(v, ~jnp.all(jnp.isfinite(v)), "state v contains NaN or inf")
    return q, v


def _vec(model: Model, x, name, n):
    x = jnp.asarray(x, model.body_pos.dtype)
    if x.shape != (n,):
        raise ValueError(f"{name} has shape {x.shape}, expected ({n},)")
    return x


def _augmented(model: Model, kin: Kinematics) -> tuple[AugmentedBodies, Array]:
    """Augmented bodies about the base points (world frame) and the links ``R_k``."""
    tree = model.tree
    par = tree.parent_array
    link = kin.base_point - kin.base_point[np.maximum(par, 0)]
    link = jnp.where(jnp.asarray(par >= 0)[:, None], link, 0.0)
    r = kin.com - kin.base_point
    aug = AugmentedBodies(
        subtree_mass=subtree_mass(tree, model.body_mass),
        static_moment=static_moment(tree, model.body_mass, r, link),
        augmented_inertia=augmented_inertia(tree, model.body_mass, kin.central_inertia, r, link),
    )
    return aug, link


def augmented_bodies(model: Model, q: Float[ArrayLike, " nq"]) -> AugmentedBodies:
    """Subtree masses, augmented static moments and inertias about ``O_0k`` (spec eqs 5–6).

    Vectors and tensors are in world axes; the base point of body ``k`` is the anchor of its
    first joint (see :mod:`jaxbody.kinematics`).
    """
    q = check_state(model, q)
    return _augmented(model, forward_kinematics(model, q))[0]


def _composite_about(model: Model, kin: Kinematics, aug: AugmentedBodies, point):
    """Mass, static moment and inertia of every subsystem about one ``point``.

    From the augmented bodies (spec §3): the subsystem static moment about ``O_0k`` is
    ``h_k = sum_{i in S(k)} m̄_i`` and its inertia ``K_k = sum_{l in S(k)} (I_l - [d_kl]×[m̄_l]×
    - [m̄_l]×[d_kl]×)`` with ``d_kl = O_0l - O_0k``; moved to ``point`` (``x_l = O_0l - point``)
    this is ``sum_{l in S(k)} (I_l - sym(x_l, m̄_l)) - m_k [x_k]×²`` and ``h_k + m_k x_k``.
    """
    tree = model.tree
    x = kin.base_point - point
    mbar, m = aug.static_moment, aug.subtree_mass
    eye = jnp.eye(3, dtype=x.dtype)
    xm = jnp.sum(x * mbar, axis=-1)[:, None, None]
    term = aug.augmented_inertia + 2.0 * xm * eye - mbar[:, :, None] * x[:, None, :] - x[:, :, None] * mbar[:, None, :]
    x2 = jnp.sum(x * x, axis=-1)[:, None, None]
    K = tree.subtree_sum(term) + m[:, None, None] * (x2 * eye - x[:, :, None] * x[:, None, :])
    h = subtree_static_moment(tree, mbar) + m[:, None] * x
    return m, h, K


def mass_matrix(model: Model, q: Float[ArrayLike, " nq"]) -> Float[Array, "nv nv"]:
    """Joint-space mass matrix ``M(q)`` (armature included), ``Aᵀ D A`` by subsystem sums.

    See the module docstring: ``M_ab = S_a · 𝕀_k S_b`` for DoF ``a`` supporting DoF ``b`` on
    body ``k``, with the subsystem inertia ``𝕀_k`` built from the augmented bodies.
    """
    q = check_state(model, q)
    kin = forward_kinematics(model, q)
    return _mass_matrix(model, kin, _augmented(model, kin)[0])


def _mass_matrix(model: Model, kin: Kinematics, aug: AugmentedBodies):
    c0 = reference_point(kin)
    m, h, K = _composite_about(model, kin, aug, c0)
    k = _i32(model.joints.dof_body)
    ang, lin0 = dof_motion_plucker(kin, c0)
    # wrench of subsystem k moving with the unit motion of DoF b, about c0
    p = m[k][:, None] * lin0 + jnp.cross(ang, h[k])
    L = jnp.cross(h[k], lin0) + jnp.einsum("nij,nj->ni", K[k], ang)
    P = lin0 @ p.T + ang @ L.T  # P[a, b] = S_a · 𝕀_k(b) S_b
    U = jnp.asarray(model.joints.mass_mask, P.dtype) * P
    return U + U.T - jnp.diag(jnp.diag(U)) + jnp.diag(model.dof_armature)


def _external_loads(model: Model, kin: Kinematics, external):
    """``(F_r, M_r about O_0k)`` from MuJoCo-style ``xfrc_applied`` (force, torque at the CM)."""
    if external is None:
        return None, None
    external = jnp.asarray(external, kin.com.dtype)
    if external.shape != (model.n_body, 6):
        raise ValueError(f"external loads have shape {external.shape}, expected ({model.n_body}, 6)")
    f, t = external[:, :3], external[:, 3:]
    return f, t + jnp.cross(kin.com - kin.base_point, f)


def _force_factors(model: Model, kin: Kinematics, v, a, external=None, augmented=None):
    """Statement 1 at state (q, v, a): relative force factors of every body."""
    tree = model.tree
    aug, link = _augmented(model, kin) if augmented is None else augmented
    motion = body_accelerations(model, kin, v, a)
    par = tree.parent_array
    has_parent = jnp.asarray(par >= 0)[:, None]
    pidx = np.maximum(par, 0)
    free = np.asarray(model.joints.body_is_free, dtype=bool)[:, None]
    zero = jnp.zeros_like(kin.base_point)
    # motion of the parent's material point at O_0k (ground: at rest)
    parent_motion = jax.tree.map(lambda x: x[pidx], motion)
    vp = jnp.where(has_parent, point_velocity(parent_motion, kin.base_point), 0.0)
    ap = jnp.where(has_parent, point_acceleration(parent_motion, kin.base_point), 0.0)
    w, e = motion.angular_velocity, motion.angular_acceleration
    rho = kin.pole - kin.base_point
    rho_dot = point_velocity(motion, kin.pole) - vp
    rho_ddot = point_acceleration(motion, kin.pole) - ap
    Vr = rho_dot - jnp.cross(w, rho)
    Wr = rho_ddot - jnp.cross(e, rho) - jnp.cross(w, rho_dot) - jnp.cross(w, Vr)
    Vr = jnp.where(free, 0.0, Vr)
    Wr = jnp.where(free, 0.0, Wr)
    W_root = jnp.where(free, point_acceleration(motion, kin.base_point), zero)
    g = model.gravity
    Fr, Mr = _external_loads(model, kin, external)
    return relative_force_factors(
        tree, aug.subtree_mass, aug.static_moment, aug.augmented_inertia, link,
        w, e, Vr, Wr, W_root, g, Fr, Mr,
    )


def _project(model: Model, kin: Kinematics, factors):
    """Generalized forces of the DoFs from the force factors of their bodies."""
    if model.nv == 0:
        return jnp.zeros((0,), kin.com.dtype)
    k = _i32(model.joints.dof_body)
    ang, vel = dof_motion_at(kin, np.arange(model.nv), kin.base_point[k])
    return jnp.sum(factors.force[k] * vel, axis=-1) + jnp.sum(factors.moment[k] * ang, axis=-1)


def inverse_dynamics(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    a: Float[ArrayLike, " nv"],
    external: Float[ArrayLike, "n_body 6"] | None = None,
) -> Float[Array, " nv"]:
    """Joint forces ``tau = M(q) a + bias(q, v)`` (minus external loads), via Statement 1.

    Args:
        external: optional loads per body, MuJoCo ``xfrc_applied`` layout: world force and
            torque applied at the body's centre of mass.
    """
    q, v = check_state(model, q, v)
    a = _vec(model, a, "a", model.nv)
    kin = forward_kinematics(model, q)
    tau = _project(model, kin, _force_factors(model, kin, v, a, external))
    return tau + model.dof_armature * a


def bias_forces(model: Model, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]) -> Float[Array, " nv"]:
    """Coriolis, centrifugal and gravity forces (MuJoCo ``qfrc_bias``): ``tau`` at ``a = 0``."""
    q, v = check_state(model, q, v)
    kin = forward_kinematics(model, q)
    return _project(model, kin, _force_factors(model, kin, v, jnp.zeros_like(v)))


def forward_dynamics(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    tau: Float[ArrayLike, " nv"] | None = None,
    external: Float[ArrayLike, "n_body 6"] | None = None,
) -> Float[Array, " nv"]:
    """Joint accelerations ``a = M⁻¹ (tau - bias + external)`` by a Cholesky solve.

    The solve is :func:`jaxbody.linalg.solve_spd` (no LAPACK call, safe under large
    ``vmap`` batches on CPU, no explicit inverse).
    """
    q, v = check_state(model, q, v)
    kin = forward_kinematics(model, q)
    augmented = _augmented(model, kin)
    rhs = -_project(model, kin, _force_factors(model, kin, v, jnp.zeros_like(v), external, augmented))
    if tau is not None:
        rhs = rhs + _vec(model, tau, "tau", model.nv)
    return solve_spd(_mass_matrix(model, kin, augmented[0]), rhs)


def joint_reactions(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    a: Float[ArrayLike, " nv"],
    external: Float[ArrayLike, "n_body 6"] | None = None,
) -> tuple[Float[Array, "n_body 3"], Float[Array, "n_body 3"]]:
    """Force and moment the parent exerts on each body at its base point ``O_0k`` (world).

    The relative force factors ``F_k``, ``M_k`` of Statement 1 (spec eqs 1–2): constraint
    reaction plus drive; the moment is about ``O_0k`` (the anchor of the body's first joint,
    the body origin for welded and free bodies).
    """
    q, v = check_state(model, q, v)
    a = _vec(model, a, "a", model.nv)
    kin = forward_kinematics(model, q)
    f = _force_factors(model, kin, v, a, external)
    return f.force, f.moment


def kinetic_energy(model: Model, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]) -> Float[Array, ""]:
    """``T = sum_k ½ m_0k |v_Ck|² + ½ ω_k·I_Ck ω_k`` from body velocities (armature adds ½ a v²)."""
    q, v = check_state(model, q, v)
    kin = forward_kinematics(model, q)
    w, u = body_velocities(model, kin, v)
    vc = u + jnp.cross(w, kin.com - kin.base_point)
    t = 0.5 * jnp.sum(model.body_mass * jnp.sum(vc * vc, axis=-1))
    t = t + 0.5 * jnp.sum(w * jnp.einsum("nij,nj->ni", kin.central_inertia, w))
    return t + 0.5 * jnp.sum(model.dof_armature * v * v)


def _quat_log_diff(qa, qb):
    """Rotation vector of ``qb⁻¹ ⊗ qa`` (MuJoCo ``mju_subQuat``), gradient-safe at zero."""
    conj = qb * jnp.asarray([1.0, -1.0, -1.0, -1.0], qb.dtype)
    d = quat_multiply(conj, qa)
    d = d * jnp.where(d[..., :1] < 0, -1.0, 1.0)
    s2 = jnp.sum(d[..., 1:] ** 2, axis=-1, keepdims=True)
    safe = jnp.where(s2 > 0, s2, 1.0)
    s = jnp.sqrt(safe)
    angle = 2.0 * jnp.arctan2(s, d[..., :1])
    scale = jnp.where(s2 > 1e-30, angle / s, 2.0)
    return d[..., 1:] * scale


def _spring_terms(model: Model, q):
    """Per joint kind: displacement vectors from the spring reference (for force and energy)."""
    joints = model.joints
    types = np.asarray(joints.type, dtype=np.int64)
    qadr = np.asarray(joints.qposadr, dtype=np.int64)
    dadr = np.asarray(joints.dofadr, dtype=np.int64)
    out = []  # (dof indices, displacement, stiffness per dof)
    for kind in (HINGE, SLIDE, BALL, FREE):
        js = np.nonzero(types == kind)[0]
        if js.size == 0:
            continue
        k = model.joint_stiffness[js]
        qa, da = qadr[js], dadr[js]
        if kind in (HINGE, SLIDE):
            out.append((da[:, None], (q[qa] - model.qpos_spring[qa])[:, None], k))
            continue
        if kind == FREE:
            idx = qa[:, None] + np.arange(3)
            out.append((da[:, None] + np.arange(3), q[idx] - model.qpos_spring[idx], k))
            qa, da = qa + 3, da + 3
        idx = qa[:, None] + np.arange(4)
        qn = q[idx] / jnp.linalg.norm(q[idx], axis=-1, keepdims=True)
        out.append((da[:, None] + np.arange(3), _quat_log_diff(qn, model.qpos_spring[idx]), k))
    return out


def potential_energy(model: Model, q: Float[ArrayLike, " nq"]) -> Float[Array, ""]:
    """Gravity plus joint-spring potential energy (as MuJoCo ``mj_energyPos``)."""
    q = check_state(model, q)
    kin = forward_kinematics(model, q)
    e = -jnp.sum(model.body_mass * (kin.com @ model.gravity))
    for _, disp, k in _spring_terms(model, q):
        e = e + 0.5 * jnp.sum(k * jnp.sum(disp * disp, axis=-1))
    return e


def passive_forces(model: Model, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]) -> Float[Array, " nv"]:
    """Joint springs towards ``qpos_spring`` and viscous damping (MuJoCo ``qfrc_passive``)."""
    q, v = check_state(model, q, v)
    f = -model.dof_damping * v
    for dofs, disp, k in _spring_terms(model, q):
        f = f.at[dofs].add(-k[:, None] * disp)
    return f
