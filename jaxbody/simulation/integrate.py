"""The entry point :func:`jaxbody.simulate`: what it accepts and how it hands each case on.

A :class:`jaxbody.Phases` goes to the phase runner; anything else becomes a scene
(:func:`as_scene`) and goes to one scene's solve. The protocol a system that is neither a
scene nor a model must follow is :class:`DynamicalSystem`.
"""

import dataclasses
from collections.abc import Callable
from typing import Protocol

import diffrax
import equinox as eqx
import jax.numpy as jnp

from .._types import Array, ArrayLike, Float, Scalar
from .._util import is_concrete
from ..effects import Actuation
from ..model import Model
from ..scene import Event, Phases, Scene, SystemScene, own_constraints, scene as build_scene
from .phases import simulate_phases
from .solution import Solution
from .auto import choose_auto, default_tolerance, warn_below_resolution
from .prefetch import prefetch_first
from .solve import simulate_scene

__all__ = ["DynamicalSystem", "simulate", "as_scene"]


class DynamicalSystem(Protocol):
    """What :func:`simulate` needs from a system that is not a :class:`jaxbody.Model`.

    ``nq``, ``nv`` (Python ints), ``qdot(q, v)``, ``acceleration(t, q, v, tau)`` (``tau`` may be
    ``None``) and optionally ``total_energy(q, v)``, ``power(t, q, v, tau)`` (the power of the
    non-conservative forces, so the energy balance closes) and ``coordinate_chart()`` (a
    :class:`jaxbody.scene.CoordinateChart`: where the coordinates are regular; a step that leaves
    it stops its trajectory with a message naming the chart, see the user guide's "Singular
    coordinates: charts").
    """

    nq: int
    nv: int

    def qdot(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nq"]: ...

    def acceleration(
        self, t: Scalar, q: Float[Array, " nq"], v: Float[Array, " nv"], tau: Float[Array, " nv"] | None
    ) -> Float[Array, " nv"]: ...


class _Constant(eqx.Module):
    """A constant ``tau`` as a law ``tau(t, q, v)`` (a module: its array is a parameter ``grad``
    reaches, not a constant folded into the compiled solve)."""

    value: Array

    def __call__(self, t, q, v):
        return self.value


def as_scene(system, tau):
    """The scene :func:`jaxbody.simulate` integrates for ``system`` (a scene, a model: its default
    scene, or a :class:`DynamicalSystem`) with the extra generalized forces ``tau`` added as an
    actuation effect."""
    if isinstance(system, Model):
        # a bare model means its own gravity, springs and dampers (jb.scene's defaults)
        system = build_scene(system)
    elif not isinstance(system, Scene):
        # checked here, before tracing, so that the error names what is missing instead of
        # failing deep inside diffrax
        missing = [n for n in ("nq", "nv", "qdot", "acceleration") if not hasattr(system, n)]
        if missing:
            raise TypeError(
                f"simulate needs a jaxbody.Scene, a jaxbody.Model or a system with nq, nv, qdot and acceleration "
                f"(see jaxbody.simulation.DynamicalSystem); {type(system).__name__} lacks {', '.join(missing)}"
            )
        # wrapped as it is: the system brings its own forces, the scene adds none
        system = SystemScene(system=system, effects=(), constraints=own_constraints(system))
    if tau is None:
        return system
    if not callable(tau):
        t_arr = jnp.asarray(tau, jnp.result_type(float))
        if t_arr.shape != (system.nv,):
            raise ValueError(f"tau must have shape ({system.nv},) or be callable, got {t_arr.shape}")
        if is_concrete(t_arr) and not bool(jnp.all(jnp.isfinite(t_arr))):
            raise ValueError(f"simulate: tau contains NaN or inf: {t_arr.tolist()}")
        tau = _Constant(t_arr)
    act = Actuation(tau)
    act.check(system)
    # the same scene class (same path, planar conversion and kernel) with one more effect: an
    # extra joint-space force changes neither the path nor the kernel that can run it
    return dataclasses.replace(system, effects=system.effects + (act,))


def simulate(
    system,
    q0: Float[ArrayLike, " nq"],
    v0: Float[ArrayLike, " nv"],
    t1: ArrayLike,
    *,
    t0: ArrayLike = 0.0,
    tau: ArrayLike | Callable | None = None,
    solver: str | diffrax.AbstractSolver = "auto",
    rtol: ArrayLike | None = None,
    atol: ArrayLike | None = None,
    target_error: float | None = None,
    dt0: ArrayLike | None = None,
    controller: diffrax.AbstractStepSizeController | None = None,
    saveat: diffrax.SaveAt | ArrayLike | None = None,
    n_save: int | None = None,
    max_steps: int | None = 100_000,
    adjoint: diffrax.AbstractAdjoint | str | None = None,
    event: Event | Callable | None = None,
    dense: bool = False,
    throw: bool = True,
    progress: bool = False,
    track_work: bool = True,
    project_initial: bool = False,
) -> Solution:
    """Integrate a scene from ``(q0, v0)`` at ``t0`` to ``t1`` (or to a terminating event).

    Args:
        system: a :class:`jaxbody.Scene`, a :class:`jaxbody.Model` (= ``jb.scene(model)``), a
            :class:`jaxbody.Phases` (one joined solution: trajectory, energy balance across the
            switches, reactions and switch reports; see "Phases" in the docstring of :mod:`jaxbody.simulation`) or
            any :class:`DynamicalSystem`.
        q0: initial coordinates ``(nq,)``; v0: initial velocities ``(nv,)``.
        t1: final time (after ``t0``).
        t0: initial time.
        tau: extra generalized forces, added as an actuation effect: a constant ``(nv,)`` array
            or a callable ``tau(t, q, v) -> (nv,)``.
        solver: ``"auto"`` (the default: chosen from the scene's stiffness, constraints and
            dtype and the accuracy asked, see :mod:`jaxbody.simulation.auto`; the choice and its
            reason are in ``Solution.solver`` and ``Solution.solver_reason``), a preset — fixed step: ``"euler"``, ``"semi_implicit_euler"``, ``"heun"``,
            ``"rk4"`` (need ``dt0``); adaptive (PID control with ``rtol``/``atol``): ``"tsit5"``,
            ``"dopri5"``, ``"dopri8"``, ``"kvaerno5"`` (implicit, for stiff springs and dampers) —
            or any diffrax solver object.
        rtol, atol: tolerances of adaptive solvers (``None``: 1e-8 in float64, 1e-5 in float32;
            a warning when asked below ten times the dtype's resolution).
        target_error: instead of ``rtol``/``atol`` with ``solver="auto"``: the error of the final
            state to aim at; the tolerances follow from the error per tolerance the accuracy study
            measured (``docs/accuracy.md``).
        dt0: step of fixed-step solvers; first trial step of adaptive ones (``None``: automatic).
        controller: a diffrax step-size controller replacing the default PID / constant step.
        saveat: times ``(n_save,)`` or a ``diffrax.SaveAt`` (``ts``, ``t0``, ``t1``, ``steps``;
            for output at any time use ``dense=True``).
        n_save: ``n_save`` evenly spaced times from ``t0`` to ``t1``; default 101.
        max_steps: step budget; running out is a failed solve (``max_steps_reached``).
        adjoint: ``None``/``"checkpoint"`` (recursive checkpointing, the default),
            ``"backsolve"``, ``"forward"`` (forward-mode, for ``jax.jacfwd``) or a diffrax adjoint.
        event: a :class:`jaxbody.Event` or a callable ``g(t, q, v)``: the solve stops where
            ``g`` crosses zero, located by Newton's method to rounding.
        dense: keep the solver's dense output: :meth:`Solution.evaluate` gives ``(q, v)`` at any
            time (memory grows with the number of steps).
        throw: raise on failure (see :mod:`jaxbody.simulation`) or return result codes.
        progress: show diffrax's ``TqdmProgressMeter`` (text meter without tqdm).
        track_work: integrate the work of the non-conservative effects (energy balance).
        project_initial: when the scene has Maggi constraints (``jb.scene(..., constraints=)``
            or a :class:`jaxbody.maggi.ConstrainedSystem`) and ``(q0, v0)`` violates them,
            project instead of raising: ``q0`` onto the holonomic rows (Newton steps,
            :func:`jaxbody.maggi.project_positions`; concrete ``q0`` only, a traced one is
            used as given), then ``v0`` onto all rows in the kinetic metric (the closest
            admissible rates in kinetic energy); the correction ``v0_projected − v0`` is
            reported in ``Solution.stats["v0_correction"]``.

    Returns:
        :class:`Solution`.

    Raises:
        TypeError: ``system`` lacks the protocol's members.
        ValueError: unknown solver, missing ``dt0``, ``t1`` not after ``t0``, non-positive or
            non-finite ``rtol``/``atol``/``dt0``/``max_steps``, wrong shapes of ``q0``/``v0``/
            ``tau`` (naming the argument), NaN/inf inputs or negative masses (concrete inputs),
            and initial rates that violate the scene's constraints (naming the constraint rows;
            under ``jit``/``vmap`` an ``eqx.error_if`` with the same message, or the result code
            ``invalid_input`` with ``throw=False``).
        SimulationError: the solve failed and ``throw=True``. With concrete inputs it is raised
            as such; under ``jax.jit`` it is raised from a host callback, so it surfaces as JAX's
            runtime error (``jax.errors.JaxRuntimeError``) whose message holds the same text:
            the time reached, the reason, and ``q``/``v`` there (with the batch member under
            ``vmap``).
    """
    dtype = _state_dtype(q0)
    choice = None
    if isinstance(solver, str) and solver == "auto":
        first = system.scenes[0] if isinstance(system, Phases) else as_scene(system, tau)
        # the native builds start now, beside the choice (an empty cache: seconds of compiler)
        prefetch_first(first, q0)
        choice = choose_auto(first, q0, t0, t1, dtype, rtol, atol, target_error)
        solver, rtol, atol = choice.solver, choice.rtol, choice.atol
    elif target_error is not None:
        raise ValueError(f"simulate: target_error needs solver='auto' (got solver={solver!r}); give rtol/atol instead")
    rtol = default_tolerance(dtype) if rtol is None else rtol
    atol = default_tolerance(dtype) if atol is None else atol
    warn_below_resolution(dtype, rtol, atol)
    sol = _dispatch(system, q0, v0, t1, t0, tau, solver, rtol, atol, dt0, controller, saveat, n_save, max_steps, adjoint,
                    event, dense, throw, progress, track_work, project_initial)
    name = solver if isinstance(solver, str) else type(solver).__name__
    reason = choice.reason if choice is not None else "asked for"
    return dataclasses.replace(sol, solver=name, solver_reason=reason)


def _state_dtype(q0):
    """The dtype a solve from ``q0`` runs in (as ``simulate_scene`` casts it)."""
    dtype = getattr(q0, "dtype", None)
    if dtype is None:
        dtype = jnp.asarray(q0).dtype
    return dtype if jnp.issubdtype(dtype, jnp.inexact) else jnp.result_type(float)


def _dispatch(system, q0, v0, t1, t0, tau, solver, rtol, atol, dt0, controller, saveat, n_save, max_steps, adjoint,
              event, dense, throw, progress, track_work, project_initial):
    """A phased run or one scene's solve, with the solver and tolerances decided."""
    if isinstance(system, Phases):
        # each phase declares its own forces and ends on its own event: a run-wide tau, event or
        # dense output would be ambiguous across the switches
        extra = [name for name, given in (("tau", tau is not None), ("event", event is not None), ("dense", dense)) if given]
        if extra:
            raise ValueError(
                f"simulate: {', '.join(extra)} cannot be given with jaxbody.Phases (declare actuation in "
                "the phases' scenes; their events end the phases; phases save at times)"
            )
        return simulate_phases(
            system, q0, v0, t1, t0=t0, solver=solver, rtol=rtol, atol=atol, dt0=dt0, controller=controller,
            saveat=saveat, n_save=n_save, max_steps=max_steps, adjoint=adjoint, throw=throw, progress=progress,
            track_work=track_work, project_initial=project_initial,
        )
    scene = as_scene(system, tau)
    sol, _ = simulate_scene(
        scene, q0, v0, t1, t0=t0, solver=solver, rtol=rtol, atol=atol, dt0=dt0, controller=controller,
        saveat=saveat, n_save=n_save, max_steps=max_steps, adjoint=adjoint, event=event, dense=dense,
        throw=throw, progress=progress, track_work=track_work, project_initial=project_initial,
    )
    return sol
