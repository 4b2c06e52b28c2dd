"""Maggi's equations in quasi-coordinates: constraints, reduced dynamics and reactions.

Joints are the first layer of Maggi's method: a tree's joint velocities ``v`` already
parametrise the admissible motions of its bodies. This module is the second layer: extra
constraints of first order in the quasi-velocities ``x`` of a *base system*,

    f*(t, q, x) = 0,    f* ∈ R^s                                   (docs/maggi.md, eq. M.6)

linear ones ``C(t, q)·x + c(t, q) = 0`` (holonomic constraints in velocity form,
rolling, skating, loop closures) and nonlinear ones (their Jacobians come from automatic
differentiation). The unconstrained motion obeys ``𝓔 = 0``, where the *bracket*

    𝓔(t, q, x, ẋ) = D(q)·ẋ + h(t, q, x)                            (M.4)

is the left-hand side of the equations of motion in quasi-velocities (``D`` the kinetic
metric ``∂²T*/∂x∂x``, ``h`` the velocity, gravity and applied terms). With extended
characteristics ``ε̃ = (ε, f*)`` solvable for ``x`` (M.8), ``[A | K] = ∂x/∂ε̃`` and

    Aᵀ·𝓔 = 0          (Maggi's equations in quasi-coordinates, M.10)
    Λ = Kᵀ·𝓔          (constraint reactions, M.12)

The constrained accelerations follow from ``Aᵀ𝓔 = 0`` and the differentiated constraints
``G·ẋ = −γ`` (``G = ∂f*/∂x``, ``γ = ∂f*/∂q·q̇ + ∂f*/∂t``): writing ``ẋ = A·α − K·γ`` gives the
symmetric positive-definite reduced system ``(AᵀDA)·α = −Aᵀ(h − D·K·γ)`` (M.11), solved
with :func:`jaxbody.linalg.solve_spd` (no LAPACK, safe under ``vmap``).

``[A | K]`` is the inverse of ``∂ε̃/∂x = [E; G]`` (``E = ∂ε/∂x``), computed by Gauss–Jordan
elimination with partial pivoting written in plain array operations (:func:`solve_general`).
``ε`` is either given by the user (a function of ``(base, t, q, x)``) or chosen by
*coordinate partitioning*: a column-pivoted QR of ``G`` at a reference state picks the
``s`` best-conditioned dependent quasi-velocities; the others are ``ε``. The choice only
fixes what ``ε`` means: ``ẋ`` and ``Λ`` do not depend on it (docs/maggi.md §4). The pivot
ratio of the elimination is returned as a conditioning measure. Along a solve the partition
is kept while well conditioned and re-chosen when it degrades: :class:`PartitionSolver`
compares its quality ``det[E; G]/sqrt(det GGᵀ)`` (M.9a) after every step with that of the
partition pivoted QR would choose there (the choice is written in array operations, so it
runs inside ``jit``/``vmap``), and ``jb.simulate`` and :func:`simulate_phases` use it;
``repartition=False`` stops the solve with ``partition_degraded`` instead.
:meth:`ConstrainedSystem.repartition` re-chooses the partition by hand (the phase runner
does so at every switch).

Errors follow the project's three layers: shape and static misuse raise ``ValueError``
while building; redundant or inconsistent constraints are detected at the reference state
by :func:`check_constraints` (``ValueError`` naming the rows); inside ``jit``, a singular
parametrisation or reduced mass matrix is a :class:`MaggiResult` code, so a batch survives
a bad member.

Drift: holonomic constraints enter in velocity form, so their positions drift. The vector
field applies Baumgarte stabilisation ``φ̈ + 2ω·φ̇ + ω²·φ = 0`` (holonomic rows) and
``ḟ* + 2ω·f* = 0`` (non-holonomic rows) with one rate ``ω`` (``baumgarte``, default
``10 s⁻¹``: residuals decay critically damped with time constant ``1/ω``; ``0`` switches it
off). It leaves exact solutions unchanged. :func:`project_positions` (Newton, minimum-norm
steps) and :func:`project_velocities` (kinetic-metric projection) put a state back on the
manifold; :func:`constraint_residuals` reports both residuals along a solution.

Switching kinematic structure: :func:`switch_constraints` projects the velocities onto the
manifold of a new constraint set, ``x⁺ = A(AᵀDA)⁻¹AᵀD·x⁻`` (impulsive constraint), and
reports the impulse and the kinetic energy lost; :func:`simulate_phases` integrates a
sequence of constraint sets with time- or state-triggered switches (diffrax events).
"""

from collections.abc import Callable, Sequence
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax import lax

from . import linalg
from ._solvers import DelegatingSolver
from ._types import Array, ArrayLike, Float, Scalar

__all__ = [
    "MaggiResult",
    "QuasiVelocitySystem",
    "ModelBase",
    "Constraint",
    "VelocityConstraint",
    "ConstrainedSystem",
    "MaggiSolution",
    "constrain",
    "check_constraints",
    "solve_general",
    "initial_state",
    "project_velocities",
    "project_positions",
    "switch_constraints",
    "SwitchReport",
    "reactions",
    "constraint_residuals",
    "Phase",
    "PhasedSolution",
    "simulate_phases",
    "PartitionSolver",
    "partition_solver",
    "partition_report",
    "with_best_partition",
    "MAX_RECORDED_REPARTITIONS",
]


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


#: relative pivot below which the parametrisation counts as singular
SINGULAR_PIVOT = 1e-11


# ---------------------------------------------------------------------------------------
# Dense general solve without LAPACK
# ---------------------------------------------------------------------------------------


def solve_general(M: Float[ArrayLike, "n n"], B: Float[ArrayLike, "n k"]) -> tuple[Float[Array, "n k"], Float[Array, ""]]:
    """Solve ``M·X = B`` by Gauss–Jordan elimination with partial (row) pivoting.

    Plain array operations in one ``lax.fori_loop`` over columns (no LAPACK call, so it
    is safe under ``vmap`` on CPU; trace size independent of ``n``); differentiable by
    ordinary autodiff.

    Args:
        M: square matrix ``(n, n)``.
        B: right-hand sides ``(n, k)``.

    Returns:
        ``(X, pivot_ratio)``: the solution and ``min |pivot| / max |M_ij|`` (``0`` for a
        singular ``M``; a conditioning measure, compare with :data:`SINGULAR_PIVOT`).
    """
    X, ratio, _, _ = _eliminate(M, B)
    return X, ratio


