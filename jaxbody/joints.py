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

import numpy as np

from ._types import ScalarLike, VectorLike

from .tree import BodyTree

__all__ = [
    "FREE",
    "BALL",
    "SLIDE",
    "HINGE",
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
JOINT_KIND_NAMES = {FREE: "free", BALL: "ball", SLIDE: "slide", HINGE: "hinge"}
JOINT_NQ = {FREE: 7, BALL: 4, SLIDE: 1, HINGE: 1}
JOINT_NV = {FREE: 6, BALL: 3, SLIDE: 1, HINGE: 1}


@dataclasses.dataclass(frozen=True)
class _JointSpec:
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
class Hinge(_JointSpec):
    """Rotation about ``axis`` through ``pos``; ``ref`` is the angle of the reference pose."""

    ref: ScalarLike = 0.0
    springref: ScalarLike = 0.0
    kind: int = dataclasses.field(default=HINGE, init=False)


@dataclasses.dataclass(frozen=True)
class Slide(_JointSpec):
    """Translation along ``axis``; ``ref`` is the displacement of the reference pose."""

    ref: ScalarLike = 0.0
    springref: ScalarLike = 0.0
    kind: int = dataclasses.field(default=SLIDE, init=False)


@dataclasses.dataclass(frozen=True)
class Ball(_JointSpec):
    """Spherical joint about ``pos``; q is a unit quaternion (w, x, y, z)."""

    kind: int = dataclasses.field(default=BALL, init=False)


@dataclasses.dataclass(frozen=True)
class Free(_JointSpec):
    """Six-DoF joint of a root body; q = (position, quaternion)."""

    kind: int = dataclasses.field(default=FREE, init=False)


def _t(a) -> tuple[int, ...]:
    return tuple(int(v) for v in np.asarray(a, dtype=np.int64).reshape(-1).tolist())


class JointLayout:
    """Static joint and DoF structure of a model (hashable; STYLE rule 4).

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
        joint_type = _t(joint_type)
        joint_body = _t(joint_body)
        nj = len(joint_type)
        if len(joint_body) != nj:
            raise ValueError(
                f"joint layout: {nj} joint kinds but {len(joint_body)} joint bodies were given"
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
        self.tree = tree
        self.type = joint_type
        self.body = joint_body
        self.names = joint_names
        self._build()

    def __eq__(self, other):
        if self is other:
            return True
        return (
            isinstance(other, JointLayout)
            and hash(self) == hash(other)
            and self.tree == other.tree
            and self.type == other.type
            and self.body == other.body
            and self.names == other.names
        )

    def __hash__(self):
        # cached: jit hashes static fields on every call that takes a model as an argument
        h = self.__dict__.get("_hash")
        if h is None:
            h = self.__dict__["_hash"] = hash((self.tree, self.type, self.body, self.names))
        return h

    def __repr__(self):
        kinds = [JOINT_KIND_NAMES[k] for k in self.type]
        return f"JointLayout(nq={self.nq}, nv={self.nv}, joints={kinds})"

    @property
    def n_joint(self) -> int:
        return len(self.type)

    def _pair_matrix(self, name, rows, cols, pairs, transpose=False):
        cache = self.__dict__.setdefault("_dense_cache", {})
        if name not in cache:
            m = np.zeros((rows, cols), dtype=np.float64)
            a, b = (np.asarray(x, dtype=np.int64) for x in pairs)
            if a.size:
                if transpose:
                    m[b, a] = 1.0
                else:
                    m[a, b] = 1.0
            cache[name] = m
        return cache[name]

    @property
    def support_matrix(self) -> np.ndarray:
        """``S[k, d] = 1`` iff DoF ``d`` moves body ``k`` (dense view of ``dof_support_pairs``)."""
        return self._pair_matrix("support", self.tree.n_body, self.nv, self.dof_support_pairs, True)

    @property
    def before_matrix(self) -> np.ndarray:
        """``B[d, e] = 1`` iff DoF ``e`` comes before DoF ``d`` (dense ``dof_before_pairs``)."""
        return self._pair_matrix("before", self.nv, self.nv, self.dof_before_pairs, True)

    @property
    def mass_mask(self) -> np.ndarray:
        """``U[a, b] = 1`` for the upper-triangle pairs of ``mass_pairs`` (a ≤ b, a supports b)."""
        return self._pair_matrix("mass", self.nv, self.nv, self.mass_pairs)

    def _build(self):
        tree = self.tree
        nb, nj = tree.n_body, len(self.type)
        qposadr, dofadr = [], []
        nq = nv = 0
        dof_joint, dof_body = [], []
        for j, kind in enumerate(self.type):
            qposadr.append(nq)
            dofadr.append(nv)
            nq += JOINT_NQ[kind]
            nv += JOINT_NV[kind]
            dof_joint += [j] * JOINT_NV[kind]
            dof_body += [self.body[j]] * JOINT_NV[kind]
        self.qposadr = tuple(qposadr)
        self.dofadr = tuple(dofadr)
        self.nq = nq
        self.nv = nv
        self.dof_joint = tuple(dof_joint)
        self.dof_body = tuple(dof_body)
        body_first = [-1] * nb
        body_njnt = [0] * nb
        for j, b in enumerate(self.body):
            if body_first[b] < 0:
                body_first[b] = j
            body_njnt[b] += 1
        self.body_first_joint = tuple(body_first)
        self.body_joint_count = tuple(body_njnt)
        self.body_is_free = tuple(
            int(body_first[b] >= 0 and self.type[body_first[b]] == FREE) for b in range(nb)
        )
        # Rotational part of each DoF: 1 for hinge/ball/free-rotation, 0 for slide/free-translation.
        dof_rot, dof_sub = [], []
        for j, kind in enumerate(self.type):
            if kind == HINGE:
                dof_rot += [1]
                dof_sub += [0]
            elif kind == SLIDE:
                dof_rot += [0]
                dof_sub += [0]
            elif kind == BALL:
                dof_rot += [1, 1, 1]
                dof_sub += [0, 1, 2]
            else:
                dof_rot += [0, 0, 0, 1, 1, 1]
                dof_sub += [0, 1, 2, 0, 1, 2]
        self.dof_is_rotation = tuple(dof_rot)
        self.dof_component = tuple(dof_sub)
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
                elif je == jd and self.type[jd] == FREE:
                    before = dof_rot[e] == 0 and dof_rot[d] == 1
                else:
                    before = False
                if before:
                    before_a.append(e)
                    before_b.append(d)
        self.dof_before_pairs = (tuple(before_a), tuple(before_b))

        # "support" pairs (d, k): DoF d moves body k (body(d) is k or a carrier of k).
        sup_d, sup_k = [], []
        for k in range(nb):
            for d in range(nv):
                if dof_body[d] == k or anc[dof_body[d], k]:
                    sup_d.append(d)
                    sup_k.append(k)
        self.dof_support_pairs = (tuple(sup_d), tuple(sup_k))

        # mass-matrix pairs (a, b), a <= b, nonzero block: body(a) supports body(b)
        ma, mb = [], []
        for b in range(nv):
            for a in range(b + 1):
                if dof_body[a] == dof_body[b] or anc[dof_body[a], dof_body[b]]:
                    ma.append(a)
                    mb.append(b)
        self.mass_pairs = (tuple(ma), tuple(mb))

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
                if self.body[j] == b:
                    node_parent.append(last)
                    node_body.append(b)
                    node_joint.append(j)
                    last = len(node_parent) - 1
            body_last_node[b] = last
        self.frame_tree = BodyTree(node_parent)
        self.node_body = tuple(node_body)
        self.node_joint = tuple(node_joint)
        self.body_last_node = tuple(body_last_node)
        self.body_offset_node = tuple(body_offset_node)
        joint_node = [0] * nj
        for n_, j in enumerate(node_joint):
            if j >= 0:
                joint_node[j] = n_
        self.joint_node = tuple(joint_node)
        # the node holding the frame just before joint j
        self.joint_pre_node = tuple(node_parent[joint_node[j]] for j in range(nj))
