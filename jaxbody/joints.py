"""Joint kinds and the static joint/DoF layout (MuJoCo qpos/qvel conventions).

Joint kinds carry MuJoCo's ``mjtJoint`` numbers so models imported from MJCF keep their
codes. A body may carry several joints (applied in order, as in MuJoCo); a body with no
joint is welded to its parent.

========  ====  ====  ==========================================================
kind      nq    nv    velocity
========  ====  ====  ==========================================================
free      7     6     linear velocity of the body origin (world), angular (body)
ball      4     3     relative angular velocity in the body frame
slide     1     1     displacement rate along the axis
hinge     1     1     rotation rate about the axis
========  ====  ====  ==========================================================

:class:`JointLayout` holds every static index array the dynamics need (DoF addresses, the
"DoF supports body" pairs, the "DoF comes before DoF" pairs used for axis derivatives, and
the frame tree used by the kinematics) as tuples of Python ints: hashable, computed once.
"""

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._types import ScalarLike, VectorLike
from ._util import index, int_tuple
from .tree import BodyTree, mask_module

__all__ = [
    "JointSpec",
    "FREE",
    "BALL",
    "SLIDE",
    "HINGE",
    "JointKind",
    "JOINT_KINDS",
    "JOINT_KIND_NAMES",
    "JOINT_NQ",
    "JOINT_NV",
    "Free",
    "Ball",
    "Slide",
    "Hinge",
    "JointLayout",
]

FREE, BALL, SLIDE, HINGE = 0, 1, 2, 3


@dataclasses.dataclass(frozen=True)
class JointKind:
    """Static description of one joint kind: the table every per-kind dispatch reads.

    Attributes:
        code: MuJoCo ``mjtJoint`` number.
        name: ``"free"``, ``"ball"``, ``"slide"`` or ``"hinge"``.
        nq, nv: sizes in ``q`` and ``v``.
        translation: number of leading translational coordinates (``q = v`` for them).
        quaternion: offset in ``q`` of the joint's unit quaternion, ``None`` if it has none.
        dof_is_rotation: per DoF, 1 if it rotates the body (hinge, ball, free rotation).
        dof_component: per DoF, the axis index of a ball/free DoF (0 for hinge and slide).
    """

    code: int
    name: str
    nq: int
    nv: int
    translation: int
    quaternion: int | None
    dof_is_rotation: tuple[int, ...]
    dof_component: tuple[int, ...]


#: the per-kind table, in the order every dispatch loop visits the kinds
JOINT_KINDS = {
    HINGE: JointKind(HINGE, "hinge", 1, 1, 0, None, (1,), (0,)),
    SLIDE: JointKind(SLIDE, "slide", 1, 1, 1, None, (0,), (0,)),
    BALL: JointKind(BALL, "ball", 4, 3, 0, 0, (1, 1, 1), (0, 1, 2)),
    FREE: JointKind(FREE, "free", 7, 6, 3, 3, (0, 0, 0, 1, 1, 1), (0, 1, 2, 0, 1, 2)),
}
JOINT_KIND_NAMES = {c: k.name for c, k in JOINT_KINDS.items()}
JOINT_NQ = {c: k.nq for c, k in JOINT_KINDS.items()}
JOINT_NV = {c: k.nv for c, k in JOINT_KINDS.items()}


@dataclasses.dataclass(frozen=True)
class JointSpec:
    """Common fields of a joint description used by :class:`jaxbody.ModelBuilder`.

    ``pos`` is the joint anchor and ``axis`` the joint axis, both in the body frame (as in
    MJCF). ``stiffness`` acts towards ``springref``; ``damping`` and ``armature`` act per DoF.
    """

    name: str | None = None
    pos: VectorLike = (0.0, 0.0, 0.0)
    axis: VectorLike = (0.0, 0.0, 1.0)
    armature: ScalarLike = 0.0
    damping: ScalarLike = 0.0
    stiffness: ScalarLike = 0.0

    kind: int = dataclasses.field(default=-1, init=False)


