"""The scene builder :func:`jaxbody.scene`: which effects are declared and which path runs.

Choices made once, when the scene is built (so that an undeclared effect is absent from the
traced program, not a zero added at every step):

* **path**: :class:`~jaxbody.scene.PlanarScene` when every joint is a hinge (one per body, fixed
  base, no armature), all hinge axes are parallel and gravity lies in their plane, unless the
  spatial path would run the native kernel as one call (faster: the planar path is JAX code);
  :class:`~jaxbody.scene.SpatialScene` otherwise; :class:`~jaxbody.scene.SystemScene` for
  planar systems and other objects with the simulation protocol;
* **no quaternions**: ``q̇ = v`` without the per-kind quaternion kinematics when the model has
  no ball or free joint;
* effects whose parameters are all zero (the model's springs or dampers) are not declared.
"""

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import maggi
from .._types import ArrayLike
from ..constraints import loop_closures, loop_system
from ..effects import Actuation, BodyLoads, Effect, Gravity, JointDampers, JointSprings, SupportMotion
from .._util import is_concrete
from ..backends import KERNELS
from ..planar import aligned_system
from ..model import Model
from ..validation import validate_at_boundary
from .base import Scene
from .planar import PlanarScene
from .spatial import SpatialScene
from .system import SystemScene, own_constraints

__all__ = ["scene"]


