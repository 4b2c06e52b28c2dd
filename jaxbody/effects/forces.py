"""Ready effects: gravity, joint springs and dampers, actuation, a Fourier-series joint torque,
body loads, moving support.

Each is a small :class:`~jaxbody.effects.Effect`. The path-dependent kinematics (spatial tree
or planar absolute angles) is the scene's business: an effect asks the scene for the
generalized force of a uniform field or of body wrenches, so the same effect serves both
paths.
"""

from collections.abc import Callable
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

import numpy as np

from .._types import Array, Float
from .._util import is_concrete
from ..backends.scalar import fourier_series
from ..kernels import spring_displacements
from ._base import Effect, EffectContext

__all__ = [
    "Gravity",
    "JointSprings",
    "JointDampers",
    "Actuation",
    "ControlSignal",
    "FourierTorque",
    "BodyLoads",
    "SupportMotion",
]


class Gravity(Effect):
    """A uniform gravity field ``g`` (world frame, m/s²) acting at every centre of mass.

    Generalized force ``τ_d = Σ_{k moved by d} m_k g·(∂C_k/∂q_d)``; potential
    ``V = −Σ_k m_k g·C_k``.
    """

    vector: Float[Array, " dim"]
    name: ClassVar[str] = "gravity"
    conservative: ClassVar[bool] = True

    def generalized_force(self, ctx: EffectContext):
        return ctx.scene.uniform_field_force(ctx, self.vector)

    def potential_energy(self, ctx: EffectContext):
        return ctx.scene.uniform_field_potential(ctx, self.vector)


class JointSprings(Effect):
    """Joint springs ``τ = −k (q ⊖ q_ref)`` (quaternion joints: rotation-vector difference).

    Attributes:
        stiffness: per joint ``(n_joint,)``.
        reference: spring reference configuration ``(nq,)`` (the model's ``qpos_spring``).
    """

    stiffness: Float[Array, " n_joint"]
    reference: Float[Array, " nq"]
    name: ClassVar[str] = "springs"
    conservative: ClassVar[bool] = True

    def _terms(self, ctx):
        model = eqx.tree_at(
            lambda m: (m.joint_stiffness, m.qpos_spring), ctx.scene.model, (self.stiffness, self.reference)
        )
        return spring_displacements(model, ctx.q)

    def generalized_force(self, ctx: EffectContext):
        f = jnp.zeros_like(ctx.v)
        for dofs, disp, k in self._terms(ctx):
            f = f.at[dofs].add(-k[:, None] * disp)
        return f

    def potential_energy(self, ctx: EffectContext):
        e = jnp.zeros((), ctx.q.dtype)
        for _, disp, k in self._terms(ctx):
            e = e + 0.5 * jnp.sum(k * jnp.sum(disp * disp, axis=-1))
        return e

    def check(self, scene):
        if self.stiffness.shape != (scene.model.n_joint,):
            raise ValueError(f"springs: stiffness has shape {self.stiffness.shape}, expected ({scene.model.n_joint},)")
        if self.reference.shape != (scene.nq,):
            raise ValueError(f"springs: reference has shape {self.reference.shape}, expected ({scene.nq},)")
        _check_coefficients("springs", "stiffness", self.stiffness, scene.model.joints.names, None)


class JointDampers(Effect):
    """Viscous joint damping ``τ = −c ⊙ v``; its (negative) work is the dissipation."""

    damping: Float[Array, " nv"]
    name: ClassVar[str] = "dampers"

    def generalized_force(self, ctx: EffectContext):
        return -self.damping * ctx.v

    def check(self, scene):
        if self.damping.shape != (scene.nv,):
            raise ValueError(f"dampers: damping has shape {self.damping.shape}, expected ({scene.nv},)")
        joints = scene.model.joints if hasattr(scene, "model") and hasattr(scene.model, "joints") else None
        _check_coefficients("dampers", "damping", self.damping, joints.names if joints else None,
                            joints.dof_joint if joints else None)


def _check_coefficients(effect, field, values, joint_names, dof_joint):
    """A spring stiffness or a damping coefficient must be finite and non-negative (a negative
    one feeds energy in without bound); checked on concrete values, naming the joint."""
    if not is_concrete(values) or np.ndim(values) != 1:
        return
    a = np.asarray(values, dtype=np.float64)
    for i in np.flatnonzero(~np.isfinite(a) | (a < 0))[:1]:
        j = int(dof_joint[i]) if dof_joint is not None else int(i)
        who = f"joint {j} ({joint_names[j]!r})" if joint_names is not None else f"entry {i}"
        what = "is not finite (NaN or inf)" if not np.isfinite(a[i]) else "is negative"
        raise ValueError(f"{effect}: {who}: {field} {what} ({a[i]})")


