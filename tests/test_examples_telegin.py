"""The papers' Examples 1–6 and the planar reference tables T-1 … T-7c (spec §11–§12).

References are the printed table values of the spec and the printed (corrected) equations of
§11 written out here by hand, never the code under test.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody import planar
from jaxbody.examples import (
    CartPendulum,
    OscillatingSupportPendulum,
    VerticalLineDoublePendulum,
    WheelsetPendulum,
    cart_pendulum,
    double_pendulum,
    oscillating_support_pendulum,
    three_link_manipulator,
    vertical_line_double_pendulum,
    wheelset_pendulum,
)

RTOL = 1e-10
G = 9.81


@jax.jit
def evaluate(sysm, t, q, v, tau):
    """Everything the tests read from an example (protocol, tables, reactions), compiled once
    per system type and shape. ``tau`` is always an array here (zeros for no drives)."""
    acc = sysm.acceleration(t, q, v, tau)
    qs, vs = jnp.stack([q, q + 0.1]), jnp.stack([v, -v])
    out = dict(
        acc=acc,
        acc_free=sysm.acceleration(t, q, v, None),
        qdot=sysm.qdot(q, v),
        energy=sysm.total_energy(q, v),
        dE=jax.jvp(sysm.total_energy, (q, v), (v, acc))[1],
        power=sysm.power(t, q, v, tau),
        batch=jax.vmap(lambda qq, vv: sysm.acceleration(t, qq, vv, None))(qs, vs),
    )
    if isinstance(sysm, planar.PlanarSystem):
        out.update(
            M=planar.mass_matrix(sysm, q),
            h=planar.bias_forces(sysm, q, v),
            gen=planar.generalized_forces(sysm, q, tau),
            acc_fd=planar.forward_dynamics(sysm, q, v, tau),
            joint_M=planar.joint_mass_matrix(sysm, q),
            aug=planar.augmented_bodies(sysm, q),
            aug_body=planar.augmented_bodies_in_body_axes(sysm),
        )
        return out
    out.update(
        r=sysm.constraint_force(t, q, v, tau),
        aug_body=planar.augmented_bodies_in_body_axes(sysm.system),
        full_state=sysm.full_state(t, q, v),
    )
    if isinstance(sysm, CartPendulum):
        out["rail"] = sysm.rail_reaction(q, v, tau)
    elif isinstance(sysm, OscillatingSupportPendulum):
        out["support"] = sysm.support_force(t, q, v, tau)
    elif isinstance(sysm, VerticalLineDoublePendulum):
        out["reaction"] = sysm.reaction(q, v, tau)
        out["end"] = sysm.end_point(q)
    elif isinstance(sysm, WheelsetPendulum):
        out["friction"] = sysm.friction_force(q, v, tau)
        out["normal"] = sysm.normal_force(q, v, tau)
    return out


def a(*x):
    return jnp.asarray(np.asarray(x, dtype=np.float64))


def close(actual, expected, rtol=RTOL):
    np.testing.assert_allclose(np.asarray(actual), np.asarray(expected, dtype=np.float64), rtol=rtol, atol=0)


# --------------------------------------------------------------------------- T-1, T-3
T1_M = [[0.594, 0.100325766146], [0.100325766146, 0.074]]
T1_H = [2.69991779907, -0.912681153405]
T1_ACC = [-6.03982668881, 17.8193431534]
T3_ACC = [-8.59701934893, 23.9889690021]


def test_table_t1_two_link_chain():
    # same body names as Example 1 so both tests share one compilation
    s = planar.chain([1.0, 0.6], [0.4, 0.3], [0.8], [0.05, 0.02], gravity=G, names=("link1", "link2"))
    q, v = a(0.3, -0.5), a(0.8, -1.2)
    out = evaluate(s, 0.0, q, v, a(0.7, -0.2))
    ab = out["aug_body"]
    close(jnp.linalg.norm(ab.static_moment, axis=-1), [0.88, 0.18])
    close(ab.augmented_inertia, [0.594, 0.074])
    close(out["M"], T1_M)
    close(out["h"], T1_H)
    # tau are the hinge torques M_k; the absolute-angle right-hand side is (M1 - M2, M2)
    close(out["gen"], [0.9, -0.2], rtol=1e-14)
    close(out["acc"], T1_ACC)
    close(out["acc_fd"], T1_ACC)


def test_table_t3_example1_double_pendulum():
    s = double_pendulum()
    q, v = a(0.3, -0.5), a(0.8, -1.2)
    out = evaluate(s, 0.0, q, v, jnp.zeros(2))
    close(out["acc_free"], T3_ACC)
    close(out["acc"], T3_ACC)
    # eq. (15) as printed, with the spec's (md)_k and J_k
    md1, md2, J1, J2, L1 = 0.88, 0.18, 0.594, 0.074, 0.8
    (a1, a2), (w1, w2) = np.asarray(q), np.asarray(v)
    e1, e2 = T3_ACC
    r1 = J1 * e1 + L1 * md2 * (math.cos(a2 - a1) * e2 - math.sin(a2 - a1) * w2**2) + md1 * G * math.sin(a1)
    r2 = md2 * L1 * (math.cos(a2 - a1) * e1 + math.sin(a2 - a1) * w1**2) + J2 * e2 + md2 * G * math.sin(a2)
    assert abs(r1) < 1e-9 and abs(r2) < 1e-9


# --------------------------------------------------------------------------- T-2
TABLE_T2 = dict(mass=[2.0, 1.5, 0.8], com_distance=[0.35, 0.25, 0.15], length=[0.7, 0.5], inertia=[0.09, 0.04, 0.01])
T2_Q, T2_V, T2_TAU = (0.3, -0.5, 1.1), (0.8, -1.2, 2.0), (3.0, -1.0, 0.5)


def test_table_t2_three_link_chain():
    s = planar.chain(**TABLE_T2, gravity=G, names=("shoulder", "forearm", "hand"))
    q, v = a(*T2_Q), a(*T2_V)
    out = evaluate(s, 0.0, q, v, a(*T2_TAU))
    ab = out["aug_body"]
    close(jnp.linalg.norm(ab.static_moment, axis=-1), [2.31, 0.775, 0.12])
    close(ab.augmented_inertia, [1.462, 0.33375, 0.028])
    close(
        out["M"],
        [
            [1.462, 0.377963389821, 0.0585233635852],
            [0.377963389821, 0.33375, -0.00175197133808],
            [0.0585233635852, -0.00175197133808, 0.028],
        ],
    )
    close(out["h"], [7.01617988684, -4.13391621311, 1.17405752701])
    close(out["acc"], [-5.0619699013, 13.5580578134, -12.6450247619])
    close(
        out["joint_M"],
        [
            [2.69321956414, 0.79473281073, 0.0847713922471],
            [0.79473281073, 0.358246057324, 0.0262480286619],
            [0.0847713922471, 0.0262480286619, 0.028],
        ],
    )


# --------------------------------------------------------------------------- T-4 (Example 2)
T4_ACC = [4.45796445019, -8.05909520248, 3.57347853845]


def _eq16_residuals(q, v, acc, tau, printed):
    """Left minus right sides of eq. (16), written from the spec (``printed``: s31 in eq. 3)."""
    md = [2.31, 0.775, 0.12]
    J = [1.462, 0.33375, 0.028]
    L1, L2 = 0.7, 0.5
    (a1, a2, a3), (w1, w2, w3), (e1, e2, e3) = q, v, acc
    M1, M2, M3 = tau
    c = lambda i, j: math.cos([a1, a2, a3][i - 1] - [a1, a2, a3][j - 1])  # noqa: E731
    s = lambda i, j: math.sin([a1, a2, a3][i - 1] - [a1, a2, a3][j - 1])  # noqa: E731
    r1 = J[0] * e1 + L1 * (md[1] * (c(2, 1) * e2 - s(2, 1) * w2**2) + md[2] * (c(3, 1) * e3 - s(3, 1) * w3**2)) - (M1 - M2)
    r2 = md[1] * L1 * (c(2, 1) * e1 + s(2, 1) * w1**2) + J[1] * e2 + L2 * md[2] * (c(3, 2) * e3 - s(3, 2) * w3**2) - (M2 - M3)
    last = s(3, 1) if printed else s(3, 2)
    r3 = md[2] * (L1 * (c(3, 1) * e1 + s(3, 1) * w1**2) + L2 * (c(3, 2) * e2 + last * w2**2)) + J[2] * e3 - M3
    return np.array([r1, r2, r3])


def test_table_t4_example2_manipulator_corrected_eq16():
    s = three_link_manipulator()
    q, v, tau = a(*T2_Q), a(*T2_V), a(*T2_TAU)
    acc = evaluate(s, 0.0, q, v, tau)["acc"]
    close(acc, T4_ACC)
    # horizontal plane: no gravity terms at all
    assert float(jnp.max(jnp.abs(evaluate(s, 0.0, q, jnp.zeros(3), tau)["h"]))) == 0.0
    res = _eq16_residuals(T2_Q, T2_V, np.asarray(acc), T2_TAU, printed=False)
    assert np.max(np.abs(res)) < 1e-9


def test_example2_printed_s31_is_not_what_we_compute():
    s = three_link_manipulator()
    q, v, tau = a(*T2_Q), a(*T2_V), a(*T2_TAU)
    acc = np.asarray(evaluate(s, 0.0, q, v, tau)["acc"])
    res = _eq16_residuals(T2_Q, T2_V, acc, T2_TAU, printed=True)
    a1, a2, a3 = T2_Q
    expected_gap = 0.12 * 0.5 * (math.sin(a3 - a1) - math.sin(a3 - a2)) * T2_V[1] ** 2
    assert abs(res[2]) > 1e-2
    np.testing.assert_allclose(res[2], expected_gap, rtol=1e-9)
    # solving the printed equations gives different accelerations
    A = np.array(
        [[1.462, 0.7 * 0.775 * math.cos(a2 - a1), 0.7 * 0.12 * math.cos(a3 - a1)],
         [0.775 * 0.7 * math.cos(a2 - a1), 0.33375, 0.5 * 0.12 * math.cos(a3 - a2)],
         [0.12 * 0.7 * math.cos(a3 - a1), 0.12 * 0.5 * math.cos(a3 - a2), 0.028]]
    )
    rhs = -_eq16_residuals(T2_Q, T2_V, np.zeros(3), T2_TAU, printed=True)
    printed_acc = np.linalg.solve(A, rhs)
    assert np.max(np.abs(printed_acc - acc)) > 1e-2


# --------------------------------------------------------------------------- T-5 (Example 3)
def test_table_t5_example3_cart_pendulum():
    c = cart_pendulum()
    assert (c.nq, c.nv) == (2, 2)
    q, v = a(0.0, 0.6), a(0.0, -1.3)
    out = evaluate(c, 0.0, q, v, jnp.zeros(2))
    xdd, phdd = np.asarray(out["acc"])
    close(xdd, 0.695188583695)
    close(phdd, -13.5842368027)
    close(out["r"][1], 33.0799160243)
    close(out["rail"], 33.0799160243)
    close(out["acc_free"], np.asarray(out["acc"]), rtol=1e-14)
    # the three printed equations (17) in φ form, M = 3.5, (md)_1 = 0.2, J_1 = 0.09
    ph, w = 0.6, -1.3
    assert abs(3.5 * xdd + 0.2 * (phdd * math.cos(ph) - w**2 * math.sin(ph))) < 1e-10
    assert abs(0.2 * xdd * math.cos(ph) + 0.09 * phdd + 0.2 * G * math.sin(ph)) < 1e-10
    Fr = 0.2 * (phdd * math.sin(ph) + w**2 * math.cos(ph)) + 3.5 * G
    close(out["r"][1], Fr, rtol=1e-12)
    ab = out["aug_body"]
    close(jnp.linalg.norm(ab.static_moment, axis=-1), [0.2])
    close(ab.augmented_inertia, [0.09])


def test_example3_rail_reaction_is_newton_for_the_whole_system():
    """F_r − M g = vertical rate of momentum, from CM positions differentiated here."""
    c = cart_pendulum()
    q, v = a(0.3, 1.1), a(-0.4, 2.2)
    tau = a(1.5, -0.3)
    out = evaluate(c, 0.0, q, v, tau)
    acc = out["acc"]

    def pend_com(qq):
        x, ph = qq
        return jnp.stack([x + 0.4 * jnp.sin(ph), -0.4 * jnp.cos(ph)])

    _, vel = jax.jvp(pend_com, (q,), (v,))
    _, acc_c = jax.jvp(lambda qq: jax.jvp(pend_com, (qq,), (v,))[1], (q,), (v,))
    acc_c = acc_c + jax.jvp(pend_com, (q,), (acc,))[1]
    # cart: no vertical acceleration; horizontal: the applied force
    close(out["rail"] - 3.5 * G, 0.5 * acc_c[1], rtol=1e-10)
    close(tau[0], 3.0 * acc[0] + 0.5 * acc_c[0], rtol=1e-10)
    del vel


# --------------------------------------------------------------------------- T-6 (Example 4)
def test_table_t6_example4_oscillating_support():
    p = oscillating_support_pendulum()
    assert (p.nq, p.nv) == (1, 1)
    for w in (0.0, 2.0):  # the equation does not depend on φ̇
        close(evaluate(p, 0.3, a(0.4), a(w), a(0.0))["acc"], [-15.5342748111])
    # printed equation: J φ̈ − (md) a0 ω² sin ωt cos(φ − β) + (md) g sin φ = 0
    md, J, a0, om, beta = 0.2, 0.09, 0.05, 12.0, 0.5
    t, ph = 0.7, -0.9
    ref = (md * a0 * om**2 * math.sin(om * t) * math.cos(ph - beta) - md * G * math.sin(ph)) / J
    close(evaluate(p, t, a(ph), a(0.3), a(0.0))["acc_free"], [ref], rtol=1e-12)


def test_example4_support_force_and_energy_rate():
    p = oscillating_support_pendulum()
    t, q, v, tau = 0.41, a(0.7), a(-1.2), a(0.3)
    out = evaluate(p, t, q, v, tau)
    acc = out["acc"]
    # Newton for the pendulum: F + m g = m a_C, with a_C from the pivot motion differentiated here
    a0, om, beta = 0.05, 12.0, 0.5

    def com(tt, ph):
        s = a0 * jnp.sin(om * tt)
        return jnp.stack([s * math.cos(beta) + 0.4 * jnp.sin(ph), s * math.sin(beta) - 0.4 * jnp.cos(ph)])

    def vel(tt, ph, w):
        return jax.jvp(com, (tt, ph), (jnp.ones_like(tt), w))[1]

    tt = jnp.asarray(t)
    acc_c = jax.jvp(lambda s_, x_: vel(s_, x_, v[0]), (tt, q[0]), (jnp.ones_like(tt), v[0]))[1]
    acc_c = acc_c + jax.jvp(lambda x_: com(tt, x_), (q[0],), (acc[0],))[1]
    close(out["support"], 0.5 * acc_c - 0.5 * a(0.0, -G), rtol=1e-10)
    close(out["r"][:2], np.asarray(out["support"]), rtol=1e-14)
    # dE/dt = power (energy relative to the support; power includes the inertial force)
    close(out["dE"], out["power"], rtol=1e-10)


# --------------------------------------------------------------------------- T-7 (Example 5)
def test_table_t7_example5_vertical_line():
    e = vertical_line_double_pendulum()
    assert (e.nq, e.nv) == (1, 1)
    q, v = a(0.5), a(1.1)
    out = evaluate(e, 0.0, q, v, a(0.0))
    ab = out["aug_body"]
    close(jnp.linalg.norm(ab.static_moment, axis=-1), [0.88, 0.18])
    close(ab.augmented_inertia, [0.594, 0.074])
    reaction = out["reaction"]
    close(out["acc"], [-10.301840335])
    close(reaction, -1.47047546454)
    # spec's closed forms (difference and sum of eq. 18)
    L, md1, md2, J1, J2, ph, w = 0.8, 0.88, 0.18, 0.594, 0.074, 0.5, 1.1
    phdd = -(2 * L * md2 * w**2 * math.sin(2 * ph) + (md1 + md2) * G * math.sin(ph)) / (
        J1 + J2 - 2 * L * md2 * math.cos(2 * ph)
    )
    close(out["acc"], [phdd], rtol=1e-12)
    Fr = (J1 - J2) * phdd / (2 * L * math.cos(ph)) + (md1 - md2) * G * math.tan(ph) / (2 * L)
    close(reaction, Fr, rtol=1e-12)
    # both rows of the free equations carry L F_r cos φ (spec: H_1 = H_2 = L F_r cos φ)
    close(out["r"], [L * Fr * math.cos(ph)] * 2, rtol=1e-10)
    # the end point stays on the vertical through O_1
    assert abs(float(evaluate(e, 0.0, a(0.93), v, a(0.0))["end"][0])) < 1e-15


def test_example5_drives():
    e = vertical_line_double_pendulum()
    q, v = a(0.3), a(-0.4)
    Q = a(0.5 - 2 * 0.2)
    close(e.generalized_force(a(0.5, 0.2)), Q, rtol=1e-12)
    out = evaluate(e, 0.0, q, v, Q)
    # power with hinge torques = (M1 − M2) α̇1 + M2 α̇2 on α = (φ, −φ)
    close(out["power"], (0.5 - 0.2) * -0.4 + 0.2 * 0.4, rtol=1e-12)
    close(out["dE"], out["power"], rtol=1e-10)


# --------------------------------------------------------------------------- T-7b (Example 6)
# J_2 = I_C2 + m_02 a_2² = 0.015 + 0.7·0.35² = 0.10075; the spec's header of T-7b prints the
# rounded "0.1007", while its accelerations were computed with 0.10075 (checked below).
WS = dict(M=4.7, md2=0.245, J1=0.12, J2=0.10075, R=0.25)


def _printed_eq19(sign, ph, w):
    """Solve ``(M ± J_1/R²) ẍ + (md)(φ̈ cos φ − φ̇² sin φ) = 0``, ``(md) ẍ cos φ + J_2 φ̈ + (md) g sin φ = 0``."""
    M, md, J1, J2, R = WS["M"], WS["md2"], WS["J1"], WS["J2"], WS["R"]
    A = np.array([[M + sign * J1 / R**2, md * math.cos(ph)], [md * math.cos(ph), J2]])
    b = np.array([md * w**2 * math.sin(ph), -md * G * math.sin(ph)])
    return np.linalg.solve(A, b)


def test_table_t7b_example6_wheelset_corrected():
    ws = wheelset_pendulum()
    assert (ws.nq, ws.nv) == (2, 2)
    q, v = a(0.0, 0.5), a(0.0, -0.9)
    out = evaluate(ws, 0.0, q, v, jnp.zeros(2))
    acc = np.asarray(out["acc"])
    friction = out["friction"]
    close(acc, [0.414561700697, -12.3216801985])
    close(friction, 0.795958465338)
    close(friction, WS["J1"] * acc[0] / WS["R"] ** 2, rtol=1e-12)
    # the corrected closed form (M + J1/R²) is what the code solves
    close(acc, _printed_eq19(+1.0, 0.5, -0.9), rtol=1e-12)
    ab = out["aug_body"]
    close(jnp.linalg.norm(ab.static_moment, axis=-1)[1], 0.245)
    close(ab.augmented_inertia[1], 0.10075)
    np.testing.assert_allclose(ab.augmented_inertia[1], 0.1007, rtol=1e-3)  # as printed, rounded
    # horizontal residual of the free equations = friction −F_r (eq. 19, first row)
    close(out["r"][0], -friction, rtol=1e-12)
    close(out["normal"], out["r"][1], rtol=1e-14)


def test_example6_printed_minus_sign_is_not_reproduced():
    ws = wheelset_pendulum()
    printed = _printed_eq19(-1.0, 0.5, -0.9)
    np.testing.assert_allclose(printed, [1.10039044329, -13.7852879356], rtol=1e-10)
    acc = np.asarray(evaluate(ws, 0.0, a(0.0, 0.5), a(0.0, -0.9), jnp.zeros(2))["acc"])
    assert np.all(np.abs(acc - printed) > 0.1)


def test_example6_rolling_kinematics_and_energy():
    ws = wheelset_pendulum()
    q, v = a(0.2, 0.4), a(0.7, -0.3)
    out = evaluate(ws, 0.0, q, v, jnp.zeros(2))
    Q, V, _, _ = out["full_state"]
    # contact point velocity ẋ + R α̇_1 = 0 (no slip), y ≡ 0
    assert abs(float(V[0] + 0.25 * V[2])) < 1e-15 and float(Q[1]) == 0.0
    assert abs(float(out["dE"])) < 1e-12


# --------------------------------------------------------------------------- T-7c
def test_table_t7c_tree_on_translating_base():
    s = planar.from_parents(
        [-1, 0, 0],
        [1.2, 0.8, 0.5],
        [[0.30, 0.05], [0.20, -0.04], [0.10, 0.03]],
        [[0.0, 0.0], [0.6, 0.0], [0.5, 0.1]],
        [0.04, 0.02, 0.01],
        gravity=(0.0, -G),
        base_mass=2.0,
    )
    q = a(0.0, 0.0, 0.4, -0.7, 1.3)
    v = a(0.0, 0.0, 0.5, -1.1, 0.9)
    out = evaluate(s, 0.0, q, v, a(2.0, 40.0, 1.5, -0.4, 0.3))
    ab = out["aug"]
    close(ab.subtree_mass, [2.5, 0.8, 0.5])
    close(ab.static_moment[:, 0], [0.961120465809, 0.101759783974, -0.00107843135003])
    close(ab.static_moment[:, 1], [0.525782702457, -0.127549779951, 0.0521903917002])
    close(ab.augmented_inertia, [0.569, 0.05328, 0.01545])
    M = np.asarray(out["M"])
    ref = np.array(
        [
            [4.5, 0.0, -0.525782702457, 0.127549779951, -0.0521903917002],
            [0.0, 4.5, 0.961120465809, 0.101759783974, -0.00107843135003],
            [-0.525782702457, 0.961120465809, 0.569, 0.0264340463437, 0.0145143468851],
            [0.127549779951, 0.101759783974, 0.0264340463437, 0.05328, 0.0],
            [-0.0521903917002, -0.00107843135003, 0.0145143468851, 0.0, 0.01545],
        ]
    )
    nz = ref != 0
    close(M[nz], ref[nz])
    assert np.all(M[~nz] == 0.0)
    acc = out["acc_fd"]
    close(acc, [-1.04664923106, 4.28103775806, -22.1246695804, -20.4953134398, 37.2892081251])
    # the same through the simulation protocol
    close(out["acc"], np.asarray(acc), rtol=1e-14)


# --------------------------------------------------------------------------- protocol
ALL = {
    "double_pendulum": (double_pendulum, (0.3, -0.5), (0.8, -1.2)),
    "three_link_manipulator": (three_link_manipulator, T2_Q, T2_V),
    "cart_pendulum": (cart_pendulum, (0.1, 0.6), (0.2, -1.3)),
    "oscillating_support_pendulum": (oscillating_support_pendulum, (0.4,), (0.5,)),
    "vertical_line_double_pendulum": (vertical_line_double_pendulum, (0.5,), (1.1,)),
    "wheelset_pendulum": (wheelset_pendulum, (0.0, 0.5), (0.1, -0.9)),
}


@pytest.mark.parametrize("name", sorted(ALL))
def test_protocol(name):
    make, q0, v0 = ALL[name]
    sysm = make()
    assert isinstance(sysm.nq, int) and isinstance(sysm.nv, int)
    q, v = a(*q0), a(*v0)
    out = evaluate(sysm, 0.2, q, v, jnp.asarray(np.full(sysm.nv, 0.3)))
    assert out["qdot"].shape == (sysm.nq,)
    assert out["acc"].shape == (sysm.nv,) and bool(jnp.all(jnp.isfinite(out["acc"])))
    assert out["energy"].shape == ()
    np.testing.assert_allclose(out["dE"], out["power"], rtol=1e-9, atol=1e-12)
    assert out["batch"].shape == (2, sysm.nv)
    np.testing.assert_allclose(out["batch"][0], out["acc_free"], rtol=1e-12, atol=1e-12)


def test_double_pendulum_demo_ten_seconds():
    """What ``jaxbody demo`` does: simulate Example 1 for 10 s; energy is conserved."""
    s = jb.examples.double_pendulum()
    sol = jb.simulate(s, jnp.array([1.2, -0.4]), jnp.array([0.0, 0.5]), 10.0, n_save=51)
    assert sol.q.shape == (51, 2)
    assert bool(jnp.all(jnp.isfinite(sol.q)))
    assert float(sol.energy_drift) < 1e-6


@jax.jit
def _acceleration(sysm, q, v):
    return sysm.acceleration(0.0, q, v)


def test_examples_build_in_float32():
    s = double_pendulum(mass=np.asarray([1.0, 0.6], np.float32))
    assert s.body_mass.dtype == jnp.float32 and s.hinge_pos.dtype == jnp.float32
    f32 = lambda *x: jnp.asarray(x, jnp.float32)  # noqa: E731
    acc = _acceleration(s, f32(0.3, -0.5), f32(0.8, -1.2))
    assert acc.dtype == jnp.float32
    np.testing.assert_allclose(acc, T3_ACC, rtol=1e-5)
    ws = wheelset_pendulum(wheel_mass=np.float32(4.0))
    acc = _acceleration(ws, f32(0.0, 0.5), f32(0.0, -0.9))
    assert acc.dtype == jnp.float32
    np.testing.assert_allclose(acc, [0.414561700697, -12.3216801985], rtol=1e-5)


def test_example_gradient_wrt_parameters():
    """d φ̈/d a_0 of Example 4 against central differences (parameters are traced fields)."""

    @jax.jit
    def f(amp):
        p = oscillating_support_pendulum(amplitude=amp)
        return p.acceleration(0.3, a(0.4), a(0.0))[0]

    g = jax.jit(jax.grad(f))(jnp.asarray(0.05))
    h = 1e-6
    fd = (f(jnp.asarray(0.05 + h)) - f(jnp.asarray(0.05 - h))) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-7)


def test_example_errors():
    with pytest.raises(ValueError, match="length must be a scalar"):
        vertical_line_double_pendulum(length=(0.8, 0.8))
    with pytest.raises(ValueError, match=r"CartPendulum: tau has shape \(3,\), expected \(2,\)"):
        cart_pendulum().acceleration(0.0, a(0.0, 0.1), a(0.0, 0.0), a(1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match=r"planar body 1 \('link2'\): body_mass is negative"):
        double_pendulum(mass=(1.0, -0.6))
    with pytest.raises(ValueError, match=r"planar body 0 \('wheelset'\): body_inertia is negative"):
        wheelset_pendulum(wheel_inertia=-0.1)