def scene(
    system,
    *,
    gravity: bool | str | ArrayLike | None = "model",
    springs: bool | str | ArrayLike | JointSprings | None = "model",
    dampers: bool | str | ArrayLike | JointDampers | None = "model",
    actuation: Callable | Actuation | tuple | None = None,
    loads: Callable | BodyLoads | None = None,
    support: Callable | SupportMotion | None = None,
    constraints: Any = "model",
    effects: Sequence[Effect] = (),
    planar: bool | None = None,
    kernel: str | None = None,
) -> Scene:
    """Build a :class:`Scene`: ``system`` plus the effects declared here, nothing else.

    Args:
        system: a :class:`jaxbody.Model`, a planar system (``jb.planar``, ``jb.examples``) or
            any object with ``nq``, ``nv``, ``qdot``, ``acceleration``.
        gravity: ``"model"`` (the model's gravity; undeclared when it is zero), ``True`` (same),
            ``False``/``None`` (off), or a world vector ``(3,)``. Planar systems: ``"model"``/
            ``True`` keep theirs, ``False`` switches it off.
        springs: joint springs: ``"model"`` (declared when a stiffness is non-zero), ``False``
            (off), a stiffness array ``(n_joint,)`` (reference: the model's ``qpos_spring``) or
            a :class:`~jaxbody.effects.JointSprings`.
        dampers: joint dampers: ``"model"``, ``False``, a damping array ``(nv,)`` or a
            :class:`~jaxbody.effects.JointDampers`.
        actuation: generalized forces: a callable ``tau(t, q, v)`` (an ``equinox.Module`` for
            differentiable parameters, e.g. a :class:`~jaxbody.effects.ControlSignal`), a pair
            ``(tau, params)`` called as ``tau(t, q, v, params)``, or an
            :class:`~jaxbody.effects.Actuation`.
        loads: body loads ``wrench(t, q, v) -> (n_body, 6)`` (``xfrc_applied`` layout) or a
            :class:`~jaxbody.effects.BodyLoads`.
        support: prescribed support translation ``s(t) -> (3,)`` or a
            :class:`~jaxbody.effects.SupportMotion`; the state is then relative to the support.
        constraints: the Maggi layer: ``"model"`` (the model's loop closures, ``model.loops``
            from MJCF ``<connect>``, with their independent directions,
            :func:`jaxbody.constraints.loop_closures`; none when it has none), ``None``/``False``
            (none, loops left open), a :class:`jaxbody.maggi.ConstrainedSystem` built on this
            model (``jaxbody.maggi.constrain(model, [...], q_ref=...)``), or a sequence of
            :class:`jaxbody.maggi.Constraint` (e.g. from :mod:`jaxbody.constraints`), then
            built at ``q_ref = model.qpos0``; or any object with the
            :class:`~jaxbody.effects.Constraint` protocol. Given constraints replace the model's
            loops; keep both with ``[*jaxbody.constraints.loop_closures(model), ...]``. A
            ``ConstrainedSystem`` passed as ``system`` brings its own constraints.
        effects: further effect modules (contact, limits, ...), appended in order.
        planar: ``None`` chooses the planar absolute-angle path when the model allows it and
            the spatial path would not run the native kernel (which is faster); ``False``
            forces the spatial path; ``True`` requires the planar path.
        kernel: forward-dynamics kernel of the spatial path (:func:`jaxbody.backends.acceleration`):
            ``None`` (:func:`jaxbody.backends.default_kernel`: ``"auto"`` unless
            ``$JAXBODY_KERNEL`` says otherwise), ``"auto"`` (the native kernel where it can be
            built, else the fastest that can run, saying why in one warning:
            :func:`jaxbody.backends.resolve_kernel`), ``"native"``, ``"unrolled"`` or
            ``"vectorised"``. docs/performance.md says when each is faster; ``repr(scene)``
            names the path and the kernel that runs.

    Returns:
        The scene.

    Raises:
        ValueError: an effect the system cannot take, a wrong shape (naming the argument), or
            ``planar=True`` on a model that is not planar.
    """
    if isinstance(system, Scene):
        raise ValueError("scene: system is already a Scene")
    # checked now: a misspelt kernel would otherwise surface only when a solve is traced
    if kernel is not None and kernel not in KERNELS:
        raise ValueError(f"scene: kernel must be one of {KERNELS}, got {kernel!r}")
    declared: list[Effect] = []
    if not isinstance(system, Model):
        # a protocol system has its own dynamics: only forces in its own coordinates (actuation)
        # can be added; springs, loads or constraints would need the model's kinematics
        for name, val in (("springs", springs), ("dampers", dampers), ("loads", loads), ("support", support), ("constraints", constraints)):
            if val is not None and val is not False and not (isinstance(val, str) and val == "model"):
                raise ValueError(
                    f"scene: {name} needs a spatial jaxbody.Model; {type(system).__name__} takes gravity and actuation only"
                )
        if gravity is False or gravity is None:
            if not hasattr(system, "gravity"):
                raise ValueError(f"scene: gravity cannot be switched off on {type(system).__name__}")
            # the system's gravity is part of its own dynamics: switching it off edits the system
            system = eqx.tree_at(lambda s: s.gravity, system, jnp.zeros_like(system.gravity))
        elif not (gravity is True or (isinstance(gravity, str) and gravity == "model")):
            raise ValueError("scene: a gravity vector needs a spatial jaxbody.Model; pass True or False")
        if actuation is not None:
            declared.append(_actuation(actuation))
        declared.extend(effects)
        out = SystemScene(system=system, effects=tuple(declared), constraints=own_constraints(system))
        # effects check themselves against the scene they are in (shapes, path), before tracing
        for e in out.effects:
            e.check(out)
        return out

    model = system
    # parameters set after building (eqx.tree_at) get the builder's checks before a solve sees them
    validate_at_boundary(model)
    dtype = model.body_pos.dtype
    if isinstance(constraints, str) and constraints == "model":
        # checked and partitioned at a configuration that closes the loops (qpos0, projected onto
        # them when it does not); a traced model gets the message of _constraint_slot
        constraints = (loop_system(model) if is_concrete(model) else loop_closures(model)) if model.loops else None
    constraints = _constraint_slot(model, constraints)
    # gravity, springs and dampers from the model are declared only when non-zero, so that a
    # model without them traces none of their terms; a traced value might be non-zero: declared
    if gravity is True or (isinstance(gravity, str) and gravity == "model"):
        if not is_concrete(model.gravity) or np.any(np.asarray(model.gravity) != 0) or gravity is True:
            declared.append(Gravity(model.gravity))
    elif gravity is not None and gravity is not False:
        g = jnp.asarray(gravity, dtype)
        if g.shape != (3,):
            raise ValueError(f"scene: gravity must be a bool or a (3,) vector, got shape {g.shape}")
        declared.append(Gravity(g))
    if isinstance(springs, JointSprings):
        declared.append(springs)
    elif isinstance(springs, str) and springs == "model":
        if not is_concrete(model.joint_stiffness) or np.any(np.asarray(model.joint_stiffness) != 0):
            declared.append(JointSprings(model.joint_stiffness, model.qpos_spring))
    elif springs is True:
        declared.append(JointSprings(model.joint_stiffness, model.qpos_spring))
    elif springs is not None and springs is not False:
        declared.append(JointSprings(jnp.asarray(springs, dtype), model.qpos_spring))
    if isinstance(dampers, JointDampers):
        declared.append(dampers)
    elif isinstance(dampers, str) and dampers == "model":
        if not is_concrete(model.dof_damping) or np.any(np.asarray(model.dof_damping) != 0):
            declared.append(JointDampers(model.dof_damping))
    elif dampers is True:
        declared.append(JointDampers(model.dof_damping))
    elif dampers is not None and dampers is not False:
        declared.append(JointDampers(jnp.asarray(dampers, dtype)))
    if actuation is not None:
        declared.append(_actuation(actuation))
    if loads is not None:
        if not (isinstance(loads, BodyLoads) or callable(loads)):
            raise ValueError(f"scene: loads must be a callable wrench(t, q, v) or a BodyLoads, got {type(loads).__name__}")
        declared.append(loads if isinstance(loads, BodyLoads) else BodyLoads(loads))
    if support is not None:
        declared.append(support if isinstance(support, SupportMotion) else SupportMotion(support))
    # further effects last: the declared order is the order of the work vector and of its names
    declared.extend(effects)

    spatial = SpatialScene(system=model, effects=tuple(declared), constraints=constraints, kernel=kernel)
    # loads and constraints are spatial: a scene with either keeps the spatial path. A
    # specialisation must never be slower than the general path: the planar path is JAX code,
    # and a spatial scene whose vector field is one native call runs the same chain about 4x
    # faster (the double pendulum's RK4 steps, benchmarks/planar_choice.py), so when the choice is ours the native kernel wins (and the
    # planarity test, a compiled kinematics pass, is not even run); without it the planar
    # path is the faster one
    native_wins = planar is None and spatial.direct_kernel() == "native"
    planar_ok = planar is not False and loads is None and constraints is None and not native_wins
    # the planar path needs gravity in the plane of motion (a field out of it would be lost)
    grav = [e.vector for e in declared if isinstance(e, Gravity)]
    converted = aligned_system(model, grav[0] if grav else None) if planar_ok else None
    if planar is True and converted is None:
        raise ValueError(
            "scene: planar=True needs hinge joints only (one per body, no armature), parallel axes, "
            "gravity in their plane, and no loads or constraints"
        )
    if converted is not None:
        psys, plane, signs = converted
        out = PlanarScene(system=model, effects=tuple(declared), planar=psys, plane=plane, axis_sign=signs)
    else:
        out = spatial
    for e in out.effects:
        e.check(out)
    return out


