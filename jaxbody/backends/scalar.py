"""The tree algorithm on scalars, written once for every scalar type.

The composite-rigid-body method with a tree-sparse factorisation, all in world axes about one
reference point ``c0`` (the base point of body 0), written out at trace time for a model's
static tree as straight-line arithmetic on **scalars**: every 3-vector is a tuple of three
scalars, every rotation a 3×3 tuple of tuples. A scalar is whatever supports ``+ − × ÷``:

* a JAX array of shape ``()`` (or ``(batch,)`` under ``vmap``): the unrolled JAX kernel,
  :mod:`jaxbody.backends.unrolled`;
* a symbol of the native kernel's tracer (:mod:`jaxbody.backends.native.symbolic`), whose
  arithmetic emits C++: the native kernel's code generator;
* the Python floats ``0.0``/``1.0``, structural constants known at trace time that the helpers
  fold away, so terms that vanish by structure (a slide's angular part, the ground's velocity,
  a free joint's unit translations, absent gravity or loads) never enter the program.

The passes:

1. **Kinematics**, root to leaves (MuJoCo's ``mj_kinematics``): body frames, joint anchors and
   axes, centres of mass, and the unit motion ``S_d = (ω_d, s_d)`` of every DoF in Plücker
   coordinates about ``c0`` (angular part, velocity of the body point at ``c0``).
2. **Velocities and bias accelerations**, root to leaves: ``V_k = V_p(k) + Σ_d S_d v_d`` and
   ``A_k = A_p(k) + Σ_d (V_before(d) × S_d) v_d`` with the root's ``A = (0, −g)`` (gravity as
   a uniform acceleration of the ground).
3. **Subtree (augmented) quantities**, leaves to root: the composite inertia of subsystem
   ``k`` is its mass ``m_k``, its static moment about ``c0`` and its inertia about ``c0`` —
   the subtree sums the augmented bodies are made of (``m_k``, ``m̄_k`` moved from ``O_0k``
   to ``c0``, ``I_k`` moved likewise); the subtree force ``F_k = Σ_{S(k)} (I_i A_i + V_i ×*
   I_i V_i − f_ext,i)``.
4. **Joint space**: ``M_ab = S_a · (𝕀_k S_b)`` for DoF ``a`` supporting DoF ``b`` on body
   ``k``, ``bias_d = S_d · F_k(d)``; armature on the diagonal (:func:`bias_and_mass`).
5. **Tree-sparse LDLᵀ** (Featherstone's ``LTDL``): ``M = Lᵀ D L`` with the fill-in confined to
   each DoF's ancestor chain (``λ(d)``, the DoF parent, is static), then two sparse
   triangular solves (:func:`ltdl_factor`, :func:`ltdl_substitute`, :func:`ltdl_solve`).

Besides forward dynamics: the energies (:func:`energies`), inverse dynamics by the
Newton–Euler passes (:func:`inverse_dynamics`) and its hand-derived adjoint
(:func:`inverse_dynamics_vjp`). The classical RK4 tableau (:data:`RK4_C`, :data:`RK4_A`,
:data:`RK4_B`) is here once for the integrators that step these programs.
"""

import functools
import math
from collections.abc import Sequence
from typing import no_type_check

import jax
import jax.numpy as jnp

from .._types import Array
from ..joints import BALL, FREE, HINGE, SLIDE

__all__ = [
    "RK4_A",
    "RK4_B",
    "RK4_C",
    "ZERO3",
    "add",
    "adjoint_applies",
    "bias_and_mass",
    "energies",
    "fourier_series",
    "inverse_dynamics",
    "inverse_dynamics_vjp",
    "ltdl_factor",
    "ltdl_solve",
    "ltdl_substitute",
    "scalars",
    "stack",
]

# ----------------------------------------------------------------------------- the RK4 tableau
#: Nodes ``c_i`` of the classical fourth-order Runge–Kutta method (Butcher tableau).
RK4_C = (0.0, 0.5, 0.5, 1.0)
#: Stage coefficients ``a_ij`` (row ``i``: the weights of stages ``0 .. i−1``).
RK4_A = ((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0))
#: Weights ``b_i`` of the stages in the step.
RK4_B = (1 / 6, 1 / 3, 1 / 3, 1 / 6)


