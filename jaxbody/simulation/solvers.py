"""The solvers of :func:`jaxbody.simulate`: presets, the RK4 variants, and the wrapper that
guards every step.

Every solve runs its solver inside :class:`Guarded`, which keeps quaternions on the unit
sphere and turns a non-finite step into a result code; :func:`choose_solver` picks the
solver object and the step-size controller from the arguments of ``simulate``.
:class:`DelegatingSolver` and :func:`for_adjoint` live in :mod:`.delegating` (the
re-partitioning wrapper of :mod:`.partitioning` is one too) and are re-exported here.
"""

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax import lax

# the module, not its functions: read at call time, so a test can intercept the native calls
from ..backends import native
from .._types import Array
from ..kinematics import normalize_qpos
from ..scene import Scene
from ..backends.scalar import RK4_A, RK4_B, RK4_C
from ..effects import FourierTorque, JointDampers
from .delegating import DelegatingSolver, for_adjoint
from .field import VectorField, native_field
from .solution import RESULTS

__all__ = [
    "RK4",
    "RK4Stages",
    "SemiImplicitEuler",
    "SOLVERS",
    "DelegatingSolver",
    "for_adjoint",
    "Guarded",
    "Failure",
    "UnitQuaternions",
    "choose_solver",
    "recording_depth",
    "failure_record",
    "apply_failure",
    "chart_outcome",
]


# the one classical RK4 tableau of the package (also what the native generator emits); diffrax
# leaves out the first stage's zero row and node
_RK4_TABLEAU = diffrax.ButcherTableau(
    a_lower=tuple(np.array(row) for row in RK4_A[1:]),
    b_sol=np.array(RK4_B),
    b_error=np.zeros(len(RK4_B)),
    c=np.array(RK4_C[1:]),
)


class RK4(diffrax.AbstractERK):
    """Classical 4th-order Runge--Kutta method, for fixed steps (``dt0``) only.

    Dense output between steps is cubic Hermite with the first and last stage slopes.
    """

    tableau = _RK4_TABLEAU
    interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        del terms
        return 4


