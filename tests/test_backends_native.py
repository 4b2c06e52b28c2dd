"""The native forward-dynamics kernel against MuJoCo and the vectorised kernel.

The native kernel is the unrolled algorithm emitted as C++ for the model's tree and called
through XLA's FFI (jaxbody/backends/native/). It is checked here against MuJoCo's ``mj_forward`` on
the shipped robots (fixed and free base), against the vectorised kernel on seeded random MJCF
trees with every joint kind, single and batched (nested ``vmap``, batches that are not a
multiple of the SIMD width, unbatched inputs), with derivatives against finite differences,
in float32, and inside ``jb.simulate``.
"""

import os
import pathlib
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from jax.test_util import check_grads
from _support.jaxpr_tools import count_eqns

import jaxbody as jb
from jaxbody import backends
from jaxbody.backends import native

pytestmark = pytest.mark.filterwarnings("ignore:from_mjcf")
REPO = pathlib.Path(__file__).resolve().parents[1]


def _states(model, rng, batch):
    q = np.asarray(model.qpos0) + 0.5 * rng.standard_normal((batch, model.nq))
    q = jax.jit(jax.vmap(lambda x: jb.normalize_qpos(model, x)))(jnp.asarray(q))
    return q, jnp.asarray(rng.standard_normal((batch, model.nv)))


def _mujoco_qacc(path, q, v, tau, ext):
    """MuJoCo's rigid-body accelerations (contacts, constraints, passive forces, actuation off)."""
    m = mujoco.MjModel.from_xml_path(str(path))
    for flag in ("mjDSBL_CONTACT", "mjDSBL_CONSTRAINT", "mjDSBL_ACTUATION", "mjDSBL_SPRING", "mjDSBL_DAMPER", "mjDSBL_PASSIVE"):
        if hasattr(mujoco.mjtDisableBit, flag):
            m.opt.disableflags |= int(getattr(mujoco.mjtDisableBit, flag))
    d = mujoco.MjData(m)
    out = []
    for i in range(q.shape[0]):
        d.qpos[:], d.qvel[:], d.qfrc_applied[:] = q[i], v[i], tau[i]
        d.xfrc_applied[1:] = ext[i]
        mujoco.mj_forward(m, d)
        out.append(d.qacc.copy())
    return np.array(out)


# anymal_c (free base, 43 s with its C++ build) runs in the slow job; the free joint is in the
# default suite through the random trees (seed 0 has a free root)
@pytest.mark.parametrize("name", ["panda", pytest.param("ur5e", marks=pytest.mark.slow),
                                  pytest.param("anymal_c", marks=pytest.mark.slow)])
def test_native_equals_mujoco_on_the_shipped_robots(models_dir, name):
    path = models_dir / f"{name}.xml"
    model = jb.from_mjcf(str(path))
    rng = np.random.default_rng(11)
    q, v = _states(model, rng, 6)
    tau = jnp.asarray(rng.standard_normal((6, model.nv)))
    ext = jnp.asarray(rng.standard_normal((6, model.n_body, 6)))
    fd = lambda kernel, e: jax.jit(jax.vmap(  # noqa: E731
        lambda q, v, t, x: backends.acceleration(model, q, v, t, gravity=model.gravity, external=x, kernel=kernel)
    ))(q, v, tau, e)
    a_native = np.asarray(fd("native", ext))
    a_ref = _mujoco_qacc(path, np.asarray(q), np.asarray(v), np.asarray(tau), np.asarray(ext))
    assert np.max(np.abs(a_native - a_ref)) <= 1e-10 * np.abs(a_ref).max()
    # without loads: a different generated program, the same numbers as the vectorised kernel
    no_loads = lambda kernel: jax.jit(jax.vmap(  # noqa: E731
        lambda q, v, t: backends.acceleration(model, q, v, t, gravity=model.gravity, kernel=kernel)
    ))(q, v, tau)
    a0, b0 = np.asarray(no_loads("native")), np.asarray(no_loads("vectorised"))
    assert np.max(np.abs(a0 - b0)) <= 1e-11 * np.abs(b0).max()


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
def test_native_on_random_trees_with_every_joint_kind(seed):
    from _support.mjcf_random import random_mjcf

    model = jb.from_mjcf(random_mjcf(seed))
    rng = np.random.default_rng(seed)
    q, v = _states(model, rng, 5)
    tau = jnp.asarray(rng.standard_normal((5, model.nv)))
    run = lambda kernel: jax.jit(jax.vmap(  # noqa: E731
        lambda q, v, t: backends.acceleration(model, q, v, t, gravity=model.gravity, kernel=kernel)
    ))(q, v, tau)
    a, b = run("native"), run("vectorised")
    assert float(jnp.max(jnp.abs(a - b))) <= 1e-9 * float(jnp.max(jnp.abs(b)))


