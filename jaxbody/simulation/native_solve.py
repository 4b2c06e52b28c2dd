"""The one-call native RK4 solve: a whole fixed-step solve as one native program.

A fixed-step ``"rk4"`` solve on the native kernel that keeps only its end state
(``saveat=SaveAt(t1=True)``), of a scene of gravity, joint springs and joint dampers, without
an event, runs as one native call (:func:`jaxbody.backends.native.rk4_rollout`) instead of diffrax's
loop. It applies only there because only there does the native program compute exactly what
the loop would: the same field (:func:`jaxbody.simulation.field.native_field`), the same steps,
failures and result codes, and nothing saved between the ends that the program would have to
hand back step by step. Its gradient with respect to the initial state is a native reverse
sweep (:func:`jaxbody.backends.native.rk4_rollout_vjp`); any other derivative (the scene's parameters)
goes through diffrax's loop, which is then run for the derivative alone.
``$JAXBODY_NATIVE_SOLVE=0`` turns this off.
"""

import os

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

# the module, not its functions: read at call time, so a test can intercept the native calls
from ..backends import native
from .adjoint import default_checkpoints
from .field import native_field
from .solution import RESULTS
from .solvers import Guarded, RK4Stages

__all__ = ["native_solve_enabled", "native_solve_applies", "native_solve", "native_reverse", "native_or_stepped"]

# the save function of a SubSaveAt that saves the state itself (diffrax's default)
_SAVE_STATE = diffrax.SubSaveAt(t1=True).fn


def native_solve_enabled() -> bool:
    """``$JAXBODY_NATIVE_SOLVE=0`` turns the one-call solve (:func:`native_solve`) off: every
    ``simulate`` then steps through diffrax's loop. Read when a solve is traced, by the caller
    of the compiled solve, so that the setting keys the compiled program."""
    return os.environ.get("JAXBODY_NATIVE_SOLVE", "1") != "0"


def native_solve_applies(scene, y0, solver, controller, saveat, adjoint, meter, event, dense, slots) -> bool:
    """Whether a solve can run as one native call (:func:`jaxbody.backends.native.rk4_rollout`): RK4 at
    constant steps on a scene whose field the native programs compute (:func:`jaxbody.simulation.field.native_field`),
    saving the end state alone, without an event, dense output or progress meter, under an
    adjoint that differentiates in reverse mode."""
    # exact types: a subclass or another wrapper (a re-partitioning solver) may step differently
    if type(solver) is not Guarded or not solver.record or type(solver.solver) is not RK4Stages:
        return False
    if type(controller) is not diffrax.ConstantStepSize or event is not None or dense:
        return False
    # the native program has no tangent rule: forward mode stays in diffrax's loop
    if not isinstance(meter, diffrax.NoProgressMeter) or isinstance(adjoint, diffrax.ForwardMode):
        return False
    main = saveat.subs if saveat.subs is not None else diffrax.SubSaveAt(ts=saveat.ts, t0=saveat.t0, t1=saveat.t1, steps=saveat.steps)
    if not isinstance(main, diffrax.SubSaveAt) or not main.t1 or main.t0 or main.ts is not None or main.steps:
        return False
    return main.fn is _SAVE_STATE and native_field(scene, y0, slots) is not None


def _native_arguments(scene, y0, valid, slots) -> tuple:
    """``(model, keyword arguments)`` of :func:`jaxbody.backends.native.rk4_rollout` for a solve of ``scene``
    from ``y0`` (:func:`jaxbody.simulation.field.native_field`)."""
    model, gravity, passive = native_field(scene, y0, slots)
    # a member that failed the boundary check stays frozen, as under the stepped field
    kwargs = dict(gravity=gravity, frozen=False if valid is None else ~valid, **passive)
    return model, kwargs


def _forward_in_time(t0, t1, dt0):
    """``t1``, checked to be no earlier than ``t0`` (the native solve steps forward only; diffrax
    raises on the same times)."""
    return eqx.error_if(t1, (t1 - t0) * dt0 < 0, "simulate: t1 must not be before t0 (a fixed-step solve runs forward)")


