"""Integrate scenes with diffrax: presets, events, phases, batches over devices, solutions on disk.

:func:`simulate` solves

    q̇ = qdot(q, v),     v̇ = a(t, q, v),     ẇ_e = f_e·v   (work of each non-conservative effect)

from ``(q0, v0)`` at ``t0`` to ``t1`` for a :class:`jaxbody.Scene` (a bare :class:`jaxbody.Model`
means ``jb.scene(model)``: the model's own gravity, springs and dampers; any other object with
the simulation protocol is wrapped as is). It returns a :class:`Solution` pytree. ``jit``,
``vmap`` and ``grad`` (through diffrax's adjoints) pass through.

A fixed-step ``"rk4"`` solve on the native kernel that keeps only its end state
(``saveat=SaveAt(t1=True)``), of a scene of gravity, joint springs and joint dampers, without
an event, runs as one native call (:func:`jaxbody.native.rk4_rollout`) instead of diffrax's
loop. Its solution is the one diffrax's loop gives (the same steps, failures and result codes).
Its gradient with respect to the initial state is a native reverse sweep
(:func:`jaxbody.native.rk4_rollout_vjp`); other derivatives go through diffrax's loop.
``$JAXBODY_NATIVE_SOLVE=0`` turns this off.

Errors come in three layers. Shapes, unknown names and impossible options raise ``ValueError``
before anything is traced. Values (NaN or infinite initial states or parameters, negative
masses, initial velocities that violate the scene's constraints) are checked once at this
boundary: with concrete inputs a ``ValueError`` names the input (or the constraint rows) at
fault; under ``jit``/``vmap`` the check is an ``eqx.error_if`` with the same message
(``throw=True``) or the result code ``RESULTS.invalid_input`` (``throw=False``: that member
integrates a frozen state and the others are untouched). Inside the solver loop there are only
result codes: a NaN trial stage is a rejected step, a fixed step that ends in NaN/inf stops the
solve there (``RESULTS.nonfinite``), and a failed solve either raises a
:class:`SimulationError` saying when (``t = ...``), in which state (``q``, ``v`` there) and why
(``throw=True``; under ``jit`` the same text arrives as JAX's runtime error, raised from a host
callback) or returns the trajectory up to the failure with its code, ``t_final``, ``q_final``
and ``v_final`` marking where it stopped.

Phases. A :class:`jaxbody.Phases` runs its scenes one after the other, each until its event;
at a switch the optional transition maps the state, and a scene with Maggi constraints receives
velocities projected onto them as an impulsive constraint (kinetic metric). The phases are
joined into one :class:`Solution`: the work of every non-conservative effect is one state
vector carried across the switches; the energy change at each switch (the energy an impulsive
constraint takes, or the change of the energy function when the conservative effects differ)
is reported per switch in ``stats["switch_energy_jump"]`` and accumulated in
``work["switches"]``, so ``energy_balance`` closes across the whole run while the jumps stay
visible; reactions and constraint residuals of phases with different numbers of constraint
rows are padded with NaN to the largest count (``layout["phase_constraint_names"]`` names each
phase's rows).
"""

import dataclasses
import functools
import json
import math
import os
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax import lax
from jax.custom_derivatives import SymbolicZero

from . import maggi

from ._solvers import DelegatingSolver, for_adjoint
from ._types import Array, ArrayLike, Float, Int, Scalar
from .scene import Event, Phases, Scene, scene as build_scene
from .effects import Actuation
from .maggi import PartitionSolver, partition_report, partition_solver, with_best_partition

__all__ = [
    "DynamicalSystem",
    "Solution",
    "SimulationError",
    "RESULTS",
    "SOLVERS",
    "RK4",
    "SemiImplicitEuler",
    "simulate",
    "simulate_batch",
    "load_solution",
]


class DynamicalSystem(Protocol):
    """What :func:`simulate` needs from a system that is not a :class:`jaxbody.Model`.

    ``nq``, ``nv`` (Python ints), ``qdot(q, v)``, ``acceleration(t, q, v, tau)`` (``tau`` may be
    ``None``) and optionally ``total_energy(q, v)`` and ``power(t, q, v, tau)`` (the power of the
    non-conservative forces, so the energy balance closes).
    """

    nq: int
    nv: int

    def qdot(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nq"]: ...

    def acceleration(
        self, t: Scalar, q: Float[Array, " nq"], v: Float[Array, " nv"], tau: Float[Array, " nv"] | None
    ) -> Float[Array, " nv"]: ...


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """diffrax's result codes plus the boundary check of :func:`simulate`."""

    invalid_input = (
        "The initial state or a parameter is NaN/inf or invalid (checked before the solve: finite values, "
        "non-negative masses, initial velocities admissible for the scene's constraints)."
    )
    partition_degraded = (
        "The coordinate partition of the constraints degraded (quality below partition_tolerance times the "
        "best partition's) and re-partitioning is off (jaxbody.maggi.constrain(..., repartition=False))."
    )
    singular_parametrisation = (
        "The constraints cannot be solved for the velocities at this state (jaxbody.maggi.MaggiResult."
        "singular_parametrisation): redundant constraints (a dead point of a linkage), or user characteristics "
        "epsilon that are singular here."
    )


class SimulationError(RuntimeError):
    """A solve that did not finish (raised with ``throw=True``): says when, where and why."""


# ----------------------------------------------------------------------------- solvers
_rk4_tableau = diffrax.ButcherTableau(
    a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.zeros(4),
    c=np.array([0.5, 0.5, 1.0]),
)


class RK4(diffrax.AbstractERK):
    """Classical 4th-order Runge--Kutta method, for fixed steps (``dt0``) only.

    Dense output between steps is cubic Hermite with the first and last stage slopes.
    """

    tableau = _rk4_tableau
    interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        del terms
        return 4


class RK4Stages(diffrax.AbstractSolver):
    """:class:`RK4` with its four stages written out one after another instead of looped over.

    Same method, same dense output; the stage loop of a tableau solver compiles the vector
    field once, this writes it four times. :func:`simulate` uses it for ``"rk4"`` when the
    scene's forward dynamics is the unrolled kernel: XLA then fuses each stage's outputs
    straight into the next stage's inputs, and a ``vmap`` batch of Panda arms runs about 2.4x
    faster than through the stage loop (docs/performance.md), at about 4x the compile time.
    """

    term_structure = diffrax.AbstractTerm
    interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        del terms
        return 4

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        fused = _native_rk4_step(terms, args, y0)
        if fused is not None:
            y1, k = fused(t0, t1, y0)
            return y1, None, dict(y0=y0, y1=y1, k=k), None, diffrax.RESULTS.successful
        h = t1 - t0
        control = terms.contr(t0, t1)

        def increment(t, y):
            # the vector field times the step, through the term's own product: for an ODE
            # term ``h * f``; diffrax's backsolve adjoint solves with terms whose ``vf`` alone
            # is not the field to multiply by ``h``
            return terms.vf_prod(t, y, args, control)

        def ahead(k, c):
            return jax.tree.map(lambda y, d: y + c * d, y0, k)

        k1 = increment(t0, y0)
        k2 = increment(t0 + h / 2, ahead(k1, 0.5))
        k3 = increment(t0 + h / 2, ahead(k2, 0.5))
        k4 = increment(t1, ahead(k3, 1.0))
        y1 = jax.tree.map(lambda y, a, b, c, d: y + (a + 2 * b + 2 * c + d) / 6, y0, k1, k2, k3, k4)
        # diffrax's Hermite interpolation takes the end slopes as increments over the step
        k = jax.tree.map(lambda a, d: jnp.stack([a, d]), k1, k4)
        return y1, None, dict(y0=y0, y1=y1, k=k), None, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def _native_rk4_step(terms, args, y0):
    """The whole RK4 step as one native call (:func:`jaxbody.native.rk4_step`), where it computes
    exactly what the four stages would: ``simulate``'s own vector field (not the augmented one of
    a backsolve adjoint) for a scene whose forward dynamics is the native kernel and whose
    effects are gravity, joint dampers and joint springs: nothing that depends on time. Returns ``(t0, t1, y0) -> (y1, k)`` or ``None``."""
    from .backends.native import rk4_step

    inner = terms
    while type(inner) is diffrax._term.WrapTerm:  # diffrax's wrapper for the direction of time
        inner = inner.term
    if type(inner) is not diffrax.ODETerm:
        return None
    field = inner.vector_field
    if field is _vector_field:
        slots = None
    elif isinstance(field, functools.partial) and field.func is _vector_field:
        slots = field.keywords.get("slots")
    else:
        return None
    if not (isinstance(args, tuple) and len(args) == 2 and isinstance(args[0], Scene)):
        return None
    scene, valid = args
    plan = _native_field(scene, y0, slots)
    if plan is None:
        return None
    model, gravity, passive = plan

    def fused(t0, t1, y0):
        # the field does not depend on time: the step is the term's control (t1 - t0, signed)
        q1, v1, k1q, k1v, k4q, k4v, work = rk4_step(model, y0[0], y0[1], terms.contr(t0, t1), gravity=gravity, **passive)
        y1, k = (q1, v1), (jnp.stack([k1q, k4q]), jnp.stack([k1v, k4v]))
        if len(y0) == 3:
            w0, slot = y0[2], slots[0]
            zeros = jnp.zeros_like(w0)
            y1 = y1 + (w0.at[slot].add(work[0].astype(w0.dtype)),)
            k = k + (jnp.stack([zeros.at[slot].set(work[1].astype(w0.dtype)), zeros.at[slot].set(work[2].astype(w0.dtype))]),)
        if valid is not None:
            # a member that failed the boundary check stays frozen, as under _vector_field
            y1 = jax.tree.map(lambda a, b: jnp.where(valid, a, b), y1, y0)
            k = jax.tree.map(lambda a: jnp.where(valid, a, 0.0), k)
        return y1, k

    return fused


def _native_field(scene, y0, slots):
    """``(model, gravity, passive)`` where the native RK4 programs compute ``scene``'s vector field
    on the state ``y0 = (q, v[, w])`` exactly (:func:`jaxbody.native.rk4_step`'s arguments):
    the native kernel, and effects that are a uniform gravity field, joint dampers and joint
    springs (nothing that depends on time); a work vector ``w`` must hold the dampers' work
    alone (``slots``). ``None`` otherwise."""
    from .effects import Gravity, JointDampers, JointSprings
    from .backends import resolve_kernel

    if not isinstance(y0, tuple) or len(y0) not in (2, 3):
        return None
    effects = scene.effects
    if not scene._direct() or not all(isinstance(e, (Gravity, JointDampers, JointSprings)) for e in effects):
        return None
    springs = [e for e in effects if isinstance(e, JointSprings)]
    dampers = [e for e in effects if isinstance(e, JointDampers)]
    if len(springs) > 1 or len(dampers) > 1 or resolve_kernel(scene.system, getattr(scene, "kernel", None)) != "native":
        return None
    if len(y0) == 3 and (not slots or not dampers or len(slots) != 1):
        return None  # a work vector whose slots are not the dampers' alone
    gravity = scene._gravity(y0[1].dtype)  # None: no field (rk4_step's default)
    passive = {}
    if springs:
        passive.update(stiffness=springs[0].stiffness, reference=springs[0].reference)
    if dampers:
        passive.update(damping=dampers[0].damping)
    return scene.system, gravity, passive


def _runs_unrolled_kernel(scene) -> bool:
    """Whether ``scene``'s vector field runs a straight-line forward-dynamics kernel (native or unrolled)."""
    from .backends import resolve_kernel

    if getattr(scene, "path", None) != "spatial" or not scene._direct():
        return False
    return resolve_kernel(scene.system, getattr(scene, "kernel", None)) in ("native", "unrolled")


class SemiImplicitEuler(diffrax.AbstractSolver):
    """Symplectic (semi-implicit) Euler on ``y = (q, v, ...)``: ``v₁ = v₀ + h a(t₀, q₀, v₀)``,
    then ``q₁ = q₀ + h q̇(q₀, v₁)``. Fixed steps only; first order, but bounded energy error on
    conservative scenes. Needs the vector field of :func:`simulate` (it splits ``q`` from ``v``).
    """

    term_structure = diffrax.AbstractTerm
    interpolation_cls = diffrax.LocalLinearInterpolation

    def order(self, terms):
        return 1

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        h = t1 - t0
        d0 = terms.vf(t0, y0, args)
        v1 = y0[1] + h * d0[1]
        d1 = terms.vf(t0, (y0[0], v1) + tuple(y0[2:]), args)
        y1 = (y0[0] + h * d1[0], v1) + tuple(y + h * d for y, d in zip(y0[2:], d0[2:]))
        return y1, None, dict(y0=y0, y1=y1), None, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


class _Guarded(DelegatingSolver):
    """Wraps a solver: projects every step's end state (unit quaternions) and flags a
    non-finite one.

    Projection after each step keeps ball/free quaternions on the unit sphere to rounding,
    while the error estimate (and so the step control) is the wrapped solver's. A step whose
    end state is NaN or inf returns diffrax's ``nonfinite`` code: an adaptive controller
    rejects that step anyway (its error estimate is not finite) and tries a smaller one, but a
    fixed step is accepted, so the solve stops there (``t_final``, ``q_final``, ``v_final`` show
    the first non-finite state) instead of carrying NaN to ``t1`` and calling that a success. ``isinstance`` checks (adaptive,
    implicit) are forwarded to the wrapped solver by diffrax.

    ``record=True`` (fixed steps): the first non-finite step of each trajectory is recorded in
    the solver state (:class:`_Failure`), the trajectory stays in the state that step ended in,
    and the loop stops only when every trajectory of a ``vmap`` batch has failed (alone, at
    once). The result code the loop sees is then the same for the whole batch, so diffrax's
    batched loop needs no per-trajectory predicate and does not select every carried array
    (saved trajectories included) on every step; the record itself is updated (a conditional
    on the batch) only once some trajectory is not finite. :func:`_apply_failure` gives each
    trajectory its own outcome after the solve, equal to what the stopping loop gives.
    """

    project: Any = None
    record: bool = eqx.field(static=True, default=False, kw_only=True)

    def __getattr__(self, name):
        # anything else diffrax reads from the solver (e.g. an implicit solver's root_finder,
        # whose tolerances it sets from the step-size controller) is the wrapped solver's
        if name.startswith("__") or name in ("solver", "project", "scan_kind", "record"):
            raise AttributeError(name)
        return getattr(self.solver, name)

    def init(self, terms, t0, t1, y0, args):
        state = self.inner.init(terms, t0, t1, y0, args)
        if not self.record:
            return state
        t0 = jnp.asarray(t0)
        failure = _Failure(failed=jnp.asarray(False), t=jnp.full_like(t0, jnp.inf),
                           steps=jnp.zeros((), jnp.int32), count=jnp.zeros((), jnp.int32))
        return state, failure

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner_state, failure = solver_state if self.record else (solver_state, None)
        y1, err, dense, state, result = self.inner.step(terms, t0, t1, y0, args, inner_state, made_jump)
        if self.project is not None:
            y1 = self.project(y1)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(y1)]))
        if not self.record:
            result = diffrax.RESULTS.where(finite, result, diffrax.RESULTS.nonfinite)
            return y1, err, dense, state, result
        count = failure.count + 1
        # a trajectory that failed stays in its first non-finite state (its final state)
        y1 = jax.tree.map(lambda a, b: jnp.where(failure.failed, a, b), y0, y1)

        def record(failure, t1):
            first = ~finite & ~failure.failed
            return _Failure(failed=failure.failed | first, t=jnp.where(first, t1, failure.t),
                            steps=jnp.where(first, count, failure.steps), count=count)

        # while every trajectory is finite (the usual case) a batch skips the record's selects
        failure = lax.cond(
            eqx.internal.unvmap_any(~finite | failure.failed),
            record,
            lambda failure, t1: eqx.tree_at(lambda f: f.count, failure, count),
            lax.stop_gradient(failure),
            lax.stop_gradient(t1),
        )
        # stop when every trajectory has failed: one code for a whole vmap batch
        result = diffrax.RESULTS.where(eqx.internal.unvmap_all(failure.failed), diffrax.RESULTS.nonfinite, result)
        return y1, err, dense, (state, failure), result