# ----------------------------------------------------------------------------- scalar algebra
# A "scalar" is a JAX array of shape () (or (batch,) under vmap) or the Python float 0.0/1.0,
# a structural constant known at trace time that the helpers fold away.
# The helpers below run once per scalar operation of a generated program (hundreds of
# thousands of calls for one native kernel): ``no_type_check`` exempts them from the runtime
# type checks the test suite instruments the package with (jaxtyping's import hook honours
# it), which tripled the code generator's time; they carry no annotations worth checking.
@no_type_check
def _is0(a) -> bool:
    return type(a) is float and a == 0.0  # not np.float64 (a float subclass): only constants


@no_type_check
def _is1(a) -> bool:
    return type(a) is float and a == 1.0


@no_type_check
def add(a, b):
    """``a + b`` with the structural zero ``0.0`` folded away."""
    if _is0(a):
        return b
    if _is0(b):
        return a
    return a + b


@no_type_check
def _sub(a, b):
    if _is0(b):
        return a
    if _is0(a):
        return -b
    return a - b


@no_type_check
def _mul(a, b):
    if _is0(a) or _is0(b):
        return 0.0
    if _is1(a):
        return b
    if _is1(b):
        return a
    return a * b


@no_type_check
def _sum(*terms):
    out = 0.0
    for t in terms:
        out = add(out, t)
    return out


ZERO3 = (0.0, 0.0, 0.0)


@no_type_check
def _vadd(a, b):
    return tuple(add(x, y) for x, y in zip(a, b))


@no_type_check
def _vsub(a, b):
    return tuple(_sub(x, y) for x, y in zip(a, b))


@no_type_check
def _vscale(s, a):
    return tuple(_mul(s, x) for x in a)


@no_type_check
def _dot(a, b):
    return _sum(*(_mul(x, y) for x, y in zip(a, b)))


@no_type_check
def _cross(a, b):
    return (
        _sub(_mul(a[1], b[2]), _mul(a[2], b[1])),
        _sub(_mul(a[2], b[0]), _mul(a[0], b[2])),
        _sub(_mul(a[0], b[1]), _mul(a[1], b[0])),
    )


@no_type_check
def _is_zero3(a) -> bool:
    return all(_is0(x) for x in a)


@no_type_check
def _matvec(R, x):
    return tuple(_dot(row, x) for row in R)


@no_type_check
def _matmul(A, B):
    cols = tuple(zip(*B))
    return tuple(tuple(_dot(row, col) for col in cols) for row in A)


@no_type_check
def _column(R, k):
    return (R[0][k], R[1][k], R[2][k])


def _quat_matrix(w, x, y, z):
    """Rotation matrix of a (not necessarily unit) quaternion: MuJoCo normalises first."""
    s = 2.0 / (w * w + x * x + y * y + z * z)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    return (
        (1.0 - (yy + zz), xy - wz, xz + wy),
        (xy + wz, 1.0 - (xx + zz), yz - wx),
        (xz - wy, yz + wx, 1.0 - (xx + yy)),
    )


@no_type_check
def _cos(a):
    # symbolic scalars (the native kernel's tracer, jaxbody.backends.native.symbolic) carry their
    # own; plain numbers (NumPy's included) stay numbers, so the algebra also runs on the host
    # with no program compiled (:func:`mass_matrix_of_numbers`)
    if getattr(a, "symbolic", False):
        return a.cos()
    return math.cos(a) if isinstance(a, float) else jnp.cos(a)


@no_type_check
def _sin(a):
    if getattr(a, "symbolic", False):
        return a.sin()
    return math.sin(a) if isinstance(a, float) else jnp.sin(a)


def _axis_angle(axis, angle):
    """Rodrigues' rotation about the unit ``axis`` by ``angle``: ``E + s[a]× + (1−c)[a]×²``.

    Written with ``[a]×² = a aᵀ − |a|² E`` as :func:`jaxbody.kinematics.axis_angle_matrix`
    is, so derivatives with respect to the axis agree with the vectorised kernel.
    """
    c, s = _cos(angle), _sin(angle)
    t = 1.0 - c
    x, y, z = axis
    n2 = x * x + y * y + z * z
    return (
        (1.0 + t * (x * x - n2), t * x * y - s * z, t * x * z + s * y),
        (t * x * y + s * z, 1.0 + t * (y * y - n2), t * y * z - s * x),
        (t * x * z - s * y, t * y * z + s * x, 1.0 + t * (z * z - n2)),
    )


