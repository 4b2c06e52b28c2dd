"""The one-call native solves: a whole fixed-step RK4 or adaptive solve as one native program.

A fixed-step ``"rk4"`` solve on the native kernel, and an adaptive ``"tsit5"``, ``"dopri5"`` or
``"dopri8"`` solve under diffrax's ``PIDController``, that save their end state and/or requested
times (``SaveAt(ts=..., t1=...)``, ``simulate``'s default ``n_save`` times among them), of a scene
of gravity, joint springs, joint dampers and a Fourier-series joint torque, without an event, run
as one native call (:func:`jaxbody.backends.native.rk4_rollout`,
:func:`jaxbody.backends.native.adaptive_solve`) instead of diffrax's loop. They apply only there
because only there does the native program compute exactly what the loop would: the same field
(:func:`jaxbody.simulation.field.native_field`), the same steps (diffrax's step times;
diffrax's tableaux, error estimate, controller and dense output, from which the requested times
are saved), failures and result codes. The gradient with respect to the initial state is a
native reverse sweep (:func:`jaxbody.backends.native.rk4_rollout_vjp`,
:func:`jaxbody.backends.native.adaptive_solve_vjp`; the saved states' cotangents through each
step's dense output); any other derivative (the scene's parameters) goes through diffrax's loop,
which is then run for the derivative alone. ``$JAXBODY_NATIVE_SOLVE=0`` turns this off.
"""

import os

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.custom_derivatives import SymbolicZero

# the module, not its functions: read at call time, so a test can intercept the native calls
from ..backends import native
from ..effects import FourierTorque, JointDampers
from .adjoint import default_checkpoints
from .field import native_field
from .solution import RESULTS
from .solvers import Guarded, RK4Stages

__all__ = ["native_solve_enabled", "native_solve_applies", "native_solve", "native_reverse", "native_or_stepped",
           "native_method"]

# the embedded pairs with a native adaptive solve, by diffrax solver class
_ADAPTIVE = {diffrax.Tsit5: "tsit5", diffrax.Dopri5: "dopri5", diffrax.Dopri8: "dopri8"}

# the save function of a SubSaveAt that saves the state itself (diffrax's default)
_SAVE_STATE = diffrax.SubSaveAt(t1=True).fn


def native_solve_enabled() -> bool:
    """``$JAXBODY_NATIVE_SOLVE=0`` turns the one-call solve (:func:`native_solve`) off: every
    ``simulate`` then steps through diffrax's loop. Read when a solve is traced, by the caller
    of the compiled solve, so that the setting keys the compiled program."""
    return os.environ.get("JAXBODY_NATIVE_SOLVE", "1") != "0"


def native_method(solver, controller) -> str | None:
    """The native program of a solve: ``"rk4"`` (RK4 at constant steps, recording each
    trajectory's failure), the name of an embedded pair under diffrax's ``PIDController``
    (``"tsit5"``, ``"dopri5"``, ``"dopri8"``: :func:`jaxbody.backends.native.adaptive_solve`), or ``None``."""
    # exact types: a subclass or another wrapper (a re-partitioning solver) may step differently
    if type(solver) is not Guarded:
        return None
    if solver.record and type(solver.solver) is RK4Stages and type(controller) is diffrax.ConstantStepSize:
        return "rk4"
    method = _ADAPTIVE.get(type(solver.solver))
    # PIDController's own loop (no step_ts/jump_ts: those make it a ClipStepSizeController), its
    # RMS norm and the solver's error order
    if method is None or solver.record or type(controller) is not diffrax.PIDController:
        return None
    if controller.norm is not optx.rms_norm or controller.error_order is not None:
        return None
    return method


def _main_save(saveat):
    return saveat.subs if saveat.subs is not None else diffrax.SubSaveAt(ts=saveat.ts, t0=saveat.t0, t1=saveat.t1,
                                                                         steps=saveat.steps)


