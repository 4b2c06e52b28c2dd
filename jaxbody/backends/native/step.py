"""One RK4 step of the native kernel as a JAX function (value and derivatives native)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import scalar
from ..._types import Array, ArrayLike, Float
from ...model import Model
from .rk4 import fourier_torque, joint_force, rk4_scalars
from .build import compiled_kernel
from .primitives import forward_dynamics_call, split_jvp, state_rows
from .solve import torque_operand

# ----------------------------------------------------------------------------- one RK4 step
def _step_rows(model, q, v, force, gravity, external, h, stiffness, reference, damping):
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    return (*state_rows(model, q, v, force, gravity, external), row(h), row(stiffness), row(reference), row(damping))


def _rk4_composed(fd_kernel, model, q, v, force, gravity, external, h, stiffness, reference, damping):
    """The RK4 step written in JAX around the native forward dynamics (its derivatives with
    respect to the parameters, gravity, loads, ``h``, springs and dampers)."""
    sc = scalar.scalars

    def field(qs, vs, t):
        total, power = joint_force(model.joints, qs, vs, sc(force), sc(stiffness), sc(reference), sc(damping))
        a = forward_dynamics_call(fd_kernel, model, jnp.stack(qs), jnp.stack(vs), scalar.stack(total, q.dtype), gravity, external)
        return sc(a), power

    out = rk4_scalars(field, model.joints, sc(q), sc(v), h)
    return tuple(scalar.stack(o, q.dtype) for o in out)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _rk4_step(kernel, fd_kernel, model, q, v, force, gravity, external, h, stiffness, reference, damping):
    rows = _step_rows(model, q, v, force, gravity, external, h, stiffness, reference, damping)
    return tuple(o[0] for o in kernel.batched(*rows))


def _rk4_step_jvp(kernel, fd_kernel, primals, tangents):
    # value: the native step; tangent: split_jvp with the step's generated programs, the rest
    # (parameters, gravity, loads, h, springs, dampers) from the step written in JAX around the
    # native forward dynamics
    out = _rk4_step(kernel, fd_kernel, *primals)
    reference = functools.partial(_rk4_composed, fd_kernel)
    return out, split_jvp(kernel, "rk4_jvp", _step_rows(*primals), out, primals, tangents, reference)


_rk4_step.defjvp(_rk4_step_jvp, symbolic_zeros=True)


def _timed_composed(fd_kernel, harmonics, model, q, v, force, gravity, external, h, stiffness, reference, damping,
                    coefficients, times):
    """The step with a Fourier-series torque at the stages' times, written in JAX around the native
    forward dynamics (every derivative of :func:`_timed_step`): the same arithmetic as the program."""
    sc = scalar.scalars

    def field(qs, vs, t):
        tau = fourier_torque(sc(coefficients), model.nv, harmonics, t)
        power = 0.0
        for ti, vi in zip(tau, vs):
            power = power + ti * vi
        held = [fi + ti for fi, ti in zip(sc(force), tau)]
        total, damper = joint_force(model.joints, qs, vs, held, sc(stiffness), sc(reference), sc(damping))
        a = forward_dynamics_call(fd_kernel, model, jnp.stack(qs), jnp.stack(vs), scalar.stack(total, q.dtype), gravity, external)
        return sc(a), [damper, power]

    out = list(rk4_scalars(field, model.joints, sc(q), sc(v), h, times[0], times[1]))
    out[-1] = [x for part in out[-1] for x in part]
    return tuple(scalar.stack(o, q.dtype) for o in out)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _timed_step(kernel, fd_kernel, harmonics, model, q, v, force, gravity, external, h, stiffness, reference, damping,
                coefficients, times):
    rows = _step_rows(model, q, v, force, gravity, external, h, stiffness, reference, damping)
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    return tuple(o[0] for o in kernel.batched(*rows, row(coefficients), row(times)))


def _timed_step_jvp(kernel, fd_kernel, harmonics, primals, tangents):
    # value: the native step; every tangent from the step written in JAX (no derivative programs)
    out = _timed_step(kernel, fd_kernel, harmonics, *primals)
    reference = functools.partial(_timed_composed, fd_kernel, harmonics)
    return out, split_jvp(kernel, None, None, out, primals, tangents, reference)


_timed_step.defjvp(_timed_step_jvp, symbolic_zeros=True)


def rk4_step(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    h: ArrayLike,
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    external: Float[ArrayLike, "n_body 6"] | None = None,
    stiffness: Float[ArrayLike, " n_joint"] | None = None,
    reference: Float[ArrayLike, " nq"] | None = None,
    damping: Float[ArrayLike, " nv"] | None = None,
    torque: tuple | None = None,
    t0: ArrayLike = 0.0,
    t1: ArrayLike | None = None,
) -> tuple[Array, Array, Array, Array, Array, Array, Array]:
    """One classical RK4 step of ``(q̇, v̇) = (q̇(q, v), a(q, v))`` in one native call.

    The joint force at each stage is ``force − k (q − q_ref) − c v``: ``force``, ``gravity`` and
    ``external`` are held over the step; ``stiffness`` (per joint; ball and free joints: a
    spring on the rotation vector from the reference orientation, as :class:`jaxbody.JointSprings`),
    ``reference`` (``(nq,)``) and ``damping`` (per DoF) default to none. Returns ``(q1, v1, k1q, k1v, k4q, k4v, work)``: the
    state after the step (quaternions not renormalised), the increments ``h·f`` of the first
    and last stage (the end slopes of the step's cubic Hermite dense output), and ``work =
    (Δw, k1w, k4w)``: the dampers' work over the step by the same RK4 rule and its first and
    last stage increments.

    ``torque = (frequency, sine, cosine, offset)`` (:class:`jaxbody.FourierTorque`'s fields) adds a
    Fourier-series joint torque evaluated at the stages' times ``t0``, ``t0 + h/2`` (twice) and
    ``t1`` (default ``t0 + h``); its work ``τ·v`` is a second one: ``work`` is then ``(Δw, k1w,
    k4w)`` of each, ``(Δw_dampers, Δw_torque, k1w_dampers, …)``, and every derivative comes from
    the step written around :func:`forward_dynamics`.

    The four stages, the quaternion rates and the combination run in the generated program of
    the tree: no intermediate state goes through memory, and a ``vmap`` batch is one call.
    Derivatives along ``(q, v, force)`` come from the step's generated forward- and
    reverse-mode programs (trees up to :data:`MAX_DERIVATIVE_DOFS`), the others from the same
    step written around :func:`forward_dynamics`.
    """
    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    h = jnp.asarray(h, dtype)
    force = jnp.zeros(model.nv, dtype) if force is None else jnp.asarray(force, dtype)
    gravity = jnp.zeros(3, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    stiffness = jnp.zeros(model.joints.n_joint, dtype) if stiffness is None else jnp.asarray(stiffness, dtype)
    reference = jnp.zeros(model.nq, dtype) if reference is None else jnp.asarray(reference, dtype)
    damping = jnp.zeros(model.nv, dtype) if damping is None else jnp.asarray(damping, dtype)
    if external is not None:
        external = jnp.asarray(external, dtype)
    with_external = external is not None
    fd_kernel = compiled_kernel(model.tree, model.joints, with_external, np.dtype(dtype))
    if torque is not None:
        coefficients, harmonics = torque_operand(torque, model.nv, dtype)
        t0 = jnp.asarray(t0, dtype)
        times = jnp.stack([t0, t0 + h if t1 is None else jnp.asarray(t1, dtype)])
        kernel = compiled_kernel(model.tree, model.joints, with_external, np.dtype(dtype), "rk4", harmonics)
        return _timed_step(kernel, fd_kernel, harmonics, model, q, v, force, gravity, external, h, stiffness, reference,
                           damping, coefficients[0], times)
    kernel = compiled_kernel(model.tree, model.joints, with_external, np.dtype(dtype), "rk4")
    return _rk4_step(kernel, fd_kernel, model, q, v, force, gravity, external, h, stiffness, reference, damping)