def fourier_series(t, omega, offset: Sequence, sine: Sequence, cosine: Sequence) -> list:
    """``c_i + Σ_{k=1..K} (a_ik sin(k ω t) + b_ik cos(k ω t))`` for each entry ``i`` (``offset``:
    the ``c_i``; ``sine``, ``cosine``: each entry's ``K`` coefficients); one sine and cosine, the
    harmonics by rotation ``(s, c)_{k+1} = (s_k c_1 + c_k s_1, c_k c_1 − s_k s_1)`` (rounding ~``k ε``).
    :class:`jaxbody.FourierTorque` runs it on array columns, the code generator on symbols."""
    harmonics = len(sine[0]) if len(sine) else 0
    waves = [(_sin(omega * t), _cos(omega * t))] if harmonics else []
    s1, c1 = waves[0] if waves else (0.0, 0.0)
    for _ in range(1, harmonics):
        s, c = waves[-1]
        waves.append((s * c1 + c * s1, c * c1 - s * s1))
    out = []
    for c, a, b in zip(offset, sine, cosine):
        total = c
        for (s, co), ak, bk in zip(waves, a, b):
            total = total + ak * s + bk * co
        out.append(total)
    return out


def scalars(x) -> list:
    """A 1-D array as a list of scalars (one slice each, made once)."""
    return [x[i] for i in range(x.shape[0])]


def _rows3(x, i) -> tuple:
    return (x[i, 0], x[i, 1], x[i, 2])


# ----------------------------------------------------------------------------- spatial algebra
# motion (angular ω, linear v about c0); force (moment about c0 L, force p)
@no_type_check
def _motion_cross(V, S):
    """``V × S`` of two motions (``Ṡ`` of a DoF carried by a frame moving with ``V``)."""
    (w, v), (ws, vs) = V, S
    return _cross(w, ws), _vadd(_cross(w, vs), _cross(v, ws))


@no_type_check
def _force_cross(V, F):
    """``V ×* F``: rate of change of a momentum ``F`` carried by the motion ``V``."""
    (w, v), (L, p) = V, F
    return _vadd(_cross(w, L), _cross(v, p)), _cross(w, p)


@no_type_check
def _inertia_apply(I, S):
    """Spatial inertia ``(m, h, K)`` about ``c0`` applied to a motion: ``(K ω + h × v, m v + ω × h)``."""
    m, h, K = I
    w, v = S
    L = _vadd(_sym_apply(K, w), _cross(h, v))
    p = _vadd(_vscale(m, v), _cross(w, h))
    return L, p


@no_type_check
def _sym_apply(K, w):
    """Symmetric 3×3 stored as (xx, yy, zz, xy, xz, yz) applied to ``w``."""
    xx, yy, zz, xy, xz, yz = K
    return (
        _sum(_mul(xx, w[0]), _mul(xy, w[1]), _mul(xz, w[2])),
        _sum(_mul(xy, w[0]), _mul(yy, w[1]), _mul(yz, w[2])),
        _sum(_mul(xz, w[0]), _mul(yz, w[1]), _mul(zz, w[2])),
    )


@no_type_check
def _spatial_dot(S, F):
    return add(_dot(S[0], F[0]), _dot(S[1], F[1]))


# ----------------------------------------------------------------------------- structure
# The passes below take ``model`` unannotated: a Model, or the native kernel's code generator's
# stand-in whose parameters are symbols (jaxbody.backends.native.symbolic.SymbolicModel).
def _structure(model):
    """Static per-body joint lists and the DoF parent array ``λ`` (trace time, cached per tree)."""
    return _structure_of(model.joints, model.tree)


@functools.lru_cache(maxsize=256)
def _structure_of(joints, tree):
    nb = tree.n_body
    body_joints: list[list[int]] = [[] for _ in range(nb)]
    for j, b in enumerate(joints.body):
        body_joints[b].append(j)
    dof_body = list(joints.dof_body)
    nv = len(dof_body)
    parent = list(tree.parent)
    # last DoF on each body or its nearest ancestor with DoFs
    last_dof = [-1] * nb
    dof_parent = [-1] * nv
    for b in range(nb):
        p = parent[b]
        above = last_dof[p] if p >= 0 else -1
        for d in range(nv):
            if dof_body[d] == b:
                dof_parent[d] = above
                above = d
        last_dof[b] = above
    return tuple(tuple(js) for js in body_joints), tuple(dof_parent)


