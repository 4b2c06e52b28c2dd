"""One scene's solve: boundary checks, the diffrax call (or the one-call native solve) and the
fields of the :class:`Solution` computed from the saved states.

:func:`simulate_scene` is :func:`jaxbody.simulate` for one scene; a phased run calls it once
per phase, carrying the work vector across the switches.
"""

import contextlib
import dataclasses

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .. import maggi, program_store
from .._util import concrete_primals, is_concrete
from ..scene import Event
from ..shared_evaluation import shared_evaluations
from ..validation import raise_if_any
from .adjoint import choose_adjoint, step_bound
from .checks import (
    batch_member_checks,
    check_positive,
    checked_save_times,
    save_times,
    checked_step_sign,
    concrete_constraint_check,
    concrete_value_checks,
    scene_constraints,
    traced_constraint_check,
    traced_position_check,
    value_checks,
)
from .failures import mark_invalid, raise_on_failure
from .field import VectorField
from .native_solve import (native_adaptive_reverse, native_adaptive_solve, native_method, native_or_stepped,
                           native_reverse, native_solve, native_solve_applies, native_solve_enabled)
from .solution import RESULTS, Solution, balance_scale, energy_balance, ran_by, solution_layout
from .prefetch import prefetch_first, prefetch_solve
from .partitioning import PartitionSolver, partition_report, partition_solver, with_best_partition
from .solvers import Guarded, apply_failure, chart_outcome, choose_solver, failure_record, for_adjoint, recording_depth

__all__ = ["simulate_scene", "integrate", "make_event", "progress_meter"]


