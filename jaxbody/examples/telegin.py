"""The six worked examples of the augmented-body paper as ready systems.

Every constructor's defaults are the data of the reference tables of the paper's reference tables, so e.g.
``double_pendulum()`` reproduces T-1/T-3. Angles ``φ``/``α`` are measured **from the downward
vertical**, counter-clockwise (eq. 14 convention); ``g = 9.81``.

==============================================  =====================================  ==========
constructor                                     coordinates ``q``                       table
==============================================  =====================================  ==========
:func:`double_pendulum` (Ex. 1, eq. 15)         ``(α_1, α_2)``                          T-1, T-3
:func:`three_link_manipulator` (Ex. 2, eq. 16)  ``(α_1, α_2, α_3)``, horizontal plane   T-4
:func:`cart_pendulum` (Ex. 3, eq. 17)           ``(x, φ)``                              T-5
:func:`oscillating_support_pendulum` (Ex. 4)    ``(φ,)``                                T-6
:func:`vertical_line_double_pendulum` (Ex. 5)   ``(φ,)``, ``α_1 = φ, α_2 = −φ``          T-7
:func:`wheelset_pendulum` (Ex. 6, eq. 19)       ``(x, φ)``                              T-7b
==============================================  =====================================  ==========

All implement the simulation protocol (``nq``, ``nv``, ``qdot``, ``acceleration``,
``total_energy``, ``power``); examples 3–6 also give their reaction forces.
"""

import jax.numpy as jnp

from .. import planar
from .._types import Array, ArrayLike, Float
from ..planar import ParamLike
from ..planar.arrays import array_namespace, float_dtype
from ._embedded import EmbeddedPlanarSystem

__all__ = [
    "double_pendulum",
    "three_link_manipulator",
    "cart_pendulum",
    "CartPendulum",
    "oscillating_support_pendulum",
    "OscillatingSupportPendulum",
    "vertical_line_double_pendulum",
    "VerticalLineDoublePendulum",
    "wheelset_pendulum",
    "WheelsetPendulum",
]


def _prep(reference, *values):
    """Array module (``np`` for concrete inputs, ``jnp`` when traced) and the float dtype of
    ``reference``; every value converted to that dtype."""
    xp = array_namespace(reference, *values)
    dtype = float_dtype(reference)
    return xp, dtype, [xp.asarray(v).astype(dtype) for v in (reference, *values)]


# ------------------------------------------------------------------------- Example 1
def double_pendulum(
    mass: ParamLike = (1.0, 0.6),
    com_distance: ParamLike = (0.4, 0.3),
    length: ParamLike = (0.8, 0.8),
    inertia: ParamLike = (0.05, 0.02),
    gravity: ParamLike = 9.81,
) -> planar.PlanarSystem:
    """Example 1, eq. (15): double pendulum in a vertical plane (a 2-link :func:`~jaxbody.planar.chain`).

    ``q = (α_1, α_2)``: absolute link angles from the downward vertical; ``tau`` = hinge torques
    ``(M_1, M_2)``. ``length = (L_1, L_2)``; only ``L_1`` enters the dynamics (``L_2`` is the
    length of the second link for drawing and may be omitted).
    """
    return planar.chain(mass, com_distance, length, inertia, gravity=gravity, names=("link1", "link2"))


# ------------------------------------------------------------------------- Example 2
def three_link_manipulator(
    mass: ParamLike = (2.0, 1.5, 0.8),
    com_distance: ParamLike = (0.35, 0.25, 0.15),
    length: ParamLike = (0.7, 0.5),
    inertia: ParamLike = (0.09, 0.04, 0.01),
    gravity: ParamLike = 0.0,
) -> planar.PlanarSystem:
    """Example 2, eq. (16) **[corrected]**: shoulder, forearm, hand in a horizontal plane.

    The corrected third equation has ``s_32`` in its last term (the printed ``s_31`` does not
    satisfy Lagrange's equations) and no gravity terms in a horizontal plane (``gravity = 0``;
    pass ``9.81`` for a vertical plane). ``q = (α_1, α_2, α_3)`` absolute angles; ``tau`` =
    direct-drive torques ``(M_1, M_2, M_3)``.
    """
    return planar.chain(
        mass, com_distance, length, inertia, gravity=gravity, names=("shoulder", "forearm", "hand")
    )


