"""The data of a planar system: its tree, parameters and coordinate conventions.

A planar system is :class:`~jaxbody.tree.BodyTree` of rigid bodies hinged about axes
normal to the plane of motion. Every root body is hinged either to the fixed ground
(Cor. 6/7) or to a **translating base** of given mass that moves without rotating (Cor. 5).

Frames and angles
-----------------
* World axes: ``i`` horizontal, ``j`` vertical **up**, angles counter-clockwise (docs/mathematics.md, "Planar systems in absolute angles").
* Each body has body-fixed axes with origin at its own hinge ``O_k``. Its **absolute angle**
  ``θ_k`` is the angle from ``i`` to the body-fixed x-axis, counter-clockwise.
* The generalized coordinates are ``q = (x, y, q_1..q_n)`` with a translating base (``x, y``
  = base reference point) or ``q = (q_1..q_n)`` on the ground, where ``q_k = θ_k - angle_origin``.
  ``angle_origin`` (a static float) is the direction of the zero angle measured from ``i``:
  ``0`` for the horizontal convention of eqs (10)–(13) (:func:`jaxbody.planar.from_parents`), ``-π/2`` for angles
  measured from the **downward vertical** as in eq. (14) and the reference tables T-1/T-2
  (:func:`jaxbody.planar.chain`). Use :func:`jaxbody.planar.vertical_to_horizontal` /
  :func:`jaxbody.planar.horizontal_to_vertical` to convert.
* Velocities ``v = q̇`` (absolute angular rates ``θ̇_k``, base velocity).
* Drive/generalized forces ``tau`` have the layout of ``v``: ``(F_x, F_y, M_1..M_n)`` with a
  base (``F`` = force on the base) or ``(M_1..M_n)``; ``M_k`` is the drive torque that the base
  body of ``k`` (ground/base for roots) applies to body ``k`` about its hinge (docs/mathematics.md, "Loads").

Parameters (traced arrays, so ``jax.grad`` reaches them)
------------------------------------------------------
``body_mass`` ``m_0k``; ``body_com`` ``r_k`` in body-``k`` axes from ``O_k``; ``hinge_pos`` =
position of hinge ``k`` in the axes of its base body, measured from the base body's hinge (for a
root: in world axes from the world origin, or from the base reference point); ``body_inertia``
``I_Ck`` (central, about the hinge-axis direction); ``gravity`` (2-vector); ``base_mass``.

The augmented static moments ``m̄_k`` (eq. 5) and ``J_k`` (eq. 6, planar) are constants in body
axes, which is what makes the absolute-angle form cheap: the mass matrix (docs/mathematics.md, "Corollary 6") is
``ℳ_kk = J_k``, ``ℳ_ki = R_{c(i,k)}·m̄_k`` for carrier pairs, computed as gathers and
scatters over the static carrier pairs (the trace does not grow with ``n``).
"""

from collections.abc import Sequence

import equinox as eqx

from .._types import Array, ArrayLike, Float
from ..tree import BodyTree

ParamLike = ArrayLike | Sequence
"""Parameters given as arrays, scalars or (nested) sequences of numbers."""

__all__ = ["ParamLike", "PlanarParameters"]


class PlanarParameters(eqx.Module):
    """The data of a planar tree of hinged bodies in absolute angles (docs/mathematics.md, "Planar systems in absolute angles"; see the module
    docstring): what every function of :mod:`jaxbody.planar.dynamics` reads.

    The systems users hold are :class:`jaxbody.planar.PlanarSystem`, which adds the
    ``DynamicalSystem`` protocol; build them with :func:`jaxbody.planar.from_parents`,
    :func:`jaxbody.planar.chain` or :func:`jaxbody.planar.from_model`.

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