def simulate_scene(
    scene, q0, v0, t1, *, t0, solver, rtol, atol, dt0, controller, saveat, n_save, max_steps, adjoint, event,
    dense, throw, progress, track_work, project_initial, work_names=None, work0=None, check_constraints=True,
    phase_start=False,
):
    """:func:`jaxbody.simulate` of one scene (already built, see
    :func:`jaxbody.simulation.integrate.as_scene`). Returns ``(solution, work at the end)``.

    ``work_names``/``work0``: the work vector carried as state (default: the scene's own
    non-conservative effects, from zero); a phased run passes the union over its phases and
    the work reached at the switch. ``phase_start``: ``t0`` may equal ``t1`` (a phase that
    starts at the end of the run because an earlier event never triggered).
    """
    dtype = jnp.result_type(float)
    q0 = jnp.asarray(q0)
    q0 = q0.astype(q0.dtype if jnp.issubdtype(q0.dtype, jnp.inexact) else dtype)
    v0 = jnp.asarray(v0).astype(q0.dtype)
    if q0.shape != (scene.nq,) or v0.shape != (scene.nv,):
        raise ValueError(
            f"q0 must have shape ({scene.nq},) and v0 ({scene.nv},), got {q0.shape} and {v0.shape}"
        )
    for name, val in (("rtol", rtol), ("atol", atol), ("dt0", dt0)):
        check_positive(name, val)
    # the native builds start now, beside everything below (an empty cache: seconds of compiler)
    # (the solve's own program is named below, once its settings are known)
    prefetch_first(scene, q0)
    if max_steps is not None:
        check_positive("max_steps", max_steps, integer=True)
    if not phase_start and is_concrete(t0, t1) and not float(np.asarray(t1)) > float(np.asarray(t0)):
        raise ValueError(f"simulate: t1 ({float(np.asarray(t1))}) must be after t0 ({float(np.asarray(t0))})")
    if saveat is not None and n_save is not None:
        raise ValueError("give saveat or n_save, not both")
    if n_save is not None and n_save < 2:
        raise ValueError(f"n_save must be at least 2 (t0 and t1), got {n_save}")
    solver_obj, controller = choose_solver(solver, scene, q0.dtype, rtol, atol, dt0, controller)
    # the budget first: the default adjoint's checkpoints are planned over it
    max_steps = step_bound(controller, t0, t1, dt0, max_steps, q0.dtype)
    # no adjoint asked for: the program store may take a derivative in forward mode instead
    adjoint_chosen = adjoint is not None
    adjoint = choose_adjoint(adjoint, max_steps, q0.size + v0.size, q0.dtype.itemsize)
    if dt0 is not None:
        dt0 = jnp.asarray(dt0, q0.dtype)
    t0 = jnp.asarray(t0, q0.dtype)
    t1 = jnp.asarray(t1, q0.dtype)
    if saveat is None:
        saveat = diffrax.SaveAt(ts=save_times(t0, t1, n_save, q0.dtype))
    elif not isinstance(saveat, diffrax.SaveAt):
        ts = jnp.asarray(saveat, dtype=q0.dtype)
        if ts.ndim != 1:
            raise ValueError(f"simulate: saveat must be 1-D times, got shape {ts.shape}")
        saveat = diffrax.SaveAt(ts=ts)
    # the solution is built from one SubSaveAt of states (plus the end state beside it): dense
    # output has its own argument and nested saves have no place in a Solution
    if saveat.dense or saveat.subs is not None and not isinstance(saveat.subs, diffrax.SubSaveAt):
        raise ValueError("simulate: pass dense=True instead of SaveAt(dense=True); nested subs are not supported")
    saveat = checked_save_times(saveat, t0, t1)
    dt0 = checked_step_sign(dt0, t0, t1)
    adjoint = choose_adjoint(adjoint)
    if isinstance(controller, (diffrax.ConstantStepSize, diffrax.StepTo)) and not isinstance(
        adjoint, diffrax.BacksolveAdjoint
    ):
        # fixed steps: each trajectory's failure is recorded, not stopped on (one loop predicate
        # for a vmap batch); backsolve's adjoint solve keeps the stopping guard (no solver state)
        solver_obj = Guarded(solver_obj.solver, solver_obj.project, record=True)
    # constraints that choose their partition automatically re-partition during the solve
    # (partition_solver wraps the guard); the stage loop is chosen from the outermost wrapper
    guarded = solver_obj
    solver_obj = for_adjoint(partition_solver(solver_obj, scene, adjoint), adjoint, max_steps)

    constrained = scene_constraints(scene) if check_constraints else None
    if constrained is not None and constrained.n_constraint == 0:
        constrained = None
    correction = None
    # concrete inputs get Python errors with the culprit's index and value; traced ones can only
    # carry a fixed message, so they are flags for error_if or a result code. Under eager
    # differentiation (jax.grad of concrete values) the values are concrete too: checked as such
    concrete = is_concrete(scene, q0, v0, t0)
    primals = (scene, q0, v0, t0) if concrete else concrete_primals((scene, q0, v0, t0))
    valid = None
    if primals is not None:
        concrete_value_checks(*primals[:3])
        if constrained is not None:
            cs = constrained if concrete else scene_constraints(primals[0])
            q_checked, v_checked, correction = concrete_constraint_check(cs, primals[3], primals[1], primals[2],
                                                                         project_initial)
            if concrete:
                q0, v0 = q_checked, v_checked
            elif q_checked is not primals[1] or v_checked is not primals[2]:
                primals = None  # a state to project: projected below, where derivatives pass through it
    if primals is None:
        if throw:
            batch_member_checks(scene, q0, v0)
        checks = value_checks(scene, q0, v0)
        if constrained is not None:
            if not project_initial:
                checks.append(traced_position_check(constrained, t0, q0))
            bad, msg = traced_constraint_check(constrained, t0, q0, v0)
            if project_initial:
                # projected only where the check failed, so an admissible v0 passes bit for bit
                projected = jnp.where(bad, maggi.project_velocities(constrained, q0, v0, t0), v0)
                correction = projected - v0
                v0 = projected
            else:
                checks.append((bad, msg))
        if throw:
            q0 = raise_if_any(q0, checks)
            valid = None
        else:
            valid = ~jnp.any(jnp.stack([b for b, _ in checks]))
            # a member that failed the check integrates a safe state: frozen (see VectorField)
            q0 = jnp.where(valid, q0, jnp.nan_to_num(q0, nan=0.0, posinf=0.0, neginf=0.0))
            v0 = jnp.where(valid, v0, jnp.nan_to_num(v0, nan=0.0, posinf=0.0, neginf=0.0))
    own = scene.work_names if (track_work and scene.has_energy) else ()
    if work_names is None:
        work_names = own
    # a phased run passes the union of its phases' work names: this scene's must be among them
    missing = [n for n in own if n not in work_names]
    if missing:
        raise ValueError(f"simulate: internal: work slots {work_names} lack {missing}")
    slots = tuple(work_names.index(n) for n in own)
    if track_work and scene.has_energy and work_names:
        # a host array: an eager jnp.zeros would compile a program of its own
        w0 = jnp.asarray(np.zeros((len(work_names),), q0.dtype) if work0 is None else work0, q0.dtype)
        y0 = (q0, v0, w0)
    else:
        y0 = (q0, v0)
    meter = progress_meter(progress)
    event = make_event(event, q0.dtype)
    prefetch_solve(scene, y0, solver_obj, controller, saveat, adjoint, meter, event, dense, slots)
    # the layout and the native switch are computed out here: static arguments of the compiled solve
    # a program traced in an earlier process is run as stored (no trace: program_store)
    native = native_solve_enabled()
    # a forward-mode variant only matters where a derivative may be taken (traced inputs)
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((scene, y0, t0, t1)))
    integrated, saved = program_store.call_then(
        _integrate, (scene, y0, t0, t1, valid, solver_obj, controller, dt0, saveat, max_steps, adjoint, meter, event,
                     dense, slots, native), "simulate",
        _saved_quantities, lambda out: (scene, y0, t0, out[0], out[1], tuple(work_names)), "saved",
        first_forward_args=None if adjoint_chosen or not traced else _forward_variant(
            scene, y0, t0, t1, valid, guarded, solver_obj, controller, dt0, saveat, max_steps, adjoint, meter, event,
            dense, slots, native))
    sol = _solution(integrated, saved, solution_layout(scene))
    yf = integrated[3]
    w_final = yf[2] if len(yf) == 3 else None
    if correction is not None:
        sol = dataclasses.replace(sol, stats={**sol.stats, "v0_correction": correction})
    sol = dataclasses.replace(sol, **ran_by(scene, solver))
    if valid is not None:
        sol = mark_invalid(sol, valid, t0)
    if throw:
        forward = None if concrete else concrete_primals((sol, scene, t0, t1))
        if forward is not None:
            raise_on_failure(*forward)  # the forward values, checked as an eager solve's
        else:
            sol = raise_on_failure(sol, scene, t0, t1)
    return sol, w_final


