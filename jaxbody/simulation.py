"""Integrate scenes with diffrax: presets, events, phases, batches over devices, solutions on disk.

:func:`simulate` solves

    q̇ = qdot(q, v),     v̇ = a(t, q, v),     ẇ_e = f_e·v   (work of each non-conservative effect)

from ``(q0, v0)`` at ``t0`` to ``t1`` for a :class:`jaxbody.Scene` (a bare :class:`jaxbody.Model`
means ``jb.scene(model)``: the model's own gravity, springs and dampers; any other object with
the simulation protocol is wrapped as is). It returns a :class:`Solution` pytree. ``jit``,
``vmap`` and ``grad`` (through diffrax's adjoints) pass through.

Errors come in three layers. Shapes, unknown names and impossible options raise ``ValueError``
before anything is traced. Values (NaN or infinite initial states or parameters, negative
masses) are checked once at this boundary: with concrete inputs a ``ValueError`` names the
input at fault; under ``jit``/``vmap`` the check is an ``eqx.error_if`` (``throw=True``) or the
result code ``RESULTS.invalid_input`` (``throw=False``: that member integrates a frozen state and
the others are untouched). Inside the solver loop there are only result codes: a NaN trial stage
is a rejected step, and a failed solve either raises a :class:`SimulationError` saying when, in
which state and why (``throw=True``) or returns the trajectory up to the failure with its code.
"""

import json
import math
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._types import Array, ArrayLike, Float, Int, Scalar
from .scene import Event, Phases, Scene, scene as build_scene
from .effects import Actuation

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

    invalid_input = "The initial state or a parameter is NaN/inf or invalid (checked before the solve)."


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


