"""Planar systems with parallel hinge axes in absolute angles (spec §9–§10; [T] Cor. 5–8).

A planar system is a :class:`~jaxbody.tree.BodyTree` of rigid bodies hinged about axes
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
  ``0`` for the horizontal convention of eqs (10)–(13) (:func:`tree`), ``-π/2`` for angles
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
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Float
from .augmented import (
    AugmentedBodies,
    augmented_moment_of_inertia,
    static_moment,
    subtree_mass,
)
from .linalg import solve_spd
from .tree import BodyTree

ParamLike = ArrayLike | Sequence
"""Parameters given as arrays, scalars or (nested) sequences of numbers."""

__all__ = [
    "DOWNWARD_VERTICAL",
    "PlanarSystem",
    "tree",
    "chain",
    "validate",
    "vertical_to_horizontal",
    "horizontal_to_vertical",
    "absolute_angles",
    "augmented_bodies",
    "mass_matrix",
    "bias_forces",
    "generalized_forces",
    "forward_dynamics",
    "inverse_dynamics",
    "joint_forces",
    "root_force",
    "body_positions",
    "point_position",
    "point_load",
    "kinetic_energy",
    "potential_energy",
    "total_energy",
    "power",
    "absolute_to_relative",
    "relative_to_absolute",
    "joint_mass_matrix",
    "joint_bias_forces",
    "DecouplingReport",
    "decoupling_report",
]

DOWNWARD_VERTICAL = -0.5 * math.pi
"""``angle_origin`` of angles measured from the downward vertical ``e_0`` (eq. 14)."""


class PlanarSystem(eqx.Module):
    """A planar tree of hinged bodies in absolute angles (spec §9; see the module docstring).

    Build it with :func:`tree` or :func:`chain`, which validate the parameters.
    Implements the simulation protocol: ``nq``, ``nv``, ``qdot``, ``acceleration``,
    ``total_energy``, ``power``.

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
        return forward_dynamics(self, q, v, tau)

    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        """Kinetic plus gravitational potential energy."""
        return total_energy(self, q, v)

    def power(
        self,
        t: ArrayLike,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, ""]:
        """Power of the drives ``tau`` (so ``dE/dt = power`` along a motion)."""
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


