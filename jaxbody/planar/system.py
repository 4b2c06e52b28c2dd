"""The planar system users hold: :class:`PlanarSystem` and its builders.

A :class:`PlanarSystem` is the data of :class:`~jaxbody.planar.parameters.PlanarParameters`
(frames, angles and parameters are described there) plus the ``DynamicalSystem`` protocol,
so :func:`jaxbody.simulate` and :func:`jaxbody.scene` take it as it is. Build it with
:func:`from_parents` (any tree, on the ground or on a translating base), :func:`chain` (the
chain of eq. 14) or :func:`jaxbody.planar.from_model` (a spatial model with parallel hinges).
"""

import math
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from .._types import Array, ArrayLike, Float
from ..tree import BodyTree
from ..validation import validate_planar
from . import dynamics
from .arrays import array_namespace, float_dtype, is_traced
from .parameters import ParamLike, PlanarParameters

__all__ = [
    "DOWNWARD_VERTICAL",
    "PlanarSystem",
    "from_parents",
    "chain",
    "validate",
    "vertical_to_horizontal",
    "horizontal_to_vertical",
]

DOWNWARD_VERTICAL = -0.5 * math.pi
"""``angle_origin`` of angles measured from the downward vertical ``e_0`` (eq. 14)."""


class PlanarSystem(PlanarParameters):
    """A planar tree of hinged bodies in absolute angles (docs/mathematics.md, "Planar systems in absolute angles"), as users hold it.

    The data (tree, parameters, conventions) are those of
    :class:`~jaxbody.planar.parameters.PlanarParameters`. Build it with :func:`from_parents`,
    :func:`chain` or :func:`jaxbody.planar.from_model`, which validate the parameters.

    It implements the ``DynamicalSystem`` protocol (``nq``, ``nv``, ``qdot``,
    ``acceleration``, ``total_energy``, plus ``power``), so :func:`jaxbody.simulate` and
    scenes take it directly: these are the only methods, thin calls of
    :mod:`jaxbody.planar.dynamics` (everything else is a function of that module). They check
    no values, so they are safe inside a vmapped solver loop (validate once with
    :func:`jaxbody.check_inputs`).
    """

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
        return dynamics.forward_dynamics(self, q, v, tau)

    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        """Kinetic plus gravitational potential energy."""
        return dynamics.total_energy(self, q, v)

    def power(
        self,
        t: ArrayLike,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, ""]:
        """Power of the drives ``tau`` (so ``dE/dt = power`` along a motion)."""
        return dynamics.power(self, q, v, tau)


def _as_param(value, dtype, shape, field: str):
    if is_traced(value):
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
    """Build a planar tree (docs/mathematics.md, "Planar systems in absolute angles" to "Corollary 6"; Cor. 5 with ``base_mass``, Cor. 6 without).

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
    dtype = float_dtype(mass)
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
    dtype = float_dtype(mass)
    xp = array_namespace(mass, com_distance, length, inertia, gravity)
    if np.ndim(mass) != 1:
        raise ValueError(
            f"planar chain: mass must be a 1-D array of link masses, got shape {np.shape(mass)}"
        )
    n = int(np.shape(mass)[0])
    a = _as_param(com_distance, dtype, (n,), "com_distance")
    L = length if is_traced(length) else np.asarray(length)
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


def vertical_to_horizontal(alpha: ArrayLike) -> Array:
    """``θ = α - π/2``: angle from the downward vertical (eq. 14) → angle from ``i`` (eq. 12)."""
    return jnp.asarray(alpha) - 0.5 * math.pi


def horizontal_to_vertical(theta: ArrayLike) -> Array:
    """``α = θ + π/2`` (``α_0k`` of docs/mathematics.md, "Planar systems in absolute angles"): angle from ``i`` → angle from the downward vertical."""
    return jnp.asarray(theta) + 0.5 * math.pi
