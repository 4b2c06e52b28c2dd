"""Integrate the equations of motion of a system with diffrax.

:func:`simulate` solves the first-order system

    q̇ = qdot(q, v),        v̇ = acceleration(t, q, v, tau)

from ``(q0, v0)`` at ``t0`` to ``t1`` and returns a :class:`Solution` pytree: the saved
trajectory, the total energy along it and its relative drift, the solver's step counts and
its result code. It is a pure function of pytrees: ``jax.jit``, ``jax.vmap`` (over initial
states, parameters, ...) and ``jax.grad`` (through diffrax's adjoint) pass through.

Two kinds of system are accepted:

* anything implementing :class:`DynamicalSystem` (``nq``, ``nv``, ``qdot``,
  ``acceleration`` and optionally ``total_energy``): planar systems of ``jaxbody.examples``,
  scenes, or a model written in a test. Make it an ``equinox.Module`` whose physical
  parameters are array fields, so ``grad`` reaches them and ``jit`` does not bake them in;
* a :class:`jaxbody.Model` (spatial tree), through ``jaxbody.dynamics.forward_dynamics``
  (with the model's joint springs and dampers, ``passive_forces``, added to ``tau``) and
  ``jaxbody.kinematics.qpos_rate``; its energy is kinetic plus gravity and spring
  potential. Quaternions are integrated as q̇ = qpos_rate(q, v) without renormalisation;
  at the default tolerances their norm drifts negligibly.

Scenes, events and phases come later; this is the minimal wrapper they will build on.
"""

from collections.abc import Callable
from typing import Any, Protocol

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Float, Int, Scalar

__all__ = ["DynamicalSystem", "Solution", "simulate", "SOLVERS", "RK4"]


class DynamicalSystem(Protocol):
    """What :func:`simulate` needs from a system (structural: no base class required).

    Attributes:
        nq: number of generalized coordinates (Python int).
        nv: number of generalized velocities (Python int).
    """

    nq: int
    nv: int

    def qdot(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, " nq"]:
        """Coordinate rates from velocities: identity for planar systems, quaternion
        kinematics for ball and free joints."""
        ...

    def acceleration(
        self, t: Scalar, q: Float[Array, " nq"], v: Float[Array, " nv"], tau: Float[Array, " nv"] | None
    ) -> Float[Array, " nv"]:
        """Forward dynamics ``v̇``; ``tau`` (generalized forces) may be ``None``."""
        ...

    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Scalar:
        """Kinetic plus potential energy. Optional: without it the solution has no energy."""
        ...


class _ModelSystem(eqx.Module):
    """Adapter giving a :class:`jaxbody.Model` the :class:`DynamicalSystem` interface.

    The spatial engine is imported on first use so this module imports on its own.
    """

    model: Any

    @property
    def nq(self) -> int:
        return self.model.nq

    @property
    def nv(self) -> int:
        return self.model.nv

    def qdot(self, q, v):
        from .kinematics import qpos_rate

        return qpos_rate(self.model, q, v)

    def acceleration(self, t, q, v, tau):
        from .dynamics import forward_dynamics, passive_forces

        # The model's joint springs and dampers act as MuJoCo's passive forces do.
        force = passive_forces(self.model, q, v)
        if tau is not None:
            force = force + tau
        return forward_dynamics(self.model, q, v, force)

    def total_energy(self, q, v):
        from .dynamics import kinetic_energy, potential_energy

        return kinetic_energy(self.model, q, v) + potential_energy(self.model, q)


# Classical 4th-order Runge--Kutta (fixed step only: it has no error estimate).
_rk4_tableau = diffrax.ButcherTableau(
    a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.zeros(4),
    c=np.array([0.5, 0.5, 1.0]),
)


class RK4(diffrax.AbstractERK):
    """Classical 4th-order Runge--Kutta method, for fixed steps (``dt0``) only.

    Dense output between steps is cubic Hermite with the first and last stage slopes,
    as diffrax does for its other non-FSAL low-order methods.
    """

    tableau = _rk4_tableau
    interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        del terms
        return 4


#: Solver presets: name -> (solver class, adaptive).
SOLVERS: dict[str, tuple[type, bool]] = {
    "tsit5": (diffrax.Tsit5, True),
    "dopri5": (diffrax.Dopri5, True),
    "dopri8": (diffrax.Dopri8, True),
    "rk4": (RK4, False),
    "euler": (diffrax.Euler, False),
}