def _eliminate(M, B):
    """Gauss–Jordan elimination of :func:`solve_general`; also returns ``det M`` as
    ``(sign, log|det|)`` (product of the pivots and the parity of the row exchanges)."""
    M = jnp.asarray(M)
    B = jnp.asarray(B, M.dtype)
    n = M.shape[0]
    if M.ndim != 2 or M.shape != (n, n) or B.ndim != 2 or B.shape[0] != n:
        raise ValueError(f"solve_general: M must be (n, n) and B (n, k), got {M.shape} and {B.shape}")
    if n == 0:
        return B, jnp.ones((), M.dtype), jnp.ones((), M.dtype), jnp.zeros((), M.dtype)
    scale = jnp.maximum(jnp.max(jnp.abs(M)), jnp.finfo(M.dtype).tiny)
    rows = jnp.arange(n)

    def step(k, carry):
        M, B, smallest, sign, logdet = carry
        col = jnp.where(rows >= k, jnp.abs(M[:, k]), -1.0)
        p = jnp.argmax(col)
        perm = rows.at[k].set(p).at[p].set(k)
        M, B = M[perm], B[perm]
        pivot = M[k, k]
        smallest = jnp.minimum(smallest, jnp.abs(pivot))
        sign = sign * jnp.where(p == k, 1.0, -1.0) * jnp.sign(pivot)
        logdet = logdet + jnp.log(jnp.abs(pivot))
        safe = jnp.where(pivot == 0, jnp.ones_like(pivot), pivot)
        row_m, row_b = M[k] / safe, B[k] / safe
        factor = jnp.where(rows == k, 0.0, M[:, k])
        M = (M - factor[:, None] * row_m[None, :]).at[k].set(row_m)
        B = (B - factor[:, None] * row_b[None, :]).at[k].set(row_b)
        return M, B, smallest, sign, logdet

    one, zero = jnp.ones((), M.dtype), jnp.zeros((), M.dtype)
    _, X, smallest, sign, logdet = lax.fori_loop(0, n, step, (M, B, jnp.asarray(jnp.inf, M.dtype), one, zero))
    return X, smallest / scale, sign, logdet


# ---------------------------------------------------------------------------------------
# Base systems: the bracket 𝓔 = D ẋ + h
# ---------------------------------------------------------------------------------------


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
        from .kinematics import qpos_rate

        return qpos_rate(self.model, q, x)

    def bracket_terms(self, t, q, x, tau=None):
        # the unchecked kernels on one state pytree: nothing raises inside a solver loop
        from .data import compute_data
        from .kernels import bias_forces, mass_matrix, passive_forces

        data = compute_data(self.model, q, x)
        D = mass_matrix(self.model, data)
        h = bias_forces(self.model, data) - passive_forces(self.model, data)
        if tau is not None:
            h = h - tau
        return D, h

    def total_energy(self, q, x):
        from .data import compute_data
        from .kernels import kinetic_energy, potential_energy

        data = compute_data(self.model, q, x)
        return kinetic_energy(self.model, data) + potential_energy(self.model, data)


# ---------------------------------------------------------------------------------------
# Constraints
# ---------------------------------------------------------------------------------------


class Constraint(eqx.Module):
    """Protocol of a constraint on a base system (subclass it; parameters as array fields).

    ``size`` rows ``f*(t, q, x) = 0`` (:meth:`velocity`); ``linear`` says ``f*`` is affine in
    ``x`` (then ``G`` does not depend on ``x``); holonomic constraints also give their
    position residual ``φ(t, q)`` (:meth:`position`, same rows, ``dφ/dt = f*``), used by the
    Baumgarte stabilisation and :func:`project_positions`; non-holonomic ones return ``None``.
    """

    def velocity(self, base, t, q, x) -> Array:
        raise NotImplementedError

    def position(self, base, t, q) -> Array | None:
        return None

    @property
    def size(self) -> int:
        raise NotImplementedError

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f"{type(self).__name__}[{i}]" for i in range(self.size))

    @property
    def linear(self) -> bool:
        return True


class VelocityConstraint(Constraint):
    """A constraint from functions: ``f*(base, t, q, x)`` and optionally ``φ(base, t, q)``.

    Example (no lateral slip of a disk): ``VelocityConstraint(lambda b, t, q, x:
    b.contact_velocity(q, x)[1:2], size=1, label="skate")``. The functions are static (part of
    the compiled program); keep parameters on the base system or in ``params``, passed as
    ``fn(base, t, q, x, params)`` when ``params`` is not ``None``.
    """

    fn: Callable = eqx.field(static=True)
    n_rows: int = eqx.field(static=True)
    label: str = eqx.field(static=True, default="constraint")
    is_linear: bool = eqx.field(static=True, default=True)
    position_fn: Callable | None = eqx.field(static=True, default=None)
    params: Any = None

    def __init__(self, fn, size, label="constraint", linear=True, position=None, params=None):
        self.fn, self.n_rows, self.label = fn, int(size), label
        self.is_linear, self.position_fn, self.params = bool(linear), position, params

    def _call(self, f, *args):
        return f(*args) if self.params is None else f(*args, self.params)

    def velocity(self, base, t, q, x):
        return jnp.reshape(self._call(self.fn, base, t, q, x), (self.n_rows,))

    def position(self, base, t, q):
        if self.position_fn is None:
            return None
        return jnp.reshape(self._call(self.position_fn, base, t, q), (self.n_rows,))

    @property
    def size(self):
        return self.n_rows

    @property
    def names(self):
        return tuple(f"{self.label}[{i}]" for i in range(self.n_rows))

    @property
    def linear(self):
        return self.is_linear


# ---------------------------------------------------------------------------------------
# The constrained system
# ---------------------------------------------------------------------------------------


class MaggiSolution(eqx.Module):
    """Reduced dynamics at one state (docs/maggi.md M.10–M.12).

    Attributes:
        xdot: quasi-accelerations ``ẋ`` (n,).
        epsilon_dot: ``ε̇ = d/dt ε(t, q, x)`` along the motion (n − s,).
        reactions: ``Λ = Kᵀ𝓔`` (s,): generalized reactions of the constraints as written
            (Lagrange multipliers of ``f* = 0``; a contact-point velocity constraint gives
            the contact force components).
        A, K: ``∂x/∂ε`` (n, n − s) and ``∂x/∂f*`` (n, s).
        bracket: ``𝓔 = D ẋ + h`` (n,) (equals ``Gᵀ Λ``).
        pivot_ratio: conditioning of ``[E; G]`` (see :func:`solve_general`).
        result: :class:`MaggiResult`.
    """

    xdot: Array
    epsilon_dot: Array
    reactions: Array
    A: Array
    K: Array
    bracket: Array
    pivot_ratio: Array
    result: MaggiResult