def test_batches_single_states_and_nested_vmap(models_dir):
    """One state, a batch of 103 (a partial SIMD block at the end), an unbatched ``q`` with a
    batched ``v``, and parameters batched outside states: all equal the vectorised kernel."""
    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    rng = np.random.default_rng(2)
    q, v = _states(model, rng, 103)

    def fd(kernel):
        return lambda m, q, v: backends.acceleration(m, q, v, -0.3 * v, gravity=m.gravity, kernel=kernel)

    def close(x, y, tol=1e-11):
        assert float(jnp.max(jnp.abs(x - y))) <= tol * float(jnp.max(jnp.abs(y)))

    # (every call jitted: the vectorised kernel run op by op costs more than its compilation)
    close(jax.jit(fd("native"))(model, q[0], v[0]), jax.jit(fd("vectorised"))(model, q[0], v[0]))
    batch = jax.jit(jax.vmap(fd("native"), in_axes=(None, 0, 0)))(model, q, v)
    close(batch, jax.jit(jax.vmap(fd("vectorised"), in_axes=(None, 0, 0)))(model, q, v))
    shared_q = jax.jit(jax.vmap(fd("native"), in_axes=(None, None, 0)))(model, q[0], v)
    close(shared_q, jax.jit(jax.vmap(fd("vectorised"), in_axes=(None, None, 0)))(model, q[0], v))
    masses = model.body_mass * (1.0 + 0.2 * jnp.arange(3.0))[:, None]
    nested = lambda kernel: jax.jit(jax.vmap(  # noqa: E731
        lambda mass: jax.vmap(fd(kernel), in_axes=(None, 0, 0))(eqx.tree_at(lambda m: m.body_mass, model, mass), q[:9], v[:9])
    ))(masses)
    out = nested("native")
    assert out.shape == (3, 9, model.nv)
    close(out, nested("vectorised"))
    # the inner batch varies over the outer one (v batched inside, masses outside)
    assert float(jnp.max(jnp.abs(out[0] - out[2]))) > 1e-3


