"""Planar systems with parallel hinge axes in absolute angles (spec §9–§10; [T] Cor. 5–8).

Planar systems: the system pytree, its builders and the converter from a spatial model.

A planar system is :class:`~jaxbody.tree.BodyTree` of rigid bodies hinged about axes
normal to the plane of motion. Every root body is hinged either to the fixed ground
(Cor. 6/7) or to a **translating base** of given mass that moves without rotating (Cor. 5).

Frames and angles
-----------------
* World axes: ``i`` horizontal, ``j`` vertical **up**, angles counter-clockwise (spec §9.1).
* Each body has body-fixed axes with origin at its own hinge ``O_k``. Its **absolute angle**
  ``θ_k`` is the angle from ``i`` to the body-fixed x-axis, counter-clockwise.
* The generalized coordinates are ``q = (x, y, q_1..q_n)`` with a translating base (``x, y``
  = base reference point) or ``q = (q_1..q_n)`` on the ground, where ``q_k = θ_k - angle_origin``.
  ``angle_origin`` (a static float) is the direction of the zero angle measured from ``i``:
  ``0`` for the horizontal convention of eqs (10)–(13) (:func:`from_parents`), ``-π/2`` for angles
  measured from the **downward vertical** as in eq. (14) and the reference tables T-1/T-2
  (:func:`chain`). Use :func:`vertical_to_horizontal` / :func:`horizontal_to_vertical` to convert.
* Velocities ``v = q̇`` (absolute angular rates ``θ̇_k``, base velocity).
* Drive/generalized forces ``tau`` have the layout of ``v``: ``(F_x, F_y, M_1..M_n)`` with a
  base (``F`` = force on the base) or ``(M_1..M_n)``; ``M_k`` is the drive torque that the base
  body of ``k`` (ground/base for roots) applies to body ``k`` about its hinge (spec §4).

Parameters (traced arrays, so ``jax.grad`` reaches them)
------------------------------------------------------
``body_mass`` ``m_0k``; ``body_com`` ``r_k`` in body-``k`` axes from ``O_k``; ``hinge_pos`` =
position of hinge ``k`` in the axes of its base body, measured from the base body's hinge (for a
root: in world axes from the world origin, or from the base reference point); ``body_inertia``
``I_Ck`` (central, about the hinge-axis direction); ``gravity`` (2-vector); ``base_mass``.

The augmented static moments ``m̄_k`` (eq. 5) and ``J_k`` (eq. 6, planar) are constants in body
axes, which is what makes the absolute-angle form cheap: the mass matrix (spec §9.3) is
``ℳ_kk = J_k``, ``ℳ_ki = R_{c(i,k)}·m̄_k`` for carrier pairs, computed as gathers and
scatters over the static carrier pairs (STYLE rule 6: the trace does not grow with ``n``).
"""

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._types import Array, ArrayLike, Float
from ..tree import BodyTree
from ..validation import validate_planar

ParamLike = ArrayLike | Sequence
"""Parameters given as arrays, scalars or (nested) sequences of numbers."""

__all__ = [
    "DOWNWARD_VERTICAL",
    "PlanarSystem",
    "from_parents",
    "chain",
    "from_model",
    "validate",
    "vertical_to_horizontal",
    "horizontal_to_vertical",
]

DOWNWARD_VERTICAL = -0.5 * math.pi
"""``angle_origin`` of angles measured from the downward vertical ``e_0`` (eq. 14)."""