class ConstrainedSystem(eqx.Module):
    """A base system plus constraints; implements :class:`jaxbody.DynamicalSystem`.

    Its velocities ``v`` are the base system's quasi-velocities ``x`` (all ``n`` of them:
    the redundant ones need not be eliminated), so ``jb.simulate(system, q0, x0, t1)``
    integrates the constrained motion. Build it with :func:`constrain`.

    Attributes:
        base: a :class:`QuasiVelocitySystem`, a :class:`ModelBase` or any object with
            ``nq``, ``nv``, ``qdot(q, x)``, ``bracket_terms(t, q, x, tau)``, ``total_energy``.
        constraints: tuple of :class:`Constraint`.
        epsilon: user characteristics ``ε(base, t, q, x)`` (n − s,) or ``None`` (partition).
        free: indices of ``x`` used as ``ε`` by coordinate partitioning, an integer array
            (n − s,) (a tuple is converted); data, not structure, so a solve can change it
            without recompiling.
        baumgarte: stabilisation rate ``ω`` in 1/s (``0``: off).
        repartitioning: re-choose the partition inside a solve when it degrades (see
            :func:`partition_solver`); ``False``: keep it and stop the solve with the result
            code ``partition_degraded`` when it degrades.
        partition_tolerance: the partition counts as degraded when its quality
            (:meth:`partition_quality`) falls below ``partition_tolerance`` times the quality
            of the partition pivoted QR chooses at the same state, or when its sign changes.
    """

    base: Any
    constraints: tuple
    epsilon: Callable | None = eqx.field(static=True)
    free: Array = eqx.field(converter=lambda f: jnp.asarray(f, dtype=jnp.int32))
    baumgarte: Array
    repartitioning: bool = eqx.field(static=True, default=True)
    partition_tolerance: float = eqx.field(static=True, default=0.1)

    @property
    def nq(self) -> int:
        return self.base.nq

    @property
    def nv(self) -> int:
        return self.base.nv

    @property
    def n_constraint(self) -> int:
        return sum(c.size for c in self.constraints)

    @property
    def constraint_names(self) -> tuple[str, ...]:
        return tuple(n for c in self.constraints for n in c.names)

    # -- DynamicalSystem protocol --------------------------------------------------------
    def qdot(self, q, v):
        return self.base.qdot(q, v)

    def acceleration(self, t, q, v, tau=None):
        return self.solve(t, q, v, tau, stabilise=True).xdot

    def total_energy(self, q, v):
        return self.base.total_energy(q, v)

    # -- constraint functions ------------------------------------------------------------
    def constraint_residual(self, t, q, x) -> Array:
        """``f*(t, q, x)`` of all constraints, concatenated (s,)."""
        if not self.constraints:
            return jnp.zeros((0,), jnp.asarray(x).dtype)
        return jnp.concatenate([c.velocity(self.base, t, q, x) for c in self.constraints])

    def position_residual(self, t, q) -> Array:
        """``φ(t, q)`` of the holonomic rows, zero on non-holonomic rows (s,)."""
        parts = []
        q = jnp.asarray(q)
        for c in self.constraints:
            p = c.position(self.base, t, q)
            parts.append(jnp.zeros((c.size,), q.dtype) if p is None else p)
        return jnp.concatenate(parts) if parts else jnp.zeros((0,), q.dtype)

    def constraint_jacobian(self, t, q, x) -> Array:
        """``G = ∂f*/∂x`` (s, n)."""
        return jax.jacfwd(lambda xx: self.constraint_residual(t, q, xx))(x)

    def characteristics(self, t, q, x) -> Array:
        """``ε(t, q, x)`` (n − s,)."""
        if self.epsilon is not None:
            return jnp.reshape(self.epsilon(self.base, t, q, x), (self.nv - self.n_constraint,))
        return self._selection(x) @ jnp.asarray(x)

    def _selection(self, x) -> Array:
        """``E = ∂ε/∂x`` of the partition: one-hot rows (n − s, n) (a product, not a gather:
        the partition changes inside a solve, and XLA's dynamic gathers are slow on CPU)."""
        return (self.free[:, None] == jnp.arange(self.nv, dtype=self.free.dtype)[None, :]).astype(jnp.asarray(x).dtype)

    def parametrisation(self, t, q, x) -> tuple[Array, Array, Array]:
        """``(A, K, pivot_ratio)`` with ``[A | K] = (∂ε̃/∂x)⁻¹`` (M.8–M.9)."""
        n, s = self.nv, self.n_constraint
        if self.epsilon is None:
            E = self._selection(x)
        else:
            E = jax.jacfwd(lambda xx: self.characteristics(t, q, xx))(x)
        G = self.constraint_jacobian(t, q, x)
        J = jnp.concatenate([E, G], axis=0) if s else E
        AK, ratio = solve_general(J, jnp.eye(n, dtype=J.dtype))
        return AK[:, : n - s], AK[:, n - s :], ratio

    @property
    def partitioned(self) -> bool:
        """``ε`` chosen by coordinate partitioning (not given), with something to choose."""
        return self.epsilon is None and 0 < self.n_constraint < self.nv

    def partition_quality(self, t, q, x) -> Array:
        """Signed quality of the coordinate partition at ``(t, q, x)`` (docs/maggi.md M.9a).

        ``det[E; G] / sqrt(det(G·Gᵀ))``: its magnitude is ``|det G_d| / sqrt(det(G·Gᵀ))``,
        ``G_d`` the columns of ``G`` of the dependent quasi-velocities, which equals
        ``1/sqrt(det(AᵀA))`` and lies in ``[0, 1]`` (``1``: the dependent velocities are
        exactly the constraint directions; ``0``: ``[E; G]`` is singular). Unchanged by
        scaling or combining the constraint rows; the sign is constant while the partition
        stays valid, so a sign change means the motion crossed a singular state.
        """
        if not self.partitioned:
            return jnp.ones((), jnp.asarray(x).dtype)
        return _quality(self._selection(x), self.constraint_jacobian(t, q, x))

    def best_partition(self, t, q, x) -> Array:
        """The free quasi-velocities that column-pivoted QR of ``G`` chooses at ``(t, q, x)``
        (ascending indices, (n − s,)); written in array operations (no LAPACK), so it runs
        inside ``jit`` and ``vmap``."""
        return _pivoted_free(self.constraint_jacobian(t, q, x))

    def with_partition(self, free) -> "ConstrainedSystem":
        """The same system with the free quasi-velocities ``free``."""
        return eqx.tree_at(lambda s: s.free, self, jnp.asarray(free, dtype=jnp.int32))

    def solve(self, t, q, x, tau=None, *, stabilise=False) -> MaggiSolution:
        """Reduced dynamics (M.11), reactions (M.12) at ``(t, q, x)``.

        ``stabilise=True`` adds the Baumgarte terms to the constraint accelerations (the
        vector field does so); reference values are taken without them.
        """
        x = jnp.asarray(x)
        q = jnp.asarray(q)
        t = jnp.asarray(t, x.dtype)
        # eagerly: compiled once per system instead of run op by op; traced (a vector field, its
        # stages, events, saved reactions): the solve is traced once and its jaxpr reused
        return _solve_jit(self, t, q, x, tau, stabilise)

    def _solve(self, t, q, x, tau, stabilise) -> MaggiSolution:
        D, h = self.base.bracket_terms(t, q, x, tau)
        return self._reduce(t, q, x, D, h, stabilise)

    def _reduce(self, t, q, x, D, h, stabilise) -> MaggiSolution:
        """M.11–M.12 from the bracket terms ``(D, h)`` (given by the base system, or by a scene)."""
        n, s = self.nv, self.n_constraint
        A, K, ratio = self.parametrisation(t, q, x)
        if s:
            qd = self.base.qdot(q, x)
            f_dot0 = jax.jvp(
                lambda tt, qq: self.constraint_residual(tt, qq, x),
                (t, q),
                (jnp.ones_like(t), qd),
            )[1]
            gamma = f_dot0
            if stabilise:
                w = self.baumgarte
                gamma = gamma + 2.0 * w * self.constraint_residual(t, q, x) + w**2 * self.position_residual(t, q)
            rhs = -(A.T @ (h + D @ (K @ (-gamma))))
            S = A.T @ D @ A
            alpha = linalg.solve_spd(S, rhs) if n - s else jnp.zeros((0,), D.dtype)
            xdot = A @ alpha - K @ gamma
        else:
            S = D
            xdot = linalg.solve_spd(D, -h)
        bracket = D @ xdot + h
        reactions = K.T @ bracket
        eps_dot = jax.jvp(
            lambda tt, qq, xx: self.characteristics(tt, qq, xx),
            (t, q, x),
            (jnp.ones_like(t), self.base.qdot(q, x), xdot),
        )[1]
        bad_param = ~(ratio > SINGULAR_PIVOT)
        bad_mass = ~jnp.all(jnp.isfinite(xdot)) & ~bad_param
        result = MaggiResult.where(bad_param, MaggiResult.singular_parametrisation, MaggiResult.successful)
        result = MaggiResult.where(bad_mass, MaggiResult.singular_reduced_mass, result)
        return MaggiSolution(
            xdot=xdot, epsilon_dot=eps_dot, reactions=reactions, A=A, K=K, bracket=bracket,
            pivot_ratio=ratio, result=result,
        )

    # -- the constraint slot of a scene (jaxbody.effects.Constraint) --------------------
    def _on_scene(self, ctx) -> "ConstrainedSystem":
        """This system with the scene's model as base, so that the scene's parameters (not
        a copy made when the constraints were built) are the ones evaluated and differentiated."""
        return self._on_model(getattr(ctx.scene, "system", None))

    def _on_model(self, model) -> "ConstrainedSystem":
        from .model import Model

        if isinstance(self.base, ModelBase) and isinstance(model, Model) and model is not self.base.model:
            return eqx.tree_at(lambda s: s.base, self, ModelBase(model))
        return self

    def accelerations(self, ctx, mass_matrix, force) -> tuple[Array, Array]:
        """Scene protocol: ``(a, Λ)`` for ``M·a = force + GᵀΛ`` with the constraints.

        The scene gives the mass matrix ``D = M`` and the right-hand side ``force`` (its
        declared effects minus the velocity terms), so the bracket is ``𝓔 = M·a − force``;
        ``a`` solves M.11 with the Baumgarte terms, ``Λ = Kᵀ𝓔`` (M.12) is the reaction of each
        constraint row as written (:attr:`constraint_names`).
        """
        v = jnp.asarray(ctx.v)
        t = jnp.asarray(ctx.t, v.dtype)
        r = self._on_scene(ctx)._reduce(t, ctx.q, v, mass_matrix, -force, True)
        return r.xdot, r.reactions

    def drift(self, ctx) -> tuple[Array, Array]:
        """Scene protocol: ``(φ(t, q), f*(t, q, x))``, the position residuals of the holonomic
        rows (zero on the others) and the velocity residuals of all rows, each (s,)."""
        v = jnp.asarray(ctx.v)
        t = jnp.asarray(ctx.t, v.dtype)
        sys = self._on_scene(ctx)
        return sys.position_residual(t, ctx.q), sys.constraint_residual(t, ctx.q, v)

    def kinetic_metric(self, t, q, x) -> Array:
        """``D(q)``: the mass matrix in quasi-velocities."""
        return self.base.bracket_terms(t, q, x, None)[0]

    def repartition(self, q, x=None, t=0.0) -> "ConstrainedSystem":
        """The same system with the coordinate partition re-chosen at ``(t, q, x)``."""
        if self.epsilon is not None:
            return self
        x = jnp.zeros((self.nv,), jnp.asarray(q).dtype) if x is None else x
        return _with_free(self, _partition(self, t, q, x))