def tree(
    parent: Sequence[int] | BodyTree,
    mass: ParamLike,
    com: ParamLike,
    hinge_pos: ParamLike,
    inertia: ParamLike,
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
    if not any(_is_traced(x) for x in params.values()):
        _validate_values(tr, **params)
    return PlanarSystem(
        tree=tr,
        **{k: jnp.asarray(v) for k, v in params.items()},
        translating_base=base_mass is not None,
        angle_origin=float(angle_origin),
    )


def chain(
    mass: ParamLike,
    com_distance: ParamLike,
    length: ParamLike,
    inertia: ParamLike,
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
        ValueError: as :func:`tree`, and for a ``length`` of the wrong size.
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
    return tree(
        list(range(-1, n - 1)),
        mass,
        com,
        hinge,
        inertia,
        gravity=grav,
        names=names,
        angle_origin=DOWNWARD_VERTICAL,
    )


def _validate_values(tr: BodyTree, body_mass, body_com, hinge_pos, body_inertia, gravity, base_mass):
    names = tr.names
    fields = {
        "body_mass": body_mass, "body_com": body_com, "hinge_pos": hinge_pos,
        "body_inertia": body_inertia,
    }
    arrays = {}
    for field, value in fields.items():
        a = np.asarray(value, dtype=np.float64)
        bad = ~np.isfinite(a)
        if bad.any():
            k = int(np.argwhere(bad)[0][0])
            raise ValueError(f"planar body {k} ({names[k]!r}): {field} is not finite (NaN or inf)")
        arrays[field] = a
    for field, value in (("gravity", gravity), ("base_mass", base_mass)):
        if not np.all(np.isfinite(np.asarray(value, dtype=np.float64))):
            raise ValueError(f"planar system: {field} is not finite (NaN or inf)")
    mass, inertia = arrays["body_mass"], arrays["body_inertia"]
    for k in range(tr.n_body):
        if mass[k] < 0:
            raise ValueError(f"planar body {k} ({names[k]!r}): body_mass is negative ({mass[k]})")
    for k in range(tr.n_body):
        if inertia[k] < 0:
            raise ValueError(
                f"planar body {k} ({names[k]!r}): body_inertia is negative ({inertia[k]})"
            )
    sub = tr.subtree_mask.astype(np.float64) @ mass
    for k in range(tr.n_body):
        if not sub[k] > 0:
            raise ValueError(
                f"planar body {k} ({names[k]!r}): body_mass of its subsystem is zero; "
                "a moving body needs positive total mass"
            )
    # eq. (6), planar: J_k = I_Ck + m_0k |r_k|² + Σ_{j∈A(k)} m_j |R_j|²
    J = inertia + mass * np.sum(arrays["body_com"] ** 2, axis=-1)
    for j in range(tr.n_body):
        p = tr.parent[j]
        if p >= 0:
            J[p] += sub[j] * np.sum(arrays["hinge_pos"][j] ** 2)
    for k in range(tr.n_body):
        if not J[k] > 0:
            raise ValueError(
                f"planar body {k} ({names[k]!r}): body_inertia gives a zero augmented moment of "
                "inertia J_k (all of its mass on its hinge axis); the mass matrix would be singular"
            )
    base = float(np.asarray(base_mass))
    if base < 0:
        raise ValueError(f"planar system: base_mass is negative ({base})")


def validate(system: PlanarSystem) -> None:
    """Check the parameters on concrete values; raise ``ValueError`` naming body and field.

    Skipped (silently) for traced parameters, e.g. when a system is built inside ``jit``/``grad``.
    """
    params = dict(
        body_mass=system.body_mass, body_com=system.body_com, hinge_pos=system.hinge_pos,
        body_inertia=system.body_inertia, gravity=system.gravity, base_mass=system.base_mass,
    )
    if any(_is_traced(x) for x in params.values()):
        return
    _validate_values(system.tree, **params)


# ---------------------------------------------------------------------------------- helpers
def vertical_to_horizontal(alpha: ArrayLike) -> Array:
    """``θ = α - π/2``: angle from the downward vertical (eq. 14) → angle from ``i`` (eq. 12)."""
    return jnp.asarray(alpha) - 0.5 * math.pi


def horizontal_to_vertical(theta: ArrayLike) -> Array:
    """``α = θ + π/2`` (``α_0k`` of spec §9.1): angle from ``i`` → angle from the downward vertical."""
    return jnp.asarray(theta) + 0.5 * math.pi


def _rot(theta, v):
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _perp(v):
    """``k × v``."""
    return jnp.stack([-v[..., 1], v[..., 0]], axis=-1)


def _cross(a, b):
    """``k · (a × b)`` for planar vectors."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def _idx(values) -> Array:
    return jnp.asarray(np.asarray(values, dtype=np.int32).reshape(-1))


def _segsum(x, ids, n):
    return jax.ops.segment_sum(x, _idx(ids), num_segments=n)


def _check_vec(x, n: int, what: str) -> Array:
    x = jnp.asarray(x)
    if x.shape != (n,):
        raise ValueError(f"planar system: {what} has shape {tuple(x.shape)}, expected ({n},)")
    return x


def _split(system: PlanarSystem, x):
    nb = system.n_base
    return x[:nb], x[nb:]


def absolute_angles(system: PlanarSystem, q: Float[Array, " nq"]) -> Float[Array, " n_body"]:
    """``θ_k = q_k + angle_origin``: absolute angles from ``i`` (spec §9.1)."""
    q = _check_vec(q, system.nq, "q")
    return _split(system, q)[1] + system.angle_origin


class _Kin(NamedTuple):
    theta: Array  # (n,) absolute angles from i
    mbar: Array  # (n, 2) static moments of the augmented bodies, world axes (eq. 5)
    link: Array  # (n, 2) R_k in world axes (root: its hinge position in world/base axes)
    J: Array  # (n,) augmented moments of inertia (eq. 6, planar)
    m_sub: Array  # (n,) subsystem masses


def _kin(system: PlanarSystem, q) -> _Kin:
    tr = system.tree
    theta = absolute_angles(system, q)
    m_sub = subtree_mass(tr, system.body_mass)
    mbar_body = static_moment(tr, system.body_mass, system.body_com, system.hinge_pos)
    J = augmented_moment_of_inertia(
        tr, system.body_mass, system.body_inertia, system.body_com, system.hinge_pos
    )
    parent = np.asarray(tr.parent)
    theta_parent = theta[_idx(np.maximum(parent, 0))]
    link = jnp.where(
        jnp.asarray(parent < 0)[:, None], system.hinge_pos, _rot(theta_parent, system.hinge_pos)
    )
    return _Kin(theta, _rot(theta, mbar_body), link, J, m_sub)


def _pairs(system: PlanarSystem):
    tr = system.tree
    return tr.carrier_pair_ancestor, tr.carrier_pair_body, tr.carrier_pair_child


# ---------------------------------------------------------------------------------- augmented
def augmented_bodies(system: PlanarSystem, q: Float[Array, " nq"] | None = None) -> AugmentedBodies:
    """Subsystem masses ``m_k``, static moments ``m̄_k`` (eq. 5) and ``J_k`` (eq. 6, planar).

    Args:
        system: planar system.
        q: configuration; if given, ``static_moment`` is in world axes (``m̄_k·i``, ``m̄_k·j`` as in
            table T-7c), otherwise in body-``k`` axes (configuration independent).

    Returns:
        :class:`~jaxbody.augmented.AugmentedBodies` with ``augmented_inertia`` = ``J_k``, ``(n,)``.
    """
    tr = system.tree
    mbar = static_moment(tr, system.body_mass, system.body_com, system.hinge_pos)
    if q is not None:
        mbar = _rot(absolute_angles(system, q), mbar)
    return AugmentedBodies(
        subtree_mass=subtree_mass(tr, system.body_mass),
        static_moment=mbar,
        augmented_inertia=augmented_moment_of_inertia(
            tr, system.body_mass, system.body_inertia, system.body_com, system.hinge_pos
        ),
    )


# ---------------------------------------------------------------------------------- dynamics
def mass_matrix(system: PlanarSystem, q: Float[Array, " nq"]) -> Float[Array, "nv nv"]:
    """Mass matrix in absolute angles (spec §9.3, from eqs 10–13).

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
    R = kin.link[_idx(child)]
    val = _dot(R, kin.mbar[_idx(body)])
    Mt = jnp.diag(kin.J)
    if anc:
        Mt = Mt.at[_idx(body), _idx(anc)].add(val).at[_idx(anc), _idx(body)].add(val)
    if not system.translating_base:
        return Mt
    total = system.base_mass + jnp.sum(system.body_mass)
    Mbb = total * jnp.eye(2, dtype=Mt.dtype)
    Mbt = _perp(kin.mbar).T  # (2, n): rows (-m̄·j, m̄·i)
    return jnp.block([[Mbb, Mbt], [Mbt.T, Mt]])


def bias_forces(
    system: PlanarSystem, q: Float[Array, " nq"], v: Float[Array, " nv"]
) -> Float[Array, " nv"]:
    """Velocity-product and gravity terms ``h`` with ``ℳ q̈ + h = τ`` (spec §9.3, eqs 10–13).

    ``h_k = Σ_{i∈C(k)} (R_{c(i,k)} × m̄_k) θ̇_i² − Σ_{i∈S(k), i≠k} (R_{c(k,i)} × m̄_i) θ̇_i²
    − m̄_k × g``; base rows ``−Σ_k m̄_k θ̇_k² − M g`` (eqs 10–11).
    """
    v = _check_vec(v, system.nv, "v")
    kin = _kin(system, q)
    n = system.n_body
    _, w = _split(system, v)
    w2 = w * w
    anc, body, child = _pairs(system)
    h = -_cross(kin.mbar, system.gravity)
    if anc:
        cr = _cross(kin.link[_idx(child)], kin.mbar[_idx(body)])
        h = h + _segsum(cr * w2[_idx(anc)], body, n) - _segsum(cr * w2[_idx(body)], anc, n)
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
    system: PlanarSystem,
    q: Float[Array, " nq"],
    tau: Float[Array, " _nv"] | None = None,
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
        tau = _check_vec(tau, system.nv, "tau")
    F, Mr = _loads(system, external_force, external_moment, system.body_mass.dtype)
    kin = _kin(system, q)
    tr = system.tree
    tau = jnp.zeros((system.nv,), kin.theta.dtype) if tau is None else tau
    Fb, Mk = _split(system, tau)
    Fsub = tr.subtree_sum(F)
    t_abs = Mk - tr.children_sum(Mk) + Mr + tr.children_sum(_cross(kin.link, Fsub))
    if not system.translating_base:
        return t_abs
    return jnp.concatenate([Fb + jnp.sum(F, axis=0), t_abs])


def forward_dynamics(
    system: PlanarSystem,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    tau: Float[Array, " _nv"] | None = None,
    external_force: Float[Array, "_n_body 2"] | None = None,
    external_moment: Float[Array, " _n_body"] | None = None,
) -> Float[Array, " nv"]:
    """Accelerations ``q̈ = ℳ⁻¹(τ − h)`` of eqs (10)–(13) (absolute angular accelerations)."""
    f = generalized_forces(system, q, tau, external_force, external_moment)
    rhs = f - bias_forces(system, q, v)
    return solve_spd(mass_matrix(system, q), rhs)


def inverse_dynamics(
    system: PlanarSystem,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    a: Float[Array, " _nv"],
    external_force: Float[Array, "_n_body 2"] | None = None,
    external_moment: Float[Array, " _n_body"] | None = None,
) -> Float[Array, " nv"]:
    """Drives that produce the accelerations ``a`` (spec §9.4).

    Computes ``u = ℳa + h − (external part of τ)`` (so ``u_k = M_k − Σ_{j∈A(k)} M_j``) and returns
    the drive torques ``M_k = Σ_{i∈S(k)} u_i`` (preceded by the base force ``F`` with a
    translating base), the layout of ``tau`` in :func:`forward_dynamics`.
    """
    a = _check_vec(a, system.nv, "a")
    _loads(system, external_force, external_moment, system.body_mass.dtype)
    u = mass_matrix(system, q) @ a + bias_forces(system, q, v)
    u = u - generalized_forces(system, q, None, external_force, external_moment)
    ub, ut = _split(system, u)
    return jnp.concatenate([ub, system.tree.subtree_sum(ut)])


def joint_forces(
    system: PlanarSystem,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    a: Float[Array, " _nv"],
    external_force: Float[Array, "_n_body 2"] | None = None,
) -> Float[Array, "n_body 2"]:
    """Force ``F_k`` (world axes) that the base body of ``k`` applies to body ``k`` at its hinge.

    Eq. (1) in the plane: ``F_k = m_k W_0k + F_ek − m_k g − Σ_{i∈S(k)} F_ri`` with eq. (3)
    ``W_0k = W_0 + Σ_{i∈C(k)} [θ̈_i k×R_{c(i,k)} − θ̇_i² R_{c(i,k)}]`` (``W_0`` = base
    acceleration, zero on the ground) and eq. (4) ``F_ek = Σ_{i∈S(k)} [θ̈_i k×m̄_i − θ̇_i² m̄_i]``.
    """
    v = _check_vec(v, system.nv, "v")
    a = _check_vec(a, system.nv, "a")
    F, _ = _loads(system, external_force, None, system.body_mass.dtype)
    kin = _kin(system, q)
    tr = system.tree
    n = system.n_body
    _, w = _split(system, v)
    ab, e = _split(system, a)
    W0 = ab if system.translating_base else jnp.zeros((2,), kin.theta.dtype)
    anc, body, child = _pairs(system)
    W = jnp.broadcast_to(W0, (n, 2))
    if anc:
        R = kin.link[_idx(child)]
        ia = _idx(anc)
        W = W + _segsum(e[ia][:, None] * _perp(R) - (w[ia] ** 2)[:, None] * R, body, n)
    Fe = tr.subtree_sum(e[:, None] * _perp(kin.mbar) - (w * w)[:, None] * kin.mbar)
    m = kin.m_sub[:, None]
    return m * W + Fe - m * system.gravity - tr.subtree_sum(F)


def root_force(
    system: PlanarSystem,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    a: Float[Array, " _nv"],
    external_force: Float[Array, "_n_body 2"] | None = None,
) -> Float[Array, "2"]:
    """Total force the ground (or the translating base) applies at the root hinges.

    Eqs (10)–(11) written for the bodies only (with ``ẍ = ÿ = 0`` on the fixed ground, spec §9.3):
    ``F = m W + Σ_i [θ̈_i k×m̄_i − θ̇_i² m̄_i] − m g − Σ_i F_ri``, ``m`` = mass of the bodies.
    """
    roots = [k for k in range(system.n_body) if system.tree.parent[k] < 0]
    return jnp.sum(joint_forces(system, q, v, a, external_force)[_idx(roots)], axis=0)


# ---------------------------------------------------------------------------------- kinematics
def body_positions(
    system: PlanarSystem, q: Float[Array, " nq"]
) -> tuple[Float[Array, "n_body 2"], Float[Array, "n_body 2"]]:
    """World positions of the hinges ``O_k`` and of the centres of mass ``C_k``."""
    kin = _kin(system, q)
    base, _ = _split(system, jnp.asarray(q))
    hinge = system.tree.path_sum(kin.link)
    if system.translating_base:
        hinge = hinge + base
    com = hinge + _rot(kin.theta, system.body_com)
    return hinge, com


def point_position(
    system: PlanarSystem, q: Float[Array, " nq"], body: int, point: ParamLike
) -> Float[Array, "2"]:
    """World position of a point fixed in ``body`` (given in its axes from its hinge)."""
    hinge, _ = body_positions(system, q)
    theta = absolute_angles(system, q)
    return hinge[body] + _rot(theta[body], jnp.asarray(point))


def point_load(
    system: PlanarSystem,
    q: Float[Array, " nq"],
    body: int,
    point: ParamLike,
    force: ParamLike,
) -> tuple[Float[Array, "n_body 2"], Float[Array, " n_body"]]:
    """External loads ``(F_r, M_r)`` of a force (world axes) applied at a point of ``body``.

    ``M_r`` is the moment about the body's hinge ``O_k`` (spec §4), ready for
    :func:`generalized_forces`.
    """
    theta = absolute_angles(system, q)
    force = jnp.asarray(force)
    arm = _rot(theta[body], jnp.asarray(point))
    n = system.n_body
    F = jnp.zeros((n, 2), force.dtype).at[body].set(force)
    Mr = jnp.zeros((n,), force.dtype).at[body].set(_cross(arm, force))
    return F, Mr


def kinetic_energy(
    system: PlanarSystem, q: Float[Array, " nq"], v: Float[Array, " nv"]
) -> Float[Array, ""]:
    """``T = Σ_k (½ m_0k |v_Ck|² + ½ I_Ck θ̇_k²) + ½ m_base |v_base|²`` (body by body).

    Computed from the hinge and CM velocities, not from ``ℳ`` (``T = ½ vᵀℳv`` is a test).
    """
    v = _check_vec(v, system.nv, "v")
    kin = _kin(system, q)
    vb, w = _split(system, v)
    parent = np.asarray(system.tree.parent)
    w_parent = jnp.where(jnp.asarray(parent >= 0), w[_idx(np.maximum(parent, 0))], 0.0)
    v_hinge = system.tree.path_sum(w_parent[:, None] * _perp(kin.link))
    if system.translating_base:
        v_hinge = v_hinge + vb
    v_com = v_hinge + w[:, None] * _perp(_rot(kin.theta, system.body_com))
    T = 0.5 * jnp.sum(system.body_mass * jnp.sum(v_com**2, axis=-1))
    T = T + 0.5 * jnp.sum(system.body_inertia * w * w)
    if system.translating_base:
        T = T + 0.5 * system.base_mass * jnp.sum(vb * vb)
    return T


def potential_energy(system: PlanarSystem, q: Float[Array, " nq"]) -> Float[Array, ""]:
    """Gravitational potential ``V = −Σ_k m_0k g·C_k − m_base g·(x, y)`` (world origin = 0)."""
    _, com = body_positions(system, q)
    V = -jnp.sum(system.body_mass * _dot(com, system.gravity))
    if system.translating_base:
        V = V - system.base_mass * _dot(jnp.asarray(q)[:2], system.gravity)
    return V


def total_energy(
    system: PlanarSystem, q: Float[Array, " nq"], v: Float[Array, " nv"]
) -> Float[Array, ""]:
    """``T + V``."""
    return kinetic_energy(system, q, v) + potential_energy(system, q)


def power(
    system: PlanarSystem,
    q: Float[Array, " nq"],
    v: Float[Array, " nv"],
    tau: Float[Array, " _nv"] | None = None,
    external_force: Float[Array, "_n_body 2"] | None = None,
    external_moment: Float[Array, " _n_body"] | None = None,
) -> Float[Array, ""]:
    """Power of the drives and external loads, ``τ^abs·v`` (= ``dE/dt`` along a motion)."""
    v = _check_vec(v, system.nv, "v")
    return jnp.dot(generalized_forces(system, q, tau, external_force, external_moment), v)


# ---------------------------------------------------------------------------------- joint space
def absolute_to_relative(system: PlanarSystem, q: Float[Array, " nq"]) -> Float[Array, " nq"]:
    """Joint (relative) angles ``q_k = θ_k − θ_{p(k)}`` (spec §9.4, ``α = T q``).

    Roots keep their angle (relative to the ground/base, in the system's angle convention); base
    coordinates pass through. Linear, so it converts rates and accelerations alike.
    """
    q = _check_vec(q, system.nq, "q")
    qb, a = _split(system, q)
    parent = np.asarray(system.tree.parent)
    ap = jnp.where(jnp.asarray(parent >= 0), a[_idx(np.maximum(parent, 0))], 0.0)
    return jnp.concatenate([qb, a - ap])


def relative_to_absolute(system: PlanarSystem, q_rel: Float[Array, " nq"]) -> Float[Array, " nq"]:
    """Absolute angles ``α = T q`` from joint angles: ``α_k = Σ_{i∈C(k)∪{k}} q_i`` (spec §9.4)."""
    q_rel = _check_vec(q_rel, system.nq, "q_rel")
    qb, r = _split(system, q_rel)
    return jnp.concatenate([qb, system.tree.path_sum(r)])


def _transpose_path(system, x):
    """``Tᵀ x`` over the leading (angle) axis: ``(Tᵀx)_i = Σ_{k∈S(i)} x_k``."""
    return system.tree.subtree_sum(x)


def joint_mass_matrix(system: PlanarSystem, q: Float[Array, " nq"]) -> Float[Array, "nv nv"]:
    """Joint-space mass matrix ``Tᵀ ℳ T`` (spec §9.4; identity on the base block)."""
    M = mass_matrix(system, q)
    nb = system.n_base
    Mbb, Mbt, Mtt = M[:nb, :nb], M[:nb, nb:], M[nb:, nb:]
    Mtt_q = _transpose_path(system, _transpose_path(system, Mtt).T).T
    if nb == 0:
        return Mtt_q
    Mbt_q = _transpose_path(system, Mbt.T).T
    return jnp.block([[Mbb, Mbt_q], [Mbt_q.T, Mtt_q]])


def joint_bias_forces(
    system: PlanarSystem, q: Float[Array, " nq"], v: Float[Array, " nv"]
) -> Float[Array, " nv"]:
    """``Tᵀ h``: velocity and gravity terms of Lagrange's equations in joint angles (spec §9.4).

    ``v`` are the absolute rates (convert joint rates with :func:`relative_to_absolute`).
    """
    hb, ht = _split(system, bias_forces(system, q, v))
    return jnp.concatenate([hb, _transpose_path(system, ht)])


# ---------------------------------------------------------------------------------- Cor. 8
class DecouplingReport(NamedTuple):
    """Result of :func:`decoupling_report` (spec §10, corrected Cor. 8).

    Attributes:
        static_moment: ``m̄_k`` in body-``k`` axes, ``(n, 2)`` (NumPy).
        static_moment_magnitude: ``(md)_k = |m̄_k|``, ``(n,)``.
        must_vanish: ``(n,)`` bool: bodies whose ``m̄_k`` must vanish for decoupling — those with
            a carrier (non-empty ``C(k)``); all bodies on a translating base.
        offending: indices of bodies in ``must_vanish`` whose ``(md)_k`` exceeds the tolerance.
        decoupled: ``True`` when no body is offending.
        residual: largest ``|off-diagonal|`` of the absolute-angle mass matrix over the
            configurations.
        configurations: the configurations used, ``(n_config, nq)``.
    """

    static_moment: np.ndarray
    static_moment_magnitude: np.ndarray
    must_vanish: np.ndarray
    offending: tuple[int, ...]
    decoupled: bool
    residual: float
    configurations: np.ndarray


_batched_mass_matrix = jax.jit(jax.vmap(mass_matrix, in_axes=(None, 0)))


def decoupling_report(
    system: PlanarSystem,
    configurations: ParamLike | None = None,
    n_samples: int = 32,
    seed: int = 0,
    atol: float = 1e-12,
) -> DecouplingReport:
    """Dynamic decoupling check of Cor. 8 as corrected in spec §10 (concrete values, not traced).

    The absolute-angle mass matrix is diagonal for all configurations iff ``m̄_k = 0`` for every
    body with a carrier (given non-zero hinge offsets ``R``); with a translating base, iff
    ``m̄_k = 0`` for every body. ``m̄`` of a body hinged to the fixed ground only gives its own
    gravity torque and does not couple.

    Args:
        system: planar system.
        configurations: ``(n_config, nq)`` configurations; default: ``n_samples`` uniform random
            angles in ``[-π, π)`` (base coordinates zero, they do not enter ``ℳ``) from ``seed``.
        atol: tolerance on ``(md)_k`` (scaled by ``1 + max (md)``) for ``offending``.
    """
    n = system.n_body
    mbar = np.asarray(
        static_moment(system.tree, system.body_mass, system.body_com, system.hinge_pos),
        dtype=np.float64,
    )
    md = np.linalg.norm(mbar, axis=-1)
    if system.translating_base:
        must = np.ones(n, dtype=bool)
    else:
        must = ~system.tree.is_root
    tol = atol * (1.0 + float(md.max()))
    offending = tuple(int(k) for k in np.nonzero(must & (md > tol))[0].tolist())
    if configurations is None:
        rng = np.random.default_rng(seed)
        cfg = np.zeros((n_samples, system.nq))
        cfg[:, system.n_base :] = rng.uniform(-np.pi, np.pi, size=(n_samples, n))
    else:
        cfg = np.asarray(configurations, dtype=np.float64)
        if cfg.ndim != 2 or cfg.shape[1] != system.nq:
            raise ValueError(
                f"decoupling_report: configurations has shape {cfg.shape}, "
                f"expected (n_config, {system.nq})"
            )
    dtype = system.body_mass.dtype
    Ms = _batched_mass_matrix(system, jnp.asarray(cfg, dtype=dtype))
    Ms = np.asarray(Ms, dtype=np.float64)
    off = Ms * (1.0 - np.eye(system.nv))[None]
    residual = float(np.abs(off).max()) if off.size else 0.0
    return DecouplingReport(
        static_moment=mbar,
        static_moment_magnitude=md,
        must_vanish=must,
        offending=offending,
        decoupled=not offending,
        residual=residual,
        configurations=cfg,
    )
