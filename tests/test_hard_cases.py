"""Hard cases stay numerically stable: chaos, long chains, extreme mass ratios, near-singular
states, stiffness, float32, long-rollout gradients, a bad member in a batch, very long runs.

References are independent of the code under test: MuJoCo's ``mj_forward`` on the same MJCF
(built here as text), the closed forms of the papers (Example 5's reaction, a free rotation),
energy conservation, converged high-order runs, finite differences, and the unbatched solves.
The long versions are marked ``slow``; each has a short default-suite version.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxbody as jb

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


# -------------------------------------------------------------------- rolling disk nearly flat
def test_rolling_disk_nearly_flat():
    """The disk rolls with its plane close to the ground (θ = 0.08 rad, sin θ in the kinematics'
    denominators): energy and the rolling constraints hold; closer to flat than the solve can follow,
    it stops with a failed result instead of returning a wrong trajectory."""
    from jaxbody.examples import disk as dk

    roll = dk.rolling_disk()
    q0 = jnp.array([0.0, 0.0, 0.0, 0.08, 0.0])
    # spinning about its own axis and precessing: the disk stays low and circles
    qdot = jnp.array([0.0, 0.0, 3.0, 0.0, 0.0])
    qdot = qdot.at[0].set(-roll.base.radius * qdot[4])
    x0 = roll.base.quasi_velocities(q0, qdot)
    x0 = x0.at[3].set(-roll.base.radius * x0[2]).at[4].set(-roll.base.radius * jnp.sin(q0[3]) * x0[0])
    sol = jb.simulate(roll, q0, x0, 0.5, rtol=1e-10, atol=1e-10, n_save=51, throw=False, max_steps=20_000)
    theta = np.asarray(sol.q[:, 3])
    ok = np.isfinite(theta) & (np.asarray(sol.t) <= float(sol.t_final))
    assert ok[:5].all()
    if bool(sol.success):
        assert np.all(np.abs(np.sin(theta)) > 0)
        assert float(sol.energy_drift) < 1e-7
        assert float(jnp.max(jnp.abs(sol.constraint_drift["velocity"]))) < 1e-7
    else:
        assert float(sol.t_final) < 0.5