class RK4Stages(diffrax.AbstractSolver):
    """:class:`RK4` with its four stages written out one after another instead of looped over.

    Same method, same dense output; the stage loop of a tableau solver compiles the vector
    field once, this writes it four times. :func:`simulate` uses it for ``"rk4"`` when the
    scene's forward dynamics is the unrolled kernel: XLA then fuses each stage's outputs
    straight into the next stage's inputs, which makes a ``vmap`` batch faster than the stage
    loop at several times the compile time (the GPU rollouts of ``benchmarks/throughput.py``).
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

        # the tableau's nodes and rows (each stage reads only the one before it); the weights
        # RK4_B are applied as (1, 2, 2, 1) / 6, the rounding the native step uses too
        k1 = increment(t0, y0)
        k2 = increment(t0 + RK4_C[1] * h, ahead(k1, RK4_A[1][0]))
        k3 = increment(t0 + RK4_C[2] * h, ahead(k2, RK4_A[2][1]))
        k4 = increment(t1, ahead(k3, RK4_A[3][2]))
        y1 = jax.tree.map(lambda y, a, b, c, d: y + (a + 2 * b + 2 * c + d) / 6, y0, k1, k2, k3, k4)
        # diffrax's Hermite interpolation takes the end slopes as increments over the step
        k = jax.tree.map(lambda a, d: jnp.stack([a, d]), k1, k4)
        return y1, None, dict(y0=y0, y1=y1, k=k), None, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def _native_rk4_step(terms, args, y0):
    """The whole RK4 step as one native call (:func:`jaxbody.backends.native.rk4_step`), where it computes
    exactly what the four stages would: ``simulate``'s own vector field (not the augmented one of
    a backsolve adjoint) for a scene whose forward dynamics is the native kernel and whose
    effects are gravity, joint dampers and joint springs, and a Fourier-series joint torque (the
    one thing that depends on time, evaluated at the stages' times) where diffrax's term says
    which way time runs. Returns ``(t0, t1, y0) -> (y1, k)`` or ``None``."""
    # diffrax wraps the term (for the direction of time, and a backsolve adjoint wraps it again):
    # look for simulate's own field among the term's nodes; the augmented state of an adjoint
    # solve is then ruled out by its shape (native_field)
    odes = [x for x in jax.tree.leaves(terms, is_leaf=lambda x: isinstance(x, diffrax.ODETerm))
            if isinstance(x, diffrax.ODETerm)]
    if len(odes) != 1 or not isinstance(odes[0].vector_field, VectorField):
        return None
    slots = odes[0].vector_field.slots
    if not (isinstance(args, tuple) and len(args) == 2 and isinstance(args[0], Scene)):
        return None
    scene, valid = args
    # diffrax integrates in time times its direction (its wrapping term's): a torque needs the time
    wraps = [x for x in jax.tree.leaves(terms, is_leaf=lambda x: hasattr(x, "direction") and hasattr(x, "term"))
             if hasattr(x, "direction") and hasattr(x, "term")]
    plan = native_field(scene, y0, slots, timed=len(wraps) == 1)
    if plan is None:
        return None
    model, gravity, passive = plan
    if "torque" in passive:
        return _native_timed_step(terms, wraps[0].direction, scene, valid, y0, slots, plan)

    def fused(t0, t1, y0):
        # the field does not depend on time: the step is the term's control (t1 - t0, signed)
        q1, v1, k1q, k1v, k4q, k4v, work = native.rk4_step(model, y0[0], y0[1], terms.contr(t0, t1), gravity=gravity, **passive)
        y1, k = (q1, v1), (jnp.stack([k1q, k4q]), jnp.stack([k1v, k4v]))
        if len(y0) == 3:
            w0, slot = y0[2], slots[0]
            zeros = jnp.zeros_like(w0)
            y1 = y1 + (w0.at[slot].add(work[0].astype(w0.dtype)),)
            k = k + (jnp.stack([zeros.at[slot].set(work[1].astype(w0.dtype)), zeros.at[slot].set(work[2].astype(w0.dtype))]),)
        if valid is not None:
            # a member that failed the boundary check stays frozen, as under VectorField
            y1 = jax.tree.map(lambda a, b: jnp.where(valid, a, b), y1, y0)
            k = jax.tree.map(lambda a: jnp.where(valid, a, 0.0), k)
        return y1, k

    return fused


def _native_timed_step(terms, direction, scene, valid, y0, slots, plan):
    """:func:`_native_rk4_step` for a scene with a Fourier-series torque: the step's times in the
    scene's time (diffrax's times its direction), the torque's work and the dampers' each added
    to its own slot of the work vector."""
    model, gravity, passive = plan
    own = scene.work_names  # the scene's works in the order of slots
    names = (JointDampers.name, FourierTorque.name)  # the native step's works (jaxbody.backends.native.rk4_step)
    layout = [slots[own.index(n)] if len(y0) == 3 and n in own else None for n in names]

    def fused(t0, t1, y0):
        q1, v1, k1q, k1v, k4q, k4v, work = native.rk4_step(model, y0[0], y0[1], terms.contr(t0, t1), gravity=gravity,
                                                           t0=t0 * direction, t1=t1 * direction, **passive)
        y1, k = (q1, v1), (jnp.stack([k1q, k4q]), jnp.stack([k1v, k4v]))
        if len(y0) == 3:
            w0 = y0[2]
            w1, ka, kb = w0, jnp.zeros_like(w0), jnp.zeros_like(w0)
            for j, slot in enumerate(layout):
                if slot is not None:  # work = (Δw, k1w, k4w) of each work, work by work within each
                    w1 = w1.at[slot].add(work[j].astype(w0.dtype))
                    ka = ka.at[slot].set(work[2 + j].astype(w0.dtype))
                    kb = kb.at[slot].set(work[4 + j].astype(w0.dtype))
            y1, k = y1 + (w1,), k + (jnp.stack([ka, kb]),)
        if valid is not None:
            y1 = jax.tree.map(lambda a, b: jnp.where(valid, a, b), y1, y0)
            k = jax.tree.map(lambda a: jnp.where(valid, a, 0.0), k)
        return y1, k

    return fused


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


class Guarded(DelegatingSolver):
    """Wraps a solver: projects every step's end state (unit quaternions) and flags a
    non-finite one, or one outside the scene's coordinate chart.

    Projection after each step keeps ball/free quaternions on the unit sphere to rounding,
    while the error estimate (and so the step control) is the wrapped solver's. A step whose
    end state is NaN or inf returns diffrax's ``nonfinite`` code: an adaptive controller
    rejects that step anyway (its error estimate is not finite) and tries a smaller one, but a
    fixed step is accepted, so the solve stops there (``t_final``, ``q_final``, ``v_final`` show
    the first non-finite state) instead of carrying NaN to ``t1`` and calling that a success.
    A step that ends outside the coordinate chart the scene declares
    (:meth:`jaxbody.scene.Scene.coordinate_chart`, e.g. Euler angles near their singular set)
    returns ``singular``: finite, so the error estimate accepts it, but the coordinates no longer
    describe the motion. ``isinstance`` checks (adaptive, implicit) are forwarded to the wrapped
    solver by diffrax.

    ``record=True`` (fixed steps): the first non-finite step of each trajectory is recorded in
    the solver state (:class:`Failure`), the trajectory stays in the state that step ended in,
    and the loop stops only when every trajectory of a ``vmap`` batch has failed (alone, at
    once). The result code the loop sees is then the same for the whole batch, so diffrax's
    batched loop needs no per-trajectory predicate and does not select every carried array
    (saved trajectories included) on every step; the record itself is updated (a conditional
    on the batch) only once some trajectory is not finite. :func:`apply_failure` gives each
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
        failure = Failure(failed=jnp.asarray(False), t=jnp.full_like(t0, jnp.inf),
                           steps=jnp.zeros((), jnp.int32), count=jnp.zeros((), jnp.int32),
                           chart=jnp.asarray(False))
        return state, failure

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner_state, failure = solver_state if self.record else (solver_state, None)
        y1, err, dense, state, result = self.inner.step(terms, t0, t1, y0, args, inner_state, made_jump)
        if self.project is not None:
            y1 = self.project(y1)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(y1)]))
        inside = _inside_chart(args, y1)
        if not self.record:
            result = diffrax.RESULTS.where(finite, result, diffrax.RESULTS.nonfinite)
            # a step that ends outside the scene's coordinate chart is accepted by the error
            # estimate (it is finite) but its coordinates no longer describe the motion: diffrax's
            # ``singular`` code stops this trajectory alone (a batch's other members go on)
            result = diffrax.RESULTS.where(~finite | inside, result, diffrax.RESULTS.singular)
            return y1, err, dense, state, result
        count = failure.count + 1
        # a step outside the chart fails the trajectory as a non-finite one does
        chart_left = finite & ~inside
        finite = finite & inside
        # a trajectory that failed stays in its first non-finite state (its final state)
        y1 = jax.tree.map(lambda a, b: jnp.where(failure.failed, a, b), y0, y1)

        def record(failure, t1):
            first = ~finite & ~failure.failed
            return Failure(failed=failure.failed | first, t=jnp.where(first, t1, failure.t),
                            steps=jnp.where(first, count, failure.steps), count=count,
                            chart=failure.chart | (first & chart_left))

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


