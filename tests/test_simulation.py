"""Tests of ``jb.simulate`` against closed-form solutions and finite differences."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from _support.jaxpr_tools import count_eqns
from jaxbody.simulation import DynamicalSystem, Solution


class Oscillator(eqx.Module):
    """``m x'' + c x' + k x = tau`` in ``n`` independent coordinates."""

    k: jax.Array
    c: jax.Array
    m: jax.Array
    n: int = eqx.field(static=True, default=1)

    @property
    def nq(self):
        return self.n

    @property
    def nv(self):
        return self.n

    def qdot(self, q, v):
        return v

    def acceleration(self, t, q, v, tau):
        f = -self.k * q - self.c * v
        if tau is not None:
            f = f + tau
        return f / self.m

    def total_energy(self, q, v):
        return 0.5 * self.m * jnp.sum(v * v) + 0.5 * self.k * jnp.sum(q * q)


def oscillator(k=4.0, c=0.0, m=1.0, n=1):
    return Oscillator(jnp.asarray(k), jnp.asarray(c), jnp.asarray(m), n)


def damped_exact(k, c, m, x0, v0, t):
    """Underdamped ``m x'' + c x' + k x = 0``, closed form."""
    zeta_w = c / (2 * m)
    wd = jnp.sqrt(k / m - zeta_w**2)
    return jnp.exp(-zeta_w * t) * (x0 * jnp.cos(wd * t) + (v0 + zeta_w * x0) / wd * jnp.sin(wd * t))


class PlanarPendulum(eqx.Module):
    """``J θ'' = -m g a sin θ`` (θ from the downward vertical)."""

    mass: jax.Array
    arm: jax.Array
    inertia: jax.Array
    g: jax.Array
    nq: int = eqx.field(static=True, default=1)
    nv: int = eqx.field(static=True, default=1)

    def qdot(self, q, v):
        return v

    def acceleration(self, t, q, v, tau):
        return -self.mass * self.g * self.arm * jnp.sin(q) / (self.inertia + self.mass * self.arm**2)

    def total_energy(self, q, v):
        j = self.inertia + self.mass * self.arm**2
        return 0.5 * j * jnp.sum(v * v) - self.mass * self.g * self.arm * jnp.sum(jnp.cos(q))


def test_protocol_is_structural():
    sys_ = oscillator()
    assert isinstance(sys_.nq, int) and sys_.nq == 1
    # Annotating with the protocol is enough; no base class.
    system: DynamicalSystem = sys_
    sol = jb.simulate(system, jnp.array([1.0]), jnp.array([0.0]), 1.0)
    assert isinstance(sol, Solution)
    assert sol.t.shape == (101,) and sol.q.shape == (101, 1) and sol.v.shape == (101, 1)
    assert bool(sol.success)


@pytest.mark.parametrize("solver", ["tsit5", "dopri5", "dopri8"])
def test_harmonic_oscillator_matches_exact_and_error_shrinks_with_rtol(solver):
    k = 4.0
    q0, v0 = jnp.array([0.3]), jnp.array([-1.1])
    errors = []
    for tol in (1e-6, 1e-8, 1e-10):
        sol = jb.simulate(oscillator(k), q0, v0, 5.0, solver=solver, rtol=tol, atol=tol, n_save=51)
        exact = damped_exact(k, 0.0, 1.0, q0[0], v0[0], sol.t)
        err = float(jnp.max(jnp.abs(sol.q[:, 0] - exact)))
        errors.append(err)
        # Global error of a 5 s run with a local tolerance tol: within a small multiple of it.
        # Dopri8 takes very long steps here (27 for 5 s at 1e-10) and overshoots more.
        factor = 1000 if solver == "dopri8" else 100
        assert err < factor * tol, (solver, tol, err)
        assert float(sol.energy_drift) < factor * tol
    assert errors[0] > errors[1] > errors[2], errors
    np.testing.assert_allclose(sol.t, np.linspace(0.0, 5.0, 51), rtol=0, atol=1e-14)
    stats = sol.stats
    assert int(stats["num_accepted_steps"]) > 0
    assert int(stats["num_steps"]) == int(stats["num_accepted_steps"]) + int(stats["num_rejected_steps"])


