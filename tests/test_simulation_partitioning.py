"""Coordinate partitioning kept while well conditioned, re-chosen when it degrades.

The mechanism: a point mass on two slide joints (x, z) held on a circle of radius L about the
origin by one velocity constraint ``x·ẋ + z·ż = 0`` (a pendulum in Cartesian coordinates).
Pivoted QR at the bottom chooses ``ε = ẋ``, which cannot parametrise the motion at the
horizontal, where ``ż`` is not determined by ``ẋ``. References: the same pendulum in its joint
angle, ``θ̈ = −(g/L) sin θ``, integrated by scipy's ``solve_ivp`` (DOP853, rtol 1e-13), its rod
tension ``m(g cos θ + L θ̇²)``, and numpy/scipy for the partition measures.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from scipy.integrate import solve_ivp

import jaxbody as jb
from jaxbody import maggi

L, MASS, G = 1.0, 0.7, 9.81
T_END = 2.0
TS = np.linspace(0.0, T_END, 41)
KW = dict(saveat=TS, rtol=1e-11, atol=1e-11)
Q0 = jnp.array([0.0, -L])  # at the bottom
W0 = 7.0  # rad/s: enough to go over the top


@functools.lru_cache
def bob_model():
    b = jb.ModelBuilder(gravity=(0, 0, -G))
    b.add_body("bob", mass=MASS, inertia=(1e-3, 1e-3, 1e-3),
               joints=[jb.Slide(axis=(1, 0, 0)), jb.Slide(axis=(0, 0, 1))])
    return b.build()


def on_circle():
    return maggi.VelocityConstraint(
        lambda base, t, q, x: q[0] * x[0] + q[1] * x[1], size=1, label="on circle",
        position=lambda base, t, q: 0.5 * (q @ q - L**2),
    )


@functools.lru_cache
def pendulum(repartition=True):
    return maggi.constrain(bob_model(), [on_circle()], q_ref=Q0, repartition=repartition)


@functools.lru_cache
def reference():
    """θ(t) from the bottom, dense (θ̈ = −(g/L) sin θ)."""
    return solve_ivp(lambda t, y: [y[1], -G / L * np.sin(y[0])], (0, T_END), [0.0, W0], method="DOP853",
                     rtol=1e-13, atol=1e-13, dense_output=True)


def cartesian(theta, omega):
    q = np.stack([L * np.sin(theta), -L * np.cos(theta)], -1)
    v = np.stack([L * omega * np.cos(theta), L * omega * np.sin(theta)], -1)
    return q, v


@pytest.fixture(scope="module")
def scene_run():
    return jb.simulate(jb.scene(bob_model(), constraints=pendulum()), Q0, jnp.array([W0 * L, 0.0]), T_END, **KW)


def test_initial_partition_is_x_and_degrades_at_the_horizontal():
    s = pendulum()
    assert s.free.tolist() == [0]  # ε = ẋ: ż is the dependent velocity
    for theta in (0.3, 1.2, 1.5):
        q, v = cartesian(theta, 1.0)
        c = float(s.partition_quality(0.0, jnp.asarray(q), jnp.asarray(v)))
        assert abs(c) == pytest.approx(np.cos(theta), rel=1e-12)  # |z|/L
    q, v = cartesian(np.pi / 2, 1.0)
    assert s.best_partition(0.0, jnp.asarray(q), jnp.asarray(v)).tolist() == [1]


def _linear_rows(base, t, q, x, C):
    return C @ x


@jax.jit
def _measures(system, free, q, x):
    sf = system.with_partition(free)
    return sf.partition_quality(0.0, q, x), sf.solve(0.0, q, x).A, system.best_partition(0.0, q, x)


def test_partition_measures_against_numpy():
    """Quality = |det G_d| / sqrt(det G Gᵀ) = 1/sqrt(det AᵀA), invariant under row scaling;
    the array-operation choice equals scipy's column-pivoted QR."""
    rng = np.random.default_rng(4)
    n, s = 5, 2
    b = jb.ModelBuilder(gravity=(0, 0, 0))
    parent = None
    for i in range(n):
        b.add_body(f"b{i}", parent=parent, mass=1.0 + i, inertia=(0.1, 0.1, 0.1),
                   joints=[jb.Slide(axis=tuple(np.eye(3)[i % 3]))])
        parent = f"b{i}"
    model = b.build()
    q = jnp.zeros(n)
    for trial in range(3):
        C = rng.normal(size=(s, n))
        x = jnp.asarray(rng.normal(size=n))
        scaled = np.diag(rng.uniform(0.1, 10.0, s)) @ C
        systems = [maggi.constrain(model, [maggi.VelocityConstraint(_linear_rows, size=s, params=jnp.asarray(c))], q_ref=q)
                   for c in (C, scaled)]
        _, _, piv = scipy.linalg.qr(C, pivoting=True)
        expected_free = sorted(set(range(n)) - set(piv[:s].tolist()))
        assert systems[0].free.tolist() == expected_free  # chosen at build time
        for free in ([0, 1, 2], [2, 3, 4], expected_free):
            dep = sorted(set(range(n)) - set(free))
            want = abs(np.linalg.det(C[:, dep])) / np.sqrt(np.linalg.det(C @ C.T))
            c, A, best = _measures(systems[0], jnp.asarray(free), q, x)
            assert best.tolist() == expected_free
            assert abs(float(c)) == pytest.approx(want, rel=1e-10)
            A = np.asarray(A)
            assert abs(float(c)) == pytest.approx(1 / np.sqrt(np.linalg.det(A.T @ A)), rel=1e-10)
            assert float(_measures(systems[1], jnp.asarray(free), q, x)[0]) == pytest.approx(float(c), rel=1e-10)