@dataclasses.dataclass(frozen=True)
class Hinge(JointSpec):
    """Rotation about ``axis`` through ``pos``; ``ref`` is the angle of the reference pose."""

    ref: ScalarLike = 0.0
    springref: ScalarLike = 0.0
    kind: int = dataclasses.field(default=HINGE, init=False)


@dataclasses.dataclass(frozen=True)
class Slide(JointSpec):
    """Translation along ``axis``; ``ref`` is the displacement of the reference pose."""

    ref: ScalarLike = 0.0
    springref: ScalarLike = 0.0
    kind: int = dataclasses.field(default=SLIDE, init=False)


@dataclasses.dataclass(frozen=True)
class Ball(JointSpec):
    """Spherical joint about ``pos``; q is a unit quaternion (w, x, y, z)."""

    kind: int = dataclasses.field(default=BALL, init=False)


@dataclasses.dataclass(frozen=True)
class Free(JointSpec):
    """Six-DoF joint of a root body; q = (position, quaternion)."""

    kind: int = dataclasses.field(default=FREE, init=False)


class JointLayout:
    """Static joint and DoF structure of a model (immutable and hashable: static fields of the model).

    Every index array is built at construction; the traced helpers (:meth:`support_sum`,
    :meth:`before_sum`, :meth:`mass_mask`, :meth:`kind_groups`) follow the tree's traversal
    and build their 0/1 matrices inside the program from length-``nv`` index vectors.

    Args:
        tree: the body tree.
        joint_type: kind code of each joint (``FREE``, ``BALL``, ``SLIDE``, ``HINGE``).
        joint_body: body index of each joint; joints of one body are consecutive and in the
            order MuJoCo applies them, and bodies appear in increasing order.
        joint_names: names for messages.

    Raises:
        ValueError: naming the joint, for an unknown kind, an unknown body, joints out of
            body order, a free joint below a root or a free joint sharing its body.
    """

    def __init__(
        self,
        tree: BodyTree,
        joint_type: Sequence[int],
        joint_body: Sequence[int],
        joint_names: Sequence[str] | None = None,
    ):
        joint_type = int_tuple(joint_type)
        joint_body = int_tuple(joint_body)
        nj = len(joint_type)
        if len(joint_body) != nj:
            raise ValueError(
                f"joint layout: {nj} joint kinds but {len(joint_body)} joint bodies were given"
            )
        if nj == 0:
            # every body welded to the world: nothing moves, and the joint-space arrays the engine
            # is written over (nv >= 1) would be empty
            raise ValueError(
                f"model has no degree of freedom: no body has a joint ({tree.n_body} "
                f"{'body' if tree.n_body == 1 else 'bodies'} welded to the world); add a joint to a body"
            )
        if joint_names is None:
            joint_names = [f"joint{j}" for j in range(nj)]
        joint_names = tuple(str(s) for s in joint_names)
        nb = tree.n_body
        for j, (kind, body) in enumerate(zip(joint_type, joint_body)):
            label = f"joint {j} ({joint_names[j]!r})"
            if kind not in JOINT_NQ:
                raise ValueError(f"{label} has unknown kind {kind} (free=0, ball=1, slide=2, hinge=3)")
            if not 0 <= body < nb:
                raise ValueError(f"{label} belongs to unknown body {body}")
            if j and body < joint_body[j - 1]:
                raise ValueError(f"{label}: joints must be listed in body order")
            if kind == FREE:
                if tree.parent[body] != -1:
                    raise ValueError(
                        f"{label} is a free joint on body {body} ({tree.names[body]!r}), which is "
                        "not a root body: free joints are allowed only on bodies attached to the world"
                    )
                if joint_body.count(body) != 1:
                    raise ValueError(
                        f"{label}: a free joint must be the only joint of body {body} ({tree.names[body]!r})"
                    )
        fields = dict(tree=tree, type=joint_type, body=joint_body, names=joint_names)
        fields.update(_layout_arrays(tree, joint_type, joint_body))
        # jit hashes static fields on every call that takes a model: hash once here
        fields["_hash"] = hash((tree, joint_type, joint_body, joint_names))
        for k, v in fields.items():
            object.__setattr__(self, k, v)

    def __setattr__(self, name, value):
        raise AttributeError("JointLayout is immutable")

    def __delattr__(self, name):
        raise AttributeError("JointLayout is immutable")

    def __eq__(self, other):
        if self is other:
            return True
        return (
            isinstance(other, JointLayout)
            and self._hash == other._hash
            and self.tree == other.tree
            and self.type == other.type
            and self.body == other.body
            and self.names == other.names
        )

    def __hash__(self):
        return self._hash

    def __repr__(self):
        kinds = [JOINT_KIND_NAMES[k] for k in self.type]
        return f"JointLayout(nq={self.nq}, nv={self.nv}, joints={kinds})"

    @property
    def n_joint(self) -> int:
        return len(self.type)

    def kind_groups(self):
        """``(kind, joints, qposadr, dofadr)`` for each joint kind present, as NumPy index arrays.

        The one dispatch over joint kinds: kinematics, ``q`` integration and springs loop
        over these groups (a static Python loop over at most four kinds).
        """
        types = np.asarray(self.type, dtype=np.int64)
        qadr = np.asarray(self.qposadr, dtype=np.int64)
        dadr = np.asarray(self.dofadr, dtype=np.int64)
        out = []
        for code, kind in JOINT_KINDS.items():
            js = np.nonzero(types == code)[0]
            if js.size:
                out.append((kind, js, qadr[js], dadr[js]))
        return out

    # ------------------------------------------------------------------ traced helpers
    def _support(self, dtype):
        """``S[k, d] = 1`` iff DoF ``d`` moves body ``k`` (built in the program)."""
        xp = mask_module(self.tree.n_body * self.nv)
        db = xp.asarray(index(self.dof_body))
        return self.tree.ancestor_or_self(db[None, :], xp.arange(self.tree.n_body, dtype=np.int32)[:, None]).astype(dtype)

    def _before(self, dtype):
        """``B[d, e] = 1`` iff DoF ``e`` comes before DoF ``d`` (see ``dof_before_pairs``)."""
        xp = mask_module(self.nv**2)
        db = xp.asarray(index(self.dof_body))
        dj = xp.asarray(index(self.dof_joint))
        rot = xp.asarray(index(self.dof_is_rotation))
        free = xp.asarray(index([int(self.type[j] == FREE) for j in self.dof_joint]))
        d, e = (slice(None), None), (None, slice(None))
        same_body = db[d] == db[e]
        strict_ancestor = self.tree.ancestor_or_self(db[e], db[d]) & ~same_body
        earlier_joint = same_body & (dj[e] < dj[d])
        free_translation = (dj[e] == dj[d]) & (free[d] == 1) & (rot[e] == 0) & (rot[d] == 1)
        return (strict_ancestor | earlier_joint | free_translation).astype(dtype)

    def mass_mask(self, dtype):
        """``U[a, b] = 1`` for ``a <= b`` with body(a) supporting body(b) (upper triangle of ``M``)."""
        xp = mask_module(self.nv**2)
        db = xp.asarray(index(self.dof_body))
        ids = xp.arange(self.nv, dtype=np.int32)
        upper = ids[:, None] <= ids[None, :]
        return (upper & self.tree.ancestor_or_self(db[:, None], db[None, :])).astype(dtype)

    def support_sum(self, x):
        """``out[k] = sum_d S[k, d] x[d]``: sum over the DoFs that move body ``k``. ``x``: (nv, ...)."""
        if self.tree.traversal == "dense":
            return jnp.tensordot(self._support(x.dtype), x, axes=1)
        d, k = (jnp.asarray(index(a)) for a in self.dof_support_pairs)
        return jax.ops.segment_sum(x[d], k, num_segments=self.tree.n_body)

    def before_sum(self, x):
        """``out[d] = sum_e B[d, e] x[e]``: sum over the DoFs that come before DoF ``d``."""
        if self.tree.traversal == "dense":
            return jnp.tensordot(self._before(x.dtype), x, axes=1)
        e, d = (jnp.asarray(index(a)) for a in self.dof_before_pairs)
        return jax.ops.segment_sum(x[e], d, num_segments=self.nv)


