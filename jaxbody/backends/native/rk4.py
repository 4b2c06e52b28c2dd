"""The native kernel's RK4 step, joint springs and dampers on lists of scalars.

Written for symbols (:mod:`jaxbody.backends.native.symbolic`) and JAX scalars alike: the code
generator steps the generated acceleration with them, and the JAX fallbacks of the derivative
rules evaluate the same arithmetic. The step is the classical tableau of
:mod:`jaxbody.backends.scalar` (``RK4_C``, ``RK4_A``, ``RK4_B``).
"""

from ..scalar import fourier_series, RK4_A, RK4_B, RK4_C
from .symbolic import sym_atan2, sym_sqrt, where_negative

def qdot_scalars(joints, q: list, v: list) -> list:
    """``q̇`` for joint rates ``v`` on lists of scalars (quaternions: ``q̇ = ½ q ⊗ (0, ω)``), as
    :func:`jaxbody.kinematics.qpos_rate`; works on symbols and on JAX scalars alike."""
    qd = [0.0] * joints.nq
    for kind, _, qa, da in joints.kind_groups():
        for qi, di in zip(qa.tolist(), da.tolist()):
            if kind.quaternion is None:
                qd[qi] = v[di]
                continue
            n = kind.translation
            for k in range(n):
                qd[qi + k] = v[di + k]
            i = qi + kind.quaternion
            aw, ax, ay, az = q[i], q[i + 1], q[i + 2], q[i + 3]
            wx, wy, wz = v[di + n], v[di + n + 1], v[di + n + 2]
            qd[i] = 0.5 * (-(ax * wx) - ay * wy - az * wz)
            qd[i + 1] = 0.5 * (aw * wx + ay * wz - az * wy)
            qd[i + 2] = 0.5 * (aw * wy - ax * wz + az * wx)
            qd[i + 3] = 0.5 * (aw * wz + ax * wy - ay * wx)
    return qd


def _quat_spring_displacement(q: list, r: list) -> list:
    """Rotation vector of ``r⁻¹ ⊗ q/|q|`` on scalars, the short way round, as
    :func:`jaxbody.kernels._quat_log_diff` (MuJoCo's ``mju_subQuat``; the same safe branches)."""
    n = sym_sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    aw, ax, ay, az = (x / n for x in q)
    bw, bx, by, bz = r[0], -r[1], -r[2], -r[3]
    d = [
        bw * aw - bx * ax - by * ay - bz * az,
        bw * ax + bx * aw + by * az - bz * ay,
        bw * ay - bx * az + by * aw + bz * ax,
        bw * az + bx * ay - by * ax + bz * aw,
    ]
    sign = where_negative(d[0], -1.0, 1.0)
    d = [x * sign for x in d]
    s2 = d[1] * d[1] + d[2] * d[2] + d[3] * d[3]
    s = sym_sqrt(where_negative(-s2, s2, 1.0))  # s2 > 0, else 1: no infinite derivative at zero
    scale = where_negative(1e-30 - s2, 2.0 * sym_atan2(s, d[0]) / s, 2.0)
    return [d[1] * scale, d[2] * scale, d[3] * scale]


def _spring_displacements(joints, q: list, reference: list) -> list:
    """``(joint, DoF, q ⊖ q_ref)`` of every DoF on scalars: a coordinate's difference, or for the
    rotation of a ball or free joint a component of the rotation vector of ``q_ref⁻¹ ⊗ q``."""
    out = []
    for kind, js, qa, da in joints.kind_groups():
        for j, qi, di in zip(js.tolist(), qa.tolist(), da.tolist()):
            if kind.quaternion is None:
                out.append((j, di, q[qi] - reference[qi]))
                continue
            n = kind.translation
            for k in range(n):
                out.append((j, di + k, q[qi + k] - reference[qi + k]))
            i = qi + kind.quaternion
            disp = _quat_spring_displacement(q[i : i + 4], reference[i : i + 4])
            for k in range(3):
                out.append((j, di + n + k, disp[k]))
    return out


def spring_potential(joints, q: list, stiffness: list, reference: list):
    """``½ Σ_j k_j |q_j ⊖ q_ref,j|²`` on scalars, as the potential of :class:`jaxbody.JointSprings`."""
    total = 0.0
    for j, _, disp in _spring_displacements(joints, q, reference):
        total = total + stiffness[j] * (disp * disp)
    return 0.5 * total


