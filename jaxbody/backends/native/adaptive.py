"""Whole adaptive solves by embedded Runge–Kutta pairs in one native call, and their reverse sweep.

The pairs are diffrax's Tsit5, Dopri5 and Dopri8 (:mod:`.tableaux`); the step-size control is
diffrax's ``PIDController`` (the scaled error ``‖e / (atol + rtol·max(|y₀|, |y₁|))‖_rms`` over
the whole state, the factor ``safety · ε⁻ᵏ¹ · ε_prev⁻ᵏ² · ε_prevprev⁻ᵏ³`` clipped to
``[factormin, factormax]``, ``dtmin``/``dtmax``, the initial step chosen as in Hairer, Nørsett
the next step rounded to ``t1`` within 100 ulp); the
states at requested times come from each method's dense output (:class:`.tableaux.Tableau`).
"""

import jax.numpy as jnp
import numpy as np

from ..._types import Array, ArrayLike, Float
from ...model import Model
from .build import compiled_kernel
from .rk4 import work_count
from .solve import STATUS, run_whole_solve, torque_operand, work_row
from .symbolic import parameter_vector
from .tableaux import METHODS

__all__ = ["Control", "adaptive_solve", "adaptive_solve_vjp", "adaptive_checkpoint_layout", "STATUS"]


class Control:
    """The step-size controller's settings (diffrax's ``PIDController`` fields)."""

    def __init__(self, rtol, atol, pcoeff=0.0, icoeff=1.0, dcoeff=0.0, dtmin=None, dtmax=None, force_dtmin=True,
                 factormin=0.2, factormax=10.0, safety=0.9):
        self.rtol, self.atol, self.pcoeff, self.icoeff, self.dcoeff = rtol, atol, pcoeff, icoeff, dcoeff
        self.dtmin, self.dtmax, self.force_dtmin = dtmin, dtmax, force_dtmin
        self.factormin, self.factormax, self.safety = factormin, factormax, safety

    @classmethod
    def of(cls, controller) -> "Control":
        """The settings of a ``diffrax.PIDController``."""
        c = controller
        return cls(c.rtol, c.atol, c.pcoeff, c.icoeff, c.dcoeff, c.dtmin, c.dtmax, c.force_dtmin, c.factormin,
                   c.factormax, c.safety)


#: The first step without ``dt0``: diffrax's loop wraps the term (for the direction of time), and
#: ``PIDController`` chooses an initial step by Hairer, Nørsett & Wanner's rule for a bare
#: ``ODETerm`` only, else starts at 0.01: so does the native solve, which takes diffrax's steps.
_FIRST_STEP = 0.01


def _harmonics(torque):
    return None if torque is None else int(jnp.shape(torque[1])[-1])


