"""Re-partitioning during a solve: a diffrax solver wrapper that keeps the coordinate partition
of a constrained system while it is well conditioned and re-chooses it when it degrades
(docs/maggi.md §4). It belongs with the solve (it wraps diffrax solvers and reads scenes)."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from ..maggi import SINGULAR_PIVOT, ConstrainedSystem
from ..maggi.constrained import partition_qualities, pivoted_free
from ..scene import Scene
from .delegating import DelegatingSolver

__all__ = ["MAX_RECORDED_REPARTITIONS", "with_best_partition", "PartitionSolver", "partition_solver", "partition_report"]

#: re-partition times recorded per solve (the count goes on beyond them)
MAX_RECORDED_REPARTITIONS = 16


def _constrained_of(args, partitioned_only=True):
    """The automatically partitioned :class:`ConstrainedSystem` that a solve's ``args``
    evaluate (a :class:`jaxbody.Scene`, ``(scene, ...)`` or a system), bound to the scene's
    model; ``None`` when there is none (``partitioned_only=False``: any constrained system
    with constraints)."""
    obj = args[0] if isinstance(args, tuple) and args else args
    if isinstance(obj, Scene):
        cs = obj.constraints
        # bound to the scene's model, so the checks evaluate the parameters being solved and
        # differentiated, not the copy taken when the constraints were built
        cs = cs.on_model(obj.system) if isinstance(cs, ConstrainedSystem) else None
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
    # a discrete choice that the outputs do not depend on: no derivative flows through it
    return _set_partition(obj, lax.stop_gradient(cs.best_partition(t, lax.stop_gradient(q), lax.stop_gradient(x))))


def _partition_check(cs, t, q, x, sign):
    """``(degraded, quality, best, best_quality)`` of the current partition of ``cs`` at a state;
    ``sign`` is the sign of the quality when last checked (``0``: unknown)."""
    # the check only decides which partition to use and ẋ does not depend on it: no
    # derivative of the solution passes here, and none is traced through the QR sweep
    t, q, x = lax.stop_gradient((t, q, x))
    G = cs.constraint_jacobian(t, q, x)
    best = pivoted_free(G)
    # both qualities through their s × s dependent blocks, with one Gram determinant
    c, cb = partition_qualities(G, cs.free, best)
    flipped = (sign != 0) & (jnp.sign(c) != sign)
    # relative to the best partition here, so the tolerance does not depend on how well G is
    # conditioned at this state; a sign change means the step crossed a singular state even if
    # |c| has recovered by its end, and a NaN quality counts as degraded
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
        # back to integers for this step only; the carried copies stay floats (see init)
        free, count = free.astype(jnp.int32), count.astype(jnp.int32)
        args = _set_partition(args, free)
        y1, err, dense, inner, result = self.inner.step(terms, t0, t1, y0, args, inner, made_jump)
        t1 = jnp.asarray(t1, times.dtype)
        degraded, c, best, cb = _partition_check(_constrained_of(args), t1, y1[0], y1[1], sign)
        # no regular partition at all: G lost rank (reported, whatever ``repartition`` says)
        bad = jnp.where((bad == _OK) & (cb == 0), _SINGULAR, bad).astype(dtype)
        if self.repartition:
            changed = degraded & jnp.any(best != free)
            # a fixed number of slots, since shapes are static inside the loop: the first changes are
            # recorded, the count goes on
            slot = jnp.minimum(count, MAX_RECORDED_REPARTITIONS - 1)
            times = jnp.where(changed & (count < MAX_RECORDED_REPARTITIONS), times.at[slot].set(t1), times)
            count = count + changed.astype(jnp.int32)
            # only the partition changes, never y1: ẋ does not depend on it, so the accepted step stands
            free = jnp.where(degraded, best, free)
            sign = jnp.sign(jnp.where(degraded, cb, c))
        else:
            bad = jnp.where((bad == _OK) & degraded, _DEGRADED, bad).astype(dtype)
            sign = jnp.sign(c)
        # a failed result, not an exception: inside diffrax's loop that is what stops one member of
        # a batch alone; partition_report tells the cause apart from the carried flag
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
