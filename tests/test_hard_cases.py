"""Hard cases stay numerically stable: chaos, long chains, extreme mass ratios, near-singular
states, stiffness, float32, long-rollout gradients, a bad member in a batch, very long runs.

References are independent of the code under test: MuJoCo's ``mj_forward`` on the same MJCF
(built here as text), the closed forms of the papers (Example 5's reaction, a free rotation),
energy conservation, converged high-order runs, finite differences, and the unbatched solves.
The default suite keeps the cheap cases (a short chaotic run, the long chain and the mass ratios
against MuJoCo, Example 5's reaction in float64 and float32, the quaternion sign flip, an adaptive solve
leaving its coordinate chart, a bad member in a batch on the default kernel); the long runs and the
costly compilations are marked ``slow``.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxbody as jb
from jaxbody.examples import disk as dk
from jaxbody.scene import CoordinateChart

from test_constraints import four_bar, four_bar_angles, four_bar_rates

# ------------------------------------------------------------------------------ helpers


def chain_mjcf(n, masses=None, stiffness=None, damping=None, length=0.3, axes=("0 1 0", "1 0 0"), gravity=-9.81):
    """An ``n``-link chain of hinges hanging along −z as MJCF text: link ``i`` has mass
    ``masses[i]`` (default 1) spread as a thin rod, its hinge axis alternates over ``axes``
    (spatial motion unless a single axis is given), optional joint stiffness and damping."""
    masses = np.ones(n) if masses is None else np.asarray(masses, float)
    body, close = "", ""
    for i in range(n):
        m = float(masses[i])
        rod = m * length**2 / 12
        extra = ""
        if stiffness is not None:
            extra += f' stiffness="{float(stiffness[i])!r}"'
        if damping is not None:
            extra += f' damping="{float(damping[i])!r}"'
        pos = "0 0 0" if i == 0 else f"0 0 {-length}"
        body += (f'<body name="l{i}" pos="{pos}"><joint name="j{i}" axis="{axes[i % len(axes)]}"{extra}/>'
                 f'<inertial pos="0 0 {-length / 2}" mass="{m!r}" diaginertia="{rod!r} {rod!r} {m * 1e-4!r}"/>')
        close += "</body>"
    return f'<mujoco><option gravity="0 0 {gravity}"/><worldbody>{body}{close}</worldbody></mujoco>'


def mujoco_qacc(xml, q, v, tau):
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.qfrc_applied[:] = q, v, tau
    mujoco.mj_forward(m, d)
    return d.qacc.copy()


def random_state(nq, seed, scale=1.0):
    rng = np.random.default_rng(seed)
    return scale * rng.uniform(-1, 1, nq), scale * rng.uniform(-1, 1, nq), scale * rng.uniform(-1, 1, nq)


# ------------------------------------------------------------------ chaotic double pendulum
# Example 1 started from well above the horizontal: chaotic, and its energy is far from zero
DP_Q0, DP_V0 = jnp.array([2.5, 2.0]), jnp.array([0.0, 0.0])


def double_pendulum_energy_error(t1, solver="dopri8", tol=1e-11, dtype=np.float64, **kw):
    system = jb.examples.double_pendulum() if dtype == np.float64 else jax.tree.map(
        lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, jb.examples.double_pendulum())
    sol = jb.simulate(system, DP_Q0.astype(dtype), DP_V0.astype(dtype), t1, solver=solver, rtol=tol, atol=tol,
                      n_save=201, max_steps=1_000_000, **kw)
    e = np.asarray(sol.energy, np.float64)
    return np.max(np.abs(e - e[0])) / abs(e[0]), sol


def test_chaotic_double_pendulum_energy_10s():
    """Short version of the 100 s run: |ΔE|/E ≤ 1e-8 at rtol = atol = 1e-11."""
    drift, sol = double_pendulum_energy_error(10.0)
    assert float(jnp.ptp(sol.q[:, 1])) > 6.0  # the outer link flips over: the chaotic regime
    assert drift <= 1e-8, drift


@pytest.mark.slow
def test_chaotic_double_pendulum_energy_100s():
    drift, sol = double_pendulum_energy_error(100.0)
    assert drift <= 1e-8, drift


# ------------------------------------------------------------------------ 100-link chain
CHAIN_N = 100


@pytest.fixture(scope="module")
def long_chain():
    xml = chain_mjcf(CHAIN_N)
    return xml, jb.from_mjcf(xml)


def test_100_link_chain_forward_dynamics_against_mujoco(long_chain, record_property):
    xml, model = long_chain
    for seed in range(2):
        q, v, tau = random_state(CHAIN_N, seed, scale=0.5)
        ref = mujoco_qacc(xml, q, v, tau)
        a = np.asarray(jb.forward_dynamics(model, q, v, tau))
        np.testing.assert_allclose(a, ref, rtol=0, atol=1e-8 * np.max(np.abs(ref)))
    M = np.asarray(jb.mass_matrix(model, jnp.asarray(q)))
    cond = np.linalg.cond(M)
    record_property("mass_matrix_condition_number", float(cond))
    print(f"100-link chain: cond(M) = {cond:.3e}")
    # a long light chain is badly conditioned, and still agrees with MuJoCo to 1e-8 above
    assert cond > 1e6


@pytest.mark.slow
def test_100_link_chain_10k_steps_stay_finite(long_chain):
    _, model = long_chain
    q0, v0, _ = random_state(CHAIN_N, 3, scale=0.2)
    sol = jb.simulate(jb.scene(model, kernel="auto"), q0, v0, 1.0, solver="rk4", dt0=1e-4, n_save=11)
    assert sol.success and int(sol.stats["num_steps"]) == 10_000
    assert np.isfinite(np.asarray(sol.q)).all() and np.isfinite(np.asarray(sol.v)).all()
    # RK4 at 1e-4 on a chain without dampers: the energy stays put
    e = np.asarray(sol.energy)
    assert np.max(np.abs(e - e[0])) <= 1e-4 * np.max(np.abs(e)), np.max(np.abs(e - e[0]))


# ------------------------------------------------------------------------ extreme mass ratios
# neighbours differ by 1e6 both ways, and the leaf is a micro-gram
MASSES = np.array([1.0, 1e6, 1.0, 1e-6, 1e3, 1e-3, 1e-9])


def test_extreme_mass_ratios_against_mujoco():
    xml = chain_mjcf(len(MASSES), masses=MASSES)
    model = jb.from_mjcf(xml)
    for seed in range(3):
        q, v, tau = random_state(len(MASSES), seed)
        tau = tau * MASSES  # forces that move every link, the heavy ones included
        ref = mujoco_qacc(xml, q, v, tau)
        a = np.asarray(jb.forward_dynamics(model, q, v, tau))
        # every acceleration to 1e-8 of its own size plus MuJoCo's own rounding (cond(M) ε |a|)
        np.testing.assert_allclose(a, ref, rtol=1e-8, atol=1e-10 * np.max(np.abs(ref)))


# ------------------------------------------------------------------ Example 5 near φ = π/2
def example5_reaction_times_cos(phi, dphi, m1=1.0, m2=0.6, a1=0.4, a2=0.3, L=0.8, I1=0.05, I2=0.02, g=9.81):
    """``F_r cos φ`` of Example 5 from the closed form of its reaction (table T-7), written without
    the division by ``cos φ``: ``(J1 − J2) φ̈ / 2L + (m̃1 − m̃2) g sin φ / 2L``."""
    md1, md2 = m1 * a1 + m2 * L, m2 * a2
    J1, J2 = I1 + m1 * a1**2 + m2 * L**2, I2 + m2 * a2**2
    ddphi = (-(md1 + md2) * g * np.sin(phi) - 2 * L * md2 * dphi**2 * np.sin(2 * phi)) / (
        J1 + J2 - 2 * L * md2 * np.cos(2 * phi))
    return (J1 - J2) * ddphi / (2 * L) + (md1 - md2) * g * np.sin(phi) / (2 * L)


def test_example5_reaction_near_the_horizontal_links():
    """At φ = π/2 both links lie on the horizontal through the pivot and the reaction grows like
    1/cos φ: a real singularity of the constraint, not a numerical one. Approaching it, the computed
    reaction keeps all its digits: F_r cos φ equals the closed form to 1e-9 down to cos φ ~ 1e-9."""
    ex5 = jb.examples.vertical_line_double_pendulum()
    reaction = eqx.filter_jit(ex5.reaction)
    for delta in (1e-2, 1e-4, 1e-6, 1e-9):
        for dphi in (0.0, 1.3):
            phi = np.pi / 2 - delta
            fr = float(reaction(jnp.array([phi]), jnp.array([dphi])))
            ref = example5_reaction_times_cos(phi, dphi)
            np.testing.assert_allclose(fr * np.cos(phi), ref, rtol=1e-9)


@pytest.mark.slow
def test_example5_runs_through_the_horizontal():
    """φ passes π/2 and back: the motion itself is regular there; energy is conserved."""
    ex5 = jb.examples.vertical_line_double_pendulum()
    sol = jb.simulate(ex5, jnp.array([1.2]), jnp.array([5.0]), 1.0, solver="dopri8", rtol=1e-11, atol=1e-11, n_save=101)
    assert sol.success and float(jnp.max(sol.q[:, 0])) > np.pi / 2 + 0.1
    e = np.asarray(sol.energy)
    assert np.max(np.abs(e - e[0])) <= 1e-9 * np.max(np.abs(e))


# ------------------------------------------------------------ four-bar through its folded state
@pytest.fixture(scope="module")
def four_bar_scene():
    cs = four_bar()
    return jb.scene(cs.base.model, constraints=cs)


def four_bar_start():
    """The crank at 0.6 rad turning at 12 rad/s, in the scene's relative coordinates."""
    th = four_bar_angles(0.6)
    w = four_bar_rates(th, 12.0)
    return np.array([th[0], th[1] - th[0], th[2]]), np.array([w[0], w[1] - w[0], w[2]])