def test_damped_oscillator_energy_decreases_and_matches_exact():
    k, c = 9.0, 0.4
    q0, v0 = jnp.array([1.0]), jnp.array([0.5])
    sol = jb.simulate(oscillator(k, c), q0, v0, 8.0, rtol=1e-10, atol=1e-10, n_save=201)
    np.testing.assert_allclose(sol.q[:, 0], damped_exact(k, c, 1.0, 1.0, 0.5, sol.t), atol=1e-8)
    de = np.diff(np.asarray(sol.energy))
    assert np.all(de <= 1e-12), de.max()
    # dE/dt = -c v², so the loss over the run is ∫ c v² dt (trapezoid on the saved points).
    loss = c * np.trapezoid(np.asarray(sol.v[:, 0]) ** 2, np.asarray(sol.t))
    np.testing.assert_allclose(float(sol.energy[0] - sol.energy[-1]), loss, rtol=1e-3)
    assert float(sol.energy_drift) > 0.5


def test_constant_and_feedback_tau():
    k = 4.0
    q0, v0 = jnp.array([0.2]), jnp.array([0.0])
    # Constant force F: oscillation about the shifted equilibrium F/k.
    sol = jb.simulate(oscillator(k), q0, v0, 3.0, tau=jnp.array([2.0]), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sol.q[:, 0], 0.5 + (0.2 - 0.5) * jnp.cos(2.0 * sol.t), atol=1e-8)
    # Feedback tau(t, q, v) = -c v reproduces the damped oscillator.
    sol = jb.simulate(oscillator(k), q0, v0, 3.0, tau=lambda t, q, v: -0.3 * v, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sol.q[:, 0], damped_exact(k, 0.3, 1.0, 0.2, 0.0, sol.t), atol=1e-8)


def test_vmap_and_jit_over_initial_states():
    system = oscillator(4.0, n=2)
    key_q, key_v = jax.random.split(jax.random.key(0))
    q0 = jax.random.normal(key_q, (7, 2))
    v0 = jax.random.normal(key_v, (7, 2))

    @jax.jit
    @jax.vmap
    def run(q0, v0):
        return jb.simulate(system, q0, v0, 2.0, n_save=21, rtol=1e-10, atol=1e-10)

    sol = run(q0, v0)
    assert sol.q.shape == (7, 21, 2) and sol.energy.shape == (7, 21) and sol.energy_drift.shape == (7,)
    assert sol.stats["num_accepted_steps"].shape == (7,)
    assert bool(jnp.all(sol.success))
    exact = damped_exact(4.0, 0.0, 1.0, q0[:, None, :], v0[:, None, :], sol.t[:, :, None])
    np.testing.assert_allclose(sol.q, exact, atol=1e-8)
    one = jb.simulate(system, q0[3], v0[3], 2.0, n_save=21, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sol.q[3], one.q, atol=1e-12)


def test_vmapped_batch_survives_a_failed_member_with_throw_false():
    # Stiffness 1e8 needs far more than 200 steps; the soft members finish.
    stiffness = jnp.array([1.0, 1e8, 4.0])

    def run(k):
        return jb.simulate(oscillator(k), jnp.array([1.0]), jnp.array([0.0]), 1.0,
                           max_steps=200, throw=False, n_save=5)

    sol = jax.vmap(run)(stiffness)
    assert sol.success.tolist() == [True, False, True]
    assert (sol.result == jb.RESULTS.max_steps_reached).tolist() == [False, True, False]
    np.testing.assert_allclose(sol.q[2, :, 0], jnp.cos(2.0 * sol.t[2]), atol=1e-6)
    with pytest.raises(Exception, match="maximum number of solver steps"):
        run_throw = lambda k: jb.simulate(oscillator(k), jnp.array([1.0]), jnp.array([0.0]), 1.0, max_steps=200)
        jax.block_until_ready(run_throw(jnp.asarray(1e8)))