def _kinematics(model, q: list):
    """Body frames, DoF motions about ``c0``, centres of mass (scalar tuples), root to leaves."""
    joints = model.joints
    nb = model.n_body
    parent = model.tree.parent
    body_joints, _ = _structure(model)
    qadr, types = joints.qposadr, joints.type
    qpos0 = model.qpos0
    R: list = [None] * nb
    x: list = [None] * nb
    base: list = [None] * nb
    # per joint: (anchor, world axis); ball/free DoFs are finished once the body's frame is known
    anchors: dict[int, tuple] = {}
    axes: dict[int, tuple] = {}
    for b in range(nb):
        js = body_joints[b]
        if js and types[js[0]] == FREE:
            a = qadr[js[0]]
            R[b] = _quat_matrix(q[a + 3], q[a + 4], q[a + 5], q[a + 6])
            x[b] = (q[a], q[a + 1], q[a + 2])
            anchors[js[0]] = x[b]
            base[b] = x[b]
            continue
        Roff = _quat_matrix(*(model.body_quat[b, i] for i in range(4)))
        pos = _rows3(model.body_pos, b)
        p = parent[b]
        if p < 0:
            Rb, xb = Roff, pos
        else:
            Rb, xb = _matmul(R[p], Roff), _vadd(x[p], _matvec(R[p], pos))
        for j in js:
            jp = _rows3(model.joint_pos, j)
            ja = _rows3(model.joint_axis, j)
            anchor = _vadd(xb, _matvec(Rb, jp))
            anchors[j] = anchor
            kind = types[j]
            if kind == HINGE:
                axis = _matvec(Rb, ja)
                axes[j] = axis
                Rb = _matmul(Rb, _axis_angle(ja, q[qadr[j]] - qpos0[qadr[j]]))
                xb = _vsub(anchor, _matvec(Rb, jp))
            elif kind == SLIDE:
                axis = _matvec(Rb, ja)
                axes[j] = axis
                xb = _vadd(xb, _vscale(q[qadr[j]] - qpos0[qadr[j]], axis))
            else:  # BALL
                a = qadr[j]
                Rb = _matmul(Rb, _quat_matrix(q[a], q[a + 1], q[a + 2], q[a + 3]))
                xb = _vsub(anchor, _matvec(Rb, jp))
        R[b], x[b] = Rb, xb
        base[b] = anchors[js[0]] if js else xb
    c0 = base[0]
    # DoF motions about c0, in DoF order
    S: list = []
    for j in range(joints.n_joint):
        b = joints.body[j]
        kind = types[j]
        if kind == HINGE:
            w = axes[j]
            S.append((w, _cross(w, _vsub(c0, anchors[j]))))
        elif kind == SLIDE:
            S.append((ZERO3, axes[j]))
        else:
            if kind == FREE:
                for k in range(3):
                    S.append((ZERO3, tuple(1.0 if i == k else 0.0 for i in range(3))))
            for k in range(3):
                w = _column(R[b], k)
                S.append((w, _cross(w, _vsub(c0, anchors[j]))))
    return R, x, c0, S


def _body_inertias(model, R, x, c0):
    """Spatial inertia ``(m, h, K)`` of every body about ``c0`` (world axes) and its CM."""
    out, com = [], []
    for b in range(model.n_body):
        m = model.body_mass[b]
        c = _vadd(x[b], _matvec(R[b], _rows3(model.body_com, b)))
        com.append(c)
        # the symmetric part (derivatives then agree with the vectorised kernel's R I Rᵀ)
        Ib = tuple(tuple(0.5 * (model.body_inertia[b, i, k] + model.body_inertia[b, k, i]) for k in range(3)) for i in range(3))
        T = _matmul(R[b], Ib)  # R I, then (R I) Rᵀ: six entries of the symmetric result
        Rb = R[b]
        Iw = {(i, k): _dot(T[i], Rb[k]) for i in range(3) for k in range(i, 3)}
        r = _vsub(c, c0)
        h = _vscale(m, r)
        # K = I_C + m (|r|² E − r rᵀ) = I_C + (h·r) E − h rᵀ
        hr = _dot(h, r)
        K = (
            Iw[0, 0] + hr - h[0] * r[0],
            Iw[1, 1] + hr - h[1] * r[1],
            Iw[2, 2] + hr - h[2] * r[2],
            Iw[0, 1] - h[0] * r[1],
            Iw[0, 2] - h[0] * r[2],
            Iw[1, 2] - h[1] * r[2],
        )
        out.append((m, h, K))
    return out, com