@eqx.filter_jit
def _solve_jit(system, t, q, x, tau, stabilise):
    return system._solve(t, q, x, tau, stabilise)


def _with_free(system, free):
    return system.with_partition(free)


def _quality(E, G) -> Array:
    """Signed partition quality ``det[E; G] / sqrt(det(G·Gᵀ))`` (see
    :meth:`ConstrainedSystem.partition_quality`); ``0`` where ``[E; G]`` is singular."""
    J = jnp.concatenate([E, G], axis=0)
    _, ratio, sign, logdet = _eliminate(J, jnp.zeros((J.shape[0], 0), J.dtype))
    _, _, _, loggram = _eliminate(G @ G.T, jnp.zeros((G.shape[0], 0), J.dtype))
    quality = sign * jnp.exp(jnp.minimum(logdet - 0.5 * loggram, 0.0))
    return jnp.where(ratio > SINGULAR_PIVOT, quality, 0.0)


def _pivoted_free(G) -> Array:
    """Column-pivoted QR (Businger–Golub) of ``G`` (s, n), choice of columns only: ``s``
    times, take the column of largest remaining norm as dependent and remove its direction
    from the others (modified Gram–Schmidt). Returns the other ``n − s`` column indices,
    ascending. Plain array operations (no LAPACK: safe under ``vmap`` on CPU)."""
    s, n = G.shape
    if s == 0:
        return jnp.arange(n, dtype=jnp.int32)
    tiny = jnp.finfo(G.dtype).tiny

    def step(_, carry):
        R, chosen = carry
        norms = jnp.where(chosen, -1.0, jnp.sum(R * R, axis=0))
        j = jnp.argmax(norms)
        u = R[:, j] / jnp.sqrt(jnp.maximum(norms[j], tiny))
        R = R - u[:, None] * (u @ R)[None, :]
        return R, chosen.at[j].set(True)

    _, chosen = lax.fori_loop(0, s, step, (G, jnp.zeros((n,), bool)))
    return jnp.argsort(chosen.astype(jnp.int32), stable=True)[: n - s].astype(jnp.int32)


def _partition(system, t, q, x) -> tuple[int, ...]:
    """Free quasi-velocities by a column-pivoted QR of ``G`` at a reference state."""
    n, s = system.nv, system.n_constraint
    if s == 0:
        return tuple(range(n))
    q = jnp.asarray(q)
    dtype = q.dtype if jnp.issubdtype(q.dtype, jnp.inexact) else jnp.result_type(float)
    t, q, x = jnp.asarray(t, dtype), q.astype(dtype), jnp.asarray(x, dtype)
    return tuple(int(i) for i in np.asarray(_best_free_jit(system, t, q, x)))


@eqx.filter_jit
def _best_free_jit(system, t, q, x):
    return system.best_partition(t, q, x)


def check_constraints(system: ConstrainedSystem, q, x=None, t=0.0, *, rtol: float = 1e-9) -> None:
    """Build-time check at a reference state: raise ``ValueError`` naming redundant or
    inconsistent constraint rows (rows of ``G`` that depend on earlier rows; inconsistent
    when the affine part of a dependent linear row contradicts the earlier ones)."""
    s, n = system.n_constraint, system.nv
    if s == 0:
        return
    if s > n:
        raise ValueError(f"{s} constraints on {n} quasi-velocities: at least {s - n} are redundant")
    x = jnp.zeros((n,), jnp.asarray(q).dtype) if x is None else jnp.asarray(x)
    G = np.asarray(system.constraint_jacobian(t, q, x), dtype=np.float64)
    # affine part at x = 0 for linear constraints: f* = G x + c
    c = np.asarray(system.constraint_residual(t, q, x), dtype=np.float64) - G @ np.asarray(x)
    names = system.constraint_names
    scale = max(np.abs(G).max(), 1e-300)
    kept: list[int] = []
    for i in range(s):
        trial = G[kept + [i]]
        sv = np.linalg.svd(trial, compute_uv=False)
        if sv[-1] <= rtol * scale * max(1.0, np.sqrt(n)):
            # row i is a combination of the kept rows: consistent only if c follows the same combination
            coef, *_ = np.linalg.lstsq(G[kept].T, G[i], rcond=None) if kept else (np.zeros(0),)
            mismatch = abs(c[i] - (coef @ c[kept] if kept else 0.0))
            deps = [names[j] for j, a in zip(kept, coef) if abs(a) > 1e-9] if kept else []
            what = "inconsistent" if mismatch > 1e-9 * max(1.0, np.abs(c).max()) else "redundant"
            raise ValueError(
                f"constraints are {what}: row {names[i]!r} depends on "
                f"{deps if deps else 'nothing (it is zero)'} at the reference state; remove it "
                f"(or choose fewer components)"
            )
        kept.append(i)