class Failure(eqx.Module):
    """The first failed step of a trajectory (:class:`Guarded` with ``record=True``): whether
    there was one, its end time, and how many steps it was; ``count``: the steps taken so far;
    ``chart``: the step ended outside the scene's coordinate chart (finite, but singular
    coordinates) rather than non-finite. (The state stays where that step ended.)"""

    failed: Array
    t: Array
    steps: Array
    count: Array
    chart: Array


def _inside_chart(args, y1):
    """Whether the step's end state lies inside the coordinate chart its scene declares
    (:meth:`jaxbody.scene.Scene.coordinate_chart`); true without a chart, and for solves whose
    arguments are not :func:`simulate`'s ``(scene, valid)`` (a backsolve adjoint's reverse solve)."""
    if not (isinstance(args, tuple) and len(args) == 2 and isinstance(args[0], Scene)):
        return jnp.asarray(True)
    chart = args[0].coordinate_chart()
    q = y1[0]
    if chart is None or not isinstance(q, jax.Array) or q.shape != (args[0].nq,):
        return jnp.asarray(True)
    # a member that failed the boundary check integrates a frozen placeholder state, whatever
    # chart it lies in: it is reported as invalid input, not as a chart it left
    valid = args[1]
    inside = chart.inside(lax.stop_gradient(q))
    return inside if valid is None else inside | ~valid


def chart_outcome(scene, valid, q_final, result):
    """``result`` with diffrax's ``singular`` made :attr:`RESULTS.singular_coordinates` where the
    solve stopped outside the scene's coordinate chart: the step guard's code (inside diffrax's
    loop only diffrax's own codes exist) told apart from a failed linear solve, which also gives
    ``singular``."""
    left = ~_inside_chart((scene, valid), (q_final,))
    return RESULTS.where((result == RESULTS.singular) & left, RESULTS.singular_coordinates, result)


def recording_depth(solver) -> int | None:
    """How many wrappers (a PartitionSolver) sit above a recording :class:`Guarded` in
    ``solver``; ``None`` when it has none."""
    depth = 0
    # type(), not isinstance: diffrax counts a wrapper as an instance of what it wraps
    while issubclass(type(solver), DelegatingSolver) and type(solver) is not Guarded:
        solver, depth = solver.solver, depth + 1
    return depth if type(solver) is Guarded and solver.record else None


