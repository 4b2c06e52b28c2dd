"""Whole fixed-step RK4 solves in one native call, and their reverse sweep."""

import jax.numpy as jnp
import numpy as np

from ..._types import Array, ArrayLike, Float
from ...model import Model
from .symbolic import parameter_vector
from .build import compiled_kernel
from .rk4 import work_count


def torque_operand(torque, nv: int, dtype) -> tuple:
    """``(row, harmonics)`` of a Fourier-series joint torque ``(frequency, sine, cosine, offset)``
    (:class:`jaxbody.FourierTorque`'s fields: ``f`` in Hz, ``(nv, K)``, ``(nv, K)``, ``(nv,)``):
    the coefficient row the whole-solve programs read in the loads' slot (``ω = 2π f``, then
    ``c``, ``a``, ``b``: :func:`.rk4.torque_size` entries), and ``K``; ``None`` gives the unused slot's
    ``(1, 1)`` zeros and no harmonics."""
    if torque is None:
        return jnp.zeros((1, 1), dtype), None
    frequency, sine, cosine, offset = (jnp.asarray(x, dtype) for x in torque)
    harmonics = int(sine.shape[-1])
    if sine.shape != (nv, harmonics) or cosine.shape != (nv, harmonics) or offset.shape != (nv,) or frequency.shape != ():
        raise ValueError(f"torque: expected frequency (), sine and cosine ({nv}, K), offset ({nv},); got "
                         f"{frequency.shape}, {sine.shape}, {cosine.shape}, {offset.shape}")
    # ω as jaxbody.FourierTorque computes it, so both evaluate the same series
    row = jnp.concatenate([jnp.reshape(2 * np.pi * frequency, (1,)), offset, jnp.ravel(sine), jnp.ravel(cosine)])
    return row[None], harmonics

# ----------------------------------------------------------------------------- a whole solve
#: The columns of a whole solve's status row (:func:`rk4_rollout`, and the adaptive solves of
#: :mod:`.adaptive`): the time reached, steps attempted, accepted, rejected, the result code (0
#: success, 1 a kept step not finite, 2 ``dtmin`` reached without ``force_dtmin``) and the number
#: of saved states.
STATUS = ("t", "num_steps", "num_accepted_steps", "num_rejected_steps", "code", "saved")


def rk4_rollout(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    t0: ArrayLike,
    t1: ArrayLike,
    dt0: ArrayLike,
    max_steps: int | None = None,
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    ts: Float[ArrayLike, " n_ts"] | None = None,
    gravity: Float[ArrayLike, "3"] | None = None,
    stiffness: Float[ArrayLike, " n_joint"] | None = None,
    reference: Float[ArrayLike, " nq"] | None = None,
    damping: Float[ArrayLike, " nv"] | None = None,
    torque: tuple | None = None,
    work0: ArrayLike = 0.0,
    frozen: ArrayLike = False,
) -> tuple[Array, Array, Array, Array, Array]:
    """A fixed-step RK4 solve from ``t0`` to ``t1`` in one native call.

    The steps are those of :func:`jaxbody.simulate` with ``solver="rk4"`` and ``dt0`` (diffrax's
    constant step size): ``N = ceil((t1 − t0) / dt0)`` steps ending at ``t_k = t0 + (t1 − t0)·k/N``,
    each one :func:`rk4_step` (same field: ``force``, ``gravity``, springs and dampers held) plus
    a Fourier-series joint torque ``torque = (frequency, sine, cosine, offset)``
    (:class:`jaxbody.FourierTorque`'s fields) evaluated at each stage's time,
    the quaternions of ball and free joints renormalised after every step. A step whose result
    is not finite ends that trajectory there (its state is that step's); ``max_steps`` (``None``:
    no bound) ends it after that many steps. ``work0``: the dampers' work at ``t0`` (with a
    torque, the pair of the dampers' and the torque's works, each integrated); ``frozen``:
    take the steps without moving (as :func:`jaxbody.simulate` does for an input that failed
    its checks with ``throw=False``). ``ts``: times (non-decreasing, within ``[t0, t1]``) at which
    the state ``(q, v, w)`` is saved, as diffrax's loop saves them: after each step
    ``[t_k, t_k+1]`` every pending time ``≤ t_k+1`` from the step's dense output, the cubic
    Hermite interpolant of its end states (``q`` before renormalisation) and its first and last
    stage increments (diffrax's ``ThirdOrderHermitePolynomialInterpolation.from_k``).

    Returns ``(q, v, work, status, ys)``: the final state and work, the status row
    (:data:`STATUS`: the time reached, ``t1`` or the end of the last step taken; the steps taken;
    the code 1 where a step was not finite; the saves made) and the saved states ``(n_ts, nq +
    nv + works)`` (rows past ``status[5]``: ``inf``). A ``vmap`` batch is one call (split over
    the CPU cores), each state with its own times. Derivatives with respect to the initial
    state: :func:`rk4_rollout_vjp`; :func:`jaxbody.simulate` differentiates anything else through
    its step-by-step solve, which computes the same values. No checks; ``t1 >= t0``.
    """
    return _rollout(model, q, v, t0, t1, dt0, max_steps, force, ts, gravity, stiffness, reference, damping, torque,
                    work0, frozen, None)


