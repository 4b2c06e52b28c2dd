"""How a solve is differentiated: the adjoint, and the step budget it plans checkpoints over."""

import math

import diffrax
import jax.numpy as jnp
import numpy as np

from .._util import is_concrete

__all__ = ["CHECKPOINT_BYTES", "default_checkpoints", "step_bound", "choose_adjoint"]


def step_bound(controller, t0, t1, dt0, max_steps, dtype):
    """The step budget of the solve: ``max_steps``, or for constant steps of a known length over
    a known span the steps the solve can take, if fewer (the steps ``|t1 − t0| / dt0``, plus
    the most that rounding the time in ``dtype`` can add, plus two). Nothing changes in the
    solution; the checkpointed adjoint then plans its checkpoints over the steps that are
    taken, not over the whole budget (for a 1000-step Panda gradient under the default budget of
    100,000 steps, half the time)."""
    if not isinstance(controller, diffrax.ConstantStepSize) or dt0 is None or not is_concrete(t0, t1, dt0):
        return max_steps
    a, b, h = (float(np.asarray(x)) for x in (t0, t1, dt0))
    span = abs(b - a)
    steps = math.ceil(span / h)
    # each time t + h is rounded by at most half an ulp of max|t|: at most steps·eps·max|t|/h extra
    extra = math.ceil(steps * float(jnp.finfo(dtype).eps) * max(abs(a), abs(b)) / h)
    bound = steps + extra + 2
    return bound if max_steps is None else min(max_steps, bound)


#: Memory (bytes) the default checkpointed adjoint may give one trajectory's checkpoints.
#: diffrax's own default, about log2(max_steps) checkpoints, recomputes each step several
#: times on the way back (for a 1000-step Panda gradient on the native kernel, about twice
#: the time of one checkpoint per step); 3,000 Panda states fit in 1 MiB, 1,000 of a 20-link
#: chain.
CHECKPOINT_BYTES = 1 << 20


def default_checkpoints(max_steps: int | None, n_state: int, itemsize: int = 8) -> int:
    """Checkpoints of the default adjoint: as many as :data:`CHECKPOINT_BYTES` holds.

    One checkpoint holds the solve's loop state — the state ``(q, v)`` of ``n_state`` numbers
    and what the solver and controller carry besides — counted as ``3 * n_state`` numbers, a
    margin for solvers that carry more than RK4 (XLA's temporaries of a 1000-step RK4 gradient,
    one checkpoint a step, are about 1.2 numbers per state and checkpoint for the Panda arm and
    1.1 for a 20-link chain: benchmarks/results/gradients.md). Never fewer than
    ``ceil(log2(max_steps)) + 1`` (the O(n log n) recomputation bound of diffrax's default) and
    never more than ``max_steps`` (then no step is recomputed twice). Memory stays bounded
    whatever the horizon. (Counted as ``4 * n_state``, a 20-link chain got 819 checkpoints for
    1000 steps, and its gradient took twice as long as with one checkpoint per step.)
    """
    k = max(int(CHECKPOINT_BYTES // (3 * max(n_state, 1) * itemsize)), 2)
    if max_steps is None:
        return k
    return int(min(max_steps, max(k, math.ceil(math.log2(max(max_steps, 2))) + 1)))


def choose_adjoint(adjoint, max_steps=None, n_state=None, itemsize=8):
    """The diffrax adjoint of ``simulate``'s ``adjoint`` argument: ``None``/``"checkpoint"``
    (recursive checkpointing with :func:`default_checkpoints` when the state size ``n_state`` is
    given), ``"backsolve"``, ``"forward"``, or a diffrax adjoint as it is."""
    if adjoint is None or (isinstance(adjoint, str) and adjoint == "checkpoint"):
        if n_state is None:
            return diffrax.RecursiveCheckpointAdjoint()
        return diffrax.RecursiveCheckpointAdjoint(checkpoints=default_checkpoints(max_steps, n_state, itemsize))
    if isinstance(adjoint, str):
        if adjoint == "backsolve":
            return diffrax.BacksolveAdjoint()
        if adjoint == "forward":
            return diffrax.ForwardMode()
        raise ValueError(f"simulate: adjoint must be 'checkpoint', 'backsolve', 'forward' or a diffrax adjoint, got {adjoint!r}")
    return adjoint