class PlanarSystem(eqx.Module):
    """A planar tree of hinged bodies in absolute angles (spec §9; see the module docstring).

    Build it with :func:`from_parents`, :func:`chain` or :func:`from_model`, which validate the
    parameters. Implements the ``DynamicalSystem`` protocol itself (``nq``, ``nv``, ``qdot``,
    ``acceleration``, ``total_energy``, plus ``power``); those methods check no values, so
    they are safe inside a vmapped solver loop (validate once with :func:`jaxbody.check_inputs`).

    Attributes:
        tree: static topology; ``parent[k] = -1`` for bodies hinged to the ground/base.
        body_mass: ``m_0k``.
        body_com: ``r_k``, CM of body ``k`` in its own axes from its hinge ``O_k``.
        hinge_pos: hinge ``k`` in the axes of its base body from the base body's hinge
            (``R_k`` in body axes); roots: in world axes from the origin / base reference point.
        body_inertia: central moment of inertia ``I_Ck`` about the hinge-axis direction.
        gravity: gravity vector in the plane (world axes).
        base_mass: mass of the translating base (unused on the fixed ground).
        translating_base: Cor. 5 (``True``: coordinates ``(x, y, q_1..q_n)``) or Cor. 6.
        angle_origin: ``θ_k = q_k + angle_origin`` (``0``: from ``i``; ``-π/2``: from the
            downward vertical).
    """

    tree: BodyTree = eqx.field(static=True)
    body_mass: Float[Array, " n_body"]
    body_com: Float[Array, "n_body 2"]
    hinge_pos: Float[Array, "n_body 2"]
    body_inertia: Float[Array, " n_body"]
    gravity: Float[Array, "2"]
    base_mass: Float[Array, ""]
    translating_base: bool = eqx.field(static=True, default=False)
    angle_origin: float = eqx.field(static=True, default=0.0)

    @property
    def n_body(self) -> int:
        return self.tree.n_body

    @property
    def n_base(self) -> int:
        """Number of base coordinates (2 with a translating base, else 0)."""
        return 2 if self.translating_base else 0

    @property
    def nq(self) -> int:
        return self.n_base + self.tree.n_body

    @property
    def nv(self) -> int:
        return self.nq

    def qdot(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nq"]:
        """``q̇ = v`` (the velocities are the coordinate rates)."""
        return v

    def acceleration(
        self,
        t: ArrayLike,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, " nv"]:
        """Forward dynamics (eqs 10–13); ``tau`` = drives in the layout of ``v`` or ``None``."""
        # the dynamics module imports this one, hence the import here
        from .dynamics import forward_dynamics

        return forward_dynamics(self, q, v, tau)

    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        """Kinetic plus gravitational potential energy."""
        from .dynamics import total_energy

        return total_energy(self, q, v)

    def power(
        self,
        t: ArrayLike,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, ""]:
        """Power of the drives ``tau`` (so ``dE/dt = power`` along a motion)."""
        from .dynamics import power

        return power(self, q, v, tau)


# ---------------------------------------------------------------------------------- build
def _is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _xp(*values):
    """``jnp`` when any value is traced (building inside ``jit``/``grad``), else ``np``.

    Concrete parameters are assembled and validated in NumPy: eager JAX would compile every
    small operation of the builder.
    """
    return jnp if any(_is_traced(v) for v in values) else np


def _float_dtype(x):
    if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating):
        return jax.dtypes.canonicalize_dtype(x.dtype)
    return jax.dtypes.canonicalize_dtype(np.float64)


def _as_param(value, dtype, shape, field: str):
    if _is_traced(value):
        arr = value
    else:
        arr = np.asarray(value)
        if arr.dtype == object or not (
            np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.bool_)
        ):
            raise ValueError(f"planar system: {field} must be numeric, got {value!r}")
    if tuple(arr.shape) != tuple(shape):
        raise ValueError(
            f"planar system: {field} has shape {tuple(arr.shape)}, expected {tuple(shape)}"
        )
    return arr.astype(dtype)