# ------------------------------------------------------------------------- Example 3
class CartPendulum(EmbeddedPlanarSystem):
    """Example 3, eq. (17): cart on a smooth horizontal rail carrying a pendulum.

    ``q = (x, φ)``: cart position and pendulum angle from the downward vertical; ``tau`` =
    ``(F_x, M_1)`` (horizontal force on the cart, hinge torque). The rail keeps ``y ≡ 0``.
    """

    @property
    def nq(self) -> int:
        return 2

    def embed(self, t, q):
        return jnp.stack([q[0], jnp.zeros_like(q[0]), q[1]])

    def lift(self, q, tau):
        return jnp.stack([tau[0], jnp.zeros_like(tau[0]), tau[1]])

    def rail_reaction(
        self,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, ""]:
        """Vertical rail reaction ``F_r`` on the cart (eq. 11 with ``ÿ = 0``)."""
        return self.constraint_force(jnp.zeros((), q.dtype), q, v, tau)[1]


def cart_pendulum(
    cart_mass: ParamLike = 3.0,
    mass: ParamLike = 0.5,
    com_distance: ParamLike = 0.4,
    inertia: ParamLike = 0.01,
    gravity: ParamLike = 9.81,
) -> CartPendulum:
    """Example 3 (table T-5): cart of mass ``m_c`` with a pendulum ``m_01``, ``a_1``, ``I_C1``."""
    xp, dt, (m, mc, a, inertia, g) = _prep(mass, cart_mass, com_distance, inertia, gravity)
    zero = xp.zeros((), dt)
    system = planar.from_parents(
        [-1],
        m.reshape(1),
        xp.stack([a, zero]).reshape(1, 2),
        xp.zeros((1, 2), dt),
        inertia.reshape(1),
        gravity=xp.stack([zero, -g]),
        base_mass=mc,
        names=("pendulum",),
        angle_origin=planar.DOWNWARD_VERTICAL,
    )
    return CartPendulum(system=system)


# ------------------------------------------------------------------------- Example 4
class OscillatingSupportPendulum(EmbeddedPlanarSystem):
    """Example 4: pendulum whose pivot moves as ``s(t) = a_0 sin ωt`` along a line at ``β``.

    ``q = (φ,)`` from the downward vertical; ``tau = (M_1,)`` hinge torque. The constraint is
    rheonomic, so ``total_energy`` is the energy **relative to the support** (kinetic energy in
    the translating support frame plus the gravity potential of the pendulum about the pivot) and
    ``power`` includes the power of the inertial force ``−m_01 W(t)`` of the support frame:
    ``dE/dt = M_1 φ̇ − W·(Σ θ̇_k k × m̄_k)``.
    """

    amplitude: Float[Array, ""]
    frequency: Float[Array, ""]
    incline: Float[Array, ""]

    @property
    def nq(self) -> int:
        return 1

    def support_position(self, t: ArrayLike) -> Array:
        """``(x, y) = a_0 sin ωt (cos β, sin β)``."""
        t = jnp.asarray(t, dtype=self.amplitude.dtype)
        s = self.amplitude * jnp.sin(self.frequency * t)
        return s * jnp.stack([jnp.cos(self.incline), jnp.sin(self.incline)])

    def embed(self, t, q):
        return jnp.concatenate([self.support_position(t), q])

    def lift(self, q, tau):
        return jnp.concatenate([jnp.zeros((2,), tau.dtype), tau])

    def support_force(
        self,
        t: ArrayLike,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, "2"]:
        """Force (world axes) the moving support applies to the pendulum at the pivot ``O_1``."""
        return self.constraint_force(t, q, v, tau)[:2]

    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        zero = jnp.zeros((2,), q.dtype)
        return planar.total_energy(
            self.system, jnp.concatenate([zero, q]), jnp.concatenate([zero, v])
        )

    def power(
        self,
        t: ArrayLike,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, ""]:
        Q, _, _, c = self.full_state(t, q, v)
        W = c[:2]  # support acceleration (Q̈ = A q̈ + c; the support does not depend on q)
        mbar = planar.augmented_bodies(self.system, Q).static_moment
        momentum_rel = jnp.sum(v[:, None] * jnp.stack([-mbar[:, 1], mbar[:, 0]], axis=-1), axis=0)
        p = -jnp.dot(W, momentum_rel)
        if tau is not None:
            p = p + jnp.dot(jnp.asarray(tau), v)
        return p