def _rollout(model, q, v, t0, t1, dt0, max_steps, force, ts, gravity, stiffness, reference, damping, torque, work0,
             frozen, checkpoints) -> tuple:
    """:func:`rk4_rollout`, and with ``checkpoints`` (a bounded ``max_steps``) also the
    checkpoints of :func:`rk4_rollout_vjp`."""
    every = 1
    if checkpoints is not None:
        every, width = checkpoint_layout(model, max_steps, checkpoints)
    rows, n_ts, harmonics = _rollout_rows(model, q, v, t0, t1, dt0, max_steps, force, ts, gravity, stiffness, reference,
                                          damping, torque, work0, frozen, every)
    kernel = compiled_kernel(model.tree, model.joints, False, np.dtype(model.body_pos.dtype), "rk4_run", harmonics)
    return run_whole_solve(kernel, model, rows, n_ts, harmonics, width if checkpoints is not None else None)


def run_whole_solve(kernel, model: Model, rows: tuple, n_ts: int, harmonics: int | None,
                    checkpoint_width: int | None) -> tuple:
    """One call of a whole-solve program (RK4 or adaptive) on its operand ``rows``: ``(q, v, w,
    status, saved states)`` and, with a ``checkpoint_width``, the checkpoints row."""
    n = model.nq + model.nv + work_count(harmonics)
    widths = kernel.widths + (max(n_ts * n, 1),) + ((checkpoint_width,) if checkpoint_width is not None else ())
    outs = kernel.batched_with(widths)(*rows)
    q1, v1, w1, status, ys = (o[0] for o in outs[:5])
    result = (q1, v1, w1[0] if w1.shape[0] == 1 else w1, status, saved_rows(ys, status, n_ts, n))
    return result + ((outs[5][0],) if checkpoint_width is not None else ())


def saved_rows(ys: Array, status: Array, n_ts: int, n: int) -> Array:
    """The states a whole solve saved, ``(n_ts, n)``, from its flat result row: the rows past its
    saves (:data:`STATUS` ``"saved"``) ``inf``, as diffrax pads the times a solve did not reach."""
    made = jnp.arange(n_ts, dtype=status.dtype)[:, None] < status[STATUS.index("saved")]
    return jnp.where(made, ys[: n_ts * n].reshape(n_ts, n), jnp.inf)


