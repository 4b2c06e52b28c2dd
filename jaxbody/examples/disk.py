"""A homogeneous disk on a horizontal plane: one base system, three regimes by constraints.

The base system is the disk *sliding on a perfectly smooth plane* (docs/maggi.md §5):
coordinates ``q = (x, y, ψ, θ, φ)`` — the horizontal position of the centre ``C``,
precession, nutation (the angle between the symmetry axis and the vertical, ``π/2`` when
upright) and spin, Euler angles z–x–z with ``R = R_z(ψ)R_x(θ)R_z(φ)``. Contact with the
plane is built into the coordinates (``z_C = ρ sin θ``). Quasi-velocities (eq. D.1):

    x₁ = θ̇,  x₂ = ψ̇ sin θ,  x₃ = φ̇ + ψ̇ cos θ   (angular velocity on the Résal axes x₂, y₂, z₂)
    x₄, x₅ = velocity of C on the horizontal axes x₁, y₁ (turned by ψ)

The kinetic energy is written from rigid-body mechanics (``½m|v_C|² + ½ωᵀI_Cω``), so
the equations of motion come from :class:`jaxbody.maggi.QuasiVelocitySystem` by automatic
differentiation. The other regimes **add constraints** to this base system:

* :func:`skating_disk` — on ice, a sharp edge slips only along the disk plane: the lateral
  component of the contact-point velocity vanishes, ``x₅ + ρ sin θ·x₁ = 0``; its reaction
  is the lateral friction force;
* :func:`rolling_disk` — on a rough plane, the contact point has no horizontal velocity:
  ``x₄ + ρx₃ = 0``, ``x₅ + ρ sin θ·x₁ = 0``; the reactions are the friction force
  components on the horizontal axes along and across the line of nodes.

The Euler angles are singular where the disk lies flat (``sin θ = 0``): ``ψ̇ = x₂ / sin θ`` in
:meth:`DiskOnPlane.qdot` grows without bound as a disk with ``x₂ ≠ 0`` falls flat, which is
also where the model of a disk touching the plane at one rim point ends. The disk declares its
chart (:meth:`DiskOnPlane.coordinate_chart`: ``|sin θ|`` above a bound), so a solve that falls
flat stops with the result code ``singular`` and a message naming the chart, ``sin θ`` and the
time. To stop at a chosen height instead, pass
``event=jb.Event(lambda t, q, x: jnp.sin(q[3]) - h, direction=False)`` with ``h`` above the bound.

Users give ``(q, q̇)``; :func:`initial_velocities` converts to ``x`` and rejects rates that
violate the regime. :func:`disk_outputs` gives the centre, contact point, normal force,
friction reactions and energy along a solution.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import maggi
from .._types import Array, ArrayLike, Float, Scalar
from ..scene import CoordinateChart

__all__ = [
    "DiskOnPlane",
    "disk_on_plane",
    "sliding_disk",
    "skating_disk",
    "rolling_disk",
    "skate_constraint",
    "rolling_constraint",
    "initial_velocities",
    "disk_outputs",
    "DiskOutputs",
]


def _rz(a):
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def _rx(a):
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([o, z, z]), jnp.stack([z, c, -s]), jnp.stack([z, s, c])])


class DiskOnPlane(maggi.QuasiVelocitySystem):
    """Homogeneous disk sliding on a smooth horizontal plane (the base system).

    Attributes:
        mass: ``m`` (kg).
        radius: ``ρ`` (m).
        gravity: ``g`` (m/s², magnitude; gravity points along ``−z``).
    """

    mass: Float[Array, ""]
    radius: Float[Array, ""]
    gravity: Float[Array, ""]

    nq = 5
    nv = 5

    # -- geometry ------------------------------------------------------------------------
    def rotation(self, q: Float[Array, " 5"]) -> Float[Array, "3 3"]:
        """Body rotation ``R_z(ψ)R_x(θ)R_z(φ)`` (body → world)."""
        return _rz(q[2]) @ _rx(q[3]) @ _rz(q[4])

    def centre(self, q: Float[Array, " 5"]) -> Float[Array, " 3"]:
        """Centre ``C = (x, y, ρ sin θ)``."""
        return jnp.stack([q[0], q[1], self.radius * jnp.sin(q[3])])

    def contact_point(self, q: Float[Array, " 5"]) -> Float[Array, " 3"]:
        """Contact point ``D = C − ρ·y₂`` (on the plane ``z = 0``)."""
        y2 = _rz(q[2]) @ jnp.stack([jnp.zeros_like(q[3]), jnp.cos(q[3]), jnp.sin(q[3])])
        return self.centre(q) - self.radius * y2

    def angular_velocity(self, q, qdot) -> Float[Array, " 3"]:
        """World angular velocity from ``Ṙ Rᵀ``."""
        R, Rd = jax.jvp(self.rotation, (q,), (qdot,))
        W = Rd @ R.T
        return jnp.stack([W[2, 1], W[0, 2], W[1, 0]])

    def central_inertia(self) -> Float[Array, "3 3"]:
        """``diag(A, A, C)`` in body axes: ``A = mρ²/4``, ``C = mρ²/2``."""
        a = self.mass * self.radius**2 / 4
        return jnp.diag(jnp.stack([a, a, 2 * a]))

    # -- QuasiVelocitySystem -------------------------------------------------------------
    def kinetic_energy_rates(self, q, qdot) -> Scalar:
        vc = jax.jvp(self.centre, (q,), (qdot,))[1]
        w = self.angular_velocity(q, qdot)
        R = self.rotation(q)
        I = R @ self.central_inertia() @ R.T
        return 0.5 * self.mass * vc @ vc + 0.5 * w @ I @ w

    def potential_energy(self, q) -> Scalar:
        return self.mass * self.gravity * self.radius * jnp.sin(q[3])

    def quasi_velocities(self, q, qdot) -> Float[Array, " 5"]:
        """``x`` from ``(q, q̇)`` (D.1): angular velocity on the Résal axes, centre velocity
        on the horizontal axes turned by ψ."""
        w = self.angular_velocity(q, qdot)
        resal = _rz(q[2]) @ _rx(q[3])
        vc = jax.jvp(self.centre, (q,), (qdot,))[1]
        v1 = _rz(q[2]).T @ vc
        return jnp.concatenate([resal.T @ w, v1[:2]])

    def qdot(self, q, x) -> Float[Array, " 5"]:
        """Kinematic equations ``q̇ = H(q)x`` (D.2)."""
        psi, th = q[2], q[3]
        s, c = jnp.sin(th), jnp.cos(th)
        return jnp.stack(
            [
                x[3] * jnp.cos(psi) - x[4] * jnp.sin(psi),
                x[3] * jnp.sin(psi) + x[4] * jnp.cos(psi),
                x[1] / s,
                x[0],
                x[2] - x[1] * c / s,
            ]
        )

    def coordinate_chart(self) -> CoordinateChart:
        """The z–x–z Euler angles are regular while ``|sin θ|`` stays above the chart's bound
        (``ε^(1/4)`` of the dtype): the kinematics (D.2) divides by ``sin θ``."""
        return CoordinateChart(
            name="z-x-z Euler angles (ψ, θ, φ) of the disk",
            coordinates=("|sin θ| (θ = q[3], the nutation: the disk lies flat where it is 0)",),
            margins=_sin_nutation,
            advice=("To end the solve before the disk lies flat, pass event=jb.Event(lambda t, q, x: "
                    "jnp.sin(q[3]) - h, direction=False) with h above the bound (the centre's height is ρ sin θ)"),
        )

    # -- contact -------------------------------------------------------------------------
    def contact_velocity(self, q, x) -> Float[Array, " 3"]:
        """Velocity of the disk's material point at ``D`` on the axes ``x₁, y₁, z₁`` (D.3)."""
        qd = self.qdot(q, x)
        vc = jax.jvp(self.centre, (q,), (qd,))[1]
        w = self.angular_velocity(q, qd)
        vd = vc + jnp.cross(w, self.contact_point(q) - self.centre(q))
        return _rz(q[2]).T @ vd

    def normal_force(self, q, x, xdot) -> Scalar:
        """``N = m(g + z̈_C)`` (Newton's law vertically; the model holds while ``N ≥ 0``)."""
        vz = lambda qq, xx: jax.jvp(self.centre, (qq,), (self.qdot(qq, xx),))[1][2]
        zdd = jax.jvp(vz, (q, x), (self.qdot(q, x), xdot))[1]
        return self.mass * (self.gravity + zdd)


