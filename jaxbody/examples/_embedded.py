"""Planar systems restricted by explicitly solved holonomic constraints (rails, rolling, ...).

The full planar system (:class:`~jaxbody.planar.PlanarSystem`) has coordinates ``Q``; the
constrained one has independent coordinates ``q`` with ``Q = embed(t, q)``. Then
``Q̇ = A q̇ + ∂Q/∂t`` and ``Q̈ = A q̈ + c`` with ``A = ∂Q/∂q`` and ``c`` the second derivative
of ``s ↦ embed(t + s, q + s q̇)`` (both from forward-mode autodiff). Projecting eqs (10)–(13)
onto the admissible directions (Maggi's equations with ``A``, docs/maggi.md, "Maggi's equations and the reactions") gives

    (Aᵀ ℳ A) q̈ = Aᵀ (τ(Q) − h(Q, Q̇) − ℳ c),

and the residual ``r = ℳ Q̈ + h − τ`` of the full equations is the generalized constraint force,
from which each example reads its reactions (rail, support, friction ...).
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import planar
from .._types import Array, ArrayLike, Float
from ..linalg import solve_spd

__all__ = ["EmbeddedPlanarSystem"]


class EmbeddedPlanarSystem(eqx.Module):
    """Base class: a :class:`~jaxbody.planar.PlanarSystem` with coordinates ``Q = embed(t, q)``.

    Subclasses define ``embed(t, q)`` (full coordinates) and ``lift(q, tau)`` (the drives of the
    full system, in :func:`~jaxbody.planar.generalized_forces` layout, that a reduced generalized
    force ``tau`` stands for; ``Aᵀ τ^abs(lift(tau)) = tau``). The simulation protocol (``nq``,
    ``nv``, ``qdot``, ``acceleration``, ``total_energy``, ``power``) is implemented here;
    ``tau`` is the generalized force conjugate to ``q``.
    """

    system: planar.PlanarSystem

    @property
    def nq(self) -> int:
        raise NotImplementedError

    @property
    def nv(self) -> int:
        return self.nq

    def embed(self, t, q):
        raise NotImplementedError

    def lift(self, q, tau):
        raise NotImplementedError

    # ------------------------------------------------------------------ kinematics
    def _t(self, t, q):
        return jnp.asarray(t, dtype=q.dtype)

    def full_state(
        self, t: ArrayLike, q: Float[Array, " nq"], v: Float[Array, " nv"]
    ) -> tuple[Array, Array, Array, Array]:
        """``(Q, Q̇, A, c)`` with ``Q̈ = A q̈ + c`` (full coordinates of the planar system)."""
        q = jnp.asarray(q)
        v = jnp.asarray(v)
        if q.shape != (self.nq,) or v.shape != (self.nv,):
            raise ValueError(
                f"{type(self).__name__}: q and v must have shapes ({self.nq},) and ({self.nv},), "
                f"got {q.shape} and {v.shape}"
            )
        t = self._t(t, q)

        def path(s):
            return self.embed(t + s, q + s * v)

        def first(s):
            return jax.jvp(path, (s,), (jnp.ones_like(s),))

        zero = jnp.zeros((), q.dtype)
        (Q, V), (_, c) = jax.jvp(first, (zero,), (jnp.ones_like(zero),))
        A = jax.jacfwd(lambda qq: self.embed(t, qq))(q)
        return Q, V, A, c

    def _drives(self, q, tau):
        if tau is None:
            return None
        tau = jnp.asarray(tau)
        if tau.shape != (self.nv,):
            raise ValueError(
                f"{type(self).__name__}: tau has shape {tau.shape}, expected ({self.nv},)"
            )
        return self.lift(q, tau)

    def _solve(self, t, q, v, tau):
        drives = self._drives(q, tau)
        Q, V, A, c = self.full_state(t, q, v)
        M = planar.mass_matrix(self.system, Q)
        h = planar.bias_forces(self.system, Q, V)
        f = planar.generalized_forces(self.system, Q, drives)
        a = solve_spd(A.T @ M @ A, A.T @ (f - h - M @ c))
        residual = M @ (A @ a + c) + h - f
        return a, residual, Q, V

    # ------------------------------------------------------------------ protocol
    def qdot(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nq"]:
        """``q̇ = v``."""
        return v

    def acceleration(
        self,
        t: ArrayLike,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, " nv"]:
        """``q̈`` from ``(Aᵀℳ A) q̈ = Aᵀ(τ − h − ℳ c)``."""
        return self._solve(t, q, v, tau)[0]

    def constraint_force(
        self,
        t: ArrayLike,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Array:
        """Generalized constraint force ``ℳ Q̈ + h − τ`` in the full coordinates ``Q``."""
        return self._solve(t, q, v, tau)[1]

    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        """Energy of the full system at ``t = 0`` (scleronomic constraints: conserved)."""
        Q, V, _, _ = self.full_state(jnp.zeros((), q.dtype), q, v)
        return planar.total_energy(self.system, Q, V)

    def power(
        self,
        t: ArrayLike,
        q: Float[Array, " nq"],
        v: Float[Array, " nv"],
        tau: Float[Array, " _nv"] | None = None,
    ) -> Float[Array, ""]:
        """Power ``tau·v`` of the generalized drives."""
        if tau is None:
            return jnp.zeros((), q.dtype)
        return jnp.dot(jnp.asarray(tau), v)