def test_gradients_match_finite_differences():
    """Derivatives along the state and force (the generated programs) and along the masses
    (the vectorised kernel) against finite differences, on a tree of hinges and slides with
    several joints on a body (the generated derivatives of quaternion joints:
    ``test_generated_derivatives_equal_the_vectorised_kernel``; Panda's, in the slow job:
    ``test_panda_rollout_gradient_with_generated_derivatives``)."""
    from _support.random_models import random_model

    model = random_model(0, n_body=3, kinds=("hinge", "slide", "hinge2", "slide_hinge"), free_root=False)
    assert 4 <= model.nv <= native.MAX_DERIVATIVE_DOFS
    rng = np.random.default_rng(7)
    q, v = _states(model, rng, 1)
    tau = jnp.asarray(rng.standard_normal(model.nv))

    def fun(q, v, tau, mass):
        m = eqx.tree_at(lambda m: m.body_mass, model, mass)
        return backends.acceleration(m, q, v, tau, gravity=model.gravity, kernel="native")

    check_grads(jax.jit(fun), (q[0], v[0], tau, model.body_mass), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


def _small_tree():
    """A free base and a ball (9 DoFs, both quaternion joints): the generated derivatives serve
    it (hinges: Panda in ``test_gradients_match_finite_differences``)."""
    from _support.random_models import random_model

    model = random_model(0, n_body=2, kinds=("ball",))
    assert model.nv <= native.MAX_DERIVATIVE_DOFS
    return model


def test_generated_derivatives_equal_the_vectorised_kernel():
    """Forward mode (the generated tangent program) and reverse mode (the generated adjoint
    program, as the transpose) w.r.t. state and force, with gravity and body loads, single,
    under vmap with batched and shared tangents, and a second derivative (through the JAX
    fallback of the derivative's own derivative)."""
    model = _small_tree()
    rng = np.random.default_rng(11)
    q, v = _states(model, rng, 4)
    tau = jnp.asarray(rng.standard_normal((4, model.nv)))
    ext = jnp.asarray(rng.standard_normal((model.tree.n_body, 6)))

    def fd(kernel):
        return lambda q, v, t: backends.acceleration(model, q, v, t, gravity=model.gravity, external=ext, kernel=kernel)

    def close(x, y, tol=1e-10):
        for a, b in zip(jax.tree.leaves(x), jax.tree.leaves(y)):
            assert float(jnp.max(jnp.abs(a - b))) <= tol * max(float(jnp.max(jnp.abs(b))), 1.0)

    args = (q[0], v[0], tau[0])
    for jac in (jax.jacfwd, jax.jacrev):
        close(jax.jit(jac(fd("native"), argnums=(0, 1, 2)))(*args), jax.jit(jac(fd("vectorised"), argnums=(0, 1, 2)))(*args))

    # batched states, one tangent shared by all (its cotangent is summed over the batch)
    def loss(kernel):
        return lambda v_shared: jnp.sum(jnp.sin(jax.vmap(lambda q, t: fd(kernel)(q, v_shared, t))(q, tau)))

    close(jax.jit(jax.grad(loss("native")))(v[0]), jax.jit(jax.grad(loss("vectorised")))(v[0]))
    dq = jnp.asarray(rng.standard_normal(model.nq))
    jvp = lambda k: lambda: jax.vmap(lambda q, v: jax.jvp(lambda q: fd(k)(q, v, tau[0]), (q,), (dq,))[1])(q, v)  # noqa: E731
    close(jax.jit(jvp("native"))(), jax.jit(jvp("vectorised"))())


@pytest.mark.slow  # builds ANYmal C's forward- and reverse-mode programs (about a minute)
def test_generated_derivatives_of_an_18_dof_free_base_robot(models_dir):
    """Trees above 12 DoFs (up to MAX_DERIVATIVE_DOFS) take their state derivatives from the
    generated programs too: ANYmal C (free base, 18 DoFs), with body loads, both modes."""
    model = jb.from_mjcf(str(models_dir / "anymal_c.xml"))
    assert 12 < model.nv <= native.MAX_DERIVATIVE_DOFS
    rng = np.random.default_rng(5)
    q, v = _states(model, rng, 1)
    tau = jnp.asarray(rng.standard_normal(model.nv))
    ext = jnp.asarray(rng.standard_normal((model.n_body, 6)))

    def fd(kernel):
        return lambda q, v, t: backends.acceleration(model, q, v, t, gravity=model.gravity, external=ext, kernel=kernel)

    for jac in (jax.jacfwd, jax.jacrev):
        got = jax.jit(jac(fd("native"), argnums=(0, 1, 2)))(q[0], v[0], tau)
        want = jax.jit(jac(fd("vectorised"), argnums=(0, 1, 2)))(q[0], v[0], tau)
        for a, b in zip(got, want):
            assert float(jnp.max(jnp.abs(a - b))) <= 1e-10 * max(float(jnp.max(jnp.abs(b))), 1.0)


@pytest.mark.slow  # about 15 s: the fallback compiles the unrolled kernel's second derivatives
def test_second_derivatives_through_the_native_kernel():
    """The derivative of the generated derivative (its residuals' part from the same map
    written in JAX) equals the vectorised kernel's Hessian."""
    model = _small_tree()
    rng = np.random.default_rng(12)
    q, v = _states(model, rng, 1)
    tau = jnp.asarray(rng.standard_normal(model.nv))

    def hess(kernel):
        fd = lambda v: backends.acceleration(model, q[0], v, tau, gravity=model.gravity, kernel=kernel)  # noqa: E731
        return jax.jit(jax.hessian(lambda v: jnp.sum(fd(v) ** 2)))(v[0])

    a, b = hess("native"), hess("vectorised")
    assert float(jnp.max(jnp.abs(a - b))) <= 1e-9 * float(jnp.max(jnp.abs(b)))


def _rollout_gradients(model, kernels_and_adjoints, q0, v0):
    import diffrax

    out = []
    for kernel, adjoint in kernels_and_adjoints:
        scene = jb.scene(model, kernel=kernel)

        def loss(q0, scene=scene, adjoint=adjoint):
            sol = jb.simulate(scene, q0, v0, 0.05, solver="rk4", dt0=1e-3, saveat=diffrax.SaveAt(t1=True), adjoint=adjoint, max_steps=100)
            return jnp.sum(sol.q[-1] ** 2) + jnp.sum(sol.v[-1] ** 2)

        out.append(jax.jit(jax.grad(loss))(q0))
    return out


@pytest.mark.slow  # about 90 s: four rollout gradients of a free-base tree
def test_rollout_gradient_with_generated_derivatives_checkpoint_and_backsolve():
    """A rollout gradient on the native kernel (generated derivatives, the written-out RK4
    stages) equals the vectorised kernel's (the tableau RK4), for the checkpointed and the
    backsolve adjoint (which renormalises the quaternions it reconstructs in reverse time)."""
    model = _small_tree()
    q0 = jb.normalize_qpos(model, model.qpos0 + 0.2)
    v0 = jnp.linspace(-1.0, 1.0, model.nv)
    pairs = [(k, a) for a in ("checkpoint", "backsolve") for k in ("vectorised", "native")]
    ck_ref, ck, bs_ref, bs = _rollout_gradients(model, pairs, q0, v0)
    for g, ref in ((ck, ck_ref), (bs, bs_ref)):
        assert float(jnp.max(jnp.abs(g - ref))) <= 1e-9 * float(jnp.max(jnp.abs(ref)))


@pytest.mark.slow  # about 30 s: Panda's derivative programs and the vectorised reference
def test_panda_rollout_gradient_with_generated_derivatives(models_dir):
    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    v0 = jnp.linspace(-1.0, 1.0, model.nv)
    ref, ck, bs = _rollout_gradients(model, [("vectorised", "checkpoint"), ("native", "checkpoint"), ("native", "backsolve")], model.qpos0 + 0.2, v0)
    for g in (ck, bs):
        assert float(jnp.max(jnp.abs(g - ref))) <= 1e-8 * float(jnp.max(jnp.abs(ref)))


@pytest.mark.slow  # about 25 s
def test_reverse_mode_under_vmap_equals_the_vectorised_kernel(models_dir):
    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    rng = np.random.default_rng(7)
    tau = jnp.asarray(rng.standard_normal(model.nv))
    qs, vs = _states(model, rng, 6)
    loss = lambda k: lambda q, v: jnp.sum(jnp.sin(backends.acceleration(model, q, v, tau, gravity=model.gravity, kernel=k)))  # noqa: E731
    g_n = jax.vmap(jax.grad(loss("native"), argnums=(0, 1)))(qs, vs)
    g_v = jax.vmap(jax.grad(loss("vectorised"), argnums=(0, 1)))(qs, vs)
    for x, y in zip(g_n, g_v):
        assert float(jnp.max(jnp.abs(x - y))) <= 1e-10 * float(jnp.max(jnp.abs(y)))


def test_program_size_does_not_grow_with_the_tree():
    from _support.random_models import hinge_chain

    def size(n):
        m = hinge_chain(n)
        fn = lambda q, v: backends.acceleration(m, q, v, kernel="native")  # noqa: E731
        return count_eqns(jax.make_jaxpr(fn)(jnp.zeros(m.nq), jnp.zeros(m.nv)).jaxpr)

    assert size(3) == size(12)


def test_large_batch_and_a_nan_member(models_dir):
    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    rng = np.random.default_rng(4)
    q, v = _states(model, rng, 65536)
    v = v.at[5].set(jnp.nan)
    a = jax.jit(jax.vmap(lambda q, v: backends.acceleration(model, q, v, gravity=model.gravity, kernel="native")))(q, v)
    assert a.shape == (65536, model.nv)
    assert bool(jnp.all(jnp.isnan(a[5])))
    finite = jnp.isfinite(a).all(axis=1)
    assert int(finite.sum()) == 65535
    ref = jax.jit(jax.vmap(lambda q, v: backends.acceleration(model, q, v, gravity=model.gravity, kernel="vectorised")))(q[-64:], v[-64:])
    assert float(jnp.max(jnp.abs(a[-64:] - ref))) <= 1e-11 * float(jnp.max(jnp.abs(ref)))


def test_float32_within_1e4_of_float64(models_dir):
    import subprocess
    import sys

    code = f"""
import warnings; warnings.simplefilter('ignore')
import jax, jax.numpy as jnp, numpy as np
import jaxbody as jb
from jaxbody import backends
m = jb.from_mjcf({str(models_dir / 'panda.xml')!r})
rng = np.random.default_rng(0)
q = np.asarray(m.qpos0) + 0.4 * rng.standard_normal((37, m.nq)); v = rng.standard_normal((37, m.nv))
f = jax.vmap(lambda q, v: backends.acceleration(m, q, v, gravity=m.gravity, kernel='native'))
# 37 states: the 512-bit build where there is AVX-512 (two full blocks of 16 and a partial one,
# read by gathers and written by scatters), else the 256-bit one; 8 states: the 256-bit build
a = f(jnp.asarray(q, jnp.float32), jnp.asarray(v, jnp.float32))
assert a.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(a)))
a8 = f(jnp.asarray(q[:8], jnp.float32), jnp.asarray(v[:8], jnp.float32))
assert float(jnp.max(jnp.abs(a8 - a[:8]))) <= 1e-5 * float(jnp.max(jnp.abs(a[:8])))
# a single state runs the scalar build, a batch the vector one: the same float32 operations
one = jax.jit(lambda q, v: backends.acceleration(m, q, v, gravity=m.gravity, kernel='native'))(jnp.asarray(q[3], jnp.float32), jnp.asarray(v[3], jnp.float32))
assert one.dtype == jnp.float32 and float(jnp.max(jnp.abs(one - a[3]))) <= 1e-5 * float(jnp.max(jnp.abs(a[3]))), (one, a[3])
print(' '.join(repr(float(x)) for x in np.ravel(a)))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    a32 = np.array([float(x) for x in out.stdout.split()]).reshape(37, -1)
    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    rng = np.random.default_rng(0)
    q = np.asarray(model.qpos0) + 0.4 * rng.standard_normal((37, model.nq))
    v = rng.standard_normal((37, model.nv))
    a64 = np.asarray(jax.jit(jax.vmap(lambda q, v: backends.acceleration(model, q, v, gravity=model.gravity, kernel="vectorised")))(q, v))
    assert np.max(np.abs(a32 - a64)) <= 1e-4 * max(1.0, np.abs(a64).max())


@pytest.mark.parametrize("spin_ns", ["0", "100000"])
def test_thread_pool_back_to_back_calls_with_more_threads_than_cores(models_dir, spin_ns):
    """The pool's threads spin between calls (``SPIN_NS``) or sleep at once (0); with three
    threads on any machine, batches that use one, two or three of them, Python-driven calls
    and 60 calls back to back inside a jitted loop all equal the vectorised kernel."""
    import subprocess
    import sys

    code = f"""
import os
os.environ['JAXBODY_NATIVE_THREADS'] = '3'
os.environ['JAXBODY_NATIVE_SPIN_NS'] = {spin_ns!r}
import warnings; warnings.simplefilter('ignore')
import jax; jax.config.update('jax_enable_x64', True)
import jax.numpy as jnp, numpy as np
import jaxbody as jb
from jaxbody import backends
m = jb.from_mjcf({str(models_dir / 'panda.xml')!r})
rng = np.random.default_rng(5)
q = jnp.asarray(np.asarray(m.qpos0) + 0.4 * rng.standard_normal((1000, m.nq)))
v = jnp.asarray(rng.standard_normal((1000, m.nv)))
def fd(kernel):
    return jax.vmap(lambda q, v: backends.acceleration(m, q, v, gravity=m.gravity, kernel=kernel))
native, ref = jax.jit(fd('native')), jax.jit(fd('vectorised'))
for rep in range(3):
    for b in (100, 130, 257, 1000):  # one, two, three (partial) and three slices
        a, r = native(q[:b], v[:b]), ref(q[:b], v[:b])
        assert float(jnp.max(jnp.abs(a - r))) <= 1e-11 * float(jnp.max(jnp.abs(r))), (rep, b)
def loop(f):
    return jax.jit(lambda v: jax.lax.fori_loop(0, 60, lambda i, v: v + 1e-4 * f(q, v), v))
a, r = loop(fd('native'))(v), loop(fd('vectorised'))(v)
assert float(jnp.max(jnp.abs(a - r))) <= 1e-10 * float(jnp.max(jnp.abs(r)))
print('ok')
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


@pytest.mark.slow  # about 50 s (Panda's generated RK4 step); test_backends_native_step.py covers simulate on the native kernel
def test_simulate_with_the_native_kernel_equals_the_vectorised_one(models_dir):
    from jaxbody import simulation

    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    fast, ref = jb.scene(model, kernel="auto"), jb.scene(model, kernel="vectorised")
    assert backends.resolve_kernel(model, "auto") == "native"
    pick = lambda sc: simulation.choose_solver("rk4", sc, jnp.float64, 1e-8, 1e-8, 1e-3, None)[0].solver  # noqa: E731
    assert type(pick(fast)) is simulation.RK4Stages
    q0 = model.qpos0 + 0.2
    v0 = jnp.linspace(-1.0, 1.0, model.nv)
    run = lambda sc, q: jb.simulate(sc, q, v0, 0.1, solver="rk4", dt0=1e-3, n_save=5)  # noqa: E731
    a, b = run(fast, q0), run(ref, q0)
    np.testing.assert_allclose(a.q, b.q, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.v, b.v, rtol=1e-11, atol=1e-11)
    qs = q0 + 0.05 * jnp.arange(6.0)[:, None]
    ba = jax.jit(jax.vmap(lambda q: run(fast, q).q))(qs)
    bb = jax.vmap(lambda q: run(ref, q).q)(qs)
    np.testing.assert_allclose(ba, bb, rtol=1e-12, atol=1e-12)


def test_unavailable_native_kernel_is_a_clear_error_and_auto_falls_back(monkeypatch, tmp_path):
    from _support.random_models import hinge_chain

    model = hinge_chain(2)
    # the package re-exports what its build module defines and uses: both say why
    reason = "no C++ compiler found (g++; set $CXX to one)"
    monkeypatch.setattr(native, "unavailable_reason", lambda: reason)
    monkeypatch.setattr(native.build, "unavailable_reason", lambda: reason)
    monkeypatch.setattr(backends, "_warned", set())
    assert not native.available() and not native.applies(model)
    with pytest.raises(RuntimeError, match=r"kernel='native' needs a C\+\+17 compiler .*\(no C\+\+ compiler found"):
        backends.acceleration(model, jnp.zeros(2), jnp.zeros(2), kernel="native")
    # falling back says why, in one warning per reason and process
    with pytest.warns(backends.KernelFallbackWarning, match=r"runs the vectorised kernel, not the native one: no C\+\+ compiler"):
        assert backends.resolve_kernel(model, "auto") == "vectorised"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert backends.resolve_kernel(hinge_chain(3), "auto") == "vectorised"
    with pytest.raises(ValueError, match="kernel must be one of"):
        backends.resolve_kernel(model, "fast")
    # a compiler that fails: the error shows the command and the compiler's message
    monkeypatch.setenv("CXX", "false")
    monkeypatch.setenv("JAXBODY_CACHE_DIR", str(tmp_path))
    with pytest.raises(RuntimeError, match="building the native kernel failed"):
        native.build.build_library("int x;", "probe")


def test_auto_limit_counts_mass_matrix_entries_not_dofs(monkeypatch):
    """``kernel="auto"`` bounds the tree by the entries of its tree-sparse mass matrix (what the
    generated code grows with), so a 25-DoF humanoid gets the native kernel and a 25-link chain
    does not; the count is the pairs of DoFs whose bodies are on one path to the root (a dense
    walk of the tree's path matrix here)."""
    from _support.random_models import hinge_chain

    monkeypatch.setattr(backends, "_warned", set())
    humanoid = jb.from_mjcf(str(REPO / "benchmarks" / "models" / "humanoid25.xml"))
    body = np.asarray(humanoid.joints.dof_body)
    on_path = humanoid.tree.path_matrix[body][:, body]  # [i, j]: DoF j's body is i's or carries it
    assert native.mass_matrix_entries(humanoid) == int(np.tril(on_path).sum()) == 194
    assert [native.mass_matrix_entries(hinge_chain(n)) for n in (1, 24, 25)] == [1, 300, 325]
    if native.available():
        assert humanoid.nv == 25 and backends.resolve_kernel(humanoid, "auto") == "native"
        with pytest.warns(backends.KernelFallbackWarning, match=r"25 DoFs\) has 325 mass-matrix entries, above .* limit of 300"):
            assert backends.resolve_kernel(hinge_chain(25), "auto") == "vectorised"
        # asked for by name, the native kernel takes any tree
        assert backends.resolve_kernel(hinge_chain(25), "native") == "native"


def test_concurrent_builders_of_one_library_compile_it_once(tmp_path):
    """Processes that build the same library at the same time (test workers, a batch job's
    processes) take turns on a lock: the compiler runs once and every process gets the file."""
    import shutil
    import subprocess
    import sys

    compiler = shutil.which("g++")
    if compiler is None:
        pytest.fail("this test needs g++ (the native kernel's compiler)")
    log = tmp_path / "calls.log"
    wrapper = tmp_path / "cxx"
    # a compiler that records each call and takes a while, so the builders overlap
    wrapper.write_text(f"#!/bin/sh\necho call >> {log}\nsleep 1\nexec {compiler} \"$@\"\n")
    wrapper.chmod(0o755)
    env = dict(os.environ, CXX=str(wrapper), JAXBODY_CACHE_DIR=str(tmp_path / "cache"))
    code = ("import sys; from jaxbody.backends.native.build import build_library; "
            "print(build_library('extern \"C\" int jb_probe() { return 7; }', 'probe'))")
    procs = [subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True)
             for _ in range(3)]
    paths = {p.communicate(timeout=120)[0].strip() for p in procs}
    assert all(p.returncode == 0 for p in procs)
    assert len(paths) == 1 and os.path.isfile(paths.pop())
    assert log.read_text().split() == ["call"]