def joint_force(joints, q: list, v: list, force: list, stiffness: list, reference: list, damping: list) -> tuple:
    """``force`` plus joint springs ``−k (q ⊖ q_ref)`` (quaternion joints: rotation-vector
    difference) and dampers ``−c v`` on lists of scalars, and the dampers' power ``(−c v)·v``;
    as :class:`jaxbody.JointSprings` and :class:`jaxbody.JointDampers`."""
    total = list(force)
    for j, d, disp in _spring_displacements(joints, q, reference):
        total[d] = total[d] - stiffness[j] * disp
    power = 0.0
    for i in range(len(v)):
        damper = -(damping[i] * v[i])
        total[i] = total[i] + damper
        power = power + damper * v[i]
    return total, power


# The classical tableau's only nonzero stage coefficients are on its subdiagonal, and its
# weights are integers over one denominator: the step is written with those.
assert all(a == 0.0 for i, row in enumerate(RK4_A) for a in row[: i - 1])
_RK4_DENOMINATOR = 1.0 / RK4_B[0]
_RK4_WEIGHTS = tuple(b * _RK4_DENOMINATOR for b in RK4_B)
assert _RK4_WEIGHTS == (1.0, 2.0, 2.0, 1.0) and _RK4_DENOMINATOR == 6.0


def rk4_scalars(field, joints, q: list, v: list, h, t0=None, t1=None) -> tuple:
    """One classical RK4 step of ``(q̇, v̇, ẇ) = (q̇(q, v), a, P)`` on lists of scalars, where
    ``field(q, v, t) = (a, P)`` (``P``: the power integrated as work, or a list of powers each
    integrated as its own work; ``t``: the stage's time, ``None`` without ``t0``). Returns ``(q1, v1, k1q, k1v, k4q, k4v, (Δw, k1w, k4w))``, the
    stage increments ``k = h·f`` being those of the first and last stage (the dense output's end
    slopes). The tableau is :data:`~jaxbody.backends.scalar.RK4_A`,
    :data:`~jaxbody.backends.scalar.RK4_B`; the stage times ``t0``, ``t0 + c_i h`` and ``t1``
    (:data:`~jaxbody.backends.scalar.RK4_C`); the same arithmetic, in the same order, as
    :class:`jaxbody.simulation.RK4Stages`."""

    def increment(q, v, t):
        a, power = field(q, v, t)
        work = [h * p for p in power] if isinstance(power, list) else h * power
        return [h * x for x in qdot_scalars(joints, q, v)], [h * x for x in a], work

    def ahead(k, c):
        return [y + c * d for y, d in zip(q, k[0])], [y + c * d for y, d in zip(v, k[1])]

    def combine(k1, k2, k3, k4):
        # (k1 + 2 k2 + 2 k3 + k4) / 6: integer weights, one division
        return (k1 + _RK4_WEIGHTS[1] * k2 + _RK4_WEIGHTS[2] * k3 + k4) / _RK4_DENOMINATOR

    times = [None] * 4 if t0 is None else [t0, t0 + RK4_C[1] * h, t0 + RK4_C[2] * h, t1]
    k1 = increment(q, v, times[0])
    k2 = increment(*ahead(k1, RK4_A[1][0]), times[1])
    k3 = increment(*ahead(k2, RK4_A[2][1]), times[2])
    k4 = increment(*ahead(k3, RK4_A[3][2]), times[3])
    y1 = [[y + combine(a, b, c, d) for y, a, b, c, d in zip(y0, *ks)] for y0, *ks in zip((q, v), k1, k2, k3, k4)]
    if isinstance(k1[2], list):
        work = [combine(*ws) for ws in zip(k1[2], k2[2], k3[2], k4[2])]
    else:
        work = combine(k1[2], k2[2], k3[2], k4[2])
    return y1[0], y1[1], k1[0], k1[1], k4[0], k4[1], [work, k1[2], k4[2]]


def work_count(harmonics) -> int:
    """Works a whole-solve program integrates: the dampers', and a Fourier-series joint torque's
    where it has one (``harmonics`` not ``None``)."""
    return 1 if harmonics is None else 2


def torque_size(nv: int, harmonics: int) -> int:
    """Length of the torque's coefficient row (:func:`torque_row`): ``ω``, then ``c`` ``(nv,)``,
    ``a`` and ``b`` ``(nv, K)`` row by row."""
    return 1 + nv * (1 + 2 * harmonics)


def fourier_torque(coefficients: list, nv: int, harmonics: int, t) -> list:
    """The torque :func:`~jaxbody.backends.scalar.fourier_series` at time ``t`` from its
    coefficient row (:func:`torque_size`) on scalars."""
    omega, offset = coefficients[0], coefficients[1 : 1 + nv]
    rows = lambda start: [coefficients[start + i * harmonics : start + (i + 1) * harmonics] for i in range(nv)]  # noqa: E731
    return fourier_series(t, omega, offset, rows(1 + nv), rows(1 + nv + nv * harmonics))
