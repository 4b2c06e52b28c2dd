"""Integrate scenes with diffrax: presets, events, phases, batches over devices, solutions on disk.

:func:`simulate` solves

    q̇ = qdot(q, v),     v̇ = a(t, q, v),     ẇ_e = f_e·v   (work of each non-conservative effect)

from ``(q0, v0)`` at ``t0`` to ``t1`` for a :class:`jaxbody.Scene` (a bare :class:`jaxbody.Model`
means ``jb.scene(model)``: the model's own gravity, springs and dampers; any other object with
the simulation protocol is wrapped as is). It returns a :class:`Solution` pytree. ``jit``,
``vmap`` and ``grad`` (through diffrax's adjoints) pass through.

A fixed-step ``"rk4"`` solve (or an adaptive Tsit5, Dopri5 or Dopri8 one) on the native kernel
that saves its end state and/or requested times (``saveat=ts``, ``n_save``, ``SaveAt(ts=...,
t1=...)``), of a scene of gravity, joint springs, joint dampers and a Fourier-series joint
torque, without an event, runs as one native call (:func:`jaxbody.backends.native.rk4_rollout`)
instead of diffrax's loop. Its solution is the one diffrax's loop gives (the same steps, saved
states from the same dense output, failures and result codes). Its gradient with respect to the
initial state is a native reverse sweep (:func:`jaxbody.backends.native.rk4_rollout_vjp`); other
derivatives go through diffrax's loop. ``$JAXBODY_NATIVE_SOLVE=0`` turns this off.

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

The package, one job per module: :mod:`~jaxbody.simulation.integrate` (the entry point),
:mod:`~jaxbody.simulation.solve` (one scene's solve), :mod:`~jaxbody.simulation.phases`,
:mod:`~jaxbody.simulation.batch`, :mod:`~jaxbody.simulation.solvers` (presets and the step
guard), :mod:`~jaxbody.simulation.field` (the vector field), :mod:`~jaxbody.simulation.native_solve`
(the one-call native solve), :mod:`~jaxbody.simulation.adjoint` (how a solve is differentiated),
:mod:`~jaxbody.simulation.checks` (boundary checks),
:mod:`~jaxbody.simulation.partitioning` (re-partitioning Maggi constraints during a solve),
:mod:`~jaxbody.simulation.delegating` (the base of the step wrappers), :mod:`~jaxbody.simulation.failures`
(failure reports) and :mod:`~jaxbody.simulation.solution` (what a solve returns).
"""

from .adjoint import CHECKPOINT_BYTES as CHECKPOINT_BYTES, default_checkpoints as default_checkpoints
from .batch import simulate_batch as simulate_batch
from .failures import explain_failure as explain_failure
from .integrate import DynamicalSystem as DynamicalSystem, simulate as simulate
from .partitioning import (
    PartitionSolver as PartitionSolver,
    partition_report as partition_report,
    partition_solver as partition_solver,
    with_best_partition as with_best_partition,
)
from .solution import (
    RESULTS as RESULTS,
    SimulationError as SimulationError,
    Solution as Solution,
    load_solution as load_solution,
)
from .solvers import (
    RK4 as RK4,
    RK4Stages as RK4Stages,
    SOLVERS as SOLVERS,
    SemiImplicitEuler as SemiImplicitEuler,
    choose_solver as choose_solver,
)

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