def native_solve_applies(scene, y0, solver, controller, saveat, adjoint, meter, event, dense, slots) -> bool:
    """Whether a solve can run as one native call: RK4 at constant steps
    (:func:`jaxbody.backends.native.rk4_rollout`) or an embedded pair under PID control
    (:func:`jaxbody.backends.native.adaptive_solve`) saving the end state and/or requested times
    (a 1-D ``ts``), on a scene whose field the native programs compute
    (:func:`jaxbody.simulation.field.native_field`), without an event, dense output or progress
    meter, under an adjoint that differentiates in reverse mode."""
    method = native_method(solver, controller)
    if method is None or event is not None or dense:
        return False
    # the native program has no tangent rule: forward mode stays in diffrax's loop
    if not isinstance(meter, diffrax.NoProgressMeter) or isinstance(adjoint, diffrax.ForwardMode):
        return False
    main = _main_save(saveat)
    if not isinstance(main, diffrax.SubSaveAt) or main.t0 or main.steps or main.fn is not _SAVE_STATE:
        return False
    if main.ts is None and not main.t1 or main.ts is not None and jnp.ndim(main.ts) != 1:
        return False
    plan = native_field(scene, y0, slots, timed=True)
    if plan is None:
        return False
    # the adaptive program's error norm counts the works it carries: they must be the whole work
    # vector (a phased run's vector may hold other phases' works too)
    carried = sorted(s for s in _work_layout(scene, y0, slots, plan[2]) if s is not None)
    return method == "rk4" or len(y0) == 2 or carried == list(range(jnp.size(y0[2])))


def _work_layout(scene, y0, slots, passive) -> tuple:
    """For each work the native programs integrate (the dampers', then a Fourier-series torque's
    where the scene has one: :func:`jaxbody.backends.native.rk4_rollout`), its index in the work
    vector ``y0[2]``, or ``None`` where the solve does not carry it."""
    names = (JointDampers.name,) + ((FourierTorque.name,) if "torque" in passive else ())
    if len(y0) != 3:
        return (None,) * len(names)
    own = scene.work_names  # the scene's works, in the order of slots
    return tuple(slots[own.index(n)] if n in own else None for n in names)


def _works(w, layout, dtype):
    """The native program's works from a work vector ``w`` (zero where not carried)."""
    return jnp.stack([w[s] if s is not None else jnp.zeros((), dtype) for s in layout])


def _work_vector(like, layout, works):
    """``like`` (a work vector, or rows of them) with the native program's ``works`` (last axis) set
    in their slots."""
    for j, s in enumerate(layout):
        if s is not None:
            like = like.at[..., s].set(works[..., j].astype(like.dtype))
    return like


def _native_arguments(scene, y0, valid, slots) -> tuple:
    """``(model, keyword arguments)`` of :func:`jaxbody.backends.native.rk4_rollout` for a solve of ``scene``
    from ``y0`` (:func:`jaxbody.simulation.field.native_field`)."""
    model, gravity, passive = native_field(scene, y0, slots, timed=True)
    # a member that failed the boundary check stays frozen, as under the stepped field
    kwargs = dict(gravity=gravity, frozen=False if valid is None else ~valid, **passive)
    layout = _work_layout(scene, y0, slots, passive)
    return model, dict(kwargs, work0=_works(y0[2] if len(y0) == 3 else None, layout, y0[0].dtype)), layout


def _forward_in_time(t0, t1, dt0):
    """``t1``, checked to be no earlier than ``t0`` (the native solve steps forward only; diffrax
    raises on the same times)."""
    return eqx.error_if(t1, (t1 - t0) * dt0 < 0, "simulate: t1 must not be before t0 (a fixed-step solve runs forward)")


def native_solve(scene, y0, t0, t1, dt0, valid, max_steps, slots, saveat):
    """The solve of :func:`jaxbody.simulation.solve.integrate` by RK4 at constant steps as one
    native call per batch (:func:`jaxbody.backends.native.rk4_rollout`): ``(ts, ys, tf, yf, stats, result)``."""
    model, kwargs, layout = _native_arguments(scene, y0, valid, slots)
    t1 = _forward_in_time(t0, t1, dt0)
    out = native.rk4_rollout(model, y0[0], y0[1], t0, t1, dt0, max_steps, ts=_main_save(saveat).ts, **kwargs)
    return _saved_outputs(y0, t1, saveat, layout, *out, fixed=True)