@pytest.mark.slow
def test_four_bar_through_folded_configuration(four_bar_scene):
    """The crank turns full circles, through the configurations where crank and coupler are
    collinear (folded over each other and stretched out): constraints, energy and the motion stay
    regular."""
    th = four_bar_angles(0.6)
    w = four_bar_rates(th, 12.0)
    q0, v0 = jnp.array([th[0], th[1] - th[0], th[2]]), jnp.array([w[0], w[1] - w[0], w[2]])
    sol = jb.simulate(four_bar_scene, q0, v0, 1.5, rtol=1e-10, atol=1e-10, n_save=151)
    assert sol.success
    # relative angle crank–coupler passes ±π (folded) and 0 (stretched) mod 2π
    rel = np.asarray(sol.q[:, 1])
    assert float(np.ptp(np.asarray(sol.q[:, 0]))) > 2 * np.pi  # more than one revolution
    assert np.any(np.cos(rel) < -0.99) or np.any(np.cos(rel) > 0.99)
    assert float(jnp.max(jnp.abs(sol.constraint_drift["position"]))) < 1e-8
    assert float(sol.energy_drift) < 1e-8


# ------------------------------------------------------- ball joint through the quaternion's sign flip
def test_ball_joint_through_quaternion_sign_flip():
    """A free rotation about a principal axis for one turn: the quaternion's scalar part goes
    through zero and changes sign; the attitude follows exp(tω̂) to the solver's tolerance."""
    b = jb.ModelBuilder(gravity=(0, 0, 0))
    b.add_body("top", mass=1.0, com=(0, 0, 0), inertia=(0.3, 0.2, 0.1), joints=[jb.Ball()])
    model = b.build()
    omega = np.array([0.0, 0.0, 2 * np.pi])  # about the axis of least inertia: a stable rotation
    sol = jb.simulate(model, jnp.array([1.0, 0, 0, 0]), jnp.asarray(omega), 1.0, solver="dopri8",
                      rtol=1e-12, atol=1e-12, n_save=101)
    quat = np.asarray(sol.q)
    assert quat[0, 0] > 0.99 and quat[-1, 0] < -0.99  # w went from +1 to −1
    assert np.max(np.abs(np.diff(quat, axis=0))) < 0.1  # continuous: no jump to the other hemisphere
    for t, qt in zip(np.asarray(sol.t), quat):
        ref = Rotation.from_rotvec(omega * t).as_matrix()
        got = Rotation.from_quat(qt[[1, 2, 3, 0]]).as_matrix()
        np.testing.assert_allclose(got, ref, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-14)