def test_sines_of_large_joint_angles():
    """The kernel's vectorised sine/cosine (range reduction by π/2) at angles of many turns,
    and libm's path beyond 1e5 rad, give the vectorised kernel's accelerations."""
    from _support.random_models import hinge_chain

    model = hinge_chain(4)
    rng = np.random.default_rng(9)
    base = rng.uniform(-3.0, 3.0, (8, 4))
    for offset in (0.0, 2.0e3 * np.pi + 0.3, 7.0e4, 3.0e5):
        q = jnp.asarray(base + offset)
        v = jnp.asarray(rng.standard_normal((8, 4)))
        run = lambda kernel: jax.jit(jax.vmap(lambda q, v: backends.acceleration(model, q, v, gravity=model.gravity, kernel=kernel)))(q, v)  # noqa: E731
        a, b = run("native"), run("vectorised")
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-10 * float(jnp.max(jnp.abs(b))), offset


def test_float32_sines_over_many_turns(monkeypatch):
    """Single precision has its own (shorter) sine/cosine polynomials: accelerations of a hinge
    chain in float32 stay within float32 rounding of float64 at the same angles, over 4096
    angles spread across ±200 rad (full SIMD blocks and a partial one). Built at -O2: the range
    reduction's accuracy needs the fused multiply-adds the optimiser makes (the suite builds at
    -O0); the chain's own body names give it kernels of its own, built here."""
    monkeypatch.setenv("JAXBODY_NATIVE_OPTIMISATION", "-O2")
    rng = np.random.default_rng(12)
    q32 = jnp.asarray(rng.uniform(-200.0, 200.0, (4093, 3)), jnp.float32)
    v32 = jnp.asarray(rng.standard_normal((4093, 3)), jnp.float32)

    def hinge_chain(n, dtype):
        b = jb.ModelBuilder()
        for k in range(n):
            b.add_body(f"sines{k}", None if k == 0 else f"sines{k - 1}", pos=(0.0, 0.0, 0.0 if k == 0 else -0.3),
                       mass=1.0 + 0.1 * k, com=(0.01, 0.0, -0.15), inertia=(0.01, 0.01, 0.002),
                       joints=[jb.Hinge(axis=(0, 1, 0))])
        return b.build(dtype=dtype)

    def run(dtype):
        model = hinge_chain(3, dtype=dtype)
        fn = jax.jit(jax.vmap(lambda q, v: backends.acceleration(model, q, v, gravity=model.gravity, kernel="native")))
        return np.asarray(fn(q32.astype(dtype), v32.astype(dtype)), np.float64)

    a32, a64 = run(jnp.float32), run(jnp.float64)
    scale = np.max(np.abs(a64), axis=1, keepdims=True)
    assert np.max(np.abs(a32 - a64) / scale) < 2e-5