def _adaptive_arguments(scene, y0, valid, slots, controller):
    model, kwargs, layout = _native_arguments(scene, y0, valid, slots)
    kwargs.update(has_work=tuple(s is not None for s in layout), control=native.Control.of(controller))
    return model, kwargs, layout


def _saved_outputs(y0, t1, saveat, layout, q, v, w, status, saved, fixed=False) -> tuple:
    """:func:`jaxbody.simulation.solve.integrate`'s outputs from a native solve's
    (:data:`jaxbody.backends.native.solve.STATUS`): the requested times (unsaved ones ``inf``,
    as diffrax pads them) and/or the end state; the works the program does not carry keep their
    initial value. ``fixed``: a fixed-step solve, whose step counts the loop gives as its failure
    record counts them."""
    dtype = y0[0].dtype
    main = _main_save(saveat)
    nq, nv = y0[0].shape[0], y0[1].shape[0]

    def state(rows):
        if len(y0) == 2:
            return rows[:, :nq], rows[:, nq : nq + nv]
        works = _work_vector(jnp.broadcast_to(y0[2], (rows.shape[0],) + y0[2].shape), layout, rows[:, nq + nv :])
        return rows[:, :nq], rows[:, nq : nq + nv], works

    final = jnp.concatenate([q, v, jnp.atleast_1d(w)])[None]
    tf = status[0].astype(dtype)[None]
    yf = state(final)
    if main.ts is None:
        ts, ys = tf, yf
    else:
        ts = jnp.where(jnp.arange(saved.shape[0], dtype=status.dtype) < status[5], jnp.asarray(main.ts, dtype), jnp.inf)
        rows = saved
        if main.t1:
            ts, rows = jnp.concatenate([ts, tf]), jnp.concatenate([saved, final])
        ys = state(rows)
    if fixed:  # the failure record's counts (solvers.Failure), none rejected
        steps = status[1].astype(jnp.int32)
        stats = {"num_steps": steps, "num_accepted_steps": steps, "num_rejected_steps": jnp.asarray(0)}
    else:
        count = jnp.result_type(int)  # diffrax's counters
        stats = {"num_steps": status[1].astype(count), "num_accepted_steps": status[2].astype(count),
                 "num_rejected_steps": status[3].astype(count)}
    code = status[4]
    result = RESULTS.where(tf[0] < t1, RESULTS.max_steps_reached, RESULTS.successful)
    result = RESULTS.where(code == 2, RESULTS.dt_min_reached, result)
    result = RESULTS.where(code == 1, RESULTS.nonfinite, result)
    return ts, ys, tf, yf, stats, result


def native_adaptive_solve(scene, y0, t0, t1, dt0, valid, max_steps, slots, method, controller, saveat):
    """The solve of :func:`jaxbody.simulation.solve.integrate` by an embedded pair as one native
    call per batch (:func:`jaxbody.backends.native.adaptive_solve`): ``(ts, ys, tf, yf, stats, result)``."""
    model, kwargs, layout = _adaptive_arguments(scene, y0, valid, slots, controller)
    t1 = _forward_in_time(t0, t1, 1.0)
    ts = _main_save(saveat).ts
    out = native.adaptive_solve(model, method, y0[0], y0[1], t0, t1, dt0=dt0, max_steps=max_steps, ts=ts, **kwargs)
    return _saved_outputs(y0, t1, saveat, layout, *out)


def _saved_cotangents(saveat, layout, y0, cotangents) -> tuple:
    """The cotangents of ``(ts, ys, tf, yf, ...)`` as a native reverse sweep takes them: those of
    the final state ``[q, v, w]`` (the end state's saved point added where it is one) and of the
    saved states, ``(n_ts, nq + nv + works)`` rows in the program's layout (``None`` without
    ``ts``)."""
    main = _main_save(saveat)
    _, ys, _, yf, _, _ = cotangents
    ys = [_instantiate(a) for a in ys]
    ct = [_instantiate(b)[0] for b in yf]
    if main.ts is None:
        return [a[0] + b for a, b in zip(ys, ct)], None, None  # the end state is the saved point
    if main.t1:  # the end state saved after the requested times
        ct = [a[-1] + b for a, b in zip(ys, ct)]
        ys = [a[:-1] for a in ys]
    zeros = jnp.zeros((ys[0].shape[0],), ys[0].dtype)
    works = [ys[2][:, s] if s is not None else zeros for s in layout]
    return ct, jnp.concatenate(list(ys[:2]) + [jnp.stack(works, axis=1)], axis=1), ys[2] if len(y0) == 3 else None


