"""A failed solve, reported: ``throw=True`` raises a :class:`SimulationError` saying when, in
which state and why, eagerly or from inside a compiled program."""

import equinox as eqx
import jax
import numpy as np
from jax import lax

from .._util import is_concrete
from .solution import RESULTS, SimulationError, Solution, result_code, result_from_code

__all__ = ["raise_on_failure", "failure_message"]


def raise_on_failure(sol: Solution) -> Solution:
    """``throw=True``: a failed solve raises a :class:`SimulationError` naming the time reached,
    the reason and the state there. Eagerly it is raised here; under ``jit``/``vmap``/``grad``
    the check is a ``lax.cond`` on "any member failed" whose failing branch calls back to the
    host with ``(t_final, q_final, v_final)`` and raises there (JAX re-raises it as its runtime
    error with the same text). The callback sits in a custom JVP, so derivatives pass through."""
    failed = ~sol.success
    code = result_code(sol.result)
    # eager solves raise a plain Python error here, with this call's traceback; only a traced
    # one needs the callback
    if is_concrete(code, sol.t_final, sol.q_final, sol.v_final):
        if bool(np.any(np.asarray(failed))):
            raise SimulationError(
                failure_message(np.asarray(failed), np.asarray(code), np.asarray(sol.t_final),
                                np.asarray(sol.q_final), np.asarray(sol.v_final))
            )
        return sol
    # the check is threaded through every array of the solution, so JAX cannot drop it as dead
    # code and no result is used before it has run
    dynamic, static = eqx.partition(sol, eqx.is_array)
    dynamic = _fail_with_state(dynamic, failed, code, sol.t_final, sol.q_final, sol.v_final)
    return eqx.combine(dynamic, static)


@eqx.filter_custom_jvp
def _fail_with_state(dynamic, failed, code, t, q, v):
    leaves, treedef = jax.tree.flatten(dynamic)
    shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]

    def report(failed, code, t, q, v, *rest):
        raise SimulationError(failure_message(failed, code, t, q, v))

    def fail():
        return jax.pure_callback(report, shapes, failed, code, t, q, v, *leaves, vmap_method="broadcast_all")

    # one predicate for a whole vmapped batch: the failing branch runs (and raises) only when
    # some member failed, and reports the first one that did
    out = lax.cond(eqx.internal.unvmap_any(failed), fail, lambda: leaves)
    return jax.tree.unflatten(treedef, out)


# the check changes no value: tangents pass through unchanged (a callback has no derivative rule)
@_fail_with_state.def_jvp
def _fail_with_state_jvp(primals, tangents):
    return _fail_with_state(*primals), tangents[0]


def failure_message(failed, code, t, q, v) -> str:
    """The text of a :class:`SimulationError`: the first failed member's time, reason (from its
    result ``code``) and state (``failed`` marks the failed members of a batch)."""
    failed = np.asarray(failed)
    batch = failed.shape
    flat = failed.reshape(-1)
    i = int(np.flatnonzero(flat)[0]) if flat.any() else 0
    # every field broadcast to the batch shape: under vmap_method="broadcast_all" some arrive unbatched
    code = int(np.broadcast_to(np.asarray(code), batch).reshape(-1)[i])
    t = float(np.broadcast_to(np.asarray(t), batch).reshape(-1)[i])
    q = np.asarray(q).reshape((-1,) + np.shape(q)[len(batch):])[i]
    v = np.asarray(v).reshape((-1,) + np.shape(v)[len(batch):])[i]
    where = f" (batch member {np.unravel_index(i, batch) if len(batch) > 1 else i} of {flat.size})" if batch else ""
    return (
        f"simulate: the solve failed at t = {t:.6g}{where}: {_reason(code)}\n"
        f"  state at the failure: q = {q.tolist()}, v = {v.tolist()}\n"
        f"  pass throw=False to get the trajectory up to the failure and the result code"
    )


def _reason(code: int) -> str:
    """Why the solve failed, in words; jaxbody's own wording where diffrax's message would
    mislead (a non-finite state is a blow-up of the motion, not a solver bug)."""
    if code == int(np.asarray(result_code(RESULTS.nonfinite))):
        return ("the state became NaN or inf (the motion blew up, e.g. a fixed step too large for stiff "
                "dynamics, or a force returned NaN); the state shown is the first non-finite one, the "
                "trajectory saved before it is finite")
    # "successful" with a failed solve: diffrax stopped without a code of its own
    if code == int(np.asarray(result_code(RESULTS.successful))):
        return "the step-size controller or the solver's root finder failed"
    return RESULTS[result_from_code(np.asarray(code))]
