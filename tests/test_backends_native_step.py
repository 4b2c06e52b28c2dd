"""The native RK4 step: one generated program for the four stages of a classical RK4 step.

``jaxbody.backends.native.rk4_step`` is checked against RK4 written out here in JAX around the
vectorised kernel (an independent path: no generated code), with springs, dampers and the
dampers' work, for a hinge chain and a free-base tree with a ball joint; its derivatives
(the step's generated forward- and reverse-mode programs, and the JAX path for parameters)
against the same reference; and ``jb.simulate`` on the native kernel, which takes the step
for scenes of gravity, springs and dampers, against the vectorised kernel.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody import backends, kernels, simulation
from jaxbody.backends import native
from jaxbody.kinematics import qpos_rate

pytestmark = pytest.mark.filterwarnings("ignore:from_mjcf")


def _reference_step(model, q, v, h, force, gravity, stiffness, reference, damping):
    """RK4 of (q̇, v̇, ẇ) in JAX on the vectorised kernel, springs from the kernels' own
    per-kind spring displacements (rotation vectors for ball and free joints)."""
    springy = eqx.tree_at(lambda m: (m.joint_stiffness, m.qpos_spring), model, (stiffness, reference))

    def field(q, v):
        spring = jnp.zeros_like(v)
        for dofs, disp, k in kernels.spring_displacements(springy, q):
            spring = spring.at[dofs].add(-k[:, None] * disp)
        damper = -damping * v
        a = backends.acceleration(model, q, v, force + spring + damper, gravity=gravity, kernel="vectorised")
        return h * qpos_rate(model, q, v), h * a, h * jnp.dot(damper, v)

    k1 = field(q, v)
    k2 = field(q + 0.5 * k1[0], v + 0.5 * k1[1])
    k3 = field(q + 0.5 * k2[0], v + 0.5 * k2[1])
    k4 = field(q + k3[0], v + k3[1])
    comb = [(a + 2 * b + 2 * c + d) / 6 for a, b, c, d in zip(k1, k2, k3, k4)]
    return q + comb[0], v + comb[1], k1[0], k1[1], k4[0], k4[1], jnp.stack([comb[2], k1[2], k4[2]])


def _models():
    from _support.random_models import hinge_chain, random_model

    chain = hinge_chain(3)
    tree = random_model(0, n_body=2, kinds=("ball",))  # a free base and a ball joint: 9 DoFs
    return [("chain", chain), ("free_ball", tree)]


def _inputs(model, rng, springs):
    q = jb.normalize_qpos(model, jnp.asarray(model.qpos0) + 0.4 * rng.standard_normal(model.nq))
    v = jnp.asarray(rng.standard_normal(model.nv))
    force = jnp.asarray(rng.standard_normal(model.nv))
    stiffness = jnp.asarray(rng.uniform(1.0, 3.0, model.joints.n_joint)) if springs else jnp.zeros(model.joints.n_joint)
    reference = jb.normalize_qpos(model, jnp.asarray(model.qpos0) + 0.1)
    damping = jnp.asarray(rng.uniform(0.1, 0.5, model.nv))
    return q, v, force, stiffness, reference, damping


def _close(x, y, tol=1e-10):
    for a, b in zip(jax.tree.leaves(x), jax.tree.leaves(y)):
        assert a.shape == b.shape
        assert float(jnp.max(jnp.abs(a - b))) <= tol * max(float(jnp.max(jnp.abs(b))), 1.0), (a, b)


def _step_and_reference(name):
    model = dict(_models())[name]
    rng = np.random.default_rng(3)
    q, v, force, k, r, d = _inputs(model, rng, True)
    h, g = 0.01, jnp.asarray(model.gravity)
    passive = dict(stiffness=k, reference=r)

    def step(q, v, force, d):
        return native.rk4_step(model, q, v, h, force, gravity=g, damping=d, **passive)

    def ref(q, v, force, d):
        return _reference_step(model, q, v, h, force, g, k, r, d)

    return model, rng, step, ref, (q, v, force, d)


# the chain's values are also checked through simulate (test_simulate_takes_the_native_step...);
# the free base with a ball joint is the default job's only check of the step's quaternion rates
# and ball springs against an independent reference
@pytest.mark.parametrize("name", [pytest.param("chain", marks=pytest.mark.slow), "free_ball"])
def test_native_step_equals_rk4_on_the_vectorised_kernel(name):
    """Values, single and under vmap."""
    model, _, step, ref, (q, v, force, d) = _step_and_reference(name)
    _close(jax.jit(step)(q, v, force, d), jax.jit(ref)(q, v, force, d), 1e-12)
    qs = jnp.stack([q, jb.normalize_qpos(model, q + 0.1)])
    batch = lambda f: jax.jit(jax.vmap(f, in_axes=(0, None, None, None)))  # noqa: E731
    _close(batch(step)(qs, v, force, d), batch(ref)(qs, v, force, d), 1e-12)


# about 35 s (chain) and 60 s (free_ball): the default job checks the step's derivative programs
# through a rollout gradient and forward-mode Jacobian (test_rollout_gradient_through_the_native_step)
@pytest.mark.slow
@pytest.mark.parametrize("name", ["chain", "free_ball"])
def test_native_step_derivatives_equal_the_reference(name):
    """Forward mode along a random direction of (q, v, force, damping) (the step's generated
    forward-mode program, and the JAX path for the damping), reverse mode of a random cotangent
    of all seven results (its reverse-mode program)."""
    model, rng, step, ref, args = _step_and_reference(name)
    tangents = tuple(jnp.asarray(rng.standard_normal(x.shape)) for x in args)
    jvp = lambda f: jax.jit(lambda *a: jax.jvp(f, a, tangents)[1])  # noqa: E731
    _close(jvp(step)(*args), jvp(ref)(*args))
    cts = tuple(jnp.asarray(rng.standard_normal(x.shape)) for x in jax.jit(ref)(*args))
    vjp = lambda f: jax.jit(lambda *a: jax.vjp(f, *a)[1](cts))  # noqa: E731
    _close(vjp(step)(*args), vjp(ref)(*args))


def test_native_step_in_float32_stays_near_float64():
    model64 = dict(_models())["free_ball"]
    model32 = jax.tree.map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, model64)
    rng = np.random.default_rng(4)
    q, v, force, _, _, d = _inputs(model64, rng, False)
    out = []
    for m in (model64, model32):
        dt = m.body_pos.dtype
        out.append(native.rk4_step(m, q.astype(dt), v.astype(dt), 0.01, force.astype(dt), gravity=m.gravity, damping=d.astype(dt)))
    assert out[1][0].dtype == jnp.float32
    for a32, a64 in zip(out[1], out[0]):
        assert float(jnp.max(jnp.abs(a32.astype(jnp.float64) - a64))) <= 1e-4 * max(1.0, float(jnp.max(jnp.abs(a64))))


def test_simulate_takes_the_native_step_and_equals_the_vectorised_kernel(monkeypatch):
    """Gravity, springs and dampers (with the dampers' work and dense output at save times),
    single and batched with an invalid member (throw=False), against the vectorised kernel;
    a scene with a time-dependent torque keeps the four-stage path. (Diffrax's loop: the one-call
    solve, which would otherwise run this solve, is test_simulation_native_solve.py's.)"""
    monkeypatch.setenv("JAXBODY_NATIVE_SOLVE", "0")
    model = dict(_models())["chain"]
    model = eqx.tree_at(lambda m: (m.joint_stiffness, m.dof_damping), model, (jnp.full(model.joints.n_joint, 2.0), jnp.full(model.nv, 0.3)))
    calls = []
    step = native.rk4_step
    monkeypatch.setattr(native, "rk4_step", lambda *a, **kw: calls.append(1) or step(*a, **kw))
    fast, ref = jb.scene(model, kernel="native", planar=False), jb.scene(model, kernel="vectorised", planar=False)
    assert {type(e).__name__ for e in fast.effects} == {"Gravity", "JointSprings", "JointDampers"}
    q0, v0 = jnp.asarray(model.qpos0) + 0.3, jnp.linspace(-1.0, 1.0, model.nv)
    run = lambda sc, q, **kw: jb.simulate(sc, q, v0, 0.2, solver="rk4", dt0=1e-2, saveat=jnp.linspace(0.0, 0.2, 7), **kw)  # noqa: E731
    a, b = run(fast, q0), run(ref, q0)
    assert calls, "simulate did not take the native step"
    _close((a.q, a.v, a.work["dampers"]), (b.q, b.v, b.work["dampers"]), 1e-12)
    _close(a.energy_balance, b.energy_balance, 1e-9)

    qs = jnp.stack([q0, q0 + 0.1, q0.at[0].set(jnp.nan)])
    codes, q_batch = jax.jit(jax.vmap(lambda q: (lambda s: (s.result._value, s.q))(run(fast, q, throw=False))))(qs)
    ok, bad = int(jb.RESULTS.successful._value), int(jb.RESULTS.invalid_input._value)
    assert codes.tolist() == [ok, ok, bad]
    _close(q_batch[1], run(ref, q0 + 0.1).q, 1e-12)

    calls.clear()
    torque = jb.scene(model, kernel="native", planar=False, actuation=lambda t, q, v: jnp.full(model.nv, jnp.sin(t)))
    run(torque, q0)
    assert not calls


def test_rollout_gradient_through_the_native_step():
    """The gradient of a rollout through the step's reverse-mode program (checkpointed adjoint)
    and its forward-mode program equal the vectorised kernel's."""
    model = dict(_models())["chain"]
    fast, ref = jb.scene(model, kernel="native", planar=False), jb.scene(model, kernel="vectorised", planar=False)
    v0 = jnp.linspace(-1.0, 1.0, model.nv)

    def loss(scene, **kw):
        def f(q0):
            sol = jb.simulate(scene, q0, v0, 0.1, solver="rk4", dt0=1e-2, saveat=diffrax.SaveAt(t1=True), **kw)
            return jnp.sum(sol.q[-1] ** 2) + jnp.sum(sol.v[-1] ** 2)

        return f

    q0 = jnp.asarray(model.qpos0) + 0.3
    g_ref = jax.jit(jax.grad(loss(ref)))(q0)
    _close(jax.jit(jax.grad(loss(fast)))(q0), g_ref)
    _close(jax.jit(jax.jacfwd(loss(fast, adjoint=diffrax.ForwardMode())))(q0), g_ref)