# ------------------------------------------------------------------ leaving a coordinate chart
def _radius(q):
    return q[:1]


class PolarParticle(eqx.Module):
    """A free unit point mass in the plane in polar coordinates ``q = (r, φ)``, ``v = (ṙ, φ̇)``:
    ``r̈ = r φ̇²``, ``φ̈ = −2 ṙ φ̇ / r``. The chart ends at the origin (``r = 0``), which a particle
    aimed within ``bound`` of it reaches in finite time while its Cartesian motion stays regular."""

    bound: float = eqx.field(static=True, default=1e-3)
    nq = 2
    nv = 2

    def qdot(self, q, v):
        return v

    def acceleration(self, t, q, v, tau=None):
        return jnp.stack([q[0] * v[1] ** 2, -2 * v[0] * v[1] / q[0]])

    def total_energy(self, q, v):
        return 0.5 * (v[0] ** 2 + (q[0] * v[1]) ** 2)

    def coordinate_chart(self):
        return CoordinateChart(name="polar coordinates (r, φ)", coordinates=("r",), margins=_radius,
                                        bound=self.bound, advice="Integrate in Cartesian coordinates instead")


def polar_start(miss):
    """From ``(1, miss)`` at unit speed along −x: it passes the origin at distance ``miss`` at t = 1."""
    x, y, vx, vy = 1.0, miss, -1.0, 0.0
    r = np.hypot(x, y)
    return jnp.array([r, np.arctan2(y, x)]), jnp.array([(x * vx + y * vy) / r, (x * vy - y * vx) / r**2])


def polar_exact(miss, t):
    """Cartesian position at ``t`` of :func:`polar_start`'s particle (a straight line)."""
    return np.stack([1.0 - np.asarray(t), np.full_like(np.asarray(t, float), miss)], axis=-1)


def cartesian(q):
    q = np.asarray(q)
    return np.stack([q[..., 0] * np.cos(q[..., 1]), q[..., 0] * np.sin(q[..., 1])], axis=-1)


HIT, MISS = 1e-4, 0.1  # passes the origin inside the chart's bound 1e-3 / well outside it
T_POLAR = 1.2
POLAR_CASES = {"adaptive": dict(solver="tsit5", rtol=1e-10, atol=1e-10, n_save=5),
               "fixed": dict(solver="rk4", dt0=1e-4, n_save=5)}


# fixed steps (the recorded failure) cost 12,000 steps per solve: slow
@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.slow) if c == "fixed" else c for c in sorted(POLAR_CASES)])
def test_leaving_the_coordinate_chart_stops_with_its_name(case):
    """The step guard stops a solve whose accepted step leaves the scene's declared chart: result
    ``singular_coordinates`` at the first step that ends with r at or below the bound (the exact crossing time
    from the straight line), the state there still equal to the exact motion; the message names the
    chart, the coordinate, the time and the advice, eagerly and when raised. In a batch the member
    that misses the origin finishes and equals its own solve (adaptive: the step guard's code;
    fixed steps: the recorded failure)."""
    kw = POLAR_CASES[case]
    system = PolarParticle()
    t_cross = 1.0 - np.sqrt(system.bound**2 - HIT**2)  # |r(t)| = bound on the way in
    q0, v0 = polar_start(HIT)
    sol = jb.simulate(system, q0, v0, T_POLAR, throw=False, **kw)
    assert not bool(sol.success) and bool(sol.result == jb.RESULTS.singular_coordinates)
    tf = float(sol.t_final)
    assert t_cross <= tf and float(sol.q_final[0]) <= system.bound
    if case == "fixed":
        assert tf < t_cross + 1e-4 + 1e-12  # the first step past the crossing
        assert int(sol.stats["num_steps"]) == round(tf / 1e-4)
    np.testing.assert_allclose(cartesian(sol.q_final), polar_exact(HIT, tf), atol=1e-7)
    why = jb.simulation.explain_failure(system, sol, 0.0, T_POLAR)
    assert why.startswith("the coordinates left their chart, the polar coordinates (r, φ): r = ")
    assert f"at t = {tf:.6g}" in why and "bound 0.001" in why and "Cartesian coordinates instead" in why
    with pytest.raises(jb.SimulationError, match=r"failed at t = .*left their chart, the polar coordinates \(r, φ\): r ="):
        jb.simulate(system, q0, v0, T_POLAR, **kw)
    q1, v1 = polar_start(MISS)
    batch = jb.simulate_batch(system, jnp.stack([q0, q1]), jnp.stack([v0, v1]), T_POLAR, **kw)
    assert not bool(batch.success[0]) and bool(batch[0].result == jb.RESULTS.singular_coordinates) and bool(batch.success[1])
    # a vmapped adaptive solve rounds its step sizes apart from the unbatched one by ulps
    np.testing.assert_allclose(float(batch.t_final[0]), tf, rtol=0, atol=1e-10)
    alone = jb.simulate(system, q1, v1, T_POLAR, **kw)
    np.testing.assert_allclose(np.asarray(batch.q_final[1]), np.asarray(alone.q_final), rtol=0, atol=1e-10)
    np.testing.assert_allclose(cartesian(alone.q_final), polar_exact(MISS, T_POLAR), atol=1e-6)