def _inertia_add(a, b):
    return (add(a[0], b[0]), _vadd(a[1], b[1]), tuple(add(x, y) for x, y in zip(a[2], b[2])))


def _dof_owners(model):
    """For each joint: its DoF indices, and for FREE joints the (translation, rotation) split."""
    joints = model.joints
    out = []
    for j in range(joints.n_joint):
        d0 = joints.dofadr[j]
        kind = joints.type[j]
        n = {HINGE: 1, SLIDE: 1, BALL: 3, FREE: 6}[kind]
        out.append(list(range(d0, d0 + n)))
    return out


def _motions(model, S, v, gravity, want_acceleration=True, acceleration=None, per_dof=None):
    """Body velocities ``V_k`` and bias accelerations ``A_k`` (root: ``(0, −g)``), root to leaves.

    ``want_acceleration=False``: the velocities alone (``A`` is ``None``). ``acceleration``
    (per DoF): the body accelerations of these joint accelerations, ``A_k + Σ S_d a_d`` over
    the DoFs from the root to ``k`` (inverse dynamics); default zero. ``per_dof``: a dict that
    receives, per DoF, ``"V-"`` the velocity just before it and ``"A+"`` the acceleration just
    after it (lists over the DoFs).
    """
    joints = model.joints
    nb = model.n_body
    parent = model.tree.parent
    body_joints, _ = _structure(model)
    dofs_of_joint = _dof_owners(model)
    A_ground = (ZERO3, ZERO3 if gravity is None else tuple(-gi for gi in gravity))
    V: list = [None] * nb
    A: list = [None] * nb
    if per_dof is not None:
        per_dof["V-"], per_dof["A+"] = [None] * model.nv, [None] * model.nv
    for b in range(nb):
        p = parent[b]
        Vb = (ZERO3, ZERO3) if p < 0 else V[p]
        Ab = A_ground if p < 0 else A[p]
        for j in body_joints[b]:
            ds = dofs_of_joint[j]
            if joints.type[j] == FREE:
                groups = [ds[:3], ds[3:]]  # translation moves the frame before the rotation
            else:
                groups = [ds]
            for group in groups:
                Vbefore = Vb
                for d in group:
                    Sd = S[d]
                    if per_dof is not None:
                        per_dof["V-"][d] = Vb
                    if want_acceleration and not (_is_zero3(Vbefore[0]) and _is_zero3(Vbefore[1])):
                        Sdot = _motion_cross(Vbefore, Sd)
                        Ab = (_vadd(Ab[0], _vscale(v[d], Sdot[0])), _vadd(Ab[1], _vscale(v[d], Sdot[1])))
                    if want_acceleration and acceleration is not None:
                        Ab = (_vadd(Ab[0], _vscale(acceleration[d], Sd[0])), _vadd(Ab[1], _vscale(acceleration[d], Sd[1])))
                    Vb = (_vadd(Vb[0], _vscale(v[d], Sd[0])), _vadd(Vb[1], _vscale(v[d], Sd[1])))
                    if per_dof is not None:
                        per_dof["A+"][d] = Ab
        V[b], A[b] = Vb, Ab
    return V, (A if want_acceleration else None)


