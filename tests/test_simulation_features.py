"""Simulation features: presets, manifold, validation, result codes in batches, events, phases,
energy balance, files, adjoints, sharded batches (closed forms, finite differences, loops)."""

import os
import subprocess
import sys
import textwrap

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody._xla import default_xla_flags


def pendulum(damping=0.0, stiffness=0.0, g=9.81):
    b = jb.ModelBuilder(gravity=np.array([0.0, 0.0, -g]))
    b.add_body("link", mass=1.3, com=np.array([0.0, 0.0, -0.4]), inertia=np.array([0.03, 0.02, 0.01]),
               joints=[jb.Hinge(axis=np.array([0.0, -1.0, 0.0]), damping=damping, stiffness=stiffness)])
    return b.build()


def top():
    b = jb.ModelBuilder(gravity=np.array([0.0, 0.0, -9.81]))
    b.add_body("top", mass=2.0, com=np.array([0.0, 0.0, 0.3]), inertia=np.array([0.05, 0.04, 0.02]), joints=[jb.Ball()])
    return b.build()


class Osc(eqx.Module):
    k: jax.Array
    nq: int = eqx.field(static=True, default=1)
    nv: int = eqx.field(static=True, default=1)

    def qdot(self, q, v):
        return v

    def acceleration(self, t, q, v, tau):
        f = -self.k * q
        return f if tau is None else f + tau

    def total_energy(self, q, v):
        return 0.5 * jnp.sum(v * v) + 0.5 * self.k * jnp.sum(q * q)