class Solution(eqx.Module):
    """Result of :func:`simulate` (a pytree: batches and gradients pass through).

    Attributes:
        t: saved times.
        q: coordinates at the saved times.
        v: velocities at the saved times.
        energy: total energy at the saved times; ``None`` when the system has no
            ``total_energy``.
        energy_drift: ``max_t |E(t) − E(t0)| / max(|E(t0)|, tiny)`` over the saved times
            (a conservation check: meaningful without damping or actuation); ``None``
            with ``energy``. ``E(t0)`` is the energy of the first saved point. Between
            solver steps the saved states come from the solver's dense output, whose
            interpolation error shows up here too.
        stats: diffrax step counts: ``num_steps``, ``num_accepted_steps``,
            ``num_rejected_steps``.
        result: diffrax result code (``diffrax.RESULTS.successful`` when the solve
            finished). With ``throw=False`` a failed solve keeps ``inf`` after the failure.
    """

    t: Float[Array, " n_save"]
    q: Float[Array, "n_save nq"]
    v: Float[Array, "n_save nv"]
    energy: Float[Array, " n_save"] | None
    energy_drift: Float[Array, ""] | None
    stats: dict[str, Int[Array, ""]]
    result: diffrax.RESULTS

    @property
    def success(self) -> jax.Array:
        """Boolean array: the solve finished (per member when batched)."""
        return self.result == diffrax.RESULTS.successful

    @property
    def energy_error(self) -> Float[Array, "*batch n_save"] | None:
        """Signed relative energy error ``(E(t) − E(t0)) / max(|E(t0)|, tiny)`` per saved time."""
        if self.energy is None:
            return None
        return _relative_energy_error(self.energy)


def _relative_energy_error(energy):
    e0 = energy[..., :1]
    scale = jnp.maximum(jnp.abs(e0), jnp.finfo(energy.dtype).tiny)
    return (energy - e0) / scale


def _vector_field(t, y, args):
    system, tau = args
    q, v = y
    if callable(tau):
        tau = tau(t, q, v)
    return system.qdot(q, v), system.acceleration(t, q, v, tau)


def _check_system(system):
    missing = [name for name in ("nq", "nv", "qdot", "acceleration") if not hasattr(system, name)]
    if missing:
        raise TypeError(
            f"simulate needs a jaxbody.Model or a system with nq, nv, qdot and acceleration "
            f"(see jaxbody.simulate.DynamicalSystem); {type(system).__name__} lacks {', '.join(missing)}"
        )


def _progress_meter(progress):
    if not progress:
        return diffrax.NoProgressMeter()
    try:
        import tqdm  # noqa: F401
    except ImportError:
        return diffrax.TextProgressMeter()
    return diffrax.TqdmProgressMeter()


