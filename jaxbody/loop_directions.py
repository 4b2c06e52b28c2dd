"""Which directions a loop closure constrains, and configurations that close the loops.

A loop closure keeps a point of one body on a point of another (:class:`jaxbody.loops.LoopSpec`).
Its rows are the gap ``g(q) = R_fᵀ (p_a(q) − p_b(q))`` expressed in the frame of a reference
body ``f`` — the lowest common ancestor of the two bodies (the world when they share none) —
along some directions of that frame. Only the directions in which the loop can open at all may
be constrained (a planar four-bar: the two in-plane ones), otherwise the set is redundant.

Why the common ancestor's frame: the motion of the joints above it moves both points alike,
so at a closed configuration the gap's rate depends only on the joints of the loop itself; in
that frame the directions a planar loop cannot open along are fixed (across the plane of its
hinges), while in the world frame they turn with a floating base or a hip joint.

The directions are found numerically, with no program compiled per loop:

1. a configuration where every loop is closed (:func:`close_loops`: Newton's method with
   minimum-norm steps from ``qpos0`` or a keyframe, on the rotation group for quaternions);
2. there, the 3 × nv velocity Jacobian of each loop's gap in its frame (from one evaluation of
   the frames, :func:`gap_jacobians`, or from MuJoCo's ``mj_jac`` in the MJCF importer);
3. :func:`loop_rows`: per loop, the left singular vectors with non-negligible singular values
   (the frame's axes when they span them); then across loops, in order, a rank-revealing test
   that drops a row that depends on the rows kept before it (two loops closing the same
   mechanism), with a report naming every dropped row and why.

:func:`point_gap` and :func:`point_gap_velocity` are the rows of
:class:`jaxbody.constraints.LoopClosure`, :func:`gap_velocity_bias` their rate's part that the
joint accelerations do not carry.
"""

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, Float
from .kinematics import body_accelerations, forward_kinematics
from .shared_evaluation import shared

__all__ = [
    "loop_frame",
    "point_gap",
    "point_gap_velocity",
    "gap_and_jacobian",
    "gap_velocity_bias",
    "gap_jacobians",
    "close_loops",
    "loop_rows",
    "LoopRows",
    "CLOSED_ATOL",
]

#: A loop counts as closed when every gap component is at most this (model length units).
CLOSED_ATOL = 1e-9


def loop_frame(parent: Sequence[int], body_a: int, body_b: int) -> int:
    """The lowest common ancestor of two bodies (``-1``: the world), the loop's reference frame."""
    def chain(b):
        out = []
        while b >= 0:
            out.append(b)
            b = parent[b]
        return out

    above_a = set(chain(body_a))
    for b in chain(body_b):
        if b in above_a:
            return b
    return -1


def _point_and_jacobian(model, kin, body: int, point):
    """World position of a body point and its velocity Jacobian ``(3, nv)`` (columns
    ``s_d + ω_d × (X − a_d)`` over the DoFs that carry the body; zero for the world)."""
    dtype = kin.body_position.dtype
    if body < 0:
        return jnp.asarray(point, dtype), jnp.zeros((3, model.nv), dtype)
    X = kin.body_position[body] + kin.body_rotation[body] @ jnp.asarray(point, dtype)
    # static 0/1 mask of the DoFs carrying the body: a product, no gather over bodies
    carries = np.asarray(model.tree.subtree_mask[np.asarray(model.joints.dof_body, int), body], float)
    cols = (kin.dof_linear + jnp.cross(kin.dof_angular, X - kin.dof_anchor)) * jnp.asarray(carries, dtype)[:, None]
    return X, cols.T