def test_grad_matches_finite_differences():
    """d/dθ of a trajectory loss w.r.t. stiffness, damping, mass and initial state."""

    def loss(params):
        k, c, m, x0, v0 = params
        sol = jb.simulate(Oscillator(k, c, m), x0[None], v0[None], 3.0, n_save=31, rtol=1e-12, atol=1e-12)
        return jnp.sum(sol.q[:, 0] ** 2) + sol.v[-1, 0] + sol.energy[-1]

    params = [jnp.asarray(x) for x in (5.0, 0.3, 1.2, 0.7, -0.4)]
    grads = jax.grad(loss)(params)
    h = 1e-5
    for i in range(len(params)):
        plus = [p + h if j == i else p for j, p in enumerate(params)]
        minus = [p - h if j == i else p for j, p in enumerate(params)]
        fd = (loss(plus) - loss(minus)) / (2 * h)
        np.testing.assert_allclose(float(grads[i]), float(fd), rtol=1e-6, atol=1e-8, err_msg=f"param {i}")


def test_grad_matches_closed_form_derivative():
    """Independent reference: the derivative of the exact solution."""

    def x_end(k, x0):
        sol = jb.simulate(oscillator(k), x0[None], jnp.zeros(1), 2.0, n_save=2, rtol=1e-12, atol=1e-12)
        return sol.q[-1, 0]

    k, x0 = jnp.asarray(3.0), jnp.asarray(0.8)
    exact = jax.grad(lambda k, x0: x0 * jnp.cos(jnp.sqrt(k) * 2.0), argnums=(0, 1))(k, x0)
    got = jax.grad(x_end, argnums=(0, 1))(k, x0)
    np.testing.assert_allclose(got, exact, rtol=1e-8)


@pytest.mark.parametrize("solver, order", [("rk4", 4), ("euler", 1)])
def test_fixed_step_convergence_order(solver, order):
    t1 = 2.0
    q0, v0 = jnp.array([1.0]), jnp.array([0.5])
    exact = damped_exact(4.0, 0.0, 1.0, 1.0, 0.5, t1)
    steps = (40, 80, 160, 320) if solver == "rk4" else (400, 800, 1600, 3200)
    errors = []
    for n in steps:
        sol = jb.simulate(oscillator(4.0), q0, v0, t1, solver=solver, dt0=t1 / n, n_save=2)
        assert int(sol.stats["num_steps"]) == n
        errors.append(abs(float(sol.q[-1, 0] - exact)))
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    np.testing.assert_allclose(rates, order, atol=0.15 * order)


def test_explicit_save_times():
    ts = jnp.array([0.0, 0.25, 1.0, 1.5])
    sol = jb.simulate(oscillator(4.0), jnp.array([1.0]), jnp.array([0.0]), 1.5, saveat=ts, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sol.t, ts)
    np.testing.assert_allclose(sol.q[:, 0], jnp.cos(2.0 * ts), atol=1e-9)
    sol = jb.simulate(oscillator(4.0), jnp.array([1.0]), jnp.array([0.0]), 1.5, t0=0.5, n_save=3)
    np.testing.assert_allclose(sol.t, [0.5, 1.0, 1.5])


class NoEnergy(eqx.Module):
    nq: int = eqx.field(static=True, default=1)
    nv: int = eqx.field(static=True, default=1)

    def qdot(self, q, v):
        return v

    def acceleration(self, t, q, v, tau):
        return -q


def test_system_without_energy():
    sol = jb.simulate(NoEnergy(), jnp.array([1.0]), jnp.array([0.0]), 1.0)
    assert sol.energy is None and sol.energy_drift is None and sol.energy_error is None
    np.testing.assert_allclose(sol.q[:, 0], jnp.cos(sol.t), atol=1e-7)


