"""Ready constraints on spatial models: Example 5, a four-bar linkage, a rolling wheel on a
free body, knife edge, prescribed motion.

References: the spec's table T-7 (Example 5), planar Newton–Euler equations of the four-bar
written here (pin forces as unknowns), the disk example of Maggi's paper (an independent
set of coordinates), and analytic conditions.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
from scipy.spatial.transform import Rotation

import jaxbody as jb
from jaxbody import constraints as jc
from jaxbody import maggi
from jaxbody.examples import disk as dk
from _support.jaxpr_tools import count_eqns

Y_DOWN = (0.0, -1.0, 0.0)  # hinge axis: angle α maps local +x to (cos α, 0, sin α), local −z to (sin α, 0, −cos α)


def example5(m1=1.0, m2=0.6, a1=0.4, a2=0.3, L=0.8, I1=0.05, I2=0.02):
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    b.add_body("link1", mass=m1, com=(0, 0, -a1), inertia=(I1, I1, 2 * I1), joints=[jb.Hinge(axis=Y_DOWN)])
    b.add_body("link2", parent="link1", pos=(0, 0, -L), mass=m2, com=(0, 0, -a2), inertia=(I2, I2, 2 * I2),
               joints=[jb.Hinge(axis=Y_DOWN)])
    model = b.build()
    end_on_vertical = jc.PointOnPlane(model, "link2", (0, 0, -L), normal=(1, 0, 0))
    return maggi.constrain(model, [end_on_vertical], q_ref=jnp.array([0.5, -1.0]))


def test_example5_table_t7():
    s = example5()
    phi, dphi = 0.5, 1.1
    q = jnp.array([phi, -2 * phi])
    v = jnp.array([dphi, -2 * dphi])
    r = s.solve(0.0, q, v)
    np.testing.assert_allclose(r.xdot[0], -10.301840335, rtol=1e-9)
    np.testing.assert_allclose(r.xdot[1], -2 * r.xdot[0], rtol=1e-12)
    np.testing.assert_allclose(r.reactions, [-1.47047546454], rtol=1e-9)
    assert int(r.result._value) == 0


def test_example5_reaction_gradient_wrt_mass():
    """∂F_r/∂m₂ through the model parameters vs the closed form of the spec, and vs FD."""
    q = jnp.array([0.5, -1.0])
    v = jnp.array([1.1, -2.2])

    def fr(m2):
        return example5(m2=m2).solve(0.0, q, v).reactions[0]

    def closed_form(m2, m1=1.0, a1=0.4, a2=0.3, L=0.8, I1=0.05, I2=0.02, g=9.81, phi=0.5, dphi=1.1):
        md1, md2 = m1 * a1 + m2 * L, m2 * a2
        J1, J2 = I1 + m1 * a1**2 + m2 * L**2, I2 + m2 * a2**2
        ddphi = (-(md1 + md2) * g * jnp.sin(phi) - 2 * L * md2 * dphi**2 * jnp.sin(2 * phi)) / (
            J1 + J2 - 2 * L * md2 * jnp.cos(2 * phi))
        return (J1 - J2) * ddphi / (2 * L * jnp.cos(phi)) + (md1 - md2) * g * jnp.tan(phi) / (2 * L)

    m2 = 0.6
    np.testing.assert_allclose(fr(m2), closed_form(m2), rtol=1e-10)
    # the model is rebuilt from a float in example5, so differentiate through the parameters
    model = example5().base.model
    s = example5()

    def fr_param(m2):
        mdl = jax.tree_util.tree_map(lambda x: x, model)
        mdl = eqx_set_mass(mdl, 1, m2)
        sys = maggi.ConstrainedSystem(base=maggi.ModelBase(mdl), constraints=s.constraints, epsilon=None,
                                      free=s.free, baumgarte=s.baumgarte)
        return sys.solve(0.0, q, v).reactions[0]

    np.testing.assert_allclose(jax.grad(fr_param)(m2), jax.grad(closed_form)(m2), rtol=1e-8)


def eqx_set_mass(model, body, mass):
    import equinox as eqx

    return eqx.tree_at(lambda m: m.body_mass, model, model.body_mass.at[body].set(mass))


# ------------------------------------------------------------------------------ four-bar
D_GROUND, L1, L2, L3 = 1.0, 0.4, 1.0, 0.7
MASS = (0.5, 1.2, 0.9)
INER = tuple(m * l**2 / 12 for m, l in zip(MASS, (L1, L2, L3)))
G = 9.81


@functools.lru_cache
def four_bar():
    b = jb.ModelBuilder(gravity=(0, 0, -G))
    for name, parent, pos, m, l, I in (
        ("crank", None, (0, 0, 0), MASS[0], L1, INER[0]),
        ("coupler", "crank", (L1, 0, 0), MASS[1], L2, INER[1]),
        ("rocker", None, (D_GROUND, 0, 0), MASS[2], L3, INER[2]),
    ):
        b.add_body(name, parent=parent, pos=pos, mass=m, com=(l / 2, 0, 0), inertia=(I / 10, I, I),
                   joints=[jb.Hinge(axis=Y_DOWN)])
    model = b.build()
    loop = jc.LoopClosure(model, "coupler", (L2, 0, 0), "rocker", (L3, 0, 0), axes=[(1, 0, 0), (0, 0, 1)])
    th = four_bar_angles(0.6)
    return maggi.constrain(model, [loop], q_ref=jnp.array([th[0], th[1] - th[0], th[2]]))


def _e(t):
    return np.array([np.cos(t), np.sin(t)])


def _n(t):
    return np.array([-np.sin(t), np.cos(t)])


def four_bar_angles(t1):
    def closure(z):
        return L1 * _e(t1) + L2 * _e(z[0]) - (np.array([D_GROUND, 0]) + L3 * _e(z[1]))

    z = scipy.optimize.fsolve(closure, [0.3, 1.6], xtol=1e-14)
    return np.array([t1, z[0], z[1]])


def four_bar_rates(th, w1):
    # l2 ω2 n2 − l3 ω3 n3 = −l1 ω1 n1
    Amat = np.stack([L2 * _n(th[1]), -L3 * _n(th[2])], axis=1)
    w23 = np.linalg.solve(Amat, -L1 * w1 * _n(th[0]))
    return np.array([w1, *w23])


def four_bar_newton_euler(th, w, crank_acceleration=None):
    """Planar Newton–Euler with pin forces: unknowns (α1, α2, α3, F01, F12, FL, F03).

    With ``crank_acceleration`` the crank is driven: α1 is given and the drive torque τ on
    the crank (about the hinge axis) is a twelfth unknown, returned last."""
    driven = crank_acceleration is not None
    n_unknown = 12 if driven else 11
    cross = lambda r, f: r[0] * f[1] - r[1] * f[0]
    g = np.array([0.0, -G])

    def residual(z):
        al, F01, F12, FL, F03 = z[:3], z[3:5], z[5:7], z[7:9], z[9:11]
        e, n = [_e(t) for t in th], [_n(t) for t in th]
        aB = al[0] * L1 * n[0] - w[0] ** 2 * L1 * e[0]
        ac1 = 0.5 * (al[0] * L1 * n[0] - w[0] ** 2 * L1 * e[0])
        ac2 = aB + 0.5 * (al[1] * L2 * n[1] - w[1] ** 2 * L2 * e[1])
        aC2 = aB + al[1] * L2 * n[1] - w[1] ** 2 * L2 * e[1]
        ac3 = 0.5 * (al[2] * L3 * n[2] - w[2] ** 2 * L3 * e[2])
        aC3 = al[2] * L3 * n[2] - w[2] ** 2 * L3 * e[2]
        return np.concatenate([
            MASS[0] * ac1 - (F01 - F12 + MASS[0] * g),
            MASS[1] * ac2 - (F12 + FL + MASS[1] * g),
            MASS[2] * ac3 - (F03 - FL + MASS[2] * g),
            [INER[0] * al[0] - (cross(-0.5 * L1 * e[0], F01) + cross(0.5 * L1 * e[0], -F12) + (z[11] if driven else 0.0))],
            [INER[1] * al[1] - (cross(-0.5 * L2 * e[1], F12) + cross(0.5 * L2 * e[1], FL))],
            [INER[2] * al[2] - (cross(-0.5 * L3 * e[2], F03) + cross(0.5 * L3 * e[2], -FL))],
            aC2 - aC3,
            [al[0] - crank_acceleration] if driven else [],
        ])

    r0 = residual(np.zeros(n_unknown))
    Amat = np.stack([residual(np.eye(n_unknown)[i]) - r0 for i in range(n_unknown)], axis=1)
    return np.linalg.solve(Amat, -r0)


@pytest.mark.parametrize("t1,w1", [(0.6, 1.5), (2.0, -3.0), (4.0, 0.7)])
def test_four_bar_against_planar_newton_euler(t1, w1):
    s = four_bar()
    th = four_bar_angles(t1)
    w = four_bar_rates(th, w1)
    q = jnp.array([th[0], th[1] - th[0], th[2]])
    v = jnp.array([w[0], w[1] - w[0], w[2]])
    np.testing.assert_allclose(s.constraint_residual(0.0, q, v), 0.0, atol=1e-12)
    np.testing.assert_allclose(s.position_residual(0.0, q), 0.0, atol=1e-12)
    r = s.solve(0.0, q, v)
    ref = four_bar_newton_euler(th, w)
    al = np.array([r.xdot[0], r.xdot[0] + r.xdot[1], r.xdot[2]])
    np.testing.assert_allclose(al, ref[:3], rtol=1e-10, atol=1e-10)
    # the loop reaction is the pin force on the coupler, (x, z) components
    np.testing.assert_allclose(r.reactions, ref[7:9], rtol=1e-10, atol=1e-10)


@pytest.mark.slow
def test_four_bar_long_run_drift_is_bounded():
    s = four_bar()
    th = four_bar_angles(0.6)
    w = four_bar_rates(th, 2.0)
    q0 = jnp.array([th[0], th[1] - th[0], th[2]])
    v0 = jnp.array([w[0], w[1] - w[0], w[2]])
    sol = jb.simulate(s, q0, v0, 20.0, rtol=1e-9, atol=1e-9, n_save=401)
    pos, vel = maggi.constraint_residuals(s, sol.t, sol.q, sol.v)
    assert float(jnp.max(jnp.abs(pos))) < 1e-8
    assert float(jnp.max(jnp.abs(vel))) < 1e-7
    assert float(sol.energy_drift) < 1e-6
    # without stabilisation the residuals grow but stay at the integrator's error level
    s0 = maggi.ConstrainedSystem(base=s.base, constraints=s.constraints, epsilon=None, free=s.free,
                                 baumgarte=jnp.asarray(0.0))
    sol0 = jb.simulate(s0, q0, v0, 20.0, rtol=1e-9, atol=1e-9, n_save=401)
    pos0, _ = maggi.constraint_residuals(s0, sol0.t, sol0.q, sol0.v)
    assert float(jnp.max(jnp.abs(pos0))) < 1e-5
    # projection puts a drifted state back on the manifold
    qp = maggi.project_positions(s0, sol0.q[-1])
    np.testing.assert_allclose(s0.position_residual(0.0, qp), 0.0, atol=1e-13)


def test_redundant_and_inconsistent_constraints_are_named():
    s = four_bar()
    model = s.base.model
    full = jc.LoopClosure(model, "coupler", (L2, 0, 0), "rocker", (L3, 0, 0))  # y row is identically zero
    th = four_bar_angles(0.6)
    q = jnp.array([th[0], th[1] - th[0], th[2]])
    with pytest.raises(ValueError, match=r"constraints are redundant: row 'loop coupler-rocker\[1\]'"):
        maggi.constrain(model, [full], q_ref=q)
    twice = jc.PointOnPlane(model, "coupler", (L2, 0, 0), normal=(1, 0, 0), origin=(5.0, 0, 0))
    with pytest.raises(ValueError, match=r"constraints are redundant: row 'again' depends on \[\"point of 'coupler' on plane\"\]"):
        maggi.constrain(model, [twice, jc.PointOnPlane(model, "coupler", (L2, 0, 0), normal=(2, 0, 0), label="again")], q_ref=q)
    drive = jc.PrescribedCoordinate(model, 0, lambda t, p: 0.6 + 2.0 * t)
    drive2 = jc.PrescribedCoordinate(model, 0, lambda t, p: 0.6 + 3.0 * t)
    with pytest.raises(ValueError, match=r"constraints are inconsistent: row \"prescribed 'crank_hinge0'\" depends on"):
        maggi.constrain(model, [drive, drive2], q_ref=q)


def test_prescribed_crank_drives_the_four_bar():
    s = four_bar()
    model = s.base.model
    drive = jc.PrescribedCoordinate(model, "crank_hinge0", lambda t, p: 0.6 + 2.0 * t)
    th = four_bar_angles(0.6)
    w = four_bar_rates(th, 2.0)
    q0 = jnp.array([th[0], th[1] - th[0], th[2]])
    # the reference must close the loop (and meet the drive at t = 0)
    driven = maggi.constrain(s, [drive], q_ref=q0)
    assert driven.n_constraint == 3
    v0 = jnp.array([w[0], w[1] - w[0], w[2]])
    sol = jb.simulate(driven, q0, v0, 1.0, rtol=1e-10, atol=1e-10, n_save=5)
    np.testing.assert_allclose(sol.q[:, 0], 0.6 + 2.0 * sol.t, atol=1e-8)
    th1 = four_bar_angles(float(sol.q[-1, 0]))
    np.testing.assert_allclose(sol.q[-1], [th1[0], th1[1] - th1[0], th1[2]], atol=1e-7)
    # at constant crank rate, the drive torque is the crank row of the Newton–Euler balance with
    # α1 = 0 and the torque as unknown; the loop rows stay the pin force on the coupler
    assert sol.reactions.shape == (5, 3) and driven.constraint_names[2] == "prescribed 'crank_hinge0'"
    torques = []
    for q, v, lam in zip(np.asarray(sol.q), np.asarray(sol.v), np.asarray(sol.reactions)):
        th = np.array([q[0], q[0] + q[1], q[2]])
        w = np.array([v[0], v[0] + v[1], v[2]])
        ref = four_bar_newton_euler(th, w, crank_acceleration=0.0)
        np.testing.assert_allclose(lam, [ref[7], ref[8], ref[11]], rtol=1e-7, atol=1e-7)
        torques.append(ref[11])
    assert np.ptp(torques) > 0.1  # the torque varies along the run: a real comparison


def test_a_constrained_solve_traces_the_kinematics_once(monkeypatch):
    """Every point of a constraint needs the body frames, and the residual, its Jacobian and
    its rate each differentiate them: the frames are traced once per model and shape and the
    trace reused (without that, these three traces of the four-bar's reduced dynamics traced
    them 26 times). Counted on the function that builds the joint frames."""
    from jaxbody import kinematics

    calls = []
    local_frames = kinematics._local_frames
    monkeypatch.setattr(kinematics, "_local_frames", lambda *a: calls.append(1) or local_frames(*a))
    s = four_bar()
    th = four_bar_angles(0.6)
    q = jnp.array([th[0] + 0.01, th[1] - th[0], th[2]])
    v = maggi.project_velocities(s, q, jnp.array([1.0, 0.0, 0.0]))
    for _ in range(3):  # three traces of the solve, as a solver's stages and events make
        jax.make_jaxpr(lambda q, v: s.solve(0.0, q, v).xdot)(q, v)
    # at most one trace of the frames per abstract signature (none if an earlier test in this
    # process traced the same model structure already)
    assert len(calls) <= 2, f"the frames were traced {len(calls)} times"
    # and the cached trace gives the solve's own values
    np.testing.assert_allclose(s.solve(0.0, q, v).xdot, jax.jit(lambda q, v: s.solve(0.0, q, v).xdot)(q, v), rtol=1e-13)


def test_initial_velocity_errors_and_projection():
    s = four_bar()
    th = four_bar_angles(0.6)
    q = jnp.array([th[0], th[1] - th[0], th[2]])
    bad = jnp.array([1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"initial velocities violate the constraints \['loop coupler-rocker\[0\]'"):
        maggi.initial_state(s, q, bad)
    _, xp, corr = maggi.initial_state(s, q, bad, project_initial=True)
    np.testing.assert_allclose(s.constraint_residual(0.0, q, xp), 0.0, atol=1e-12)
    np.testing.assert_allclose(xp - bad, corr)
    # the projection is the kinetic-metric closest admissible velocity: D-orthogonal to A
    r = s.solve(0.0, q, xp)
    D = s.kinetic_metric(0.0, q, xp)
    np.testing.assert_allclose(r.A.T @ D @ corr, 0.0, atol=1e-12)


def test_singular_state_is_a_result_code_in_jit():
    """At a dead point of the linkage the loop constraints become dependent: the vmapped
    batch survives and the bad member carries the code."""
    s = four_bar()
    th = four_bar_angles(0.6)
    good = jnp.array([th[0], th[1] - th[0], th[2]])
    # crank and coupler folded onto the rocker's line: G loses rank
    dead = jnp.array([0.0, 0.0, np.pi])
    qs = jnp.stack([good, dead])
    res = jax.jit(jax.vmap(lambda q: s.solve(0.0, q, jnp.zeros(3)).result._value))(qs)
    assert int(res[0]) == 0
    assert int(res[1]) == int(maggi.MaggiResult.singular_parametrisation._value)


@pytest.mark.slow  # 30 s; the rolling disk example (same constraint) is in test_examples_disk
def test_rolling_wheel_on_a_free_body_matches_the_disk_example():
    """A free rigid disk + PlaneContact + RollingContact reproduces the rolling disk of the
    paper (coordinates (x, y, ψ, θ, φ)): same accelerations, N and friction reactions."""
    m, rho = 2.0, 0.3
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    b.add_body("disk", mass=m, inertia=(m * rho**2 / 4, m * rho**2 / 4, m * rho**2 / 2), joints=[jb.Free()])
    model = b.build()
    wheel = jc.rolling_wheel(model, "disk", rho)
    ref = dk.rolling_disk()
    base = ref.base
    rng = np.random.default_rng(3)
    qd_ = jnp.array([0.2, -0.1, 0.4, 1.1, 0.3])
    q_ref_free = free_state(base, qd_, jnp.zeros(5))[0]
    s = maggi.constrain(model, wheel, q_ref=q_ref_free)
    for _ in range(3):
        qd = jnp.asarray(rng.uniform(-1, 1, 5)).at[3].set(rng.uniform(0.5, 2.6))
        e = rng.normal(size=3)
        xd = jnp.array([e[0], e[1], e[2], -rho * e[2], -rho * np.sin(float(qd[3])) * e[0]])
        qf, vf = free_state(base, qd, xd)
        np.testing.assert_allclose(s.constraint_residual(0.0, qf, vf), 0.0, atol=1e-12)
        np.testing.assert_allclose(s.position_residual(0.0, qf), 0.0, atol=1e-12)
        rf = s.solve(0.0, qf, vf)
        rd = ref.solve(0.0, qd, xd)
        # normal force and friction (RollingContact heading t1 = a × n = −x1, lateral −y1)
        np.testing.assert_allclose(rf.reactions[0], base.normal_force(qd, xd, rd.xdot), rtol=1e-10)
        np.testing.assert_allclose(rf.reactions[1:], -rd.reactions, rtol=1e-9, atol=1e-10)
        # acceleration of the centre
        vc = lambda qq, xx: jax.jvp(base.centre, (qq,), (base.qdot(qq, xx),))[1]
        a_ref = jax.jvp(vc, (qd, xd), (base.qdot(qd, xd), rd.xdot))[1]
        np.testing.assert_allclose(rf.xdot[:3], a_ref, rtol=1e-9, atol=1e-10)


def _skew(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def test_point_on_line_on_a_free_body_against_newton_euler():
    """A free rigid body (6 DoF) with one of its points on a skew line through space: both
    rows of PointOnLine act (4 DoF left, not redundant). Accelerations and the two reaction
    components against the world-frame Newton–Euler equations with the force across the line
    as unknown: m a_c = m g + F, I α + ω × Iω = r × F, n_k·(a_c + α × r + ω × (ω × r)) = 0."""
    m, Ib = 1.7, np.diag([0.05, 0.08, 0.11])
    g = np.array([0.0, 0.0, -9.81])
    b = jb.ModelBuilder(gravity=tuple(g))
    b.add_body("body", mass=m, inertia=tuple(np.diag(Ib)), joints=[jb.Free()])
    model = b.build()
    p_b = np.array([0.3, -0.1, 0.2])  # the constrained point, body frame (the c.o.m. is the origin)
    d = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    line = jc.PointOnLine(model, "body", p_b, direction=d, origin=(0.2, -0.4, 0.9))
    n = np.asarray(line.normals)
    np.testing.assert_allclose(n @ d, 0.0, atol=1e-15)
    np.testing.assert_allclose(n @ n.T, np.eye(2), atol=1e-15)
    rng = np.random.default_rng(11)

    def state():
        R = Rotation.random(random_state=rng).as_matrix()
        r = R @ p_b
        c = np.array([0.2, -0.4, 0.9]) + rng.normal() * d - r  # the point on the line
        w = rng.normal(size=3) * 2  # world angular velocity
        vc = rng.normal(size=3)
        vc = vc - n.T @ (n @ (vc + np.cross(w, r)))  # the point moves along the line only
        quat = Rotation.from_matrix(R).as_quat()
        return R, r, c, w, vc, jnp.asarray(np.concatenate([c, [quat[3]], quat[:3]])), jnp.asarray(np.concatenate([vc, R.T @ w]))

    *_, q_ref, _ = state()
    s = maggi.constrain(model, [line], q_ref=q_ref)
    assert s.n_constraint == 2 and s.constraint_names == (f"{line.label}[n1]", f"{line.label}[n2]")
    for _ in range(3):
        R, r, c, w, vc, q, v = state()
        np.testing.assert_allclose(s.position_residual(0.0, q), 0.0, atol=1e-12)
        np.testing.assert_allclose(s.constraint_residual(0.0, q, v), 0.0, atol=1e-12)
        sol = s.solve(0.0, q, v)
        Iw = R @ Ib @ R.T
        # unknowns z = (a_c, α, f1, f2), F = f1 n1 + f2 n2
        A = np.zeros((8, 8))
        rhs = np.zeros(8)
        A[0:3, 0:3] = m * np.eye(3)
        A[0:3, 6:8] = -n.T
        rhs[0:3] = m * g
        A[3:6, 3:6] = Iw
        A[3:6, 6:8] = -_skew(r) @ n.T
        rhs[3:6] = -np.cross(w, Iw @ w)
        A[6:8, 0:3] = n
        A[6:8, 3:6] = -n @ _skew(r)  # α × r = −r × α
        rhs[6:8] = -n @ np.cross(w, np.cross(w, r))
        z = np.linalg.solve(A, rhs)
        np.testing.assert_allclose(sol.reactions, z[6:8], rtol=1e-10, atol=1e-10)
        # free joint: v̇ = (a_c, d/dt(Rᵀω) = Rᵀα)
        np.testing.assert_allclose(sol.xdot, np.concatenate([z[:3], R.T @ z[3:6]]), rtol=1e-10, atol=1e-10)
        assert abs(z[6]) + abs(z[7]) > 1.0  # both rows carry force


def free_state(base, q, x):
    R = np.asarray(base.rotation(q))
    quat = Rotation.from_matrix(R).as_quat()  # x, y, z, w
    qf = jnp.asarray(np.concatenate([np.asarray(base.centre(q)), [quat[3]], quat[:3]]))
    qdot = base.qdot(q, x)
    vc = jax.jvp(base.centre, (q,), (qdot,))[1]
    w = base.angular_velocity(q, qdot)
    return qf, jnp.concatenate([vc, jnp.asarray(R).T @ w])


def test_knife_edge_on_a_free_sled():
    """A sled (free body in the plane) with a knife edge: its point moves only along the edge;
    the lateral reaction equals m times the centripetal acceleration when it turns."""
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    # one body with three joints (massless intermediate bodies are rejected, as by MuJoCo)
    b.add_body("sled", joints=[jb.Slide(axis=(1, 0, 0)), jb.Slide(axis=(0, 1, 0)), jb.Hinge(axis=(0, 0, 1))],
               mass=3.0, inertia=(0.1, 0.2, 0.25))
    model = b.build()
    edge = jc.KnifeEdge(model, "sled", (0, 0, 0), edge=(1, 0, 0))
    s = maggi.constrain(model, [edge], q_ref=jnp.zeros(3))
    q = jnp.array([0.0, 0.0, 0.3])
    u, w = 1.5, 0.8
    v = jnp.array([u * np.cos(0.3), u * np.sin(0.3), w])
    r = s.solve(0.0, q, v)
    # speed along the edge and spin are constant; lateral force = m u w
    np.testing.assert_allclose(r.reactions, [3.0 * u * w], rtol=1e-10)
    np.testing.assert_allclose(r.xdot[2], 0.0, atol=1e-12)
    np.testing.assert_allclose(r.xdot[:2] @ np.array([np.cos(0.3), np.sin(0.3)]), 0.0, atol=1e-12)


def _kinematics_calls(jaxpr) -> int:
    """How many evaluations of forward kinematics (nested calls) a traced program holds."""
    return count_eqns(jaxpr, lambda e: e.primitive.name in ("pjit", "jit") and e.params.get("name") == "_forward_kinematics")


def test_each_ready_constraint_evaluates_the_frames_once():
    """A constraint's residual and rate each evaluate forward kinematics once, however many
    points or frames they use: every evaluation is one more copy of the kinematics in the
    compiled program, and a solve differentiates these functions several times."""
    s = four_bar()
    th = four_bar_angles(0.6)
    q, v = jnp.array([th[0], th[1] - th[0], th[2]]), jnp.array([1.0, -0.5, 0.3])
    (loop,) = s.constraints
    assert _kinematics_calls(jax.make_jaxpr(lambda q: loop.position(s.base, 0.0, q))(q).jaxpr) == 1
    assert _kinematics_calls(jax.make_jaxpr(lambda q, v: loop.velocity(s.base, 0.0, q, v))(q, v).jaxpr) == 1
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    b.add_body("wheel", joints=[jb.Free()], mass=2.0, inertia=(0.05, 0.05, 0.09))
    model = b.build()
    q = jnp.array([0.1, 0.2, 0.3, 0.9, 0.1, 0.3, 0.2])
    q = q.at[3:].set(q[3:] / jnp.linalg.norm(q[3:]))
    v = jnp.array([0.3, -0.2, 0.1, 0.5, 1.0, -0.4])
    wheel = jc.rolling_wheel(model, "wheel", 0.3)[1]
    skate = jc.KnifeEdge(model, "wheel", (0.1, 0, 0), edge=(1, 0, 0))
    base = maggi.constrain(model, [skate], q_ref=q).base
    for c in (wheel, skate):
        jaxpr = jax.make_jaxpr(lambda q, v, c=c: c.velocity(base, 0.0, q, v))(q, v).jaxpr
        assert _kinematics_calls(jaxpr) == 1, type(c).__name__
    # the single evaluation gives what the point-by-point functions give
    m = model
    R, o, Rd, od = jc._body_frame_rate(m, q, v, 0)
    np.testing.assert_allclose(od + Rd @ jnp.array([0.1, 0, 0]), jc.body_point_velocity(m, q, v, 0, jnp.array([0.1, 0, 0])), rtol=1e-13)
    np.testing.assert_allclose(jc._angular_velocity(R, Rd), jc.body_angular_velocity(m, q, v, 0), rtol=1e-13)


def four_bar_mjcf(th, solref="0.0002 1", solimp="0.99999 0.99999 0.001", sites=False):
    """The four-bar of four_bar() in MJCF, its body frames turned so that qpos = 0 is the closed
    configuration ``th`` (MuJoCo places the connect's second anchor at qpos = 0). ``sites``:
    the connect joins two sites at the link ends instead of a body anchor."""
    q = [th[0], th[1] - th[0], th[2]]
    site = lambda name, l: f'<site name="{name}" pos="{l} 0 0"/>' if sites else ""
    ends = 'site1="s_coupler" site2="s_rocker"' if sites else f'body1="coupler" body2="rocker" anchor="{L2} 0 0"'
    inert = lambda m, l, I: f'<inertial pos="{l / 2} 0 0" mass="{m}" diaginertia="{I / 10} {I} {I}"/>'
    return f"""
<mujoco>
  <compiler angle="radian"/>
  <option gravity="0 0 -{G}" timestep="0.0001"><flag contact="disable"/></option>
  <worldbody>
    <body name="crank" euler="0 {-q[0]} 0">
      <joint name="j1" type="hinge" axis="0 -1 0"/>
      {inert(MASS[0], L1, INER[0])}
      <body name="coupler" pos="{L1} 0 0" euler="0 {-q[1]} 0">
        <joint name="j2" type="hinge" axis="0 -1 0"/>
        {inert(MASS[1], L2, INER[1])}
        {site("s_coupler", L2)}
      </body>
    </body>
    <body name="rocker" pos="{D_GROUND} 0 0" euler="0 {-q[2]} 0">
      <joint name="j3" type="hinge" axis="0 -1 0"/>
      {inert(MASS[2], L3, INER[2])}
      {site("s_rocker", L3)}
    </body>
  </worldbody>
  <equality>
    <connect name="loop" {ends} solref="{solref}" solimp="{solimp}"/>
  </equality>
</mujoco>"""


def test_mjcf_connect_imports_as_loop_closure_and_matches_mujoco():
    import warnings

    import mujoco

    th = four_bar_angles(0.6)
    xml = four_bar_mjcf(th)
    mj = mujoco.MjModel.from_xml_string(xml)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        model = jb.from_mujoco(mj)
    assert not rec  # the connect is imported, nothing else is ignored: no warning
    (spec,) = model.loops
    assert spec.label == "loop" and (spec.body_a, spec.body_b) == (model.body_index("coupler"), model.body_index("rocker"))
    np.testing.assert_allclose(spec.point_b, [L3, 0, 0], atol=1e-9)  # MuJoCo's anchor in the rocker frame
    assert "loops=1" in repr(model)
    # the model's loop, with its independent directions found automatically (the y row of a
    # loop in the x-z plane vanishes identically), equals the explicit choice of axes
    (auto,) = jc.loop_closures(model)
    np.testing.assert_allclose(auto.axes, [[1, 0, 0], [0, 0, 1]], atol=1e-12)
    loops = jc.connect_constraints(mj, model, axes=[(1, 0, 0), (0, 0, 1)])
    assert len(loops) == 1 and loops[0].names == ("loop[0]", "loop[1]") == auto.names
    q = jnp.asarray(mj.qpos0)
    np.testing.assert_allclose(q, 0.0)
    s = maggi.constrain(model, loops, q_ref=q)
    w = four_bar_rates(th, 1.5)
    v = jnp.array([w[0], w[1] - w[0], w[2]])
    r = s.solve(0.0, q, v)
    # same as the builder-made linkage
    ref = four_bar().solve(0.0, jnp.array([th[0], th[1] - th[0], th[2]]), v)
    np.testing.assert_allclose(r.xdot, ref.xdot, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(r.reactions, ref.reactions, rtol=1e-10, atol=1e-10)
    # the default scene of the imported model imposes the loop: same accelerations and force
    a, _, lam = jb.scene(model).evaluate(0.0, q, v)
    np.testing.assert_allclose(a, ref.xdot, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(lam, ref.reactions, rtol=1e-9, atol=1e-9)
    # MuJoCo with a stiff, nearly hard connect: same accelerations and pin force within its softness
    d = mujoco.MjData(mj)
    d.qpos[:] = np.asarray(q)
    d.qvel[:] = np.asarray(v)
    mujoco.mj_forward(mj, d)
    np.testing.assert_allclose(d.qacc, r.xdot, rtol=1e-3, atol=1e-3 * float(jnp.max(jnp.abs(r.xdot))))
    # MuJoCo's connect rows are the world components of the force on body1, like Λ (y row: 0)
    f_world = np.asarray(d.efc_force[:3])
    np.testing.assert_allclose(f_world[[0, 2]], r.reactions, rtol=1e-3)
    assert abs(f_world[1]) < 1e-9
    # opting out leaves the loop open: the tree falls freely
    open_scene = jb.scene(model, constraints=None)
    assert open_scene.constraints is None and open_scene.path == "planar"



@pytest.mark.slow  # about 20-30 s
def test_loop_scene_parameters_change_inside_jit_and_grad():
    """The importer stores each loop's directions; a scene is built once (its constraints are
    checked and partitioned on concrete values) and its parameters change inside jit/grad:
    ∂Λ/∂(link masses) through the loop equals central differences. Building a constrained
    scene from a traced model says what to do instead."""
    import warnings

    import equinox as eqx

    th = four_bar_angles(0.6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mjcf(four_bar_mjcf(th))
    assert model.loops[0].axes == ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    sc = jb.scene(model)
    q = model.qpos0
    w = four_bar_rates(th, 1.5)
    v = jnp.array([w[0], w[1] - w[0], w[2]])

    def force(mass):
        s = eqx.tree_at(lambda s: s.system.body_mass, sc, mass)
        return s.evaluate(0.0, q, v)[2][1]

    g = jax.jit(jax.grad(force))(model.body_mass)
    h = 1e-6
    fd = [(force(model.body_mass.at[i].add(h)) - force(model.body_mass.at[i].add(-h))) / (2 * h) for i in range(3)]
    np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-9)
    assert np.all(np.abs(np.asarray(g)) > 1e-3)  # every link's mass loads the loop
    with pytest.raises(ValueError, match=r"scene: constraints are checked .* traced .* equinox.tree_at"):
        jax.jit(lambda m: jb.scene(m).evaluate(0.0, q, v)[0])(model)


@pytest.mark.slow  # 30 s; test_mjcf_connect_imports_as_loop_closure_and_matches_mujoco checks the default scene of the imported model
def test_imported_four_bar_simulates_closed_with_its_loop_force():
    """`jb.simulate` on the imported model (no constraint written by the user): the loop stays
    closed and the solution carries the loop force, as the builder-made linkage."""
    import warnings

    th = four_bar_angles(0.6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing is ignored
        model = jb.from_mjcf(four_bar_mjcf(th))
    w = four_bar_rates(th, 1.5)
    v0 = jnp.array([w[0], w[1] - w[0], w[2]])
    sol = jb.simulate(model, model.qpos0, v0, 0.3, rtol=1e-10, atol=1e-10, n_save=4)
    assert sol.reactions.shape == (4, 2)
    assert float(jnp.max(jnp.abs(sol.constraint_drift["position"]))) < 1e-8
    ref = four_bar().solve(0.0, jnp.array([th[0], th[1] - th[0], th[2]]), v0)
    np.testing.assert_allclose(sol.reactions[0], ref.reactions, rtol=1e-8)


def test_inactive_and_disabled_connects_are_not_loops():
    import warnings

    th = four_bar_angles(0.6)
    xml = four_bar_mjcf(th).replace('<connect name="loop"', '<connect name="loop" active="false"')
    with pytest.warns(UserWarning, match=r"equality constraints other than active <connect> loops \(ignored\): 1 constraints \('loop'\)"):
        model = jb.from_mjcf(xml)
    assert model.loops == () and jb.scene(model).constraints is None
    xml = four_bar_mjcf(th).replace('<flag contact="disable"/>', '<flag contact="disable" equality="disable"/>')
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert jb.from_mjcf(xml).loops == ()


def test_cassie_style_loops_are_not_reported_as_ignored():
    th = four_bar_angles(0.6)
    xml = four_bar_mjcf(th).replace("</equality>", '<joint name="couple" joint1="j1" joint2="j3"/></equality>')
    with pytest.warns(UserWarning) as rec:
        model = jb.from_mjcf(xml)
    (msg,) = [str(w.message) for w in rec]
    assert "1 constraints ('couple')" in msg and "'loop'" not in msg and "connect" in msg  # only the joint coupling
    assert [spec.label for spec in model.loops] == ["loop"]


def test_site_based_connect_and_scene_path():
    """A <connect site1= site2=> closes the four-bar like the body/anchor form: the closure
    from connect_constraints, passed to jb.scene, gives the builder-made linkage's
    accelerations and pin force (the documented path of docs/maggi.md)."""
    import warnings

    import mujoco

    th = four_bar_angles(0.6)
    xml = four_bar_mjcf(th, sites=True)
    assert 'site1="s_coupler"' in xml and xml.count("<site") == 2
    mj = mujoco.MjModel.from_xml_string(xml)
    assert int(mj.eq_objtype[0]) == int(mujoco.mjtObj.mjOBJ_SITE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mujoco(mj)
    loops = jc.connect_constraints(mj, model, axes=[(1, 0, 0), (0, 0, 1)])
    assert len(loops) == 1 and loops[0].body_a == model.body_index("coupler") and loops[0].body_b == model.body_index("rocker")
    np.testing.assert_allclose(loops[0].point_a, [L2, 0, 0], atol=1e-12)
    np.testing.assert_allclose(loops[0].point_b, [L3, 0, 0], atol=1e-12)
    assert [spec.label for spec in model.loops] == ["loop"]
    sc = jb.scene(model, constraints=loops)  # checked at qpos0, the closed configuration
    assert jb.scene(model).constraints is not None  # the default scene imposes the model's loop
    q = jnp.asarray(mj.qpos0)
    w = four_bar_rates(th, 1.5)
    v = jnp.array([w[0], w[1] - w[0], w[2]])
    a, _, lam = sc.evaluate(0.0, q, v)
    ref = four_bar().solve(0.0, jnp.array([th[0], th[1] - th[0], th[2]]), v)
    np.testing.assert_allclose(a, ref.xdot, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(lam, ref.reactions, rtol=1e-9, atol=1e-9)


SPATIAL_LOOP = """
<mujoco>
  <option gravity="0 0 -9.81" timestep="0.0001"><flag contact="disable"/></option>
  <worldbody>
    <body name="a">
      <joint type="ball"/>
      <inertial pos="0.2 0 0.02" mass="1.0" diaginertia="0.004 0.02 0.021"/>
      <body name="b" pos="0.4 0 0" euler="20 -30 50">
        <joint type="ball"/>
        <inertial pos="0.25 0.01 0" mass="0.8" diaginertia="0.003 0.03 0.031"/>
      </body>
    </body>
    <body name="c" pos="0.7 0.5 -0.3" euler="-10 40 15">
      <joint type="ball"/>
      <inertial pos="0.1 -0.1 0.1" mass="0.6" diaginertia="0.01 0.012 0.015"/>
    </body>
  </worldbody>
  <equality>
    <connect name="ring" body1="b" body2="c" anchor="0.5 0 0" solref="0.0002 1" solimp="0.99999 0.99999 0.001"/>
  </equality>