def test_chart_failure_raised_from_a_compiled_solve():
    """Under ``jit`` the raised message names the chart too (margins computed in the program)."""
    system = PolarParticle()
    q0, v0 = polar_start(HIT)
    run = jax.jit(lambda q0, v0: jb.simulate(system, q0, v0, T_POLAR, **POLAR_CASES["adaptive"]).q_final)
    with pytest.raises(Exception, match=r"left their chart, the polar coordinates \(r, φ\): r = .* at t = 0\.999"):
        run(q0, v0)


# -------------------------------------------------------------------- rolling disk nearly flat
def flat_disk_start(theta0=0.05, precession=3.0):
    """The rolling disk nearly flat, precessing, not spinning: the contact point rests, so the
    centre moves at −ρψ̇ cos θ along x₁."""
    roll = dk.rolling_disk()
    q0 = jnp.array([0.0, 0.0, 0.0, theta0, 0.0])
    x0 = dk.initial_velocities(roll, q0, jnp.array([-0.3 * precession * np.cos(theta0), 0.0, precession, 0.0, 0.0]))
    return roll, q0, x0


@pytest.mark.slow
def test_rolling_disk_falling_flat():
    """The rolling disk started at θ = 0.05 rad (nearly flat) falls onto the plane: θ → 0 while
    ψ̇ sin θ stays non-zero, so ψ̇ = x₂ / sin θ of its Euler-angle kinematics grows without bound
    (the disk lands flat; the continuous-contact model ends there too). Up to the landing the motion
    is integrated accurately (energy, rolling constraints); the solve stops where |sin θ| reaches the
    disk's chart bound with the result ``singular`` and a message naming the chart, sin θ and the
    time (eagerly, raised, and for the member of a batch whose other member finishes), and an event
    on sin θ stops it there cleanly."""
    roll, q0, x0 = flat_disk_start()
    kw = dict(rtol=1e-10, atol=1e-10, n_save=7, throw=False)
    before = jb.simulate(roll, q0, x0, 0.06, max_steps=2_000, **kw)
    assert before.success and 0 < float(before.q[-1, 3]) < 5e-3
    assert float(before.energy_drift) < 1e-8
    assert float(jnp.max(jnp.abs(before.constraint_drift["velocity"]))) < 1e-8
    across = jb.simulate(roll, q0, x0, 0.1, max_steps=2_000, **kw)
    bound = float(np.finfo(np.float64).eps) ** 0.25
    assert bool(across.result == jb.RESULTS.singular_coordinates) and 0.06 < float(across.t_final) < 0.0615
    assert np.isfinite(np.asarray(across.q_final)).all() and 0 < float(across.q_final[3]) <= bound
    # well within the step budget: the guard stops it, not max_steps
    print(f"flat disk: stopped at t = {float(across.t_final):.4g}, |sin θ| = {float(across.q_final[3]):.3g}, "
          f"{int(across.stats['num_steps'])} steps")
    assert int(across.stats["num_steps"]) < 500
    why = jb.simulation.explain_failure(roll, across, 0.0, 0.1)
    assert why.startswith("the coordinates left their chart, the z-x-z Euler angles (ψ, θ, φ) of the disk: |sin θ|")
    assert f"t = {float(across.t_final):.6g}" in why and "jb.Event(lambda t, q, x: jnp.sin(q[3]) - h" in why
    with pytest.raises(jb.SimulationError, match=r"failed at t = 0\.061.*left their chart.*\|sin θ\|"):
        jb.simulate(roll, q0, x0, 0.1, max_steps=2_000, **{**kw, "throw": True})
    # a batch: the nearly flat disk beside one started steeper (θ = 0.3), which stays up until 0.1 s
    roll2, q1, x1 = flat_disk_start(theta0=0.3)
    batch = jb.simulate_batch(roll, jnp.stack([q0, q1]), jnp.stack([x0, x1]), 0.1, max_steps=2_000, **kw)
    assert bool(batch[0].result == jb.RESULTS.singular_coordinates) and bool(batch.success[1])
    # the vmapped program rounds apart from the unbatched one, and the last steps before the bound
    # are short: the member stops at a neighbouring accepted step, below the same bound
    assert 0 < float(batch.q_final[0, 3]) <= bound
    np.testing.assert_allclose(float(batch.t_final[0]), float(across.t_final), rtol=0, atol=1e-5)
    alone = jb.simulate(roll, q1, x1, 0.1, max_steps=2_000, **kw)
    np.testing.assert_allclose(np.asarray(batch.q_final[1]), np.asarray(alone.q_final), rtol=0, atol=1e-12)
    assert "left their chart" in jb.simulation.explain_failure(roll, batch[0], 0.0, 0.1)
    stop = jb.Event(lambda t, q, x: jnp.sin(q[3]) - 1e-3, direction=False)
    landed = jb.simulate(roll, q0, x0, 0.1, max_steps=2_000, event=stop, **kw)
    assert landed.success
    np.testing.assert_allclose(float(jnp.sin(landed.q_final[3])), 1e-3, rtol=1e-6)


# ------------------------------------------------------------------------------ float32
@pytest.mark.slow
def test_float32_chaotic_double_pendulum():
    """Float32 with a tolerance float32 can meet: no NaN, and the energy drifts no more than a few
    hundred float32 ulps over 10 s of chaos (the trajectory itself decorrelates: chaos)."""
    drift, sol = double_pendulum_energy_error(10.0, solver="tsit5", tol=1e-6, dtype=np.float32)
    assert sol.q.dtype == jnp.float32 and np.isfinite(np.asarray(sol.q)).all()
    assert drift <= 1e-4, drift