class ControlSignal(eqx.Module):
    """A control signal sampled on a time grid, interpolated by diffrax (a ``tau`` law).

    ``ControlSignal(ts, values)(t, q, v)`` returns the signal at ``t``: piecewise linear
    (``method="linear"``) or a C¹ cubic Hermite spline through the samples (``"cubic"``).
    Outside ``[ts[0], ts[-1]]`` the end segments are extrapolated.

    Attributes:
        interpolation: a diffrax interpolation of ``values`` ``(n_time, nv)`` over ``ts``.
    """

    interpolation: Any

    def __init__(self, ts, values, method: str = "linear"):
        ts = jnp.asarray(ts)
        values = jnp.asarray(values)
        if ts.ndim != 1 or values.ndim != 2 or values.shape[0] != ts.shape[0]:
            raise ValueError(
                f"control signal: ts must be (n_time,) and values (n_time, nv), got {ts.shape} and {values.shape}"
            )
        if method == "linear":
            self.interpolation = diffrax.LinearInterpolation(ts=ts, ys=values)
        elif method == "cubic":
            coeffs = diffrax.backward_hermite_coefficients(ts, values)
            self.interpolation = diffrax.CubicInterpolation(ts, coeffs)
        else:
            raise ValueError(f"control signal: method must be 'linear' or 'cubic', got {method!r}")

    def __call__(self, t, q, v):
        return self.interpolation.evaluate(t)


class Actuation(Effect):
    """Generalized forces ``τ(t, q, v)`` (or ``τ(t, q, v, params)``) in the layout of ``v``.

    Attributes:
        law: a callable. Make it an ``equinox.Module`` (a feedback law, a
            :class:`ControlSignal`) so ``grad`` reaches its array fields; a plain function is
            a static part of the compiled solve.
        params: optional pytree passed as the fourth argument (``grad`` reaches it).
    """

    law: Callable
    params: Any = None
    name: ClassVar[str] = "actuation"

    def __call__(self, t, q, v):
        if self.params is None:
            return self.law(t, q, v)
        return self.law(t, q, v, self.params)

    def generalized_force(self, ctx: EffectContext):
        return jnp.asarray(self(ctx.t, ctx.q, ctx.v), ctx.v.dtype)

    def check(self, scene):
        dt = jnp.result_type(float)
        s = jax.ShapeDtypeStruct
        try:
            out = jax.eval_shape(self.__call__, s((), dt), s((scene.nq,), dt), s((scene.nv,), dt))
        except Exception as err:  # the law fails on the state shapes: say so first
            raise ValueError(f"actuation: tau(t, q, v) fails for q ({scene.nq},), v ({scene.nv},): {err}") from err
        if getattr(out, "shape", None) != (scene.nv,):
            raise ValueError(
                f"actuation: tau(t, q, v) returned shape {getattr(out, 'shape', type(out))}, expected ({scene.nv},)"
            )


