"""The planar system of a model whose hinges are parallel: the conversion the planar path runs on.

Decided once, when the scene is built, from concrete values: a model whose parameters are
traced (a scene built inside ``jit``) keeps the spatial path, which computes the same dynamics.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import planar
from ..joints import HINGE
from ..kinematics import forward_kinematics
from ..model import Model

__all__ = ["planar_from_model", "is_concrete"]


def is_concrete(*xs) -> bool:
    """Whether no leaf of ``xs`` is traced (a structural choice can be made from it now)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(xs))


def planar_from_model(model: Model, gravity=None, tol: float = 1e-9):
    """The planar system of a model whose hinges are parallel, or ``None``.

    Body axes of the planar system coincide with the plane basis ``(e1, e2)`` at the reference
    configuration ``qpos0``, so the absolute angle of body ``k`` is
    ``θ_k = Σ_{j on the path to k} s_j (q_j − q0_j)`` with ``s_j = ±1`` the sense of hinge ``j``
    about the plane normal ``n``. Returns ``(system, plane (2, 3), signs)``.
    """
    joints = model.joints
    if model.n_body == 0 or model.n_joint != model.n_body:
        return None
    if any(int(k) != HINGE for k in joints.type) or list(joints.body) != list(range(model.n_body)):
        return None
    if not is_concrete(model):
        return None
    # armature is a rotor inertia about the joint axis, which the absolute-angle equations lack
    if np.any(np.asarray(model.dof_armature) != 0):
        return None
    # concrete model: evaluate now even when the scene is built inside a jit trace
    with jax.ensure_compile_time_eval():
        return _planar_conversion(model, gravity, tol)


def _planar_conversion(model, gravity, tol):
    """:func:`jaxbody.planar.from_model` of the same mechanism with every hinge turned to
    point along the plane normal ``n`` (``s_j`` records the turn), without its springs and
    dampers (they are effects of the scene) and without gravity (an effect too)."""
    kin = forward_kinematics(model, model.qpos0)
    axes = np.asarray(kin.dof_angular)
    axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    n = axes[0]
    if np.any(np.linalg.norm(np.cross(axes, n), axis=-1) > tol):
        return None
    signs = np.sign(axes @ n)
    # a traced gravity might leave the plane: only a concrete one can be checked to lie in it
    if gravity is not None and not is_concrete(gravity):
        return None
    g = np.zeros(3) if gravity is None else np.asarray(gravity, dtype=float)
    gn = np.linalg.norm(g)
    if gn > 0 and abs(g @ n) > tol * gn:
        return None
    dtype = model.body_pos.dtype
    aligned = eqx.tree_at(
        lambda m: (m.joint_axis, m.dof_damping, m.joint_stiffness, m.gravity),
        model,
        (
            model.joint_axis * jnp.asarray(signs, dtype)[:, None],
            jnp.zeros_like(model.dof_damping),
            jnp.zeros_like(model.joint_stiffness),
            jnp.asarray(g, dtype),
        ),
    )
    try:
        converted = planar.from_model(aligned, atol=tol)
    except ValueError:
        # not a valid planar system (e.g. bad parameters): the spatial path and the boundary
        # checks of simulate report what is wrong, in the model's own terms
        return None
    system = eqx.tree_at(lambda s: s.gravity, converted, jnp.zeros(2, dtype))
    plane = jnp.asarray(planar.plane_basis(n, g), dtype)
    return system, plane, tuple(float(s) for s in signs)