def _native_outputs(y0, t1, slots, q, v, w, t, steps, failed) -> tuple:
    """:func:`jaxbody.simulation.solve.integrate`'s outputs for a solve that saves the end state
    alone, from the native solve's results."""
    dtype = y0[0].dtype
    ys = (q[None], v[None]) + ((y0[2].at[slots[0]].set(w.astype(dtype))[None],) if len(y0) == 3 else ())
    ts = t.astype(dtype)[None]
    stats = {"num_steps": steps, "num_accepted_steps": steps, "num_rejected_steps": jnp.asarray(0)}  # as diffrax gives it
    # the codes diffrax's loop would give: stopping short of t1 means the step budget ran out
    result = RESULTS.where(t < t1, RESULTS.max_steps_reached, RESULTS.successful)
    result = RESULTS.where(failed, RESULTS.nonfinite, result)
    return ts, ys, ts, ys, stats, result


def native_solve(scene, y0, t0, t1, dt0, valid, max_steps, slots):
    """The solve of :func:`jaxbody.simulation.solve.integrate` as one native call per batch
    (:func:`jaxbody.backends.native.rk4_rollout`): ``(ts, ys, tf, yf, stats, result)``."""
    model, kwargs = _native_arguments(scene, y0, valid, slots)
    w0 = y0[2][slots[0]] if len(y0) == 3 else 0.0
    t1 = _forward_in_time(t0, t1, dt0)
    out = native.rk4_rollout(model, y0[0], y0[1], t0, t1, dt0, max_steps, work0=w0, **kwargs)
    return _native_outputs(y0, t1, slots, *out)


def _instantiate(cotangent):
    """A cotangent given as ``SymbolicZero`` as an array of zeros."""
    if isinstance(cotangent, SymbolicZero):
        return jnp.zeros(cotangent.aval.shape, cotangent.aval.dtype)
    return cotangent


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
        out, pullback = jax.vjp(lambda d, y: stepped(eqx.combine(d, static), y), values, y0_values)
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
    """``(forward, backward)`` of :func:`native_or_stepped` by the native reverse sweep
    (:func:`jaxbody.backends.native.rk4_rollout_vjp`): the solve keeps as many checkpoints as the
    checkpointed ``adjoint`` would (default: :func:`default_checkpoints`, within its memory
    budget); ``None`` without a bounded step budget."""
    # the sweep's checkpoint memory is planned over the step budget: without one, diffrax's loop
    if max_steps is None:
        return None
    checkpoints = adjoint.checkpoints
    if checkpoints is None:
        checkpoints = default_checkpoints(max_steps, y0[0].size + y0[1].size, y0[0].dtype.itemsize)

    def forward(rest, y0):
        scene, t0, t1, dt0, valid = rest[:5]
        model, kwargs = _native_arguments(scene, y0, valid, slots)
        w0 = y0[2][slots[0]] if len(y0) == 3 else 0.0
        t1 = _forward_in_time(t0, t1, dt0)
        *out, saved = native.rk4_rollout_checkpointed(model, y0[0], y0[1], t0, t1, dt0, max_steps, checkpoints, work0=w0,
                                               **kwargs)
        return _native_outputs(y0, t1, slots, *out), (rest, y0, saved, out[4])

    def backward(residuals, cotangents):
        (scene, t0, t1, dt0, valid, *_), y0, saved, steps = residuals
        _, ys, _, yf, _, _ = cotangents
        # the end state is both the saved point and the final state
        ct = [_instantiate(a)[0] + _instantiate(b)[0] for a, b in zip(ys, yf)]
        model, kwargs = _native_arguments(scene, y0, valid, slots)
        work = ct[2][slots[0]] if len(y0) == 3 else 0.0
        ct_q, ct_v = native.rk4_rollout_vjp(model, y0[0], y0[1], t0, t1, dt0, max_steps, checkpoints, saved, steps, ct[0],
                                     ct[1], work, **kwargs)
        return (ct_q, ct_v) + ((ct[2],) if len(y0) == 3 else ())

    return forward, backward
