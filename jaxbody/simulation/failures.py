"""A failed solve, reported: ``throw=True`` raises a :class:`SimulationError` saying when, in
which state and why, eagerly or from inside a compiled program.

Why a solve failed is diagnosed after it, at the state where it stopped, outside the solver's
loop (:func:`diagnose`): a force that returns NaN there (or just next to it, where the solver's
trial steps went), a mass matrix that is not positive definite, equations of motion that are
singular (finite forces, non-finite accelerations: a singular coordinate chart), or a step size
that collapsed. Eagerly every one of these is checked; under ``jit``/``vmap`` the message gives
the result code's reason and the step statistics.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._util import is_concrete
from ..dynamics import mass_matrix
from ..model import Model
from ..scene import ModelScene
from ..scene.chart import chart_of
from .solution import RESULTS, SUCCESS_CODES, SimulationError, Solution, result_code, result_from_code

__all__ = ["raise_on_failure", "failure_message", "diagnose", "explain_failure", "mark_invalid"]

# a step this much shorter than the interval is a collapse, not a long motion
_COLLAPSE = 1e-7
# the step guard's code for a step that left the scene's coordinate chart, and diffrax's for a
# singular solve (which a chart's margins may still explain)
_CHART = int(np.asarray(result_code(RESULTS.singular_coordinates)))
_SINGULAR = int(np.asarray(result_code(RESULTS.singular)))


def mark_invalid(sol: Solution, valid, t0) -> Solution:
    """The members of a batch that failed the boundary check (``valid`` false) marked as such:
    result ``invalid_input``, ``t_final = t0`` and NaN states and energies (they integrated a
    frozen placeholder state, which must not pass for a trajectory)."""
    nan = lambda x: None if x is None else jnp.where(_expand(valid, x), x, jnp.nan)  # noqa: E731
    return dataclasses.replace(
        sol,
        result=RESULTS.where(valid, sol.result, RESULTS.invalid_input),
        t_final=jnp.where(valid, sol.t_final, jnp.asarray(t0, sol.t_final.dtype)),
        q=nan(sol.q), v=nan(sol.v), q_final=nan(sol.q_final), v_final=nan(sol.v_final),
        energy=nan(sol.energy), energy_drift=nan(sol.energy_drift), energy0=nan(sol.energy0),
        work={k: nan(w) for k, w in sol.work.items()},
    )


def _expand(flag, x):
    return jnp.reshape(flag, jnp.shape(flag) + (1,) * (jnp.ndim(x) - jnp.ndim(flag)))


def diagnose(scene, t, q, v, code, num_steps, t0, t1) -> str | None:
    """Why a solve stopped at ``(t, q, v)``, in words, or ``None`` when nothing specific is found
    (concrete values; evaluated once, after the solve)."""
    if not (np.all(np.isfinite(np.asarray(q))) and np.all(np.isfinite(np.asarray(v)))):
        return None
    t, q, v = jnp.asarray(t, q.dtype), jnp.asarray(q), jnp.asarray(v)
    # a step guard that stopped the solve at the edge of the scene's coordinate chart: named first,
    # the dynamics there are finite and the checks below would find nothing
    chart = chart_of(scene)
    if chart is not None:
        why = chart.explain_at(q, float(t))
        if why is not None:
            return why
    # the forces where the solve stopped and just ahead of it, along the motion: an adaptive
    # solver retries ever smaller steps when every trial stage ends in NaN
    try:
        a = scene.acceleration(t, q, v)
        rate = scene.qdot(q, v)
    except Exception:  # noqa: BLE001 (a diagnosis must not hide the failure it explains)
        return None
    forces = getattr(scene, "effect_forces", None)
    if forces is not None:
        for h in (0.0, 1e-9, 1e-6, 1e-3):
            qh, vh = q + h * rate, v + h * jnp.where(jnp.isfinite(a), a, 0.0)
            ctx = scene.context(t + h, qh, vh)
            for eff in scene.effects:
                f = np.asarray(eff.generalized_force(ctx))
                if not np.all(np.isfinite(f)):
                    where = "at this state" if h == 0 else f"a step of {h:g} s ahead of this state"
                    return (f"the {eff.name} force returned NaN or inf {where} (a control law or force that "
                            "breaks down there); the solver could not step past it")
    model = scene.system if isinstance(scene, ModelScene) else None
    if isinstance(model, Model):
        try:
            lam = np.linalg.eigvalsh(np.asarray(mass_matrix(model, q), dtype=np.float64))
        except ValueError as err:  # the input checks of mass_matrix name a bad parameter
            return f"the model is invalid at this state: {err}"
        if not (np.all(np.isfinite(lam)) and lam[0] > 1e-12 * max(abs(lam[-1]), 1e-300)):
            return (f"the mass matrix is not positive definite at this state (eigenvalues from {lam[0]:.3g} to "
                    f"{lam[-1]:.3g}): a massless moving body, a zero joint axis or a negative mass")
    if not np.all(np.isfinite(np.asarray(a))):
        return ("the accelerations are NaN or inf at this state while the forces are finite: the equations of "
                "motion are singular here (a singular coordinate chart, e.g. an angle at which the coordinates "
                "degenerate, or a dead point of a linkage)")
    if code == int(np.asarray(result_code(RESULTS.max_steps_reached))):
        n = max(int(num_steps), 1)
        span = float(t) - float(t0)
        h = span / n
        if h < _COLLAPSE * (float(t1) - float(t0)):
            return (f"the step size collapsed: {n} steps advanced the solve by {span:.3g} s (average step "
                    f"{h:.3g} s): stiff dynamics (try solver='kvaerno5'), a discontinuity in the forces, or a "
                    "force that breaks down near this state; raising max_steps will not help")
        # the budget simply ran out: diffrax's own advice holds, with the figures behind it
        return (f"{_reason(code)} ({n} steps reached t = {float(t):.6g}, average step {h:.3g} s; loosen rtol/atol "
                "or, for stiff springs or dampers, use an implicit solver: solver='kvaerno5')")
    return None


def explain_failure(scene, sol: Solution, t0, t1) -> str:
    """Why the (single, concrete) solve ``sol`` of ``scene`` from ``t0`` to ``t1`` failed, in words:
    the diagnosis at its final state, else its result code's reason (``throw=False`` callers, such
    as the command line, report this)."""
    code = int(np.asarray(result_code(sol.result)))
    why = diagnose(scene, sol.t_final, sol.q_final, sol.v_final, code, np.asarray(sol.stats["num_steps"]), t0, t1)
    return why or _reason(code)


def raise_on_failure(sol: Solution, scene=None, t0=None, t1=None) -> Solution:
    """``throw=True``: a failed solve raises a :class:`SimulationError` naming the time reached,
    the reason and the state there. Eagerly it is raised here; under ``jit``/``vmap``/``grad``
    the check is a ``lax.cond`` on "any member failed" whose failing branch calls back to the
    host with ``(t_final, q_final, v_final)`` and raises there (JAX re-raises it as its runtime
    error with the same text). The callback sits in a custom JVP, so derivatives pass through."""
    code = result_code(sol.result)
    chart = chart_of(scene)
    # eager solves raise a plain Python error here, with this call's traceback; only a traced
    # one needs the callback
    if is_concrete(code, sol.t_final, sol.q_final, sol.v_final):
        # Solution.success in NumPy: eager JAX operations would each compile on a first call
        failed = ~np.isin(np.asarray(code), SUCCESS_CODES)
        if bool(np.any(failed)):
            why = None
            if scene is not None and np.ndim(code) == 0 and is_concrete(scene, t0, t1):
                why = diagnose(scene, sol.t_final, sol.q_final, sol.v_final, int(np.asarray(code)),
                               np.asarray(sol.stats["num_steps"]), t0, t1)
            margins = None if chart is None else _chart_margins(chart, sol.q_final)
            raise SimulationError(
                failure_message(failed, np.asarray(code), np.asarray(sol.t_final),
                                np.asarray(sol.q_final), np.asarray(sol.v_final), why, chart, margins)
            )
        return sol
    failed = ~sol.success
    # the check is threaded through every array of the solution, so JAX cannot drop it as dead
    # code and no result is used before it has run
    dynamic, static = eqx.partition(sol, eqx.is_array)
    # the chart's margins at the final state travel to the host beside it: the message of a
    # member that left its chart names the coordinate (the chart itself is static)
    margins = jnp.zeros((0,), sol.q_final.dtype) if chart is None else _chart_margins(chart, sol.q_final)
    dynamic = _fail_with_state(dynamic, failed, code, sol.t_final, sol.q_final, sol.v_final, margins, chart)
    return eqx.combine(dynamic, static)


def _chart_margins(chart, q):
    """The chart's margins at ``q`` (a batch of states: one row each)."""
    q = jnp.asarray(q)
    flat = q.reshape((-1, q.shape[-1]))
    return jax.vmap(chart.margin_values)(flat).reshape(q.shape[:-1] + (len(chart.coordinates),))


