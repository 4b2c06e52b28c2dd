"""From a spatial model to a planar system: the planarity test, the plane's axes and the
conversion.

A spatial :class:`~jaxbody.Model` is a planar mechanism when every body carries exactly one
joint, a hinge, without armature, all hinge axes are parallel at the reference configuration
``qpos0`` and gravity lies in the plane normal to them. :func:`planarity` is the one test of
that; :func:`from_model` (the public converter, strict: it names what is wrong) and
:func:`aligned_system` (the planar path of a scene: ``None`` when the test fails) both use it.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._util import is_concrete
from ..joints import HINGE
from ..kinematics import forward_kinematics
from .system import PlanarSystem, from_parents

__all__ = ["NotPlanar", "planarity", "plane_basis", "from_model", "aligned_system"]

_JOINT_KINDS = ["free", "ball", "slide", "hinge"]


class NotPlanar(ValueError):
    """A model that is not a planar mechanism; the message names the body, joint or field at fault."""


def planarity(model, gravity=None, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """The planarity test of a spatial model; returns its plane normal and the hinges' senses.

    The model is a planar mechanism when every body carries exactly one joint, a hinge (bodies
    and joints in the same order); no DoF has armature; at ``qpos0`` the axes of all hinges, in
    world axes, are parallel to the first one ``n`` within ``tol`` (in either sense,
    ``s_j = sign(axis_j · n)``); and ``gravity`` (a 3-vector, or ``None`` for none) lies in the
    plane normal to ``n`` within ``tol · |g|``. Runs on concrete values.

    Returns:
        ``(n, s)``: the unit normal ``(3,)`` and the senses ``(n_joint,)`` (``±1``).

    Raises:
        NotPlanar: naming the first body, joint or field that breaks the test.
    """
    joints, names = model.joints, model.body_names
    if model.n_body == 0:
        raise NotPlanar("planar.from_model: the model has no bodies")
    for k in range(model.n_body):
        count = joints.body_joint_count[k]
        if count != 1 or joints.type[joints.body_first_joint[k]] != HINGE:
            raise NotPlanar(
                f"planar.from_model: body {k} ({names[k]!r}) must carry exactly one hinge joint "
                f"(it has {count} joint(s)"
                + (f", the first a {_JOINT_KINDS[joints.type[joints.body_first_joint[k]]]}" if count else "")
                + ")"
            )
    if list(joints.body) != list(range(model.n_body)):
        raise NotPlanar("planar.from_model: the joints must be listed in the order of their bodies")
    armature = np.asarray(model.dof_armature)
    if np.any(armature != 0):
        j = int(np.nonzero(armature != 0)[0][0])
        raise NotPlanar(
            f"planar.from_model: joint {j} ({model.joint_names[j]!r}) has dof_armature "
            f"{float(armature[j])}; a planar system has no armature, damping or stiffness"
        )
    kin = forward_kinematics(model, model.qpos0)
    axes = np.asarray(kin.dof_angular)
    axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    n = axes[0]
    off = np.linalg.norm(np.cross(axes, n), axis=-1) > tol
    if np.any(off):
        raise NotPlanar(_axis_message(model, axes, n, int(np.nonzero(off)[0][0]), "parallel"))
    signs = np.sign(axes @ n)
    g = np.zeros(3) if gravity is None else np.asarray(gravity, dtype=float)
    gn = np.linalg.norm(g)
    if gn > 0 and abs(g @ n) > tol * gn:
        raise NotPlanar(
            f"planar.from_model: gravity {g.tolist()} is not in the plane of motion (normal "
            f"{n.round(12).tolist()})"
        )
    return n, signs


def _axis_message(model, axes, n, j, requirement):
    return (
        f"planar.from_model: the axis of joint {j} ({model.joint_names[j]!r}) is "
        f"{axes[j].round(12).tolist()} in world axes, not {n.round(12).tolist()} like joint 0: "
        f"all hinges must be {requirement}"
    )


def plane_basis(normal, gravity) -> np.ndarray:
    """Rows ``(e_1, e_2)`` of the plane of motion normal to ``normal``, in world axes.

    ``e_2 = −g/|g|`` points up (any direction normal to ``normal`` when there is no gravity)
    and ``e_1 = e_2 × n``, so angles in the plane are counter-clockwise about ``n``. The one
    choice of axes used by :func:`from_model` and by scenes that run on the planar path.
    """
    n = np.asarray(normal, dtype=np.float64)
    g = np.asarray(gravity, dtype=np.float64)
    if np.linalg.norm(g) > 0:
        e2 = -g / np.linalg.norm(g)
    else:
        e2 = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
        e2 /= np.linalg.norm(e2)
    return np.stack([np.cross(e2, n), e2])


def _convert(model, n) -> PlanarSystem:
    """The planar system of a model that passed :func:`planarity` with every hinge along ``n``."""
    g = np.asarray(model.gravity, dtype=np.float64)
    kin = forward_kinematics(model, model.qpos0)
    P = plane_basis(n, g)  # world -> plane
    hinge = np.asarray(kin.base_point, dtype=np.float64)
    com = np.asarray(kin.com, dtype=np.float64)
    par = model.tree.parent_array
    rel = hinge - np.where(par[:, None] >= 0, hinge[np.maximum(par, 0)], 0.0)
    inertia = np.einsum("i,nij,j->n", n, np.asarray(kin.central_inertia, dtype=np.float64), n)
    dtype = model.body_mass.dtype
    return from_parents(
        model.tree.parent,
        np.asarray(model.body_mass, dtype=np.float64).astype(dtype),
        ((com - hinge) @ P.T).astype(dtype),
        (rel @ P.T).astype(dtype),
        inertia.astype(dtype),
        gravity=(P @ g).astype(dtype),
        names=model.body_names,
    )


def from_model(model, *, atol: float = 1e-9) -> PlanarSystem:
    """The planar system of a spatial :class:`~jaxbody.Model` whose hinges are all parallel.

    Requirements (each failure names the body or joint): :func:`planarity` with the model's
    gravity and ``atol``; all hinges point the same way ``n``; no damping or stiffness (a
    planar system has none).

    The plane gets the axes ``e_2 = −g/|g|`` (up; any direction normal to ``n`` without
    gravity) and ``e_1 = e_2 × n``, so angles are counter-clockwise about ``n``. Body ``k``'s
    planar axes coincide with ``(e_1, e_2)`` at ``qpos0``; its hinge ``O_k`` is its joint
    anchor; positions are projected on the plane (offsets along ``n`` do not enter the
    planar dynamics), and ``I_Ck`` is ``n·I_Ck n``.

    Coordinates: the joint angles of the model map to the absolute angles of the planar
    system by ``θ = jaxbody.planar.relative_to_absolute(system, q - model.qpos0)`` (and
    ``v`` likewise, without the offset); drives are the same hinge torques. So
    ``jaxbody.planar.joint_mass_matrix(system, θ)`` equals ``jaxbody.mass_matrix(model, q)``.

    Raises:
        ValueError: the model is not such a planar mechanism.
    """
    n, signs = planarity(model, model.gravity, atol)
    for field in ("dof_damping", "joint_stiffness"):
        values = np.asarray(getattr(model, field))
        if np.any(values != 0):
            j = int(np.nonzero(values != 0)[0][0])
            raise ValueError(
                f"planar.from_model: joint {j} ({model.joint_names[j]!r}) has {field} "
                f"{float(values[j])}; a planar system has no armature, damping or stiffness"
            )
    if np.any(signs < 0):
        kin = forward_kinematics(model, model.qpos0)
        axes = np.asarray(kin.dof_angular)
        axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
        raise ValueError(_axis_message(model, axes, n, int(np.nonzero(signs < 0)[0][0]),
                                       "parallel and point the same way"))
    return _convert(model, n)


def aligned_system(model, gravity=None, tol: float = 1e-9):
    """The planar system of a model whose hinges are parallel, for a scene's planar path; or ``None``.

    Body axes of the planar system coincide with the plane basis ``(e1, e2)`` at the reference
    configuration ``qpos0``, so the absolute angle of body ``k`` is
    ``θ_k = Σ_{j on the path to k} s_j (q_j − q0_j)`` with ``s_j = ±1`` the sense of hinge ``j``
    about the plane normal ``n``. The system is the mechanism with every hinge turned to point
    along ``n`` (``s_j`` records the turn), without its springs and dampers (they are effects of
    the scene) and without gravity (an effect too). ``None`` when the model fails
    :func:`planarity` with ``gravity`` (the scene's), when the model or gravity is traced, or
    when the converted parameters are not a valid planar system (the spatial path and the
    boundary checks of simulate then report what is wrong, in the model's own terms).

    Returns:
        ``(system, plane (2, 3), signs)`` or ``None``.
    """
    if not is_concrete(model) or (gravity is not None and not is_concrete(gravity)):
        return None
    # concrete model: evaluate now even when the scene is built inside a jit trace
    with jax.ensure_compile_time_eval():
        try:
            n, signs = planarity(model, gravity, tol)
        except NotPlanar:
            return None
        g = np.zeros(3) if gravity is None else np.asarray(gravity, dtype=float)
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
            converted = _convert(aligned, n)
        except ValueError:
            return None
        system = eqx.tree_at(lambda s: s.gravity, converted, jnp.zeros(2, dtype))
        plane = jnp.asarray(plane_basis(n, g), dtype)
        return system, plane, tuple(float(s) for s in signs)