class _Failure(eqx.Module):
    """The first non-finite step of a trajectory (:class:`_Guarded` with ``record=True``):
    whether there was one, its end time, and how many steps it was; ``count``: the steps taken
    so far. (The state stays where that step ended.)"""

    failed: Array
    t: Array
    steps: Array
    count: Array


def _recording_depth(solver) -> int | None:
    """How many wrappers (a PartitionSolver) sit above a recording :class:`_Guarded` in
    ``solver``; ``None`` when it has none."""
    depth = 0
    # type(), not isinstance: diffrax counts a wrapper as an instance of what it wraps
    while issubclass(type(solver), DelegatingSolver) and type(solver) is not _Guarded:
        solver, depth = solver.solver, depth + 1
    return depth if type(solver) is _Guarded and solver.record else None


def _failure_record(solver_state, depth: int):
    """The :class:`_Failure` in a solve's final solver state (a wrapper's state holds the
    wrapped solver's first)."""
    for _ in range(depth):
        solver_state = solver_state[0]
    return solver_state[1]


def _apply_failure(failure, ts, ys, tf, stats, result, final_is_last):
    """Each trajectory's own outcome from the recorded first failure: the result ``nonfinite``,
    the end time of the failing step as the final time (the state stayed there), the step counts
    up to it, and the saved times after it padded with ``inf`` as diffrax pads times a solve
    never reached (``final_is_last``: the last saved point is the final state, diffrax's
    ``SaveAt(t1=True)``)."""
    failed = failure.failed
    late = failed & (ts > failure.t)
    if final_is_last:
        late = late.at[-1].set(False)
    pad = lambda x: jnp.where(late.reshape(late.shape + (1,) * (x.ndim - 1)), jnp.inf, x)  # noqa: E731
    ts = pad(ts)
    ys = jax.tree.map(pad, ys)
    if final_is_last:
        ts = ts.at[-1].set(jnp.where(failed, failure.t, ts[-1]))
    tf = tf.at[-1].set(jnp.where(failed, failure.t, tf[-1]))
    steps = jnp.where(failed, failure.steps, stats["num_steps"])
    stats = {**stats, "num_steps": steps, "num_accepted_steps": jnp.where(failed, steps, stats["num_accepted_steps"])}
    result = RESULTS.where(failed, RESULTS.nonfinite, result)
    return ts, ys, tf, stats, result


class _UnitQuaternions(eqx.Module):
    """Renormalises the ball/free quaternions of ``y[0]`` (a module, so the model's arrays are
    traced and equal scenes share one compilation)."""

    model: Any

    def __call__(self, y):
        from .kinematics import normalize_qpos

        if isinstance(y[0], tuple):
            # diffrax's backsolve adjoint steps the augmented state (state, adjoints, ...) with
            # the same solver: renormalise the state it reconstructs in reverse time
            return (self(y[0]),) + tuple(y[1:])
        return (normalize_qpos(self.model, y[0]),) + tuple(y[1:])


#: Solver presets: name -> (factory, adaptive).
SOLVERS: dict[str, tuple[Callable[[], diffrax.AbstractSolver], bool]] = {
    "euler": (diffrax.Euler, False),
    "semi_implicit_euler": (SemiImplicitEuler, False),
    "heun": (diffrax.Heun, False),
    "rk4": (RK4, False),
    "tsit5": (diffrax.Tsit5, True),
    "dopri5": (diffrax.Dopri5, True),
    "dopri8": (diffrax.Dopri8, True),
    "kvaerno5": (diffrax.Kvaerno5, True),
}