def _initial_work_cotangent(y0, layout, ct_final, ct_saved_works, status, ct_w):
    """The cotangent of the initial work vector: the native sweep's ``ct_w`` for the works the
    program carries; a work it does not carry stays at its initial value, in the end state and
    in every state saved (``ct_saved_works``, rows past the saves made never reached)."""
    total = ct_final
    if ct_saved_works is not None:
        made = jnp.arange(ct_saved_works.shape[0], dtype=status.dtype) < status[5]
        total = total + jnp.sum(jnp.where(made[:, None], ct_saved_works, 0.0), axis=0)
    return _work_vector(total.astype(y0[2].dtype), layout, jnp.atleast_1d(ct_w))


def _native_reverse(adjoint, max_steps, slots, y0, method):
    """``(forward, backward)`` of :func:`native_or_stepped` by the native reverse sweep of
    ``method`` (``"rk4"`` or an embedded pair), its checkpoints as many as the checkpointed
    ``adjoint`` would keep (default: :func:`default_checkpoints`, within its memory budget);
    ``None`` without a bounded step budget (diffrax's loop differentiates: the sweep's
    checkpoint memory is planned over the budget)."""
    if max_steps is None:
        return None
    checkpoints = adjoint.checkpoints
    if checkpoints is None:
        checkpoints = default_checkpoints(max_steps, y0[0].size + y0[1].size, y0[0].dtype.itemsize)
    held = []

    def arguments(rest, y0):
        scene, t0, t1, dt0, valid, _, controller, _, saveat = rest
        if method == "rk4":
            model, kwargs, layout = _native_arguments(scene, y0, valid, slots)
            times = (t0, _forward_in_time(t0, t1, dt0), dt0, max_steps)
        else:
            model, kwargs, layout = _adaptive_arguments(scene, y0, valid, slots, controller)
            times = (t0, _forward_in_time(t0, t1, 1.0))
            kwargs.update(dt0=dt0, max_steps=max_steps)
        return model, kwargs, layout, times, saveat

    def forward(rest, y0):
        model, kwargs, layout, times, saveat = arguments(rest, y0)
        ts = _main_save(saveat).ts
        if method == "rk4":
            *out, saved = native.rk4_rollout_checkpointed(model, y0[0], y0[1], *times, checkpoints, ts=ts, **kwargs)
        else:
            *out, saved = native.adaptive_solve(model, method, y0[0], y0[1], *times, ts=ts, checkpoints=checkpoints,
                                                **kwargs)
        # residuals are arrays: the rest (the controller's norm, the solver) is held here
        dynamic, static = eqx.partition(rest, eqx.is_array)
        held.append(static)
        return _saved_outputs(y0, times[1], saveat, layout, *out, fixed=method == "rk4"), (dynamic, y0, saved, out[3])

    def backward(residuals, cotangents):
        dynamic, y0, saved, status = residuals
        rest = eqx.combine(dynamic, held[-1])
        model, kwargs, layout, times, saveat = arguments(rest, y0)
        ct, ct_saved, ct_saved_works = _saved_cotangents(saveat, layout, y0, cotangents)
        work = _works(ct[2], layout, y0[0].dtype) if len(y0) == 3 else 0.0
        common = dict(saved=saved, status=status, cotangent_q=ct[0], cotangent_v=ct[1], cotangent_work=work,
                      ts=_main_save(saveat).ts, cotangent_saved=ct_saved)
        if method == "rk4":
            kwargs.pop("work0")
            ct_q, ct_v, ct_w = native.rk4_rollout_vjp(model, y0[0], y0[1], *times, checkpoints, **common, **kwargs)
        else:
            ct_q, ct_v, ct_w = native.adaptive_solve_vjp(model, method, y0[0], y0[1], *times, checkpoints=checkpoints,
                                                         **common, **kwargs)
        if len(y0) == 2:
            return ct_q, ct_v
        return ct_q, ct_v, _initial_work_cotangent(y0, layout, ct[2], ct_saved_works, status, ct_w)

    return forward, backward