@pytest.mark.parametrize(
    "solver, dt0, tol",
    [("euler", 1e-4, 5e-3), ("semi_implicit_euler", 1e-4, 5e-3), ("heun", 1e-3, 1e-5), ("rk4", 1e-2, 1e-7),
     ("tsit5", None, 1e-7), ("dopri5", None, 1e-7), ("dopri8", None, 1e-7), ("kvaerno5", None, 1e-6)],
)
def test_presets_reach_the_exact_solution(solver, dt0, tol):
    sol = jb.simulate(Osc(jnp.asarray(4.0)), jnp.array([1.0]), jnp.array([0.0]), 1.0, solver=solver, dt0=dt0,
                      n_save=11, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(sol.q[:, 0], np.cos(2.0 * np.asarray(sol.t)), atol=tol)


def test_dense_output():
    sol = jb.simulate(Osc(jnp.asarray(4.0)), jnp.array([1.0]), jnp.array([0.0]), 2.0, n_save=2, dense=True,
                      rtol=1e-10, atol=1e-10)
    for t in (0.1234, 1.5):
        q, v = sol.evaluate(t)
        np.testing.assert_allclose([q[0], v[0]], [np.cos(2 * t), -2 * np.sin(2 * t)], atol=1e-8)
    with pytest.raises(ValueError, match=r"needs simulate\(..., dense=True\)"):
        jb.simulate(Osc(jnp.asarray(4.0)), jnp.array([1.0]), jnp.array([0.0]), 2.0).evaluate(0.5)


def test_any_diffrax_solver_and_controller():
    sol = jb.simulate(Osc(jnp.asarray(4.0)), jnp.array([1.0]), jnp.array([0.0]), 1.0, solver=diffrax.Bosh3(),
                      controller=diffrax.PIDController(rtol=1e-10, atol=1e-10, pcoeff=0.3, icoeff=0.4))
    np.testing.assert_allclose(sol.q[:, 0], np.cos(2.0 * np.asarray(sol.t)), atol=1e-8)


def test_quaternion_stays_on_unit_sphere_over_1e4_steps():
    sol = jb.simulate(top(), jnp.array([np.cos(0.2), np.sin(0.2), 0.0, 0.0]), jnp.array([0.1, 0.3, 12.0]), 1.0,
                      solver="rk4", dt0=1e-4, saveat=diffrax.SaveAt(steps=True), max_steps=10_000)
    assert int(sol.stats["num_steps"]) == 10_000
    norms = np.linalg.norm(np.asarray(sol.q), axis=-1)
    np.testing.assert_allclose(norms, 1.0, rtol=0, atol=1e-12)
    assert abs(np.linalg.norm(np.asarray(sol.q_final)) - 1.0) < 1e-12
    assert float(sol.energy_drift) < 1e-9


def test_validation_names_the_argument():
    m = pendulum()
    q0, v0 = jnp.array([0.1]), jnp.array([0.0])
    with pytest.raises(ValueError, match=r"t1 \(-1.0\) must be after t0 \(0.0\)"):
        jb.simulate(m, q0, v0, -1.0)
    with pytest.raises(ValueError, match="rtol must be a positive finite number"):
        jb.simulate(m, q0, v0, 1.0, rtol=0.0)
    with pytest.raises(ValueError, match="atol must be a positive finite number"):
        jb.simulate(m, q0, v0, 1.0, atol=float("nan"))
    with pytest.raises(ValueError, match="dt0 must be a positive finite number"):
        jb.simulate(m, q0, v0, 1.0, solver="rk4", dt0=-0.1)
    with pytest.raises(ValueError, match="max_steps must be a positive finite number"):
        jb.simulate(m, q0, v0, 1.0, max_steps=0)
    with pytest.raises(ValueError, match=r"actuation: tau\(t, q, v\) returned shape \(2,\), expected \(1,\)"):
        jb.simulate(m, q0, v0, 1.0, tau=lambda t, q, v: jnp.zeros(2))
    with pytest.raises(ValueError, match=r"simulate: q0 contains NaN or inf at indices \[0\]"):
        jb.simulate(m, jnp.array([jnp.nan]), v0, 1.0)
    bad = eqx.tree_at(lambda mm: mm.body_mass, m, jnp.array([-1.0]))
    with pytest.raises(ValueError, match=r"body 0 \('link'\): body_mass is negative \(-1.0\)"):
        jb.simulate(bad, q0, v0, 1.0)
    nanp = eqx.tree_at(lambda mm: mm.dof_damping, pendulum(damping=0.1), jnp.array([jnp.nan]))
    with pytest.raises(ValueError, match=r"joint 0 \('link_hinge0'\): dof_damping is not finite"):
        jb.simulate(nanp, q0, v0, 1.0)
    with pytest.raises(ValueError, match="unknown solver 'rk45'"):
        jb.simulate(m, q0, v0, 1.0, solver="rk45")
    with pytest.raises(ValueError, match="adjoint must be"):
        jb.simulate(m, q0, v0, 1.0, adjoint="magic")


def test_nan_member_among_three_keeps_the_others():
    m = pendulum(damping=0.1)
    v0s = jnp.array([[0.5], [jnp.nan], [-0.3]])

    @jax.jit
    @jax.vmap
    def run(v0):
        return jb.simulate(m, jnp.array([0.2]), v0, 1.0, throw=False, n_save=5)

    sol = run(v0s)
    assert sol.success.tolist() == [True, False, True]
    assert (sol.result == jb.RESULTS.invalid_input).tolist() == [False, True, False]
    one = jb.simulate(m, jnp.array([0.2]), jnp.array([-0.3]), 1.0, n_save=5)
    np.testing.assert_allclose(sol.q[2], one.q, atol=1e-12)
    with pytest.raises(Exception, match="v0 contains NaN or inf"):
        jax.block_until_ready(jax.jit(lambda v: jb.simulate(m, jnp.array([0.2]), v, 1.0).q)(jnp.array([jnp.nan])))


def test_nan_parameter_member_in_a_batch():
    scenes = [jb.scene(pendulum(damping=d)) for d in (0.1, 0.1, 0.2)]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *scenes)
    assert stacked.effect_names == ("gravity", "dampers")
    stacked = eqx.tree_at(lambda s: s.effects[1].damping, stacked, stacked.effects[1].damping.at[1].set(jnp.nan))
    sol = jb.simulate_batch(stacked, jnp.full((3, 1), 0.2), jnp.zeros((3, 1)), 1.0, batched_system=True, n_save=5)
    assert sol.success.tolist() == [True, False, True]
    ref = jb.simulate(scenes[2], jnp.array([0.2]), jnp.array([0.0]), 1.0, n_save=5)
    np.testing.assert_allclose(sol.q[2], ref.q, atol=1e-12)