def _sin_nutation(q):
    # the chart's margin: ψ̇ = x₂ / sin θ and φ̇ = x₃ − x₂ cos θ / sin θ (D.2)
    return jnp.abs(jnp.sin(q[3]))


def _scalar(v, name):
    v = jnp.asarray(v)
    if v.ndim != 0:
        raise ValueError(f"disk: {name} must be a scalar, got shape {v.shape}")
    return v if jnp.issubdtype(v.dtype, jnp.inexact) else v.astype(jnp.result_type(float))


def disk_on_plane(mass: ArrayLike = 2.0, radius: ArrayLike = 0.3, gravity: ArrayLike = 9.81) -> DiskOnPlane:
    """The base system (defaults: the reference disk of the documentation tests)."""
    m, r, g = _scalar(mass, "mass"), _scalar(radius, "radius"), _scalar(gravity, "gravity")
    dtype = jnp.result_type(m, r, g)
    return DiskOnPlane(mass=m.astype(dtype), radius=r.astype(dtype), gravity=g.astype(dtype))


def skate_constraint() -> maggi.VelocityConstraint:
    """Ice: no lateral slip of the contact point, ``v_D·y₁ = x₅ + ρ sin θ·x₁ = 0`` (D.4)."""
    return maggi.VelocityConstraint(
        lambda b, t, q, x: b.contact_velocity(q, x)[1:2], size=1, label="skate (lateral slip)"
    )