def simulate(
    system,
    q0: ArrayLike,
    v0: ArrayLike,
    t1: ArrayLike,
    *,
    t0: ArrayLike = 0.0,
    tau: ArrayLike | Callable | None = None,
    solver: str = "tsit5",
    rtol: ArrayLike = 1e-8,
    atol: ArrayLike = 1e-8,
    dt0: ArrayLike | None = None,
    saveat: diffrax.SaveAt | ArrayLike | None = None,
    n_save: int | None = None,
    max_steps: int | None = 100_000,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = True,
    progress: bool = False,
) -> Solution:
    """Integrate ``q̇ = qdot(q, v)``, ``v̇ = acceleration(t, q, v, tau)`` from ``t0`` to ``t1``.

    Args:
        system: a :class:`jaxbody.Model` or any :class:`DynamicalSystem`.
        q0: initial coordinates, ``(nq,)``.
        v0: initial velocities, ``(nv,)``.
        t1: final time.
        t0: initial time.
        tau: generalized forces ``(nv,)``: ``None``, a constant array, or a callable
            ``tau(t, q, v) -> (nv,)`` (a feedback law; make it an ``equinox.Module`` to
            differentiate through its parameters; a plain function is a static argument
            of the compiled solve, so pass the same object to reuse the compilation).
        solver: ``"tsit5"``, ``"dopri5"``, ``"dopri8"`` (adaptive, PID step control with
            ``rtol``/``atol``), ``"rk4"``, ``"euler"`` (fixed step ``dt0``).
        rtol, atol: tolerances of adaptive solvers.
        dt0: the step of fixed-step solvers (required); the first trial step of adaptive
            ones (``None``: chosen by diffrax).
        saveat: an array of times, or a ``diffrax.SaveAt`` saving the state at times
            (``ts``, ``t0``, ``t1``; no ``fn``, ``dense`` or ``steps``, whose padding
            would spoil the energy). Include ``t0``: the drift is measured from the
            first saved point.
        n_save: save at ``n_save`` evenly spaced times from ``t0`` to ``t1`` inclusive.
            With neither ``saveat`` nor ``n_save``: 101 evenly spaced times.
        max_steps: step budget; exceeding it is a failed solve (see ``throw``).
        adjoint: a diffrax adjoint for ``grad`` (default: ``RecursiveCheckpointAdjoint``).
        throw: raise on solver failure. ``False`` returns the failure in ``result`` so a
            vmapped batch survives a bad member.
        progress: show a progress meter (tqdm if installed).

    Returns:
        :class:`Solution` with ``t``, ``q``, ``v``, ``energy``, ``energy_drift``, ``stats``,
        ``result``.

    Raises:
        TypeError: ``system`` lacks the protocol's members.
        ValueError: unknown solver name, fixed-step solver without ``dt0``, both
            ``saveat`` and ``n_save``, ``n_save < 2``, or ``q0``/``v0``/``tau`` of the
            wrong shape.
    """
    from .model import Model

    if isinstance(system, Model):
        system = _ModelSystem(system)
    _check_system(system)

    q0 = jnp.asarray(q0)
    v0 = jnp.asarray(v0)
    if not jnp.issubdtype(q0.dtype, jnp.inexact):
        q0 = q0.astype(jnp.result_type(float))
    v0 = v0.astype(q0.dtype)
    if q0.shape != (system.nq,) or v0.shape != (system.nv,):
        raise ValueError(
            f"q0 must have shape ({system.nq},) and v0 ({system.nv},), got {q0.shape} and {v0.shape}"
        )
    if tau is not None and not callable(tau):
        tau = jnp.asarray(tau, dtype=q0.dtype)
        if tau.shape != (system.nv,):
            raise ValueError(f"tau must have shape ({system.nv},) or be callable, got {tau.shape}")

    try:
        solver_cls, adaptive = SOLVERS[solver]
    except KeyError:
        raise ValueError(f"unknown solver {solver!r}; choose from {sorted(SOLVERS)}") from None
    # Tolerances, steps and times as arrays of the state dtype: jit traces them instead of
    # compiling once per value (tolerance sweeps, batches of horizons).
    if adaptive:
        controller = diffrax.PIDController(rtol=jnp.asarray(rtol, q0.dtype), atol=jnp.asarray(atol, q0.dtype))
    else:
        if dt0 is None:
            raise ValueError(f"fixed-step solver {solver!r} needs dt0")
        controller = diffrax.ConstantStepSize()
    if dt0 is not None:
        dt0 = jnp.asarray(dt0, q0.dtype)

    if saveat is not None and n_save is not None:
        raise ValueError("give saveat or n_save, not both")
    if n_save is not None and n_save < 2:
        raise ValueError(f"n_save must be at least 2 (t0 and t1), got {n_save}")
    t0 = jnp.asarray(t0, dtype=q0.dtype)
    t1 = jnp.asarray(t1, dtype=q0.dtype)
    if saveat is None:
        saveat = diffrax.SaveAt(ts=jnp.linspace(t0, t1, 101 if n_save is None else n_save))
    elif not isinstance(saveat, diffrax.SaveAt):
        saveat = diffrax.SaveAt(ts=jnp.asarray(saveat, dtype=q0.dtype))

    return _solve(
        system,
        (q0, v0),
        t0,
        t1,
        tau,
        solver_cls(),
        controller,
        dt0,
        saveat,
        max_steps,
        diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint,
        throw,
        _progress_meter(progress),
    )


@eqx.filter_jit
def _solve(system, y0, t0, t1, tau, solver, controller, dt0, saveat, max_steps, adjoint, throw, meter):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field),
        solver,
        t0,
        t1,
        dt0,
        y0,
        args=(system, tau),
        saveat=saveat,
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=throw,
        progress_meter=meter,
    )
    q, v = sol.ys
    if hasattr(system, "total_energy"):
        energy = jax.vmap(system.total_energy)(q, v)
        energy_drift = jnp.max(jnp.abs(_relative_energy_error(energy)))
    else:
        energy = energy_drift = None
    stats = {k: jnp.asarray(sol.stats[k]) for k in ("num_steps", "num_accepted_steps", "num_rejected_steps")}
    return Solution(
        t=sol.ts, q=q, v=v, energy=energy, energy_drift=energy_drift, stats=stats, result=sol.result
    )