def _forward_variant(scene, y0, t0, t1, valid, guarded, solver, controller, dt0, saveat, max_steps, adjoint, meter,
                     event, dense, slots, native):
    """The arguments of :func:`_integrate` under diffrax's forward-mode adjoint: the program
    store differentiates a solve through them in forward mode when a derivative is taken with
    respect to a few scalars (:data:`jaxbody.program_store.FORWARD_MAX_INPUTS`), a smaller program to
    compile than the reverse sweep through checkpoints. ``None`` where the solve is one native
    call differentiated by its own native reverse sweep (a derivative with respect to the
    initial state alone), which is faster than either."""
    scene_differentiated = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(scene))
    if native and not scene_differentiated and native_solve_applies(scene, y0, solver, controller, saveat, adjoint,
                                                                    meter, event, dense, slots):
        return None
    forward = diffrax.ForwardMode()
    solver = for_adjoint(partition_solver(guarded, scene, forward), forward, max_steps)
    return (scene, y0, t0, t1, valid, solver, controller, dt0, saveat, max_steps, forward, meter, event, dense, slots,
            native)


def make_event(event, dtype):
    """diffrax's terminating event of ``simulate``'s ``event`` argument (``None`` without one):
    its zero located by Newton's method to a hundred ulps of ``dtype``."""
    if event is None:
        return None
    if not isinstance(event, Event):
        if not callable(event):
            raise ValueError(f"simulate: event must be a jaxbody.Event or a callable g(t, q, v), got {type(event).__name__}")
        event = Event(event)
    tol = 100 * float(jnp.finfo(dtype).eps)
    return diffrax.Event(_EventCondition(event), root_finder=optx.Newton(rtol=tol, atol=tol), direction=event.direction)


