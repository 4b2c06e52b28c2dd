"""What balancing reads off a planar system or a model: which bodies move and must be
balanced, their static moments and inertias in body axes, and the reach of each link."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .. import planar
from .._util import quat_to_matrix
from ..dynamics import augmented_bodies
from ..kinematics import forward_kinematics
from ..model import Model

__all__ = [
    "is_planar", "check_system", "dimension", "moving_bodies", "joint_anchors", "static_moments",
    "inertia_measure", "required_bodies", "body_names", "resolve_bodies", "link_reach", "link_length",
]


def is_planar(system) -> bool:
    """Whether ``system`` is a planar system (else a spatial :class:`Model`)."""
    return isinstance(system, planar.PlanarSystem)


def check_system(system):
    """Raise ``TypeError`` unless ``system`` is a planar system or a :class:`Model`."""
    if not (is_planar(system) or isinstance(system, Model)):
        raise TypeError(
            f"balancing needs a planar system (jaxbody.planar) or a jaxbody.Model, got {type(system).__name__}"
        )


def dimension(system) -> int:
    """2 for a planar system, 3 for a model: the length of positions and static moments."""
    return 2 if is_planar(system) else 3


def moving_bodies(model: Model) -> np.ndarray:
    """``(n,)`` bool: bodies with a joint of their own or carried by a body that has one."""
    joints = np.asarray(model.joints.body_joint_count) > 0
    carriers = model.tree.carrier_mask  # [i, k]: i carries k
    return joints | (carriers & joints[:, None]).any(axis=0)


def joint_anchors(model: Model) -> np.ndarray:
    """Base point of each body in its own frame: the anchor of its first joint (else origin)."""
    first = np.asarray(model.joints.body_first_joint)
    jp = np.asarray(model.joint_pos)
    return np.where((first >= 0)[:, None], jp[np.maximum(first, 0)], 0.0)


def static_moments(system, q=None):
    """Static moments ``m̄_k`` of the augmented bodies in body axes, about each base point.

    Planar systems: configuration independent (:func:`jaxbody.planar.augmented_bodies`),
    ``(n, 2)``. Models: from :func:`jaxbody.augmented_bodies` at ``q`` (default ``qpos0``)
    rotated into body axes, ``(n, 3)`` (configuration independent for hinge and ball trees).
    """
    check_system(system)
    return _static_moments(system, q)


@eqx.filter_jit
def _static_moments(system, q=None):
    """Static moments ``m̄_k`` of the augmented bodies in body axes, about each base point.

    Planar systems: configuration independent (:func:`jaxbody.planar.augmented_bodies`),
    ``(n, 2)``. Models: from :func:`jaxbody.augmented_bodies` at ``q`` (default ``qpos0``)
    rotated into body axes, ``(n, 3)`` (configuration independent for hinge and ball trees).
    """
    check_system(system)
    if is_planar(system):
        return planar.augmented_bodies_in_body_axes(system).static_moment
    q = system.qpos0 if q is None else jnp.asarray(q)
    rot = forward_kinematics(system, q).body_rotation
    return jnp.einsum("nji,nj->ni", rot, augmented_bodies(system, q).static_moment)


def inertia_measure(system):
    """Per body: planar ``J_k``; spatial trace of the augmented inertia (rotation invariant)."""
    if is_planar(system):
        return planar.augmented_bodies_in_body_axes(system).augmented_inertia
    I = augmented_bodies(system, system.qpos0).augmented_inertia
    return jnp.trace(I, axis1=-2, axis2=-1)


def required_bodies(system) -> tuple[int, ...]:
    """Bodies whose ``m̄_k`` must vanish for decoupling (the corrected Cor. 8).

    Planar: every body with a carrier on a fixed base; every body on a translating base.
    Models: every moving body with a moving carrier; every moving body when a root body is
    free-floating.
    """
    check_system(system)
    if is_planar(system):
        if system.translating_base:
            return tuple(range(system.n_body))
        return tuple(int(k) for k in np.nonzero(~system.tree.is_root)[0])
    moving = moving_bodies(system)
    carriers = system.tree.carrier_mask
    free_root = any(system.joints.body_is_free[k] for k in range(system.n_body) if system.tree.parent[k] < 0)
    out = []
    for k in range(system.n_body):
        if not moving[k] or system.joints.body_joint_count[k] == 0:
            continue
        if free_root or (carriers[:, k] & moving).any():
            out.append(k)
    return tuple(out)


def body_names(system):
    """The names of the bodies, in body order."""
    return system.tree.names


def resolve_bodies(system, bodies, what):
    """Bodies given by index or name, ``"all"`` or ``None`` -> sorted body indices.

    ``None``: :func:`required_bodies`; ``"all"``: every body (planar) or every moving body
    with a joint (models). ``what`` names the argument in the error message.

    Raises:
        ValueError: an unknown name, an index out of range or another string than ``"all"``.
    """
    n = system.n_body
    if bodies is None:
        return required_bodies(system)
    if isinstance(bodies, str):
        if bodies == "all":
            if is_planar(system):
                return tuple(range(n))
            return tuple(int(k) for k in np.nonzero(moving_bodies(system))[0] if system.joints.body_joint_count[k] > 0)
        raise ValueError(f"{what} must be a list of bodies, 'all' or None, got {bodies!r}")
    out = []
    for b in bodies:
        if isinstance(b, str):
            if b not in body_names(system):
                raise ValueError(f"{what}: no body named {b!r}; bodies: {list(body_names(system))}")
            b = body_names(system).index(b)
        b = int(b)
        if not 0 <= b < n:
            raise ValueError(f"{what}: body index {b} out of range (0..{n - 1})")
        out.append(b)
    return tuple(sorted(set(out)))


def link_reach(system) -> tuple[np.ndarray, np.ndarray]:
    """Per body: its base point and the vector from it to the farthest of its CM and its
    children's joints (the link's own reach), ``(n, dim)`` each."""
    n = system.n_body
    if is_planar(system):
        com = np.asarray(system.body_com)
        hinge = np.asarray(system.hinge_pos)
        anchor = np.zeros((n, 2))
        child_pts = [(k, hinge[j]) for j in range(n) for k in [system.tree.parent[j]] if k >= 0]
    else:
        com = np.asarray(system.body_com)
        anchor = joint_anchors(system)
        # a child's joint anchor in the parent's frame at the reference configuration
        pos, quat = np.asarray(system.body_pos), np.asarray(system.body_quat)
        child_pts = [(system.tree.parent[j], pos[j] + np.asarray(quat_to_matrix(quat[j])) @ anchor[j])
                     for j in range(n) if system.tree.parent[j] >= 0]
    vec = com - anchor
    for k, pt in child_pts:
        if np.linalg.norm(pt - anchor[k]) > np.linalg.norm(vec[k]):
            vec[k] = pt - anchor[k]
    return anchor, vec


def link_length(system) -> np.ndarray:
    """Per body: the farthest of its CM and its children's joints from its own base point."""
    L = np.linalg.norm(link_reach(system)[1], axis=1)
    return np.where(L > 0, L, 1.0)