def from_parents(
    parent: Sequence[int] | BodyTree,
    mass: ParamLike,
    com: ParamLike,
    hinge_pos: ParamLike,
    inertia: ParamLike,
    *,
    gravity: ParamLike = (0.0, -9.81),
    base_mass: ParamLike | None = None,
    names: Sequence[str] | None = None,
    angle_origin: float = 0.0,
) -> PlanarSystem:
    """Build a planar tree (spec §9.1–9.3; Cor. 5 with ``base_mass``, Cor. 6 without).

    Args:
        parent: base body of each body, ``-1`` for a body hinged to the ground/base;
            topological numbering (``parent[k] < k``). A :class:`~jaxbody.tree.BodyTree` is
            accepted too.
        mass: ``m_0k``, shape ``(n,)``.
        com: ``r_k``, the CM of body ``k`` in its own axes from its hinge, ``(n, 2)``.
        hinge_pos: position of hinge ``k`` in the axes of its base body from the base body's
            hinge (``R_k`` in body axes); for a root, in world axes from the world origin (ground)
            or from the base reference point (translating base). ``(n, 2)``.
        inertia: ``I_Ck``, central moment of inertia about the hinge-axis direction, ``(n,)``.
        gravity: gravity acceleration vector in the plane (default ``(0, -9.81)``; for a plane
            inclined at ``β`` use ``(0, -g sin β)``, spec Remark 2).
        base_mass: mass of a translating base (Cor. 5); ``None`` for the fixed ground.
        names: body names used in error messages.
        angle_origin: direction of ``q_k = 0`` from ``i`` (``θ_k = q_k + angle_origin``); ``0``
            here, ``-π/2`` for angles from the downward vertical.

    Returns:
        A validated :class:`PlanarSystem` (parameters in the dtype of ``mass`` when it is a
        floating array, else the default float dtype).

    Raises:
        ValueError: wrong shapes or lengths, NaN/inf, negative mass or inertia, a body whose
            subsystem has zero mass, a zero augmented moment of inertia, negative base mass
            (the message names the body and field). Value checks are skipped for traced inputs.
    """
    if isinstance(parent, BodyTree):
        tr = parent
        if names is not None and tuple(names) != tr.names:
            tr = BodyTree(list(tr.parent), names)
    else:
        tr = BodyTree(list(parent), names)
    n = tr.n_body
    if n == 0:
        raise ValueError("planar system: needs at least one body")
    dtype = _float_dtype(mass)
    params = dict(
        body_mass=_as_param(mass, dtype, (n,), "mass (body_mass)"),
        body_com=_as_param(com, dtype, (n, 2), "com (body_com)"),
        hinge_pos=_as_param(hinge_pos, dtype, (n, 2), "hinge_pos"),
        body_inertia=_as_param(inertia, dtype, (n,), "inertia (body_inertia)"),
        gravity=_as_param(gravity, dtype, (2,), "gravity"),
        base_mass=_as_param(0.0 if base_mass is None else base_mass, dtype, (), "base_mass"),
    )
    system = PlanarSystem(
        tree=tr,
        **{k: jnp.asarray(v) for k, v in params.items()},
        translating_base=base_mass is not None,
        angle_origin=float(angle_origin),
    )
    validate_planar(system)
    return system