class _EventCondition(eqx.Module):
    """diffrax's ``cond_fn(t, y, args)`` of a :class:`jaxbody.Event` (a module, not a closure made
    per call, so that repeated solves with the same event reuse one compilation)."""

    event: Event

    def __call__(self, t, y, args, **kwargs):
        del args, kwargs
        return self.event(t, y[0], y[1])


def progress_meter(progress):
    """diffrax's progress meter for ``progress``: tqdm's when it is installed, else a text one."""
    if not progress:
        return diffrax.NoProgressMeter()
    try:
        import tqdm  # noqa: F401  (optional dependency: only asked for when a meter is)
    except ImportError:
        return diffrax.TextProgressMeter()
    return diffrax.TqdmProgressMeter()


# the beginnings of diffrax's argument checks that jaxbody makes itself before the solve: the
# save times (checks.checked_save_times) and the sign of (t1 - t0) * dt0 (checks.checked_step_sign)
_RECHECKS = ("saveat.ts must be increasing or decreasing.", "saveat.ts must lie between t0 and t1.",
             "Must have (t1 - t0) * dt0 >= 0")


@contextlib.contextmanager
def _rechecks_left_out():
    """While diffrax's solve is traced: its checks of what jaxbody has already checked return
    their argument unchanged instead of staging an ``eqx.error_if``.

    Why: an ``error_if`` on traced values is a host callback in the compiled program, and JAX's
    persistent compilation cache stores no program with a host callback; diffrax checks the save
    times (traced arguments of the compiled solve) on every call, so without this the main solve
    would be compiled anew in every process. Every other check (diffrax's, optimistix's,
    lineax's) is kept. The replacement lives only for the trace (the solve's compiled program is
    built from it) and calls nothing cached, so no other program is traced without its checks."""
    original = eqxi.error_if

    def error_if(x, pred, msg, *args, **kwargs):
        if isinstance(msg, str) and msg.startswith(_RECHECKS):
            return x
        return original(x, pred, msg, *args, **kwargs)

    eqxi.error_if = error_if
    try:
        yield
    finally:
        eqxi.error_if = original


def integrate(scene, y0, t0, t1, valid, solver, controller, dt0, saveat, max_steps, adjoint, meter, event, dense, slots):
    """The step-by-step solve (diffrax): ``(ts, ys, tf, yf, stats, result)`` (saved times and
    states, the final time and state as arrays of one entry, the step counts and the result,
    each trajectory's failure applied) and diffrax's solution. The caller has checked the save
    times and the sign of ``(t1 - t0) * dt0`` (see :func:`_rechecks_left_out`)."""
    main = saveat.subs if saveat.subs is not None else diffrax.SubSaveAt(ts=saveat.ts, t0=saveat.t0, t1=saveat.t1, steps=saveat.steps)
    # the end state is saved separately, except with backsolve (which takes no SaveAt(subs=...))
    # and when the saved times include t1 (diffrax saves the state the solve ended in there, at
    # t1 or where it stopped): there the last saved point stands for it (one save state less
    # carried through the loop and its checkpoints)
    single = isinstance(adjoint, diffrax.BacksolveAdjoint) or (main.t1 and not isinstance(solver, PartitionSolver))
    depth = recording_depth(solver)
    state = isinstance(solver, PartitionSolver) or depth is not None
    with _rechecks_left_out():
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(VectorField(slots)),
            solver,
            t0,
            t1,
            dt0,
            y0,
            args=(scene, valid),
            saveat=diffrax.SaveAt(subs=main, dense=dense, solver_state=state) if single else diffrax.SaveAt(
                subs=[main, diffrax.SubSaveAt(t1=True)], dense=dense, solver_state=state),
            stepsize_controller=controller,
            max_steps=max_steps,
            adjoint=adjoint,
            throw=False,
            progress_meter=meter,
            event=event,
        )
    ys, yf = (sol.ys, sol.ys) if single else sol.ys
    ts, tf = (sol.ts, sol.ts) if single else sol.ts
    stats = {k: jnp.asarray(sol.stats[k]) for k in ("num_steps", "num_accepted_steps", "num_rejected_steps")}
    result = chart_outcome(scene, valid, yf[0][-1], RESULTS.promote(sol.result))
    failure = None if depth is None else failure_record(sol.solver_state, depth)
    if failure is not None:
        # a trajectory that failed has no derivative to give: no cotangent enters the loop's state
        failure = jax.lax.stop_gradient(failure)
        ts, ys, tf, stats, result = apply_failure(failure, ts, ys, tf, stats, result, single and main.t1)
        if single:
            yf = ys
    return (ts, ys, tf, yf, stats, result), sol