@eqx.filter_custom_jvp
def _fail_with_state(dynamic, failed, code, t, q, v, margins, chart):
    leaves, treedef = jax.tree.flatten(dynamic)
    shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]

    def report(failed, code, t, q, v, margins, *rest):
        raise SimulationError(failure_message(failed, code, t, q, v, None, chart, margins if chart is not None else None))

    def fail():
        return jax.pure_callback(report, shapes, failed, code, t, q, v, margins, *leaves, vmap_method="broadcast_all")

    # one predicate for a whole vmapped batch: the failing branch runs (and raises) only when
    # some member failed, and reports the first one that did
    out = lax.cond(eqx.internal.unvmap_any(failed), fail, lambda: leaves)
    return jax.tree.unflatten(treedef, out)


# the check changes no value: tangents pass through unchanged (a callback has no derivative rule)
@_fail_with_state.def_jvp
def _fail_with_state_jvp(primals, tangents):
    return _fail_with_state(*primals), tangents[0]


def failure_message(failed, code, t, q, v, why: str | None = None, chart=None, margins=None) -> str:
    """The text of a :class:`SimulationError`: the first failed member's time, reason (from its
    result ``code``, or ``why`` from :func:`diagnose`) and state (``failed`` marks the failed
    members of a batch). With the scene's coordinate ``chart`` and its ``margins`` at the final
    states, a member stopped outside the chart is told so, naming the coordinate."""
    failed = np.asarray(failed)
    batch = failed.shape
    flat = failed.reshape(-1)
    i = int(np.flatnonzero(flat)[0]) if flat.any() else 0
    # every field broadcast to the batch shape: under vmap_method="broadcast_all" some arrive unbatched
    code = int(np.broadcast_to(np.asarray(code), batch).reshape(-1)[i])
    t = float(np.broadcast_to(np.asarray(t), batch).reshape(-1)[i])
    q = np.asarray(q).reshape((-1,) + np.shape(q)[len(batch):])[i]
    v = np.asarray(v).reshape((-1,) + np.shape(v)[len(batch):])[i]
    if why is None and chart is not None and margins is not None and code in (_CHART, _SINGULAR):
        m = np.asarray(margins)
        m = m.reshape((-1,) + m.shape[len(batch):])[i] if batch and m.ndim > 1 else m.reshape(-1)
        if not np.all(m > chart.limit(q.dtype)):
            why = chart.explain(m, t, q.dtype)
    where = f" (batch member {np.unravel_index(i, batch) if len(batch) > 1 else i} of {flat.size})" if batch else ""
    return (
        f"simulate: the solve failed at t = {t:.6g}{where}: {why or _reason(code)}\n"
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
    if code == _CHART:
        return ("a step ended outside the scene's coordinate chart (jaxbody.CoordinateChart): the coordinates "
                "degenerate there; switch charts with an Event or use another formulation")
    if code == _SINGULAR:
        return ("the equations of motion became singular at this state: a linear solve of the dynamics failed "
                "(an implicit solver's Newton iteration, or a singular mass matrix)")
    # "successful" with a failed solve: diffrax stopped without a code of its own
    if code == int(np.asarray(result_code(RESULTS.successful))):
        return "the step-size controller or the solver's root finder failed"
    return RESULTS[result_from_code(np.asarray(code))]