def test_max_steps_exhausted_without_throw_keeps_the_trajectory():
    m = pendulum(damping=0.1)
    sol = jb.simulate(m, jnp.array([0.5]), jnp.array([0.0]), 2.0, max_steps=5, throw=False, rtol=1e-10, atol=1e-10)
    assert not bool(sol.success) and bool(sol.result == jb.RESULTS.max_steps_reached)
    reached = np.isfinite(np.asarray(sol.q[:, 0]))
    assert reached[0] and not reached[-1]
    assert 0.0 < float(sol.t_final) < 2.0 and np.isfinite(np.asarray(sol.q_final)).all()
    full = jb.simulate(m, jnp.array([0.5]), jnp.array([0.0]), 2.0, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sol.q[reached], full.q[reached], atol=1e-8)
    with pytest.raises(jb.SimulationError, match=r"failed at t = .*maximum number of solver steps.*\n.*state at the failure: q = "):
        jb.simulate(m, jnp.array([0.5]), jnp.array([0.0]), 2.0, max_steps=5)


class Fragile(eqx.Module):
    """x'' = -x, but the right-hand side is NaN off the true orbit (|x| > 1.05)."""

    nq: int = eqx.field(static=True, default=1)
    nv: int = eqx.field(static=True, default=1)

    def qdot(self, q, v):
        return v

    def acceleration(self, t, q, v, tau):
        return jnp.where(jnp.abs(q) > 1.05, jnp.nan, -q)


def test_nan_trial_stage_is_a_rejected_step():
    sol = jb.simulate(Fragile(), jnp.array([0.0]), jnp.array([1.0]), 3.0, dt0=1.5, rtol=1e-8, atol=1e-8)
    assert bool(sol.success) and int(sol.stats["num_rejected_steps"]) > 0
    np.testing.assert_allclose(sol.q[:, 0], np.sin(np.asarray(sol.t)), atol=1e-6)


def test_energy_drift_is_measured_from_t0_whatever_the_saved_times():
    """With only t1 saved (or saved times after t0), the balance still starts at E(t0): the
    drift of a coarse RK4 run is what the same run reports at t1 when t0 is saved too."""
    m = pendulum(damping=0.3, stiffness=2.0)
    sc = jb.scene(m, actuation=lambda t, q, v: 0.5 * jnp.sin(3.0 * t)[None])
    q0, v0 = jnp.array([0.8]), jnp.array([0.0])
    run = lambda saveat: jb.simulate(sc, q0, v0, 3.0, solver="rk4", dt0=0.1, saveat=saveat)  # noqa: E731
    full = run(diffrax.SaveAt(ts=jnp.array([0.0, 1.5, 3.0])))
    end = run(diffrax.SaveAt(t1=True))
    later = run(diffrax.SaveAt(ts=jnp.array([1.5, 3.0])))
    np.testing.assert_allclose(float(end.energy0), float(sc.total_energy(q0, v0)), rtol=1e-14)
    np.testing.assert_allclose(float(full.energy0), float(full.energy[0]), rtol=1e-14)
    err_t1 = float(full.energy_error[-1])
    assert abs(err_t1) > 1e-7  # dt = 0.1 with damping and actuation: a visible balance error
    np.testing.assert_allclose(float(end.energy_error[-1]), err_t1, rtol=1e-12)
    np.testing.assert_allclose(float(end.energy_drift), abs(err_t1), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(later.energy_error), np.asarray(full.energy_error[1:]), rtol=1e-12)
    np.testing.assert_allclose(float(later.energy_drift), float(full.energy_drift), rtol=1e-12)


def test_energy_balance_closes_with_dampers_springs_and_actuation():
    m = pendulum(damping=0.3, stiffness=2.0)
    sc = jb.scene(m, actuation=lambda t, q, v: 0.5 * jnp.sin(3.0 * t)[None])
    sol = jb.simulate(sc, jnp.array([0.8]), jnp.array([0.0]), 3.0, rtol=1e-11, atol=1e-11)
    assert set(sol.work) == {"dampers", "actuation"}
    assert float(sol.dissipation[-1]) > 0.05
    assert float(sol.energy_drift) < 1e-8
    # the dissipation is the integral of c v² (trapezoid on a fine save grid)
    np.testing.assert_allclose(float(sol.dissipation[-1]), 0.3 * np.trapezoid(np.asarray(sol.v[:, 0]) ** 2, np.asarray(sol.t)), rtol=2e-3)