@eqx.filter_jit
def _integrate(scene, y0, t0, t1, valid, solver, controller, dt0, saveat, max_steps, adjoint, meter, event, dense, slots,
               native_enabled):
    """The solve: ``(ts, ys, tf, yf, stats, result, repartition_times, interpolation)`` (the saved
    times and states, the final time and state, the statistics and outcome, and the dense interpolation
    where asked). ``native_enabled``: whether a solve may run as one native call
    (:func:`jaxbody.simulation.native_solve.native_solve_enabled`, read by the caller so that it
    keys the compiled program)."""
    one_call = native_enabled and native_solve_applies(scene, y0, solver, controller, saveat, adjoint, meter, event,
                                                       dense, slots)
    sol = None
    if not one_call:
        (ts, ys, tf, yf, stats, result), sol = integrate(scene, y0, t0, t1, valid, solver, controller, dt0, saveat,
                                                         max_steps, adjoint, meter, event, dense, slots)
    else:
        # one native call; derivatives by the native reverse sweep (initial state alone) or
        # through the step-by-step solve
        # the save times travel in `rest` (arrays of a custom VJP's primal function are its
        # arguments, not closed over)
        def stepped(rest, y0):
            scene, t0, t1, dt0, valid, solver, controller, adjoint, saveat = rest
            return integrate(scene, y0, t0, t1, valid, solver, controller, dt0, saveat, max_steps, adjoint, meter,
                             event, dense, slots)[0]

        method = native_method(solver, controller)

        def native(rest, y0):
            scene, t0, t1, dt0, valid, _, controller, _, saveat = rest
            if method == "rk4":
                return native_solve(scene, y0, t0, t1, dt0, valid, max_steps, slots, saveat)
            return native_adaptive_solve(scene, y0, t0, t1, dt0, valid, max_steps, slots, method, controller, saveat)

        rest = (scene, t0, t1, dt0, valid, solver, controller, adjoint, saveat)
        # the native reverse sweep keeps checkpoints as the checkpointed adjoint would; another
        # adjoint asked for its own way of differentiating, which the stepped solve honours
        reverse = None
        if isinstance(adjoint, diffrax.RecursiveCheckpointAdjoint):
            reverse = (native_reverse(adjoint, max_steps, slots, y0) if method == "rk4"
                       else native_adaptive_reverse(adjoint, max_steps, slots, y0, method))
        ts, ys, tf, yf, stats, result = native_or_stepped(rest, y0, native, stepped, reverse)
    if sol is None:
        stats["num_repartitions"], repartition_times = jnp.zeros((), jnp.int32), None
    else:
        stats["num_repartitions"], repartition_times, result = _partition_outcome(solver, sol, result)
    interpolation = sol.interpolation if dense and sol is not None else None
    # the final time and state leave the program as scalars and vectors: indexing its outputs
    # outside would be eager operations, each compiled on a first call
    tf, yf = tf[-1], jax.tree.map(lambda leaf: leaf[-1], yf)
    return ts, ys, tf, yf, stats, result, repartition_times, interpolation