def constrain(
    base,
    constraints: Sequence = (),
    *,
    q_ref: ArrayLike,
    x_ref: ArrayLike | None = None,
    t_ref: float = 0.0,
    epsilon: Callable | None = None,
    baumgarte: float = 10.0,
    repartition: bool = True,
    partition_tolerance: float = 0.1,
) -> ConstrainedSystem:
    """Add constraints to a base system (docs/maggi.md §3–4).

    Args:
        base: base system (a :class:`QuasiVelocitySystem`, :class:`ModelBase`, or a
            :class:`ConstrainedSystem`, whose constraints are kept and extended).
        constraints: constraints to add.
        q_ref, x_ref, t_ref: reference state for the build-time checks and the automatic
            partition (``x_ref`` defaults to zero).
        epsilon: user characteristics ``ε(base, t, q, x)`` returning ``n − s`` values, such
            that ``(ε, f*)`` is solvable for ``x``; ``None``: coordinate partitioning.
        baumgarte: stabilisation rate ``ω`` (1/s) of the constraint residuals.
        repartition: with coordinate partitioning, re-choose the partition during a solve
            when it degrades (``False``: stop the solve with ``partition_degraded`` instead).
        partition_tolerance: in ``(0, 1)``; the partition degrades when its quality falls
            below this fraction of the quality of the best (pivoted-QR) partition at the
            current state (docs/maggi.md §4).

    Raises:
        ValueError: redundant or inconsistent constraints at the reference state, an
            ``epsilon`` of the wrong size / not completing ``f*`` to an invertible set, or a
            ``partition_tolerance`` outside ``(0, 1)``.
    """
    from .model import Model

    if isinstance(base, Model):
        base = ModelBase(base)
    if isinstance(base, ConstrainedSystem):
        constraints = tuple(base.constraints) + tuple(constraints)
        base = base.base
    constraints = tuple(constraints)
    for c in constraints:
        if not isinstance(c, Constraint):
            raise ValueError(f"constraints must be jaxbody.maggi.Constraint instances, got {type(c).__name__}")
    q_ref = jnp.asarray(q_ref)
    dtype = q_ref.dtype if jnp.issubdtype(q_ref.dtype, jnp.inexact) else jnp.result_type(float)
    q_ref = q_ref.astype(dtype)
    x_ref = jnp.zeros((base.nv,), dtype) if x_ref is None else jnp.asarray(x_ref, dtype)
    tol = float(partition_tolerance)
    if not 0.0 < tol < 1.0:
        raise ValueError(f"constrain: partition_tolerance must lie in (0, 1), got {partition_tolerance!r}")
    system = ConstrainedSystem(
        base=base, constraints=constraints, epsilon=epsilon, free=tuple(range(base.nv)),
        baumgarte=jnp.asarray(baumgarte, dtype), repartitioning=bool(repartition), partition_tolerance=tol,
    )
    check_constraints(system, q_ref, x_ref, t_ref)
    if epsilon is None:
        system = _with_free(system, _partition(system, t_ref, q_ref, x_ref))
    else:
        n_eps = int(np.prod(jax.eval_shape(lambda: epsilon(base, t_ref, q_ref, x_ref)).shape))
        if n_eps != base.nv - system.n_constraint:
            raise ValueError(
                f"epsilon must give n - s = {base.nv} - {system.n_constraint} = "
                f"{base.nv - system.n_constraint} characteristics, got {n_eps}"
            )
        _, _, ratio = system.parametrisation(t_ref, q_ref, x_ref)
        if not float(ratio) > SINGULAR_PIVOT:
            raise ValueError(
                "epsilon does not complete the constraints to solvable extended characteristics "
                f"(ε, f*) at the reference state (pivot ratio {float(ratio):.3g})"
            )
    return system


# ---------------------------------------------------------------------------------------
# States on the constraint manifold
# ---------------------------------------------------------------------------------------


def project_velocities(system: ConstrainedSystem, q, x, t=0.0, *, iterations: int = 3):
    """Kinetic-metric projection of ``x`` onto ``f*(t, q, ·) = 0``.

    ``x⁺ = x − D⁻¹Gᵀ(GD⁻¹Gᵀ)⁻¹ f*`` (the closest admissible velocity in kinetic energy;
    exact in one step for linear constraints, Newton iterations for nonlinear ones).

    Returns:
        ``x⁺``.
    """
    if system.n_constraint == 0:
        return jnp.asarray(x)
    D = system.kinetic_metric(t, q, x)

    def step(_, xx):
        G = system.constraint_jacobian(t, q, xx)
        f = system.constraint_residual(t, q, xx)
        DiGt = linalg.solve_spd(D, G.T)
        lam = linalg.solve_spd(G @ DiGt, f)
        return xx - DiGt @ lam

    return lax.fori_loop(0, 1 if all(c.linear for c in system.constraints) else iterations, step, jnp.asarray(x))


def project_positions(system: ConstrainedSystem, q, t=0.0, *, iterations: int = 8):
    """Newton's method with minimum-norm steps on the holonomic residuals ``φ(t, q) = 0``
    (``q ← q − Jᵀ(JJᵀ)⁻¹φ``, ``J = ∂φ/∂q`` over the holonomic rows). Coordinates must be
    plain (no quaternions). Returns the projected ``q``."""
    rows = [i for i, ok in enumerate(_holonomic_mask(system)) if ok]
    q = jnp.asarray(q)
    if not rows:
        return q
    idx = jnp.asarray(rows, dtype=jnp.int32)
    phi = lambda qq: system.position_residual(t, qq)[idx]

    # Newton iterations with minimum-norm steps (optimistix's Newton needs a square
    # system; its least-squares solvers call LAPACK, which is unsafe in CPU batches).
    def step(_, qq):
        J = jax.jacfwd(phi)(qq)
        return qq - J.T @ linalg.solve_spd(J @ J.T, phi(qq))

    return lax.fori_loop(0, iterations, step, q)


def _holonomic_mask(system: ConstrainedSystem) -> list[bool]:
    mask = []
    q = jnp.zeros((system.nq,))
    for c in system.constraints:
        try:
            p = c.position(system.base, 0.0, q)
        except Exception:  # noqa: BLE001 - a position function may not accept a probe state
            p = None
        mask += [p is not None] * c.size
    return mask


def initial_state(system: ConstrainedSystem, q, x, t=0.0, *, project_initial: bool = False, atol: float = 1e-9):
    """Check (or project) an initial state against the constraints.

    Args:
        system: constrained system.
        q, x: initial coordinates and quasi-velocities.
        project_initial: project ``x`` on the constraint manifold (kinetic metric) instead of
            raising; the correction is returned.
        atol: admissible velocity residual ``max |f*|`` (scaled by ``max(1, |x|)``).

    Returns:
        ``(q, x, correction)`` with ``correction = x_projected − x`` (zeros when not projected).

    Raises:
        ValueError: the initial quasi-velocities violate the constraints, naming the rows.
    """
    q = jnp.asarray(q)
    x = jnp.asarray(x, q.dtype)
    f = np.asarray(system.constraint_residual(t, q, x))
    scale = max(1.0, float(np.max(np.abs(np.asarray(x)))) if x.size else 1.0)
    bad = [system.constraint_names[i] for i in np.flatnonzero(np.abs(f) > atol * scale)]
    if not bad:
        return q, x, jnp.zeros_like(x)
    if not project_initial:
        raise ValueError(
            f"initial velocities violate the constraints {bad} (residuals "
            f"{[float(v) for v in f[np.abs(f) > atol * scale]]}); give admissible rates or "
            "pass project_initial=True"
        )
    xp = project_velocities(system, q, x, t)
    return q, xp, xp - x