def _mujoco_energies(xml, q, v):
    """MuJoCo's ``mj_energyVel`` and ``mj_energyPos`` (gravity and joint springs) per state."""
    m = mujoco.MjModel.from_xml_string(xml)
    D = mujoco.mjtDisableBit
    m.opt.disableflags |= int(D.mjDSBL_CONSTRAINT | D.mjDSBL_CONTACT | D.mjDSBL_ACTUATION)
    m.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    d = mujoco.MjData(m)
    out = []
    for i in range(q.shape[0]):
        d.qpos[:], d.qvel[:] = q[i], v[i]
        mujoco.mj_forward(m, d)
        mujoco.mj_energyPos(m, d)
        mujoco.mj_energyVel(m, d)
        out.append((d.energy[1], d.energy[0]))
    return np.array(out)


@pytest.mark.parametrize("kernel", ["native", "unrolled"])
def test_scene_energies_from_the_straight_line_kernels_equal_mujoco(kernel):
    """A scene on the native or unrolled kernel evaluates its kinetic energy, gravity and
    joint-spring potentials with the kernel's own straight-line program (one native call for
    a batch of states): against MuJoCo's energies on a random tree with every joint kind and
    springs on every joint (free root, ball joints: springs on the rotation vector)."""
    from _support.mjcf_random import random_mjcf

    xml = random_mjcf(0, springs=True)
    model = jb.from_mjcf(xml)
    assert model.joints.nv > 6 and bool(jnp.any(model.joint_stiffness > 0))
    scene = jb.scene(model, kernel=kernel)
    assert scene._kernel_energies(jnp.asarray(model.qpos0), jnp.zeros(model.nv)) is not None
    rng = np.random.default_rng(3)
    q, v = _states(model, rng, 7)
    ref = _mujoco_energies(xml, np.asarray(q), np.asarray(v))
    kinetic = jax.jit(jax.vmap(scene.kinetic_energy))(q, v)
    total = jax.jit(jax.vmap(scene.total_energy))(q, v)
    assert np.allclose(np.asarray(kinetic), ref[:, 0], rtol=1e-11, atol=0)
    scale = np.max(np.abs(ref[:, 1])) + np.max(ref[:, 0])
    assert np.max(np.abs(np.asarray(total) - ref.sum(axis=1))) <= 1e-11 * scale
    # the vectorised kernel's scene keeps its own kinematics (derivatives of the native energies:
    # test_native_energies_derivatives_and_float32)
    assert jb.scene(model, kernel="vectorised")._kernel_energies(q[0], v[0]) is None


