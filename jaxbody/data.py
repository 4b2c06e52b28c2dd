"""The state pytree :class:`Data`: what one state ``(q, v)`` of a model needs, computed once.

:func:`compute_data` runs the stages in order — kinematics (frames, base points, poles,
centres of mass, DoF motions), augmented bodies (spec eqs 5–6) and body velocities — and
every kernel of :mod:`jaxbody.kernels` reads the result: mass matrix, bias forces, inverse and
forward dynamics, joint reactions, energies, passive forces. Constraints, scenes and
identification read the same pytree instead of recomputing the kinematics.

``compute_data`` checks shapes only (before tracing); values are checked once at the API
boundary with :func:`jaxbody.check_inputs`, never here, so it is safe inside a vmapped solver
loop (value checks return result codes inside loops instead of raising).

Example::

    data = jb.compute_data(model, q, v)
    M = jb.kernels.mass_matrix(model, data)
    qacc = jb.kernels.forward_dynamics(model, data, tau, include_passive=True)
"""

import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Float
from ._util import check_shape
from .augmented import AugmentedBodies, augmented_inertia, static_moment, subtree_mass
from .kinematics import Kinematics, body_velocities, forward_kinematics
from .model import Model

__all__ = ["Data", "compute_data"]


class Data(Kinematics):
    """State of a :class:`~jaxbody.Model` at ``(q, v)`` (all vectors in world axes).

    A :class:`~jaxbody.kinematics.Kinematics` extended by the velocity-dependent and augmented
    quantities, so a ``Data`` serves wherever kinematics are expected.

    Attributes:
        q: coordinates ``(nq,)`` (MuJoCo ``qpos`` layout).
        v: velocities ``(nv,)`` (MuJoCo ``qvel`` layout).
        body_rotation: rotation matrix of each body frame (MuJoCo ``xmat``).
        body_position: origin of each body frame (MuJoCo ``xpos``).
        base_point: ``O_0k``, the anchor of body ``k``'s first joint (its origin when welded
            or free).
        pole: ``O_k``, the body-fixed point that coincides with ``O_0k`` at the joint's
            reference.
        com: centre of mass ``C_k`` (MuJoCo ``xipos``).
        central_inertia: ``I_Ck`` about the centre of mass, world axes.
        dof_angular, dof_linear, dof_anchor: unit motion of each DoF: angular velocity
            ``dof_angular[d]``, velocity ``dof_linear[d] + dof_angular[d] × (X - dof_anchor[d])``
            of a point ``X`` of the bodies it moves.
        link: ``R_k = O_0k - O_0,p(k)`` (zero for roots).
        augmented: subtree masses, augmented static moments and inertias about ``O_0k``.
        angular_velocity: ``ω_k``, absolute angular velocity of each body.
        base_point_velocity: velocity of body ``k``'s material point at ``O_0k``.
    """

    q: Float[Array, " nq"]
    v: Float[Array, " nv"]
    link: Float[Array, "n_body 3"]
    augmented: AugmentedBodies
    angular_velocity: Float[Array, "n_body 3"]
    base_point_velocity: Float[Array, "n_body 3"]


def compute_data(
    model: Model, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"] | None = None
) -> Data:
    """Kinematics, augmented bodies and body velocities of ``model`` at ``(q, v)``, once.

    Args:
        model: the model.
        q: coordinates ``(nq,)``.
        v: velocities ``(nv,)``; ``None`` = at rest (enough for the mass matrix, gravity,
            potential energy).

    Returns:
        :class:`Data`.

    Raises:
        ValueError: ``q`` or ``v`` of the wrong shape (before tracing). No value checks:
            see :func:`jaxbody.check_inputs`.
    """
    dtype = model.body_pos.dtype
    q = check_shape(q, (model.nq,), "q", dtype=dtype)
    v = jnp.zeros((model.nv,), dtype) if v is None else check_shape(v, (model.nv,), "v", dtype=dtype)
    tree = model.tree
    with jax.named_scope("kinematics"):
        kin = forward_kinematics(model, q)
    with jax.named_scope("augmented_bodies"):
        par = tree.parent_array
        link = kin.base_point - kin.base_point[np.maximum(par, 0)]
        link = jnp.where(jnp.asarray(par >= 0)[:, None], link, 0.0)
        r = kin.com - kin.base_point
        aug = AugmentedBodies(
            subtree_mass=subtree_mass(tree, model.body_mass),
            static_moment=static_moment(tree, model.body_mass, r, link),
            augmented_inertia=augmented_inertia(tree, model.body_mass, kin.central_inertia, r, link),
        )
    with jax.named_scope("body_velocities"):
        w, u = body_velocities(model, kin, v)
    return Data(
        q=q,
        v=v,
        body_rotation=kin.body_rotation,
        body_position=kin.body_position,
        base_point=kin.base_point,
        pole=kin.pole,
        com=kin.com,
        central_inertia=kin.central_inertia,
        dof_angular=kin.dof_angular,
        dof_linear=kin.dof_linear,
        dof_anchor=kin.dof_anchor,
        link=link,
        augmented=aug,
        angular_velocity=w,
        base_point_velocity=u,
    )