def energies(model, q, v, gravity) -> tuple:
    """Kinetic energy ``T = ½ Σ_k V_k·(𝕀_k V_k) + ½ Σ_d a_d v_d²`` (armature ``a``) and the
    gravity potential ``−Σ_k m_k g·C_k`` on scalars (``gravity=None``: zero), as
    :func:`jaxbody.kernels.kinetic_energy` and the potential of :class:`jaxbody.Gravity`."""
    R, x, c0, S = _kinematics(model, q)
    inertia, com = _body_inertias(model, R, x, c0)
    V, _ = _motions(model, S, v, None, want_acceleration=False)
    twice = 0.0
    for b in range(model.n_body):
        if _is_zero3(V[b][0]) and _is_zero3(V[b][1]):
            continue
        twice = add(twice, _spatial_dot(V[b], _inertia_apply(inertia[b], V[b])))
    for d in range(model.nv):
        twice = add(twice, _mul(model.dof_armature[d], _mul(v[d], v[d])))
    kinetic = _mul(0.5, twice)
    potential = 0.0
    if gravity is not None:
        for b in range(model.n_body):
            potential = _sub(potential, _mul(model.body_mass[b], _dot(gravity, com[b])))
    return kinetic, potential




def _body_force(inertia, V, A) -> tuple:
    """The Newton–Euler force ``f = 𝕀 A + V ×* 𝕀 V`` of one body and its momentum ``𝕀 V``."""
    IA = _inertia_apply(inertia, A)
    P = _inertia_apply(inertia, V)
    VxP = _force_cross(V, P)
    return (_vadd(IA[0], VxP[0]), _vadd(IA[1], VxP[1])), P


def _joint_forces(model, S, inertia, com, c0, V, A, external) -> list:
    """``τ_d = S_d · Σ_{k ⪰ body(d)} (𝕀_k A_k + V_k ×* 𝕀_k V_k − f_k^ext)``: the Newton–Euler
    body forces, summed leaves to root and projected on each DoF's axis."""
    nb = model.n_body
    parent = model.tree.parent
    F: list = [None] * nb
    for b in range(nb):
        (L, p_), _ = _body_force(inertia[b], V[b], A[b])
        if external is not None:
            f = external[b][:3]
            t = external[b][3:]
            L = _vsub(L, _vadd(t, _cross(_vsub(com[b], c0), f)))
            p_ = _vsub(p_, f)
        F[b] = (L, p_)
    for b in reversed(range(nb)):
        p = parent[b]
        if p >= 0:
            F[p] = (_vadd(F[p][0], F[b][0]), _vadd(F[p][1], F[b][1]))
    dof_body = model.joints.dof_body
    return [_spatial_dot(S[d], F[dof_body[d]]) for d in range(model.nv)]


def inverse_dynamics(model, q, v, acceleration, gravity, external) -> list:
    """``τ = M(q) a + bias(q, v)`` by the recursive Newton–Euler passes (armature included): the
    residual whose derivatives give those of forward dynamics (``∂a = M⁻¹ (∂τ − ∂_x τ)``)."""
    R, x, c0, S = _kinematics(model, q)
    inertia, com = _body_inertias(model, R, x, c0)
    V, A = _motions(model, S, v, gravity, acceleration=acceleration)
    tau = _joint_forces(model, S, inertia, com, c0, V, A, external)
    return [add(t, _mul(model.dof_armature[d], acceleration[d])) for d, t in enumerate(tau)]


def _spatial_add(a, b):
    return _vadd(a[0], b[0]), _vadd(a[1], b[1])


def _spatial_sub(a, b):
    return _vsub(a[0], b[0]), _vsub(a[1], b[1])


def _spatial_scale(s, a):
    return _vscale(s, a[0]), _vscale(s, a[1])


def adjoint_applies(joints) -> bool:
    """Whether :func:`inverse_dynamics_vjp` serves a tree with these joints: hinges and slides
    only (one DoF each, the reference point ``c0`` fixed)."""
    return all(int(t) in (HINGE, SLIDE) for t in joints.type)