def oscillating_support_pendulum(
    mass: ParamLike = 0.5,
    com_distance: ParamLike = 0.4,
    inertia: ParamLike = 0.01,
    amplitude: ParamLike = 0.05,
    frequency: ParamLike = 12.0,
    incline: ParamLike = 0.5,
    gravity: ParamLike = 9.81,
) -> OscillatingSupportPendulum:
    """Example 4 (table T-6): ``m_01``, ``a_1``, ``I_C1``; support amplitude ``a_0``, ``ω``, ``β``.

    Equation: ``J_1 φ̈ − (md)_1 a_0 ω² sin ωt cos(φ − β) + (md)_1 g sin φ = M_1``.
    """
    xp, dt, (m, a, inertia, amplitude, frequency, incline, g) = _prep(
        mass, com_distance, inertia, amplitude, frequency, incline, gravity
    )
    zero = xp.zeros((), dt)
    system = planar.from_parents(
        [-1],
        m.reshape(1),
        xp.stack([a, zero]).reshape(1, 2),
        xp.zeros((1, 2), dt),
        inertia.reshape(1),
        gravity=xp.stack([zero, -g]),
        base_mass=zero,
        names=("pendulum",),
        angle_origin=planar.DOWNWARD_VERTICAL,
    )
    return OscillatingSupportPendulum(
        system=system,
        amplitude=jnp.asarray(amplitude),
        frequency=jnp.asarray(frequency),
        incline=jnp.asarray(incline),
    )


# ------------------------------------------------------------------------- Example 5
class VerticalLineDoublePendulum(EmbeddedPlanarSystem):
    """Example 5, eq. (18): double pendulum (``L_1 = L_2 = L``) whose end ``A`` stays on the
    vertical through ``O_1``.

    ``q = (φ,)`` with ``α_1 = φ``, ``α_2 = −φ`` (from the downward vertical); ``tau = (Q_φ,)`` the
    generalized force conjugate to ``φ``; hinge torques ``(M_1, M_2)`` give ``Q_φ = M_1 − 2 M_2``
    (:meth:`generalized_force`). The smooth constraint applies a horizontal force ``F_r i`` at
    ``A`` (:meth:`reaction`).
    """

    length: Float[Array, ""]

    @property
    def nq(self) -> int:
        return 1

    def embed(self, t, q):
        return jnp.concatenate([q, -q])

    def lift(self, q, tau):
        return jnp.concatenate([tau, jnp.zeros_like(tau)])

    def generalized_force(self, hinge_torques: Float[Array, "2"]) -> Float[Array, "1"]:
        """``Q_φ = Aᵀ τ^abs = (M_1 − M_2) − M_2`` for hinge torques ``(M_1, M_2)``."""
        M = jnp.asarray(hinge_torques)
        return jnp.reshape(M[0] - 2.0 * M[1], (1,))

    def end_point(self, q: Float[Array, " nq"]) -> Float[Array, "2"]:
        """Position of the end point ``A`` of link 2 (``x_A = 0`` on the constraint)."""
        point = jnp.stack([self.length, jnp.zeros_like(self.length)])
        return planar.point_position(self.system, self.embed(0.0, q), 1, point)

    def reaction(
        self,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, ""]:
        """``F_r``: the ``i``-component of the constraint force on ``A``.

        The residual of the free double pendulum equals ``F_r ∂x_A/∂α`` with
        ``∂x_A/∂α = (L cos α_1, L cos α_2)`` (eq. 18: both rows ``= L F_r cos φ``).
        """
        r = self.constraint_force(jnp.zeros((), q.dtype), q, v, tau)
        G = self.length * jnp.cos(self.embed(0.0, q))
        return jnp.dot(G, r) / jnp.dot(G, G)


