"""The Maggi layer through the simulator: constraints in a scene's constraint slot.

A four-bar linkage (a spatial ``Model`` plus a ``LoopClosure``) and Example 5 run as scenes
through ``jb.simulate`` and ``jb.simulate_batch``; the rolling disk (a ``ConstrainedSystem`` on a
quasi-velocity base system) runs through both entry points directly. ``Solution.reactions`` and
``Solution.constraint_drift`` are checked against independent references: the planar
Newton–Euler equations of the four-bar with the pin forces as unknowns (``test_constraints``),
the disk's own Maggi solve at the saved states, and central finite differences for the
gradient of a loop reaction with respect to a link mass through the solve.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody import constraints as jc
from jaxbody import maggi
from jaxbody.examples import disk as dk

from test_constraints import example5, four_bar, four_bar_angles, four_bar_newton_euler, four_bar_rates

# shared by the four-bar tests, so one compiled solve serves them (forward-mode adjoint: the
# gradient test takes jax.jacfwd through the solve)
KW = dict(n_save=11, rtol=1e-10, atol=1e-10, adjoint="forward")
T_END = 1.0


def four_bar_state(crank_angle, crank_rate):
    th = four_bar_angles(crank_angle)
    w = four_bar_rates(th, crank_rate)
    return jnp.array([th[0], th[1] - th[0], th[2]]), jnp.array([w[0], w[1] - w[0], w[2]])


@pytest.fixture(scope="module")
def four_bar_scene():
    cs = four_bar()
    return jb.scene(cs.base.model, constraints=cs)


@pytest.fixture(scope="module")
def ex5():
    return example5()


@pytest.fixture(scope="module")
def four_bar_run(four_bar_scene):
    q0, v0 = four_bar_state(0.6, 2.0)
    return jb.simulate(four_bar_scene, q0, v0, T_END, **KW)


def test_four_bar_scene_reactions_and_residuals(four_bar_scene, four_bar_run):
    sol = four_bar_run
    assert four_bar_scene.path == "spatial" and isinstance(four_bar_scene.constraints, maggi.ConstrainedSystem)
    assert sol.reactions.shape == (11, 2)
    assert set(sol.constraint_drift) == {"position", "velocity"}
    assert dict(sol.layout)["constraint_names"] == four_bar().constraint_names
    # residuals bounded along the run
    assert float(jnp.max(jnp.abs(sol.constraint_drift["position"]))) < 1e-9
    assert float(jnp.max(jnp.abs(sol.constraint_drift["velocity"]))) < 1e-8
    assert float(sol.energy_drift) < 1e-8
    # the loop reaction is the pin force on the coupler: planar Newton–Euler at each saved state
    for q, v, lam in zip(np.asarray(sol.q), np.asarray(sol.v), np.asarray(sol.reactions)):
        th = np.array([q[0], q[0] + q[1], q[2]])
        w = np.array([v[0], v[0] + v[1], v[2]])
        np.testing.assert_allclose(lam, four_bar_newton_euler(th, w)[7:9], rtol=1e-7, atol=1e-7)


def test_four_bar_drift_is_bounded_over_two_seconds(four_bar_scene):
    """Default-suite smoke version of test_constraints::test_four_bar_long_run_drift_is_bounded
    (20 s, slow): 2 s of the four-bar scene, with Baumgarte stabilisation and without it.
    Same compiled solve as the other four-bar runs here (t1 and the Baumgarte rate are data)."""
    q0, v0 = four_bar_state(0.6, 2.0)
    sol = jb.simulate(four_bar_scene, q0, v0, 2.0, **KW)
    assert float(jnp.max(jnp.abs(sol.constraint_drift["position"]))) < 1e-9
    assert float(jnp.max(jnp.abs(sol.constraint_drift["velocity"]))) < 1e-8
    assert float(sol.energy_drift) < 1e-8
    assert float(jnp.ptp(sol.q[:, 0])) > 0.5  # the linkage swings (not a state at rest)
    off = eqx.tree_at(lambda s: s.constraints.baumgarte, four_bar_scene, jnp.zeros_like(four_bar_scene.constraints.baumgarte))
    sol0 = jb.simulate(off, q0, v0, 2.0, **KW)
    drift0 = float(jnp.max(jnp.abs(sol0.constraint_drift["position"])))
    assert drift0 < 1e-8  # measured 3e-10 (stabilised: 4e-11)
    # the unstabilised run follows the same motion to the integrator's error level
    np.testing.assert_allclose(sol0.q, sol.q, atol=1e-7)


@pytest.mark.slow
def test_four_bar_scene_equals_constrained_system(four_bar_run):
    """The scene path (gravity a declared effect, M and f from the scene) and the
    ConstrainedSystem itself (its ModelBase bracket) integrate the same motion."""
    sol = four_bar_run
    direct = jb.simulate(four_bar(), sol.q[0], sol.v[0], T_END, **KW)
    np.testing.assert_allclose(direct.q, sol.q, atol=1e-9)
    np.testing.assert_allclose(direct.reactions, sol.reactions, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(direct.constraint_drift["position"], sol.constraint_drift["position"], atol=1e-9)


@pytest.mark.slow  # about 45 s; a constrained simulate_batch stays in the default suite (test_simulation_partitioning)
def test_four_bar_batch_equals_loop(four_bar_scene):
    states = [four_bar_state(a, w) for a, w in ((0.6, 2.0), (1.4, -1.0), (2.5, 0.5))]
    q0s = jnp.stack([s[0] for s in states])
    v0s = jnp.stack([s[1] for s in states])
    batch = jb.simulate_batch(four_bar_scene, q0s, v0s, T_END, **KW)
    assert batch.reactions.shape == (3, 11, 2) and batch.constraint_drift["velocity"].shape == (3, 11, 2)
    for i in range(3):
        one = jb.simulate(four_bar_scene, q0s[i], v0s[i], T_END, **KW)
        np.testing.assert_allclose(batch.q[i], one.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.v[i], one.v, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.reactions[i], one.reactions, rtol=1e-12, atol=1e-12)
        for k in ("position", "velocity"):
            np.testing.assert_allclose(batch.constraint_drift[k][i], one.constraint_drift[k], rtol=0, atol=1e-12)


@pytest.mark.slow  # 40-65 s; the default suite differentiates constrained solves in test_simulation_partitioning.py and the disk tests
def test_loop_reaction_gradient_wrt_link_mass_through_the_solve(four_bar_scene):
    """∂Λ(t1)/∂m_coupler through a constrained simulation vs central finite differences."""
    q0, v0 = four_bar_state(0.6, 2.0)
    t1 = 0.3

    def final_reaction(m):
        sc = eqx.tree_at(lambda s: s.system.body_mass, four_bar_scene, four_bar_scene.system.body_mass.at[1].set(m))
        return jb.simulate(sc, q0, v0, t1, **KW).reactions[-1, 0]

    m = 1.2
    g = float(jax.jacfwd(final_reaction)(m))
    h = 1e-3
    fd = (float(final_reaction(m + h)) - float(final_reaction(m - h))) / (2 * h)
    assert abs(g) > 1e-2
    np.testing.assert_allclose(g, fd, rtol=1e-5)


@pytest.mark.slow  # ~2-5 min: reverse mode through the checkpointed solve of the spatial four-bar
def test_loop_reaction_gradient_wrt_link_mass_reverse_mode():
    """The same gradient with the default (checkpointed) adjoint: ``jax.grad`` through the
    PartitionSolver, whose partition lives in the solver state, vs central differences."""
    cs = four_bar()
    sc = jb.scene(cs.base.model, constraints=cs)
    q0, v0 = four_bar_state(0.6, 2.0)
    kw = dict(n_save=11, rtol=1e-10, atol=1e-10)  # adjoint: the default

    def final_reaction(m):
        s = eqx.tree_at(lambda s: s.system.body_mass, sc, sc.system.body_mass.at[1].set(m))
        return jb.simulate(s, q0, v0, 0.3, **kw).reactions[-1, 0]

    m, h = 1.2, 1e-3
    g = float(jax.grad(final_reaction)(m))
    fd = (float(final_reaction(m + h)) - float(final_reaction(m - h))) / (2 * h)
    assert abs(g) > 1e-2
    np.testing.assert_allclose(g, fd, rtol=1e-5)  # measured: 4e-7


class PointMass(maggi.QuasiVelocitySystem):
    """A particle in a vertical plane, Cartesian coordinates = quasi-velocities."""

    mass: jax.Array
    nq = 2
    nv = 2

    def kinetic_energy_rates(self, q, qd):
        return 0.5 * self.mass * qd @ qd

    def potential_energy(self, q):
        return self.mass * 9.81 * q[1]

    def qdot(self, q, x):
        return x

    def quasi_velocities(self, q, qd):
        return qd


@pytest.mark.slow  # 11-12 s; test_simulation_partitioning.py checks a repartitioned solve's gradient by default
def test_reverse_mode_gradient_through_repartitioning_solve():
    """``jax.grad`` with the default checkpointed adjoint through a constrained solve whose
    coordinate partition changes on the way (a Cartesian pendulum swinging past the
    horizontal: the free velocity switches from x to y), vs central differences."""
    L, th0 = 1.3, 0.3
    rod = maggi.VelocityConstraint(lambda b, t, q, x: (q @ x)[None] / L, size=1, label="rod",
                                   position=lambda b, t, q: ((q @ q - L**2) / (2 * L))[None])
    q0 = jnp.array([L * np.sin(th0), -L * np.cos(th0)])
    cs = maggi.constrain(PointMass(jnp.asarray(0.7)), [rod], q_ref=q0)
    assert cs.partitioned

    def run(w):
        return jb.simulate(cs, q0, w * jnp.array([np.cos(th0), np.sin(th0)]), 1.0, n_save=2, rtol=1e-10, atol=1e-10)

    sol = run(jnp.asarray(5.0))
    assert int(sol.stats["num_repartitions"]) >= 1  # the partition in the solver state changed
    # the reaction is the rod force along q/L: λ = −m v²/L + m g y/L (radial Newton's law)
    q, v = np.asarray(sol.q[-1]), np.asarray(sol.v[-1])
    np.testing.assert_allclose(sol.reactions[-1, 0], 0.7 * (-(v @ v) + 9.81 * q[1]) / L, rtol=1e-7)
    f = lambda w: run(w).reactions[-1, 0]
    g = float(jax.grad(f)(5.0))
    h = 1e-4
    fd = (float(f(5.0 + h)) - float(f(5.0 - h))) / (2 * h)
    assert abs(g) > 1.0
    np.testing.assert_allclose(g, fd, rtol=1e-6)  # measured: 1e-9


def test_singular_user_parametrisation_is_a_result_code_of_simulate():
    """A user ε that is singular at a member's state (ε = horizontal velocity of a Cartesian
    pendulum: no parametrisation when the rod is horizontal): jb.simulate_batch gives that
    member RESULTS.singular_parametrisation and finishes the others; throw=True names it."""
    L = 1.3
    rod = maggi.VelocityConstraint(lambda b, t, q, x: (q @ x)[None] / L, size=1, label="rod",
                                   position=lambda b, t, q: ((q @ q - L**2) / (2 * L))[None])
    hanging = jnp.array([L * np.sin(0.3), -L * np.cos(0.3)])
    cs = maggi.constrain(PointMass(jnp.asarray(0.7)), [rod], q_ref=hanging, epsilon=lambda b, t, q, x: x[:1])
    assert not cs.partitioned
    q0s = jnp.stack([hanging, jnp.array([L, 0.0])])  # the second starts horizontal
    v0s = jnp.stack([jnp.array([np.cos(0.3), np.sin(0.3)]), jnp.array([0.0, -1.0])])
    kw = dict(n_save=3, rtol=1e-10, atol=1e-10, throw=False)
    batch = jb.simulate_batch(cs, q0s, v0s, 0.5, **kw)
    assert int(batch.result._value[0]) == int(jb.RESULTS.successful._value)
    assert int(batch.result._value[1]) == int(jb.RESULTS.singular_parametrisation._value)
    assert "cannot be solved for the velocities" in jb.RESULTS._index_to_message[int(batch.result._value[1])]
    # the good member is untouched by the bad one: the same as alone, and physical
    one = jb.simulate(cs, q0s[0], v0s[0], 0.5, **kw)
    np.testing.assert_allclose(batch.q[0], one.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(jnp.sum(batch.q[0] ** 2, axis=1), L**2, rtol=1e-9)
    with pytest.raises(jb.SimulationError, match="cannot be solved for the velocities"):
        jb.simulate(cs, q0s[1], v0s[1], 0.5, n_save=3)


def test_example5_point_on_line_is_redundant_in_the_plane(ex5):
    """Example 5 (simulated through the slot in test_scene) written as a point on the vertical
    line: of its two rows, the one normal to the plane of motion is satisfied by the hinges
    identically, so the scene names it redundant (the in-plane PointOnPlane is the one to use)."""
    model = ex5.base.model
    with pytest.raises(ValueError, match="redundant"):
        jb.scene(model, constraints=[jc.PointOnLine(model, "link2", (0, 0, -0.8), direction=(0, 0, 1))])


@pytest.mark.slow  # ~20 s (two compilations of the disk's autodiff bracket)
def test_rolling_disk_through_simulate_and_simulate_batch():
    cs = dk.rolling_disk()
    rho = float(cs.base.radius)
    th = 1.2

    def admissible(x1, x2, x3):  # rolling: x4 = −ρ x3, x5 = −ρ sin θ x1
        return jnp.array([x1, x2, x3, -rho * x3, -rho * np.sin(th) * x1])

    q0s = jnp.array([[0.0, 0.0, 0.0, th, 0.0], [0.1, -0.2, 0.3, th, 0.5]])
    x0s = jnp.stack([admissible(0.2, 1.0, 6.0), admissible(-0.3, 0.5, 4.0)])
    kw = dict(n_save=6, rtol=1e-10, atol=1e-10)
    batch = jb.simulate_batch(cs, q0s, x0s, 0.5, **kw)
    assert batch.reactions.shape == (2, 6, 2)
    for i in range(2):
        one = jb.simulate(cs, q0s[i], x0s[i], 0.5, **kw)
        np.testing.assert_allclose(batch.q[i], one.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.reactions[i], one.reactions, rtol=1e-12, atol=1e-12)
        # the friction reactions equal the Maggi solve at the saved states
        out = dk.disk_outputs(cs, one.t, one.q, one.v)
        np.testing.assert_allclose(one.reactions, out.reactions, rtol=1e-7, atol=1e-8)
        # non-holonomic rows: no position residual; velocity residuals bounded; energy kept
        np.testing.assert_array_equal(one.constraint_drift["position"], 0.0)
        assert float(jnp.max(jnp.abs(one.constraint_drift["velocity"]))) < 1e-9
        assert float(one.energy_drift) < 1e-8


def test_solution_file_keeps_residuals_and_reactions(four_bar_run, tmp_path):
    four_bar_run.save(tmp_path / "fb.npz")
    back = jb.load_solution(tmp_path / "fb.npz")
    np.testing.assert_array_equal(back.reactions, four_bar_run.reactions)
    for k in ("position", "velocity"):
        np.testing.assert_array_equal(back.constraint_drift[k], four_bar_run.constraint_drift[k])
    assert dict(back.layout)["constraint_names"] == dict(four_bar_run.layout)["constraint_names"]


def test_constraint_slot_errors(four_bar_scene, ex5):
    model = four_bar_scene.system
    loop = four_bar().constraints[0]
    # at qpos0 the four-bar lies along x: the x row of the loop is redundant there
    with pytest.raises(ValueError, match=r"scene: constraints: .*q_ref="):
        jb.scene(model, constraints=[loop])
    with pytest.raises(ValueError, match="not on a jaxbody.Model"):
        jb.scene(model, constraints=dk.rolling_disk())
    with pytest.raises(ValueError, match="lacks accelerations, drift"):
        jb.scene(model, constraints=object())
    with pytest.raises(ValueError, match=r"\(nq, nv\) = \(2, 2\)"):
        jb.scene(model, constraints=ex5)