def test_native_energies_derivatives_and_float32(models_dir):
    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    rng = np.random.default_rng(5)
    q, v = _states(model, rng, 1)
    k = jnp.asarray(rng.uniform(0.5, 2.0, model.joints.n_joint))
    r = jnp.asarray(model.qpos0) + 0.1

    def total(q, v, mass, k):
        m = eqx.tree_at(lambda m: m.body_mass, model, mass)
        return sum(native.energies(m, q, v, gravity=model.gravity, stiffness=k, reference=r))

    check_grads(jax.jit(total), (q[0], v[0], model.body_mass, k), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)
    # float32: a batch of 40 states (two blocks of 16 lanes and a partial one) within 1e-5
    m32 = jb.from_mjcf(str(models_dir / "panda.xml"), dtype=jnp.float32)
    qs, vs = _states(model, rng, 40)
    e64 = jax.jit(jax.vmap(lambda q, v: jnp.stack(native.energies(model, q, v, gravity=model.gravity))))(qs, vs)
    e32 = jax.jit(jax.vmap(lambda q, v: jnp.stack(native.energies(m32, q, v, gravity=m32.gravity))))(
        qs.astype(jnp.float32), vs.astype(jnp.float32))
    assert e32.dtype == jnp.float32
    assert float(jnp.max(jnp.abs(e32.astype(jnp.float64) - e64))) <= 1e-5 * float(jnp.max(jnp.abs(e64)))