def _rollout_rows(model, q, v, t0, t1, dt0, max_steps, force, ts, gravity, stiffness, reference, damping, torque, work0,
                  frozen, every) -> tuple:
    """The operands of the ``"rk4_run"`` programs (:data:`_RUN_SLOTS`, then the save times), as
    ``(1, n)`` rows, the number of save times and the torque's harmonics (:func:`torque_operand`)."""
    from equinox.internal import nextafter, prevbefore

    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    t0, t1, dt0 = (jnp.asarray(x, dtype) for x in (t0, t1, dt0))
    force = jnp.zeros(model.nv, dtype) if force is None else jnp.asarray(force, dtype)
    gravity = jnp.zeros(3, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    stiffness = jnp.zeros(model.joints.n_joint, dtype) if stiffness is None else jnp.asarray(stiffness, dtype)
    reference = jnp.zeros(model.nq, dtype) if reference is None else jnp.asarray(reference, dtype)
    damping = jnp.zeros(model.nv, dtype) if damping is None else jnp.asarray(damping, dtype)
    # diffrax's ConstantStepSize: the step count, and the time 100 ulp below t1 above which a
    # step's end is rounded to t1
    steps = jnp.ceil((t1 - t0) / nextafter(dt0))
    t1_floor = t1
    for _ in range(100):
        t1_floor = prevbefore(t1_floor)
    limit = jnp.asarray(np.inf if max_steps is None else max_steps, dtype)
    if ts is not None and jnp.ndim(ts) != 1:
        raise ValueError(f"ts: expected a 1-D array of save times, got shape {jnp.shape(ts)}")
    n_ts = 0 if ts is None else int(jnp.shape(ts)[0])
    schedule = jnp.stack([t0, t1, steps, t1_floor, limit, dt0, jnp.asarray(frozen, dtype), jnp.asarray(every, dtype),
                          jnp.asarray(n_ts, dtype)])
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    coefficients, harmonics = torque_operand(torque, model.nv, dtype)
    ts_row = jnp.zeros((1,), dtype) if ts is None or n_ts == 0 else jnp.asarray(ts, dtype)
    return (row(q), row(v), row(force), row(parameter_vector(model)), row(gravity), coefficients,
            row(stiffness), row(reference), row(damping), work_row(work0, harmonics, dtype), row(schedule),
            row(ts_row)), n_ts, harmonics


def work_row(work, harmonics, dtype):
    """The works of a whole solve (or their cotangents) as a ``(1, n)`` row of the program's
    :func:`.rk4.work_count` works, a scalar given for each."""
    return jnp.broadcast_to(jnp.asarray(work, dtype), (work_count(harmonics),))[None]


def checkpoint_layout(model: Model, max_steps: int, checkpoints: int) -> tuple[int, int]:
    """``(every, width)``: steps between the checkpoints of a solve of at most ``max_steps``
    steps kept in ``checkpoints`` slots, and the width of their row (each: ``q``, ``v``, the
    step's two times and the saves made before it)."""
    every = max(1, -(-max_steps // max(checkpoints, 1)))
    slots = -(-max_steps // every)
    return every, slots * (model.nq + model.nv + 3)


def rk4_rollout_checkpointed(model: Model, q, v, t0, t1, dt0, max_steps: int, checkpoints: int, force=None, *, ts=None,
                             gravity=None, stiffness=None, reference=None, damping=None, torque=None, work0=0.0,
                             frozen=False):
    """:func:`rk4_rollout` (bounded ``max_steps``) that also returns the checkpoints of its
    reverse sweep (:func:`rk4_rollout_vjp`): the state every ``every`` steps, ``every`` the
    fewest steps that fit ``max_steps`` into ``checkpoints`` slots (:func:`checkpoint_layout`).
    Returns ``(q, v, work, status, ys, checkpoints)``."""
    return _rollout(model, q, v, t0, t1, dt0, max_steps, force, ts, gravity, stiffness, reference, damping, torque,
                    work0, frozen, checkpoints)


def rk4_rollout_vjp(model: Model, q, v, t0, t1, dt0, max_steps: int, checkpoints: int, saved, status, cotangent_q,
                    cotangent_v, cotangent_work=0.0, force=None, *, ts=None, cotangent_saved=None, gravity=None,
                    stiffness=None, reference=None, damping=None, torque=None, frozen=False):
    """Reverse mode of :func:`rk4_rollout` with respect to the initial ``(q, v, w)``, in one native call.

    ``saved``, ``status``: the checkpoints and the status row, from
    :func:`rk4_rollout_checkpointed` with the same arguments; ``cotangent_*``: of the final ``q``,
    ``v`` and work, and of the states saved at ``ts`` (``(n_ts, nq + nv + works)``), which go
    back through each step's dense output. The steps between two checkpoints are recomputed
    (the same program as the solve's), then each step's generated reverse-mode program carries
    the cotangents back. Returns the cotangents of ``(q, v, w)``. A frozen trajectory passes
    them through."""
    every, _ = checkpoint_layout(model, max_steps, checkpoints)
    rows, n_ts, harmonics = _rollout_rows(model, q, v, t0, t1, dt0, max_steps, force, ts, gravity, stiffness, reference,
                                          damping, torque, 0.0, frozen, every)
    dtype = model.body_pos.dtype
    row = lambda x: jnp.reshape(jnp.asarray(x, dtype), (1, -1))  # noqa: E731
    ct_saved = jnp.zeros((1,), dtype) if cotangent_saved is None or n_ts == 0 else cotangent_saved
    kernel = compiled_kernel(model.tree, model.joints, False, np.dtype(dtype), "rk4_run_vjp", harmonics)
    ct_q, ct_v, ct_w = kernel.batched(*rows[:11], row(saved), row(status), row(cotangent_q), row(cotangent_v),
                                      work_row(cotangent_work, harmonics, dtype), rows[11], row(ct_saved))
    return ct_q[0], ct_v[0], ct_w[0, 0] if ct_w.shape[1] == 1 else ct_w[0]