def inverse_dynamics_vjp(model, q, v, acceleration, gravity, lam) -> tuple[list, list]:
    """``λᵀ ∂τ/∂q`` and ``λᵀ ∂τ/∂v`` of ``τ = `` :func:`inverse_dynamics` ``(q, v, a)`` with
    ``a`` held, for trees of hinge and slide joints (:func:`adjoint_applies`), no body loads.

    Derived by hand, not by reverse mode through the Newton–Euler passes. Write
    ``λᵀτ = Σ_k Λ_k · f_k`` with ``Λ_k = Σ_{d ⪯ k} λ_d S_d`` (a motion summed root to leaves,
    like ``V_k``) and ``f_k = 𝕀_k A_k + V_k ×* 𝕀_k V_k``. Turning joint ``j`` by ``δq`` moves
    everything carried after it rigidly with the screw ``S_j δq``; a motion or force carried
    along changes by ``S_j ×`` (``S_j ×*``) of itself, and ``(S × m)·f + m·(S ×* f) = 0`` cancels
    all of that but the parts not carried along: ``Λ``, ``V`` and ``A`` just before ``j``, and
    the Coriolis terms of the DoFs after ``j`` that refer to the velocity before it. With
    ``G_k = 𝕀_k Λ_k``, ``P_k = 𝕀_k V_k``, ``Y_k = V_k ×* G_k − Λ_k ×* P_k − 𝕀_k (V_k × Λ_k)``
    and ``ΣG``, ``ΣY``, ``F`` their sums over the subtree of ``j``'s body ``b``:

    - ``∂(λᵀτ)/∂q_j = −S_j · [Λ⁻_j ×* F + A⁺_j ×* ΣG + V⁻_j ×* (ΣY − V⁺_j ×* ΣG)]``,
    - ``∂(λᵀτ)/∂v_j = S_j · (ΣY − 2 V⁻_j ×* ΣG)``,

    where ``⁻``/``⁺`` are the values just before/after joint ``j`` (``V⁺ = V⁻ + S_j v_j``).
    Uses the identity ``(a × b)·f = a·(b ×* f)`` to gather each sum once per body; with
    ``m·(n ×* f) = −(n × m)·f`` and ``Ṡ_j = V⁻_j × S_j`` (a term of the acceleration recursion,
    so already computed) the projections are evaluated as

    - ``∂q_j = (Λ⁻_j × S_j)·F + (A⁺_j × S_j + V⁺_j × Ṡ_j)·ΣG + Ṡ_j·ΣY``,
    - ``∂v_j = S_j·ΣY + 2 Ṡ_j·ΣG``,

    three motion cross products and five dot products a joint. The cost is a few spatial
    products per body: O(n), about a third of the reverse-mode program.

    ``lam``: the cotangent of ``τ`` (one scalar per DoF; Python ``0.0`` where it is zero).
    Returns ``(q̄, v̄)``: lists over ``nq`` and ``nv``.
    """
    joints = model.joints
    parent = model.tree.parent
    R, x, c0, S = _kinematics(model, q)
    inertia, _ = _body_inertias(model, R, x, c0)
    before: dict = {}  # V⁻ and A⁺ per joint; the same operations as inverse dynamics (shared)
    V, A = _motions(model, S, v, gravity, acceleration=acceleration, per_dof=before)
    lam_before: dict = {}  # Λ is summed like a velocity, with λ for v
    Lam, _ = _motions(model, S, lam, None, want_acceleration=False, per_dof=lam_before)
    F: list = []
    G: list = []
    Y: list = []
    for b in range(model.n_body):
        f, P = _body_force(inertia[b], V[b], A[b])
        F.append(f)
        G.append(_inertia_apply(inertia[b], Lam[b]))
        Y.append(_spatial_sub(
            _spatial_sub(_force_cross(V[b], G[b]), _force_cross(Lam[b], P)),
            _inertia_apply(inertia[b], _motion_cross(V[b], Lam[b])),
        ))
    for b in reversed(range(model.n_body)):  # subtree sums, leaves to root
        p = parent[b]
        if p >= 0:
            F[p] = _spatial_add(F[p], F[b])
            G[p] = _spatial_add(G[p], G[b])
            Y[p] = _spatial_add(Y[p], Y[b])
    q_bar: list = [0.0] * model.nq
    v_bar: list = [0.0] * model.nv
    for j in range(joints.n_joint):
        b, d = joints.body[j], joints.dofadr[j]
        Sd, Vm = S[d], before["V-"][d]
        Vp = _spatial_add(Vm, _spatial_scale(v[d], Sd))  # V⁺ (inverse dynamics' own sum)
        Sdot = _motion_cross(Vm, Sd)  # V⁻ × S: the acceleration recursion's term (shared)
        # S·(m ×* f) = −(m × S)·f turns each projected force cross product into a motion cross
        # product with S (or with Sdot = V⁻ × S, already computed) dotted with a subtree sum
        GY = _spatial_add(_motion_cross(before["A+"][d], Sd), _motion_cross(Vp, Sdot))
        q_bar[joints.qposadr[j]] = add(
            add(_spatial_dot(_motion_cross(lam_before["V-"][d], Sd), F[b]), _spatial_dot(GY, G[b])),
            _spatial_dot(Sdot, Y[b]),
        )
        v_bar[d] = add(_spatial_dot(Sd, Y[b]), _mul(2.0, _spatial_dot(Sdot, G[b])))
    return q_bar, v_bar