# ----------------------------------------------------------------------------- solution
class Solution(eqx.Module):
    """Result of :func:`simulate` (a pytree: batches and gradients pass through).

    Attributes:
        t: saved times ``(n_save,)``.
        q: coordinates at the saved times ``(n_save, nq)`` (MuJoCo ``qpos`` layout for models).
        v: velocities ``(n_save, nv)``.
        energy: total mechanical energy (kinetic + potentials of the declared conservative
            effects) ``(n_save,)``; ``None`` when the system has none.
        work: work done since ``t0`` by each non-conservative effect, ``{name: (n_save,)}``
            (``"actuation"``, ``"dampers"`` (negative: minus the dissipation), ``"loads"``,
            ``"support"``; for a :class:`jaxbody.Phases` run also ``"switches"``, the energy
            change at the switches up to each time); empty when there are none.
        energy_drift: ``max_t |E(t) − E(t0) − Σ work(t)| / max(|E(t0)|, tiny)`` over the saved
            times: how far the energy balance is from closing (a check of the integration,
            meaningful with damping and actuation too); ``None`` without energy. ``E(t0)`` is
            ``energy0``, so the drift is measured from the start whatever the saved times are
            (with ``SaveAt(t1=True)`` alone, it is the balance at ``t1``).
        constraint_drift: constraint residuals at the saved times, ``{"position": (n_save, s),
            "velocity": (n_save, s)}`` (position residuals ``φ(t, q)`` of the holonomic rows, zero
            on non-holonomic rows; velocity residuals ``f*(t, q, v)`` of every row), or ``None``
            without constraints.
        reactions: constraint reactions ``Λ`` at the saved times ``(n_save, s)``, one column per
            constraint row (``layout`` lists their names under ``"constraint_names"``; forces in
            newtons for the point constraints of :mod:`jaxbody.constraints`), or ``None``. For a
            :class:`jaxbody.Phases` run, ``s`` is the largest row count over the phases and a
            phase with fewer rows is padded with NaN (``layout["phase_constraint_names"]`` names
            each phase's columns); ``constraint_drift`` likewise.
        stats: ``num_steps``, ``num_accepted_steps``, ``num_rejected_steps``; ``v0_correction``
            ``(nv,)`` when ``project_initial=True`` projected ``v0`` onto the constraints; for a
            :class:`jaxbody.Phases` run also ``phase`` ``(n_save,)`` and the switch reports
            ``switch_time``, ``switch_occurred``, ``switch_energy_jump``, ``switch_energy_lost``
            ``(n_switch,)`` (module docstring, "Phases"); ``num_repartitions``
            (changes of the constraints' coordinate partition, see
            :class:`jaxbody.maggi.PartitionSolver`; ``0`` without constraints).
        result: a :class:`RESULTS` code (``successful``; ``event_occurred`` when an event ended
            the solve; a failure code otherwise).
        t_final, q_final, v_final: where the solve stopped (``t1``, the event time, or the
            last step of a failed solve: with ``throw=False`` these are the failure's time and
            state, the ones a ``throw=True`` error message quotes).
        layout: static description of ``q``/``v`` (names, joint kinds, addresses) for replay.
        repartition_times: times at which the coordinate partition was re-chosen (the first
            ``jaxbody.maggi.MAX_RECORDED_REPARTITIONS``, NaN in unused slots), or ``None``
            without an automatically partitioned constraint set.
        energy0: total energy ``E(t0)`` of the initial state (after ``project_initial``), the
            reference of ``energy_balance``, ``energy_error`` and ``energy_drift``; ``None``
            without energy.
    """

    t: Float[Array, " n_save"]
    q: Float[Array, "n_save nq"]
    v: Float[Array, "n_save nv"]
    energy: Float[Array, " n_save"] | None
    work: dict
    energy_drift: Float[Array, ""] | None
    constraint_drift: Any
    reactions: Any
    stats: dict[str, Array]
    result: RESULTS
    t_final: Float[Array, ""]
    q_final: Float[Array, " nq"]
    v_final: Float[Array, " nv"]
    layout: tuple = eqx.field(static=True, default=())
    interpolation: Any = None
    repartition_times: Any = None
    energy0: Float[Array, ""] | None = None

    def evaluate(self, t: ArrayLike) -> tuple[Float[Array, " nq"], Float[Array, " nv"]]:
        """``(q, v)`` at any time ``t`` in ``[t0, t_final]`` from the solver's dense output
        (needs ``simulate(..., dense=True)``)."""
        if self.interpolation is None:
            raise ValueError("Solution.evaluate needs simulate(..., dense=True)")
        y = self.interpolation.evaluate(t)
        return y[0], y[1]

    @property
    def success(self) -> jax.Array:
        """Boolean array: the solve reached ``t1`` or a terminating event (per member when batched)."""
        return (self.result == RESULTS.successful) | (self.result == RESULTS.event_occurred)

    @property
    def event_occurred(self) -> jax.Array:
        return self.result == RESULTS.event_occurred

    @property
    def dissipation(self) -> Float[Array, "*batch n_save"] | None:
        """Energy dissipated by the dampers since ``t0`` (``−work["dampers"]``)."""
        return None if "dampers" not in self.work else -self.work["dampers"]

    @property
    def energy_balance(self) -> Float[Array, "*batch n_save"] | None:
        """``E(t) − E(t0) − Σ work(t)`` (zero up to integration error)."""
        if self.energy is None:
            return None
        return _balance(self.energy, self.work, self.energy0)

    @property
    def energy_error(self) -> Float[Array, "*batch n_save"] | None:
        """Signed relative balance error ``(E − E0 − Σ work) / max(|E0|, tiny)`` per saved time."""
        if self.energy is None:
            return None
        return _balance(self.energy, self.work, self.energy0) / _scale(self.energy, self.energy0)

    # ------------------------------------------------------------------ files
    def _layout_dict(self):
        return dict(self.layout)

    def save(self, path) -> None:
        """Write the solution to an ``.npz`` file (arrays plus the q/v layout as JSON)."""
        arrays = {
            "t": np.asarray(self.t),
            "q": np.asarray(self.q),
            "v": np.asarray(self.v),
            "result": np.asarray(self.result._value),
            "t_final": np.asarray(self.t_final),
            "q_final": np.asarray(self.q_final),
            "v_final": np.asarray(self.v_final),
            "layout": np.asarray(json.dumps(self._layout_dict())),
        }
        if self.energy is not None:
            arrays["energy"] = np.asarray(self.energy)
            arrays["energy_drift"] = np.asarray(self.energy_drift)
            if self.energy0 is not None:
                arrays["energy0"] = np.asarray(self.energy0)
        for k, w in self.work.items():
            arrays[f"work/{k}"] = np.asarray(w)
        for k, s in self.stats.items():
            arrays[f"stats/{k}"] = np.asarray(s)
        if self.constraint_drift is not None:
            for k, r in self.constraint_drift.items():
                arrays[f"constraint_drift/{k}"] = np.asarray(r)
        if self.reactions is not None:
            arrays["reactions"] = np.asarray(self.reactions)
        if self.repartition_times is not None:
            arrays["repartition_times"] = np.asarray(self.repartition_times)
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)

    def to_csv(self, path) -> None:
        """Write ``t``, the coordinates, velocities, energy and work as CSV columns (one row per time).

        The header names the columns as ``jaxbody simulate --csv`` does: ``t``, then ``q:<joint>``
        for each coordinate and ``v:<joint>`` for each velocity in the MuJoCo ``qpos``/``qvel``
        layout (a ball or free joint's entries as ``q:<joint>.qw`` ... and ``v:<joint>.wx`` ...;
        ``q:q0``, ``v:v0`` ... for systems without joint names), then ``energy`` and ``work_<effect>``.
        """
        lay = self._layout_dict()
        nq, nv = self.q.shape[-1], self.v.shape[-1]
        if "joint_names" in lay and "joint_kinds" in lay:
            q_parts = {"ball": ("qw", "qx", "qy", "qz"), "free": ("x", "y", "z", "qw", "qx", "qy", "qz")}
            v_parts = {"ball": ("wx", "wy", "wz"), "free": ("vx", "vy", "vz", "wx", "wy", "wz")}
            qn, vn = [], []
            for name, kind in zip(lay["joint_names"], lay["joint_kinds"]):
                qn += [f"{name}.{c}" for c in q_parts[kind]] if kind in q_parts else [name]
                vn += [f"{name}.{c}" for c in v_parts[kind]] if kind in v_parts else [name]
        else:
            qn, vn = [], []
        if len(qn) != nq or len(vn) != nv:
            qn, vn = [f"q{i}" for i in range(nq)], [f"v{i}" for i in range(nv)]
        cols = [np.asarray(self.t)[:, None], np.asarray(self.q), np.asarray(self.v)]
        names = ["t", *(f"q:{n}" for n in qn), *(f"v:{n}" for n in vn)]
        if self.energy is not None:
            cols.append(np.asarray(self.energy)[:, None])
            names.append("energy")
        for k, w in self.work.items():
            cols.append(np.asarray(w)[:, None])
            names.append(f"work_{k}")
        np.savetxt(path, np.concatenate(cols, axis=1), delimiter=",", header=",".join(names), comments="")


def load_solution(path) -> Solution:
    """Read a solution written by :meth:`Solution.save`."""
    with np.load(path) as data:
        d = {k: data[k] for k in data.files}
    work = {k[5:]: jnp.asarray(v) for k, v in d.items() if k.startswith("work/")}
    stats = {k[6:]: jnp.asarray(v) for k, v in d.items() if k.startswith("stats/")}
    layout = json.loads(str(d["layout"]))
    result = RESULTS.where(jnp.asarray(True), RESULTS.successful, RESULTS.successful)
    result = eqx.tree_at(lambda r: r._value, result, jnp.asarray(d["result"]))
    return Solution(
        t=jnp.asarray(d["t"]),
        q=jnp.asarray(d["q"]),
        v=jnp.asarray(d["v"]),
        energy=jnp.asarray(d["energy"]) if "energy" in d else None,
        work=work,
        energy_drift=jnp.asarray(d["energy_drift"]) if "energy_drift" in d else None,
        energy0=jnp.asarray(d["energy0"]) if "energy0" in d else None,
        constraint_drift={k[17:]: jnp.asarray(v) for k, v in d.items() if k.startswith("constraint_drift/")} or None,
        reactions=jnp.asarray(d["reactions"]) if "reactions" in d else None,
        stats=stats,
        result=result,
        t_final=jnp.asarray(d["t_final"]),
        q_final=jnp.asarray(d["q_final"]),
        v_final=jnp.asarray(d["v_final"]),
        layout=tuple(sorted((k, _tuples(v)) for k, v in layout.items())),
        repartition_times=jnp.asarray(d["repartition_times"]) if "repartition_times" in d else None,
    )


def _tuples(x):
    """JSON lists back to (hashable) tuples, nested ones too."""
    return tuple(_tuples(y) for y in x) if isinstance(x, list) else x


def _scale(energy, energy0=None):
    e0 = energy[..., :1] if energy0 is None else energy0[..., None]
    return jnp.maximum(jnp.abs(e0), jnp.finfo(energy.dtype).tiny)


