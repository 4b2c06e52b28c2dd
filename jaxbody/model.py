"""The :class:`Model`: static topology plus physical parameters as a JAX pytree.

Conventions follow MuJoCo so that an imported MJCF model compares one-to-one:

* body ``k`` of jaxbody is MuJoCo body ``k + 1`` (the world body is implicit);
* ``body_pos``/``body_quat`` place the body frame in the parent's frame at the reference
  configuration (joints at ``qpos0``); quaternions are (w, x, y, z);
* ``body_com`` is the centre of mass in the body frame and ``body_inertia`` the full inertia
  tensor about the centre of mass in body axes (MuJoCo's ``body_iquat``/``body_inertia``
  combined);
* ``joint_pos``/``joint_axis`` are the anchor and axis in the body frame; ``qpos0`` is the
  reference configuration (hinge/slide ``ref``; identity quaternions; free body pose);
* ``qpos_spring`` is the spring reference of joint springs (``springref``).

Static structure (:class:`~jaxbody.tree.BodyTree`, :class:`~jaxbody.joints.JointLayout`)
lives in static fields; every physical parameter is a traced array, so ``jax.grad`` reaches
masses, centres of mass, inertias, offsets and axes.

A :class:`Model` is data only: the dynamics live in :mod:`jaxbody.kernels` (``(model, data)``
functions) and :func:`jaxbody.scene`, whose :class:`~jaxbody.Scene` of a model provides
``qdot``, ``acceleration`` and ``total_energy`` (what :func:`jaxbody.simulate` integrates; it
wraps a model into a scene itself).
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, Float, ScalarLike, VectorLike
from .joints import FREE, HINGE, JOINT_KIND_NAMES, JOINT_KINDS, SLIDE, JointLayout, JointSpec
from .loops import LoopSpec
from .tree import BodyTree
from .validation import validate_parameters

__all__ = ["LoopSpec", "Model", "ModelBuilder", "validate_parameters"]


class Model(eqx.Module):
    """A rigid-body tree with joints (see the module docstring for conventions)."""

    tree: BodyTree = eqx.field(static=True)
    joints: JointLayout = eqx.field(static=True)
    body_pos: Float[Array, "n_body 3"]
    body_quat: Float[Array, "n_body 4"]
    body_mass: Float[Array, " n_body"]
    body_com: Float[Array, "n_body 3"]
    body_inertia: Float[Array, "n_body 3 3"]
    joint_pos: Float[Array, "n_joint 3"]
    joint_axis: Float[Array, "n_joint 3"]
    joint_stiffness: Float[Array, " n_joint"]
    dof_armature: Float[Array, " nv"]
    dof_damping: Float[Array, " nv"]
    qpos0: Float[Array, " nq"]
    qpos_spring: Float[Array, " nq"]
    gravity: Float[Array, "3"]
    keyframe_qpos: Float[Array, "n_key nq"]
    keyframe_qvel: Float[Array, "n_key nv"]
    keyframe_names: tuple[str, ...] = eqx.field(static=True, default=())
    name: str = eqx.field(static=True, default="model")
    #: Loop closures that make the tree a closed mechanism (from MJCF ``<connect>``). The tree
    #: dynamics (``forward_dynamics``, :func:`jaxbody.backends.acceleration`) ignore them; scenes impose them as
    #: Maggi constraints (``jb.scene(model)``, ``jb.simulate(model, ...)``).
    loops: tuple[LoopSpec, ...] = eqx.field(static=True, default=())

    @property
    def n_body(self) -> int:
        return self.tree.n_body

    @property
    def n_joint(self) -> int:
        return self.joints.n_joint

    @property
    def nq(self) -> int:
        return self.joints.nq

    @property
    def nv(self) -> int:
        return self.joints.nv

    @property
    def body_names(self) -> tuple[str, ...]:
        return self.tree.names

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.joints.names

    def body_index(self, name: str) -> int:
        try:
            return self.tree.names.index(name)
        except ValueError:
            raise KeyError(f"no body named {name!r}; bodies: {list(self.tree.names)}") from None

    def joint_index(self, name: str) -> int:
        try:
            return self.joints.names.index(name)
        except ValueError:
            raise KeyError(f"no joint named {name!r}; joints: {list(self.joints.names)}") from None

    def keyframe(self, name: str):
        """``(qpos, qvel)`` of a named keyframe."""
        try:
            i = self.keyframe_names.index(name)
        except ValueError:
            raise KeyError(f"no keyframe named {name!r}; keyframes: {list(self.keyframe_names)}") from None
        return self.keyframe_qpos[i], self.keyframe_qvel[i]

    def __repr__(self):
        loops = f", loops={len(self.loops)}" if self.loops else ""
        return (
            f"Model({self.name!r}: n_body={self.n_body}, n_joint={self.n_joint}, "
            f"nq={self.nq}, nv={self.nv}{loops})"
        )


def _concrete(value, what):
    """``value`` unless it holds a traced value (the builder called inside ``jax.jit``, ``vmap``
    or ``grad`` with a traced argument): a ``ValueError`` naming ``what`` then, where NumPy would
    raise JAX's TracerArrayConversionError."""
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(value)):
        raise ValueError(
            f"{what} is a traced value (the model is being built inside jax.jit, vmap or grad from a traced "
            "argument): a model's structure and its checks need concrete numbers; build the model outside the "
            "traced function and pass the values to trace into it with eqx.tree_at, e.g. "
            "eqx.tree_at(lambda m: m.body_mass, model, masses)"
        )
    return value