@pytest.mark.slow
def test_float32_long_chain_and_mass_ratios_within_conditioning(long_chain):
    """Float32 forward dynamics of the 100-link chain and of the 1e6 mass ratios: finite, and as
    accurate as the mass matrix's conditioning allows (error ≲ cond(M)·ε₃₂·|a|): for these models
    that is no correct digit at all, the documented reason to stay in float64 for them."""
    eps32 = float(np.finfo(np.float32).eps)
    for xml in (long_chain[0], chain_mjcf(len(MASSES), masses=MASSES)):
        model32 = jb.from_mjcf(xml, dtype=np.float32)
        model64 = jb.from_mjcf(xml)
        q, v, tau = random_state(model64.nv, 0, scale=0.5)
        a32 = np.asarray(jb.forward_dynamics(model32, *(jnp.asarray(x, jnp.float32) for x in (q, v, tau))))
        assert a32.dtype == np.float32 and np.isfinite(a32).all()
        ref = mujoco_qacc(xml, q, v, tau)
        cond = np.linalg.cond(np.asarray(jb.mass_matrix(model64, jnp.asarray(q))))
        err = np.max(np.abs(a32 - ref)) / np.max(np.abs(ref))
        assert err <= 10 * cond * eps32, (err, cond)
        print(f"float32: n = {model64.nv}, cond(M) = {cond:.2e}, relative error {err:.2e}")


# ------------------------------------------------ float32 on the singular and stiff scenes
EPS32 = float(np.finfo(np.float32).eps)


def to_dtype(tree, dtype):
    """Every floating array of a model or system in ``dtype`` (integers and static fields kept)."""
    return jax.tree.map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, tree)


def test_float32_example5_reaction_near_the_horizontal_links():
    """Float32 keeps Example 5's reaction near φ = π/2 to float32 round-off: F_r cos φ equals the
    closed form (evaluated at the float32 angle) to a few ulps down to cos φ ≈ 1e-4."""
    ex5 = to_dtype(jb.examples.vertical_line_double_pendulum(), np.float32)
    reaction = eqx.filter_jit(ex5.reaction)
    for delta in (1e-2, 1e-4):
        for dphi in (0.0, 1.3):
            phi = float(np.float32(np.pi / 2 - delta))
            fr = reaction(jnp.array([phi], np.float32), jnp.array([dphi], np.float32))
            assert fr.dtype == jnp.float32
            np.testing.assert_allclose(float(fr) * np.cos(phi), example5_reaction_times_cos(phi, dphi), rtol=50 * EPS32)


@pytest.mark.slow
def test_float32_ball_joint_through_quaternion_sign_flip():
    """The free rotation through the quaternion's sign flip in float32 (``tsit5`` at 1e-5): no NaN,
    the attitude follows exp(tω̂) and the quaternion stays unit, to the solver's tolerance, and
    continuous through the flip."""
    b = jb.ModelBuilder(gravity=(0, 0, 0))
    # the float64 case's thin plate (0.3, 0.2, 0.1), on the triangle inequality's edge, which
    # float32 rounding crosses (0.1 + 0.2 < 0.3): the builder's check allows the dtype's rounding
    b.add_body("top", mass=1.0, com=(0, 0, 0), inertia=(0.3, 0.2, 0.1), joints=[jb.Ball()])
    model = b.build(dtype=np.float32)
    omega = np.array([0.0, 0.0, 2 * np.pi])
    sol = jb.simulate(model, jnp.array([1.0, 0, 0, 0], np.float32), jnp.asarray(omega, np.float32),
                      jnp.asarray(1.0, np.float32), solver="tsit5", rtol=1e-5, atol=1e-5, n_save=21)
    quat = np.asarray(sol.q, np.float64)
    assert sol.q.dtype == jnp.float32 and bool(sol.success) and np.isfinite(quat).all()
    assert quat[0, 0] > 0.99 and quat[-1, 0] < -0.99 and np.max(np.abs(np.diff(quat, axis=0))) < 0.2
    for t, qt in zip(np.asarray(sol.t, np.float64), quat):
        ref = Rotation.from_rotvec(omega * t).as_matrix()
        # to the solver's tolerance (1e-5 per step, accumulated over the turn)
        np.testing.assert_allclose(Rotation.from_quat(qt[[1, 2, 3, 0]]).as_matrix(), ref, atol=1e-4)
    # every step ends on the unit sphere; the saved points between steps are interpolated, off it by
    # the solver's tolerance
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-4)


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_float32_stiff_chain_kvaerno5():
    """The stiff chain (springs 1 to 1e6, critically damped) in float32 with ``kvaerno5`` at 1e-5:
    finite and within 1e-5 of float64, but the Newton iterations cannot meet the tolerance in float32
    (the 1e6 spring's torque cancels to a small difference): hundreds of times the steps of float64
    at the same tolerance, most of them rejected. The documented advice: stiff springs in float64."""
    damping, q0, _, _ = STIFF_CASES["critically_damped"]
    xml = chain_mjcf(5, stiffness=STIFFNESS, damping=damping(), axes=("0 1 0",))
    kw = dict(solver="kvaerno5", n_save=21, max_steps=100_000)
    runs = {}
    for dtype, tol in ((np.float64, 1e-10), (np.float64, 1e-5), (np.float32, 1e-5)):
        scene = jb.scene(jb.from_mjcf(xml, dtype=dtype), planar=False)
        runs[dtype, tol] = jb.simulate(scene, jnp.asarray(q0, dtype), jnp.zeros(5, dtype), jnp.asarray(0.02, dtype),
                                       rtol=tol, atol=tol, **kw)
    s32, ref, s64 = runs[np.float32, 1e-5], runs[np.float64, 1e-10], runs[np.float64, 1e-5]
    assert s32.q.dtype == jnp.float32 and bool(s32.success) and np.isfinite(np.asarray(s32.q)).all()
    assert np.max(np.abs(np.asarray(s32.q, np.float64) - np.asarray(ref.q))) < 1e-5
    steps = int(s32.stats["num_steps"]), int(s64.stats["num_steps"])
    print(f"stiff chain, kvaerno5 at 1e-5 over 0.02 s: float32 {steps[0]} steps ({int(s32.stats['num_rejected_steps'])} "
          f"rejected), float64 {steps[1]}; max |q32 - q64| = "
          f"{np.max(np.abs(np.asarray(s32.q, np.float64) - np.asarray(ref.q))):.2g}")
    assert steps[0] > 20 * steps[1], steps


