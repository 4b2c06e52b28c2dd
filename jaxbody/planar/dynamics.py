"""Dynamics of planar systems in absolute angles (docs/mathematics.md, "Planar systems in absolute angles" to "Corollary 8"; the paper's Corollaries 5–7).

Coordinates, drives and loads as in :mod:`jaxbody.planar.parameters`: ``q = (x, y, q_1..q_n)``
or ``(q_1..q_n)``, absolute angles; ``tau`` in the layout of ``v`` (base force, hinge drive
torques); external loads as ``external_force`` ``(n, 2)`` (world axes) and
``external_moment`` ``(n,)`` about each body's hinge (see :func:`point_load`).

The mass matrix ``ℳ`` and the bias ``h`` are the closed forms of eqs (10)–(13) (gathers and
scatters over the static carrier pairs, so the trace does not grow with ``n``); reactions and
inverse dynamics are Statement 1 itself — the same kernel as the spatial path
(:func:`jaxbody.spatial.relative_force_factors`), with planar vectors in the plane ``z = 0``.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._types import Array, Float
from .._util import axial3, check_shape, cross2, index, perp2, plane3, rot2
from ..augmented import AugmentedBodies, augmented_moment_of_inertia, static_moment, subtree_mass
from ..kinematics import rigid_body_kinetic_energy
from ..linalg import solve_spd
from ..spatial import relative_force_factors
from .parameters import ParamLike, PlanarParameters

__all__ = [
    "split_base",
    "absolute_angles",
    "augmented_bodies",
    "augmented_bodies_in_body_axes",
    "mass_matrix",
    "bias_forces",
    "generalized_forces",
    "forward_dynamics",
    "inverse_dynamics",
    "joint_reactions",
    "root_force",
    "body_positions",
    "point_position",
    "point_load",
    "kinetic_energy",
    "potential_energy",
    "total_energy",
    "power",
]


def _dot2(a, b):
    return jnp.sum(a * b, axis=-1)


def _segsum(x, ids, n):
    return jax.ops.segment_sum(x, jnp.asarray(index(ids)), num_segments=n)


def split_base(system: PlanarParameters, x):
    """``(base part, body part)`` of a vector in the layout of ``q`` or ``v``: the two base
    coordinates of a translating base (none on the ground), then one entry per body."""
    nb = system.n_base
    return x[:nb], x[nb:]


def absolute_angles(system: PlanarParameters, q: Float[Array, " nq"]) -> Float[Array, " n_body"]:
    """``θ_k = q_k + angle_origin``: absolute angles from ``i`` (docs/mathematics.md, "Planar systems in absolute angles")."""
    q = check_shape(q, (system.nq,), "q", "planar system")
    return split_base(system, q)[1] + system.angle_origin


class _Kin(NamedTuple):
    theta: Array  # (n,) absolute angles from i
    mbar: Array  # (n, 2) static moments of the augmented bodies, world axes (eq. 5)
    link: Array  # (n, 2) R_k in world axes (root: its hinge position in world/base axes)
    J: Array  # (n,) augmented moments of inertia (eq. 6, planar)
    m_sub: Array  # (n,) subsystem masses


def _kin(system: PlanarParameters, q) -> _Kin:
    tr = system.tree
    theta = absolute_angles(system, q)
    m_sub = subtree_mass(tr, system.body_mass)
    mbar_body = static_moment(tr, system.body_mass, system.body_com, system.hinge_pos)
    J = augmented_moment_of_inertia(
        tr, system.body_mass, system.body_inertia, system.body_com, system.hinge_pos
    )
    parent = np.asarray(tr.parent)
    theta_parent = theta[index(np.maximum(parent, 0))]
    link = jnp.where(
        jnp.asarray(parent < 0)[:, None], system.hinge_pos, rot2(theta_parent, system.hinge_pos)
    )
    return _Kin(theta, rot2(theta, mbar_body), link, J, m_sub)


def _pairs(system: PlanarParameters):
    tr = system.tree
    return tr.carrier_pair_ancestor, tr.carrier_pair_body, tr.carrier_pair_child


# ---------------------------------------------------------------------------------- augmented
def augmented_bodies_in_body_axes(system: PlanarParameters) -> AugmentedBodies:
    """:func:`augmented_bodies` with ``static_moment`` in body-``k`` axes (configuration independent)."""
    tr = system.tree
    return AugmentedBodies(
        subtree_mass=subtree_mass(tr, system.body_mass),
        static_moment=static_moment(tr, system.body_mass, system.body_com, system.hinge_pos),
        augmented_inertia=augmented_moment_of_inertia(
            tr, system.body_mass, system.body_inertia, system.body_com, system.hinge_pos
        ),
    )


def augmented_bodies(system: PlanarParameters, q: Float[Array, " nq"]) -> AugmentedBodies:
    """Subsystem masses ``m_k``, static moments ``m̄_k`` (eq. 5) and ``J_k`` (eq. 6, planar) at ``q``.

    ``static_moment`` is in world axes (``m̄_k·i``, ``m̄_k·j`` as in table T-7c), as
    :func:`jaxbody.augmented_bodies` of a spatial model; in body-``k`` axes (configuration
    independent) see :func:`augmented_bodies_in_body_axes`.

    Returns:
        :class:`~jaxbody.augmented.AugmentedBodies` with ``augmented_inertia`` = ``J_k``, ``(n,)``.
    """
    kin = _kin(system, q)
    return AugmentedBodies(subtree_mass=kin.m_sub, static_moment=kin.mbar, augmented_inertia=kin.J)


# ---------------------------------------------------------------------------------- dynamics
def mass_matrix(system: PlanarParameters, q: Float[Array, " nq"]) -> Float[Array, "nv nv"]:
    """Mass matrix in absolute angles (docs/mathematics.md, "Corollary 6", from eqs 10–13).

    ``ℳ_kk = J_k``; ``ℳ_ki = ℳ_ik = R_{c(i,k)}·m̄_k`` for ``i`` a carrier of ``k``; zero when
    neither body carries the other. With a translating base the leading rows/columns are those of
    ``(ẍ, ÿ)``: ``ℳ_xx = ℳ_yy = M`` (total mass, base included), ``ℳ_x,k = -m̄_k·j``,
    ``ℳ_y,k = m̄_k·i``.

    Args:
        system: planar system.
        q: coordinates ``(x, y, q_1..q_n)`` or ``(q_1..q_n)``.

    Returns:
        Symmetric positive-definite ``(nv, nv)`` matrix.
    """
    kin = _kin(system, q)
    anc, body, child = _pairs(system)
    R = kin.link[index(child)]
    val = _dot2(R, kin.mbar[index(body)])
    Mt = jnp.diag(kin.J)
    if anc:
        Mt = Mt.at[index(body), index(anc)].add(val).at[index(anc), index(body)].add(val)
    if not system.translating_base:
        return Mt
    total = system.base_mass + jnp.sum(system.body_mass)
    Mbb = total * jnp.eye(2, dtype=Mt.dtype)
    Mbt = perp2(kin.mbar).T  # (2, n): rows (-m̄·j, m̄·i)
    return jnp.block([[Mbb, Mbt], [Mbt.T, Mt]])


def bias_forces(
    system: PlanarParameters, q: Float[Array, " nq"], v: Float[Array, " nv"]
) -> Float[Array, " nv"]:
    """Velocity-product and gravity terms ``h`` with ``ℳ q̈ + h = τ`` (docs/mathematics.md, "Corollary 6", eqs 10–13).

    ``h_k = Σ_{i∈C(k)} (R_{c(i,k)} × m̄_k) θ̇_i² − Σ_{i∈S(k), i≠k} (R_{c(k,i)} × m̄_i) θ̇_i²
    − m̄_k × g``; base rows ``−Σ_k m̄_k θ̇_k² − M g`` (eqs 10–11).
    """
    v = check_shape(v, (system.nv,), "v", "planar system")
    kin = _kin(system, q)
    n = system.n_body
    _, w = split_base(system, v)
    w2 = w * w
    anc, body, child = _pairs(system)
    h = -cross2(kin.mbar, system.gravity)
    if anc:
        cr = cross2(kin.link[index(child)], kin.mbar[index(body)])
        h = h + _segsum(cr * w2[index(anc)], body, n) - _segsum(cr * w2[index(body)], anc, n)
    if not system.translating_base:
        return h
    total = system.base_mass + jnp.sum(system.body_mass)
    hb = -jnp.sum(kin.mbar * w2[:, None], axis=0) - total * system.gravity
    return jnp.concatenate([hb, h])


def _loads(system, external_force, external_moment, dtype):
    n = system.n_body
    F = jnp.zeros((n, 2), dtype) if external_force is None else jnp.asarray(external_force)
    Mr = jnp.zeros((n,), dtype) if external_moment is None else jnp.asarray(external_moment)
    if F.shape != (n, 2):
        raise ValueError(f"planar system: external_force has shape {F.shape}, expected ({n}, 2)")
    if Mr.shape != (n,):
        raise ValueError(f"planar system: external_moment has shape {Mr.shape}, expected ({n},)")
    return F, Mr


def generalized_forces(
    system: PlanarParameters,
    q: Float[Array, " nq"],
    tau: Float[Array, " _nv"] | None = None,
    *,
    external_force: Float[Array, "_n_body 2"] | None = None,
    external_moment: Float[Array, " _n_body"] | None = None,
) -> Float[Array, " nv"]:
    """Right-hand sides of eqs (10)–(12): forces conjugate to ``(x, y, θ_1..θ_n)``.

    ``τ^abs_k = M_k − Σ_{j∈A(k)} M_j + M_rk + Σ_{j∈A(k)} k·(R_j × Σ_{i∈S(j)} F_ri)``; base rows
    ``F + Σ_i F_ri``.

    Args:
        system: planar system.
        q: coordinates.
        tau: drives ``(F_x, F_y, M_1..M_n)`` / ``(M_1..M_n)``; ``None`` = zero.
        external_force: ``F_rk`` (world axes), resultant external force on body ``k``, ``(n, 2)``.
        external_moment: ``M_rk``, moment of the external loads on body ``k`` about its hinge
            ``O_k`` (counter-clockwise), ``(n,)``. See :func:`point_load`.
    """
    if tau is not None:
        tau = check_shape(tau, (system.nv,), "tau", "planar system")
    F, Mr = _loads(system, external_force, external_moment, system.body_mass.dtype)
    kin = _kin(system, q)
    tr = system.tree
    tau = jnp.zeros((system.nv,), kin.theta.dtype) if tau is None else tau
    Fb, Mk = split_base(system, tau)
    Fsub = tr.subtree_sum(F)
    t_abs = Mk - tr.children_sum(Mk) + Mr + tr.children_sum(cross2(kin.link, Fsub))
    if not system.translating_base:
        return t_abs
    return jnp.concatenate([Fb + jnp.sum(F, axis=0), t_abs])


def forward_dynamics(
    system: PlanarParameters,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    tau: Float[Array, " _nv"] | None = None,
    *,
    external_force: Float[Array, "_n_body 2"] | None = None,
    external_moment: Float[Array, " _n_body"] | None = None,
) -> Float[Array, " nv"]:
    """Accelerations ``q̈ = ℳ⁻¹(τ − h)`` of eqs (10)–(13) (absolute angular accelerations)."""
    f = generalized_forces(system, q, tau, external_force=external_force, external_moment=external_moment)
    rhs = f - bias_forces(system, q, v)
    return solve_spd(mass_matrix(system, q), rhs)


def _force_factors(system, q, v, a, external_force=None, external_moment=None):
    """Statement 1 (:func:`jaxbody.spatial.relative_force_factors`) for the planar tree.

    The one Statement-1 kernel of the package, with planar vectors in the plane ``z = 0``,
    angular rates along ``k`` and the augmented inertia acting on ``k`` only (``J_k k kᵀ``):
    hinges have no relative pole motion (``V_r = W_r = 0``); the roots' base points move with
    the translating base (``W_0 = (ẍ, ÿ)``) or rest on the ground.
    """
    v = check_shape(v, (system.nv,), "v", "planar system")
    a = check_shape(a, (system.nv,), "a", "planar system")
    F, Mr = _loads(system, external_force, external_moment, system.body_mass.dtype)
    kin = _kin(system, q)
    n = system.n_body
    _, w = split_base(system, v)
    ab, e = split_base(system, a)
    W0 = jnp.broadcast_to(plane3(ab), (n, 3)) if system.translating_base else None
    kk = jnp.zeros((3, 3), kin.theta.dtype).at[2, 2].set(1.0)
    return relative_force_factors(
        system.tree,
        kin.m_sub,
        plane3(kin.mbar),
        kin.J[:, None, None] * kk,
        plane3(kin.link),
        axial3(w),
        axial3(e),
        None,
        None,
        W0,
        plane3(system.gravity),
        plane3(F),
        axial3(Mr),
    )


def inverse_dynamics(
    system: PlanarParameters,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    a: Float[Array, " _nv"],
    *,
    external_force: Float[Array, "_n_body 2"] | None = None,
    external_moment: Float[Array, " _n_body"] | None = None,
) -> Float[Array, " nv"]:
    """Drives that produce the accelerations ``a``, by Statement 1 (docs/mathematics.md, "Corollary 7", eqs 1–2).

    The drive torque ``M_k`` is the moment about the hinge that the base body of ``k`` exerts
    on ``k`` (a hinge's reaction has no moment about its own axis); with a translating base
    the leading entries are the force ``F`` on the base,
    ``F = m_base (W_0 − g) + Σ_{roots} F_k``. Returns the layout of ``tau`` in
    :func:`forward_dynamics`.
    """
    f = _force_factors(system, q, v, a, external_force, external_moment)
    torques = f.moment[:, 2]
    if not system.translating_base:
        return torques
    W0 = check_shape(a, (system.nv,), "a", "planar system")[:2]
    roots = index([k for k in range(system.n_body) if system.tree.parent[k] < 0])
    base = system.base_mass * (W0 - system.gravity) + jnp.sum(f.force[roots, :2], axis=0)
    return jnp.concatenate([base, torques])


def joint_reactions(
    system: PlanarParameters,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    a: Float[Array, " _nv"],
    *,
    external_force: Float[Array, "_n_body 2"] | None = None,
    external_moment: Float[Array, " _n_body"] | None = None,
) -> tuple[Float[Array, "n_body 2"], Float[Array, " n_body"]]:
    """``(force, moment)`` the base body of ``k`` exerts on body ``k`` at its hinge ``O_k``.

    Eq. (1) in the plane: ``F_k = m_k W_0k + F_ek − m_k g − Σ_{i∈S(k)} F_ri`` (world axes) and
    eq. (2): the moment about ``O_k`` (counter-clockwise), which for a hinge is the drive
    torque. The same convention as :func:`jaxbody.joint_reactions` of a spatial model, in the
    plane.
    """
    f = _force_factors(system, q, v, a, external_force, external_moment)
    return f.force[:, :2], f.moment[:, 2]


def root_force(
    system: PlanarParameters,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    a: Float[Array, " _nv"],
    *,
    external_force: Float[Array, "_n_body 2"] | None = None,
) -> Float[Array, "2"]:
    """Total force the ground (or the translating base) applies at the root hinges.

    Eqs (10)–(11) written for the bodies only (with ``ẍ = ÿ = 0`` on the fixed ground, docs/mathematics.md, "Corollary 6"):
    ``F = m W + Σ_i [θ̈_i k×m̄_i − θ̇_i² m̄_i] − m g − Σ_i F_ri``, ``m`` = mass of the bodies.
    """
    roots = [k for k in range(system.n_body) if system.tree.parent[k] < 0]
    force, _ = joint_reactions(system, q, v, a, external_force=external_force)
    return jnp.sum(force[index(roots)], axis=0)


# ---------------------------------------------------------------------------------- kinematics
def body_positions(
    system: PlanarParameters, q: Float[Array, " nq"]
) -> tuple[Float[Array, "n_body 2"], Float[Array, "n_body 2"]]:
    """World positions of the hinges ``O_k`` and of the centres of mass ``C_k``."""
    kin = _kin(system, q)
    base, _ = split_base(system, jnp.asarray(q))
    hinge = system.tree.path_sum(kin.link)
    if system.translating_base:
        hinge = hinge + base
    com = hinge + rot2(kin.theta, system.body_com)
    return hinge, com


def point_position(
    system: PlanarParameters, q: Float[Array, " nq"], body: int, point: ParamLike
) -> Float[Array, "2"]:
    """World position of a point fixed in ``body`` (given in its axes from its hinge)."""
    hinge, _ = body_positions(system, q)
    theta = absolute_angles(system, q)
    return hinge[body] + rot2(theta[body], jnp.asarray(point))


def point_load(
    system: PlanarParameters,
    q: Float[Array, " nq"],
    body: int,
    point: ParamLike,
    force: ParamLike,
) -> tuple[Float[Array, "n_body 2"], Float[Array, " n_body"]]:
    """External loads ``(F_r, M_r)`` of a force (world axes) applied at a point of ``body``.

    ``M_r`` is the moment about the body's hinge ``O_k`` (docs/mathematics.md, "Loads"), ready for
    :func:`generalized_forces`.
    """
    theta = absolute_angles(system, q)
    force = jnp.asarray(force)
    arm = rot2(theta[body], jnp.asarray(point))
    n = system.n_body
    F = jnp.zeros((n, 2), force.dtype).at[body].set(force)
    Mr = jnp.zeros((n,), force.dtype).at[body].set(cross2(arm, force))
    return F, Mr


def kinetic_energy(
    system: PlanarParameters, q: Float[Array, " nq"], v: Float[Array, " nv"]
) -> Float[Array, ""]:
    """``T = Σ_k (½ m_0k |v_Ck|² + ½ I_Ck θ̇_k²) + ½ m_base |v_base|²`` (body by body).

    Computed from the hinge and CM velocities, not from ``ℳ`` (``T = ½ vᵀℳv`` is a test).
    """
    v = check_shape(v, (system.nv,), "v", "planar system")
    kin = _kin(system, q)
    vb, w = split_base(system, v)
    parent = np.asarray(system.tree.parent)
    w_parent = jnp.where(jnp.asarray(parent >= 0), w[index(np.maximum(parent, 0))], 0.0)
    v_hinge = system.tree.path_sum(w_parent[:, None] * perp2(kin.link))
    if system.translating_base:
        v_hinge = v_hinge + vb
    v_com = v_hinge + w[:, None] * perp2(rot2(kin.theta, system.body_com))
    kk = jnp.zeros((3, 3), v_com.dtype).at[2, 2].set(1.0)
    T = rigid_body_kinetic_energy(
        system.body_mass, plane3(v_com), axial3(w), system.body_inertia[:, None, None] * kk
    )
    if system.translating_base:
        T = T + 0.5 * system.base_mass * jnp.sum(vb * vb)
    return T


def potential_energy(system: PlanarParameters, q: Float[Array, " nq"]) -> Float[Array, ""]:
    """Gravitational potential ``V = −Σ_k m_0k g·C_k − m_base g·(x, y)`` (world origin = 0)."""
    _, com = body_positions(system, q)
    V = -jnp.sum(system.body_mass * _dot2(com, system.gravity))
    if system.translating_base:
        V = V - system.base_mass * _dot2(jnp.asarray(q)[:2], system.gravity)
    return V


def total_energy(
    system: PlanarParameters, q: Float[Array, " nq"], v: Float[Array, " nv"]
) -> Float[Array, ""]:
    """``T + V``."""
    return kinetic_energy(system, q, v) + potential_energy(system, q)


def power(
    system: PlanarParameters,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    tau: Float[Array, " _nv"] | None = None,
    *,
    external_force: Float[Array, "_n_body 2"] | None = None,
    external_moment: Float[Array, " _n_body"] | None = None,
) -> Float[Array, ""]:
    """Power of the drives and external loads, ``τ^abs·v`` (= ``dE/dt`` along a motion)."""
    v = check_shape(v, (system.nv,), "v", "planar system")
    return jnp.dot(generalized_forces(system, q, tau, external_force=external_force, external_moment=external_moment), v)