@shared  # a loop's rows and their Jacobian from one evaluation within a vector field's
def gap_and_jacobian(model, q, body_a: int, point_a, body_b: int, point_b, frame: int = -1):
    """``(φ, G)``: the gap ``φ = R_fᵀ (p_a − p_b)`` of two body points in the frame of body
    ``frame`` (``-1``: world axes) and its exact velocity Jacobian ``G = ∂φ̇/∂v``, from one
    evaluation of the frames.

    With ``g = p_a − p_b`` and the frame's angular velocity ``ω_f = J_ω v``,
    ``φ̇ = R_fᵀ (ġ − ω_f × g)``, so ``G = R_fᵀ (J_a − J_b + [g]× J_ω)``, ``J_a``, ``J_b`` the
    point Jacobians (columns ``s_d + ω_d × (X − a_d)``). Closed form: no automatic
    differentiation of the kinematics, which a solve would otherwise repeat at every evaluation.
    """
    nv = model.nv
    if body_a < 0 and body_b < 0 and frame < 0:
        dtype = jnp.asarray(q).dtype
        return jnp.asarray(point_a, dtype) - jnp.asarray(point_b, dtype), jnp.zeros((3, nv), dtype)
    kin = forward_kinematics(model, q)
    xa, ja = _point_and_jacobian(model, kin, body_a, point_a)
    xb, jb = _point_and_jacobian(model, kin, body_b, point_b)
    g, J = xa - xb, ja - jb
    if frame < 0:
        return g, J
    carries = np.asarray(model.tree.subtree_mask[np.asarray(model.joints.dof_body, int), frame], float)
    J_w = (kin.dof_angular * jnp.asarray(carries, g.dtype)[:, None]).T  # (3, nv)
    R = kin.body_rotation[frame]
    return R.T @ g, R.T @ (J + jnp.cross(g[:, None], J_w, axis=0))


def point_gap(model, q, body_a: int, point_a, body_b: int, point_b, frame: int = -1) -> Float[Array, " 3"]:
    """``R_fᵀ (p_a(q) − p_b(q))``: the gap of two body points (``-1``: the world) in the frame of
    body ``frame`` (``-1``: world axes), the frames computed once."""
    if body_a < 0 and body_b < 0 and frame < 0:
        return jnp.asarray(point_a, q.dtype) - jnp.asarray(point_b, q.dtype)
    kin = forward_kinematics(model, q)

    def at(body, point):
        if body < 0:
            return jnp.asarray(point, q.dtype)
        return kin.body_position[body] + kin.body_rotation[body] @ point

    gap = at(body_a, point_a) - at(body_b, point_b)
    return gap if frame < 0 else kin.body_rotation[frame].T @ gap


def _point_motion(kin, motion, body: int, point):
    """Position, velocity and acceleration of a point fixed in ``body`` (``-1``: the world)
    from the bodies' motion (:func:`jaxbody.kinematics.body_accelerations`)."""
    dtype = kin.body_position.dtype
    if body < 0:
        zero = jnp.zeros((3,), dtype)
        return jnp.asarray(point, dtype), zero, zero
    X = kin.body_position[body] + kin.body_rotation[body] @ jnp.asarray(point, dtype)
    d = X - motion.reference_point[body]
    w = motion.angular_velocity[body]
    velocity = motion.velocity[body] + jnp.cross(w, d)
    acceleration = (motion.acceleration[body] + jnp.cross(motion.angular_acceleration[body], d)
                    + jnp.cross(w, motion.velocity[body] + jnp.cross(w, d)))
    return X, velocity, acceleration


@shared
def _velocity_product_motion(model, kin, v):
    """The bodies' motion at joint rates ``v`` and zero joint accelerations: one pass for every
    loop of a model (shared within a vector field's evaluation)."""
    return body_accelerations(model, kin, v, jnp.zeros_like(v))


def gap_velocity_bias(model, q, v, body_a: int, point_a, body_b: int, point_b, frame: int = -1) -> Float[Array, " 3"]:
    """``Ġ v``: the second derivative of :func:`point_gap` along ``q̇ = qpos_rate(q, v)`` at
    zero joint accelerations, so that ``φ̈ = G v̇ + Ġ v`` (the constraint rows' ``γ``).

    Closed form from one pass of the bodies' velocities and accelerations (MuJoCo's
    ``cdof_dot`` recursion, :func:`jaxbody.kinematics.body_accelerations` with ``v̇ = 0``):
    with ``g = p_a − p_b``, the frame's rotation ``R_f`` and angular velocity ``ω_f``,
    ``φ = R_fᵀ g`` gives ``φ̈ = R_fᵀ (g̈ − ω̇_f × g − 2 ω_f × ġ + ω_f × (ω_f × g))``. Differentiating
    the kinematics in forward mode gives the same numbers with about one and a half times the
    compile and run time of a biped's constrained vector field.
    """
    dtype = jnp.asarray(q).dtype
    if body_a < 0 and body_b < 0 and frame < 0:
        return jnp.zeros((3,), dtype)
    kin = forward_kinematics(model, q)
    v = jnp.asarray(v)
    motion = _velocity_product_motion(model, kin, v)
    xa, va, aa = _point_motion(kin, motion, body_a, point_a)
    xb, vb, ab = _point_motion(kin, motion, body_b, point_b)
    g, g_dot, g_ddot = xa - xb, va - vb, aa - ab
    if frame < 0:
        return g_ddot
    w, w_dot = motion.angular_velocity[frame], motion.angular_acceleration[frame]
    R = kin.body_rotation[frame]
    return R.T @ (g_ddot - jnp.cross(w_dot, g) - 2.0 * jnp.cross(w, g_dot) + jnp.cross(w, jnp.cross(w, g)))