@pytest.mark.slow
def test_float32_rolling_disk_falling_flat():
    """The nearly flat rolling disk in float32: it follows float64 to 1e-4 while it falls, and stops
    at float32's chart bound (|sin θ| ≤ ε₃₂^(1/4) = 1.8e-2), earlier than float64, with the same
    message naming the chart."""
    runs = {}
    for dtype, tol in ((np.float64, 1e-10), (np.float32, 1e-5)):
        roll = dk.rolling_disk(*(jnp.asarray(x, dtype) for x in (2.0, 0.3, 9.81)))
        q0 = jnp.array([0.0, 0.0, 0.0, 0.05, 0.0], dtype)
        x0 = dk.initial_velocities(roll, q0, jnp.array([-0.9 * np.cos(0.05), 0.0, 3.0, 0.0, 0.0], dtype),
                                   atol=1e-5 if dtype == np.float32 else 1e-9)
        runs[dtype] = roll, jb.simulate(roll, q0, x0, jnp.asarray(0.1, dtype), rtol=tol, atol=tol, max_steps=4_000,
                                        saveat=jnp.linspace(0, 0.05, 6).astype(dtype), throw=False)
    roll, s32 = runs[np.float32]
    s64 = runs[np.float64][1]
    assert s32.q.dtype == jnp.float32 and bool(s32.result == jb.RESULTS.singular_coordinates)
    assert 0.05 < float(s32.t_final) < float(s64.t_final)
    assert float(jnp.sin(s32.q_final[3])) <= EPS32**0.25 < 0.02
    assert "left their chart" in jb.simulation.explain_failure(roll, s32, 0.0, 0.1)
    print(f"flat disk, float32: stopped at t = {float(s32.t_final):.4g} (float64: {float(s64.t_final):.4g}), "
          f"max |q32 - q64| up to 0.05 s = {np.max(np.abs(np.asarray(s32.q, np.float64) - np.asarray(s64.q))):.2g}, "
          f"|v32 - v64| = {np.max(np.abs(np.asarray(s32.v, np.float64) - np.asarray(s64.v))):.2g}")
    np.testing.assert_allclose(np.asarray(s32.q, np.float64), np.asarray(s64.q), atol=1e-4)
    np.testing.assert_allclose(np.asarray(s32.v, np.float64), np.asarray(s64.v), atol=1e-4)


@pytest.mark.slow
def test_float32_example5_and_four_bar_through_their_singular_configurations(four_bar_scene):
    """Example 5 through φ = π/2 and the four-bar through its folded configuration in float32
    (``tsit5`` at 1e-5): no NaN, energy and constraints within 1e-4, the motion within 1e-3 of
    float64."""
    ex64 = jb.examples.vertical_line_double_pendulum()
    for name, system, q0, v0, t1, checks in (
        ("Example 5", ex64, np.array([1.2]), np.array([5.0]), 1.0, ()),
        ("four-bar", four_bar_scene, *four_bar_start(), 1.5, ("position",)),
    ):
        sols = {}
        for dtype, tol in ((np.float64, 1e-10), (np.float32, 1e-5)):
            sys_d = system if dtype == np.float64 else to_dtype(system, dtype)
            sols[dtype] = jb.simulate(sys_d, jnp.asarray(q0, dtype), jnp.asarray(v0, dtype), jnp.asarray(t1, dtype),
                                      solver="tsit5", rtol=tol, atol=tol, n_save=51)
        s32, s64 = sols[np.float32], sols[np.float64]
        drift = {k: float(jnp.max(jnp.abs(s32.constraint_drift[k]))) for k in checks}
        print(f"{name}, float32: energy drift {float(s32.energy_drift):.2g}, constraints {drift}, "
              f"max |q32 - q64| = {np.max(np.abs(np.asarray(s32.q, np.float64) - np.asarray(s64.q))):.2g}, "
              f"{int(s32.stats['num_steps'])} steps")
        assert s32.q.dtype == jnp.float32 and bool(s32.success) and np.isfinite(np.asarray(s32.q)).all()
        assert float(s32.energy_drift) < 1e-4
        for kind in checks:
            assert float(jnp.max(jnp.abs(s32.constraint_drift[kind]))) < 1e-4
        np.testing.assert_allclose(np.asarray(s32.q, np.float64), np.asarray(s64.q), atol=1e-3)


# ------------------------------------------------------------------------------ gradients
DAMPED = chain_mjcf(2, damping=(0.05, 0.05), axes=("0 1 0", "1 0 0"))


@pytest.mark.slow
def test_gradient_through_10k_step_rollout():
    """∂q(10 s)/∂q0 through 10⁴ RK4 steps of a damped (non-chaotic) chain: finite and equal to
    central finite differences."""
    scene = jb.scene(jb.from_mjcf(DAMPED))

    @jax.jit
    def final(q0):
        sol = jb.simulate(scene, q0, jnp.zeros(2), 10.0, solver="rk4", dt0=1e-3, n_save=2)
        return sol.q[-1]

    q0 = jnp.array([0.4, -0.3])
    jac = np.asarray(jax.jacrev(final)(q0))
    assert np.isfinite(jac).all()
    h = 1e-6
    fd = np.stack([(np.asarray(final(q0.at[i].add(h))) - np.asarray(final(q0.at[i].add(-h)))) / (2 * h)
                   for i in range(2)], axis=1)
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-8)
    assert np.abs(jac).max() > 1e-3  # damped, but the final state still depends on the start