def native_adaptive_reverse(adjoint, max_steps, slots, y0, method):
    """``(forward, backward)`` of :func:`native_or_stepped` for an adaptive solve by the native
    reverse sweep (:func:`jaxbody.backends.native.adaptive_solve_vjp`; the saved states'
    cotangents through each step's dense output), its checkpoints planned as
    :func:`native_reverse` plans them; ``None`` without a bounded step budget."""
    return _native_reverse(adjoint, max_steps, slots, y0, method)


def _instantiate(cotangent):
    """A cotangent given as ``SymbolicZero`` as an array of zeros."""
    if isinstance(cotangent, SymbolicZero):
        return jnp.zeros(cotangent.aval.shape, cotangent.aval.dtype)
    return cotangent


def _final_row(outputs):
    """``(ts, ys, tf, yf, stats, result)`` with the final time and state as one row, as the native
    solves give them: where diffrax's loop saves the end state among the requested times it
    returns every saved row for them too, its last the final one."""
    ts, ys, tf, yf, stats, result = outputs
    return ts, ys, tf[-1:], tuple(a[-1:] for a in yf), stats, result


def native_or_stepped(rest, y0, native, stepped, reverse):
    """``native(rest, y0)``, differentiated in reverse mode by ``reverse`` where only ``y0``
    carries a derivative and ``reverse`` is given, else as ``stepped(rest, y0)`` (the same
    values, computed step by step through diffrax: its adjoint, its checkpoints).

    ``reverse``: ``(forward, backward)``: ``forward(rest, y0) -> (outputs, residuals)`` and
    ``backward(residuals, cotangents) -> cotangent of y0``."""
    # the custom VJP takes arrays only; the rest (solver, controller, plain Python) is closed over
    dynamic, static = eqx.partition(rest, eqx.is_array)

    @jax.custom_vjp
    def run(dynamic, y0):
        return native(eqx.combine(dynamic, static), y0)

    def forward(dynamic, y0):
        values = jax.tree.map(lambda p: p.value, dynamic)
        y0_values = jax.tree.map(lambda p: p.value, y0)
        # the native sweep differentiates with respect to the initial state only; a perturbed
        # parameter needs diffrax's adjoint, so the forward pass is redone step by step then
        if reverse is not None and not any(p.perturbed for p in jax.tree.leaves(dynamic)):
            out, residuals = reverse[0](eqx.combine(values, static), y0_values)
            return out, (None, residuals)
        out, pullback = jax.vjp(lambda d, y: _final_row(stepped(eqx.combine(d, static), y)), values, y0_values)
        return out, (pullback, None)

    def backward(residuals, cotangents):
        pullback, native_residuals = residuals
        if pullback is None:
            # nothing but y0 was perturbed: no cotangent for the rest
            return None, reverse[1](native_residuals, cotangents)
        return pullback(jax.tree.map(_instantiate, cotangents, is_leaf=lambda c: isinstance(c, SymbolicZero)))

    run.defvjp(forward, backward, symbolic_zeros=True)
    return run(dynamic, y0)


def native_reverse(adjoint, max_steps, slots, y0):
    """``(forward, backward)`` of :func:`native_or_stepped` for an RK4 solve at constant steps by
    the native reverse sweep (:func:`jaxbody.backends.native.rk4_rollout_vjp`; the saved states'
    cotangents through each step's dense output): the solve keeps as many checkpoints as the
    checkpointed ``adjoint`` would (default: :func:`default_checkpoints`, within its memory
    budget); ``None`` without a bounded step budget."""
    return _native_reverse(adjoint, max_steps, slots, y0, "rk4")