def vertical_line_double_pendulum(
    mass: ParamLike = (1.0, 0.6),
    com_distance: ParamLike = (0.4, 0.3),
    length: ParamLike = 0.8,
    inertia: ParamLike = (0.05, 0.02),
    gravity: ParamLike = 9.81,
) -> VerticalLineDoublePendulum:
    """Example 5 (table T-7): the Example-1 pendulum with ``L_1 = L_2 = L`` and ``A`` on the vertical."""
    xp, dt, (m, L) = _prep(mass, length)
    if L.shape != ():
        raise ValueError(f"vertical_line_double_pendulum: length must be a scalar L, got shape {L.shape}")
    system = planar.chain(
        m, com_distance, xp.stack([L, L]), inertia, gravity=gravity, names=("link1", "link2")
    )
    return VerticalLineDoublePendulum(system=system, length=jnp.asarray(L))


# ------------------------------------------------------------------------- Example 6
class WheelsetPendulum(EmbeddedPlanarSystem):
    """Example 6, eq. (19) **[corrected]**: wheelset rolling on rails with a pendulum on its axle.

    ``q = (x, φ)``: axle position and pendulum angle from the downward vertical. Rolling without
    slip gives ``x = −R α_1`` (counter-clockwise wheel angle; the paper's ``x = R α_1`` has the
    wrong sign), hence ``(M + J_1/R²) ẍ + (md)_2(φ̈ cos φ − φ̇² sin φ) = 0`` (the paper prints
    ``M − J_1/R²``). ``tau = (F_x, M_2)``: horizontal force on the axle, torque on the pendulum.
    """

    radius: Float[Array, ""]

    @property
    def nq(self) -> int:
        return 2

    def embed(self, t, q):
        x, phi = q[0], q[1]
        return jnp.stack([x, jnp.zeros_like(x), -x / self.radius, phi])

    def lift(self, q, tau):
        z = jnp.zeros_like(tau[0])
        return jnp.stack([tau[0], z, z, tau[1]])

    def friction_force(
        self,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, ""]:
        """``F_r`` with the rail friction on the wheels ``−F_r i`` (``F_r = J_1 ẍ / R²`` unloaded)."""
        r = self.constraint_force(jnp.zeros((), q.dtype), q, v, tau)
        return -r[2] / self.radius

    def normal_force(
        self,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, ""]:
        """Total vertical rail reaction on the wheels (eq. 11 with ``ÿ = 0``)."""
        return self.constraint_force(jnp.zeros((), q.dtype), q, v, tau)[1]


def wheelset_pendulum(
    wheel_mass: ParamLike = 4.0,
    wheel_inertia: ParamLike = 0.12,
    radius: ParamLike = 0.25,
    mass: ParamLike = 0.7,
    com_distance: ParamLike = 0.35,
    inertia: ParamLike = 0.015,
    gravity: ParamLike = 9.81,
) -> WheelsetPendulum:
    """Example 6 (table T-7b): wheelset ``m_w``, ``J_1``, ``R``; pendulum ``m_02``, ``a_2``, ``I_C2``.

    Modelled as Cor. 5: a massless carrier frame on the axle axis carrying the wheelset (body 1,
    CM on the axle) and the pendulum (body 2), so ``M = m_w + m_02``.
    """
    xp, dt, (mw, Jw, R, m, a, inertia, g) = _prep(
        wheel_mass, wheel_inertia, radius, mass, com_distance, inertia, gravity
    )
    zero = xp.zeros((), dt)
    system = planar.from_parents(
        [-1, -1],
        xp.stack([mw, m]),
        xp.stack([xp.stack([zero, zero]), xp.stack([a, zero])]),
        xp.zeros((2, 2), dt),
        xp.stack([Jw, inertia]),
        gravity=xp.stack([zero, -g]),
        base_mass=zero,
        names=("wheelset", "pendulum"),
        angle_origin=planar.DOWNWARD_VERTICAL,
    )
    return WheelsetPendulum(system=system, radius=jnp.asarray(R))