@eqx.filter_jit
def _saved_quantities(scene, y0, t0, ts, ys, work_names):
    """What the solution reports at the saved states ``(ts, ys)`` of a solve from ``y0``:
    ``(energy, work, energy_drift, energy0, constraint_drift, reactions)`` (``None`` where the
    scene has no energy or no constraints). A program of its own, apart from the solve's: the
    reactions evaluate the whole constrained vector field again (about a third to a half of a
    constrained solve's compiled code), so a first call compiles the two side by side
    (:func:`jaxbody.program_store.call_then`)."""
    q, v = ys[0], ys[1]
    finite = jnp.all(jnp.isfinite(q), axis=-1) & jnp.all(jnp.isfinite(v), axis=-1)
    constrained = scene.constraints is not None
    # diffrax pads unsaved entries with inf: evaluate everything on a safe state there
    qs = jnp.where(finite[:, None], q, y0[0])
    vs = jnp.where(finite[:, None], v, y0[1])
    ts_safe = jnp.where(finite, ts, t0)

    # the energy, the drift and the reactions of one state from one computation of its frames
    @shared_evaluations()
    def at_state(tt, qq, vv):
        energy = scene.total_energy(qq, vv) if scene.has_energy else None
        if not constrained:
            return energy, None, None
        # Λ does not depend on the coordinate partition: each state with its best-conditioned one
        return energy, scene.constraint_drift(tt, qq, vv), with_best_partition(scene, tt, qq, vv).evaluate(tt, qq, vv)[2]

    energy, residuals, lam = jax.vmap(at_state)(ts_safe, qs, vs)
    work = {}
    if scene.has_energy:
        energy = jnp.where(finite, energy, jnp.nan)
        if len(ys) == 3:
            work = {name: ys[2][:, i] for i, name in enumerate(work_names)}
        # the balance from the initial state, not from the first saved time (which may be later)
        energy0 = scene.total_energy(y0[0], y0[1])
        bal = energy_balance(energy, work, energy0, y0[2] if len(y0) == 3 else None) / balance_scale(energy, energy0)
        drift = jnp.max(jnp.where(finite, jnp.abs(bal), 0.0))
    else:
        drift = energy0 = None
    cdrift = reactions = None
    if constrained:
        # constraint residuals and reactions at the saved states (padding entries: NaN)
        pos, vel = residuals
        cdrift = {
            "position": jnp.where(finite[:, None], pos, jnp.nan),
            "velocity": jnp.where(finite[:, None], vel, jnp.nan),
        }
        reactions = jnp.where(finite[:, None], lam, jnp.nan)
    return energy, work, drift, energy0, cdrift, reactions


def _solution(integrated, saved, layout) -> Solution:
    """The :class:`Solution` of :func:`_integrate`'s and :func:`_saved_quantities`' outputs."""
    ts, ys, tf, yf, stats, result, repartition_times, interpolation = integrated
    energy, work, drift, energy0, cdrift, reactions = saved
    return Solution(
        t=ts, q=ys[0], v=ys[1], energy=energy, work=work, energy_drift=drift, constraint_drift=cdrift,
        reactions=reactions, stats=stats, result=result, t_final=tf, q_final=yf[0], v_final=yf[1],
        layout=layout, interpolation=interpolation, repartition_times=repartition_times, energy0=energy0,
    )


def _partition_outcome(solver, sol, result):
    """``(num_repartitions, repartition_times, result)`` of a solve: what the
    :class:`jaxbody.simulation.PartitionSolver` did (zero and ``None`` for other solvers); a solve
    it stopped on a degraded partition gets ``RESULTS.partition_degraded``, one stopped on a
    singular parametrisation ``RESULTS.singular_parametrisation``."""
    report = partition_report(solver, sol.solver_state)
    if report is None:
        return jnp.zeros((), jnp.int32), None, result
    result = RESULTS.where(report["degraded"], RESULTS.partition_degraded, result)
    result = RESULTS.where(report["singular"], RESULTS.singular_parametrisation, result)
    return report["num_repartitions"], report["repartition_times"], result