def chain(
    mass: ParamLike,
    com_distance: ParamLike,
    length: ParamLike,
    inertia: ParamLike,
    *,
    gravity: ParamLike = 9.81,
    names: Sequence[str] | None = None,
) -> PlanarSystem:
    """The ``n``-link chain of Cor. 7, eq. (14), hinged to the ground at the world origin.

    Link ``k`` lies along its body x-axis: CM at distance ``a_k`` (``com_distance``) from hinge
    ``k``, hinge ``k+1`` at distance ``L_k`` (``length``). The coordinates ``q_k = α_k`` are the
    absolute angles of the links **from the downward vertical**, counter-clockwise (eq. 14, tables
    T-1/T-2); ``θ_k = α_k - π/2`` (``angle_origin = -π/2``).

    Args:
        mass: ``m_0k``, ``(n,)``.
        com_distance: ``a_k``, ``(n,)``.
        length: ``L_k`` for ``k = 1..n-1`` (``(n-1,)``); an ``(n,)`` array is accepted and its
            last entry (the length of the last link, which does not enter the dynamics) ignored.
        inertia: central ``I_Ck``, ``(n,)``.
        gravity: magnitude ``g`` of gravity, pointing down (``0`` for a horizontal plane).
        names: body names.

    Returns:
        A validated :class:`PlanarSystem`.

    Raises:
        ValueError: as :func:`from_parents`, and for a ``length`` of the wrong size.
    """
    dtype = _float_dtype(mass)
    xp = _xp(mass, com_distance, length, inertia, gravity)
    if np.ndim(mass) != 1:
        raise ValueError(
            f"planar chain: mass must be a 1-D array of link masses, got shape {np.shape(mass)}"
        )
    n = int(np.shape(mass)[0])
    a = _as_param(com_distance, dtype, (n,), "com_distance")
    L = length if _is_traced(length) else np.asarray(length)
    L = L.reshape(1) if L.ndim == 0 else L
    if tuple(L.shape) not in ((n - 1,), (n,)):
        raise ValueError(
            f"planar chain: length has shape {tuple(L.shape)}, expected ({n - 1},) (L_1..L_{n - 1})"
            f" or ({n},)"
        )
    L = L.astype(dtype)[: n - 1]
    g = _as_param(gravity, dtype, (), "gravity")
    zeros = xp.zeros((n,), dtype)
    com = xp.stack([a, zeros], axis=-1)
    hinge = xp.stack([xp.concatenate([xp.zeros((1,), dtype), L]), zeros], axis=-1)
    grav = xp.stack([xp.zeros((), dtype), -g])
    return from_parents(
        list(range(-1, n - 1)),
        mass,
        com,
        hinge,
        inertia,
        gravity=grav,
        names=names,
        angle_origin=DOWNWARD_VERTICAL,
    )


def validate(system: PlanarSystem) -> None:
    """Check the parameters on concrete values; raise ``ValueError`` naming body and field.

    Skipped (silently) for traced parameters, e.g. when a system is built inside ``jit``/``grad``.
    See :func:`jaxbody.validation.validate_planar`.
    """
    validate_planar(system)


# ---------------------------------------------------------------------------------- helpers
def vertical_to_horizontal(alpha: ArrayLike) -> Array:
    """``θ = α - π/2``: angle from the downward vertical (eq. 14) → angle from ``i`` (eq. 12)."""
    return jnp.asarray(alpha) - 0.5 * math.pi


def horizontal_to_vertical(theta: ArrayLike) -> Array:
    """``α = θ + π/2`` (``α_0k`` of spec §9.1): angle from ``i`` → angle from the downward vertical."""
    return jnp.asarray(theta) + 0.5 * math.pi




def plane_basis(normal, gravity) -> np.ndarray:
    """Rows ``(e_1, e_2)`` of the plane of motion normal to ``normal``, in world axes.

    ``e_2 = −g/|g|`` points up (any direction normal to ``normal`` when there is no gravity)
    and ``e_1 = e_2 × n``, so angles in the plane are counter-clockwise about ``n``. The one
    choice of axes used by :func:`from_model` and by scenes that run on the planar path.
    """
    n = np.asarray(normal, dtype=np.float64)
    g = np.asarray(gravity, dtype=np.float64)
    if np.linalg.norm(g) > 0:
        e2 = -g / np.linalg.norm(g)
    else:
        e2 = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
        e2 /= np.linalg.norm(e2)
    return np.stack([np.cross(e2, n), e2])


