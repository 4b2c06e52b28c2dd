"""Base systems of Maggi's equations: the bracket ``𝓔 = D·ẋ + h`` (docs/maggi.md M.4).

A base system is a holonomic system written in quasi-velocities ``x``: a
:class:`QuasiVelocitySystem` derives its bracket from ``T(q, q̇)``, ``Π(q)`` and ``q̇ = π(q, x)``
by automatic differentiation; a :class:`ModelBase` takes it from a :class:`jaxbody.Model`'s
kernels (quasi-velocities = joint velocities). :class:`MaggiResult` are the result codes of the
reduced dynamics built on them.
"""

from typing import Any

import equinox as eqx
import jax

from .._types import Array, Scalar
from ..data import compute_data
from ..kernels import bias_forces, kinetic_energy, mass_matrix, passive_forces, potential_energy
from ..kinematics import qpos_rate

__all__ = ["MaggiResult", "SINGULAR_PIVOT", "QuasiVelocitySystem", "ModelBase"]


class MaggiResult(eqx.Enumeration):
    """Result codes of the reduced dynamics (survive ``vmap``; see module docstring)."""

    successful = ""
    singular_parametrisation = (
        "the extended characteristics (ε, f*) cannot be solved for the quasi-velocities at this "
        "state: redundant or inconsistent constraints, or a degenerate choice of ε"
    )
    singular_reduced_mass = "the reduced mass matrix AᵀDA is not positive definite"
    partition_degraded = (
        "the coordinate partition degraded during the solve (its quality fell below "
        "partition_tolerance times the best partition's) and re-partitioning is off"
    )


# relative to the largest entry, so independent of units; about five orders of magnitude
# above double-precision round-off, so only genuinely dependent rows fall below it
#: relative pivot below which the parametrisation counts as singular
SINGULAR_PIVOT = 1e-11


class QuasiVelocitySystem(eqx.Module):
    """A holonomic system written in quasi-velocities ``x`` (docs/maggi.md §1–2).

    Subclasses give the kinetic energy in generalized velocities ``T(q, q̇)``, the potential
    energy ``Π(q)``, the kinematic relation ``q̇ = π(q, x)`` (M.2) and its inverse
    ``x = x(q, q̇)`` (M.1). The bracket of the equations of motion in quasi-velocities is then
    ``𝓔 = Hᵀ·(d/dt ∂T/∂q̇ − ∂T/∂q + ∂Π/∂q − Q)`` with ``H = ∂π/∂x`` (M.3–M.4), obtained by
    automatic differentiation. Applied forces are given in quasi-velocity components
    ``Q* = HᵀQ`` (the ``tau`` of :meth:`bracket_terms`).
    """

    def kinetic_energy_rates(self, q, qdot) -> Scalar:
        """``T(q, q̇)``."""
        raise NotImplementedError

    def potential_energy(self, q) -> Scalar:
        """``Π(q)``."""
        raise NotImplementedError

    def qdot(self, q, x) -> Array:
        """``q̇ = π(q, x)`` (M.2)."""
        raise NotImplementedError

    def quasi_velocities(self, q, qdot) -> Array:
        """``x = x(q, q̇)`` (M.1)."""
        raise NotImplementedError

    def total_energy(self, q, x) -> Scalar:
        """``T* + Π``."""
        return self.kinetic_energy_rates(q, self.qdot(q, x)) + self.potential_energy(q)

    def bracket_terms(self, t, q, x, tau=None) -> tuple[Array, Array]:
        """``(D, h)`` with ``𝓔 = D·ẋ + h`` (M.4); ``tau`` = applied forces ``Q*``."""
        qd = self.qdot(q, x)
        # H = ∂π/∂x maps variations of x to δq̇ = H·δx (M.2); D = Hᵀ·∂²T/∂q̇²·H is the metric of T*
        H = jax.jacfwd(lambda xx: self.qdot(q, xx))(x)
        p = lambda qq, vv: jax.grad(self.kinetic_energy_rates, argnums=1)(qq, vv)
        Mq = jax.jacfwd(p, argnums=1)(q, qd)
        # q̈ = H ẋ + (∂π/∂q) q̇; the part without ẋ:
        qdd0 = jax.jvp(lambda qq: self.qdot(qq, x), (q,), (qd,))[1]
        dp_dq = jax.jvp(lambda qq: p(qq, qd), (q,), (qd,))[1]
        dT_dq = jax.grad(self.kinetic_energy_rates, argnums=0)(q, qd)
        dV_dq = jax.grad(self.potential_energy)(q)
        lagrange0 = Mq @ qdd0 + dp_dq - dT_dq + dV_dq
        D = H.T @ Mq @ H
        h = H.T @ lagrange0
        if tau is not None:
            h = h - tau
        # an autodiff Hessian is symmetric only up to round-off, and the Cholesky solves read one
        # triangle: made exactly symmetric so that every reader sees the same metric
        return 0.5 * (D + D.T), h


class ModelBase(eqx.Module):
    """A :class:`jaxbody.Model` as base system: quasi-velocities = joint velocities ``v``.

    The joint layer is the first Maggi layer, so the bracket is the joint-space equation
    ``𝓔 = M(q)·v̇ + bias(q, v) − passive(q, v) − τ`` (``D = M``, the mass matrix with armature).
    """

    model: Any

    @property
    def nq(self) -> int:
        return self.model.nq

    @property
    def nv(self) -> int:
        return self.model.nv

    def qdot(self, q, x):
        return qpos_rate(self.model, q, x)

    def bracket_terms(self, t, q, x, tau=None):
        # the unchecked kernels on one state pytree: nothing raises inside a solver loop
        data = compute_data(self.model, q, x)
        D = mass_matrix(self.model, data)
        # the joint-space equation M·v̇ + bias = passive + τ written as the bracket 𝓔 = 0
        h = bias_forces(self.model, data) - passive_forces(self.model, data)
        if tau is not None:
            h = h - tau
        return D, h

    def total_energy(self, q, x):
        data = compute_data(self.model, q, x)
        return kinetic_energy(self.model, data) + potential_energy(self.model, data)
