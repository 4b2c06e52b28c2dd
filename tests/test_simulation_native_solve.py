"""A whole fixed-step RK4 solve in one native call, and its native reverse sweep.

``jb.simulate(..., solver="rk4", dt0=...)`` on the native kernel, saving the end state and/or
requested times, runs the solve as one call (``jaxbody.backends.native.rk4_rollout``): every
field of the solution must equal the step-by-step solve through diffrax
(``$JAXBODY_NATIVE_SOLVE=0``; the saved states from each step's cubic Hermite dense output) and
the vectorised kernel, including each trajectory's own outcome in a batch (invalid input, a
non-finite step, the step budget). Gradients with respect to the initial state come from the
native reverse sweep (``jaxbody.backends.native.rk4_rollout_vjp``, the saved states' cotangents
through the dense output, with recomputed segments when the checkpoints do not hold every step);
every other gradient through the step-by-step solve.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxbody as jb
from jaxbody.backends import native
from jaxbody.simulation import adjoint as simulation  # default_checkpoints reads its memory budget there

pytestmark = pytest.mark.filterwarnings("ignore:from_mjcf")


@pytest.fixture(autouse=True)
def _fresh_traces():
    """The tests count native calls while a solve is traced: no compiled program carried over."""
    jax.clear_caches()
    yield


def _models():
    from _support.random_models import hinge_chain, random_model

    chain = hinge_chain(3)
    chain = eqx.tree_at(lambda m: (m.joint_stiffness, m.dof_damping), chain,
                        (jnp.full(chain.joints.n_joint, 2.0), jnp.full(chain.nv, 0.3)))
    tree = random_model(0, n_body=2, kinds=("ball",))  # a free base and a ball joint: 9 DoFs
    tree = eqx.tree_at(lambda m: m.dof_damping, tree, jnp.full(tree.nv, 0.2))
    return {"chain": chain, "free_ball": tree}


def _state(model, seed=0):
    rng = np.random.default_rng(seed)
    q = jb.normalize_qpos(model, jnp.asarray(model.qpos0) + 0.3 * rng.standard_normal(model.nq))
    return q, jnp.asarray(rng.standard_normal(model.nv))


def _solve(scene, q0, v0, t1=0.2, saveat=diffrax.SaveAt(t1=True), **kw):
    return jb.simulate(scene, q0, v0, t1, solver="rk4", dt0=1e-2, saveat=saveat, **kw)


# save times of a solve over [0, 0.2] in steps of 0.01: t0, inside a step, a step's end (saved in
# the step it ends, from its dense output at θ = 1), a step's end and a time just before it, t1
_TS = jnp.array([0.0, 0.004, 0.01, 0.01, 0.0999, 0.1, 0.137, 0.2])
_SAVES = diffrax.SaveAt(ts=_TS, t1=True)


def _leaves_close(a, b, tol):
    la, ta = jax.tree.flatten(a)
    lb, tb = jax.tree.flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape and x.dtype == y.dtype, (x, y)
        if np.issubdtype(x.dtype, np.inexact):
            assert np.array_equal(np.isfinite(x), np.isfinite(y)), (x, y)
            finite = np.isfinite(x)
            scale = max(1.0, float(np.max(np.abs(y[finite]), initial=0.0)))
            assert float(np.max(np.abs(x[finite] - y[finite]), initial=0.0)) <= tol * scale, (x, y)
        else:
            assert np.array_equal(x, y), (x, y)


def _stepped(monkeypatch):
    monkeypatch.setenv("JAXBODY_NATIVE_SOLVE", "0")


@pytest.mark.parametrize("name", ["chain", "free_ball"])
def test_native_solve_equals_the_stepped_solve(name, monkeypatch):
    """Gravity, springs and dampers (with their work), saving at requested times and the end:
    the one-call solve equals diffrax's step-by-step solve on the same kernel (every field of
    the solution; the saved states from each step's dense output, at t0, inside steps, at their
    ends, and, on the free base, the quaternions before their renormalisation as diffrax
    interpolates them) and the vectorised kernel; inside the jitted program there is no loop
    left, only the native call."""
    model = _models()[name]
    calls = []
    rollout = native.rk4_rollout
    monkeypatch.setattr(native, "rk4_rollout", lambda *a, **kw: calls.append(1) or rollout(*a, **kw))
    fast = jb.scene(model, kernel="native", planar=False)
    q0, v0 = _state(model)
    a = _solve(fast, q0, v0, saveat=_SAVES)
    assert calls, "simulate did not take the native solve"
    assert int(a.stats["num_steps"]) == 20 and a.work["dampers"][-1] < 0
    assert a.q.shape[0] == _TS.size + 1 and bool(jnp.all(a.t[:-1] == _TS))
    jaxpr = jax.make_jaxpr(lambda q, v: _solve(fast, q, v, saveat=_SAVES, throw=False).q)(q0, v0)
    assert "while" not in str(jaxpr)
    with pytest.raises(Exception, match="t1 must not be before t0"):  # traced: diffrax raises too
        jax.block_until_ready(jax.jit(lambda t1: _solve(fast, q0, v0, t1, throw=False).q)(jnp.asarray(-0.1)))

    _stepped(monkeypatch)
    calls.clear()
    b = _solve(fast, q0, v0, saveat=_SAVES)
    assert not calls
    _leaves_close(a, b, 1e-13)
    c = _solve(jb.scene(model, kernel="vectorised", planar=False), q0, v0, saveat=_SAVES)
    _leaves_close((a.q, a.v, a.work, a.t), (c.q, c.v, c.work, c.t), 1e-10)


def test_native_solve_batch_outcomes_equal_the_stepped_solve(monkeypatch):
    """A vmap batch, each member with its own end time and save times (from t0 to its t1),
    ``throw=False``: an invalid input (NaN: frozen, its saves its state), a member whose steps
    overflow (non-finite: no saves after that step), members the step budget stops (no saves
    after it), and members that finish: result codes, times, saved and final states and step
    counts as the step-by-step solve gives them, in one native call."""
    model = _models()["free_ball"]
    scene = jb.scene(model, kernel="native", planar=False)
    q0, v0 = _state(model)
    rng = np.random.default_rng(1)
    vs = jnp.asarray(rng.standard_normal((9, model.nv)))
    vs = vs.at[2, 0].set(jnp.nan).at[4].multiply(1e150)
    qs = jnp.tile(q0, (9, 1))
    t1s = jnp.linspace(0.05, 0.4, 9)

    def run():
        def one(q, v, t1):
            return _solve(scene, q, v, t1, saveat=jnp.linspace(0.0, 1.0, 6) * t1, throw=False, max_steps=30)

        return jax.jit(jax.vmap(one))(qs, vs, t1s)

    calls = []
    rollout = native.rk4_rollout
    monkeypatch.setattr(native, "rk4_rollout", lambda *a, **kw: calls.append(1) or rollout(*a, **kw))
    a = run()
    assert len(calls) == 1, "the batch did not run as one native call"
    _stepped(monkeypatch)
    b = run()
    codes = a.result._value.tolist()
    R = jb.RESULTS
    assert codes[2] == int(R.invalid_input._value) and codes[4] == int(R.nonfinite._value)
    assert codes[0] == int(R.successful._value) and codes[-1] == int(R.max_steps_reached._value)
    assert bool(jnp.all(jnp.isinf(a.t[-1, -2:]))) and bool(jnp.all(jnp.isfinite(a.q[-1, :-2])))
    _leaves_close(a, b, 1e-13)


def _gradient_setup(name, monkeypatch, saveat=diffrax.SaveAt(t1=True)):
    model = _models()[name]
    scene = jb.scene(model, kernel="native", planar=False)
    q0, v0 = _state(model, 2)

    def loss(q, v):
        # every saved state weighted by its own factor (the end state, the last, the most)
        sol = _solve(scene, q, v, saveat=saveat)
        weights = jnp.arange(1.0, sol.q.shape[0] + 1)
        return (jnp.sum(weights[:, None] * jnp.sin(sol.q)) + jnp.sum(weights[:, None] * sol.v ** 2)
                + 3.0 * jnp.sum(weights * sol.work["dampers"]))

    calls = []
    sweep = native.rk4_rollout_vjp
    monkeypatch.setattr(native, "rk4_rollout_vjp", lambda *a, **kw: calls.append(1) or sweep(*a, **kw))
    return model, loss, q0, v0, calls


@pytest.mark.slow  # 11-12 s; the sweep's gradients are checked by default against central differences (next test)
def test_native_reverse_sweep_gradient_equals_the_stepped_solve(monkeypatch):
    """The gradient with respect to (q0, v0) of the states saved at requested times (through each
    step's dense output) and at the end, with the dampers' work, through the native reverse
    sweep, equals the step-by-step solve's checkpointed adjoint, with a checkpoint per step and
    with segments recomputed from fewer checkpoints (saves on both sides of a segment's start);
    batched under vmap too."""
    model, loss, q0, v0, calls = _gradient_setup("chain", monkeypatch, _SAVES)
    grad = lambda: jax.jit(jax.grad(loss, argnums=(0, 1)))(q0, v0)  # noqa: E731
    every_step = grad()
    assert calls, "the gradient did not take the native reverse sweep"
    # three checkpoints for 20 steps: segments of 8 steps recomputed
    monkeypatch.setattr(simulation, "CHECKPOINT_BYTES", 3 * 3 * (model.nq + model.nv) * 8)
    assert simulation.default_checkpoints(22, model.nq + model.nv) < 20
    segments = grad()
    batched = jax.jit(jax.vmap(jax.grad(loss, argnums=(0, 1))))(jnp.stack([q0, q0]), jnp.stack([v0, -v0]))
    _stepped(monkeypatch)
    calls.clear()
    reference = grad()
    assert not calls
    assert float(jnp.max(jnp.abs(reference[1]))) > 1e-3
    _leaves_close(every_step, reference, 1e-10)
    _leaves_close(segments, reference, 1e-10)
    _leaves_close(tuple(x[1] for x in batched), jax.jit(jax.grad(loss, argnums=(0, 1)))(q0, -v0), 1e-10)


def test_native_reverse_sweep_gradient_of_a_free_base_against_finite_differences(monkeypatch):
    """The free base with a ball joint (the quaternions' renormalisation after each step, in the
    sweep too): the gradient with respect to (q0, v0) against central differences of the
    native solve itself, along every coordinate."""
    model, loss, q0, v0, calls = _gradient_setup("free_ball", monkeypatch)
    gq, gv = jax.jit(jax.grad(loss, argnums=(0, 1)))(q0, v0)
    assert calls, "the gradient did not take the native reverse sweep"
    x0 = jnp.concatenate([q0, v0])
    eps = 1e-6
    shifts = eps * jnp.concatenate([jnp.eye(x0.size), -jnp.eye(x0.size)])
    values = jax.jit(jax.vmap(lambda d: loss((x0 + d)[: model.nq], (x0 + d)[model.nq :])))(shifts)
    fd = (values[: x0.size] - values[x0.size :]) / (2 * eps)
    g = jnp.concatenate([gq, gv])
    assert float(jnp.max(jnp.abs(g))) > 1e-2
    assert float(jnp.max(jnp.abs(g - fd))) <= 1e-6 * max(1.0, float(jnp.max(jnp.abs(fd)))), (g, fd)
    # and JAX's own check of the reverse mode along random directions
    check_grads(loss, (q0, v0), order=1, modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-6)


@pytest.mark.slow  # about 10 s alone, 30 s in the parallel suite: the step-by-step gradient's compilation
def test_native_solve_parameter_gradient_goes_step_by_step(monkeypatch):
    """A gradient with respect to the model's parameters comes from the step-by-step solve
    (not the native sweep), checked against central differences of the native solve along
    every body mass. (Forward mode, ``adjoint=ForwardMode()``, never takes the native solve:
    test_backends_native_step.py's rollout gradient.)"""
    model = _models()["chain"]
    q0, v0 = _state(model, 3)
    calls = []
    sweep = native.rk4_rollout_vjp
    monkeypatch.setattr(native, "rk4_rollout_vjp", lambda *a, **kw: calls.append(1) or sweep(*a, **kw))

    def loss(mass):
        # saved times and the end state: diffrax's loop returns the end state among the saved
        # rows, the native solve as a row of its own (the forward pass gives the native layout)
        m = eqx.tree_at(lambda m: m.body_mass, model, mass)
        sol = _solve(jb.scene(m, kernel="native", planar=False), q0, v0, saveat=_SAVES)
        return jnp.sum(sol.q ** 2) + jnp.sum(sol.v ** 2) + jnp.sum(sol.v_final)

    mass = model.body_mass
    g = jax.jit(jax.grad(loss))(mass)
    assert not calls
    eps = 1e-6
    shifts = eps * jnp.concatenate([jnp.eye(mass.size), -jnp.eye(mass.size)])
    values = jax.jit(jax.vmap(lambda d: loss(mass + d)))(shifts)
    fd = (values[: mass.size] - values[mass.size :]) / (2 * eps)
    assert float(jnp.max(jnp.abs(g))) > 1e-4
    assert float(jnp.max(jnp.abs(g - fd))) <= 1e-6 * max(1.0, float(jnp.max(jnp.abs(fd)))), (g, fd)


def test_native_solve_in_float32_stays_near_float64():
    """The one-call solve in float32 (a float32 model and state), saving at ``simulate``'s
    default evenly spaced times, stays within 1e-4 of float64."""
    model = _models()["free_ball"]
    q0, v0 = _state(model, 4)
    m32 = jax.tree.map(lambda x: x.astype(jnp.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x, model)

    def run(scene, q, v):
        return jb.simulate(scene, q, v, 0.2, solver="rk4", dt0=1e-2, n_save=9)

    a = run(jb.scene(model, kernel="native", planar=False), q0, v0)
    b = run(jb.scene(m32, kernel="native", planar=False), q0.astype(jnp.float32), v0.astype(jnp.float32))
    assert b.q.dtype == jnp.float32 and bool(b.success) and b.q.shape == (9, model.nq)
    assert float(jnp.max(jnp.abs(b.q.astype(jnp.float64) - a.q))) <= 1e-4
    assert float(jnp.max(jnp.abs(b.v.astype(jnp.float64) - a.v))) <= 1e-4 * max(1.0, float(jnp.max(jnp.abs(a.v))))


# ----------------------------------------------------------------------------- adaptive solves
def _adaptive(scene, q0, v0, method, t1=0.3, **kw):
    return jb.simulate(scene, q0, v0, t1, solver=method, rtol=1e-8, atol=1e-8, **kw)


@pytest.mark.parametrize("method,name", [pytest.param("tsit5", "chain", marks=pytest.mark.slow), ("dopri5", "free_ball"),
                                         pytest.param("dopri8", "chain", marks=pytest.mark.slow)])
def test_adaptive_native_solve_equals_the_stepped_solve(method, name, monkeypatch):
    """An embedded pair under PID control on the native kernel, saving at the default 101 times
    (dense output) and at the end: one native call, the same accepted and rejected steps as
    diffrax's loop and every field of the solution equal to it (springs, dampers and their work;
    a free base and a ball joint's quaternions)."""
    model = _models()[name]
    calls = []
    solve = native.adaptive_solve
    monkeypatch.setattr(native, "adaptive_solve", lambda *a, **kw: calls.append(1) or solve(*a, **kw))
    scene = jb.scene(model, kernel="native", planar=False)
    q0, v0 = _state(model)
    a = _adaptive(scene, q0, v0, method)
    assert calls, "simulate did not take the native adaptive solve"
    assert a.q.shape[0] == 101
    _stepped(monkeypatch)
    calls.clear()
    b = _adaptive(scene, q0, v0, method)
    assert not calls
    for key in ("num_steps", "num_accepted_steps", "num_rejected_steps"):
        assert int(a.stats[key]) == int(b.stats[key]), key
    _leaves_close(a, b, 1e-10)


@pytest.mark.default_optimisation  # the native and XLA programs round alike only with their fused multiply-adds
def test_adaptive_native_batch_members_keep_their_own_outcome(monkeypatch):
    """A vmap batch of one native call, ``throw=False``: an invalid input (NaN), a member whose
    step budget runs out, members with their own end times: each member equals its own
    unbatched solve and the batch equals diffrax's loop (result codes, step counts, states)."""
    model = _models()["chain"]
    scene = jb.scene(model, kernel="native", planar=False)
    q0, v0 = _state(model)
    rng = np.random.default_rng(1)
    vs = jnp.asarray(rng.standard_normal((5, model.nv))).at[2, 0].set(jnp.nan).at[4].multiply(40.0)
    qs = jnp.tile(q0, (5, 1))
    t1s = jnp.linspace(0.1, 0.4, 5)

    def one(q, v, t1):
        return _adaptive(scene, q, v, "dopri5", t1, throw=False, max_steps=40, saveat=diffrax.SaveAt(t1=True))

    a = jax.jit(jax.vmap(one))(qs, vs, t1s)
    R = jb.RESULTS
    codes = a.result._value.tolist()
    assert codes[2] == int(R.invalid_input._value) and codes[4] == int(R.max_steps_reached._value)
    assert codes[0] == int(R.successful._value)
    single = jax.jit(one)
    for i in (0, 3, 4):
        _leaves_close(jax.tree.map(lambda x: x[i], a), single(qs[i], vs[i], t1s[i]), 0.0)
    _stepped(monkeypatch)
    _leaves_close(a, jax.jit(jax.vmap(one))(qs, vs, t1s), 1e-10)


def test_adaptive_native_gradient_against_finite_differences(monkeypatch):
    """The gradient of an adaptive solve's saved states (dense output inside the steps) and end
    state with respect to (q0, v0) by the native reverse sweep (accepted steps replayed from
    checkpoints; the interpolant, the quaternions' renormalisation and the first-same-as-last
    stage reversed) against central differences of the native solve."""
    model = _models()["free_ball"]
    scene = jb.scene(model, kernel="native", planar=False)
    q0, v0 = _state(model, 2)
    calls = []
    sweep = native.adaptive_solve_vjp
    monkeypatch.setattr(native, "adaptive_solve_vjp", lambda *a, **kw: calls.append(1) or sweep(*a, **kw))

    def loss(q, v):
        # saved times inside the steps (their dense output reversed) and the end state
        sol = _adaptive(scene, q, v, "tsit5", 0.2, saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, 0.2, 6), t1=True),
                        max_steps=200)
        weights = jnp.arange(1.0, sol.q.shape[0] + 1)[:, None]
        return jnp.sum(weights * jnp.sin(sol.q)) + jnp.sum(sol.v_final ** 2) + 3.0 * jnp.sum(sol.work["dampers"])

    gq, gv = jax.jit(jax.grad(loss, argnums=(0, 1)))(q0, v0)
    assert calls, "the gradient did not take the native reverse sweep"
    x0 = jnp.concatenate([q0, v0])
    eps = 1e-6
    shifts = eps * jnp.concatenate([jnp.eye(x0.size), -jnp.eye(x0.size)])
    values = jax.jit(jax.vmap(lambda d: loss((x0 + d)[: model.nq], (x0 + d)[model.nq :])))(shifts)
    fd = (values[: x0.size] - values[x0.size :]) / (2 * eps)
    g = jnp.concatenate([gq, gv])
    assert float(jnp.max(jnp.abs(g))) > 1e-2
    # the step sizes are held in the gradient (as diffrax holds them): differences see them move
    assert float(jnp.max(jnp.abs(g - fd))) <= 1e-5 * max(1.0, float(jnp.max(jnp.abs(fd)))), (g, fd)


def _tangent_to_quaternions(model, q, g_q):
    """``g_q`` less its component along each unit quaternion of ``q``. A solve keeps quaternions
    on the unit sphere, so that component says how a start off the sphere would be treated, not
    how the trajectory depends on the state; the native sweep and diffrax's adjoint differentiate
    the renormalisation differently there (measured on the free base and ball joint: 1e-4 along
    the quaternions, 1e-8 across them)."""
    g_q, q = np.asarray(g_q).copy(), np.asarray(q)
    start = 0
    for kind in model.joints.type:
        quaternion = {jb.joints.FREE: slice(start + 3, start + 7), jb.joints.BALL: slice(start, start + 4)}.get(kind)
        if quaternion is not None:
            p = q[quaternion] / np.linalg.norm(q[quaternion])
            g_q[quaternion] -= (g_q[quaternion] @ p) * p
        start += jb.joints.JOINT_NQ[kind]
    return g_q


@pytest.mark.slow  # the step-by-step gradient's compilation
@pytest.mark.parametrize("name", ["chain", "free_ball"])
def test_adaptive_native_gradient_equals_the_stepped_solve(name, monkeypatch):
    """The native reverse sweep of an adaptive solve equals diffrax's checkpointed adjoint of the
    same steps, with a checkpoint per accepted step and with segments replayed; the end state
    (a free base), the states saved at requested times (a chain)."""
    model = _models()[name]
    scene = jb.scene(model, kernel="native", planar=False)
    q0, v0 = _state(model, 2)

    saveat = diffrax.SaveAt(t1=True) if name == "free_ball" else diffrax.SaveAt(ts=jnp.linspace(0.0, 0.3, 7))

    def loss(q, v):
        sol = _adaptive(scene, q, v, "dopri8", 0.3, saveat=saveat, max_steps=100)
        weights = jnp.arange(1.0, sol.q.shape[0] + 1)[:, None]
        return jnp.sum(weights * jnp.sin(sol.q)) + jnp.sum(sol.v_final ** 2) + 3.0 * jnp.sum(sol.work["dampers"])

    def grad():
        g_q, g_v = jax.jit(jax.grad(loss, argnums=(0, 1)))(q0, v0)
        return _tangent_to_quaternions(model, q0, g_q), g_v

    every_step = grad()
    monkeypatch.setattr(simulation, "CHECKPOINT_BYTES", 3 * 3 * (model.nq + model.nv) * 8)
    segments = grad()
    _stepped(monkeypatch)
    reference = grad()
    _leaves_close(every_step, reference, 1e-9)
    _leaves_close(segments, reference, 1e-9)


# ----------------------------------------------------------------------------- a Fourier-series torque
def _torque_scene(nv=3, harmonics=2, seed=3):
    """The chain (gravity, springs, dampers) with a Fourier-series joint torque of every kind of term."""
    rng = np.random.default_rng(seed)
    torque = jb.FourierTorque(0.9, sine=rng.standard_normal((nv, harmonics)), cosine=rng.standard_normal((nv, harmonics)),
                              offset=rng.standard_normal(nv))
    model = _models()["chain"]
    return model, jb.scene(model, kernel="native", planar=False, effects=[torque]), torque


def test_fourier_torque_native_solves_equal_the_stepped_solve(monkeypatch):
    """Gravity, springs, dampers and a Fourier-series torque, evaluated at each stage's time inside
    the one-call programs (from a start time that is not zero: the torque's phase): the RK4 and
    Dopri5 solves (every field, the states saved at requested times from the steps' dense output,
    the torque's work beside the dampers') equal diffrax's loop, whose
    RK4 steps are the native step program with the torque (``rk4_step``), and the RK4 solve equals
    the four stages written in JAX on the vectorised kernel. Their gradients:
    :func:`test_fourier_torque_gradients` (slow: the loop's compilation)."""
    model, scene, torque = _torque_scene()
    calls = []
    for name in ("rk4_rollout", "adaptive_solve", "rk4_step"):
        fn = getattr(native, name)
        monkeypatch.setattr(native, name, lambda *a, _fn=fn, **kw: calls.append(_fn.__name__) or _fn(*a, **kw))
    q0, v0 = _state(model, 4)
    t0 = 0.35

    saves = diffrax.SaveAt(ts=t0 + jnp.array([0.0, 0.013, 0.05, 0.1]), t1=True)

    def run():
        fixed = _solve(scene, q0, v0, t0 + 0.1, t0=t0, saveat=saves)
        adaptive = _adaptive(scene, q0, v0, "dopri5", t0 + 0.2, t0=t0, saveat=diffrax.SaveAt(ts=jnp.linspace(t0, t0 + 0.2, 4)))
        return fixed, adaptive

    fixed, adaptive = run()
    assert sorted(set(calls)) == ["adaptive_solve", "rk4_rollout"], calls
    assert abs(float(fixed.work["torque"][-1])) > 1e-2 and float(fixed.work["dampers"][-1]) < 0
    _stepped(monkeypatch)
    calls.clear()
    fixed_loop, adaptive_loop = run()
    assert set(calls) == {"rk4_step"}, calls
    for key in ("num_steps", "num_accepted_steps", "num_rejected_steps"):
        assert int(adaptive.stats[key]) == int(adaptive_loop.stats[key]), key
    _leaves_close(fixed, fixed_loop, 1e-13)
    _leaves_close(adaptive, adaptive_loop, 1e-12)
    stages = _solve(jb.scene(model, kernel="vectorised", planar=False, effects=[torque]), q0, v0, t0 + 0.1, t0=t0,
                    saveat=saves)
    _leaves_close((fixed.q, fixed.v, fixed.work, fixed.t), (stages.q, stages.v, stages.work, stages.t), 1e-12)


def test_fourier_torque_against_mujoco_qfrc_applied(models_dir):
    """The Panda arm with a Fourier-series torque: the scene's acceleration at a time and state
    equals MuJoCo's ``mj_forward`` with the series, summed independently here, as
    ``qfrc_applied``; a bad coefficient is refused naming its field."""
    import mujoco

    path = models_dir / "panda.xml"
    model = jb.from_mjcf(str(path))
    rng = np.random.default_rng(5)
    f, a, b, c = 0.4, rng.standard_normal((model.nv, 3)), rng.standard_normal((model.nv, 3)), rng.standard_normal(model.nv)
    torque = jb.FourierTorque(f, sine=a, cosine=b, offset=c)
    scene = jb.scene(model, effects=[torque])
    q = np.asarray(model.qpos0) + 0.3 * rng.standard_normal(model.nq)
    v = rng.standard_normal(model.nv)
    t = 1.37
    k = np.arange(1, 4)
    tau = c + a @ np.sin(k * 2 * np.pi * f * t) + b @ np.cos(k * 2 * np.pi * f * t)
    np.testing.assert_allclose(np.asarray(torque(t)), tau, rtol=1e-13, atol=1e-13)
    m = mujoco.MjModel.from_xml_path(str(path))
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
                              | mujoco.mjtDisableBit.mjDSBL_ACTUATION)
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.qfrc_applied[:] = q, v, tau
    mujoco.mj_forward(m, d)
    acc = jax.jit(lambda t, q, v: scene.evaluate(t, q, v)[0])(t, jnp.asarray(q), jnp.asarray(v))
    assert float(np.max(np.abs(np.asarray(acc) - d.qacc))) <= 1e-9 * max(1.0, float(np.max(np.abs(d.qacc))))
    with pytest.raises(ValueError, match="torque: sine has 6 rows, expected one per DoF"):
        jb.scene(model, effects=[jb.FourierTorque(f, sine=a[:6])])
    with pytest.raises(ValueError, match=r"torque: cosine has shape \(7, 2\), expected \(7, 3\)"):
        jb.FourierTorque(f, sine=a, cosine=b[:, :2])
    with pytest.raises(ValueError, match="torque: offset is not finite"):
        jb.FourierTorque(f, sine=a, offset=np.full(model.nv, np.inf))
    with pytest.raises(ValueError, match="torque: frequency must be a scalar"):
        jb.FourierTorque(np.ones(2), sine=a)


@pytest.mark.slow  # the step-by-step gradients' compilation
def test_fourier_torque_gradients(monkeypatch):
    """With a Fourier-series torque, the gradients with respect to the initial state through the
    native reverse sweeps (the torque's stage times recomputed and replayed) equal diffrax's loop:
    RK4 and Dopri5 (states and both works saved inside the steps in the loss); the gradient
    with respect to the torque's coefficients (diffrax's loop) against central differences."""
    model, scene, torque = _torque_scene()
    q0, v0 = _state(model, 4)
    calls = []
    for name in ("rk4_rollout_vjp", "adaptive_solve_vjp"):
        fn = getattr(native, name)
        monkeypatch.setattr(native, name, lambda *a, _fn=fn, **kw: calls.append(_fn.__name__) or _fn(*a, **kw))

    def fixed(q, v):
        # states saved inside the steps, at a step's end and at t1: both works through the dense output
        saves = diffrax.SaveAt(ts=jnp.array([0.35, 0.383, 0.4, 0.427]), t1=True)
        sol = _solve(scene, q, v, 0.45, t0=0.35, max_steps=20, saveat=saves)
        weights = jnp.arange(1.0, 6.0)
        return (jnp.sum(weights[:, None] * jnp.sin(sol.q)) + jnp.sum(sol.v_final ** 2)
                + jnp.sum(weights * (3.0 * sol.work["torque"] + sol.work["dampers"])))

    def adaptive(q, v, scene=scene):
        sol = _adaptive(scene, q, v, "dopri5", 0.3, t0=0.1, saveat=diffrax.SaveAt(ts=jnp.linspace(0.1, 0.3, 5)),
                        max_steps=100)
        return jnp.sum(jnp.arange(1.0, 6.0)[:, None] * jnp.sin(sol.q)) + jnp.sum(sol.v_final ** 2) \
            + jnp.sum(sol.work["torque"])

    grads = [jax.jit(jax.grad(f, argnums=(0, 1)))(q0, v0) for f in (fixed, adaptive)]
    assert sorted(set(calls)) == ["adaptive_solve_vjp", "rk4_rollout_vjp"], calls
    _stepped(monkeypatch)
    for f, g in zip((fixed, adaptive), grads):
        _leaves_close(g, jax.jit(jax.grad(f, argnums=(0, 1)))(q0, v0), 1e-10)
    monkeypatch.setenv("JAXBODY_NATIVE_SOLVE", "1")

    def of_sine(sine):
        t = eqx.tree_at(lambda x: x.sine, torque, sine)
        return adaptive(q0, v0, jb.scene(model, kernel="native", planar=False, effects=[t]))

    g = jax.jit(jax.grad(of_sine))(torque.sine)
    eps = 1e-6
    basis = jnp.eye(torque.sine.size).reshape(-1, *torque.sine.shape)
    values = jax.jit(jax.vmap(of_sine))(jnp.concatenate([torque.sine + eps * basis, torque.sine - eps * basis]))
    fd = ((values[: basis.shape[0]] - values[basis.shape[0]:]) / (2 * eps)).reshape(torque.sine.shape)
    assert float(jnp.max(jnp.abs(g))) > 1e-3
    assert float(jnp.max(jnp.abs(g - fd))) <= 1e-6 * max(1.0, float(jnp.max(jnp.abs(fd))))
