"""The constrained system: a base system plus constraints (docs/maggi.md M.8–M.12).

With extended characteristics ``ε̃ = (ε, f*)`` solvable for ``x``, ``[A | K] = ∂x/∂ε̃`` is the
inverse of ``[E; G]`` (``E = ∂ε/∂x``, ``G = ∂f*/∂x``; :func:`jaxbody.linalg.solve_general`),
Maggi's equations ``Aᵀ·𝓔 = 0`` give the reduced system ``(AᵀDA)·α = −Aᵀ(h − D·K·γ)`` (M.11)
and the reactions are ``Λ = Kᵀ·𝓔`` (M.12). ``ε`` is given by the user or chosen by coordinate
partitioning: :func:`pivoted_free` (column-pivoted QR of ``G``) picks the free quasi-velocities,
:func:`selection_quality` measures a choice (M.9a).
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .. import linalg
from .._types import Array
from .._util import compiled_when_eager
from ..linalg import gauss_jordan, solve_general
from ..model import Model
from ..shared_evaluation import shared_evaluations
from .systems import SINGULAR_PIVOT, MaggiResult, ModelBase

__all__ = ["MaggiSolution", "ConstrainedSystem", "partition_qualities", "pivoted_free", "selection_quality"]


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
    # ``free`` is a traced leaf, so the partition solver swaps it between steps without recompiling;
    # ``epsilon`` and ``repartitioning`` are static: they decide what is traced (a function, a branch).
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

    def coordinate_chart(self):
        """The base system's chart (:class:`jaxbody.scene.CoordinateChart`), or ``None``: the
        constraints restrict the motion, not where the coordinates are regular."""
        declare = getattr(self.base, "coordinate_chart", None)
        return declare() if callable(declare) else None

    # -- constraint functions ------------------------------------------------------------
    @compiled_when_eager
    @shared_evaluations()  # every constraint's rows from one computation of the frames
    def constraint_residual(self, t, q, x) -> Array:
        """``f*(t, q, x)`` of all constraints, concatenated (s,)."""
        if not self.constraints:
            return jnp.zeros((0,), jnp.asarray(x).dtype)
        return jnp.concatenate([c.velocity(self.base, t, q, x) for c in self.constraints])

    @shared_evaluations()  # every constraint's rows from one computation of the frames
    def constraint_velocity_bias(self, t, q, x) -> Array:
        """``γ = ∂f*/∂q·q̇ + ∂f*/∂t`` at fixed ``x`` (M.6), all rows (s,): each constraint's
        closed form (:meth:`Constraint.velocity_bias`) where it gives one, else a forward-mode
        product along ``q̇ = π(q, x)`` (``∂f*/∂q`` never formed)."""
        qd = self.base.qdot(q, x)

        def differentiated(residual):
            return jax.jvp(lambda tt, qq: residual(tt, qq, x), (t, q), (jnp.ones_like(t), qd))[1]

        closed = [c.velocity_bias(self.base, t, q, x) for c in self.constraints]
        if all(b is None for b in closed):
            # one product for all rows: the program of systems without closed forms as before
            return differentiated(self.constraint_residual)
        return jnp.concatenate([
            differentiated(lambda tt, qq, xx, c=c: c.velocity(self.base, tt, qq, xx)) if b is None
            else jnp.reshape(b, (c.size,)) for c, b in zip(self.constraints, closed)
        ])

    @compiled_when_eager(quick=True)  # a check: evaluated eagerly about once per system
    @shared_evaluations()  # every constraint's rows from one computation of the frames
    def position_residual(self, t, q) -> Array:
        """``φ(t, q)`` of the holonomic rows, zero on non-holonomic rows (s,)."""
        parts = []
        q = jnp.asarray(q)
        for c in self.constraints:
            p = c.position(self.base, t, q)
            # zeros on non-holonomic rows keep φ aligned with f* row by row: the Baumgarte term ω²φ
            # (M.13) then acts on the holonomic rows only
            parts.append(jnp.zeros((c.size,), q.dtype) if p is None else p)
        return jnp.concatenate(parts) if parts else jnp.zeros((0,), q.dtype)

    @compiled_when_eager
    @shared_evaluations()  # every constraint's rows from one computation of the frames
    def constraint_jacobian(self, t, q, x) -> Array:
        """``G = ∂f*/∂x`` (s, n): each constraint's closed form
        (:meth:`Constraint.velocity_jacobian`) where it gives one, else forward mode in ``x``."""
        closed = [c.velocity_jacobian(self.base, t, q, x) for c in self.constraints]
        if all(g is None for g in closed):
            return jax.jacfwd(lambda xx: self.constraint_residual(t, q, xx))(x)
        return jnp.concatenate([
            jax.jacfwd(lambda xx, c=c: c.velocity(self.base, t, q, xx))(x) if g is None
            else jnp.reshape(g, (c.size, self.nv)) for c, g in zip(self.constraints, closed)
        ], axis=0)

    def characteristics(self, t, q, x) -> Array:
        """``ε(t, q, x)`` (n − s,)."""
        if self.epsilon is not None:
            return jnp.reshape(self.epsilon(self.base, t, q, x), (self.nv - self.n_constraint,))
        # ε = x[free] written as E·x: linear in x with ∂ε/∂x = E exactly, as parametrisation assumes
        return self.selection(x) @ jnp.asarray(x)

    def selection(self, x) -> Array:
        """``E = ∂ε/∂x`` of the partition: one-hot rows (n − s, n) (a product, not a gather:
        the partition changes inside a solve, and XLA's dynamic gathers are slow on CPU)."""
        return _partition_selections(self.free, self.nv, jnp.asarray(x).dtype)[0]

    @compiled_when_eager
    def parametrisation(self, t, q, x) -> tuple[Array, Array, Array]:
        """``(A, K, pivot_ratio)`` with ``[A | K] = (∂ε̃/∂x)⁻¹`` (M.8–M.9).

        With ``ε`` chosen by partitioning, ``[E; G]`` is inverted through its ``s × s`` block:
        with ``x = Eᵀε + Dᵀx_d`` (``D``: one-hot rows of the dependent quasi-velocities, ascending),
        ``G x = f*`` gives ``x_d = G_d⁻¹ (f* − G_f ε)``, ``G_f = G Eᵀ``, ``G_d = G Dᵀ``, so
        ``A = Eᵀ − Dᵀ G_d⁻¹ G_f`` and ``K = Dᵀ G_d⁻¹``: an elimination over ``s`` columns instead of ``n`` (a biped's 10 loop rows
        among 32 velocities). ``pivot_ratio`` is then the smallest pivot of ``G_d``'s elimination
        over the largest entry of ``[E; G]``, zero when ``free`` repeats or misses an index.
        """
        n, s = self.nv, self.n_constraint
        if self.partitioned:
            G = self.constraint_jacobian(t, q, x)
            E, Dsel = _partition_selections(self.free, n, G.dtype)
            YZ, ratio, _, _ = _dependent_block(G, E, Dsel, jnp.concatenate([G @ E.T, jnp.eye(s, dtype=G.dtype)], axis=1))
            return E.T - Dsel.T @ YZ[:, : n - s], Dsel.T @ YZ[:, n - s :], ratio
        if self.epsilon is None:
            E = self.selection(x)
        else:
            E = jax.jacfwd(lambda xx: self.characteristics(t, q, xx))(x)
        G = self.constraint_jacobian(t, q, x)
        # [E; G] is square; the first n − s columns of its inverse are A = ∂x/∂ε, the last s are
        # K = ∂x/∂f*, so that GA = 0, GK = I, EA = I, EK = 0 (M.8)
        J = jnp.concatenate([E, G], axis=0) if s else E
        # Gauss–Jordan with partial pivoting rather than LAPACK: batched LAPACK calls are unsafe
        # under vmap on CPU, and its pivot ratio is the singularity test of M.9
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
            # no partition to degrade: the best quality, so the partition solver never re-chooses
            return jnp.ones((), jnp.asarray(x).dtype)
        return partition_qualities(self.constraint_jacobian(t, q, x), self.free)[0]

    def best_partition(self, t, q, x) -> Array:
        """The free quasi-velocities that column-pivoted QR of ``G`` chooses at ``(t, q, x)``
        (ascending indices, (n − s,)); written in array operations (no LAPACK), so it runs
        inside ``jit`` and ``vmap``."""
        return pivoted_free(self.constraint_jacobian(t, q, x))

    def with_partition(self, free) -> "ConstrainedSystem":
        """The same system with the free quasi-velocities ``free``."""
        return eqx.tree_at(lambda s: s.free, self, jnp.asarray(free, dtype=jnp.int32))

    def with_best_partition(self, t, q, x) -> "ConstrainedSystem":
        """The same system with the partition pivoted QR chooses at ``(t, q, x)`` (itself when
        ``ε`` is not chosen by partitioning): the best-conditioned evaluation of one state, for
        outputs that do not depend on the partition (the reactions along a solution)."""
        if not self.partitioned:
            return self
        # the choice of columns is discrete (an argmax) and the outputs do not depend on it: no
        # derivative should flow through it
        return self.with_partition(lax.stop_gradient(self.best_partition(t, lax.stop_gradient(q), lax.stop_gradient(x))))

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

    def solve_inline(self, t, q, x, tau=None, stabilise=False) -> MaggiSolution:
        """:meth:`solve` traced into the caller's program (no compiled call of its own, no
        conversion of the arguments): for callers that already trace, such as a ``vmap`` over
        saved states."""
        # the base's bracket terms and every constraint row ask for the frames of the same q
        with shared_evaluations():
            D, h = self.base.bracket_terms(t, q, x, tau)
            return self._reduce(t, q, x, D, h, stabilise)

    def _reduce(self, t, q, x, D, h, stabilise) -> MaggiSolution:
        """M.11–M.12 from the bracket terms ``(D, h)`` (given by the base system, or by a scene)."""
        n, s = self.nv, self.n_constraint
        A, K, ratio = self.parametrisation(t, q, x)
        if s:
            gamma = self.constraint_velocity_bias(t, q, x)
            # Baumgarte (M.13): residuals obey φ̈ + 2ωφ̇ + ω²φ = 0; exact solutions (φ = f* = 0) are unchanged
            if stabilise:
                w = self.baumgarte
                gamma = gamma + 2.0 * w * self.constraint_residual(t, q, x) + w**2 * self.position_residual(t, q)
            # any ẋ = Aα − Kγ satisfies Gẋ + γ = 0 (GA = 0, GK = I); Maggi's equations Aᵀ𝓔 = 0 fix α:
            # (AᵀDA)α = −Aᵀ(h − DKγ) (M.11)
            rhs = -(A.T @ (h + D @ (K @ (-gamma))))
            S = A.T @ D @ A
            # AᵀDA is positive definite when D is and A has full column rank, so Cholesky suffices;
            # it returns NaN instead of raising, which becomes singular_reduced_mass below
            alpha = linalg.solve_spd(S, rhs) if n - s else jnp.zeros((0,), D.dtype)
            xdot = A @ alpha - K @ gamma
        else:
            S = D
            xdot = linalg.solve_spd(D, -h)
        bracket = D @ xdot + h
        # Λ = Kᵀ𝓔 (M.12): 𝓔 is orthogonal to the columns of A, so 𝓔 = GᵀΛ and Λ are the
        # multipliers of the rows of f* as written
        reactions = K.T @ bracket
        eps_dot = jax.jvp(
            lambda tt, qq, xx: self.characteristics(tt, qq, xx),
            (t, q, x),
            # tangents in the primals' dtypes: a float32 state of a system with float64
            # parameters computes ẋ in float64, and jvp needs them equal
            (jnp.ones_like(t), self.base.qdot(q, x).astype(q.dtype), xdot.astype(x.dtype)),
        )[1]
        # result codes, not exceptions: inside a solver loop under vmap raising would stop the whole
        # batch; the negated test also flags a NaN ratio; a non-finite ẋ blames AᵀDA only if [E; G] was regular
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
        return self.on_model(getattr(ctx.scene, "system", None))

    def on_model(self, model) -> "ConstrainedSystem":
        """This system with ``model`` as base when its base is a :class:`ModelBase` of another
        :class:`jaxbody.Model` (a scene's model, whose parameters are the ones to evaluate and
        differentiate); itself otherwise."""
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

    @compiled_when_eager
    def kinetic_metric(self, t, q, x) -> Array:
        """``D(q)``: the mass matrix in quasi-velocities."""
        return self.base.bracket_terms(t, q, x, None)[0]

    def repartition(self, q, x=None, t=0.0) -> "ConstrainedSystem":
        """The same system with the coordinate partition re-chosen at ``(t, q, x)``."""
        if self.epsilon is not None:
            return self
        x = jnp.zeros((self.nv,), jnp.asarray(q).dtype) if x is None else x
        return self.with_partition(_partition(self, t, q, x))


@eqx.filter_jit
def _solve_jit(system, t, q, x, tau, stabilise):
    return system.solve_inline(t, q, x, tau, stabilise)


def _partition_selections(free, n: int, dtype) -> tuple[Array, Array]:
    """``(E, D)``: one-hot rows of the free quasi-velocities ``free`` (in their order) and of the
    others (ascending), built as products (no gathers: ``free`` changes inside a solve)."""
    cols = jnp.arange(n, dtype=free.dtype)
    E = (free[:, None] == cols[None, :])
    is_free = jnp.any(E, axis=0)
    # the k-th dependent column is the one preceded by k other dependent columns
    rank = jnp.cumsum(~is_free) - 1
    D = (rank[None, :] == jnp.arange(n - free.shape[0])[:, None]) & ~is_free[None, :]
    return E.astype(dtype), D.astype(dtype)


def _dependent_block(G, E, D, B):
    """Gauss–Jordan of the dependent block ``G_d = G Dᵀ`` against ``B``: ``(G_d⁻¹B, pivot_ratio,
    sign, log|det G_d|)``, the ratio being the smallest pivot over the largest entry of
    ``[E; G]`` and zero unless ``E`` selects ``n − s`` distinct columns (repeated or missing
    indices make ``[E; G]`` singular)."""
    s, n = G.shape
    G_dep = G @ D.T
    X, ratio, sign, logdet = gauss_jordan(G_dep, B)
    tiny = jnp.finfo(G.dtype).tiny
    ratio = ratio * jnp.maximum(jnp.max(jnp.abs(G_dep)), tiny) / jnp.maximum(jnp.max(jnp.abs(G)), 1.0)
    distinct = (jnp.sum(E) == n - s) & (jnp.sum(jnp.max(E, axis=0)) == n - s)
    return X, jnp.where(distinct, ratio, 0.0), sign, logdet


def partition_qualities(G, *frees) -> tuple[Array, ...]:
    """The signed quality of :func:`selection_quality` of each partition ``free`` (indices of
    the free quasi-velocities, each (n − s,)) for one ``G``, through the partitions' ``s × s``
    dependent blocks: with ``P`` the column permutation that puts the free columns first (in
    their order) and the dependent ones after (ascending), ``[E; G] P = [[I, 0], [G_f, G_d]]``,
    so ``det[E; G] = det G_d · sign P``. ``det(G·Gᵀ)`` is computed once for all of them."""
    s, n = G.shape
    _, _, _, loggram = gauss_jordan(G @ G.T, jnp.zeros((s, 0), G.dtype))
    cols = jnp.arange(n)
    out = []
    for free in frees:
        free = jnp.asarray(free, jnp.int32)
        E, D = _partition_selections(free, n, G.dtype)
        _, ratio, sign, logdet = _dependent_block(G, E, D, jnp.zeros((s, 0), G.dtype))
        # the sign of P: the parity of the inversions of the column order (free..., dependent...)
        order = jnp.concatenate([free, (D @ cols.astype(G.dtype)).astype(jnp.int32)])
        inversions = jnp.sum(jnp.triu(order[:, None] > order[None, :], k=1))
        sign = sign * (1 - 2 * (inversions % 2)).astype(G.dtype)
        quality = sign * jnp.exp(jnp.minimum(logdet - 0.5 * loggram, 0.0))
        out.append(jnp.where(ratio > SINGULAR_PIVOT, quality, 0.0))
    return tuple(out)


def selection_quality(E, G) -> Array:
    """Signed quality ``det[E; G] / sqrt(det(G·Gᵀ))`` of the partition with selection rows
    ``E`` for the constraint Jacobian ``G`` (docs/maggi.md M.9a; see
    :meth:`ConstrainedSystem.partition_quality`); ``0`` where ``[E; G]`` is singular."""
    J = jnp.concatenate([E, G], axis=0)
    _, ratio, sign, logdet = gauss_jordan(J, jnp.zeros((J.shape[0], 0), J.dtype))
    _, _, _, loggram = gauss_jordan(G @ G.T, jnp.zeros((G.shape[0], 0), J.dtype))
    # log-determinants do not overflow; the minimum clips round-off above the bound |c| ≤ 1 (M.9a)
    quality = sign * jnp.exp(jnp.minimum(logdet - 0.5 * loggram, 0.0))
    # singular [E; G]: 0, which the partition solver reads as lost rank for the best partition
    return jnp.where(ratio > SINGULAR_PIVOT, quality, 0.0)


def pivoted_free(G) -> Array:
    """Column-pivoted QR (Businger–Golub) of ``G`` (s, n), choice of columns only: ``s``
    times, take the column of largest remaining norm as dependent and remove its direction
    from the others (modified Gram–Schmidt). Returns the other ``n − s`` column indices,
    ascending. Plain array operations (no LAPACK: safe under ``vmap`` on CPU)."""
    s, n = G.shape
    if s == 0:
        return jnp.arange(n, dtype=jnp.int32)
    # only which columns become pivots matters, so the factors are never kept; a Gram–Schmidt
    # sweep in array operations runs under vmap, where batched LAPACK is unsafe on CPU
    tiny = jnp.finfo(G.dtype).tiny

    def step(_, carry):
        R, chosen = carry
        # chosen columns masked: the largest remaining norm gives the best-conditioned dependent block
        norms = jnp.where(chosen, -1.0, jnp.sum(R * R, axis=0))
        j = jnp.argmax(norms)
        # tiny keeps a zero column (G rank-deficient) finite; the quality test detects lost rank
        u = R[:, j] / jnp.sqrt(jnp.maximum(norms[j], tiny))
        R = R - u[:, None] * (u @ R)[None, :]
        return R, chosen.at[j].set(True)

    _, chosen = lax.fori_loop(0, s, step, (G, jnp.zeros((n,), bool)))
    # a stable sort of the 0/1 mask lists the free columns first, ascending, with a static size
    return jnp.argsort(chosen.astype(jnp.int32), stable=True)[: n - s].astype(jnp.int32)


def _partition(system, t, q, x) -> tuple[int, ...]:
    """Free quasi-velocities by a column-pivoted QR of ``G`` at a reference state."""
    n, s = system.nv, system.n_constraint
    if s == 0:
        return tuple(range(n))
    q = jnp.asarray(q)
    # integer reference coordinates would make G integer: the choice is made in floating point
    dtype = q.dtype if jnp.issubdtype(q.dtype, jnp.inexact) else jnp.result_type(float)
    t, q, x = jnp.asarray(t, dtype), q.astype(dtype), jnp.asarray(x, dtype)
    return tuple(int(i) for i in np.asarray(_best_free_jit(system, t, q, x)))


@eqx.filter_jit
def _best_free_jit(system, t, q, x):
    return system.best_partition(t, q, x)