def from_model(model, *, atol: float = 1e-9) -> PlanarSystem:
    """The planar system of a spatial :class:`~jaxbody.Model` whose hinges are all parallel.

    Requirements (each failure names the body or joint): every body carries exactly one
    joint, a hinge; all hinge axes, in world axes at the reference pose ``qpos0``, point the
    same way ``n``; gravity lies in the plane normal to ``n``; no armature, damping or
    stiffness (a planar system has none).

    The plane gets the axes ``e_2 = −g/|g|`` (up; any direction normal to ``n`` without
    gravity) and ``e_1 = e_2 × n``, so angles are counter-clockwise about ``n``. Body ``k``'s
    planar axes coincide with ``(e_1, e_2)`` at ``qpos0``; its hinge ``O_k`` is its joint
    anchor; positions are projected on the plane (offsets along ``n`` do not enter the
    planar dynamics), and ``I_Ck`` is ``n·I_Ck n``.

    Coordinates: the joint angles of the model map to the absolute angles of the planar
    system by ``θ = jaxbody.planar.relative_to_absolute(system, q - model.qpos0)`` (and
    ``v`` likewise, without the offset); drives are the same hinge torques. So
    ``jaxbody.planar.joint_mass_matrix(system, θ)`` equals ``jaxbody.mass_matrix(model, q)``.

    Raises:
        ValueError: the model is not such a planar mechanism.
    """
    from ..joints import HINGE
    from ..kinematics import forward_kinematics

    joints, names = model.joints, model.body_names
    for k in range(model.n_body):
        count = joints.body_joint_count[k]
        if count != 1 or joints.type[joints.body_first_joint[k]] != HINGE:
            raise ValueError(
                f"planar.from_model: body {k} ({names[k]!r}) must carry exactly one hinge joint "
                f"(it has {count} joint(s)"
                + (f", the first a {['free', 'ball', 'slide', 'hinge'][joints.type[joints.body_first_joint[k]]]}" if count else "")
                + ")"
            )
    for field in ("dof_armature", "dof_damping", "joint_stiffness"):
        values = np.asarray(getattr(model, field))
        if np.any(values != 0):
            j = int(np.nonzero(values != 0)[0][0])
            raise ValueError(
                f"planar.from_model: joint {j} ({model.joint_names[j]!r}) has {field} "
                f"{float(values[j])}; a planar system has no armature, damping or stiffness"
            )
    kin = forward_kinematics(model, model.qpos0)
    rot = np.asarray(kin.body_rotation, dtype=np.float64)
    # the hinge axis of body k in world axes: the joint frame is the body frame at qpos0
    axes = np.einsum("nij,nj->ni", rot, np.asarray(model.joint_axis, dtype=np.float64))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    n = axes[0]
    for j in range(model.n_joint):
        if np.linalg.norm(np.cross(axes[j], n)) > atol or axes[j] @ n < 0:
            raise ValueError(
                f"planar.from_model: the axis of joint {j} ({model.joint_names[j]!r}) is "
                f"{axes[j].round(12).tolist()} in world axes, not {n.round(12).tolist()} like joint 0: "
                "all hinges must be parallel and point the same way"
            )
    g = np.asarray(model.gravity, dtype=np.float64)
    if abs(g @ n) > atol * max(1.0, np.linalg.norm(g)):
        raise ValueError(
            f"planar.from_model: gravity {g.tolist()} is not in the plane of motion (normal "
            f"{n.round(12).tolist()})"
        )
    P = plane_basis(n, g)  # world -> plane
    hinge = np.asarray(kin.base_point, dtype=np.float64)
    com = np.asarray(kin.com, dtype=np.float64)
    par = model.tree.parent_array
    rel = hinge - np.where(par[:, None] >= 0, hinge[np.maximum(par, 0)], 0.0)
    inertia = np.einsum("i,nij,j->n", n, np.asarray(kin.central_inertia, dtype=np.float64), n)
    dtype = model.body_mass.dtype
    return from_parents(
        model.tree.parent,
        np.asarray(model.body_mass, dtype=np.float64).astype(dtype),
        ((com - hinge) @ P.T).astype(dtype),
        (rel @ P.T).astype(dtype),
        inertia.astype(dtype),
        gravity=(P @ g).astype(dtype),
        names=names,
    )