# ---------------------------------------------------------------------------------------
# Along a solution
# ---------------------------------------------------------------------------------------


def reactions(system: ConstrainedSystem, t, q, x, tau=None) -> Array:
    """Constraint reactions ``Λ`` (M.12) along a trajectory: ``t`` (N,), ``q`` (N, nq),
    ``x`` (N, nv) (e.g. ``sol.t, sol.q, sol.v`` of :func:`jaxbody.simulate`). Returns (N, s)."""
    return _reactions(system, jnp.asarray(t), jnp.asarray(q), jnp.asarray(x), tau)


@eqx.filter_jit
def _reactions(system, t, q, x, tau):
    # Λ does not depend on the partition: evaluate each state with its best-conditioned one
    return jax.vmap(lambda tt, qq, xx: with_best_partition(system, tt, qq, xx)._solve(tt, qq, xx, tau, False).reactions)(t, q, x)


def constraint_residuals(system: ConstrainedSystem, t, q, x) -> tuple[Array, Array]:
    """``(position, velocity)`` residuals along a trajectory, each (N, s): ``φ(t, q)`` on the
    holonomic rows (zero elsewhere) and ``f*(t, q, x)``."""
    return _residuals(system, jnp.asarray(t), jnp.asarray(q), jnp.asarray(x))


@eqx.filter_jit
def _residuals(system, t, q, x):
    pos = jax.vmap(system.position_residual)(t, q)
    vel = jax.vmap(system.constraint_residual)(t, q, x)
    return pos, vel


@eqx.filter_jit
def _energies(system, q, x):
    return jax.vmap(system.total_energy)(q, x)


# ---------------------------------------------------------------------------------------
# Re-partitioning during a solve
# ---------------------------------------------------------------------------------------

#: re-partition times recorded per solve (the count goes on beyond them)
MAX_RECORDED_REPARTITIONS = 16


def _constrained_of(args, partitioned_only=True):
    """The automatically partitioned :class:`ConstrainedSystem` that a solve's ``args``
    evaluate (a :class:`jaxbody.Scene`, ``(scene, ...)`` or a system), bound to the scene's
    model; ``None`` when there is none (``partitioned_only=False``: any constrained system
    with constraints)."""
    from .scene import Scene

    obj = args[0] if isinstance(args, tuple) and args else args
    if isinstance(obj, Scene):
        cs = obj.constraints
        cs = cs._on_model(obj.system) if isinstance(cs, ConstrainedSystem) else None
    else:
        cs = obj if isinstance(obj, ConstrainedSystem) else None
    if cs is None or cs.n_constraint == 0:
        return None
    return cs if cs.partitioned or not partitioned_only else None


def _is_system(node) -> bool:
    return isinstance(node, ConstrainedSystem)


def _set_partition(args, free):
    """``args`` with every :class:`ConstrainedSystem` in it using the partition ``free``."""
    return jax.tree.map(lambda n: n.with_partition(free) if _is_system(n) else n, args, is_leaf=_is_system)


def with_best_partition(obj, t, q, x):
    """``obj`` (a scene, a system, or a tuple holding one) with the partition that pivoted
    QR chooses at ``(t, q, x)``: the best-conditioned evaluation of one state (outputs
    such as the reactions along a solution, which do not depend on the partition)."""
    cs = _constrained_of(obj)
    if cs is None:
        return obj
    return _set_partition(obj, lax.stop_gradient(cs.best_partition(t, lax.stop_gradient(q), lax.stop_gradient(x))))


def _partition_check(cs, t, q, x, sign):
    """``(degraded, quality, best, best_quality)`` of the current partition of ``cs`` at a state;
    ``sign`` is the sign of the quality when last checked (``0``: unknown)."""
    t, q, x = lax.stop_gradient((t, q, x))
    G = cs.constraint_jacobian(t, q, x)
    best = _pivoted_free(G)
    c = _quality(cs._selection(x), G)
    cb = _quality(cs.with_partition(best)._selection(x), G)
    flipped = (sign != 0) & (jnp.sign(c) != sign)
    degraded = (jnp.abs(c) < cs.partition_tolerance * jnp.abs(cb)) | flipped | ~jnp.isfinite(c)
    return degraded, c, best, cb


#: codes of the solver state of :class:`PartitionSolver` (held as floats)
_OK, _DEGRADED, _SINGULAR = 0.0, 1.0, 2.0


def _parametrisation_singular(cs, t, q, x):
    """Whether ``[E; G]`` of a system with user characteristics is singular at a state (the
    pivot ratio of :meth:`ConstrainedSystem.parametrisation` at most :data:`SINGULAR_PIVOT`)."""
    t, q, x = lax.stop_gradient((t, q, x))
    _, _, ratio = cs.parametrisation(t, q, x)
    return ~(ratio > SINGULAR_PIVOT)