def failure_record(solver_state, depth: int):
    """The :class:`Failure` in a solve's final solver state (a wrapper's state holds the
    wrapped solver's first)."""
    for _ in range(depth):
        solver_state = solver_state[0]
    return solver_state[1]


def apply_failure(failure, ts, ys, tf, stats, result, final_is_last):
    """Each trajectory's own outcome from the recorded first failure: the result ``nonfinite``
    (``singular_coordinates`` for a step that left the scene's coordinate chart),
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
    result = RESULTS.where(failed, RESULTS.where(failure.chart, RESULTS.singular_coordinates, RESULTS.nonfinite), result)
    return ts, ys, tf, stats, result


class UnitQuaternions(eqx.Module):
    """Renormalises the ball/free quaternions of ``y[0]`` (a module, so the model's arrays are
    traced and equal scenes share one compilation)."""

    model: Any

    def __call__(self, y):
        if isinstance(y[0], tuple):
            # diffrax's backsolve adjoint steps the augmented state (state, adjoints, ...) with
            # the same solver: renormalise the state it reconstructs in reverse time
            return (self(y[0]),) + tuple(y[1:])
        return (normalize_qpos(self.model, y[0]),) + tuple(y[1:])


def _kvaerno5() -> diffrax.Kvaerno5:
    """Kvaerno5 (an L-stable ESDIRK method) whose stage equations are solved by Newton's method
    (Jacobian re-evaluated at every iteration), at the tolerances of the step-size controller.

    diffrax's default root finder for it is the chord method: one Jacobian per step, reused by
    every stage and iteration. On a chain whose joint springs span 1 to 1e6 the fast modes move
    the state so much within a step that the frozen Jacobian no longer describes it (the
    Coriolis and spring terms change with the velocities and angles), the chord iteration stops
    converging, and each such step is rejected and retried five times shorter: more steps
    rejected than accepted, ten times the steps of Newton's method (docs/simulation.md, "Hard
    cases"). Newton costs a Jacobian per iteration (forward-mode derivatives of the vector
    field, one per state component); where the chord method converges it takes as many steps,
    each cheaper.
    """
    return diffrax.Kvaerno5(root_finder=diffrax.with_stepsize_controller_tols(optx.Newton)())


#: Solver presets: name -> (factory, adaptive).
SOLVERS: dict[str, tuple[Callable[[], diffrax.AbstractSolver], bool]] = {
    "euler": (diffrax.Euler, False),
    "semi_implicit_euler": (SemiImplicitEuler, False),
    "heun": (diffrax.Heun, False),
    "rk4": (RK4, False),
    "tsit5": (diffrax.Tsit5, True),
    "dopri5": (diffrax.Dopri5, True),
    "dopri8": (diffrax.Dopri8, True),
    "kvaerno5": (_kvaerno5, True),
}


def choose_solver(solver, scene, dtype, rtol, atol, dt0, controller):
    """``(Guarded solver, step-size controller)`` for ``simulate``'s ``solver``/``controller``
    arguments: a preset name or a diffrax solver; PID control with ``rtol``/``atol`` for an
    adaptive solver without a controller, constant steps of ``dt0`` for a fixed-step one."""
    if isinstance(solver, str):
        try:
            factory, adaptive = SOLVERS[solver]
        except KeyError:
            raise ValueError(f"unknown solver {solver!r}; choose from {sorted(SOLVERS)}") from None
        # straight-line kernels fuse across the written-out stages (RK4Stages' docstring)
        unrolled = scene.direct_kernel() in ("native", "unrolled")
        solver_obj = RK4Stages() if solver == "rk4" and unrolled else factory()
    elif isinstance(solver, diffrax.AbstractSolver):
        solver_obj = solver
        # a given controller decides the steps itself; otherwise an adaptive solver gets PID control
        adaptive = isinstance(solver, diffrax.AbstractAdaptiveSolver) and controller is None
    else:
        raise ValueError(f"simulate: solver must be a preset name or a diffrax solver, got {type(solver).__name__}")
    if controller is None:
        if adaptive:
            controller = diffrax.PIDController(rtol=jnp.asarray(rtol, dtype), atol=jnp.asarray(atol, dtype))
        else:
            if dt0 is None:
                raise ValueError(f"fixed-step solver {solver!r} needs dt0")
            controller = diffrax.ConstantStepSize()
    project = UnitQuaternions(scene.system) if scene.has_quaternions else None
    return Guarded(solver_obj, project), controller