def _layout_arrays(tree: BodyTree, types: tuple[int, ...], bodies: tuple[int, ...]) -> dict:
    """Every static index array of a joint layout (NumPy, at construction)."""
    nb, nj = tree.n_body, len(types)
    qposadr, dofadr, dof_joint, dof_body, dof_rot, dof_sub = [], [], [], [], [], []
    nq = nv = 0
    for j, code in enumerate(types):
        kind = JOINT_KINDS[code]
        qposadr.append(nq)
        dofadr.append(nv)
        nq += kind.nq
        nv += kind.nv
        dof_joint += [j] * kind.nv
        dof_body += [bodies[j]] * kind.nv
        dof_rot += list(kind.dof_is_rotation)
        dof_sub += list(kind.dof_component)
    body_first = [-1] * nb
    body_njnt = [0] * nb
    for j, b in enumerate(bodies):
        if body_first[b] < 0:
            body_first[b] = j
        body_njnt[b] += 1
    anc = tree.carrier_mask  # anc[i, k]: i strict ancestor of k

    # "before" pairs (d', d): the motion of d' changes the world axis of d (axis derivative).
    # d' is on a strict ancestor body, or on an earlier joint of the same body; the free
    # joint's translation comes before its rotation (MuJoCo's cdof_dot convention).
    before_a, before_b = [], []
    for d in range(nv):
        bd, jd = dof_body[d], dof_joint[d]
        for e in range(nv):
            be, je = dof_body[e], dof_joint[e]
            if anc[be, bd] or (be == bd and je < jd):
                before = True
            elif je == jd and types[jd] == FREE:
                before = dof_rot[e] == 0 and dof_rot[d] == 1
            else:
                before = False
            if before:
                before_a.append(e)
                before_b.append(d)

    # "support" pairs (d, k): DoF d moves body k (body(d) is k or a carrier of k).
    sup_d, sup_k = [], []
    for k in range(nb):
        for d in range(nv):
            if dof_body[d] == k or anc[dof_body[d], k]:
                sup_d.append(d)
                sup_k.append(k)

    # Frame tree for the kinematics: for each body an "offset" node (body_pos, body_quat
    # relative to the parent's final frame) followed by one node per joint.
    node_parent, node_body, node_joint = [], [], []
    body_last_node = [-1] * nb
    body_offset_node = [-1] * nb
    for b in range(nb):
        p = tree.parent[b]
        node_parent.append(body_last_node[p] if p >= 0 else -1)
        node_body.append(b)
        node_joint.append(-1)
        body_offset_node[b] = len(node_parent) - 1
        last = body_offset_node[b]
        for j in range(nj):
            if bodies[j] == b:
                node_parent.append(last)
                node_body.append(b)
                node_joint.append(j)
                last = len(node_parent) - 1
        body_last_node[b] = last
    joint_node = [0] * nj
    for n_, j in enumerate(node_joint):
        if j >= 0:
            joint_node[j] = n_
    return dict(
        qposadr=tuple(qposadr),
        dofadr=tuple(dofadr),
        nq=nq,
        nv=nv,
        dof_joint=tuple(dof_joint),
        dof_body=tuple(dof_body),
        dof_is_rotation=tuple(dof_rot),
        dof_component=tuple(dof_sub),
        body_first_joint=tuple(body_first),
        body_joint_count=tuple(body_njnt),
        body_is_free=tuple(
            int(body_first[b] >= 0 and types[body_first[b]] == FREE) for b in range(nb)
        ),
        dof_before_pairs=(tuple(before_a), tuple(before_b)),
        dof_support_pairs=(tuple(sup_d), tuple(sup_k)),
        frame_tree=BodyTree(node_parent, traversal=tree.traversal),
        node_body=tuple(node_body),
        node_joint=tuple(node_joint),
        body_last_node=tuple(body_last_node),
        body_offset_node=tuple(body_offset_node),
        joint_node=tuple(joint_node),
        # the node holding the frame just before joint j
        joint_pre_node=tuple(node_parent[joint_node[j]] for j in range(nj)),
    )