def point_gap_velocity(model, q, v, body_a: int, point_a, body_b: int, point_b, frame: int = -1) -> Float[Array, " 3"]:
    """``d/dt`` of :func:`point_gap` along ``q̇ = qpos_rate(q, v)`` (linear in ``v``):
    ``G v`` of :func:`gap_and_jacobian`."""
    return gap_and_jacobian(model, q, body_a, point_a, body_b, point_b, frame)[1] @ v


def gap_jacobians(model, loops, q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(gaps, jacobians, rotations)`` of the loops at ``q``, in NumPy (float64): the world
    gaps ``p_a − p_b`` ``(L, 3)``, their velocity Jacobians ``∂ṗ/∂v`` ``(L, 3, nv)`` (world) and
    the rotation of each loop's reference frame ``(L, 3, 3)``.

    One evaluation of the frames (a program compiled once per model structure, shared by every
    loop); each Jacobian column is the point velocity of a unit DoF rate,
    ``s_d + ω_d × (X − a_d)``, over the DoFs that carry the point.
    """
    kin = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), forward_kinematics(model, q))
    joints = model.joints
    carries = model.tree.subtree_mask  # [k, i]: body i belongs to the subtree of k
    dof_body = np.asarray(joints.dof_body, int)
    nv = model.nv

    def point_and_jacobian(body, point):
        if body < 0:
            return np.asarray(point, np.float64), np.zeros((3, nv))
        X = kin.body_position[body] + kin.body_rotation[body] @ np.asarray(point, np.float64)
        cols = kin.dof_linear + np.cross(kin.dof_angular, X - kin.dof_anchor)  # (nv, 3)
        cols = cols * carries[dof_body, body][:, None]
        return X, cols.T

    gaps, jacs, rots = [], [], []
    for spec in loops:
        xa, ja = point_and_jacobian(spec.body_a, spec.point_a)
        xb, jb = point_and_jacobian(spec.body_b, spec.point_b)
        f = loop_frame(model.tree.parent, spec.body_a, spec.body_b) if spec.frame is None else spec.frame
        gaps.append(xa - xb)
        jacs.append(ja - jb)
        rots.append(np.eye(3) if f < 0 else kin.body_rotation[f])
    return np.asarray(gaps).reshape(-1, 3), np.asarray(jacs).reshape(-1, 3, nv), np.asarray(rots).reshape(-1, 3, 3)


def close_loops(
    q,
    gaps_and_jacobians: Callable,
    integrate: Callable,
    *,
    atol: float = CLOSED_ATOL,
    iterations: int = 30,
    what: str = "qpos0",
    labels: Sequence[str] = (),
) -> np.ndarray:
    """A configuration near ``q`` that closes every loop: Newton's method with minimum-norm
    steps on the stacked world gaps, ``Δv = −J⁺ g`` (least squares, so that a loop whose gap
    cannot move in some direction is no obstacle), ``q ← integrate(q, Δv)`` (on the rotation
    group for quaternions). ``q`` itself when it closes them already.

    Args:
        gaps_and_jacobians: ``q -> (gaps (L, 3), jacobians (L, 3, nv))`` (world frame).
        integrate: ``(q, dv) -> q`` advancing ``q`` by the velocity ``dv`` for unit time.

    Raises:
        ValueError: the iterations do not close the loops (naming the loops still open and
            their gaps): the loops cannot be closed near ``q``.
    """
    q = np.asarray(q, np.float64)
    for _ in range(iterations + 1):
        g, J = gaps_and_jacobians(q)
        if np.max(np.abs(g), initial=0.0) <= atol:
            return q
        dv = -np.linalg.lstsq(J.reshape(-1, J.shape[-1]), g.reshape(-1), rcond=None)[0]
        q = np.asarray(integrate(q, dv), np.float64)
    g, _ = gaps_and_jacobians(q)
    open_ = [f"{labels[i] if i < len(labels) else i!r} (gap {np.linalg.norm(g[i]):.3g})"
             for i in range(len(g)) if np.max(np.abs(g[i])) > atol]
    raise ValueError(
        f"the loops {', '.join(open_)} do not close near {what}: {iterations} Newton steps left them "
        "open; give a configuration that closes them (a keyframe) or check the loop's anchor points"
    )


class LoopRows:
    """The rows :func:`loop_rows` keeps: ``axes[i]`` ``(k_i, 3)`` (unit directions in loop
    ``i``'s frame) and ``dropped[i]``, one sentence per dropped direction saying why."""

    def __init__(self, axes, dropped):
        self.axes, self.dropped = axes, dropped


def _fmt(v) -> str:
    return "(" + ", ".join(f"{0.0 if abs(x) < 5e-13 else x:.6g}" for x in v) + ")"


def loop_rows(jacobians, labels: Sequence[str], frame_names: Sequence[str], *, rtol: float = 1e-9) -> LoopRows:
    """Independent rows of loops from their gap Jacobians in their frames ``(L, 3, nv)`` at a
    configuration that closes them.

    Per loop, the span of the left singular vectors of its Jacobian with singular values above
    ``rtol`` times the largest (the frame's axes when they span it, so each reaction is a force
    component along an axis of the frame); then, in loop order, each kept row is tested against
    the rows kept before it by the smallest singular value of the stack (relative to the largest
    row norm), and dropped when it depends on them.

    Raises:
        ValueError: a loop whose two points move together (its Jacobian vanishes): it constrains
            nothing.
    """
    J = np.asarray(jacobians, np.float64)
    axes, dropped = [], []
    for i, Ji in enumerate(J):
        U = np.linalg.svd(Ji)[0]
        S = np.zeros(3)
        sv = np.linalg.svd(Ji, compute_uv=False)
        S[:len(sv)] = sv
        if not S[0] > 0:
            raise ValueError(f"loop {labels[i]!r}: its two points move together; it constrains nothing")
        keep = S > rtol * S[0]
        basis = U[:, keep]
        inside = [k for k in range(3) if np.linalg.norm(basis[k]) > 1.0 - 1e-9]
        if len(inside) == basis.shape[1]:
            ax, drop = np.eye(3)[inside], np.eye(3)[[k for k in range(3) if k not in inside]]
        else:
            ax, drop = basis.T, U[:, ~keep].T
        axes.append(ax)
        dropped.append([
            f"along {_fmt(d)} in the frame of {frame_names[i]}: the loop cannot open in that direction "
            f"(singular value {s:.2g} of {S[0]:.3g})"
            for d, s in zip(drop, S[~keep])
        ])
    # across loops: the rows of one loop may repeat those of another (two loops closing the
    # same mechanism), which only the stack of all rows shows
    rows = [(i, a, a @ J[i]) for i, ax in enumerate(axes) for a in ax]
    scale = max(max((np.linalg.norm(r) for _, _, r in rows), default=0.0), np.finfo(np.float64).tiny)
    kept: list[np.ndarray] = []
    final = [[] for _ in axes]
    names = []
    for i, a, r in rows:
        trial = np.stack([*kept, r])
        sv = np.linalg.svd(trial, compute_uv=False)
        # more rows than velocities, or a vanishing singular value: the row depends on the kept ones
        if len(sv) < len(trial) or sv[-1] <= rtol * scale * max(1.0, np.sqrt(J.shape[-1])):
            coef = np.linalg.lstsq(np.stack(kept).T, r, rcond=None)[0] if kept else np.zeros(0)
            deps = sorted({names[j] for j, c in enumerate(coef) if abs(c) > 1e-9})
            dropped[i].append(f"along {_fmt(a)} in the frame of {frame_names[i]}: it depends on the rows "
                              f"kept before it ({', '.join(deps) or 'none'}) at the reference configuration")
            continue
        kept.append(r)
        final[i].append(a)
        names.append(f"{labels[i]}[{len(final[i]) - 1}]")
    # a loop left with no row repeats the others entirely: it is kept with none (its report says so)
    return LoopRows([np.asarray(f).reshape(-1, 3) for f in final], [tuple(d) for d in dropped])