def _balance(energy, work, energy0=None, work0=None):
    """``E(t) − E(t0) − Σ (w(t) − w(t0))``. ``energy0``: ``E(t0)``, with ``work0`` the work
    vector at ``t0`` (default zero, in ``work``'s order); without ``energy0`` (a solution read
    from an older file) the first saved time stands for ``t0``."""
    e0 = energy[..., :1] if energy0 is None else energy0[..., None]
    out = energy - e0
    for i, w in enumerate(work.values()):
        if energy0 is None:
            out = out - (w - w[..., :1])
        else:
            out = out - (w if work0 is None else w - work0[..., i : i + 1])
    return out


def _layout(system) -> tuple:
    names = getattr(getattr(system, "constraints", None), "constraint_names", None)
    extra = (("constraint_names", tuple(names)),) if names is not None else ()
    return tuple(sorted(_layout_of(system) + extra))


def _layout_of(system) -> tuple:
    from .model import Model

    if isinstance(system, Scene):
        system = system.system
    if not isinstance(system, Model):
        return (("nq", system.nq), ("nv", system.nv))
    from .joints import JOINT_KIND_NAMES

    j = system.joints
    q_names, v_names = [], []
    for name, kind in zip(j.names, j.type):
        kind = int(kind)
        if JOINT_KIND_NAMES[kind] == "free":
            q_names += [f"{name}_{c}" for c in ("x", "y", "z", "qw", "qx", "qy", "qz")]
            v_names += [f"{name}_{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz")]
        elif JOINT_KIND_NAMES[kind] == "ball":
            q_names += [f"{name}_{c}" for c in ("qw", "qx", "qy", "qz")]
            v_names += [f"{name}_{c}" for c in ("wx", "wy", "wz")]
        else:
            q_names.append(name)
            v_names.append(name)
    return (
        ("joint_kinds", tuple(JOINT_KIND_NAMES[int(k)] for k in j.type)),
        ("joint_names", tuple(j.names)),
        ("model", system.name),
        ("nq", system.nq),
        ("nv", system.nv),
        ("q_names", tuple(q_names)),
        ("qposadr", tuple(int(a) for a in j.qposadr)),
        ("v_names", tuple(v_names)),
    )


# ----------------------------------------------------------------------------- checks
def _is_concrete(*xs):
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(xs))


def _param_leaves(system):
    leaves = jax.tree_util.tree_flatten_with_path(eqx.filter(system, eqx.is_inexact_array))[0]
    return [(jax.tree_util.keystr(path), leaf) for path, leaf in leaves if leaf is not None]


def _value_checks(system, q0, v0):
    """``[(bad, message)]``: boundary value checks (each ``bad`` a boolean scalar)."""
    from .model import Model

    checks = [
        (~jnp.all(jnp.isfinite(q0)), "simulate: q0 contains NaN or inf"),
        (~jnp.all(jnp.isfinite(v0)), "simulate: v0 contains NaN or inf"),
    ]
    for name, leaf in _param_leaves(system):
        checks.append((~jnp.all(jnp.isfinite(leaf)), f"simulate: parameter {name} contains NaN or inf"))
    model = system.system if isinstance(system, Scene) else system
    if isinstance(model, Model):
        checks.append((jnp.any(model.body_mass < 0), "simulate: parameter body_mass is negative"))
    return checks


def _concrete_value_checks(system, q0, v0):
    """Python errors naming the culprit when every input is concrete."""
    from .model import Model

    if not np.all(np.isfinite(np.asarray(q0))):
        raise ValueError(f"simulate: q0 contains NaN or inf at indices {np.nonzero(~np.isfinite(np.asarray(q0)))[0].tolist()}")
    if not np.all(np.isfinite(np.asarray(v0))):
        raise ValueError(f"simulate: v0 contains NaN or inf at indices {np.nonzero(~np.isfinite(np.asarray(v0)))[0].tolist()}")
    for name, leaf in _param_leaves(system):
        if not np.all(np.isfinite(np.asarray(leaf))):
            raise ValueError(f"simulate: parameter {name} contains NaN or inf")
    model = system.system if isinstance(system, Scene) else system
    if isinstance(model, Model):
        bad = np.nonzero(np.asarray(model.body_mass) < 0)[0]
        if bad.size:
            raise ValueError(f"simulate: body {model.body_names[bad[0]]!r} has negative mass {float(model.body_mass[bad[0]])}")


def _positive(name, value, integer=False):
    if value is None or not _is_concrete(value):
        return
    a = np.asarray(value)
    if a.size != 1 or not np.isfinite(a) or a <= 0:
        raise ValueError(f"simulate: {name} must be a positive finite number, got {value!r}")
    if integer and (int(a) != a):
        raise ValueError(f"simulate: {name} must be a positive integer, got {value!r}")


class _Constant(eqx.Module):
    value: Array

    def __call__(self, t, q, v):
        return self.value


def _as_scene(system, tau):
    from .model import Model

    if isinstance(system, Model):
        system = build_scene(system)
    elif not isinstance(system, Scene):
        missing = [n for n in ("nq", "nv", "qdot", "acceleration") if not hasattr(system, n)]
        if missing:
            raise TypeError(
                f"simulate needs a jaxbody.Scene, a jaxbody.Model or a system with nq, nv, qdot and acceleration "
                f"(see jaxbody.simulation.DynamicalSystem); {type(system).__name__} lacks {', '.join(missing)}"
            )
        from .scene import _own_constraints

        system = Scene(system=system, effects=(), constraints=_own_constraints(system), path="system")
    if tau is None:
        return system
    if not callable(tau):
        t_arr = jnp.asarray(tau, jnp.result_type(float))
        if t_arr.shape != (system.nv,):
            raise ValueError(f"tau must have shape ({system.nv},) or be callable, got {t_arr.shape}")
        tau = _Constant(t_arr)
    act = Actuation(tau)
    act.check(system)
    return Scene(
        system=system.system,
        effects=system.effects + (act,),
        constraints=system.constraints,
        planar=system.planar,
        plane=system.plane,
        axis_sign=system.axis_sign,
        path=system.path,
    )


# ----------------------------------------------------------------------------- vector field
def _vector_field(t, y, args, slots=None):
    """``(q̇, v̇, ẇ)``: ``ẇ`` holds the power of the scene's non-conservative effects, placed in
    the slots ``slots`` of the work vector (a phased run carries one work vector, the union of
    every phase's effects, across its switches; an effect absent from a phase adds nothing)."""
    scene, valid = args
    q, v = y[0], y[1]
    a, powers, _ = scene.evaluate(t, q, v)
    out = (scene.qdot(q, v), a)
    if len(y) == 3:
        if slots:
            wdot = jnp.zeros_like(y[2]).at[np.asarray(slots, dtype=np.int32)].set(jnp.stack(powers).astype(v.dtype))
        else:
            wdot = jnp.zeros_like(y[2])
        out = out + (wdot,)
    if valid is not None:
        # an input that failed the boundary check integrates a frozen state (no NaN reaches
        # the step-size controller of the other members of a batch)
        out = jax.tree.map(lambda x: jnp.where(valid, x, 0.0), out)
    return out


def _make_event(event, dtype):
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


def _solver(solver, scene, dtype, rtol, atol, dt0, controller):
    if isinstance(solver, str):
        try:
            factory, adaptive = SOLVERS[solver]
        except KeyError:
            raise ValueError(f"unknown solver {solver!r}; choose from {sorted(SOLVERS)}") from None
        solver_obj = RK4Stages() if solver == "rk4" and _runs_unrolled_kernel(scene) else factory()
    elif isinstance(solver, diffrax.AbstractSolver):
        solver_obj = solver
        adaptive = isinstance(solver, diffrax.AbstractAdaptiveSolver) and controller is None and dt0 is None
        if isinstance(solver, diffrax.AbstractAdaptiveSolver) and controller is None:
            adaptive = True
    else:
        raise ValueError(f"simulate: solver must be a preset name or a diffrax solver, got {type(solver).__name__}")
    if controller is None:
        if adaptive:
            controller = diffrax.PIDController(rtol=jnp.asarray(rtol, dtype), atol=jnp.asarray(atol, dtype))
        else:
            if dt0 is None:
                raise ValueError(f"fixed-step solver {solver!r} needs dt0")
            controller = diffrax.ConstantStepSize()
    project = _UnitQuaternions(scene.system) if scene.has_quaternions else None
    return _Guarded(solver_obj, project), controller


# ----------------------------------------------------------------------------- simulate
def simulate(
    system,
    q0: Float[ArrayLike, " nq"],
    v0: Float[ArrayLike, " nv"],
    t1: ArrayLike,
    *,
    t0: ArrayLike = 0.0,
    tau: ArrayLike | Callable | None = None,
    solver: str | diffrax.AbstractSolver = "tsit5",
    rtol: ArrayLike = 1e-8,
    atol: ArrayLike = 1e-8,
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
            switches, reactions and switch reports; see "Phases" in the module docstring) or
            any :class:`DynamicalSystem`.
        q0: initial coordinates ``(nq,)``; v0: initial velocities ``(nv,)``.
        t1: final time (after ``t0``).
        t0: initial time.
        tau: extra generalized forces, added as an actuation effect: a constant ``(nv,)`` array
            or a callable ``tau(t, q, v) -> (nv,)``.
        solver: a preset — fixed step: ``"euler"``, ``"semi_implicit_euler"``, ``"heun"``,
            ``"rk4"`` (need ``dt0``); adaptive (PID control with ``rtol``/``atol``): ``"tsit5"``,
            ``"dopri5"``, ``"dopri8"``, ``"kvaerno5"`` (implicit, for stiff springs and dampers) —
            or any diffrax solver object.
        rtol, atol: tolerances of adaptive solvers.
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
        throw: raise on failure (see the module docstring) or return result codes.
        progress: show diffrax's ``TqdmProgressMeter`` (text meter without tqdm).
        track_work: integrate the work of the non-conservative effects (energy balance).
        project_initial: when the scene has Maggi constraints (``jb.scene(..., constraints=)``
            or a :class:`jaxbody.maggi.ConstrainedSystem`) and ``v0`` violates them, project
            ``v0`` on the constraint manifold in the kinetic metric (the closest admissible
            rates in kinetic energy) instead of raising; the correction ``v0_projected − v0``
            is reported in ``Solution.stats["v0_correction"]``.

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
    if isinstance(system, Phases):
        extra = [name for name, given in (("tau", tau is not None), ("event", event is not None), ("dense", dense)) if given]
        if extra:
            raise ValueError(
                f"simulate: {', '.join(extra)} cannot be given with jaxbody.Phases (declare actuation in "
                "the phases' scenes; their events end the phases; phases save at times)"
            )
        return _simulate_phases(
            system, q0, v0, t1, t0=t0, solver=solver, rtol=rtol, atol=atol, dt0=dt0, controller=controller,
            saveat=saveat, n_save=n_save, max_steps=max_steps, adjoint=adjoint, throw=throw, progress=progress,
            track_work=track_work, project_initial=project_initial,
        )
    scene = _as_scene(system, tau)
    sol, _ = _simulate_scene(
        scene, q0, v0, t1, t0=t0, solver=solver, rtol=rtol, atol=atol, dt0=dt0, controller=controller,
        saveat=saveat, n_save=n_save, max_steps=max_steps, adjoint=adjoint, event=event, dense=dense,
        throw=throw, progress=progress, track_work=track_work, project_initial=project_initial,
    )
    return sol