@pytest.mark.slow
def test_gradients_at_rest_and_aligned():
    """At zero velocity, links aligned (hanging straight) and the ball joint at the identity
    quaternion (norms, square roots and divisions at their special points): gradients of a short
    solve and of the forward dynamics are finite and equal to finite differences."""
    xml = ('<mujoco><option gravity="0 0 -9.81"/><worldbody><body name="a"><joint name="ball" type="ball"/>'
           '<inertial pos="0 0 -0.15" mass="1" diaginertia="0.01 0.012 0.002"/>'
           '<body name="b" pos="0 0 -0.3"><joint name="h" axis="0 1 0"/>'
           '<inertial pos="0 0 -0.15" mass="0.5" diaginertia="0.005 0.005 0.001"/></body></body></worldbody></mujoco>')
    model = jb.from_mjcf(xml)
    q_rest, v_rest = jnp.array([1.0, 0, 0, 0, 0]), jnp.zeros(4)

    @jax.jit
    def final(v0):
        sol = jb.simulate(model, q_rest, v0, 0.2, solver="rk4", dt0=1e-3, n_save=2)
        return jnp.concatenate([sol.q[-1], sol.v[-1]])

    def check(fn, x, h=1e-6):
        jac = np.asarray(jax.jacrev(fn)(x))
        assert np.isfinite(jac).all()
        fd = np.stack([(np.asarray(fn(x.at[i].add(h))) - np.asarray(fn(x.at[i].add(-h)))) / (2 * h)
                       for i in range(x.shape[0])], axis=1)
        np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-7)

    check(final, v_rest)
    # forward dynamics as a function of the tangent-space rotation of the ball and of the rates
    def accel(z):
        q = jb.integrate_qpos(model, q_rest, z[:4], 1.0)
        return jb.forward_dynamics(model, q, z[4:], jnp.zeros(4))

    check(jax.jit(accel), jnp.zeros(8))


# ------------------------------------------------------------------ one bad member in a batch
BALL_CHAIN = ('<mujoco><option gravity="0 0 -9.81"/><worldbody><body name="a"><joint name="ball" type="ball" damping="0.05"/>'
              '<inertial pos="0 0 -0.15" mass="1" diaginertia="0.01 0.012 0.002"/>'
              '<body name="b" pos="0 0 -0.3"><joint name="h" axis="0 1 0" damping="0.05"/>'
              '<inertial pos="0 0 -0.15" mass="0.5" diaginertia="0.005 0.005 0.001"/></body></body></worldbody></mujoco>')
N_BATCH, BAD_PARAMETER, BAD_STATE = 1024, 5, 700


def _batch_inputs(model):
    rng = np.random.default_rng(1)
    rot = Rotation.from_rotvec(0.3 * rng.standard_normal((N_BATCH, 3))).as_quat()[:, [3, 0, 1, 2]]
    q0s = np.concatenate([rot, 0.5 * rng.standard_normal((N_BATCH, 1))], axis=1)
    q0s[BAD_STATE, :4] = 0.0  # a zero quaternion: no attitude at all (the normalisation divides by 0)
    v0s = 0.3 * rng.standard_normal((N_BATCH, model.nv))
    masses = np.tile(np.asarray(model.body_mass), (N_BATCH, 1))
    masses[BAD_PARAMETER, 1] = np.nan
    return q0s, v0s, masses


def _check_bad_member(kernel, solver_kw):
    """The batch with its two bad members against every member solved alone: the unbatched
    solves run as one ``lax.map`` over the members (one compiled program, each member traced
    without a batch axis), so all 1022 good members are compared, bit for bit up to rounding."""
    model = jb.from_mjcf(BALL_CHAIN)
    scene = jb.scene(model, kernel=kernel)
    q0s, v0s, masses = _batch_inputs(model)
    with_mass = lambda m: eqx.tree_at(lambda s: s.system.body_mass, scene, m)  # noqa: E731
    scenes = jax.vmap(with_mass)(jnp.asarray(masses))
    sol = jb.simulate_batch(scenes, q0s, v0s, 0.3, batched_system=True, **solver_kw)
    ok = np.ones(N_BATCH, bool)
    ok[[BAD_PARAMETER, BAD_STATE]] = False
    success = np.asarray(sol.success)
    assert not success[BAD_PARAMETER] and not success[BAD_STATE]
    assert success[ok].all()
    assert np.isfinite(np.asarray(sol.q_final)[ok]).all()

    # fixed steps: the end state alone, without the work integrals (the same steps, and the work
    # does not feed back into the motion) in a program that compiles in half the time; an adaptive
    # solve keeps its saves, which decide whether it runs as one native call
    end_only = dict(solver_kw)
    if "dt0" in solver_kw:
        end_only.pop("n_save", None)
        end_only.setdefault("saveat", diffrax.SaveAt(t1=True))
        end_only["track_work"] = False

    def alone(member):
        m, q0, v0 = member
        out = jb.simulate(with_mass(m), q0, v0, 0.3, throw=False, **end_only)
        return out.success, out.q_final, out.v_final

    each = jax.jit(lambda *members: jax.lax.map(alone, members))
    alone_success, alone_q, alone_v = (np.asarray(x) for x in each(jnp.asarray(masses), jnp.asarray(q0s), jnp.asarray(v0s)))
    np.testing.assert_array_equal(alone_success, success)
    np.testing.assert_allclose(np.asarray(sol.q_final)[ok], alone_q[ok], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(sol.v_final)[ok], alone_v[ok], rtol=0, atol=1e-11)


BATCH_CASES = {
    "vectorised": ("vectorised", dict(solver="rk4", dt0=1e-2, n_save=4)),
    "unrolled": ("unrolled", dict(solver="rk4", dt0=1e-2, n_save=4)),
    "native": ("native", dict(solver="tsit5", rtol=1e-8, atol=1e-8, n_save=4)),
    # fixed-step RK4 saving the end state alone on the native kernel: the one-call native solve
    "native_one_call": ("native", dict(solver="rk4", dt0=1e-2, saveat=diffrax.SaveAt(t1=True))),
}