def rolling_constraint() -> maggi.VelocityConstraint:
    """Rough plane: no slip, ``v_D·x₁ = x₄ + ρx₃ = 0``, ``v_D·y₁ = x₅ + ρ sin θ·x₁ = 0`` (D.6)."""
    return maggi.VelocityConstraint(
        lambda b, t, q, x: b.contact_velocity(q, x)[:2], size=2, label="rolling (slip x1, y1)"
    )


_Q_REF = (0.0, 0.0, 0.0, 1.2, 0.0)


def _eps_skate(b, t, q, x):
    # ε = (x₁, x₂, x₃, v_D·x₁): the contact-point velocity along the line of nodes (D.5)
    return jnp.stack([x[0], x[1], x[2], b.contact_velocity(q, x)[0]])


def _eps_all(b, t, q, x):
    return x


def _eps_rolling(b, t, q, x):
    return x[:3]


def sliding_disk(mass=2.0, radius=0.3, gravity=9.81, *, base: DiskOnPlane | None = None) -> maggi.ConstrainedSystem:
    """Disk on a perfectly smooth plane: the base system with no added constraint."""
    base = disk_on_plane(mass, radius, gravity) if base is None else base
    return maggi.constrain(base, (), q_ref=jnp.asarray(_Q_REF, base.mass.dtype), epsilon=_eps_all)


def skating_disk(mass=2.0, radius=0.3, gravity=9.81, *, base: DiskOnPlane | None = None, baumgarte=10.0) -> maggi.ConstrainedSystem:
    """Disk on ice (skate): base system + :func:`skate_constraint`; ``ε = (x₁, x₂, x₃, v_D·x₁)``."""
    base = disk_on_plane(mass, radius, gravity) if base is None else base
    return maggi.constrain(
        base, (skate_constraint(),), q_ref=jnp.asarray(_Q_REF, base.mass.dtype), epsilon=_eps_skate,
        baumgarte=baumgarte,
    )


def rolling_disk(mass=2.0, radius=0.3, gravity=9.81, *, base: DiskOnPlane | None = None, baumgarte=10.0) -> maggi.ConstrainedSystem:
    """Disk rolling without slip: base system + :func:`rolling_constraint`; ``ε = (x₁, x₂, x₃)``."""
    base = disk_on_plane(mass, radius, gravity) if base is None else base
    return maggi.constrain(
        base, (rolling_constraint(),), q_ref=jnp.asarray(_Q_REF, base.mass.dtype), epsilon=_eps_rolling,
        baumgarte=baumgarte,
    )


def initial_velocities(system: maggi.ConstrainedSystem, q: ArrayLike, qdot: ArrayLike, *, atol: float = 1e-9) -> Array:
    """Quasi-velocities ``x`` from coordinates and rates ``(q, q̇)``.

    Raises:
        ValueError: the rates violate the regime's constraints (the message names them),
            or ``θ`` is a multiple of ``π`` (the disk lies flat: the coordinates are singular).
    """
    q = jnp.asarray(q, system.base.mass.dtype)
    qdot = jnp.asarray(qdot, q.dtype)
    if q.shape != (5,) or qdot.shape != (5,):
        raise ValueError(f"disk: q and qdot must have shape (5,), got {q.shape} and {qdot.shape}")
    if abs(float(jnp.sin(q[3]))) < 1e-9:
        raise ValueError(f"disk: theta = {float(q[3])} lies flat on the plane (sin θ = 0): the angles are singular")
    x = system.base.quasi_velocities(q, qdot)
    maggi.initial_state(system, q, x, 0.0, atol=atol)
    return x


class DiskOutputs(eqx.Module):
    """Quantities along a disk trajectory (each with a leading time axis).

    Attributes:
        centre, contact_point: (N, 3) world positions of ``C`` and ``D``.
        normal_force: (N,) ``N``.
        reactions: (N, s) friction reactions ``Λ`` (skate: lateral force; rolling: force
            along ``x₁`` and ``y₁``; none for sliding).
        energy: (N,) ``T + Π``.
        xdot: (N, 5) quasi-accelerations.
    """

    centre: Array
    contact_point: Array
    normal_force: Array
    reactions: Array
    energy: Array
    xdot: Array


def disk_outputs(system: maggi.ConstrainedSystem, t, q, x) -> DiskOutputs:
    """Centre, contact point, normal force, friction reactions and energy along ``(t, q, x)``
    (e.g. ``sol.t, sol.q, sol.v`` of :func:`jaxbody.simulate`)."""
    return _disk_outputs(system, jnp.asarray(t), jnp.asarray(q), jnp.asarray(x))


@eqx.filter_jit
def _disk_outputs(system, t, q, x):
    base = system.base

    def one(tt, qq, xx):
        res = system.solve(tt, qq, xx)
        return (
            base.centre(qq), base.contact_point(qq), base.normal_force(qq, xx, res.xdot), res.reactions,
            base.total_energy(qq, xx), res.xdot,
        )

    c, d, n, lam, e, xd = jax.vmap(one)(t, q, x)
    return DiskOutputs(centre=c, contact_point=d, normal_force=n, reactions=lam, energy=e, xdot=xd)
