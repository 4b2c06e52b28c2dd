"""The vector field :func:`jaxbody.simulate` integrates, and when native programs compute it.

The state is ``y = (q, v)`` or ``y = (q, v, w)``, ``w`` the work done by the non-conservative
effects; ``args = (scene, valid)``, ``valid`` the outcome of the boundary check of a traced
input (``None`` when the input was checked eagerly or raises instead).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..effects import FourierTorque, Gravity, JointDampers, JointSprings

__all__ = ["VectorField", "native_field"]


class VectorField(eqx.Module):
    """``(q̇, v̇, ẇ)`` of a scene: ``ẇ`` holds the power of the scene's non-conservative effects,
    placed in the slots ``slots`` of the work vector (a phased run carries one work vector, the
    union of every phase's effects, across its switches; an effect absent from a phase adds
    nothing).

    A module rather than a closure so that the solvers can recognise it inside diffrax's terms
    (:class:`jaxbody.simulation.solvers.RK4Stages` replaces it by one native call) and so that
    equal solves share one compilation.
    """

    slots: tuple | None = eqx.field(static=True, default=None)

    def __call__(self, t, y, args):
        scene, valid = args
        q, v = y[0], y[1]
        a, powers, _ = scene.evaluate(t, q, v)
        # in the state's dtypes: a float32 state of a system whose parameters are float64 would
        # otherwise give float64 derivatives, which the solver's float32 buffers cannot hold
        out = (scene.qdot(q, v).astype(q.dtype), a.astype(v.dtype))
        if len(y) == 3:
            if self.slots:
                slots = np.asarray(self.slots, dtype=np.int32)
                wdot = jnp.zeros_like(y[2]).at[slots].set(jnp.stack(powers).astype(v.dtype))
            else:
                wdot = jnp.zeros_like(y[2])
            out = out + (wdot,)
        if valid is not None:
            # an input that failed the boundary check integrates a frozen state: its derivative
            # is zero, so no NaN reaches the step-size controller, which a vmap batch shares
            # with the members that are fine
            out = jax.tree.map(lambda x: jnp.where(valid, x, 0.0), out)
        return out


def native_field(scene, y0, slots, timed: bool = False):
    """``(model, gravity, passive)`` where the native RK4 programs compute ``scene``'s vector field
    on the state ``y0 = (q, v[, w])`` exactly (:func:`jaxbody.backends.native.rk4_step`'s arguments):
    the native kernel, and effects that are a uniform gravity field, joint dampers and joint
    springs, and with ``timed`` (the whole-solve programs, which know each stage's time) a
    :class:`jaxbody.FourierTorque` (``passive["torque"]``; its work is a second one: the
    whole-solve programs integrate both). ``None`` otherwise."""
    # the augmented state of a backsolve adjoint is a 4-tuple: its field is not the scene's
    if not isinstance(y0, tuple) or len(y0) not in (2, 3):
        return None
    effects = scene.effects
    # the native programs hard-code these effects; anything else (actuation, loads, another
    # time-dependent field) would be silently dropped, so it keeps the step-by-step field
    known = (Gravity, JointDampers, JointSprings) + ((FourierTorque,) if timed else ())
    if not scene.is_direct() or not all(isinstance(e, known) for e in effects):
        return None
    springs = [e for e in effects if isinstance(e, JointSprings)]
    dampers = [e for e in effects if isinstance(e, JointDampers)]
    torques = [e for e in effects if isinstance(e, FourierTorque)]
    if len(springs) > 1 or len(dampers) > 1 or len(torques) > 1 or scene.direct_kernel() != "native":
        return None
    # the native programs integrate the dampers' work and a torque's: those must be the scene's works
    if len(y0) == 3 and not slots:
        return None
    gravity = scene.gravity_vector(y0[1].dtype)  # None: no field (rk4_step's default)
    passive = {}
    if springs:
        passive.update(stiffness=springs[0].stiffness, reference=springs[0].reference)
    if dampers:
        passive.update(damping=dampers[0].damping)
    if torques:
        t = torques[0]
        passive.update(torque=(t.frequency, t.sine, t.cosine, t.offset))
    return scene.system, gravity, passive