</mujoco>"""


def test_spatial_ball_joint_loop_against_mujoco_connect():
    """A closed chain of three bodies on ball joints (6 DOF after the loop): accelerations and
    the loop force against MuJoCo's <connect> made stiff, within its softness."""
    import mujoco

    mj = mujoco.MjModel.from_xml_string(SPATIAL_LOOP)
    model = jb.from_mujoco(mj)
    loops = jc.connect_constraints(mj, model)
    (auto,) = jc.loop_closures(model)  # a spatial loop keeps all three directions
    assert np.linalg.matrix_rank(np.asarray(auto.axes)) == 3 and auto.names == loops[0].names
    q = jnp.asarray(mj.qpos0)
    s = maggi.constrain(model, loops, q_ref=q)
    rng = np.random.default_rng(5)
    v = maggi.project_velocities(s, q, jnp.asarray(rng.normal(size=9)))

    @eqx.filter_jit  # one program (called one by one the methods compile each operation)
    def residuals_and_solve(s, q, v):
        return s.position_residual(0.0, q), s.constraint_residual(0.0, q, v), s.solve(0.0, q, v)

    position, velocity, r = residuals_and_solve(s, q, v)
    np.testing.assert_allclose(position, 0.0, atol=1e-12)
    np.testing.assert_allclose(velocity, 0.0, atol=1e-12)
    assert r.A.shape == (9, 6)
    d = mujoco.MjData(mj)
    d.qpos[:] = np.asarray(q)
    d.qvel[:] = np.asarray(v)
    mujoco.mj_forward(mj, d)
    np.testing.assert_allclose(d.qacc, r.xdot, rtol=0, atol=1e-3 * float(jnp.max(jnp.abs(r.xdot))))
    np.testing.assert_allclose(d.efc_force[:3], r.reactions, rtol=0, atol=1e-3 * float(jnp.max(jnp.abs(r.reactions))))