class PartitionSolver(DelegatingSolver):
    """A diffrax solver that keeps the coordinate partition of a constrained system while it
    is well conditioned and re-chooses it when it degrades (docs/maggi.md §4).

    The partition (the integer array ``free`` of the :class:`ConstrainedSystem` in the
    solve's ``args``) is carried in the solver state. After every step the quality of the
    current partition at the step's end (:meth:`ConstrainedSystem.partition_quality`) is
    compared with that of the partition pivoted QR chooses there; when it falls below
    ``partition_tolerance`` times it, or changes sign (the step crossed a singular state),
    the next steps use the new partition (``repartition=True``) or the solve stops with a
    failed result that :func:`partition_report` reads as ``partition_degraded``
    (``repartition=False``). When ``G`` itself loses rank (no partition is regular: a dead
    point of a linkage, redundant constraints), or, for a system with user characteristics
    ``ε`` (``partitioned=False``: only this check runs), when ``[E; G]`` is singular at the
    start or at the end of a step, the solve stops with a failed result that
    :func:`partition_report` reads as ``singular_parametrisation``. The state ``(q, x)`` is never touched: ``ẋ`` does not depend on
    the partition, so the solution is the same continuous one; only ``A``, ``K`` and the
    meaning of ``ε`` change, at the recorded times. Rejected steps change nothing.
    The error estimate and step control are the wrapped solver's.

    Attributes:
        solver: the wrapped diffrax solver.
        repartition: re-choose (``True``) or stop (``False``) on degradation.
    """

    repartition: bool = eqx.field(static=True, default=True)
    partitioned: bool = eqx.field(static=True, default=True)

    def init(self, terms, t0, t1, y0, args):
        dtype = y0[1].dtype
        t0 = jnp.asarray(t0, dtype)
        if not self.partitioned:
            cs = _constrained_of(args, partitioned_only=False)
            bad = jnp.where(_parametrisation_singular(cs, t0, y0[0], y0[1]), _SINGULAR, _OK).astype(dtype)
            times = jnp.full((MAX_RECORDED_REPARTITIONS,), jnp.nan, dtype)
            zero = jnp.zeros((), dtype)
            return self.inner.init(terms, t0, t1, y0, args), zero, zero, zero, times, bad
        cs = _constrained_of(args)
        degraded, c, best, cb = _partition_check(cs, t0, y0[0], y0[1], jnp.zeros((), y0[1].dtype))
        rank_lost = cb == 0
        times = jnp.full((MAX_RECORDED_REPARTITIONS,), jnp.nan, y0[1].dtype)
        if self.repartition:
            changed = degraded & jnp.any(best != cs.free)
            free = jnp.where(degraded, best, cs.free)
            sign = jnp.sign(jnp.where(degraded, cb, c))
            times = jnp.where(changed, times.at[0].set(t0), times)
            count = changed.astype(jnp.int32)
            bad = jnp.asarray(_OK, dtype)
        else:
            free, sign, count = cs.free, jnp.sign(c), jnp.zeros((), jnp.int32)
            bad = jnp.where(degraded, _DEGRADED, _OK).astype(dtype)
        bad = jnp.where(rank_lost, _SINGULAR, bad).astype(dtype)
        inner = self.inner.init(terms, t0, t1, y0, _set_partition(args, free))
        # integers in the carried state are held as floats: an integer leaf that changes
        # inside diffrax's checkpointed loop makes every step markedly slower on CPU
        return inner, free.astype(sign.dtype), sign, count.astype(sign.dtype), times, bad

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner, free, sign, count, times, bad = solver_state
        ok = lambda r: r == diffrax.RESULTS.successful
        if not self.partitioned:
            y1, err, dense, inner, result = self.inner.step(terms, t0, t1, y0, args, inner, made_jump)
            cs = _constrained_of(args, partitioned_only=False)
            t1 = jnp.asarray(t1, times.dtype)
            bad = jnp.where(_parametrisation_singular(cs, t1, y1[0], y1[1]), _SINGULAR, bad).astype(bad.dtype)
            result = diffrax.RESULTS.where((bad > 0) & ok(result), diffrax.RESULTS.singular, result)
            return y1, err, dense, (inner, free, sign, count, times, bad), result
        dtype = sign.dtype
        free, count = free.astype(jnp.int32), count.astype(jnp.int32)
        args = _set_partition(args, free)
        y1, err, dense, inner, result = self.inner.step(terms, t0, t1, y0, args, inner, made_jump)
        t1 = jnp.asarray(t1, times.dtype)
        degraded, c, best, cb = _partition_check(_constrained_of(args), t1, y1[0], y1[1], sign)
        # no regular partition at all: G lost rank (reported, whatever ``repartition`` says)
        bad = jnp.where((bad == _OK) & (cb == 0), _SINGULAR, bad).astype(dtype)
        if self.repartition:
            changed = degraded & jnp.any(best != free)
            slot = jnp.minimum(count, MAX_RECORDED_REPARTITIONS - 1)
            times = jnp.where(changed & (count < MAX_RECORDED_REPARTITIONS), times.at[slot].set(t1), times)
            count = count + changed.astype(jnp.int32)
            free = jnp.where(degraded, best, free)
            sign = jnp.sign(jnp.where(degraded, cb, c))
        else:
            bad = jnp.where((bad == _OK) & degraded, _DEGRADED, bad).astype(dtype)
            sign = jnp.sign(c)
        result = diffrax.RESULTS.where((bad > 0) & ok(result), diffrax.RESULTS.singular, result)
        return y1, err, dense, (inner, free.astype(dtype), sign, count.astype(dtype), times, bad), result


def partition_solver(solver, system, adjoint=None):
    """Wrap ``solver`` in a :class:`PartitionSolver` when ``system`` (a scene or a
    :class:`ConstrainedSystem`) has constraints with an automatic partition; ``solver``
    itself otherwise, and under ``diffrax.BacksolveAdjoint`` (whose backward solve has
    another state: the partition is then the one given)."""
    cs = _constrained_of(system, partitioned_only=False)
    if cs is None or isinstance(adjoint, diffrax.BacksolveAdjoint):
        return solver
    return PartitionSolver(solver, repartition=cs.repartitioning, partitioned=cs.partitioned)


def partition_report(solver, solver_state) -> dict | None:
    """What a :class:`PartitionSolver` did in a solve, from the final solver state
    (``diffrax.SaveAt(solver_state=True)``): ``{"num_repartitions": int array,
    "repartition_times": (MAX_RECORDED_REPARTITIONS,) with NaN for unused slots,
    "partition": the free quasi-velocities at the end, "degraded": bool (the partition
    degraded with re-partitioning off), "singular": bool (the parametrisation became
    singular: ``G`` lost rank, or ``[E; G]`` of user characteristics is singular)}``;
    ``None`` for other solvers."""
    if not isinstance(solver, PartitionSolver) or solver_state is None:
        return None
    _, free, _, count, times, bad = solver_state
    return {"num_repartitions": count.astype(jnp.int32), "repartition_times": times if solver.partitioned else None,
            "partition": free.astype(jnp.int32), "degraded": bad == _DEGRADED, "singular": bad == _SINGULAR}


# ---------------------------------------------------------------------------------------
# Switching kinematic structure
# ---------------------------------------------------------------------------------------


class SwitchReport(eqx.Module):
    """What happened at a change of constraint set (docs/maggi.md §6).

    Attributes:
        t: switch time.
        x_before, x_after: quasi-velocities ``x⁻``, ``x⁺``.
        impulse: constraint impulses ``Π = Kᵀ·D·(x⁺ − x⁻)`` of the new constraints (s_new,).
        generalized_impulse: ``D·(x⁺ − x⁻)`` (n,).
        energy_lost: ``½(x⁻ − x⁺)ᵀD(x⁻ − x⁺)`` (≥ 0).
        energy_before, energy_after: total energy just before and after.
    """

    t: Array
    x_before: Array
    x_after: Array
    impulse: Array
    generalized_impulse: Array
    energy_lost: Array
    energy_before: Array
    energy_after: Array


def switch_constraints(new: ConstrainedSystem, t, q, x_before) -> SwitchReport:
    """Impulsive change to the constraint set of ``new`` (M.14).

    ``x⁺ = A(AᵀDA)⁻¹AᵀD·(x⁻ + K c) − K c`` where ``c = f*(t, q, 0)`` for affine constraints
    (``x⁺ = A(AᵀDA)⁻¹AᵀD·x⁻`` for homogeneous ones); a looser set (``x⁻`` already admissible)
    keeps the velocity.
    """
    x_before = jnp.asarray(x_before)
    return _switch(new, jnp.asarray(t, x_before.dtype), jnp.asarray(q), x_before)


@eqx.filter_jit
def _switch(new, t, q, x_before):
    D = new.kinetic_metric(t, q, x_before)
    if new.n_constraint == 0:
        x_after = x_before
        K = jnp.zeros((new.nv, 0), D.dtype)
    else:
        A, K, _ = new.parametrisation(t, q, x_before)
        c = new.constraint_residual(t, q, jnp.zeros_like(x_before))
        target = x_before + K @ c
        alpha = linalg.solve_spd(A.T @ D @ A, A.T @ (D @ target))
        x_after = A @ alpha - K @ c
        if not all(cn.linear for cn in new.constraints):
            x_after = project_velocities(new, q, x_after, t)
    dx = x_after - x_before
    P = D @ dx
    return SwitchReport(
        t=jnp.asarray(t, D.dtype),
        x_before=x_before,
        x_after=x_after,
        impulse=K.T @ P,
        generalized_impulse=P,
        energy_lost=0.5 * dx @ D @ dx,
        energy_before=new.total_energy(q, x_before),
        energy_after=new.total_energy(q, x_after),
    )