class FourierTorque(Effect):
    """A joint torque given as a finite Fourier series of time, in the layout of ``v``:

    ``τ_i(t) = c_i + Σ_{k=1..K} (a_ik sin(k ω t) + b_ik cos(k ω t))``, ``ω = 2π f``

    (the excitation trajectories of robot identification: smooth, periodic, band-limited).
    Unlike an :class:`Actuation` law, its form is known, so the native kernel's one-call
    solves evaluate it inside the generated program at each stage's time (a scene of gravity,
    joint springs and dampers and this torque keeps the one-call RK4 and adaptive solves);
    ``grad`` reaches every coefficient. Its power ``τ·v`` is integrated as work.

    Args:
        frequency: the fundamental frequency ``f`` in Hz (a scalar).
        sine: ``a`` ``(nv, K)``, the sine coefficients of harmonics ``1 … K``.
        cosine: ``b`` ``(nv, K)`` (default zeros).
        offset: ``c`` ``(nv,)`` (default zeros).

    The formula is :func:`jaxbody.backends.scalar.fourier_series` (one sine and cosine per
    evaluation, the harmonics by rotation). Also callable as a law ``tau(t, q, v)``.
    """

    frequency: Float[Array, ""]
    sine: Float[Array, "nv harmonics"]
    cosine: Float[Array, "nv harmonics"]
    offset: Float[Array, " nv"]
    name: ClassVar[str] = "torque"

    def __init__(self, frequency, sine=None, cosine=None, offset=None):
        given = [x for x in (sine, cosine) if x is not None]
        if not given and offset is None:
            raise ValueError("torque: give sine and/or cosine coefficients (nv, K), or an offset (nv,)")
        ref = jnp.asarray(given[0]) if given else None
        nv = ref.shape[0] if ref is not None and ref.ndim == 2 else np.shape(offset)[0] if np.ndim(offset) == 1 else None
        for field, x in (("sine", sine), ("cosine", cosine)):
            if x is not None and (np.ndim(x) != 2 or (ref is not None and np.shape(x) != ref.shape)):
                want = "(nv, K)" if ref is None or ref.ndim != 2 else str(tuple(ref.shape))
                raise ValueError(f"torque: {field} has shape {np.shape(x)}, expected {want} (a row per DoF, a column per harmonic)")
        if offset is not None and (np.ndim(offset) != 1 or (nv is not None and np.shape(offset)[0] != nv)):
            raise ValueError(f"torque: offset has shape {np.shape(offset)}, expected ({nv},) (one per DoF)")
        if np.ndim(frequency) != 0:
            raise ValueError(f"torque: frequency must be a scalar (Hz), got shape {np.shape(frequency)}")
        dtype = jnp.result_type(*(jnp.asarray(x) for x in (frequency, sine, cosine, offset) if x is not None), float)
        shape = ref.shape if ref is not None else (nv, 0)
        self.frequency = jnp.asarray(frequency, dtype)
        self.sine = jnp.zeros(shape, dtype) if sine is None else jnp.asarray(sine, dtype)
        self.cosine = jnp.zeros(shape, dtype) if cosine is None else jnp.asarray(cosine, dtype)
        self.offset = jnp.zeros(shape[0], dtype) if offset is None else jnp.asarray(offset, dtype)
        for field in ("frequency", "sine", "cosine", "offset"):
            value = getattr(self, field)
            if is_concrete(value) and not np.all(np.isfinite(np.asarray(value))):
                bad = np.argwhere(~np.isfinite(np.atleast_1d(np.asarray(value))))[0]
                raise ValueError(f"torque: {field} is not finite (NaN or inf) at index {tuple(int(i) for i in bad)}")

    @property
    def harmonics(self) -> int:
        """``K``, the number of harmonics (static: it shapes the generated programs)."""
        return int(self.sine.shape[1])

    def __call__(self, t, q=None, v=None):
        """``τ(t)`` ``(nv,)``."""
        omega = 2 * np.pi * self.frequency
        columns = lambda x: [[x[:, k] for k in range(self.harmonics)]]  # noqa: E731
        return fourier_series(t, omega, [self.offset], columns(self.sine), columns(self.cosine))[0]

    def generalized_force(self, ctx: EffectContext):
        return jnp.asarray(self(ctx.t), ctx.v.dtype)

    def check(self, scene):
        for field in ("sine", "cosine", "offset"):
            n = getattr(self, field).shape[0]
            if n != scene.nv:
                raise ValueError(f"torque: {field} has {n} rows, expected one per DoF ({scene.nv})")


class BodyLoads(Effect):
    """External loads on bodies, MuJoCo ``xfrc_applied`` layout: ``wrench(t, q, v) -> (n_body, 6)``,
    world force and world torque applied at each body's centre of mass.

    Spatial models only (a scene with loads takes the spatial path).
    """

    wrench: Callable
    name: ClassVar[str] = "loads"

    def generalized_force(self, ctx: EffectContext):
        w = jnp.asarray(self.wrench(ctx.t, ctx.q, ctx.v), ctx.v.dtype)
        return ctx.scene.body_wrench_force(ctx, w)

    def check(self, scene):
        dt = jnp.result_type(float)
        s = jax.ShapeDtypeStruct
        out = jax.eval_shape(self.wrench, s((), dt), s((scene.nq,), dt), s((scene.nv,), dt))
        want = (scene.model.n_body, 6)
        if getattr(out, "shape", None) != want:
            raise ValueError(f"loads: wrench(t, q, v) returned shape {getattr(out, 'shape', type(out))}, expected {want}")


class SupportMotion(Effect):
    """Prescribed translation ``s(t)`` of the support (the ground the roots are hinged to).

    The state ``(q, v)`` is relative to the moving support; in that translating frame every
    body feels the inertial force ``−m_k s̈(t)`` at its centre of mass (a uniform, time-varying
    field). Its work is integrated, so the energy (relative to the support) balances.

    Attributes:
        position: ``s(t) -> (3,)`` world-frame support displacement (a pure function of ``t``;
            an ``equinox.Module`` for differentiable parameters). ``s̈`` comes from forward-mode
            autodiff.
    """

    position: Callable
    name: ClassVar[str] = "support"

    def acceleration(self, t):
        def vel(tt):
            return jax.jvp(self.position, (tt,), (jnp.ones_like(tt),))[1]

        return jax.jvp(vel, (t,), (jnp.ones_like(t),))[1]

    def generalized_force(self, ctx: EffectContext):
        acc = jnp.asarray(self.acceleration(ctx.t), ctx.v.dtype)
        return ctx.scene.uniform_field_force(ctx, -acc)

    def check(self, scene):
        out = jax.eval_shape(self.position, jax.ShapeDtypeStruct((), jnp.result_type(float)))
        if getattr(out, "shape", None) != (3,):
            raise ValueError(f"support: position(t) returned shape {getattr(out, 'shape', type(out))}, expected (3,)")