@pytest.mark.slow
def test_spatial_ball_joint_loop_stays_closed():
    import mujoco

    mj = mujoco.MjModel.from_xml_string(SPATIAL_LOOP)
    model = jb.from_mujoco(mj)
    q = jnp.asarray(mj.qpos0)
    s = maggi.constrain(model, jc.connect_constraints(mj, model), q_ref=q)
    v = maggi.project_velocities(s, q, jnp.asarray(np.random.default_rng(5).normal(size=9)))
    sol = jb.simulate(s, q, v, 0.5, rtol=1e-9, atol=1e-9, n_save=6)
    pos, _ = maggi.constraint_residuals(s, sol.t, sol.q, sol.v)
    assert float(jnp.max(jnp.abs(pos))) < 1e-8


def test_example5_position_projection_and_unconstrained_equivalence():
    s = example5()
    q_off = jnp.array([0.5, -0.93])  # end point off the vertical
    assert abs(float(s.position_residual(0.0, q_off)[0])) > 1e-2
    qp = maggi.project_positions(s, q_off)
    np.testing.assert_allclose(s.position_residual(0.0, qp), 0.0, atol=1e-14)
    np.testing.assert_allclose(qp[1], -2 * qp[0], rtol=1e-12)  # α2 = −α1 on the manifold
    # without constraints the reduced dynamics is the model's forward dynamics
    free = maggi.constrain(s.base.model, [], q_ref=q_off)
    v = jnp.array([0.3, -1.2])
    np.testing.assert_allclose(free.solve(0.0, q_off, v).xdot, jb.forward_dynamics(s.base.model, q_off, v, jnp.zeros(2)), rtol=1e-12)