def test_terminating_event_located_to_tolerance():
    # x = cos 2t: first downward zero at π/4
    ev = jb.Event(lambda t, q, v: q[0], direction=False)
    sol = jb.simulate(Osc(jnp.asarray(4.0)), jnp.array([1.0]), jnp.array([0.0]), 3.0, event=ev, rtol=1e-10, atol=1e-10)
    assert bool(sol.event_occurred) and bool(sol.success)
    assert abs(float(sol.t_final) - np.pi / 4) < 1e-9
    assert abs(float(sol.q_final[0])) < 1e-9
    saved = np.isfinite(np.asarray(sol.q[:, 0]))
    assert np.all(np.asarray(sol.t)[saved] <= np.pi / 4 + 1e-9)


def test_phases_switch_at_an_event():
    m = pendulum()
    free, damped = jb.scene(m), jb.scene(m, dampers=jnp.array([0.5]))
    ph = jb.Phases(scenes=(free, damped), events=(jb.Event(lambda t, q, v: q[0], direction=False),))
    sol = jb.simulate(ph, jnp.array([0.5]), jnp.array([0.0]), 2.0, n_save=41, rtol=1e-11, atol=1e-11)
    first = jb.simulate(free, jnp.array([0.5]), jnp.array([0.0]), 2.0, event=ph.events[0], rtol=1e-11, atol=1e-11)
    te = float(first.t_final)
    second = jb.simulate(damped, first.q_final, first.v_final, 2.0, t0=te, saveat=np.linspace(te, 2.0, 5), rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(sol.q[-1], second.q[-1], atol=1e-9)
    before = np.asarray(sol.t) <= te
    ref = jb.simulate(free, jnp.array([0.5]), jnp.array([0.0]), 2.0, n_save=41, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(sol.q[before], ref.q[before], atol=1e-9)
    assert np.all(np.isfinite(np.asarray(sol.q)))


def test_control_signal_and_feedback_module_gradients():
    m = pendulum(g=0.0)  # J θ'' = tau: a control signal integrates twice
    ts = jnp.linspace(0.0, 1.0, 201)
    sig = jb.effects.ControlSignal(ts, jnp.sin(3 * ts)[:, None], method="cubic")
    J = 0.02 + 1.3 * 0.4**2
    sol = jb.simulate(jb.scene(m, actuation=sig), jnp.array([0.0]), jnp.array([0.0]), 1.0, n_save=11, rtol=1e-11, atol=1e-11)
    t = np.asarray(sol.t)
    np.testing.assert_allclose(sol.q[:, 0], (t / 3 - np.sin(3 * t) / 9) / J, atol=1e-6)

    class PD(eqx.Module):
        kp: jax.Array
        kd: jax.Array

        def __call__(self, t, q, v):
            return -self.kp * q - self.kd * v

    def loss(gains):
        sc = jb.scene(pendulum(), actuation=PD(gains[0], gains[1]))
        return jb.simulate(sc, jnp.array([0.5]), jnp.array([0.0]), 1.0, n_save=2, rtol=1e-11, atol=1e-11).q[-1, 0]

    g0 = jnp.array([3.0, 0.4])
    grad = jax.grad(loss)(g0)
    h = 1e-5
    fd = [(loss(g0.at[i].add(h)) - loss(g0.at[i].add(-h))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


@pytest.mark.slow
def test_adjoints_agree():
    for adj in ("backsolve", "forward"):
        def loss_adj(x0, adj=adj):
            return jb.simulate(pendulum(), x0, jnp.array([0.0]), 1.0, n_save=2, rtol=1e-11, atol=1e-11, adjoint=adj).q[-1, 0]
        ref = jax.grad(lambda x0: jb.simulate(pendulum(), x0, jnp.array([0.0]), 1.0, n_save=2, rtol=1e-11, atol=1e-11).q[-1, 0])(jnp.array([0.5]))
        got = jax.jacfwd(loss_adj)(jnp.array([0.5])) if adj == "forward" else jax.grad(loss_adj)(jnp.array([0.5]))
        np.testing.assert_allclose(got, ref, rtol=1e-6)


def test_save_load_and_csv(tmp_path, capfd):
    m = pendulum(damping=0.2)
    capfd.readouterr()
    sol = jb.simulate(m, jnp.array([0.5]), jnp.array([0.0]), 1.0, n_save=6, progress=True)
    err = capfd.readouterr().err  # progress=True shows diffrax's meter (tqdm, on stderr) up to 100%
    assert "100.00%" in err and "%|" in err, err[-500:]
    sol.save(tmp_path / "traj.npz")
    back = jb.load_solution(tmp_path / "traj.npz")
    for f in ("t", "q", "v", "energy", "t_final"):
        np.testing.assert_array_equal(getattr(back, f), getattr(sol, f))
    np.testing.assert_array_equal(back.work["dampers"], sol.work["dampers"])
    assert dict(back.layout)["q_names"] == ("link_hinge0",) and dict(back.layout)["joint_kinds"] == ("hinge",)
    assert bool(back.success)
    sol.to_csv(tmp_path / "traj.csv")
    lines = (tmp_path / "traj.csv").read_text().splitlines()
    # q and v columns named apart, as in `jaxbody simulate --csv` (q:<joint>, v:<joint>)
    assert lines[0] == "t,q:link_hinge0,v:link_hinge0,energy,work_dampers" and len(lines) == 7
    table = np.loadtxt(tmp_path / "traj.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(table[:, 1], sol.q[:, 0])
    np.testing.assert_array_equal(table[:, 2], sol.v[:, 0])


_REPLAY_MJCF = """
<mujoco>
  <option gravity="0 0 -9.81" integrator="RK4" timestep="1e-4"/>
  <worldbody>
    <body name="base" pos="0 0 1">
      <freejoint name="root"/>
      <inertial pos="0.01 0.02 0.0" mass="2" diaginertia="0.1 0.08 0.05"/>
      <body name="arm" pos="0.2 0 0">
        <joint name="shoulder" type="ball"/>
        <inertial pos="0.1 0 -0.05" mass="0.7" diaginertia="0.01 0.02 0.015"/>
        <body name="fore" pos="0.3 0 0">
          <joint name="elbow" type="hinge" axis="0 1 0"/>
          <inertial pos="0.15 0 0.02" mass="0.4" diaginertia="0.004 0.005 0.006"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_saved_solution_replays_in_mujoco(tmp_path):
    """The q/v layout recorded in a saved npz places each joint's entries where MuJoCo expects them:
    MuJoCo, fed the saved states through that layout, computes the same accelerations and, stepping
    from the first saved state with RK4, reaches the last one; the CSV header carries the same layout."""
    import json

    import mujoco

    (tmp_path / "m.xml").write_text(_REPLAY_MJCF)
    model = jb.from_mjcf(tmp_path / "m.xml")
    mj = mujoco.MjModel.from_xml_path(str(tmp_path / "m.xml"))
    rng = np.random.default_rng(3)
    quat = lambda: (lambda x: x / np.linalg.norm(x))(rng.standard_normal(4))  # noqa: E731
    q0 = np.concatenate([[0.1, -0.2, 1.0], quat(), quat(), [0.4]])
    v0 = rng.standard_normal(10)
    sol = jb.simulate(model, jnp.asarray(q0), jnp.asarray(v0), 0.05, n_save=3, rtol=1e-11, atol=1e-11)
    sol.save(tmp_path / "traj.npz")

    with np.load(tmp_path / "traj.npz") as f:
        t, q, v, lay = f["t"], f["q"], f["v"], json.loads(str(f["layout"]))
    nq_of, nv_of = {"free": 7, "ball": 4, "hinge": 1, "slide": 1}, {"free": 6, "ball": 3, "hinge": 1, "slide": 1}
    assert lay["joint_kinds"] == ["free", "ball", "hinge"]

    def to_mujoco(qk, vk):  # place the saved entries by joint name through the recorded layout
        qpos, qvel, vadr = np.full(mj.nq, np.nan), np.full(mj.nv, np.nan), 0
        for name, kind, qadr in zip(lay["joint_names"], lay["joint_kinds"], lay["qposadr"]):
            j = mj.joint(name)
            qpos[j.qposadr[0]:j.qposadr[0] + nq_of[kind]] = qk[qadr:qadr + nq_of[kind]]
            qvel[j.dofadr[0]:j.dofadr[0] + nv_of[kind]] = vk[vadr:vadr + nv_of[kind]]
            vadr += nv_of[kind]
        assert not (np.isnan(qpos).any() or np.isnan(qvel).any())
        return qpos, qvel

    data = mujoco.MjData(mj)
    ours = jax.jit(jax.vmap(jb.forward_dynamics, in_axes=(None, 0, 0)))(model, jnp.asarray(q), jnp.asarray(v))
    for k in range(len(t)):
        data.qpos[:], data.qvel[:] = to_mujoco(q[k], v[k])
        mujoco.mj_forward(mj, data)
        np.testing.assert_allclose(data.qacc, ours[k], rtol=1e-9, atol=1e-9)
    assert np.abs(data.qacc).max() > 1.0  # the states are not trivial

    data.qpos[:], data.qvel[:] = to_mujoco(q[0], v[0])
    for _ in range(round((t[-1] - t[0]) / mj.opt.timestep)):
        mujoco.mj_step(mj, data)
    qpos_end, qvel_end = to_mujoco(q[-1], v[-1])
    np.testing.assert_allclose(data.qpos, qpos_end, atol=1e-8)
    np.testing.assert_allclose(data.qvel, qvel_end, atol=1e-7)

    sol.to_csv(tmp_path / "traj.csv")
    header = (tmp_path / "traj.csv").read_text().splitlines()[0].split(",")
    assert header[:12] == ["t", "q:root.x", "q:root.y", "q:root.z", "q:root.qw", "q:root.qx", "q:root.qy",
                           "q:root.qz", "q:shoulder.qw", "q:shoulder.qx", "q:shoulder.qy", "q:shoulder.qz"]
    assert header[12:24] == ["q:elbow", "v:root.vx", "v:root.vy", "v:root.vz", "v:root.wx", "v:root.wy",
                             "v:root.wz", "v:shoulder.wx", "v:shoulder.wy", "v:shoulder.wz", "v:elbow", "energy"]


def test_batch_equals_loop_and_compiles_once():
    m = pendulum(damping=0.1)
    q0s = jnp.linspace(-1.0, 1.0, 5)[:, None]
    v0s = jnp.zeros((5, 1))
    sol = jb.simulate_batch(m, q0s, v0s, 1.0, n_save=5, chunk_size=2)
    for i in range(5):
        one = jb.simulate(m, q0s[i], v0s[i], 1.0, n_save=5)
        np.testing.assert_allclose(sol.q[i], one.q, atol=1e-13)


# about a minute (three programs compiled in a subprocess): slow job; the default job shards
# jb.vmap_chunked over two forced host devices (tests/test_batching.py)
@pytest.mark.slow
def test_sharded_batch_equals_unsharded_on_four_devices():
    code = textwrap.dedent("""
        import jax, jax.numpy as jnp, numpy as np
        jax.config.update("jax_enable_x64", True)
        import jaxbody as jb
        assert len(jax.devices()) == 4
        b = jb.ModelBuilder()
        b.add_body("a", mass=1.0, com=np.array([0, 0, -0.3]), inertia=np.array([0.1, 0.1, 0.1]),
                   joints=[jb.Hinge(axis=np.array([0.0, -1.0, 0.0]), damping=0.1)])
        b.add_body("b", parent="a", pos=np.array([0, 0, -0.5]), mass=0.7, com=np.array([0, 0, -0.2]),
                   inertia=np.array([0.05, 0.05, 0.05]), joints=[jb.Hinge(axis=np.array([0.0, -1.0, 0.0]))])
        m = b.build()
        q0s = jnp.stack([jnp.linspace(-2, 2, 10), jnp.linspace(1, -1, 10)], axis=1)
        v0s = jnp.zeros((10, 2)).at[3].set(jnp.nan)
        sh = jb.simulate_batch(m, q0s, v0s, 1.0, n_save=5, chunk_size=2)
        one = jb.simulate_batch(m, q0s, v0s, 1.0, n_save=5, devices=jax.devices()[:1])
        assert sh.success.tolist() == [True] * 3 + [False] + [True] * 6, sh.success
        ok = np.asarray(sh.success)
        # same numbers up to rounding: XLA vectorises a 2-member and a 10-member batch differently
        np.testing.assert_allclose(np.asarray(sh.q)[ok], np.asarray(one.q)[ok], rtol=0, atol=1e-12)
        plain = jax.jit(jax.vmap(lambda q, v: jb.simulate(m, q, v, 1.0, n_save=5, throw=False)))(q0s, v0s)
        np.testing.assert_allclose(np.asarray(sh.q)[ok], np.asarray(plain.q)[ok], rtol=0, atol=1e-12)
        assert str(sh.q.sharding) and len(sh.q.sharding.device_set) == 4
        print("SHARDED_OK")
    """)
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count=4 {default_xla_flags()}".strip(),
               JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert "SHARDED_OK" in out.stdout, out.stderr[-3000:]


class CountingLoad(jb.effects.Effect):
    """A zero force that counts how often it is traced (Python side effect at trace time)."""

    name = "counting"
    conservative = True

    def generalized_force(self, ctx):
        TRACES.append(1)
        return jnp.zeros_like(ctx.v)


TRACES = []


def test_batch_compiles_once_for_all_chunks_and_calls():
    sc = jb.scene(pendulum(), effects=(CountingLoad(),))
    q0s, v0s = jnp.linspace(-1.0, 1.0, 6)[:, None], jnp.zeros((6, 1))
    TRACES.clear()
    jb.simulate_batch(sc, q0s, v0s, 1.0, n_save=3, chunk_size=2)  # three chunks
    per_compile = len(TRACES)
    assert per_compile > 0
    jb.simulate_batch(sc, q0s + 0.1, v0s, 1.0, n_save=3, chunk_size=2)
    assert len(TRACES) == per_compile  # no new trace: one compilation served every chunk and call


def test_parameter_batch_compiles_once_and_equals_loop(capfd):
    """simulate_batch(..., batched_system=True): one compilation serves every chunk of a parameter
    batch and a second batch of other parameter values; each member equals its own solve; no
    progress meter unless asked."""
    def stack(dampings):
        scenes = [jb.scene(pendulum(damping=d), effects=(CountingLoad(),)) for d in dampings]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *scenes)

    q0s, v0s = jnp.linspace(-1.0, 1.0, 6)[:, None], jnp.zeros((6, 1))
    capfd.readouterr()
    TRACES.clear()
    sol = jb.simulate_batch(stack([0.05, 0.1, 0.2, 0.3, 0.4, 0.5]), q0s, v0s, 1.0, n_save=3, chunk_size=2,
                            batched_system=True)  # three chunks
    per_compile = len(TRACES)
    assert per_compile > 0
    sol2 = jb.simulate_batch(stack([0.6, 0.7, 0.8, 0.9, 1.0, 1.1]), q0s, v0s, 1.0, n_save=3, chunk_size=2,
                             batched_system=True)
    assert len(TRACES) == per_compile  # no new trace for other chunks or other parameter values
    assert "%|" not in capfd.readouterr().err
    one = jb.simulate(pendulum(damping=1.1), q0s[5], v0s[5], 1.0, n_save=3)  # member 5 of the second batch
    np.testing.assert_allclose(sol2.q[5], one.q, rtol=0, atol=1e-12)
    assert not np.allclose(sol.q[:, -1], sol2.q[:, -1])  # the dampings did change the motion


def test_parameter_pairs_get_gradients_and_errors_are_pinned():
    def law(t, q, v, p):
        return -p["k"] * q - p["c"] * v

    def loss(p):
        sc = jb.scene(pendulum(), actuation=(law, p))
        return jb.simulate(sc, jnp.array([0.4]), jnp.array([0.0]), 0.5, n_save=2, rtol=1e-11, atol=1e-11).q[-1, 0]

    p = {"k": jnp.asarray(2.0), "c": jnp.asarray(0.3)}
    g = jax.grad(loss)(p)
    h = 1e-5
    fd = (loss({**p, "k": p["k"] + h}) - loss({**p, "k": p["k"] - h})) / (2 * h)
    np.testing.assert_allclose(g["k"], fd, rtol=1e-5)
    m = pendulum()
    with pytest.raises(ValueError, match=r"phases: need n scenes and n - 1 events, got 2 scenes and 0 events"):
        jb.Phases(scenes=(jb.scene(m), jb.scene(m)), events=())
    with pytest.raises(ValueError, match=r"scene: gravity must be a bool or a \(3,\) vector"):
        jb.scene(m, gravity=jnp.ones(2))
    with pytest.raises(ValueError, match="scene: actuation must be callable"):
        jb.scene(m, actuation=(1.0, 2.0))
    with pytest.raises(ValueError, match="fixed-step solver 'heun' needs dt0"):
        jb.simulate(m, jnp.array([0.1]), jnp.array([0.0]), 1.0, solver="heun")
    with pytest.raises(TypeError, match="str lacks nq, nv, qdot, acceleration"):
        jb.simulate("pendulum", jnp.array([0.1]), jnp.array([0.0]), 1.0)


def test_written_out_rk4_stages_equal_the_tableau_rk4_with_every_adjoint():
    """``RK4Stages`` (the written-out RK4 of native/unrolled scenes) steps through the term's
    ``vf_prod``: its trajectory and its gradients — checkpointed, and backsolve, whose adjoint
    equations diffrax integrates with the same solver on an augmented term — equal the tableau
    RK4's to rounding. (Multiplying ``terms.vf`` by the step gave backsolve gradients wrong by
    a factor of order one.)"""
    from jaxbody.simulation import RK4, RK4Stages

    A = jnp.asarray(np.random.default_rng(3).standard_normal((4, 4)))
    term = diffrax.ODETerm(lambda t, y, a: (y[1], -a * jnp.sin(y[0]) + 0.1 * jnp.tanh(A @ y[1])))

    def final(solver, adjoint):
        def loss(y0, a):
            sol = diffrax.diffeqsolve(term, solver, 0.0, 0.5, 1e-2, y0, a, saveat=diffrax.SaveAt(t1=True), adjoint=adjoint)
            return jnp.sum(sol.ys[0][-1] ** 2) + jnp.sum(jnp.sin(sol.ys[1][-1]))

        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))

    y0 = (jnp.array([0.3, -0.2, 1.1, 0.5]), jnp.array([1.0, 0.0, -0.5, 2.0]))
    for adjoint in (diffrax.RecursiveCheckpointAdjoint(), diffrax.BacksolveAdjoint()):
        a = final(RK4Stages(), adjoint)(y0, 9.81)
        b = final(RK4(), adjoint)(y0, 9.81)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_allclose(x, y, rtol=1e-11, atol=1e-12)


def test_normalize_qpos_is_a_select_not_a_scatter():
    """normalize_qpos scales each ball/free quaternion to unit length and leaves every other
    coordinate bit for bit, and a vmap batch of it compiles without a loop over the batch
    (an indexed update compiles to a scatter that XLA's CPU backend runs as a while loop)."""
    from _support.random_models import random_model

    model = random_model(3, n_body=6, kinds=("ball", "hinge", "slide"))
    blocks = [qa[:, None] + kind.quaternion + np.arange(4) for kind, _, qa, _ in model.joints.kind_groups()
              if kind.quaternion is not None]
    iq = np.concatenate(blocks)
    assert iq.shape[0] >= 2  # the free root and at least one ball
    q = np.random.default_rng(0).normal(size=(64, model.nq)) * 3.0
    out = np.asarray(jax.jit(jax.vmap(lambda x: jb.normalize_qpos(model, x)))(jnp.asarray(q)))
    expect = q.copy()
    for rows in iq:
        expect[:, rows] = q[:, rows] / np.linalg.norm(q[:, rows], axis=1, keepdims=True)
    np.testing.assert_allclose(out, expect, rtol=4e-16 * 4, atol=0)
    others = np.setdiff1d(np.arange(model.nq), iq.ravel())
    assert np.array_equal(out[:, others], q[:, others])
    # a zero quaternion, or an inf outside the quaternions, spoils nothing else
    bad = q[0].copy()
    bad[iq[1]] = 0.0
    bad[others[0]] = np.inf
    out = np.asarray(jb.normalize_qpos(model, jnp.asarray(bad)))
    assert np.all(np.isnan(out[iq[1]])) and out[others[0]] == np.inf
    rest = np.setdiff1d(np.arange(model.nq), np.r_[iq[1], others[0]])
    assert np.all(np.isfinite(out[rest]))
    hlo = jax.jit(jax.vmap(lambda x: jb.normalize_qpos(model, x))).lower(jnp.asarray(q)).compile().as_text()
    loops = [line for line in hlo.splitlines() if " while(" in line or " scatter(" in line]
    assert not loops, loops[:3]