def _check_finite(value, what):
    a = np.asarray(_concrete(value, what), dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} is not finite (NaN or inf): {a.tolist()}")
    return a


class ModelBuilder:
    """Programmatic construction of a :class:`Model`.

    Example::

        b = jb.ModelBuilder(gravity=(0, 0, -9.81))
        b.add_body("upper", mass=1.0, com=(0, 0, -0.25), inertia=(0.02, 0.02, 0.001),
                   joints=[jb.Hinge(axis=(0, 1, 0))])
        b.add_body("lower", parent="upper", pos=(0, 0, -0.5), mass=0.5,
                   com=(0, 0, -0.2), inertia=(0.01, 0.01, 0.001), joints=[jb.Hinge(axis=(0, 1, 0))])
        model = b.build()

    ``inertia`` is the central inertia in body axes: 3 principal moments (diagonal), 6 values
    ``(xx, yy, zz, xy, xz, yz)`` (MJCF ``fullinertia``) or a 3×3 matrix.
    """

    def __init__(self, gravity: VectorLike = (0.0, 0.0, -9.81), name: str = "model"):
        self.gravity = _check_finite(gravity, "gravity")
        self.name = name
        self._bodies: list[dict] = []

    def add_body(
        self,
        name: str,
        parent: str | int | None = None,
        *,
        pos: VectorLike = (0.0, 0.0, 0.0),
        quat: VectorLike = (1.0, 0.0, 0.0, 0.0),
        mass: ScalarLike = 0.0,
        com: VectorLike = (0.0, 0.0, 0.0),
        inertia=(0.0, 0.0, 0.0),
        joints: Sequence = (),
    ) -> int:
        """Add a body; returns its index. ``parent`` is a name, an index or None (world)."""
        names = [b["name"] for b in self._bodies]
        if name in names:
            raise ValueError(f"body {name!r} is defined twice")
        if parent is None:
            pidx = -1
        elif isinstance(parent, str):
            if parent not in names:
                raise ValueError(f"body {name!r}: unknown parent body {parent!r}")
            pidx = names.index(parent)
        else:
            pidx = int(parent)
            if not -1 <= pidx < len(names):
                raise ValueError(f"body {name!r}: unknown parent index {pidx}")
        I = np.asarray(_concrete(inertia, f"body {name!r} inertia"), dtype=np.float64)
        if I.shape == (3,):
            I = np.diag(I)
        elif I.shape == (6,):
            xx, yy, zz, xy, xz, yz = I
            I = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
        elif I.shape != (3, 3):
            raise ValueError(
                f"body {name!r}: inertia must have 3, 6 or 3x3 values, got shape {I.shape}"
            )
        quat = _check_finite(quat, f"body {name!r} quat")
        if quat.shape != (4,) or not np.linalg.norm(quat) > 1e-12:
            raise ValueError(f"body {name!r}: quat must be a non-zero quaternion (w, x, y, z), got {quat.tolist()}")
        for j in joints:
            if not isinstance(j, JointSpec):
                raise ValueError(f"body {name!r}: joints must be Hinge/Slide/Ball/Free, got {j!r}")
        self._bodies.append(
            dict(
                name=name, parent=pidx, pos=_check_finite(pos, f"body {name!r} pos"),
                quat=quat,
                mass=float(_check_finite(mass, f"body {name!r} mass")),
                com=_check_finite(com, f"body {name!r} com"), inertia=I, joints=list(joints),
            )
        )
        return len(self._bodies) - 1

    # called inside a traced function (a jit that builds its model from numbers), the model is a
    # constant of the program: its arrays are made, and checked, now rather than staged into it
    @jax.ensure_compile_time_eval()
    def build(self, dtype=None, *, traversal: str | None = None) -> Model:
        """Validate and return the :class:`Model` (raises ``ValueError`` naming the culprit).

        Inside ``jax.jit`` (or ``vmap``, ``grad``) the builder gives the same model, a constant of
        the traced program; its inputs must be numbers, not traced values (a ``ValueError`` names
        the field; trace parameters by setting them on the built model with ``eqx.tree_at``).

        Args:
            dtype: floating dtype of the parameters (default: JAX's default float).
            traversal: how subtree and path sums run, ``"dense"`` or ``"segment"``
                (:class:`~jaxbody.BodyTree`; ``None``: chosen from the number of bodies).
        """
        bodies = self._bodies
        if not bodies:
            raise ValueError("model has no bodies")
        tree = BodyTree([b["parent"] for b in bodies], [b["name"] for b in bodies], traversal)
        jt, jb_, jnames, jpos, jaxis, jstiff = [], [], [], [], [], []
        arm, damp, q0, qs = [], [], [], []
        for k, b in enumerate(bodies):
            for i, j in enumerate(b["joints"]):
                jt.append(j.kind)
                jb_.append(k)
                jnames.append(j.name or f"{b['name']}_{JOINT_KIND_NAMES[j.kind]}{i}")
                jpos.append(_check_finite(j.pos, f"joint {jnames[-1]!r} of body {b['name']!r} pos"))
                ax = _check_finite(j.axis, f"joint {jnames[-1]!r} of body {b['name']!r} axis")
                nrm = np.linalg.norm(ax)
                if j.kind in (HINGE, SLIDE) and nrm < 1e-12:
                    raise ValueError(f"joint {jnames[-1]!r} of body {b['name']!r}: axis is zero")
                jaxis.append(ax / nrm if nrm > 0 else ax)
                scalar = lambda field: float(_concrete(getattr(j, field), f"joint {jnames[-1]!r} {field}"))
                jstiff.append(scalar("stiffness"))
                kind = JOINT_KINDS[j.kind]
                arm += [scalar("armature")] * kind.nv
                damp += [scalar("damping")] * kind.nv
                if kind.quaternion is None:
                    q0.append(scalar("ref"))
                    qs.append(scalar("springref"))
                elif kind.code != FREE:
                    q0 += [1.0, 0.0, 0.0, 0.0]
                    qs += [1.0, 0.0, 0.0, 0.0]
                else:
                    pose = list(b["pos"]) + list(np.asarray(b["quat"]) / np.linalg.norm(b["quat"]))
                    q0 += pose
                    qs += pose
        layout = JointLayout(tree, jt, jb_, jnames)
        assert len(q0) == layout.nq and len(arm) == layout.nv
        f = dtype or jnp.result_type(float)
        arr = lambda x, shape: jnp.asarray(np.asarray(x, dtype=np.float64).reshape(shape), dtype=f)
        nb, nj = tree.n_body, layout.n_joint
        model = Model(
            tree=tree,
            joints=layout,
            body_pos=arr([b["pos"] for b in bodies], (nb, 3)),
            body_quat=arr([np.asarray(b["quat"]) / np.linalg.norm(b["quat"]) for b in bodies], (nb, 4)),
            body_mass=arr([b["mass"] for b in bodies], (nb,)),
            body_com=arr([b["com"] for b in bodies], (nb, 3)),
            body_inertia=arr([b["inertia"] for b in bodies], (nb, 3, 3)),
            joint_pos=arr(jpos, (nj, 3)),
            joint_axis=arr(jaxis, (nj, 3)),
            joint_stiffness=arr(jstiff, (nj,)),
            dof_armature=arr(arm, (layout.nv,)),
            dof_damping=arr(damp, (layout.nv,)),
            qpos0=arr(q0, (layout.nq,)),
            qpos_spring=arr(qs, (layout.nq,)),
            gravity=arr(self.gravity, (3,)),
            keyframe_qpos=jnp.zeros((0, layout.nq), f),
            keyframe_qvel=jnp.zeros((0, layout.nv), f),
            name=self.name,
        )
        validate_parameters(model)
        return model