def _simulate_scene(
    scene, q0, v0, t1, *, t0, solver, rtol, atol, dt0, controller, saveat, n_save, max_steps, adjoint, event,
    dense, throw, progress, track_work, project_initial, work_names=None, work0=None, check_constraints=True,
    phase_start=False,
):
    """:func:`simulate` of one scene. Returns ``(solution, work at the end)``.

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
        _positive(name, val)
    if max_steps is not None:
        _positive("max_steps", max_steps, integer=True)
    if not phase_start and _is_concrete(t0, t1) and not float(np.asarray(t1)) > float(np.asarray(t0)):
        raise ValueError(f"simulate: t1 ({float(np.asarray(t1))}) must be after t0 ({float(np.asarray(t0))})")
    if saveat is not None and n_save is not None:
        raise ValueError("give saveat or n_save, not both")
    if n_save is not None and n_save < 2:
        raise ValueError(f"n_save must be at least 2 (t0 and t1), got {n_save}")
    solver_obj, controller = _solver(solver, scene, q0.dtype, rtol, atol, dt0, controller)
    max_steps = _step_bound(controller, t0, t1, dt0, max_steps, q0.dtype)
    adjoint = _adjoint(adjoint, max_steps, q0.size + v0.size, q0.dtype.itemsize)
    if dt0 is not None:
        dt0 = jnp.asarray(dt0, q0.dtype)
    t0 = jnp.asarray(t0, q0.dtype)
    t1 = jnp.asarray(t1, q0.dtype)
    if saveat is None:
        saveat = diffrax.SaveAt(ts=jnp.linspace(t0, t1, 101 if n_save is None else n_save))
    elif not isinstance(saveat, diffrax.SaveAt):
        ts = jnp.asarray(saveat, dtype=q0.dtype)
        if ts.ndim != 1:
            raise ValueError(f"simulate: saveat must be 1-D times, got shape {ts.shape}")
        saveat = diffrax.SaveAt(ts=ts)
    if saveat.dense or saveat.subs is not None and not isinstance(saveat.subs, diffrax.SubSaveAt):
        raise ValueError("simulate: pass dense=True instead of SaveAt(dense=True); nested subs are not supported")
    adjoint = _adjoint(adjoint)
    if isinstance(controller, (diffrax.ConstantStepSize, diffrax.StepTo)) and not isinstance(
        adjoint, diffrax.BacksolveAdjoint
    ):
        # fixed steps: each trajectory's failure is recorded, not stopped on (one loop predicate
        # for a vmap batch); backsolve's adjoint solve keeps the stopping guard (no solver state)
        solver_obj = _Guarded(solver_obj.solver, solver_obj.project, record=True)
    solver_obj = for_adjoint(partition_solver(solver_obj, scene, adjoint), adjoint, max_steps)

    constrained = _scene_constraints(scene) if check_constraints else None
    if constrained is not None and constrained.n_constraint == 0:
        constrained = None
    correction = None
    if _is_concrete(scene, q0, v0, t0):
        _concrete_value_checks(scene, q0, v0)
        if constrained is not None:
            v0, correction = _concrete_constraint_check(constrained, t0, q0, v0, project_initial)
        valid = None
    else:
        checks = _value_checks(scene, q0, v0)
        if constrained is not None:
            bad, msg = _traced_constraint_check(constrained, t0, q0, v0)
            if project_initial:
                projected = jnp.where(bad, maggi.project_velocities(constrained, q0, v0, t0), v0)
                correction = projected - v0
                v0 = projected
            else:
                checks.append((bad, msg))
        if throw:
            for bad, msg in checks:
                q0 = eqx.error_if(q0, bad, msg)
            valid = None
        else:
            valid = ~jnp.any(jnp.stack([b for b, _ in checks]))
            # a member that failed the check integrates a safe state: frozen (see _vector_field)
            q0 = jnp.where(valid, q0, jnp.nan_to_num(q0, nan=0.0, posinf=0.0, neginf=0.0))
            v0 = jnp.where(valid, v0, jnp.nan_to_num(v0, nan=0.0, posinf=0.0, neginf=0.0))
    own = scene.work_names if (track_work and scene.has_energy) else ()
    if work_names is None:
        work_names = own
    missing = [n for n in own if n not in work_names]
    if missing:
        raise ValueError(f"simulate: internal: work slots {work_names} lack {missing}")
    slots = tuple(work_names.index(n) for n in own)
    if track_work and scene.has_energy and work_names:
        w0 = jnp.zeros((len(work_names),), q0.dtype) if work0 is None else jnp.asarray(work0, q0.dtype)
        y0 = (q0, v0, w0)
    else:
        y0 = (q0, v0)
    meter = _progress_meter(progress)
    sol, w_final = _solve(scene, y0, t0, t1, valid, solver_obj, controller, dt0, saveat, max_steps, adjoint, meter,
                          _make_event(event, q0.dtype), _layout(scene), dense, slots, tuple(work_names),
                          _native_solve_enabled())
    if correction is not None:
        sol = dataclasses.replace(sol, stats={**sol.stats, "v0_correction": correction})
    if valid is not None:
        sol = eqx.tree_at(lambda s: s.result, sol, RESULTS.where(valid, sol.result, RESULTS.invalid_input))
    if throw:
        sol = _raise_on_failure(sol)
    return sol, w_final


# ----------------------------------------------------------------------------- constraints at t0
def _scene_constraints(scene) -> "maggi.ConstrainedSystem | None":
    """The scene's Maggi constraints as a :class:`jaxbody.maggi.ConstrainedSystem` on the
    scene's own model (so its parameters, not the copy the constraints were built with, give
    the kinetic metric), or ``None`` (no constraints, or a constraint object of another kind:
    those are neither checked at ``t0`` nor projected at switches)."""
    from .model import Model

    cs = scene.constraints
    if not isinstance(cs, maggi.ConstrainedSystem):
        return None
    if isinstance(cs.base, maggi.ModelBase) and isinstance(scene.system, Model) and cs.base.model is not scene.system:
        cs = eqx.tree_at(lambda c: c.base.model, cs, scene.system)
    return cs


def _with_constraints(scene, cs):
    """``scene`` with its constraint system replaced by ``cs`` (e.g. re-partitioned)."""
    if scene.path == "system" and scene.system is scene.constraints:
        return dataclasses.replace(scene, system=cs, constraints=cs)
    return dataclasses.replace(scene, constraints=cs)


_V0_ATOL = 1e-9  # admissible residual of v0, scaled by max(1, max|v0|) (as jaxbody.maggi.initial_state)


def _concrete_constraint_check(cs, t0, q0, v0, project_initial):
    # the admissible case (the usual one) is decided by one compiled residual; otherwise
    # jaxbody.maggi.initial_state names the rows at fault or projects
    f = np.asarray(_residual(cs, t0, q0, v0))
    scale = max(1.0, float(np.max(np.abs(np.asarray(v0)))))
    if np.all(np.abs(f) <= _V0_ATOL * scale):
        return v0, (jnp.zeros_like(v0) if project_initial else None)
    try:
        _, v0p, correction = maggi.initial_state(cs, q0, v0, t0, project_initial=project_initial, atol=_V0_ATOL)
    except ValueError as err:
        raise ValueError(f"simulate: v0: {err}") from None
    return v0p.astype(v0.dtype), (correction.astype(v0.dtype) if project_initial else None)


@eqx.filter_jit
def _residual(cs, t, q, v):
    return cs.constraint_residual(t, q, v)


def _traced_constraint_check(cs, t0, q0, v0):
    """``(bad, message)``: the check of :func:`jaxbody.maggi.initial_state` on traced values."""
    f = cs.constraint_residual(t0, q0, v0)
    scale = jnp.maximum(1.0, jnp.max(jnp.abs(v0)))
    bad = jnp.any(jnp.abs(f) > _V0_ATOL * scale)
    msg = (
        f"simulate: v0: initial velocities violate the constraints {list(cs.constraint_names)} (a residual "
        f"exceeds {_V0_ATOL:g}·max(1, max|v0|)); give admissible rates or pass project_initial=True"
    )
    return bad, msg


def _step_bound(controller, t0, t1, dt0, max_steps, dtype):
    """The step budget of the solve: ``max_steps``, or for constant steps of a known length over
    a known span the steps the solve can take, if fewer (the steps ``|t1 − t0| / dt0``, plus
    the most that rounding the time in ``dtype`` can add, plus two). Nothing changes in the
    solution; the checkpointed adjoint then plans its checkpoints over the steps that are
    taken, not over the whole budget (for a 1000-step Panda gradient under the default budget of
    100,000 steps, half the time)."""
    if not isinstance(controller, diffrax.ConstantStepSize) or dt0 is None or not _is_concrete(t0, t1, dt0):
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
    1.1 for a 20-link chain: benchmarks/results/gradients_native*.md). Never fewer than
    ``ceil(log2(max_steps)) + 1`` (the O(n log n) recomputation bound of diffrax's default) and
    never more than ``max_steps`` (then no step is recomputed twice). Memory stays bounded
    whatever the horizon. (Counted as ``4 * n_state``, a 20-link chain got 819 checkpoints for
    1000 steps, and its gradient took twice as long as with one checkpoint per step.)
    """
    k = max(int(CHECKPOINT_BYTES // (3 * max(n_state, 1) * itemsize)), 2)
    if max_steps is None:
        return k
    return int(min(max_steps, max(k, math.ceil(math.log2(max(max_steps, 2))) + 1)))


def _adjoint(adjoint, max_steps=None, n_state=None, itemsize=8):
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


def _progress_meter(progress):
    if not progress:
        return diffrax.NoProgressMeter()
    try:
        import tqdm  # noqa: F401
    except ImportError:
        return diffrax.TextProgressMeter()
    return diffrax.TqdmProgressMeter()


# ----------------------------------------------------------------------------- failures
def _raise_on_failure(sol: Solution) -> Solution:
    """``throw=True``: a failed solve raises a :class:`SimulationError` naming the time reached,
    the reason and the state there. Eagerly it is raised here; under ``jit``/``vmap``/``grad``
    the check is a ``lax.cond`` on "any member failed" whose failing branch calls back to the
    host with ``(t_final, q_final, v_final)`` and raises there (JAX re-raises it as its runtime
    error with the same text). The callback sits in a custom JVP, so derivatives pass through."""
    failed = ~sol.success
    if _is_concrete(sol.result._value, sol.t_final, sol.q_final, sol.v_final):
        if bool(np.any(np.asarray(failed))):
            raise SimulationError(
                _failure_message(np.asarray(failed), np.asarray(sol.result._value), np.asarray(sol.t_final),
                                 np.asarray(sol.q_final), np.asarray(sol.v_final))
            )
        return sol
    dynamic, static = eqx.partition(sol, eqx.is_array)
    dynamic = _fail_with_state(dynamic, failed, sol.result._value, sol.t_final, sol.q_final, sol.v_final)
    return eqx.combine(dynamic, static)


@eqx.filter_custom_jvp
def _fail_with_state(dynamic, failed, code, t, q, v):
    leaves, treedef = jax.tree.flatten(dynamic)
    shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]

    def report(failed, code, t, q, v, *rest):
        raise SimulationError(_failure_message(failed, code, t, q, v))

    def fail():
        return jax.pure_callback(report, shapes, failed, code, t, q, v, *leaves, vmap_method="broadcast_all")

    # one predicate for a whole vmapped batch: the failing branch runs (and raises) only when
    # some member failed, and reports the first one that did
    out = lax.cond(eqx.internal.unvmap_any(failed), fail, lambda: leaves)
    return jax.tree.unflatten(treedef, out)


@_fail_with_state.def_jvp
def _fail_with_state_jvp(primals, tangents):
    return _fail_with_state(*primals), tangents[0]


def _failure_message(failed, code, t, q, v) -> str:
    failed = np.asarray(failed)
    batch = failed.shape
    flat = failed.reshape(-1)
    i = int(np.flatnonzero(flat)[0]) if flat.any() else 0
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
    if code == int(np.asarray(RESULTS.nonfinite._value)):
        return ("the state became NaN or inf (the motion blew up, e.g. a fixed step too large for stiff "
                "dynamics, or a force returned NaN); the state shown is the first non-finite one, the "
                "trajectory saved before it is finite")
    if code == int(np.asarray(RESULTS.successful._value)):
        return "the step-size controller or the solver's root finder failed"
    return RESULTS._index_to_message[code]


def _integrate(scene, y0, t0, t1, valid, solver, controller, dt0, saveat, max_steps, adjoint, meter, event, dense, slots):
    """The step-by-step solve (diffrax): ``(ts, ys, tf, yf, stats, result)`` (saved times and
    states, the final time and state as arrays of one entry, the step counts and the result,
    each trajectory's failure applied) and diffrax's solution."""
    main = saveat.subs if saveat.subs is not None else diffrax.SubSaveAt(ts=saveat.ts, t0=saveat.t0, t1=saveat.t1, steps=saveat.steps)
    # the end state is saved separately, except with backsolve (which takes no SaveAt(subs=...))
    # and when the saved times include t1 (diffrax saves the state the solve ended in there, at
    # t1 or where it stopped): there the last saved point stands for it (one save state less
    # carried through the loop and its checkpoints)
    single = isinstance(adjoint, diffrax.BacksolveAdjoint) or (main.t1 and not isinstance(solver, PartitionSolver))
    depth = _recording_depth(solver)
    state = isinstance(solver, PartitionSolver) or depth is not None
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(functools.partial(_vector_field, slots=slots)),
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
    result = RESULTS.promote(sol.result)
    failure = None if depth is None else _failure_record(sol.solver_state, depth)
    if failure is not None:
        # a trajectory that failed has no derivative to give: no cotangent enters the loop's state
        failure = jax.lax.stop_gradient(failure)
        ts, ys, tf, stats, result = _apply_failure(failure, ts, ys, tf, stats, result, single and main.t1)
        if single:
            yf = ys
    return (ts, ys, tf, yf, stats, result), sol


#: ``$JAXBODY_NATIVE_SOLVE=0`` turns the one-call solve (:func:`_native_solve`) off: every
#: ``simulate`` then steps through diffrax's loop (read when a solve is traced).
def _native_solve_enabled() -> bool:
    return os.environ.get("JAXBODY_NATIVE_SOLVE", "1") != "0"


def _native_solve_applies(scene, y0, solver, controller, saveat, adjoint, meter, event, dense, slots) -> bool:
    """Whether a solve can run as one native call (:func:`jaxbody.native.rk4_rollout`): RK4 at
    constant steps on a scene whose field the native programs compute (:func:`_native_field`),
    saving the end state alone, without an event, dense output or progress meter, under an
    adjoint that differentiates in reverse mode."""
    if type(solver) is not _Guarded or not solver.record or type(solver.solver) is not RK4Stages:
        return False
    if type(controller) is not diffrax.ConstantStepSize or event is not None or dense:
        return False
    if not isinstance(meter, diffrax.NoProgressMeter) or isinstance(adjoint, diffrax.ForwardMode):
        return False
    main = saveat.subs if saveat.subs is not None else diffrax.SubSaveAt(ts=saveat.ts, t0=saveat.t0, t1=saveat.t1, steps=saveat.steps)
    if not isinstance(main, diffrax.SubSaveAt) or not main.t1 or main.t0 or main.ts is not None or main.steps:
        return False
    return main.fn is diffrax._saveat.save_y and _native_field(scene, y0, slots) is not None


def _native_arguments(scene, y0, valid, slots) -> tuple:
    """``(model, keyword arguments)`` of :func:`jaxbody.native.rk4_rollout` for a solve of ``scene``
    from ``y0`` (:func:`_native_field`)."""
    model, gravity, passive = _native_field(scene, y0, slots)
    kwargs = dict(gravity=gravity, frozen=False if valid is None else ~valid, **passive)
    return model, kwargs


def _forward_in_time(t0, t1, dt0):
    """``t1``, checked to be no earlier than ``t0`` (the native solve steps forward only; diffrax
    raises on the same times)."""
    return eqx.error_if(t1, (t1 - t0) * dt0 < 0, "simulate: t1 must not be before t0 (a fixed-step solve runs forward)")


def _native_outputs(y0, t1, slots, q, v, w, t, steps, failed) -> tuple:
    """:func:`_integrate`'s outputs for a solve that saves the end state alone, from the native
    solve's results."""
    dtype = y0[0].dtype
    ys = (q[None], v[None]) + ((y0[2].at[slots[0]].set(w.astype(dtype))[None],) if len(y0) == 3 else ())
    ts = t.astype(dtype)[None]
    stats = {"num_steps": steps, "num_accepted_steps": steps, "num_rejected_steps": jnp.asarray(0)}  # as diffrax gives it
    result = RESULTS.where(t < t1, RESULTS.max_steps_reached, RESULTS.successful)
    result = RESULTS.where(failed, RESULTS.nonfinite, result)
    return ts, ys, ts, ys, stats, result


def _native_solve(scene, y0, t0, t1, dt0, valid, max_steps, slots):
    """The solve of :func:`_integrate` as one native call per batch (:func:`jaxbody.native.rk4_rollout`)."""
    from .backends.native import rk4_rollout

    model, kwargs = _native_arguments(scene, y0, valid, slots)
    w0 = y0[2][slots[0]] if len(y0) == 3 else 0.0
    t1 = _forward_in_time(t0, t1, dt0)
    out = rk4_rollout(model, y0[0], y0[1], t0, t1, dt0, max_steps, work0=w0, **kwargs)
    return _native_outputs(y0, t1, slots, *out)


def _instantiate(cotangent):
    """A cotangent given as ``SymbolicZero`` as an array of zeros."""
    if isinstance(cotangent, SymbolicZero):
        return jnp.zeros(cotangent.aval.shape, cotangent.aval.dtype)
    return cotangent


def _native_or_stepped(rest, y0, native, stepped, reverse):
    """``native(rest, y0)``, differentiated in reverse mode by ``reverse`` where only ``y0``
    carries a derivative and ``reverse`` is given, else as ``stepped(rest, y0)`` (the same
    values, computed step by step through diffrax: its adjoint, its checkpoints).

    ``reverse``: ``(forward, backward)``: ``forward(rest, y0) -> (outputs, residuals)`` and
    ``backward(residuals, cotangents) -> cotangent of y0``."""
    dynamic, static = eqx.partition(rest, eqx.is_array)

    @jax.custom_vjp
    def run(dynamic, y0):
        return native(eqx.combine(dynamic, static), y0)

    def forward(dynamic, y0):
        values = jax.tree.map(lambda p: p.value, dynamic)
        y0_values = jax.tree.map(lambda p: p.value, y0)
        if reverse is not None and not any(p.perturbed for p in jax.tree.leaves(dynamic)):
            out, residuals = reverse[0](eqx.combine(values, static), y0_values)
            return out, (None, residuals)
        out, pullback = jax.vjp(lambda d, y: stepped(eqx.combine(d, static), y), values, y0_values)
        return out, (pullback, None)

    def backward(residuals, cotangents):
        pullback, native_residuals = residuals
        if pullback is None:
            return None, reverse[1](native_residuals, cotangents)
        return pullback(jax.tree.map(_instantiate, cotangents, is_leaf=lambda c: isinstance(c, SymbolicZero)))

    run.defvjp(forward, backward, symbolic_zeros=True)
    return run(dynamic, y0)


def _native_reverse(adjoint, max_steps, slots, y0):
    """``(forward, backward)`` of :func:`_native_or_stepped` by the native reverse sweep
    (:func:`jaxbody.native.rk4_rollout_vjp`): the solve keeps as many checkpoints as the
    checkpointed ``adjoint`` would (default: :func:`default_checkpoints`, within its memory
    budget); ``None`` without a bounded step budget."""
    from .backends.native import rk4_rollout_checkpointed, rk4_rollout_vjp

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
        *out, saved = rk4_rollout_checkpointed(model, y0[0], y0[1], t0, t1, dt0, max_steps, checkpoints, work0=w0,
                                               **kwargs)
        return _native_outputs(y0, t1, slots, *out), (rest, y0, saved, out[4])

    def backward(residuals, cotangents):
        (scene, t0, t1, dt0, valid, *_), y0, saved, steps = residuals
        _, ys, _, yf, _, _ = cotangents
        # the end state is both the saved point and the final state
        ct = [_instantiate(a)[0] + _instantiate(b)[0] for a, b in zip(ys, yf)]
        model, kwargs = _native_arguments(scene, y0, valid, slots)
        work = ct[2][slots[0]] if len(y0) == 3 else 0.0
        ct_q, ct_v = rk4_rollout_vjp(model, y0[0], y0[1], t0, t1, dt0, max_steps, checkpoints, saved, steps, ct[0],
                                     ct[1], work, **kwargs)
        return (ct_q, ct_v) + ((ct[2],) if len(y0) == 3 else ())

    return forward, backward


@eqx.filter_jit
def _solve(scene, y0, t0, t1, valid, solver, controller, dt0, saveat, max_steps, adjoint, meter, event, layout, dense,
           slots, work_names, native_solve):
    """The solve and the solution's fields. ``native_solve``: whether a solve may run as one
    native call (:func:`_native_solve_enabled`, read by the caller so that it keys the compiled
    program)."""
    native_solve = native_solve and _native_solve_applies(scene, y0, solver, controller, saveat, adjoint, meter, event,
                                                          dense, slots)
    sol = None
    if not native_solve:
        (ts, ys, tf, yf, stats, result), sol = _integrate(scene, y0, t0, t1, valid, solver, controller, dt0, saveat,
                                                          max_steps, adjoint, meter, event, dense, slots)
    else:
        # one native call; derivatives by the native reverse sweep (initial state alone) or
        # through the step-by-step solve
        def stepped(rest, y0):
            scene, t0, t1, dt0, valid, solver, controller, adjoint = rest
            return _integrate(scene, y0, t0, t1, valid, solver, controller, dt0, saveat, max_steps, adjoint, meter,
                              event, dense, slots)[0]

        def native(rest, y0):
            scene, t0, t1, dt0, valid = rest[:5]
            return _native_solve(scene, y0, t0, t1, dt0, valid, max_steps, slots)

        rest = (scene, t0, t1, dt0, valid, solver, controller, adjoint)
        reverse = _native_reverse(adjoint, max_steps, slots, y0) if isinstance(adjoint, diffrax.RecursiveCheckpointAdjoint) else None
        ts, ys, tf, yf, stats, result = _native_or_stepped(rest, y0, native, stepped, reverse)
    q, v = ys[0], ys[1]
    finite = jnp.all(jnp.isfinite(q), axis=-1) & jnp.all(jnp.isfinite(v), axis=-1)
    work = {}
    if scene.has_energy:
        # diffrax pads unsaved entries with inf: evaluate energies on a safe state there
        qs = jnp.where(finite[:, None], q, y0[0])
        vs = jnp.where(finite[:, None], v, 0.0)
        energy = jnp.where(finite, jax.vmap(scene.total_energy)(qs, vs), jnp.nan)
        if len(ys) == 3:
            work = {name: ys[2][:, i] for i, name in enumerate(work_names)}
        # the balance from the initial state, not from the first saved time (which may be later)
        energy0 = scene.total_energy(y0[0], y0[1])
        bal = _balance(energy, work, energy0, y0[2] if len(y0) == 3 else None) / _scale(energy, energy0)
        drift = jnp.max(jnp.where(finite, jnp.abs(bal), 0.0))
    else:
        energy = drift = energy0 = None
        qs, vs = q, v
    cdrift = reactions = None
    if scene.constraints is not None:
        # constraint residuals and reactions at the saved states (padding entries: NaN)
        if not scene.has_energy:
            qs = jnp.where(finite[:, None], q, y0[0])
            vs = jnp.where(finite[:, None], v, y0[1])
        t_safe = jnp.where(finite, ts, t0)
        pos, vel = jax.vmap(scene.constraint_drift)(t_safe, qs, vs)
        cdrift = {
            "position": jnp.where(finite[:, None], pos, jnp.nan),
            "velocity": jnp.where(finite[:, None], vel, jnp.nan),
        }
        # Λ does not depend on the coordinate partition: each state with its best-conditioned one
        lam = jax.vmap(lambda tt, a, b: with_best_partition(scene, tt, a, b).evaluate(tt, a, b)[2])(t_safe, qs, vs)
        reactions = jnp.where(finite[:, None], lam, jnp.nan)
    if sol is None:
        stats["num_repartitions"], repartition_times = jnp.zeros((), jnp.int32), None
    else:
        stats["num_repartitions"], repartition_times, result = _partition_outcome(solver, sol, result)
    out = Solution(
        t=ts, q=q, v=v, energy=energy, work=work, energy_drift=drift, constraint_drift=cdrift,
        reactions=reactions, stats=stats, result=result, t_final=tf[-1], q_final=yf[0][-1], v_final=yf[1][-1], layout=layout,
        interpolation=sol.interpolation if dense and sol is not None else None, repartition_times=repartition_times, energy0=energy0,
    )
    return out, (yf[2][-1] if len(yf) == 3 else None)


def _partition_outcome(solver, sol, result):
    """``(num_repartitions, repartition_times, result)`` of a solve: what the
    :class:`jaxbody.maggi.PartitionSolver` did (zero and ``None`` for other solvers); a solve
    it stopped on a degraded partition gets ``RESULTS.partition_degraded``, one stopped on a
    singular parametrisation ``RESULTS.singular_parametrisation``."""
    report = partition_report(solver, sol.solver_state)
    if report is None:
        return jnp.zeros((), jnp.int32), None, result
    result = RESULTS.where(report["degraded"], RESULTS.partition_degraded, result)
    result = RESULTS.where(report["singular"], RESULTS.singular_parametrisation, result)
    return report["num_repartitions"], report["repartition_times"], result


# ----------------------------------------------------------------------------- phases
def _simulate_phases(phases: Phases, q0, v0, t1, *, t0, saveat, n_save, track_work, project_initial, throw, **kw):
    """Run phase after phase and join them into one :class:`Solution`.

    Phase ``i`` runs from the end of phase ``i − 1`` until the first root of ``events[i]``
    (the last one to ``t1``). At a switch, ``transitions[i]`` maps the state when given; then,
    when the next scene has Maggi constraints, its velocities are projected onto them as an
    impulsive constraint (:func:`jaxbody.maggi.switch_constraints`: ``x⁺ = A(AᵀDA)⁻¹AᵀD·x⁻``,
    a looser set keeps the velocity). The joined solution carries:

    * ``q``, ``v``, ``energy`` (each saved time from its own phase's scene; the saved time at a
      switch belongs to the phase that ends there);
    * ``work``: the work of every non-conservative effect of any phase, integrated as one state
      vector carried across the switches (an effect absent from a phase adds nothing there),
      plus ``work["switches"]``: the energy change at the switches up to each time, so that
      ``energy_balance = E(t) − E(t0) − Σ work(t)`` closes across the whole run and
      ``energy_drift`` measures only integration error;
    * ``stats``: step counts summed over phases, ``"phase"`` (the phase index of each saved
      time) and per switch ``"switch_time"`` (NaN when its event never triggered),
      ``"switch_occurred"``, ``"switch_energy_jump"`` ``E⁺ − E⁻`` (an impulsive constraint
      loses energy; a phase with other conservative effects measures energy differently) and
      ``"switch_energy_lost"`` ``½(x⁻ − x⁺)ᵀD(x⁻ − x⁺) ≥ 0`` of the velocity projection (zero
      when there is none);
    * ``reactions`` and ``constraint_drift`` of every phase with constraints, padded with NaN
      to the largest row count over the phases (``(n_save, s_max)``; a phase with ``s`` rows
      fills columns ``0..s − 1``); ``dict(layout)["phase_constraint_names"]`` names each
      phase's rows, and ``"constraint_names"`` is kept when every phase has the same rows.
    """
    dtype = jnp.result_type(float)
    t0 = jnp.asarray(t0, dtype)
    t1 = jnp.asarray(t1, dtype)
    if saveat is None:
        ts = jnp.linspace(t0, t1, 101 if n_save is None else n_save)
    elif isinstance(saveat, diffrax.SaveAt):
        raise ValueError("simulate: phases save at times; pass saveat as an array or n_save")
    else:
        ts = jnp.asarray(saveat, dtype)
    scenes = list(phases.scenes)
    energetic = track_work and all(sc.has_energy for sc in scenes)
    work_names: tuple[str, ...] = ()
    if energetic:
        for sc in scenes:
            work_names += tuple(n for n in sc.work_names if n not in work_names)
    q, v, start = jnp.asarray(q0, dtype), jnp.asarray(v0, dtype), t0
    w = jnp.zeros((len(work_names),), dtype) if work_names else None
    parts, ends, switches = [], [], []
    for i, sc in enumerate(scenes):
        last = i == len(scenes) - 1
        sol, w = _simulate_scene(
            sc, q, v, t1, t0=start, saveat=jnp.clip(ts, start, t1), n_save=None,
            event=None if last else phases.events[i], dense=False, throw=throw, track_work=energetic,
            project_initial=project_initial, work_names=work_names, work0=w, check_constraints=i == 0,
            phase_start=i > 0, **kw,
        )
        parts.append(sol)
        if last:
            ends.append(t1)
            break
        hit = sol.event_occurred
        ends.append(jnp.where(hit, sol.t_final, t1))
        t_sw, q_minus, v_minus = sol.t_final, sol.q_final, sol.v_final
        q, v = q_minus, v_minus
        if phases.transitions:
            q, v = phases.transitions[i](t_sw, q, v)
        scenes[i + 1], v, lost = _switch_into(scenes[i + 1], t_sw, q, v)
        jump = _energy_jump(sc, scenes[i + 1], hit, q_minus, v_minus, q, v) if energetic else None
        switches.append((hit, jnp.where(hit, t_sw, jnp.nan), jump, jnp.where(hit, lost, 0.0)))
        start = t_sw
    return _join_phases(ts, parts, ends, switches, work_names, energetic)


@eqx.filter_jit
def _energy_jump(before, after, hit, q_minus, v_minus, q_plus, v_plus):
    """``E⁺ − E⁻`` at a switch (zero when its event did not trigger)."""
    return jnp.where(hit, after.total_energy(q_plus, v_plus) - before.total_energy(q_minus, v_minus), 0.0)


@eqx.filter_jit
def _join_phases(ts, parts, ends, switches, work_names, energetic):
    """One :class:`Solution` from the phases' solutions (see :func:`_simulate_phases`)."""
    dtype = ts.dtype
    # the saved time t belongs to the first phase whose end is at or after t
    phase = sum(((ts > end).astype(jnp.int32) for end in ends[:-1]), jnp.zeros(ts.shape, jnp.int32))

    def join(arrays):
        out = arrays[-1]
        for k in range(len(arrays) - 2, -1, -1):
            mine = (phase == k).reshape(phase.shape + (1,) * (out.ndim - 1))
            out = jnp.where(mine, arrays[k], out)
        return out

    q_out = join([p.q for p in parts])
    v_out = join([p.v for p in parts])
    energy = work = drift = energy0 = None
    if energetic:
        energy = join([p.energy for p in parts])
        work = {name: join([p.work[name] for p in parts]) for name in work_names}
        if switches:
            work["switches"] = sum((jnp.where(ts > end, jump, 0.0) for end, (_, _, jump, _) in zip(ends, switches)),
                                   jnp.zeros(ts.shape, dtype))
        finite = jnp.isfinite(energy)
        energy0 = parts[0].energy0
        drift = jnp.max(jnp.where(finite, jnp.abs(_balance(energy, work, energy0) / _scale(energy, energy0)), 0.0))
    reactions = cdrift = None
    rows = [None if p.reactions is None else p.reactions.shape[-1] for p in parts]
    if any(r is not None for r in rows):
        s_max = max(r for r in rows if r is not None)

        def padded(x):
            if x is None:
                return jnp.full(ts.shape + (s_max,), jnp.nan, dtype)
            return jnp.concatenate([x, jnp.full(x.shape[:-1] + (s_max - x.shape[-1],), jnp.nan, x.dtype)], axis=-1)

        reactions = join([padded(p.reactions) for p in parts])
        cdrift = {
            key: join([padded(None if p.constraint_drift is None else p.constraint_drift[key]) for p in parts])
            for key in ("position", "velocity")
        }
    result = parts[0].result
    for p in parts[1:]:
        ok = (result == RESULTS.successful) | (result == RESULTS.event_occurred)
        result = RESULTS.where(ok, p.result, result)
    stats = {k: sum(p.stats[k] for p in parts) for k in ("num_steps", "num_accepted_steps", "num_rejected_steps")}
    stats["phase"] = phase
    if "v0_correction" in parts[0].stats:
        stats["v0_correction"] = parts[0].stats["v0_correction"]
    if switches:
        stats["switch_occurred"] = jnp.stack([s[0] for s in switches])
        stats["switch_time"] = jnp.stack([s[1] for s in switches])
        if energetic:
            stats["switch_energy_jump"] = jnp.stack([s[2] for s in switches])
        stats["switch_energy_lost"] = jnp.stack([s[3] for s in switches]).astype(dtype)
    final = parts[-1]
    return Solution(
        t=ts, q=q_out, v=v_out, energy=energy, work=work or {}, energy_drift=drift, constraint_drift=cdrift,
        reactions=reactions, stats=stats, result=result, t_final=final.t_final, q_final=final.q_final,
        v_final=final.v_final, layout=_phases_layout(parts), energy0=energy0,
    )


def _switch_into(scene, t, q, v):
    """Velocities entering ``scene`` at a switch: projected onto its Maggi constraints in the
    kinetic metric (impulsive constraint). Returns ``(scene, v⁺, energy lost)``; ``scene`` is
    re-partitioned at the switch state when it chooses its independent quasi-velocities
    automatically and the state is concrete (as :func:`jaxbody.maggi.simulate_phases`)."""
    cs = _scene_constraints(scene)
    if cs is None or cs.n_constraint == 0:
        return scene, v, jnp.zeros((), v.dtype)
    if cs.epsilon is None and _is_concrete(cs, t, q, v):
        cs = cs.repartition(q, v, t)
        scene = _with_constraints(scene, cs)
    report = maggi.switch_constraints(cs, t, q, v)
    return scene, report.x_after.astype(v.dtype), report.energy_lost


def _phases_layout(parts) -> tuple:
    lay = dict(parts[-1].layout)
    names = [dict(p.layout).get("constraint_names", ()) for p in parts]
    lay.pop("constraint_names", None)
    if any(names):
        lay["phase_constraint_names"] = tuple(tuple(n) for n in names)
        if all(n == names[0] for n in names):
            lay["constraint_names"] = tuple(names[0])
    return tuple(sorted(lay.items()))


# ----------------------------------------------------------------------------- batches
def simulate_batch(
    system,
    q0s: Float[ArrayLike, "batch nq"],
    v0s: Float[ArrayLike, "batch nv"],
    t1: ArrayLike,
    *,
    batched_system: bool = False,
    chunk_size: int | None = None,
    devices: Sequence[jax.Device] | None = None,
    **kwargs,
) -> Solution:
    """Simulate a batch of initial states (and systems) with one compilation, over all devices.

    The batch is split in chunks of at most ``chunk_size`` members per device (all of it when
    ``None``), padded to a multiple of the device count, and each chunk is laid out over a 1-D
    device mesh (``jax.sharding.Mesh`` + ``NamedSharding`` along the batch axis): the vmapped
    solve runs data-parallel, one compiled program for every chunk. ``throw=False`` is implied:
    a failed member keeps its result code and the others their trajectories. Results equal the
    unsharded ``jax.vmap`` of :func:`simulate`.

    Args:
        system: as in :func:`simulate`; with ``batched_system=True`` its array leaves carry a
            leading batch axis (one system per member, e.g. from ``eqx.filter_vmap`` of a builder).
        q0s, v0s: ``(batch, nq)``, ``(batch, nv)``.
        t1: final time (shared).
        chunk_size: members per device per chunk (bounds memory); ``None``: one chunk.
        devices: devices to use (default ``jax.devices()``).
        **kwargs: passed to :func:`simulate` (``throw`` is forced to ``False``).

    Returns:
        :class:`Solution` with a leading batch axis on every array.
    """
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    kwargs = dict(kwargs)
    kwargs["throw"] = False
    q0s = jnp.asarray(q0s)
    v0s = jnp.asarray(v0s)
    if q0s.ndim != 2 or v0s.ndim != 2 or q0s.shape[0] != v0s.shape[0]:
        raise ValueError(f"simulate_batch: q0s and v0s must be (batch, nq) and (batch, nv), got {q0s.shape} and {v0s.shape}")
    if chunk_size is not None and (int(chunk_size) != chunk_size or chunk_size < 1):
        raise ValueError(f"simulate_batch: chunk_size must be a positive integer, got {chunk_size!r}")
    n = q0s.shape[0]
    devices = list(jax.devices() if devices is None else devices)
    n_dev = len(devices)
    per_chunk = n_dev * (math.ceil(n / n_dev) if chunk_size is None else int(chunk_size))
    n_chunks = math.ceil(n / per_chunk)
    pad = n_chunks * per_chunk - n
    params, static = eqx.partition(system, eqx.is_array)

    def padded(x):
        return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x

    q0s, v0s = padded(q0s), padded(v0s)
    if batched_system:
        params = jax.tree.map(padded, params)
    mesh = Mesh(np.asarray(devices), ("batch",))
    shard = NamedSharding(mesh, PartitionSpec("batch"))
    replicated = NamedSharding(mesh, PartitionSpec())
    run = _batch_runner(static, batched_system, t1, tuple(sorted(kwargs.items(), key=lambda kv: kv[0])))
    outs = []
    for c in range(n_chunks):
        sl = slice(c * per_chunk, (c + 1) * per_chunk)
        p = jax.tree.map(lambda x: x[sl], params) if batched_system else params
        p = jax.device_put(p, shard if batched_system else replicated)
        outs.append(run(p, jax.device_put(q0s[sl], shard), jax.device_put(v0s[sl], shard)))
    out = outs[0] if len(outs) == 1 else jax.tree.map(lambda *xs: jnp.concatenate(xs), *outs)
    return jax.tree.map(lambda x: x[:n], out) if pad else out


class _Kw:
    """Hashable wrapper of keyword arguments (arrays compared by identity)."""

    def __init__(self, items):
        self.items = items

    def __hash__(self):
        return hash(tuple((k, id(v)) for k, v in self.items))

    def __eq__(self, other):
        return isinstance(other, _Kw) and [(k, id(v)) for k, v in self.items] == [(k, id(v)) for k, v in other.items]


_RUNNERS: dict = {}


def _batch_runner(static, batched_system, t1, kw_items):
    key = (static, batched_system, _Kw(kw_items))
    try:
        hit = _RUNNERS.get(key)
    except TypeError:  # unhashable static part: compile per call
        hit, key = None, None
    if hit is not None:
        return hit[0]
    kwargs = dict(kw_items)

    @eqx.filter_jit
    def run(params, q0s, v0s, t1):
        def one(p, q0, v0):
            return simulate(eqx.combine(p, static), q0, v0, t1, **kwargs)

        return jax.vmap(one, in_axes=(0 if batched_system else None, 0, 0))(params, q0s, v0s)

    def call(params, q0s, v0s):
        return run(params, q0s, v0s, jnp.asarray(t1, q0s.dtype))

    if key is not None:
        if len(_RUNNERS) > 32:
            _RUNNERS.clear()
        _RUNNERS[key] = (call, kw_items)  # keep the kwargs alive: their ids are the key
    return call