def _constraint_slot(model: Model, constraints):
    """Validate the ``constraints`` argument of :func:`scene` (a sequence of Maggi constraints
    is built into a ``ConstrainedSystem`` at ``model.qpos0``)."""
    if constraints is None or constraints is False:
        return None
    if isinstance(constraints, maggi.Constraint):
        constraints = (constraints,)
    if isinstance(constraints, (tuple, list)):
        # the partition is a pivoted QR on concrete values: it cannot be chosen inside a trace
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(model)):
            raise ValueError(
                "scene: constraints are checked and their coordinate partition chosen when the scene is "
                "built, from concrete values; this model's parameters are traced (inside jit, vmap or grad). "
                "Build the scene outside and change its parameters inside with "
                "equinox.tree_at(lambda s: s.system.<field>, scene, value)"
            )
        try:
            # qpos0 is a default, not a state on the constraints: positions are checked at t0
            constraints = maggi.constrain(model, constraints, q_ref=model.qpos0, position_atol=None)
        except ValueError as err:
            raise ValueError(
                f"scene: constraints: {err} (they were checked at model.qpos0; pass "
                "jaxbody.maggi.constrain(model, [...], q_ref=<an admissible q>) instead)"
            ) from None
    # any object with the constraint protocol is accepted (jaxbody.effects.Constraint)
    missing = [n for n in ("accelerations", "drift") if not callable(getattr(constraints, n, None))]
    if missing:
        raise ValueError(
            f"scene: constraints must be a jaxbody.maggi.ConstrainedSystem, a sequence of "
            f"jaxbody.maggi.Constraint or an object with accelerations and drift; "
            f"{type(constraints).__name__} lacks {', '.join(missing)}"
        )
    if isinstance(constraints, maggi.ConstrainedSystem):
        if not isinstance(constraints.base, maggi.ModelBase):
            raise ValueError(
                f"scene: constraints are built on a {type(constraints.base).__name__}, not on a "
                "jaxbody.Model; simulate that ConstrainedSystem directly"
            )
        # built on another model: its rows would index the wrong coordinates
        if (constraints.nq, constraints.nv) != (model.nq, model.nv):
            raise ValueError(
                f"scene: constraints are built on a model with (nq, nv) = ({constraints.nq}, "
                f"{constraints.nv}), the scene's has ({model.nq}, {model.nv})"
            )
    return constraints


def _actuation(actuation) -> Actuation:
    """The :class:`~jaxbody.effects.Actuation` of the ``actuation`` argument of :func:`scene`."""
    if isinstance(actuation, Actuation):
        return actuation
    if isinstance(actuation, tuple) and len(actuation) == 2 and callable(actuation[0]):
        return Actuation(actuation[0], actuation[1])
    if callable(actuation):
        return Actuation(actuation)
    raise ValueError(f"scene: actuation must be callable, a (callable, params) pair or an Actuation, got {type(actuation).__name__}")