def test_a_first_solve_builds_its_programs_beside_its_trace(tmp_path, monkeypatch):
    """The native builds a first ``simulate`` needs (the handler, the energy program and the
    one-call solve's program) run in background threads started before the trace, which waits
    for them rather than building anything itself; the second solve of the same scene builds
    nothing."""
    from _support.random_models import random_model

    import subprocess
    import threading

    monkeypatch.setenv("JAXBODY_CACHE_DIR", str(tmp_path))
    compiled = []
    popen = subprocess.Popen

    def recording(cmd, *args, **kwargs):
        compiled.append(threading.current_thread().name)
        return popen(cmd, *args, **kwargs)

    monkeypatch.setattr(subprocess, "Popen", recording)
    # a tree no other test builds: its kernels are new to this process
    model = random_model(4711, n_body=2, kinds=("hinge", "slide"))
    scene = jb.scene(model, kernel="native")
    q0, v0 = jnp.asarray(model.qpos0), jnp.ones(model.nv)
    sol = jb.simulate(scene, q0, v0, 0.2, saveat=diffrax.SaveAt(t1=True))
    assert sol.kernel == "native" and bool(sol.success)
    assert len(compiled) >= 2 and all(name.startswith("jaxbody-build") for name in compiled), compiled
    built = sorted(p.name.split("_")[0] + "_" + p.name.split("_")[1] for p in (tmp_path / "native").glob("*.so"))
    assert "adaptive_tsit5" in built and "energy_" + native.build_for(native.WIDE_BATCH) in built, built
    count = len(compiled)
    jb.simulate(scene, q0, 0.5 * v0, 0.2, saveat=diffrax.SaveAt(t1=True))
    assert len(compiled) == count