def bias_and_mass(model, q, v, gravity, external, want_bias=True):
    """Joint-space ``M`` (dict over the tree's nonzero lower triangle) and ``bias`` (list)."""
    joints = model.joints
    nb, nv = model.n_body, model.nv
    parent = model.tree.parent
    _, dof_parent = _structure(model)
    R, x, c0, S = _kinematics(model, q)
    inertia, com = _body_inertias(model, R, x, c0)

    bias = None
    if want_bias:
        V, A = _motions(model, S, v, gravity)
        bias = _joint_forces(model, S, inertia, com, c0, V, A, external)

    # composite inertias, leaves to root
    Ic = list(inertia)
    for b in reversed(range(nb)):
        p = parent[b]
        if p >= 0:
            Ic[p] = _inertia_add(Ic[p], Ic[b])
    M: dict = {}
    dof_body = joints.dof_body
    for e in range(nv):
        Fe = _inertia_apply(Ic[dof_body[e]], S[e])
        d = e
        while d >= 0:
            M[e, d] = _spatial_dot(S[d], Fe)
            d = dof_parent[d]
    for d in range(nv):
        M[d, d] = add(M[d, d], model.dof_armature[d])
    return M, bias, dof_parent


def ltdl_factor(M: dict, dof_parent: Sequence[int]) -> tuple[dict, list]:
    """Featherstone's tree-sparse ``M = Lᵀ D L``: the strictly lower entries of ``L`` (dict over
    the tree's nonzero pattern) and ``D⁻¹`` (list)."""
    n = max(k for k, _ in M) + 1
    M = dict(M)
    lam = dof_parent
    inv_d: list = [None] * n
    for k in reversed(range(n)):
        inv_d[k] = 1.0 / M[k, k]  # final: only descendants (indices > k) update row k
        i = lam[k]
        while i >= 0:
            a = M[k, i] * inv_d[k]
            j = i
            while j >= 0:
                M[i, j] = _sub(M[i, j], _mul(a, M[k, j]))
                j = lam[j]
            M[k, i] = a
            i = lam[i]
    return {(i, j): m for (i, j), m in M.items() if i != j}, inv_d


def ltdl_substitute(L: dict, inv_d: list, dof_parent: Sequence[int], b: list) -> list:
    """Solve ``Lᵀ D L x = b`` with the factor of :func:`ltdl_factor`."""
    n = len(b)
    lam = dof_parent
    x = list(b)
    for i in reversed(range(n)):  # Lᵀ y = b
        j = lam[i]
        while j >= 0:
            x[j] = _sub(x[j], _mul(L[i, j], x[i]))
            j = lam[j]
    x = [_mul(xi, inv_d[i]) for i, xi in enumerate(x)]  # D z = y
    for i in range(n):  # L x = z
        j = lam[i]
        while j >= 0:
            x[i] = _sub(x[i], _mul(L[i, j], x[j]))
            j = lam[j]
    return x


def ltdl_solve(M: dict, dof_parent: Sequence[int], b: list) -> list:
    """Solve ``M x = b`` with Featherstone's tree-sparse ``M = Lᵀ D L``."""
    return ltdl_substitute(*ltdl_factor(M, dof_parent), dof_parent, b)


def stack(values: list, dtype) -> Array:
    """The scalars ``values`` as one JAX array of ``dtype`` (an optimisation barrier first)."""
    # The scalars are materialised before they are stacked: fused into the concatenation, XLA
    # evaluates the work they share once per element of the stack (on a GPU, three such
    # fusions took half of a batched RK4 step, benchmarks/results/step_profile_gpu.md).
    return jnp.stack(jax.lax.optimization_barrier([jnp.asarray(v, dtype) for v in values]))