def test_pendulum_through_the_horizontal_repartitions_and_matches_the_joint_angle(scene_run):
    sol = scene_run
    assert bool(sol.success)
    ref = reference()
    theta, omega = ref.sol(TS)
    q_ref, v_ref = cartesian(theta, omega)
    np.testing.assert_allclose(sol.q, q_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(sol.v, v_ref, rtol=0, atol=1e-8)
    # reaction of x·ẋ + z·ż = 0: the force Λ·(x, z) on the bob is minus the rod tension along (x, z)/L
    tension = MASS * (G * np.cos(theta) + L * omega**2)
    np.testing.assert_allclose(np.asarray(sol.reactions[:, 0]), -tension / L, rtol=1e-8, atol=1e-8)
    # re-chosen only where the kept partition degraded: each time within one band of a quarter
    # turn (ε = ẋ fails at the horizontal, ε = ż at the vertical), one per quarter, in order
    n = int(sol.stats["num_repartitions"])
    times = np.asarray(sol.repartition_times)
    assert n > 0 and np.all(np.isfinite(times[:n])) and np.all(np.isnan(times[n:]))
    quarters = ref.sol(times[:n])[0] / (np.pi / 2)
    np.testing.assert_array_equal(np.round(quarters), np.arange(1, n + 1))
    assert np.max(np.abs(quarters - np.round(quarters))) < np.arctan(0.1) / (np.pi / 2) + 0.02
    # every quarter reached before t1 (less the band) was passed with a new partition
    assert n == int(np.floor(ref.sol(T_END)[0] / (np.pi / 2) + np.arctan(0.1) / (np.pi / 2)))


def test_without_repartitioning_the_run_stops_with_the_degradation_code(scene_run):
    scene = jb.scene(bob_model(), constraints=pendulum(repartition=False))
    sol = jb.simulate(scene, Q0, jnp.array([W0 * L, 0.0]), T_END, throw=False, **KW)
    assert sol.result == jb.RESULTS.partition_degraded
    assert int(sol.stats["num_repartitions"]) == 0
    # it stops where the other run changed partition: the first step that ended degraded. The
    # two runs are different programs, so their steps agree to rounding, not bit for bit (about
    # 1e-9 s here); a stop one step earlier or later would be a step, milliseconds, away
    assert float(sol.t_final) == pytest.approx(float(scene_run.repartition_times[0]), abs=1e-6)
    q, v = np.asarray(sol.q_final), np.asarray(sol.v_final)
    assert abs(q[1]) < 0.1 * abs(q[0])  # near the horizontal, |z| < 0.1 |x|
    # what was integrated before is kept and right
    done = np.isfinite(np.asarray(sol.t)) & (np.asarray(sol.t) <= float(sol.t_final))
    theta, omega = reference().sol(np.asarray(sol.t)[done])
    np.testing.assert_allclose(np.asarray(sol.q)[done], cartesian(theta, omega)[0], rtol=0, atol=1e-8)
    with pytest.raises(jb.SimulationError, match="coordinate partition of the constraints degraded"):
        jb.simulate(scene, Q0, jnp.array([W0 * L, 0.0]), T_END, **KW)


@pytest.mark.slow  # ~10-18 s: a second compilation, under vmap
def test_batch_repartitions_per_member():
    """Under vmap each member keeps its own partition: a small swing keeps ε = ẋ."""
    scene = jb.scene(bob_model(), constraints=pendulum())
    v0s = jnp.array([[W0 * L, 0.0], [1.0, 0.0]])
    sol = jb.simulate_batch(scene, jnp.stack([Q0, Q0]), v0s, T_END, **KW)
    counts = np.asarray(sol.stats["num_repartitions"]).tolist()
    assert counts[0] > 0 and counts[1] == 0
    for i, w in enumerate((W0, 1.0)):
        theta, omega = solve_ivp(lambda t, y: [y[1], -G / L * np.sin(y[0])], (0, T_END), [0.0, w], method="DOP853",
                                 rtol=1e-13, atol=1e-13, t_eval=TS).y
        np.testing.assert_allclose(sol.q[i], cartesian(theta, omega)[0], rtol=0, atol=1e-8)


def single_phase(system):
    """``system`` as the one phase of a ``jb.Phases`` run."""
    return jb.Phases(scenes=(jb.scene(system),), events=())


@pytest.mark.slow  # ~25 s: the ConstrainedSystem's own bracket compiles twice
def test_constrained_system_and_phase_runner_repartition(scene_run):
    s = pendulum()
    v0 = jnp.array([W0 * L, 0.0])
    direct = jb.simulate(s, Q0, v0, T_END, **KW)
    np.testing.assert_allclose(direct.q, scene_run.q, rtol=0, atol=1e-9)
    assert int(direct.stats["num_repartitions"]) == int(scene_run.stats["num_repartitions"])
    ph = jb.simulate(single_phase(s), Q0, v0, T_END, **KW)
    assert ph.result == jb.RESULTS.successful
    theta, omega = reference().sol(np.asarray(ph.t))
    np.testing.assert_allclose(ph.q, cartesian(theta, omega)[0], rtol=0, atol=1e-8)
    stopped = jb.simulate(single_phase(pendulum(repartition=False)), Q0, v0, T_END, throw=False, **KW)
    assert stopped.result == jb.RESULTS.partition_degraded
    # it stops where the run with re-partitioning changed partition first
    assert float(stopped.t_final) == pytest.approx(float(scene_run.repartition_times[0]), abs=1e-12)


@pytest.mark.slow
def test_phase_runner_reports_its_repartitions(scene_run):
    ph = jb.simulate(single_phase(pendulum()), Q0, jnp.array([W0 * L, 0.0]), T_END, **KW)
    assert int(ph.stats["num_repartitions"]) == int(scene_run.stats["num_repartitions"])
    np.testing.assert_allclose(ph.repartition_times, scene_run.repartition_times, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_gradient_through_repartitioned_solve_matches_finite_differences():
    scene = jb.scene(bob_model(), constraints=pendulum())

    def final_x(w):
        return jb.simulate(scene, Q0, jnp.array([w * L, 0.0]), 1.0, n_save=2, rtol=1e-11, atol=1e-11,
                           adjoint="forward").q[-1, 0]

    g = float(jax.jacfwd(final_x)(W0))
    h = 1e-4
    fd = (float(final_x(W0 + h)) - float(final_x(W0 - h))) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-5)
