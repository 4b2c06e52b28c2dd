"""The disk on a plane: one base system, sliding / skating / rolling by added constraints.

References: the spec's §18 tables (B-1, B-2, B-3), an independent sympy KanesMethod
derivation of the rolling disk written here, Newton's law for the contact force, energy
conservation, and steady motions whose relations are derived here.
"""

import functools

import diffrax

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp
from sympy.physics import mechanics as me

import jaxbody as jb
from jaxbody.examples import disk as dk

M, RHO, G, TH = 2.0, 0.3, 9.81, 1.2
Q = jnp.array([0.7, -0.4, 0.9, TH, 0.25])  # x, y, ψ, φ do not enter the equations


@functools.lru_cache
def systems():
    return dk.sliding_disk(), dk.skating_disk(), dk.rolling_disk()


def test_b1_sliding():
    s = systems()[0]
    x = jnp.array([0.4, -0.7, 5.0, 1.1, -0.3])
    r = s.solve(0.0, Q, x)
    ref = [-26.2191283325, 4.10885827942, 0.0, 0.225312439319, 0.826145610837]
    np.testing.assert_allclose(r.xdot, ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(s.base.normal_force(Q, x, r.xdot), 13.8301015676, rtol=1e-10)
    assert r.reactions.shape == (0,)


def test_b2_skating():
    s = systems()[1]
    x5 = -RHO * np.sin(TH) * 0.4
    np.testing.assert_allclose(x5, -0.111844690316, rtol=1e-10)
    x = jnp.array([0.4, -0.7, 5.0, 1.1, x5])
    r = s.solve(0.0, Q, x)
    np.testing.assert_allclose(r.xdot, [-10.0945117926, 4.10885827942, 0.0, 0.084, 2.80515069114], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(r.reactions, [3.9580101606], rtol=1e-10)
    np.testing.assert_allclose(s.base.normal_force(Q, x, r.xdot), 17.3358294723, rtol=1e-10)
    # A and K of the paper (4.8)-(4.11) for ε̃ = (x1, x2, x3, x4 + ρx3, f*)
    At = np.eye(5)
    At[3, 2] = -RHO
    At[4, 0] = -RHO * np.sin(TH)
    np.testing.assert_allclose(r.A, At[:, :4], atol=1e-14)
    np.testing.assert_allclose(r.K, At[:, 4:], atol=1e-14)


def test_b3_rolling():
    s = systems()[2]
    x = jnp.array([0.4, -0.7, 5.0, -RHO * 5.0, -RHO * np.sin(TH) * 0.4])
    r = s.solve(0.0, Q, x)
    np.testing.assert_allclose(r.epsilon_dot, [-5.24117845931, 4.10885827942, -0.186666666667], rtol=1e-10)
    np.testing.assert_allclose(r.reactions, [-0.056, 5.14932795713], rtol=1e-10)
    np.testing.assert_allclose(s.base.normal_force(Q, x, r.xdot), 18.3910152534, rtol=1e-10)
    # the bracket equals Gᵀ Λ (reactions are the multipliers of f* = 0)
    Gm = s.constraint_jacobian(0.0, Q, x)
    np.testing.assert_allclose(r.bracket, Gm.T @ r.reactions, atol=1e-12)


def test_kinematics_and_energy_match_the_quasi_velocity_form():
    """q̇ = H x inverts x(q, q̇), and ½ xᵀDx is the T* of the quasi-velocity form."""
    system = systems()[0]

    @eqx.filter_jit  # one program for the five states (called one by one the methods compile each operation)
    def quantities(system, q, x):
        base = system.base
        return (base.quasi_velocities(q, base.qdot(q, x)), system.kinetic_metric(0.0, q, x), base.total_energy(q, x),
                base.contact_velocity(q, x))

    rng = np.random.default_rng(0)
    for _ in range(5):
        q = jnp.asarray(rng.uniform(-1, 1, 5)).at[3].set(rng.uniform(0.3, 2.8))
        x = jnp.asarray(rng.normal(size=5))
        x_back, D, energy, contact = quantities(system, q, x)
        np.testing.assert_allclose(x_back, x, atol=1e-13)
        th = q[3]
        T_star = 0.5 * M * (x[3] ** 2 + x[4] ** 2 + RHO**2 * jnp.cos(th) ** 2 * x[0] ** 2)
        T_star += M * RHO**2 / 8 * (x[0] ** 2 + x[1] ** 2) + M * RHO**2 / 4 * x[2] ** 2
        np.testing.assert_allclose(0.5 * x @ D @ x, T_star, rtol=1e-12)
        np.testing.assert_allclose(energy, T_star + M * G * RHO * jnp.sin(th), rtol=1e-12)
        np.testing.assert_allclose(contact, [x[3] + RHO * x[2], x[4] + RHO * jnp.sin(th) * x[0], 0.0], atol=1e-12)


@functools.lru_cache
def kane_rolling_disk():
    """Rolling disk by KanesMethod (sympy.mechanics), speeds u = (ω on Résal axes, v_C on A axes)."""
    xq, yq, psi, th, phi = me.dynamicsymbols("x y psi theta phi")
    u = me.dynamicsymbols("u1:6")
    m, r, g = sp.symbols("m r g", positive=True)
    N = me.ReferenceFrame("N")
    A = N.orientnew("A", "Axis", [psi, N.z])
    B = A.orientnew("B", "Axis", [th, A.x])
    Cf = B.orientnew("C", "Axis", [phi, B.z])
    Cf.set_ang_vel(N, u[0] * B.x + u[1] * B.y + u[2] * B.z)
    O = me.Point("O")
    O.set_vel(N, 0)
    P = O.locatenew("P", xq * N.x + yq * N.y + r * sp.sin(th) * N.z)
    P.set_vel(N, u[3] * A.x + u[4] * A.y + r * sp.cos(th) * th.diff() * N.z)
    Dp = P.locatenew("D", -r * B.y)
    Dp.v2pt_theory(P, N, Cf)
    w = Cf.ang_vel_in(N)
    wq = (A.ang_vel_in(N) + B.ang_vel_in(A) + Cf.ang_vel_in(B))  # in terms of q̇
    kd = [sp.simplify((w - wq).dot(B.x)), (w - wq).dot(B.y), (w - wq).dot(B.z)]
    vP = xq.diff() * N.x + yq.diff() * N.y
    kd += [u[3] - vP.dot(A.x), u[4] - vP.dot(A.y)]
    vD = Dp.vel(N)
    vc = [vD.dot(A.x), vD.dot(A.y)]
    Ia = m * r**2 / 4
    disk = me.RigidBody("disk", P, Cf, m, (me.inertia(Cf, Ia, Ia, 2 * Ia), P))
    kane = me.KanesMethod(
        N, q_ind=[xq, yq, psi, th, phi], u_ind=u[:3], kd_eqs=kd, u_dependent=u[3:], velocity_constraints=vc
    )
    kane.kanes_equations([disk], [(P, -m * g * N.z)])
    syms = [xq, yq, psi, th, phi] + list(u)
    Mf = kane.mass_matrix_full
    Ff = kane.forcing_full
    f = sp.lambdify([syms, m, r, g], [Mf, Ff], "numpy")
    return f, kane, syms, vc


def test_rolling_disk_against_sympy_kane():
    f, _, _, _ = kane_rolling_disk()
    s = systems()[2]
    rng = np.random.default_rng(1)
    for _ in range(6):
        q = rng.uniform(-1, 1, 5)
        q[3] = rng.uniform(0.3, 2.8)
        e = rng.normal(size=3) * 2
        x = np.array([e[0], e[1], e[2], -RHO * e[2], -RHO * np.sin(q[3]) * e[0]])
        Mf, Ff = f(list(q) + list(x), M, RHO, G)
        sol = np.linalg.solve(np.asarray(Mf, float), np.asarray(Ff, float).ravel())
        r = s.solve(0.0, jnp.asarray(q), jnp.asarray(x))
        np.testing.assert_allclose(np.asarray(s.qdot(jnp.asarray(q), jnp.asarray(x))), sol[:5], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(np.asarray(r.xdot), sol[5:], rtol=1e-10, atol=1e-10)


@pytest.mark.slow  # about 50 s; the disk's other reaction tests cover the default job
def test_reactions_equal_newton_along_a_solution():
    """Λ and N equal m·a_C minus gravity along a rolling and a skating trajectory."""
    for s, x0 in (
        (systems()[2], [0.3, -0.5, 6.0, -RHO * 6.0, -RHO * np.sin(TH) * 0.3]),
        (systems()[1], [0.3, -0.5, 6.0, 0.7, -RHO * np.sin(TH) * 0.3]),
    ):
        sol = jb.simulate(s, Q, jnp.asarray(x0), 1.0, rtol=1e-10, atol=1e-10, n_save=11)
        out = dk.disk_outputs(s, sol.t, sol.q, sol.v)
        base = s.base

        def accel_c(q, x, xdot):
            vc = lambda qq, xx: jax.jvp(base.centre, (qq,), (base.qdot(qq, xx),))[1]
            return jax.jvp(vc, (q, x), (base.qdot(q, x), xdot))[1]

        a = jax.jit(jax.vmap(accel_c))(sol.q, sol.v, out.xdot)
        force = M * a - M * jnp.array([0.0, 0.0, -G])  # contact force = m a_C − m g
        psi = sol.q[:, 2]
        fx1 = force[:, 0] * jnp.cos(psi) + force[:, 1] * jnp.sin(psi)
        fy1 = -force[:, 0] * jnp.sin(psi) + force[:, 1] * jnp.cos(psi)
        np.testing.assert_allclose(out.normal_force, force[:, 2], rtol=1e-10)
        if out.reactions.shape[1] == 2:
            np.testing.assert_allclose(out.reactions[:, 0], fx1, atol=1e-9)
            np.testing.assert_allclose(out.reactions[:, 1], fy1, atol=1e-9)
        else:
            np.testing.assert_allclose(out.reactions[:, 0], fy1, atol=1e-9)
            np.testing.assert_allclose(fx1, 0.0, atol=1e-9)  # no friction along the skate
        np.testing.assert_allclose(jnp.linalg.norm(out.contact_point[:, 2]), 0.0, atol=1e-12)


@pytest.mark.parametrize("regime", [pytest.param(0, marks=pytest.mark.slow), pytest.param(1, marks=pytest.mark.slow), 2])
def test_energy_conserved_20s(regime):
    s = systems()[regime]
    x = [0.3, -0.5, 6.0, 0.7, 0.2]
    if regime >= 1:
        x[4] = -RHO * np.sin(TH) * x[0]
    if regime == 2:
        x[3] = -RHO * x[2]
    sol = jb.simulate(s, Q, jnp.asarray(x), 20.0, rtol=1e-10, atol=1e-10, n_save=201)
    assert bool(sol.success)
    assert float(sol.energy_drift) < 1e-8
    _, vel = jb.maggi.constraint_residuals(s, sol.t, sol.q, sol.v)
    assert float(jnp.max(jnp.abs(vel), initial=0.0)) < 1e-9


def test_upright_straight_rolling():
    s = systems()[2]
    w = 8.0
    q0 = jnp.array([0.0, 0.0, 0.3, np.pi / 2, 0.0])
    x0 = jnp.array([0.0, 0.0, w, -RHO * w, 0.0])
    np.testing.assert_allclose(s.solve(0.0, q0, x0).xdot, 0.0, atol=1e-12)
    sol = jb.simulate(s, q0, x0, 3.0, rtol=1e-10, atol=1e-10, n_save=4)
    # centre moves on a straight line along −x₁ at speed ρω; the disk stays upright
    np.testing.assert_allclose(sol.q[:, 3], np.pi / 2, atol=1e-9)
    np.testing.assert_allclose(sol.q[-1, :2], -RHO * w * 3.0 * np.array([np.cos(0.3), np.sin(0.3)]), atol=1e-8)


def test_steady_circular_rolling():
    """Constant tilt: the relation between spin ε3, precession ε2 and tilt derived from Kane."""
    _, kane, syms, vc = kane_rolling_disk()
    u1, u2, u3 = syms[5:8]
    th = syms[3]
    m, r, g = sp.symbols("m r g", positive=True)
    # steady motion: u1 = 0 and u̇ = 0 -> the u1-row of Kane's equations is the relation
    rhs = kane.mass_matrix.LUsolve(kane.forcing)
    dependent = sp.solve(vc, syms[8:10], dict=True)[0]  # u4, u5 from the no-slip constraints
    relation = sp.simplify(rhs[0].subs(dependent).subs(u1, 0))
    th0, e2 = 1.1, 1.5  # tilt and precession component x2 = ψ̇ sin θ
    w3 = sp.Symbol("w3")
    e3 = sp.nsolve(relation.subs({th: th0, u2: e2, m: M, r: RHO, g: G}).subs(u3, w3), w3, 3.0)
    e3 = float(e3)
    s = systems()[2]
    q0 = jnp.array([0.0, 0.0, 0.0, th0, 0.0])
    x0 = jnp.array([0.0, e2, e3, -RHO * e3, 0.0])
    np.testing.assert_allclose(s.solve(0.0, q0, x0).epsilon_dot, 0.0, atol=1e-11)
    period = 2 * np.pi * np.sin(th0) / abs(e2)
    sol = jb.simulate(s, q0, x0, period, rtol=1e-11, atol=1e-11, n_save=9)
    np.testing.assert_allclose(sol.q[:, 3], th0, atol=1e-8)
    out = dk.disk_outputs(s, sol.t, sol.q, sol.v)
    # the contact point traces a circle and closes after one precession period
    np.testing.assert_allclose(out.contact_point[-1], out.contact_point[0], atol=1e-7)
    centre = jnp.mean(out.contact_point[:-1], axis=0)
    radii = jnp.linalg.norm(out.contact_point[:-1] - centre, axis=1)
    np.testing.assert_allclose(radii, radii[0], rtol=1e-7)


def test_rates_violating_the_regime_are_rejected():
    s = systems()[2]
    with pytest.raises(ValueError, match=r"initial velocities violate the constraints \['rolling \(slip x1, y1\)\[0\]"):
        dk.initial_velocities(s, Q, jnp.array([0.1, 0.0, 0.5, 0.2, 0.0]))
    # admissible rates: the disk rolls (ẋ, ẏ from the rolling relations)
    x_ok = jnp.array([0.4, -0.7, 5.0, -RHO * 5.0, -RHO * np.sin(TH) * 0.4])
    qd = s.qdot(Q, x_ok)
    np.testing.assert_allclose(dk.initial_velocities(s, Q, qd), x_ok, atol=1e-12)
    with pytest.raises(ValueError, match="lies flat on the plane"):
        dk.initial_velocities(s, Q.at[3].set(0.0), qd)
    # the smooth plane accepts any rates
    dk.initial_velocities(systems()[0], Q, jnp.array([0.1, 0.0, 0.5, 0.2, 0.0]))


@pytest.mark.slow  # about 50 s; the default suite keeps the reverse-mode gradient through a repartitioning solve
def test_gradient_of_final_heading_wrt_spin():
    s = systems()[2]

    def heading(spin):
        x0 = jnp.stack([0.2, 0.5, spin, -RHO * spin, -RHO * jnp.sin(TH) * 0.2])
        sol = jb.simulate(s, Q, x0, 1.0, rtol=1e-11, atol=1e-11, n_save=2, adjoint=diffrax.ForwardMode())
        return sol.q[-1, 2]

    g = jax.jacfwd(heading)(5.0)
    h = 1e-5
    fd = (heading(5.0 + h) - heading(5.0 - h)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-5)


def test_rolling_disk_in_float32_follows_float64():
    """The rolling disk in float32 (its parameters and state): it integrates through the Maggi
    layer (tangents and derivatives in the state's dtype, the initial check at float32's
    resolution) and stays within float32 tolerances of float64."""
    th, rho = 1.2, 0.3
    q0 = np.array([0.0, 0.0, 0.0, th, 0.0])
    v0 = np.array([0.3, -0.5, 6.0, -rho * 6.0, -rho * np.sin(th) * 0.3])

    def run(dtype, tol):
        system = dk.rolling_disk(*(jnp.asarray(x, dtype) for x in (2.0, 0.3, 9.81)))
        return jb.simulate(jb.scene(system), jnp.asarray(q0, dtype), jnp.asarray(v0, dtype), jnp.asarray(1.0, dtype),
                           n_save=3, rtol=tol, atol=tol)

    s32, s64 = run(jnp.float32, 1e-5), run(jnp.float64, 1e-10)
    assert s32.q.dtype == jnp.float32 and bool(s32.success)
    np.testing.assert_allclose(np.asarray(s32.q_final, np.float64), np.asarray(s64.q_final), atol=1e-3)
    np.testing.assert_allclose(np.asarray(s32.v_final, np.float64), np.asarray(s64.v_final), atol=1e-3)