@pytest.mark.parametrize("case", ["vectorised"])
def test_bad_member_leaves_the_batch_alone(case):
    kernel, kw = BATCH_CASES[case]
    _check_bad_member(kernel, kw)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["unrolled", "native", "native_one_call"])
def test_bad_member_leaves_the_batch_alone_every_kernel(case):
    kernel, kw = BATCH_CASES[case]
    _check_bad_member(kernel, kw)


# ------------------------------------------------------------------------------ the stiff chain
STIFFNESS = np.array([1.0, 10.0, 1e3, 1e5, 1e6])


def stiff_chain_scene(damping):
    model = jb.from_mjcf(chain_mjcf(5, stiffness=STIFFNESS, damping=damping, axes=("0 1 0",)))
    return jb.scene(model, planar=False)


def critical_damping():
    """Each joint critically damped on its own, ``2√(k_i M_ii)`` at the start (the coupled fast
    modes are then damped at 0.9 to 8 times critical)."""
    model = jb.from_mjcf(chain_mjcf(5, stiffness=STIFFNESS, axes=("0 1 0",)))
    M = np.asarray(jb.mass_matrix(model, jnp.full(5, 0.1)))
    return 2 * np.sqrt(STIFFNESS * np.diag(M))


STIFF_CASES = {
    # damped fast modes: where an L-stable implicit method steps over them
    "critically_damped": (critical_damping, np.full(5, 0.1), 1.0, 20),
    # damping 0.01, the soft joint deflected: the fast modes are barely excited, and an explicit
    # method is held to their stability limit
    "lightly_damped": (lambda: np.full(5, 0.01), np.array([0.1, 0, 0, 0, 0]), 1.0, 5),
}


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("case", sorted(STIFF_CASES))
def test_stiff_chain_implicit_beats_explicit(case):
    """Kvaerno5 (the ``"kvaerno5"`` preset, stages solved by Newton's method) reaches the converged
    reference at rtol = atol = 1e-7 in a fraction of the steps Tsit5 needs."""
    damping, q0, t1, fewer = STIFF_CASES[case]
    scene = stiff_chain_scene(damping())
    q0, v0 = jnp.asarray(q0), jnp.zeros(5)
    ref = jb.simulate(scene, q0, v0, t1, solver="dopri8", rtol=1e-12, atol=1e-12, n_save=2, max_steps=1_000_000)
    kw = dict(rtol=1e-7, atol=1e-7, n_save=2, max_steps=200_000)
    implicit = jb.simulate(scene, q0, v0, t1, solver="kvaerno5", **kw)
    explicit = jb.simulate(scene, q0, v0, t1, solver="tsit5", **kw)
    for sol in (implicit, explicit):
        assert float(jnp.max(jnp.abs(sol.q[-1] - ref.q[-1]))) < 1e-6
    steps = int(implicit.stats["num_steps"]), int(explicit.stats["num_steps"])
    print(f"stiff chain, {case}: kvaerno5 {steps[0]} steps, tsit5 {steps[1]}")
    assert fewer * steps[0] < steps[1], steps


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_stiff_chain_excited_fast_modes_do_not_fail_the_implicit_solver():
    """Damping 0.01 and every joint at 0.1 rad: the 1e6 spring rings at 1.5e4 rad/s with 0.1 rad
    amplitude, so accuracy (not stability) sets the step of every method. Kvaerno5 must follow it
    like Tsit5 does, in about as many steps (the chord iteration diffrax uses by default stopped
    converging here and took ten times as many, half of them rejected)."""
    scene = stiff_chain_scene(np.full(5, 0.01))
    q0, v0 = jnp.full(5, 0.1), jnp.zeros(5)
    kw = dict(rtol=1e-7, atol=1e-7, n_save=2, max_steps=50_000)
    ref = jb.simulate(scene, q0, v0, 0.01, solver="dopri8", rtol=1e-12, atol=1e-12, n_save=2, max_steps=1_000_000)
    implicit = jb.simulate(scene, q0, v0, 0.01, solver="kvaerno5", **kw)
    explicit = jb.simulate(scene, q0, v0, 0.01, solver="tsit5", **kw)
    steps = int(implicit.stats["num_steps"]), int(explicit.stats["num_steps"])
    assert steps[0] < 1.3 * steps[1], steps
    assert int(implicit.stats["num_rejected_steps"]) < 0.3 * steps[0]
    assert float(jnp.max(jnp.abs(implicit.q[-1] - ref.q[-1]))) < 1e-5


# ------------------------------------------------------------------------------ 10⁶ RK4 steps
@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_panda_million_rk4_steps(models_dir):
    """10⁶ fixed RK4 steps (1000 s at 1 ms) of Panda swinging under gravity without dampers, float64:
    no NaN, and the energy error stays bounded (no secular drift)."""
    model = jb.from_mjcf(models_dir / "panda.xml")
    scene = jb.scene(model, kernel="auto", dampers=False, springs=False)
    q0 = jnp.asarray(model.qpos0) + 0.3
    v0 = jnp.zeros(model.nv)
    sol = jb.simulate(scene, q0, v0, 1000.0, solver="rk4", dt0=1e-3, n_save=11, max_steps=1_000_001)
    assert sol.success and int(sol.stats["num_steps"]) == 1_000_000
    assert np.isfinite(np.asarray(sol.q)).all() and np.isfinite(np.asarray(sol.v)).all()
    e = np.asarray(sol.energy)
    scale = np.max(np.abs(e)) + float(jnp.max(jnp.abs(jb.potential_energy(model, q0))))
    assert np.max(np.abs(e - e[0])) <= 1e-6 * scale, (np.max(np.abs(e - e[0])), scale)