def adaptive_checkpoint_layout(model: Model, max_steps: int, checkpoints: int, works: int = 1) -> tuple[int, int]:
    """``(every, width)``: accepted steps between the reverse sweep's checkpoints for a budget of
    ``max_steps`` steps kept in ``checkpoints`` slots, and the width of their row (each: the
    state with its ``works`` works, the carried derivative and where it was evaluated, and the
    loop's seven scalars)."""
    every = max(1, -(-max_steps // max(checkpoints, 1)))
    slots = max_steps // every + 1
    n = model.nq + model.nv + works
    return every, slots * (3 * n + 7)


def _work_bits(has_work, harmonics) -> float:
    """The works the solve carries as bits (bit ``j``: work ``j`` integrated and in the error
    norm): ``has_work`` a bool for all of them, or one per work."""
    flags = (has_work,) * work_count(harmonics) if isinstance(has_work, bool) else tuple(has_work)
    if len(flags) != work_count(harmonics):
        raise ValueError(f"has_work: expected {work_count(harmonics)} flags (one per work), got {len(flags)}")
    return float(sum(1 << j for j, f in enumerate(flags) if f))


def _rows(model, method, q, v, t0, t1, dt0, max_steps, control, ts, force, gravity, stiffness, reference, damping,
          torque, work0, has_work, frozen, every):
    """The operands of the ``"adaptive:…"`` programs, as ``(1, n)`` rows, the number of save
    times and the torque's harmonics (:func:`.solve.torque_operand`)."""
    from equinox.internal import prevbefore

    if method not in METHODS:
        raise ValueError(f"unknown adaptive method {method!r}; choose from {sorted(METHODS)}")
    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    t0, t1 = jnp.asarray(t0, dtype), jnp.asarray(t1, dtype)
    force = jnp.zeros(model.nv, dtype) if force is None else jnp.asarray(force, dtype)
    gravity = jnp.zeros(3, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    stiffness = jnp.zeros(model.joints.n_joint, dtype) if stiffness is None else jnp.asarray(stiffness, dtype)
    reference = jnp.zeros(model.nq, dtype) if reference is None else jnp.asarray(reference, dtype)
    damping = jnp.zeros(model.nv, dtype) if damping is None else jnp.asarray(damping, dtype)
    coefficients, harmonics = torque_operand(torque, model.nv, dtype)
    # diffrax's loop: a next step ending within 100 ulp below t1 ends at t1
    t1_floor = t1
    for _ in range(100):
        t1_floor = prevbefore(t1_floor)
    c = control
    order = METHODS[method]().order(None)
    n_ts = 0 if ts is None else int(ts.shape[-1])
    fields = [t0, t1, t1_floor, np.inf if max_steps is None else max_steps, _FIRST_STEP if dt0 is None else dt0, c.rtol, c.atol,
              c.pcoeff, c.icoeff, c.dcoeff, 0.0 if c.dtmin is None else c.dtmin, np.inf if c.dtmax is None else c.dtmax,
              float(c.force_dtmin), c.factormin, c.factormax, c.safety, order, frozen, _work_bits(has_work, harmonics), every,
              float(c.dtmin is not None), n_ts]
    schedule = jnp.stack([jnp.asarray(x, dtype) for x in fields])
    ts_row = jnp.zeros((1,), dtype) if ts is None else jnp.asarray(ts, dtype)
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    return (row(q), row(v), row(force), row(parameter_vector(model)), row(gravity), coefficients,
            row(stiffness), row(reference), row(damping), work_row(work0, harmonics, dtype), row(schedule),
            row(ts_row)), n_ts, harmonics


def adaptive_solve(
    model: Model,
    method: str,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    t0: ArrayLike,
    t1: ArrayLike,
    control: Control,
    dt0: ArrayLike | None = None,
    max_steps: int | None = None,
    ts: Float[ArrayLike, " n_ts"] | None = None,
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    stiffness: Float[ArrayLike, " n_joint"] | None = None,
    reference: Float[ArrayLike, " nq"] | None = None,
    damping: Float[ArrayLike, " nv"] | None = None,
    torque: tuple | None = None,
    work0: ArrayLike = 0.0,
    has_work: bool | tuple = False,
    frozen: ArrayLike = False,
    checkpoints: int | None = None,
) -> tuple:
    """An adaptive solve of ``(q̇, v̇, ẇ) = (q̇(q, v), a, P)`` from ``t0`` to ``t1`` in one native call.

    ``method``: ``"tsit5"``, ``"dopri5"`` or ``"dopri8"``; ``control``: the step-size
    controller's settings; ``dt0``: the first step (``None``: 0.01, as diffrax's loop takes it);
    ``max_steps``: the budget of attempted steps; ``ts``: times (non-decreasing) at which the state
    is saved from the dense output. The field is that of :func:`rk4_step` (``force``,
    ``gravity``, springs and dampers held) plus a Fourier-series joint torque ``torque =
    (frequency, sine, cosine, offset)`` at each stage's time (:func:`rk4_rollout`; with it ``w``
    is the pair of the dampers' and the torque's works, and ``has_work`` may be one flag per work); ``w`` integrates the dampers' power ``P`` and enters
    the error norm where ``has_work``. Quaternions are renormalised after each step (not inside
    the error estimate), as :func:`jaxbody.simulate`'s guard does. ``frozen``: the state does
    not move (its field is zero), as ``simulate`` does for an input that failed its checks.

    Returns ``(q, v, w, status, ys)``: the final state and work, the status row (:data:`STATUS`)
    and the saved states ``(n_ts, nq + nv + 1)`` (rows past ``status[5]`` unwritten: ``inf``);
    with ``checkpoints`` (and a bounded ``max_steps``) also the checkpoints of
    :func:`adaptive_solve_vjp`. A ``vmap`` batch is one call, each member with its own steps and
    result.
    """
    every = 1
    if checkpoints is not None:
        every, width = adaptive_checkpoint_layout(model, max_steps, checkpoints, work_count(_harmonics(torque)))
    rows, n_ts, harmonics = _rows(model, method, q, v, t0, t1, dt0, max_steps, control, ts, force, gravity, stiffness,
                                  reference, damping, torque, work0, has_work, frozen, every)
    kernel = compiled_kernel(model.tree, model.joints, False, np.dtype(model.body_pos.dtype), f"adaptive:{method}",
                             harmonics)
    return run_whole_solve(kernel, model, rows, n_ts, harmonics, width if checkpoints is not None else None)


def adaptive_solve_vjp(model: Model, method: str, q, v, t0, t1, control: Control, dt0, max_steps: int, checkpoints: int,
                       saved, status, cotangent_q, cotangent_v, cotangent_work=0.0, force=None, *, ts=None,
                       cotangent_saved=None, gravity=None, stiffness=None, reference=None, damping=None, torque=None,
                       work0=0.0, has_work=False, frozen=False):
    """Reverse mode of :func:`adaptive_solve` with respect to the initial ``(q, v, w)``, in one
    native call: the accepted steps replayed from the checkpoints ``saved`` (:func:`adaptive_solve`
    with ``checkpoints``) and reversed through the field's generated reverse-mode program, the
    step sizes held (diffrax, too, stops the gradient through the controller). ``cotangent_*``:
    of the final state and work, and of the states saved at ``ts`` (``(n_ts, nq + nv + 1)``;
    through each step's dense output). Returns the cotangents of ``(q, v, w)``."""
    every, _ = adaptive_checkpoint_layout(model, max_steps, checkpoints, work_count(_harmonics(torque)))
    rows, n_ts, harmonics = _rows(model, method, q, v, t0, t1, dt0, max_steps, control, ts, force, gravity, stiffness,
                                  reference, damping, torque, work0, has_work, frozen, every)
    dtype = model.body_pos.dtype
    row = lambda x: jnp.reshape(jnp.asarray(x, dtype), (1, -1))  # noqa: E731
    ct_saved = jnp.zeros((1,), dtype) if cotangent_saved is None or n_ts == 0 else cotangent_saved
    kernel = compiled_kernel(model.tree, model.joints, False, np.dtype(dtype), f"adaptive_vjp:{method}", harmonics)
    ct_q, ct_v, ct_w = kernel.batched(*rows[:11], row(saved), row(status), row(cotangent_q), row(cotangent_v),
                                      work_row(cotangent_work, harmonics, dtype), rows[11], row(ct_saved))
    return ct_q[0], ct_v[0], ct_w[0, 0] if ct_w.shape[1] == 1 else ct_w[0]