class _Projected(diffrax.AbstractAdaptiveSolver, diffrax.AbstractWrappedSolver):
    """Wraps a solver and projects every step's end state (unit quaternions).

    Projection after each step keeps ball/free quaternions on the unit sphere to rounding,
    while the error estimate (and so the step control) is the wrapped solver's.
    """

    solver: diffrax.AbstractSolver
    project: Callable

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms) if hasattr(self.solver, "error_order") else self.order(terms)

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        y1, err, dense, state, result = self.solver.step(terms, t0, t1, y0, args, solver_state, made_jump)
        return self.project(y1), err, dense, state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


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
            ``"support"``); empty when there are none.
        energy_drift: ``max_t |E(t) − E(t0) − Σ work(t)| / max(|E(t0)|, tiny)``: how far the energy
            balance is from closing (a check of the integration, meaningful with damping and
            actuation too); ``None`` without energy.
        constraint_drift: constraint residuals at the saved times, ``{"position": (n_save, s),
            "velocity": (n_save, s)}`` (position residuals ``φ(t, q)`` of the holonomic rows, zero
            on non-holonomic rows; velocity residuals ``f*(t, q, v)`` of every row), or ``None``
            without constraints.
        reactions: constraint reactions ``Λ`` at the saved times ``(n_save, s)``, one column per
            constraint row (``layout`` lists their names under ``"constraint_names"``; forces in
            newtons for the point constraints of :mod:`jaxbody.constraints`), or ``None``.
        stats: ``num_steps``, ``num_accepted_steps``, ``num_rejected_steps``.
        result: a :class:`RESULTS` code (``successful``; ``event_occurred`` when an event ended
            the solve; a failure code otherwise).
        t_final, q_final, v_final: where the solve stopped (``t1``, the event time, or the
            last accepted step of a failed solve).
        layout: static description of ``q``/``v`` (names, joint kinds, addresses) for replay.
    """

    t: Float[Array, " n_save"]
    q: Float[Array, "n_save nq"]
    v: Float[Array, "n_save nv"]
    energy: Float[Array, " n_save"] | None
    work: dict
    energy_drift: Float[Array, ""] | None
    constraint_drift: Any
    reactions: Any
    stats: dict[str, Int[Array, ""]]
    result: RESULTS
    t_final: Float[Array, ""]
    q_final: Float[Array, " nq"]
    v_final: Float[Array, " nv"]
    layout: tuple = eqx.field(static=True, default=())
    interpolation: Any = None

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
        return _balance(self.energy, self.work)

    @property
    def energy_error(self) -> Float[Array, "*batch n_save"] | None:
        """Signed relative balance error ``(E − E0 − Σ work) / max(|E0|, tiny)`` per saved time."""
        if self.energy is None:
            return None
        return _balance(self.energy, self.work) / _scale(self.energy)

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
        for k, w in self.work.items():
            arrays[f"work/{k}"] = np.asarray(w)
        for k, s in self.stats.items():
            arrays[f"stats/{k}"] = np.asarray(s)
        if self.constraint_drift is not None:
            for k, r in self.constraint_drift.items():
                arrays[f"constraint_drift/{k}"] = np.asarray(r)
        if self.reactions is not None:
            arrays["reactions"] = np.asarray(self.reactions)
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)

    def to_csv(self, path) -> None:
        """Write ``t``, the coordinates, velocities, energy and work as CSV columns (one row per time)."""
        lay = self._layout_dict()
        qn = lay.get("q_names") or [f"q{i}" for i in range(self.q.shape[-1])]
        vn = lay.get("v_names") or [f"v{i}" for i in range(self.v.shape[-1])]
        cols = [np.asarray(self.t)[:, None], np.asarray(self.q), np.asarray(self.v)]
        names = ["t", *qn, *vn]
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
        constraint_drift={k[17:]: jnp.asarray(v) for k, v in d.items() if k.startswith("constraint_drift/")} or None,
        reactions=jnp.asarray(d["reactions"]) if "reactions" in d else None,
        stats=stats,
        result=result,
        t_final=jnp.asarray(d["t_final"]),
        q_final=jnp.asarray(d["q_final"]),
        v_final=jnp.asarray(d["v_final"]),
        layout=tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in layout.items())),
    )


def _scale(energy):
    e0 = energy[..., :1]
    return jnp.maximum(jnp.abs(e0), jnp.finfo(energy.dtype).tiny)


def _balance(energy, work):
    out = energy - energy[..., :1]
    for w in work.values():
        out = out - (w - w[..., :1])
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
def _vector_field(t, y, args):
    scene, valid = args
    q, v = y[0], y[1]
    a, powers, _ = scene.evaluate(t, q, v)
    out = (scene.qdot(q, v), a)
    if len(y) == 3:
        out = out + (jnp.stack(powers).astype(v.dtype),)
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

    def cond_fn(t, y, args, **kwargs):
        del args, kwargs
        return event(t, y[0], y[1])

    tol = 100 * float(jnp.finfo(dtype).eps)
    return diffrax.Event(cond_fn, root_finder=optx.Newton(rtol=tol, atol=tol), direction=event.direction)


def _solver(solver, scene, dtype, rtol, atol, dt0, controller):
    if isinstance(solver, str):
        try:
            factory, adaptive = SOLVERS[solver]
        except KeyError:
            raise ValueError(f"unknown solver {solver!r}; choose from {sorted(SOLVERS)}") from None
        solver_obj = factory()
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
    if scene.has_quaternions:
        from .kinematics import normalize_qpos

        model = scene.system
        solver_obj = _Projected(solver_obj, lambda y: (normalize_qpos(model, y[0]),) + tuple(y[1:]))
    return solver_obj, controller


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
) -> Solution:
    """Integrate a scene from ``(q0, v0)`` at ``t0`` to ``t1`` (or to a terminating event).

    Args:
        system: a :class:`jaxbody.Scene`, a :class:`jaxbody.Model` (= ``jb.scene(model)``), a
            :class:`jaxbody.Phases` or any :class:`DynamicalSystem`.
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

    Returns:
        :class:`Solution`.

    Raises:
        TypeError: ``system`` lacks the protocol's members.
        ValueError: unknown solver, missing ``dt0``, ``t1`` not after ``t0``, non-positive or
            non-finite ``rtol``/``atol``/``dt0``/``max_steps``, wrong shapes of ``q0``/``v0``/
            ``tau`` (naming the argument), and NaN/inf inputs or negative masses (concrete inputs).
        SimulationError: the solve failed and ``throw=True`` (concrete inputs).
    """
    if isinstance(system, Phases):
        return _simulate_phases(
            system, q0, v0, t1, t0=t0, solver=solver, rtol=rtol, atol=atol, dt0=dt0, controller=controller,
            saveat=saveat, n_save=n_save, max_steps=max_steps, adjoint=adjoint, throw=throw, progress=progress,
        )
    scene = _as_scene(system, tau)
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
    if _is_concrete(t0, t1) and not float(np.asarray(t1)) > float(np.asarray(t0)):
        raise ValueError(f"simulate: t1 ({float(np.asarray(t1))}) must be after t0 ({float(np.asarray(t0))})")
    if saveat is not None and n_save is not None:
        raise ValueError("give saveat or n_save, not both")
    if n_save is not None and n_save < 2:
        raise ValueError(f"n_save must be at least 2 (t0 and t1), got {n_save}")
    solver_obj, controller = _solver(solver, scene, q0.dtype, rtol, atol, dt0, controller)
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

    if _is_concrete(scene, q0, v0):
        _concrete_value_checks(scene, q0, v0)
        valid = None
    else:
        checks = _value_checks(scene, q0, v0)
        if throw:
            for bad, msg in checks:
                q0 = eqx.error_if(q0, bad, msg)
            valid = None
        else:
            valid = ~jnp.any(jnp.stack([b for b, _ in checks]))
            # a member that failed the check integrates a safe state: frozen (see _vector_field)
            q0 = jnp.where(valid, q0, jnp.nan_to_num(q0, nan=0.0, posinf=0.0, neginf=0.0))
            v0 = jnp.where(valid, v0, jnp.nan_to_num(v0, nan=0.0, posinf=0.0, neginf=0.0))
    n_work = len(scene.work_names) if (track_work and scene.has_energy) else 0
    y0 = (q0, v0) if n_work == 0 else (q0, v0, jnp.zeros((n_work,), q0.dtype))
    meter = _progress_meter(progress)
    sol = _solve(scene, y0, t0, t1, valid, solver_obj, controller, dt0, saveat, max_steps, adjoint, meter,
                 _make_event(event, q0.dtype), _layout(scene), dense)
    if valid is not None:
        sol = eqx.tree_at(lambda s: s.result, sol, RESULTS.where(valid, sol.result, RESULTS.invalid_input))
    if throw:
        sol = _raise_on_failure(sol)
    return sol


def _adjoint(adjoint):
    if adjoint is None or (isinstance(adjoint, str) and adjoint == "checkpoint"):
        return diffrax.RecursiveCheckpointAdjoint()
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


def _raise_on_failure(sol: Solution) -> Solution:
    if _is_concrete(sol.result._value, sol.t_final):
        if not bool(np.all(np.asarray(sol.success))):
            raise SimulationError(
                f"simulate: the solve failed at t = {float(np.asarray(sol.t_final).ravel()[0]):.6g}: {_reason(sol)}\n"
                f"  state at the failure: q = {np.asarray(sol.q_final).tolist()}, v = {np.asarray(sol.v_final).tolist()}\n"
                f"  pass throw=False to get the trajectory up to the failure and the result code"
            )
        return sol
    okay = sol.success
    return eqx.tree_at(lambda s: s.q, sol, sol.result.error_if(sol.q, ~okay))


def _reason(sol):
    for name in ("max_steps_reached", "dt_min_reached", "max_steps_rejected", "invalid_input", "internal_error"):
        member = getattr(RESULTS, name)
        if bool(np.all(np.asarray(sol.result == member))):
            return RESULTS[member]
    return "the step-size controller or the solver's root finder failed"


@eqx.filter_jit
def _solve(scene, y0, t0, t1, valid, solver, controller, dt0, saveat, max_steps, adjoint, meter, event, layout, dense):
    main = saveat.subs if saveat.subs is not None else diffrax.SubSaveAt(ts=saveat.ts, t0=saveat.t0, t1=saveat.t1, steps=saveat.steps)
    # the end state is saved separately, except with backsolve (which takes no SaveAt(subs=...)):
    # there the last saved point stands for it
    single = isinstance(adjoint, diffrax.BacksolveAdjoint)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field),
        solver,
        t0,
        t1,
        dt0,
        y0,
        args=(scene, valid),
        saveat=diffrax.SaveAt(subs=main, dense=dense) if single else diffrax.SaveAt(subs=[main, diffrax.SubSaveAt(t1=True)], dense=dense),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
        progress_meter=meter,
        event=event,
    )
    ys, yf = (sol.ys, sol.ys) if single else sol.ys
    ts, tf = (sol.ts, sol.ts) if single else sol.ts
    q, v = ys[0], ys[1]
    finite = jnp.all(jnp.isfinite(q), axis=-1) & jnp.all(jnp.isfinite(v), axis=-1)
    work = {}
    if scene.has_energy:
        # diffrax pads unsaved entries with inf: evaluate energies on a safe state there
        qs = jnp.where(finite[:, None], q, y0[0])
        vs = jnp.where(finite[:, None], v, 0.0)
        energy = jnp.where(finite, jax.vmap(scene.total_energy)(qs, vs), jnp.nan)
        if len(ys) == 3:
            work = {name: ys[2][:, i] for i, name in enumerate(scene.work_names)}
        bal = _balance(energy, work) / _scale(energy)
        drift = jnp.max(jnp.where(finite, jnp.abs(bal), 0.0))
    else:
        energy = drift = None
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
        reactions = jnp.where(finite[:, None], jax.vmap(lambda tt, a, b: scene.evaluate(tt, a, b)[2])(t_safe, qs, vs), jnp.nan)
    stats = {k: jnp.asarray(sol.stats[k]) for k in ("num_steps", "num_accepted_steps", "num_rejected_steps")}
    result = RESULTS.promote(sol.result)
    return Solution(
        t=ts, q=q, v=v, energy=energy, work=work, energy_drift=drift, constraint_drift=cdrift,
        reactions=reactions, stats=stats, result=result, t_final=tf[-1], q_final=yf[0][-1], v_final=yf[1][-1], layout=layout,
        interpolation=sol.interpolation if dense else None,
    )


# ----------------------------------------------------------------------------- phases
def _simulate_phases(phases: Phases, q0, v0, t1, *, t0, saveat, n_save, **kw):
    """Run phase after phase; phase ``i`` ends at the first root of ``events[i]``."""
    dtype = jnp.result_type(float)
    t0 = jnp.asarray(t0, dtype)
    t1 = jnp.asarray(t1, dtype)
    if saveat is None:
        ts = jnp.linspace(t0, t1, 101 if n_save is None else n_save)
    elif isinstance(saveat, diffrax.SaveAt):
        raise ValueError("simulate: phases save at times; pass saveat as an array or n_save")
    else:
        ts = jnp.asarray(saveat, dtype)
    q, v, start = jnp.asarray(q0, dtype), jnp.asarray(v0, dtype), t0
    parts, ends, results, steps = [], [], [], []
    for i, sc in enumerate(phases.scenes):
        last = i == len(phases.scenes) - 1
        ev = None if last else phases.events[i]
        sol = simulate(sc, q, v, t1, t0=start, saveat=jnp.clip(ts, start, t1), event=ev, track_work=False, **kw)
        parts.append(sol)
        end = t1 if last else jnp.where(sol.event_occurred, sol.t_final, t1)
        ends.append(end)
        results.append(sol.result)
        steps.append(sol.stats)
        q, v = sol.q_final, sol.v_final
        if not last and phases.transitions:
            q, v = phases.transitions[i](sol.t_final, q, v)
        start = sol.t_final
    # stitch: the saved time t belongs to the first phase whose end is after t
    out_q, out_v, out_e = parts[-1].q, parts[-1].v, parts[-1].energy
    for sol, end in zip(reversed(parts[:-1]), reversed(ends[:-1])):
        mine = ts <= end
        out_q = jnp.where(mine[:, None], sol.q, out_q)
        out_v = jnp.where(mine[:, None], sol.v, out_v)
        if out_e is not None and sol.energy is not None:
            out_e = jnp.where(mine, sol.energy, out_e)
        else:
            out_e = None
    result = results[0]
    for r in results[1:]:
        ok = (result == RESULTS.successful) | (result == RESULTS.event_occurred)
        result = RESULTS.where(ok, r, result)
    stats = {k: sum(s[k] for s in steps) for k in steps[0]}
    last = parts[-1]
    return Solution(
        t=ts, q=out_q, v=out_v, energy=out_e, work={}, energy_drift=None, constraint_drift=None, reactions=None,
        stats=stats, result=result, t_final=last.t_final, q_final=last.q_final, v_final=last.v_final,
        layout=last.layout,
    )


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