def test_errors():
    system = oscillator()
    q0, v0 = jnp.array([1.0]), jnp.array([0.0])
    with pytest.raises(ValueError, match="unknown solver 'rk45'"):
        jb.simulate(system, q0, v0, 1.0, solver="rk45")
    with pytest.raises(ValueError, match="fixed-step solver 'rk4' needs dt0"):
        jb.simulate(system, q0, v0, 1.0, solver="rk4")
    with pytest.raises(ValueError, match=r"q0 must have shape \(1,\) and v0 \(1,\), got \(2,\)"):
        jb.simulate(system, jnp.zeros(2), v0, 1.0)
    with pytest.raises(ValueError, match=r"tau must have shape \(1,\) or be callable"):
        jb.simulate(system, q0, v0, 1.0, tau=jnp.zeros(3))
    with pytest.raises(ValueError, match="give saveat or n_save, not both"):
        jb.simulate(system, q0, v0, 1.0, saveat=jnp.array([0.0, 1.0]), n_save=3)
    with pytest.raises(ValueError, match="n_save must be at least 2"):
        jb.simulate(system, q0, v0, 1.0, n_save=1)
    with pytest.raises(TypeError, match="str lacks nq, nv, qdot, acceleration"):
        jb.simulate("pendulum", q0, v0, 1.0)


def test_spatial_model_pendulum_matches_planar_equation():
    m, a, iyy, g = 1.3, 0.4, 0.02, 9.81
    b = jb.ModelBuilder(gravity=np.array([0.0, 0.0, -g]))
    b.add_body("link", mass=m, com=np.array([0.0, 0.0, -a]), inertia=np.array([0.03, iyy, 0.01]),
               joints=[jb.Hinge(axis=np.array([0.0, 1.0, 0.0]))])
    model = b.build()
    planar = PlanarPendulum(*(jnp.asarray(x) for x in (m, a, iyy, g)))
    q0, v0 = jnp.array([1.2]), jnp.array([-0.7])
    kw = dict(n_save=41, rtol=1e-11, atol=1e-11)
    got = jb.simulate(model, q0, v0, 2.0, **kw)
    ref = jb.simulate(planar, q0, v0, 2.0, **kw)
    np.testing.assert_allclose(got.q, ref.q, atol=1e-8)
    np.testing.assert_allclose(got.energy - got.energy[0], ref.energy - ref.energy[0], atol=1e-9)
    assert float(got.energy_drift) < 1e-9


def test_spatial_model_ball_joint_conserves_energy_and_quaternion_norm():
    b = jb.ModelBuilder(gravity=np.array([0.0, 0.0, -9.81]))
    b.add_body("top", mass=2.0, com=np.array([0.0, 0.0, 0.3]), inertia=np.array([0.05, 0.04, 0.02]),
               joints=[jb.Ball()])
    model = b.build()
    q0 = jnp.array([np.cos(0.2), np.sin(0.2), 0.0, 0.0])
    v0 = jnp.array([0.1, 0.3, 12.0])
    sol = jb.simulate(model, q0, v0, 1.0, n_save=11, rtol=1e-10, atol=1e-10)
    assert float(sol.energy_drift) < 1e-8
    np.testing.assert_allclose(jnp.linalg.norm(sol.q, axis=-1), 1.0, atol=1e-8)


def test_example_double_pendulum_conserves_energy():
    system = jb.examples.double_pendulum()
    assert (system.nq, system.nv) == (2, 2)
    sol = jb.simulate(system, jnp.array([1.0, -0.5]), jnp.zeros(2), 1.0, rtol=1e-10, atol=1e-10)
    assert bool(sol.success)
    assert float(sol.energy_drift) < 1e-8


