"""Identification: regressor, base parameters, weighted least squares, trajectory fitting."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxbody as jb
from jaxbody import identify as idf


@pytest.fixture(scope="module")
def panda(models_dir):
    return jb.from_mjcf(models_dir / "panda.xml")


def _pendulum(axis=(0.0, 1.0, 0.0)):
    b = jb.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_body("link", mass=1.3, com=(0.2, 0.05, -0.1), inertia=(0.03, 0.02, 0.04),
               joints=[jb.Hinge(axis=axis)])
    return b.build()


def test_regressor_single_hinge_by_hand():
    # Independent reference: a body hinged about y at the origin, gravity -z. Its CM height
    # is z = -sin(q) c_x + cos(q) c_z, so tau = I_yy(O) a - g (cos q m c_x + sin q m c_z).
    model = _pendulum()
    g = 9.81
    for q, v, a in [(0.3, 1.1, -0.7), (-2.0, 0.0, 0.4)]:
        Y = np.asarray(idf.regressor(model, jnp.array([q]), jnp.array([v]), jnp.array([a])))
        expected = np.zeros(10)
        expected[1] = -g * np.cos(q)
        expected[3] = -g * np.sin(q)
        expected[6] = a
        np.testing.assert_allclose(Y[0], expected, rtol=1e-12, atol=1e-12)


def test_regressor_reproduces_inverse_dynamics_panda(panda):
    extra = ("armature", "damping", "friction")
    friction = jnp.linspace(0.1, 0.7, panda.nv)
    pi = idf.parameters(panda, extra, friction=friction)
    q, v, a = idf.random_states(panda, 4, seed=3)
    for k in range(4):
        Y = idf.regressor(panda, q[k], v[k], a[k], extra)
        assert Y.shape == (panda.nv, 10 * panda.n_body + 3 * panda.nv)
        tau = jb.inverse_dynamics(panda, q[k], v[k], a[k]) + panda.dof_damping * v[k] + friction * np.sign(v[k])
        np.testing.assert_allclose(np.asarray(Y @ pi), np.asarray(tau), rtol=1e-11, atol=1e-11)


def test_parameters_roundtrip_and_pinocchio_order():
    model = _pendulum()
    pi = np.asarray(idf.parameters(model))
    m, c = 1.3, np.array([0.2, 0.05, -0.1])
    Io = np.diag([0.03, 0.02, 0.04]) + m * (c @ c * np.eye(3) - np.outer(c, c))
    expected = [m, *(m * c), Io[0, 0], Io[0, 1], Io[1, 1], Io[0, 2], Io[1, 2], Io[2, 2]]
    np.testing.assert_allclose(pi, expected, rtol=1e-14)
    back = idf.with_parameters(model, pi)
    for f in ("body_mass", "body_com", "body_inertia"):
        np.testing.assert_allclose(np.asarray(getattr(back, f)), np.asarray(getattr(model, f)), atol=1e-15)
    assert idf.parameter_names(model)[:3] == ["m[link]", "mc_x[link]", "mc_y[link]"]


def test_regressor_gradients_match_finite_differences():
    model = _pendulum(axis=(0.3, 1.0, 0.2))
    v, a = jnp.array([0.7]), jnp.array([-0.4])
    check_grads(lambda q: idf.regressor(model, q, v, a), (jnp.array([0.4]),), order=1, modes=("fwd",))
    pi = idf.parameters(model)
    f = lambda p: jnp.sum(jb.inverse_dynamics(idf.with_parameters(model, p), jnp.array([0.4]), v, a) ** 2)
    check_grads(f, (pi,), order=1, modes=("rev",))


def test_regressor_errors():
    model = _pendulum()
    with pytest.raises(ValueError, match="unknown extra regressor column 'stiction'"):
        idf.regressor(model, jnp.zeros(1), jnp.zeros(1), jnp.zeros(1), extra=("stiction",))
    with pytest.raises(ValueError, match=r"parameter vector has shape \(3,\), expected \(10,\)"):
        idf.with_parameters(model, jnp.zeros(3))


def test_log_cholesky_consistency_and_roundtrip():
    model = _pendulum()
    pi = np.asarray(idf.parameters(model))
    theta = idf.log_cholesky(pi)
    np.testing.assert_allclose(np.asarray(idf.from_log_cholesky(jnp.asarray(theta))), pi, rtol=1e-12, atol=1e-15)
    rng = np.random.default_rng(0)
    for _ in range(20):  # every theta is a physically consistent body
        p = idf.from_log_cholesky(jnp.asarray(rng.normal(size=10)))
        jb.validate_parameters(idf.with_parameters(model, p))
    bad = pi.copy()
    bad[4] = -1.0  # I_xx about the origin negative
    with pytest.raises(ValueError, match="body 0: inertial parameters are not physically consistent"):
        idf.log_cholesky(bad)
    check_grads(idf.from_log_cholesky, (jnp.asarray(theta),), order=1, modes=("fwd", "rev"))


@pytest.fixture(scope="module")
def panda_base(panda):
    return idf.base_parameters(panda, n_samples=64, seed=1)


def test_base_parameters_panda_noise_free(panda, panda_base):
    base = panda_base
    assert base.rank == 43  # the 43 base parameters of the Panda's rigid-body model
    pi = np.asarray(idf.parameters(panda))
    q, v, a = idf.random_states(panda, 50, seed=7)
    tau = np.stack([np.asarray(jb.inverse_dynamics(panda, q[k], v[k], a[k]) - panda.dof_armature * a[k])
                    for k in range(50)])
    fit = idf.least_squares(panda, q, v, a, tau, base, noise_std=np.ones(panda.nv))
    true = base.base(pi)
    # relative error per base parameter (combinations that vanish for this robot, |β| below
    # 1e-9 of the largest, are compared on that scale)
    err = np.abs(fit.estimate - true) / np.maximum(np.abs(true), 1e-9 * np.abs(true).max())
    assert err.max() < 1e-8, err.max()
    # the regressor factorises: Y π = Y₁ β at fresh states
    Y = np.asarray(idf.regressor(panda, q[0], v[0], a[0]))
    np.testing.assert_allclose(base.reduce(Y) @ true, Y @ pi, rtol=1e-10, atol=1e-10)
    lines = base.describe()
    assert len(lines) == 43 and lines[0].startswith("beta[0] = ")
    words = base.augmented_identifiability(panda)
    assert words[0] == "link0: fixed to the ground, nothing identifiable"
    assert "static moment m̄_k components x identifiable" in words[2]


def test_weighted_least_squares_standard_errors_are_calibrated(panda, panda_base):
    # Torque noise with known per-joint standard deviations. Over many noise draws the
    # z-scores (estimate - truth) / reported standard error must be standard normal:
    # mean of z² near 1, about 5 % beyond 1.96, none beyond 5.
    base = panda_base
    pi = np.asarray(idf.parameters(panda))
    n = 120
    q, v, a = idf.random_states(panda, n, seed=11)
    Y1 = base.reduce(idf.regression.stacked_regressor(panda, q, v, a, ()))
    tau0 = np.asarray(Y1 @ base.base(pi))
    sigma = np.linspace(0.05, 0.4, panda.nv)
    rng = np.random.default_rng(5)
    z = []
    for _ in range(40):
        tau = tau0 + sigma * rng.normal(size=tau0.shape)
        fit = idf.least_squares(panda, q, v, a, tau, base)  # sigma estimated
        z.append((fit.estimate - base.base(pi)) / fit.standard_error)
    z = np.concatenate(z)
    assert 0.9 < np.mean(z**2) < 1.1
    assert 0.035 < np.mean(np.abs(z) > 1.96) < 0.065
    assert np.abs(z).max() < 5.0
    np.testing.assert_allclose(fit.noise_std, sigma, rtol=0.15)


def test_least_squares_from_noisy_joint_positions_within_standard_errors(panda, panda_base):
    # Encoders give positions only: a 1 kHz excitation of the Panda measured with 1e-4 rad
    # noise, joint torques with 0.05 N m noise. Velocities and accelerations come from a
    # Savitzky-Golay filter; over noise draws the estimates fall within their reported
    # standard errors (z-scores of unit mean square).
    base = panda_base
    beta = base.base(np.asarray(idf.parameters(panda)))
    t = np.arange(0.0, 30.0, 1e-3)
    q, v, a = idf.excitation_trajectory(panda, t, base_frequency=0.2, seed=3)
    rng = np.random.default_rng(0)
    probe = idf.states_from_positions(t, q, window=0.101)
    Y1 = base.reduce(idf.regression.stacked_regressor(panda, q[probe.index], v[probe.index], a[probe.index], ()))
    tau = Y1 @ beta  # the true joint forces at the kept samples
    z = []
    for _ in range(8):
        measured = idf.states_from_positions(t, q + 1e-4 * rng.normal(size=q.shape), window=0.101)
        np.testing.assert_array_equal(measured.index, probe.index)
        fit = idf.least_squares(panda, measured.q, measured.v, measured.a,
                                tau + 0.05 * rng.normal(size=tau.shape), base)
        z.append((fit.estimate - beta) / fit.standard_error)
    z = np.concatenate(z)
    assert 0.7 < np.mean(z**2) < 1.4, np.mean(z**2)
    assert np.abs(z).max() < 5.0
    # the filter itself: from noise-free positions it leaves only the bias of a local quartic
    # on this smooth excitation (measured 2e-8 rad, 7e-5 rad/s, 3e-4 rad/s²)
    np.testing.assert_allclose(probe.q, q[probe.index], atol=1e-7)
    np.testing.assert_allclose(probe.v, v[probe.index], atol=2e-4)
    np.testing.assert_allclose(probe.a, a[probe.index], atol=1e-3)
    assert probe.index[0] == 50 and np.all(np.diff(probe.index) == 101)


def test_states_from_positions_errors():
    t = np.arange(0.0, 1.0, 1e-2)
    q = np.zeros((t.size, 2))
    with pytest.raises(ValueError, match="uniformly spaced"):
        idf.states_from_positions(np.r_[t[:-1], 2.0], q, window=0.1)
    with pytest.raises(ValueError, match="order must be at least 2"):
        idf.states_from_positions(t, q, window=0.1, order=1)
    with pytest.raises(ValueError, match="needs at least 7"):
        idf.states_from_positions(t, q, window=0.03)
    with pytest.raises(ValueError, match="longer than the series"):
        idf.states_from_positions(t, q, window=5.0)
    with pytest.raises(ValueError, match="NaN"):
        idf.states_from_positions(t, np.full_like(q, np.nan), window=0.1)
    with pytest.raises(ValueError, match="stride must be positive"):
        idf.states_from_positions(t, q, window=0.1, stride=0)


def _torque2(t, q, v):
    return jnp.stack([2.0 * jnp.sin(2.0 * t), jnp.cos(3.0 * t)])


@pytest.mark.slow  # about 60 s (L-BFGS); test_fit_double_pendulum_short_horizon_lm is the default-suite fit
def test_fit_double_pendulum_from_perturbed_start():
    system = jb.examples.double_pendulum()
    t = np.linspace(0.0, 1.5, 31)
    sol = jb.simulate(system, jnp.array([0.3, -0.2]), jnp.zeros(2), 1.5, tau=_torque2, saveat=t, rtol=1e-11, atol=1e-11)
    P = idf.Parameterisation(system, {"body_mass": "log", "body_com": "identity"})
    x = P.initial()
    x0 = {"body_mass": x["body_mass"] + jnp.log(jnp.array([1.3, 0.7])),
          "body_com": x["body_com"] * jnp.array([[0.7], [1.3]])}
    res = idf.fit_trajectory(P, x0, t, sol.q, tau=_torque2, v0=jnp.zeros(2), steps=80, tol=1e-20, progress=False)
    assert res.history["loss"][-1] < 1e-14 * res.history["loss"][0]
    np.testing.assert_allclose(np.asarray(res.system.body_mass), [1.0, 0.6], rtol=1e-5)
    np.testing.assert_allclose(np.asarray(res.system.body_com), [[0.4, 0.0], [0.3, 0.0]], atol=1e-5)


def _double_pendulum_data(T, n):
    system = jb.examples.double_pendulum()
    t = np.linspace(0.0, T, n)
    sol = jb.simulate(system, jnp.array([0.3, -0.2]), jnp.zeros(2), T, tau=_torque2, saveat=t, rtol=1e-11, atol=1e-11)
    return system, t, sol


def test_fit_double_pendulum_short_horizon_lm():
    # Default-suite trajectory fit: masses and centres of mass of the double pendulum from a
    # +-30 % start, 11 samples over 1 s, Levenberg-Marquardt through the integrator (14
    # iterations); the truth is the model that made the data (examples.double_pendulum).
    system, t, sol = _double_pendulum_data(1.0, 11)
    P = idf.Parameterisation(system, {"body_mass": "log", "body_com": "identity"})
    x = P.initial()
    x0 = {"body_mass": x["body_mass"] + jnp.log(jnp.array([1.3, 0.7])),
          "body_com": x["body_com"] * jnp.array([[0.7], [1.3]])}
    res = idf.fit_trajectory(P, x0, t, sol.q, sol.v, tau=_torque2, optimizer="levenberg_marquardt", steps=30,
                             tol=1e-24, progress=False)
    assert res.history["loss"][-1] < 1e-14 * res.history["loss"][0]
    assert res.n_iter < 30
    np.testing.assert_allclose(np.asarray(res.system.body_mass), [1.0, 0.6], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(res.system.body_com), [[0.4, 0.0], [0.3, 0.0]], atol=1e-6)


def test_fit_double_pendulum_masses_with_adam_and_progress_bar(capfd):
    # Adam (optax.adam, learning rate 0.1) on the two log-masses, +-30 % start, 6 samples over
    # 0.5 s: a first-order method does not reach the round-off floor of L-BFGS or LM in 100
    # steps, but it lowers the loss by orders of magnitude and lands within a few per cent.
    system, t, sol = _double_pendulum_data(0.5, 6)
    P = idf.Parameterisation(system, {"body_mass": "log"})
    x0 = {"body_mass": P.initial()["body_mass"] + jnp.log(jnp.array([1.3, 0.7]))}
    res = idf.fit_trajectory(P, x0, t, sol.q, sol.v, tau=_torque2, optimizer="adam", learning_rate=0.1,
                             steps=100, progress=True)
    loss = res.history["loss"]
    assert res.n_iter == 100 and loss.shape == (101,)
    assert loss[-1] < 1e-3 * loss[0]
    np.testing.assert_allclose(np.asarray(res.system.body_mass), [1.0, 0.6], rtol=0.03)
    # the progress bar (tqdm, on stderr) counted the steps and showed the loss
    err = capfd.readouterr().err
    assert "fit:" in err and "/100" in err and "loss=" in err


def _torque3(t, q, v):
    return jnp.stack([jnp.sin(1.7 * t), 0.8 * jnp.cos(2.3 * t), 0.4 * jnp.sin(3.1 * t)])


@pytest.mark.slow
def test_fit_three_link_arm_from_perturbed_start():
    system = jb.examples.three_link_manipulator(gravity=9.81)
    t = np.linspace(0.0, 2.0, 41)
    q0 = jnp.array([0.4, 0.2, -0.3])
    sol = jb.simulate(system, q0, jnp.zeros(3), 2.0, tau=_torque3, saveat=t, rtol=1e-11, atol=1e-11)
    P = idf.Parameterisation(system, {"body_mass": "log", "body_com": "identity"})
    x = P.initial()
    x0 = {"body_mass": x["body_mass"] + jnp.log(jnp.array([1.3, 0.7, 1.3])),
          "body_com": x["body_com"] * jnp.array([[0.7], [1.3], [0.7]])}
    res = idf.fit_trajectory(P, x0, t, sol.q, sol.v, tau=_torque3, steps=250, tol=1e-22, progress=False)
    # the augmented quantities (what the motion determines directly) to 1e-5, the raw masses
    # and centres of mass (which separate m_0k a_k from m_0k a_k², a worse-conditioned step) to 1e-3
    fit, true = jb.planar.augmented_bodies_in_body_axes(res.system), jb.planar.augmented_bodies_in_body_axes(system)
    np.testing.assert_allclose(np.asarray(fit.static_moment), np.asarray(true.static_moment), atol=1e-5 * 2.31)
    np.testing.assert_allclose(np.asarray(fit.augmented_inertia), np.asarray(true.augmented_inertia), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(res.system.body_mass), [2.0, 1.5, 0.8], rtol=1e-3)
    np.testing.assert_allclose(np.asarray(res.system.body_com)[:, 0], [0.35, 0.25, 0.15], rtol=1e-3)


def _three_link_data():
    system = jb.examples.three_link_manipulator(gravity=9.81)
    t = np.linspace(0.0, 2.0, 41)
    sol = jb.simulate(system, jnp.array([0.4, 0.2, -0.3]), jnp.zeros(3), 2.0, tau=_torque3, saveat=t, rtol=1e-11,
                      atol=1e-11)
    P = idf.Parameterisation(system, {"body_mass": "log", "body_com": "identity"})
    x = P.initial()
    x0 = {"body_mass": x["body_mass"] + jnp.log(jnp.array([1.3, 0.7, 1.3])),
          "body_com": x["body_com"] * jnp.array([[0.7], [1.3], [0.7]])}
    return system, t, sol, P, x0


def test_fit_multiple_shooting_three_link_arm_converges():
    # Two shooting segments, +-30 % start: Levenberg-Marquardt moves the segment state and the
    # parameters together and reaches the true masses and centres of mass (L-BFGS on the same
    # penalised problem crawls: benchmarks/results/identify.md).
    system, t, sol, P, x0 = _three_link_data()
    res = idf.fit_trajectory(P, x0, t, sol.q, sol.v, tau=_torque3, segments=2, optimizer="levenberg_marquardt",
                             steps=40, tol=1e-22, progress=False)
    np.testing.assert_allclose(np.asarray(res.system.body_mass), [2.0, 1.5, 0.8], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(res.system.body_com)[:, 0], [0.35, 0.25, 0.15], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(res.system.body_com)[:, 1], 0.0, atol=1e-7)
    qs, vs = res.shooting_states
    assert qs.shape == (1, 3) and vs.shape == (1, 3)
    np.testing.assert_allclose(np.asarray(qs[0]), np.asarray(sol.q[20]), atol=1e-7)
    np.testing.assert_allclose(np.asarray(vs[0]), np.asarray(sol.v[20]), atol=1e-7)
    assert res.history["loss"][-1] < 1e-15 * res.history["loss"][0]
    assert res.n_iter < 40 and res.history["loss"].shape == (res.n_iter + 1,)


def _chaotic_double_pendulum(T=8.0, n=161):
    # large swings driven by torques over 8 s: the motion depends sensitively on the parameters
    system = jb.examples.double_pendulum()
    t = np.linspace(0.0, T, n)
    sol = jb.simulate(system, jnp.array([2.0, -1.0]), jnp.zeros(2), T, tau=_torque2, saveat=t, rtol=1e-12,
                      atol=1e-12)
    P = idf.Parameterisation(system, {"body_mass": "log", "body_com": "identity"})
    x = P.initial()
    x0 = {"body_mass": x["body_mass"] + jnp.log(jnp.array([1.3, 0.7])),
          "body_com": x["body_com"] * jnp.array([[0.7], [1.3]])}
    return t, sol, P, x0


def _dp_error(system):
    em = np.abs(np.asarray(system.body_mass) / np.array([1.0, 0.6]) - 1).max()
    ec = np.abs(np.asarray(system.body_com) - np.array([[0.4, 0.0], [0.3, 0.0]])).max() / 0.3
    return max(em, ec)


@pytest.mark.slow  # 17-30 s on 2 cores; the slow job runs it
def test_multiple_shooting_fits_a_chaotic_horizon():
    # 8 segments of 1 s: each stays in the region where the loss is nearly quadratic
    t, sol, P, x0 = _chaotic_double_pendulum()
    res = idf.fit_trajectory(P, x0, t, sol.q, sol.v, tau=_torque2, segments=8, optimizer="levenberg_marquardt",
                             steps=60, tol=1e-22, progress=False)
    assert _dp_error(res.system) < 1e-6
    assert res.history["loss"][-1] < 1e-12 * res.history["loss"][0]


@pytest.mark.slow  # about 60 s: single shooting over the same horizon is stuck in a local minimum
def test_single_shooting_fails_on_the_chaotic_horizon():
    t, sol, P, x0 = _chaotic_double_pendulum()
    for opt, steps in (("levenberg_marquardt", 30), ("lbfgs", 40)):
        res = idf.fit_trajectory(P, x0, t, sol.q, sol.v, tau=_torque2, optimizer=opt, steps=steps, tol=1e-22,
                                 progress=False)
        assert res.history["loss"][-1] > 1.0  # stalled far from zero (the start is about 310)
        assert _dp_error(res.system) > 0.1


@pytest.mark.slow  # 17-30 s on 2 cores; the slow job runs it
def test_fit_link_lengths_with_centres_at_mid_link():
    # Lengths are parameters like any other: a build function ties the centres of mass to the
    # middle of each link (com = L/2), so both lengths enter the motion.
    L_true, m_true = np.array([0.8, 0.6]), np.array([1.0, 0.6])
    system = jb.examples.double_pendulum(mass=m_true, com_distance=L_true / 2, length=L_true)

    def build(x):
        L = jnp.exp(x["log_length"])
        return eqx.tree_at(lambda s: (s.body_mass, s.hinge_pos, s.body_com), system,
                           (jnp.exp(x["log_mass"]), system.hinge_pos.at[1, 0].set(L[0]),
                            system.body_com.at[:, 0].set(L / 2)))

    t = np.linspace(0.0, 1.5, 31)
    sol = jb.simulate(system, jnp.array([0.3, -0.2]), jnp.zeros(2), 1.5, tau=_torque2, saveat=t, rtol=1e-12,
                      atol=1e-12)
    x0 = {"log_length": jnp.log(L_true * np.array([1.3, 0.7])), "log_mass": jnp.log(m_true * np.array([0.7, 1.3]))}
    res = idf.fit_trajectory(build, x0, t, sol.q, sol.v, tau=_torque2, optimizer="levenberg_marquardt", steps=30,
                             tol=1e-22, progress=False)
    np.testing.assert_allclose(np.exp(np.asarray(res.variables["log_length"])), L_true, rtol=1e-6)
    np.testing.assert_allclose(np.exp(np.asarray(res.variables["log_mass"])), m_true, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(res.system.hinge_pos[1]), [0.8, 0.0], rtol=1e-6)

    # gradient of the loss with respect to the lengths against central differences
    @jax.jit
    def loss(logL):
        s = jb.simulate(build({"log_length": logL, "log_mass": jnp.log(jnp.asarray(m_true))}), sol.q[0], sol.v[0],
                        1.5, tau=_torque2, saveat=t, rtol=1e-12, atol=1e-12)
        return jnp.mean((s.q - sol.q) ** 2)

    check_grads(loss, (jnp.log(jnp.array([0.9, 0.5])),), order=1, modes=("rev",), atol=1e-6, rtol=1e-5)


def _disk_case(T=1.0, n=11):
    from jaxbody.examples import disk as dk

    system = dk.rolling_disk(mass=2.0, radius=0.3)
    th, rho = 1.2, 0.3
    q0 = jnp.array([0.0, 0.0, 0.0, th, 0.0])
    x0 = jnp.array([0.4, -0.7, 5.0, -rho * 5.0, -rho * np.sin(th) * 0.4])

    def tau(t, q, x):  # a known spin torque and a push along the line of nodes make the mass visible
        z = jnp.zeros_like(t)
        return jnp.stack([z, z, 0.3 * jnp.sin(2.0 * t), 0.5 * jnp.cos(1.3 * t), z])

    t = np.linspace(0.0, T, n)
    sol = jb.simulate(system, q0, x0, T, tau=tau, saveat=t, rtol=1e-12, atol=1e-12)
    P = idf.Parameterisation(system, {"base.mass": "log", "base.radius": "log"})
    x = P.initial()
    xp = {"base.mass": x["base.mass"] + np.log(1.3), "base.radius": x["base.radius"] + np.log(0.7)}

    def admissible(s, q, x):
        # the measured quasi-velocities roll with the true radius: make them admissible for the
        # current one (kinetic-metric projection onto the rolling constraints)
        return q, jb.maggi.project_velocities(s, q, x)

    return system, t, sol, tau, P, xp, admissible


@pytest.mark.slow  # about 60 s, mostly compiling forward-mode derivatives of the Maggi solve
def test_fit_rolling_disk_radius_and_mass():
    system, t, sol, tau, P, xp, admissible = _disk_case(2.0, 21)
    res = idf.fit_trajectory(P, xp, t, sol.q, sol.v, tau=tau, initial_state=admissible,
                             optimizer="levenberg_marquardt", steps=30, tol=1e-22, progress=False)
    np.testing.assert_allclose(float(res.system.base.mass), 2.0, rtol=1e-6)
    np.testing.assert_allclose(float(res.system.base.radius), 0.3, rtol=1e-6)


@pytest.mark.slow  # 17-30 s on 2 cores; the slow job runs it
def test_rolling_disk_loss_gradient_matches_finite_differences():
    # The disk fit's derivative on its own (both run in the slow job only): the loss and its
    # forward-mode derivative with respect to (log mass, log radius), through the projection
    # and the constrained solve.
    system, t, sol, tau, P, xp, admissible = _disk_case()

    @jax.jit
    def loss(v):
        s = P({"base.mass": v[0], "base.radius": v[1]})
        q0, x0 = admissible(s, sol.q[0], sol.v[0])
        out = jb.simulate(s, q0, x0, t[-1], tau=tau, saveat=t, rtol=1e-12, atol=1e-12, adjoint="forward")
        return jnp.mean((out.q - sol.q) ** 2) + jnp.mean((out.v - sol.v) ** 2)

    v = jnp.array([xp["base.mass"], xp["base.radius"]])
    g = jax.jit(jax.jacfwd(loss))(v)
    h = 1e-6
    fd = np.array([(loss(v.at[i].add(h)) - loss(v.at[i].add(-h))) / (2 * h) for i in range(2)])
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-5)
    assert abs(float(loss(jnp.array([np.log(2.0), np.log(0.3)])))) < 1e-16  # the truth fits


def test_fit_loss_gradient_matches_finite_differences():
    system = jb.examples.double_pendulum()
    t = np.linspace(0.0, 0.5, 6)
    sol = jb.simulate(system, jnp.array([0.3, -0.2]), jnp.zeros(2), 0.5, tau=_torque2, saveat=t)
    P = idf.Parameterisation(system, {"body_mass": "log"})

    def loss(logm):
        s = jb.simulate(P({"body_mass": logm}), jnp.array([0.3, -0.2]), jnp.zeros(2), 0.5, tau=_torque2,
                        saveat=t, rtol=1e-12, atol=1e-12)
        return jnp.mean((s.q - sol.q) ** 2)

    check_grads(loss, (jnp.log(jnp.array([1.2, 0.5])),), order=1, modes=("rev",), atol=1e-6, rtol=1e-5)


def test_fit_errors():
    system = jb.examples.double_pendulum()
    P = idf.Parameterisation(system, {"body_mass": "log"})
    with pytest.raises(ValueError, match="must be divisible by segments = 3"):
        idf.fit_trajectory(P, P.initial(), np.linspace(0, 1, 11), np.zeros((11, 2)), segments=3)
    with pytest.raises(ValueError, match="unknown optimizer 'sgd'"):
        idf.fit_trajectory(P, P.initial(), np.linspace(0, 1, 11), np.zeros((11, 2)), optimizer="sgd")
    with pytest.raises(ValueError, match="lm_damping must be 'identity' or 'marquardt', got 'diag'"):
        idf.fit_trajectory(P, P.initial(), np.linspace(0, 1, 11), np.zeros((11, 2)), optimizer="lm", lm_damping="diag")
    with pytest.raises(ValueError, match="has no field 'mass'"):
        idf.Parameterisation(system, {"mass": "log"})


def _spatial_arm(n_links):
    b = jb.ModelBuilder(gravity=(0, 0, -9.81), name="arm3")
    b.add_body("base", mass=2.0, com=(0.02, 0.01, 0.1), inertia=(0.02, 0.025, 0.01),
               joints=[jb.Hinge(axis=(0, 0, 1), damping=0.3)])
    b.add_body("upper", parent="base", pos=(0, 0, 0.2), mass=1.5, com=(0.25, 0.02, 0.0),
               inertia=(0.004, 0.03, 0.03), joints=[jb.Hinge(axis=(0, 1, 0), damping=0.2)])
    if n_links == 3:
        b.add_body("fore", parent="upper", pos=(0.5, 0, 0), mass=0.8, com=(0.2, 0.0, 0.01),
                   inertia=(0.002, 0.012, 0.012), joints=[jb.Hinge(axis=(0, 1, 0), damping=0.1)])
    return b.build()


def _pd_tracking(n):
    # Closed-loop excitation, as on a real robot: PD control tracks a multi-sine reference and
    # the torques it applies are known. The feedback keeps the arm near the reference whatever
    # the parameters, so the mismatch stays a smooth function of them (an open-loop torque that
    # makes the arm swing over the top gives a rugged landscape).
    def ref(t):
        return jnp.stack([0.8 * jnp.sin(1.3 * t) + 0.3 * jnp.sin(3.7 * t),
                          -0.3 + 0.6 * jnp.sin(2.1 * t) + 0.2 * jnp.cos(4.3 * t),
                          0.5 + 0.8 * jnp.sin(2.9 * t) + 0.3 * jnp.sin(5.1 * t)])[:n]

    def torque(t, q, v):
        qr, vr = jax.jvp(ref, (t,), (jnp.ones_like(t),))
        return 40.0 * (qr - q) + 6.0 * (vr - v)

    return torque


def _fit_spatial(n_links, T, n_t, steps):
    model = _spatial_arm(n_links)
    torque = _pd_tracking(n_links)
    t = np.linspace(0.0, T, n_t)
    sol = jb.simulate(model, jnp.array([0.0, -0.3, 0.5][:n_links]), jnp.zeros(n_links), T, tau=torque, saveat=t,
                      rtol=1e-11, atol=1e-11)
    f = np.array([1.3, 0.7, 1.3])[:n_links]
    pert = eqx.tree_at(lambda m: (m.body_mass, m.body_com, m.body_inertia, m.dof_damping), model,
                       (model.body_mass * f, model.body_com * f[::-1, None], model.body_inertia * f[:, None, None],
                        model.dof_damping * f[::-1]))
    P = idf.InertialParameterisation(model, damping=True)
    res = idf.fit_trajectory(P, P.initial(pert), t, sol.q, sol.v, tau=torque, optimizer="levenberg_marquardt",
                             steps=steps, tol=1e-22, progress=False)
    base = idf.base_parameters(model, extra=("damping",))
    bt = base.base(idf.parameters(model, ("damping",)))
    bf = base.base(idf.parameters(res.system, ("damping",)))
    b0 = base.base(idf.parameters(pert, ("damping",)))
    jb.validate_parameters(res.system)  # physically consistent by construction
    return res, bt, bf, b0


@pytest.mark.slow  # 17-30 s on 2 cores; the slow job runs it
def test_fit_spatial_two_link_arm_log_cholesky_and_damping():
    # log-Cholesky inertias (ten variables per body, fewer identifiable combinations) and
    # damping from +-30 %: the identifiable (base) parameters to 1e-6 of the largest
    res, bt, bf, b0 = _fit_spatial(2, 1.0, 21, 40)
    assert np.abs(b0 - bt).max() > 0.05 * np.abs(bt).max()
    assert np.abs(bf - bt).max() < 1e-6 * np.abs(bt).max()


@pytest.mark.slow  # about 90 s
def test_fit_spatial_arm_log_cholesky_and_damping():
    res, bt, bf, b0 = _fit_spatial(3, 2.0, 41, 60)
    assert np.abs(b0 - bt).max() > 0.1 * np.abs(bt).max()
    assert np.abs(bf - bt).max() < 1e-6 * np.abs(bt).max()