def test_a_quick_first_build_serves_until_the_optimised_build_replaces_it(tmp_path, monkeypatch):
    """With tiering on (users' default; the suite pins -O0), a program's first build is at -O0
    and runs at once; its -O2 build, made in the background, is registered under the same key,
    so the compiled XLA program that calls it runs the optimised code from then on, unchanged
    and not compiled again, with the same numbers."""
    import threading
    import uuid

    from jaxbody import cxx, ffi_targets, tiered_compilation

    monkeypatch.setenv("JAXBODY_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv(cxx.LEVEL_SWITCH, raising=False)
    monkeypatch.delenv(tiered_compilation.ENV_SWITCH, raising=False)
    assert tiered_compilation.native_enabled()
    # a tree no other test builds (its name is part of the library's identity)
    b, upper = jb.ModelBuilder(), f"upper_{uuid.uuid4().hex[:8]}"
    b.add_body(upper, mass=1.0, com=(0.0, 0.0, -0.25), inertia=(0.01, 0.01, 0.001), joints=[jb.Hinge(axis=(0, 1, 0))])
    b.add_body("lower", upper, pos=(0, 0, -0.5), mass=0.7, com=(0.0, 0.0, -0.2), inertia=(0.008, 0.008, 0.001),
               joints=[jb.Hinge(axis=(1, 0, 0))])
    model = b.build()
    # the optimised build waits for this test's signal: what runs before it is the quick build
    release = threading.Event()
    optimise = native.build.Kernel._optimise
    monkeypatch.setattr(native.build.Kernel, "_optimise", lambda self, build: (release.wait(60), optimise(self, build)))
    q, v, tau = jnp.asarray([0.3, -0.4]), jnp.asarray([0.5, 0.2]), jnp.asarray([0.1, -0.2])
    program = jax.jit(lambda q, v, tau: backends.acceleration(model, q, v, tau, kernel="native"))

    def registration():  # how a stored program would register the kernel it calls again
        (call,) = [c for c in ffi_targets.needed(program.lower(q, v, tau).as_text()) if c[1] == "register_program"]
        return call[2]

    quick = program(q, v, tau)
    final, dtype = registration()
    stem = pathlib.Path(final).name.rsplit("_", 1)[0]
    assert not os.path.isfile(final) and len(list((tmp_path / "native").glob(f"{stem}_*.so"))) == 1
    # meanwhile a stored program that calls it runs the quick build in this process (another
    # process, where it is not registered, traces the program again, which builds it:
    # test_program_store.py::test_a_later_process_runs_the_stored_programs_without_tracing)
    key = native.build.register_program(final, dtype)
    assert f"kernel = {key} : i64" in program.lower(q, v, tau).as_text()
    release.set()
    native.build.wait_for_optimised_builds()
    # the quick build and the optimised one, registered in its place
    assert os.path.isfile(final) and len(list((tmp_path / "native").glob(f"{stem}_*.so"))) == 2
    assert native.build.register_program(final, dtype) == key
    optimised = program(q, v, tau)
    assert program._cache_size() == 1  # the same XLA program
    reference = backends.acceleration(model, q, v, tau, kernel="vectorised")
    np.testing.assert_allclose(quick, reference, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(optimised, reference, rtol=1e-12, atol=1e-12)