class Phase(eqx.Module):
    """One phase of :func:`simulate_phases`: a constrained system and what ends it.

    Attributes:
        system: the :class:`ConstrainedSystem` of this phase.
        until: ``None`` (last phase), a time, or a function ``cond(t, q, x) -> scalar``
            whose sign change ends the phase (located by a root finder).
    """

    system: ConstrainedSystem
    until: Any = eqx.field(static=True, default=None)


class PhasedSolution(eqx.Module):
    """Result of :func:`simulate_phases`: saved states of every phase (concatenated) and the
    switch reports. ``phase`` says which phase each saved point belongs to.
    ``num_repartitions`` and ``repartition_times`` count and list the changes of coordinate
    partition inside the phases (the choice made at each switch is not counted); ``result``
    is :attr:`MaggiResult.partition_degraded` when a phase with ``repartition=False``
    stopped on a degraded partition, :attr:`MaggiResult.singular_parametrisation` when a
    phase reached a state where its parametrisation is singular (the solution then ends
    there), else ``successful``.
    ``v0_correction`` is ``x₀_projected − x₀`` when ``project_initial=True`` projected the
    initial velocities onto the first phase's constraints (zeros when they were admissible
    or not projected), as :func:`initial_state` returns it."""

    t: Array
    q: Array
    v: Array
    phase: Array
    reactions: tuple
    energy: Array
    switches: tuple
    switch_times: Array
    num_repartitions: Array
    repartition_times: Array
    result: MaggiResult
    v0_correction: Array | None = None


def _event_cond(cond):
    def fn(t, y, args, **kwargs):
        q, x = y
        return cond(t, q, x)

    return fn


def simulate_phases(
    phases: Sequence[Phase],
    q0: ArrayLike,
    x0: ArrayLike,
    t1: float,
    *,
    t0: float = 0.0,
    n_save: int = 101,
    rtol: float = 1e-9,
    atol: float = 1e-9,
    max_steps: int = 100_000,
    project_initial: bool = False,
) -> PhasedSolution:
    """Integrate a sequence of constraint sets with switches (docs/maggi.md §6).

    Each phase runs with Tsit5 until its ``until`` (a time, or the first sign change of a
    state function, located by diffrax's event handling with a Newton root finder) or
    ``t1``; at the switch the velocities are projected on the next system's constraints by
    :func:`switch_constraints` and the partition of the next system is re-chosen at the
    switch state. Inside a phase the partition is kept while well conditioned and re-chosen
    when it degrades (:class:`PartitionSolver`; counted in ``num_repartitions``); a system
    built with ``repartition=False`` ends the run there with ``result =
    partition_degraded``. Saved points: ``n_save`` evenly spaced times over ``[t0, t1]`` that
    fall in each phase, plus every phase's start and end.

    ``project_initial=True`` projects initial velocities that violate the first phase's
    constraints onto them (kinetic metric, :func:`initial_state`); the correction is
    returned as :attr:`PhasedSolution.v0_correction`.

    Raises:
        ValueError: the initial velocities violate the first phase's constraints (unless
            ``project_initial``).
        RuntimeError: a phase's solve failed (step budget, step size), naming the phase.
    """
    q = jnp.asarray(q0)
    x = jnp.asarray(x0, q.dtype)
    t = float(t0)
    grid = np.linspace(t0, t1, n_save)
    ts, qs, vs, ph, lams, energies, reports, switch_t = [], [], [], [], [], [], [], []
    n_rep, rep_times, degraded, singular = 0, [], False, False
    q, x, v0_correction = initial_state(phases[0].system, q, x, t, project_initial=project_initial)
    for k, phase in enumerate(phases):
        system = phase.system
        if k > 0:
            system = system.repartition(q, x, t)
            rep = switch_constraints(system, t, q, x)
            reports.append(rep)
            switch_t.append(t)
            x = rep.x_after
        until = phase.until
        t_end = float(t1)
        event = None
        if until is not None and not callable(until):
            t_end = min(float(until), float(t1))
        elif callable(until):
            event = diffrax.Event(_event_cond(until), root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
        if t_end <= t:
            continue
        inner = grid[(grid > t) & (grid < t_end)]
        save_ts = np.concatenate([[t], inner])
        solver = partition_solver(diffrax.Tsit5(), system)
        sol = _phase_solve(system, (q, x), t, t_end, jnp.asarray(save_ts, q.dtype), rtol, atol, max_steps, event, solver)
        report = partition_report(solver, sol.solver_state)
        if report is not None:
            n_rep += int(report["num_repartitions"])
            if report["repartition_times"] is not None:
                rt = np.asarray(report["repartition_times"])
                rep_times.extend(rt[np.isfinite(rt)].tolist())
            degraded = degraded or bool(report["degraded"])
            singular = singular or bool(report["singular"])
        if not (degraded or singular) and not bool(np.asarray((sol.result == diffrax.RESULTS.successful) | (sol.result == diffrax.RESULTS.event_occurred))):
            raise RuntimeError(f"simulate_phases: phase {k} failed: {diffrax.RESULTS[sol.result]}")
        tt = np.asarray(sol.ts)
        q_all, x_all = np.asarray(sol.ys[0]), np.asarray(sol.ys[1])
        # saves before an event, then the end of the phase (the t1 save: the event time if one
        # occurred), then unused slots filled with inf
        keep = np.isfinite(tt) & np.all(np.isfinite(q_all), axis=1)
        tt, q_all, x_all = tt[keep], q_all[keep], x_all[keep]
        t_stop = float(tt[-1])
        q_end, x_end = jnp.asarray(q_all[-1]), jnp.asarray(x_all[-1])
        ts.append(tt)
        qs.append(q_all)
        vs.append(x_all)
        ph.append(np.full(tt.shape, k))
        lams.append(np.asarray(reactions(system, jnp.asarray(tt), jnp.asarray(q_all), jnp.asarray(x_all))))
        energies.append(np.asarray(_energies(system, jnp.asarray(q_all), jnp.asarray(x_all))))
        q, x, t = q_end, x_end, t_stop
        if degraded or singular or t >= float(t1) - 1e-14:
            break
    return PhasedSolution(
        t=jnp.asarray(np.concatenate(ts)),
        q=jnp.asarray(np.concatenate(qs)),
        v=jnp.asarray(np.concatenate(vs)),
        phase=jnp.asarray(np.concatenate(ph)),
        reactions=tuple(jnp.asarray(l) for l in lams),
        energy=jnp.asarray(np.concatenate(energies)),
        switches=tuple(reports),
        switch_times=jnp.asarray(np.asarray(switch_t, dtype=np.float64)),
        num_repartitions=jnp.asarray(n_rep),
        repartition_times=jnp.asarray(np.asarray(rep_times, dtype=np.float64)),
        result=MaggiResult.where(
            jnp.asarray(singular), MaggiResult.singular_parametrisation,
            MaggiResult.where(jnp.asarray(degraded), MaggiResult.partition_degraded, MaggiResult.successful)),
        v0_correction=v0_correction,
    )


def _vf(t, y, system):
    q, x = y
    return system.qdot(q, x), system.acceleration(t, q, x, None)


@eqx.filter_jit
def _phase_solve(system, y0, t0, t1, save_ts, rtol, atol, max_steps, event, solver):
    return diffrax.diffeqsolve(
        diffrax.ODETerm(_vf),
        solver,
        t0,
        t1,
        None,
        y0,
        args=system,
        saveat=diffrax.SaveAt(ts=save_ts, t1=True, solver_state=isinstance(solver, PartitionSolver)),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
        event=event,
        throw=False,
    )