def test_example_double_pendulum_matches_scipy_on_eq15():
    """Independent reference: eq. (15) written out here, integrated by SciPy's DOP853."""
    from scipy.integrate import solve_ivp

    m1, m2, a1, a2, l1, ic1, ic2, g = 1.0, 0.6, 0.4, 0.3, 0.8, 0.05, 0.02, 9.81
    md1, md2 = m1 * a1 + m2 * l1, m2 * a2
    j1, j2 = ic1 + m1 * a1**2 + m2 * l1**2, ic2 + m2 * a2**2

    def rhs(t, y):
        x1, x2, w1, w2 = y
        c, s = np.cos(x2 - x1), np.sin(x2 - x1)
        mass = np.array([[j1, l1 * md2 * c], [md2 * l1 * c, j2]])
        force = np.array([l1 * md2 * s * w2**2 - md1 * g * np.sin(x1), -md2 * l1 * s * w1**2 - md2 * g * np.sin(x2)])
        return np.concatenate([[w1, w2], np.linalg.solve(mass, force)])

    system = jb.examples.double_pendulum(
        mass=np.array([m1, m2]), com_distance=np.array([a1, a2]), length=np.array([l1, l1]),
        inertia=np.array([ic1, ic2]), gravity=g,
    )
    y0 = np.array([1.0, -0.5, 0.3, 0.0])
    ts = np.linspace(0.0, 2.0, 21)
    ref = solve_ivp(rhs, (0.0, 2.0), y0, method="DOP853", t_eval=ts, rtol=1e-12, atol=1e-12)
    sol = jb.simulate(system, jnp.asarray(y0[:2]), jnp.asarray(y0[2:]), 2.0, n_save=21, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(sol.q, ref.y[:2].T, atol=1e-8)
    np.testing.assert_allclose(sol.v, ref.y[2:].T, atol=1e-8)



def test_batched_energy_error():
    def run(q0):
        return jb.simulate(oscillator(), q0, jnp.zeros(1), 1.0, n_save=11)

    sol = jax.vmap(run)(jnp.array([[0.5], [1.0]]))
    err = sol.energy_error
    assert err.shape == (2, 11)
    np.testing.assert_allclose(jnp.max(jnp.abs(err), axis=-1), sol.energy_drift)
    np.testing.assert_allclose(err[:, 0], 0.0)


def test_constant_steps_bound_the_budget_and_the_checkpoints():
    """A constant-step solve over a known span gets a step budget of the steps it can take (the
    checkpointed adjoint then stores one checkpoint a step instead of planning for the whole
    default budget); the solution is unchanged, float32 time with its rounding included, and
    the gradient is the same as under the user's budget."""
    from jaxbody.simulation.adjoint import default_checkpoints, step_bound as _step_bound

    # the memory budget holds one checkpoint a step for 1000 steps of a 20-link chain (40 states)
    assert default_checkpoints(1016, 40) == 1016
    assert default_checkpoints(10**6, 14) == (1 << 20) // (3 * 14 * 8)
    const = diffrax.ConstantStepSize()
    assert 1001 <= _step_bound(const, 0.0, 1.0, 1e-3, 100_000, jnp.float64) <= 1004
    assert _step_bound(const, 0.0, 1.0, 1e-3, 500, jnp.float64) == 500  # the user's smaller budget
    assert _step_bound(diffrax.PIDController(rtol=1e-6, atol=1e-6), 0.0, 1.0, 1e-3, 100_000, jnp.float64) == 100_000
    # float32 time: 100,000 steps of 1e-4 up to t = 10 may drift by a few hundred steps
    bound32 = _step_bound(const, 0.0, 10.0, 1e-4, None, jnp.float32)
    assert 100_002 < bound32 < 200_000
    q0, v0 = jnp.array([1.0, 0.2]), jnp.array([0.5, -0.3])
    sol32 = jb.simulate(oscillator(4.0, n=2), q0.astype(jnp.float32), v0.astype(jnp.float32), 10.0, solver="rk4",
                        dt0=1e-4, saveat=diffrax.SaveAt(t1=True))
    assert bool(sol32.success) and int(sol32.stats["num_steps"]) <= bound32
    assert abs(float(sol32.t_final) - 10.0) < 1e-5

    def loss(q0, max_steps):
        sol = jb.simulate(oscillator(4.0, c=0.3, n=2), q0, v0, 1.0, solver="rk4", dt0=1e-2,
                          saveat=diffrax.SaveAt(t1=True), max_steps=max_steps)
        return jnp.sum(sol.q[-1] ** 2) + jnp.sum(sol.v[-1] ** 2), sol.stats["num_steps"]

    (l_default, n_default), g_default = jax.value_and_grad(loss, has_aux=True)(q0, 100_000)
    (l_tight, n_tight), g_tight = jax.value_and_grad(loss, has_aux=True)(q0, 101)
    assert int(n_default) == int(n_tight) == 100
    np.testing.assert_allclose(l_default, l_tight, rtol=1e-14)
    np.testing.assert_allclose(g_default, g_tight, rtol=1e-12)


def _callbacks(jaxpr) -> int:
    return count_eqns(jaxpr, lambda e: "callback" in e.primitive.name)


def test_the_compiled_solve_has_no_host_callback_and_the_checks_stay_outside():
    """JAX's persistent cache stores no program with a host callback: the solve's program has
    none (diffrax's checks of the save times and of the step's sign are made by jaxbody before
    it), so a second process loads it from the cache. Under the user's ``jit`` the checks are
    still in the user's program, outside the solve, and a user's own diffrax solve keeps them."""
    system, q0, v0 = oscillator(4.0), jnp.array([1.0]), jnp.array([0.0])

    def run(t1):
        return jb.simulate(system, q0, v0, t1, solver="rk4", dt0=0.05, saveat=jnp.array([0.0, 0.5]) * t1).q

    jaxpr = jax.make_jaxpr(run)(1.0).jaxpr
    # the solve and the quantities at its saved states: two programs, neither with a callback
    solves = [e for e in jaxpr.eqns if e.params.get("name") in ("_integrate", "_saved_quantities")]
    assert sorted(e.params["name"] for e in solves) == ["_integrate", "_saved_quantities"]
    assert all(_callbacks(e.params["jaxpr"].jaxpr) == 0 for e in solves)
    assert _callbacks(jaxpr) > 0  # the traced boundary checks and the failure report, outside
    with pytest.raises(Exception, match=r"t1 must not be before t0"):
        jax.block_until_ready(jax.jit(run)(-1.0))
    with pytest.raises(Exception, match="saveat.ts must be increasing or decreasing"):
        diffrax.diffeqsolve(diffrax.ODETerm(lambda t, y, args: -y), diffrax.Tsit5(), 0.0, 1.0, 0.1, jnp.array(1.0),
                            saveat=diffrax.SaveAt(ts=jnp.array([0.5, 0.2])))


def test_default_save_times_are_spaced_on_the_host_when_concrete():
    # concrete bounds: NumPy's spacing, both ends exact, and no JAX operation (each would be a
    # program compiled on a process's first call); traced bounds: the same times in the program
    from jaxbody.simulation.checks import save_times

    def count_compiles(fn):
        compiled = []
        jax.monitoring.register_event_duration_secs_listener(
            lambda name, secs, **_: compiled.append(name) if name == "/jax/core/compile/backend_compile_duration" else None)
        out = fn()
        return out, len(compiled)

    # a count of steps no other test asks for: JAX's own in-memory caches cannot hide a compile
    n = 37
    ts, compiles = count_compiles(lambda: save_times(jnp.asarray(0.3), jnp.asarray(2.1), n, np.float64))
    assert compiles == 0
    np.testing.assert_array_equal(np.asarray(ts), np.linspace(0.3, 2.1, n))
    assert ts.dtype == jnp.float64 and float(ts[0]) == 0.3 and float(ts[-1]) == 2.1
    traced = jax.jit(lambda a, b: save_times(a, b, n, np.float64))(0.3, 2.1)
    np.testing.assert_allclose(np.asarray(traced), np.linspace(0.3, 2.1, n), rtol=0, atol=1e-15)
    assert len(save_times(0.0, 1.0, None, np.float32)) == 101
