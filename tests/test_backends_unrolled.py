"""The unrolled forward-dynamics kernel against the vectorised one and MuJoCo.

The vectorised kernel agrees with MuJoCo to ~1e-14 (test_dynamics_mujoco.py); here the
unrolled kernel is compared with both on the shipped robots and on seeded random MJCF trees
with every joint kind, in float64 and float32, single and batched, with derivatives.
"""

import jax
import jax.numpy as jnp
import mujoco
from jax.test_util import check_grads
import numpy as np
import pytest
from _support.jaxpr_tools import count_eqns

import jaxbody as jb
from jaxbody import backends, kernels
from jaxbody.backends import unrolled

pytestmark = pytest.mark.filterwarnings("ignore:from_mjcf")


def _state(model, rng, batch=None):
    shape = () if batch is None else (batch,)
    q = np.asarray(model.qpos0) + 0.4 * rng.standard_normal(shape + (model.nq,))
    q = jnp.asarray(q)
    q = jax.jit(jax.vmap(lambda x: jb.kinematics.normalize_qpos(model, x)))(q.reshape(-1, model.nq)).reshape(q.shape)
    v = jnp.asarray(rng.standard_normal(shape + (model.nv,)))
    return q, v


@pytest.mark.parametrize("name", ["panda", "ur5e", "anymal_c"])
def test_unrolled_equals_vectorised_and_mujoco(models_dir, name):
    model = jb.from_mjcf(str(models_dir / f"{name}.xml"))
    rng = np.random.default_rng(3)
    q, v = _state(model, rng)
    tau = jnp.asarray(rng.standard_normal(model.nv))
    ext = jnp.asarray(rng.standard_normal((model.n_body, 6)))
    a = {k: backends.acceleration(model, q, v, tau, gravity=model.gravity, external=ext, kernel=k) for k in ("unrolled", "vectorised")}
    scale = float(jnp.max(jnp.abs(a["vectorised"])))
    assert float(jnp.max(jnp.abs(a["unrolled"] - a["vectorised"]))) <= 1e-11 * scale
    # MuJoCo on the same file, rigid body only
    m = mujoco.MjModel.from_xml_path(str(models_dir / f"{name}.xml"))
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = np.asarray(q), np.asarray(v)
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    assert np.allclose(np.asarray(unrolled.mass_matrix(model, q)), M, rtol=1e-12, atol=1e-12 * np.abs(M).max())
    assert np.max(np.abs(np.asarray(unrolled.bias_forces(model, q, v, gravity=model.gravity)) - d.qfrc_bias)) <= 1e-11 * np.abs(d.qfrc_bias).max()


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_unrolled_on_random_trees_with_every_joint_kind(seed):
    from _support.mjcf_random import random_mjcf

    model = jb.from_mjcf(random_mjcf(seed))
    rng = np.random.default_rng(seed)
    q, v = _state(model, rng)
    tau = jnp.asarray(rng.standard_normal(model.nv))
    args = dict(gravity=model.gravity)
    a_u = backends.acceleration(model, q, v, tau, kernel="unrolled", **args)
    a_v = backends.acceleration(model, q, v, tau, kernel="vectorised", **args)
    assert float(jnp.max(jnp.abs(a_u - a_v))) <= 1e-9 * float(jnp.max(jnp.abs(a_v)))
    M_u = unrolled.mass_matrix(model, q)
    M_v = kernels.mass_matrix(model, jb.compute_data(model, q))
    assert float(jnp.max(jnp.abs(M_u - M_v))) <= 1e-12 * float(jnp.max(jnp.abs(M_v)))


@pytest.mark.slow
def test_unrolled_batches_and_derivatives_agree_with_the_vectorised_kernel(models_dir):
    """The unrolled kernel for one state and under vmap: values and derivatives agree with the
    vectorised kernel."""
    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    rng = np.random.default_rng(5)
    q, v = _state(model, rng, batch=64)

    def f(kernel):
        return lambda q, v: backends.acceleration(model, q, v, -v, gravity=model.gravity, kernel=kernel)

    a_auto = jax.jit(jax.vmap(f("unrolled")))(q, v)
    a_vec = jax.jit(jax.vmap(f("vectorised")))(q, v)
    assert float(jnp.max(jnp.abs(a_auto - a_vec))) <= 1e-11 * float(jnp.max(jnp.abs(a_vec)))
    np.testing.assert_allclose(jax.jit(f("unrolled"))(q[0], v[0]), a_vec[0], rtol=1e-11, atol=1e-11)

    def size(fn, *args):
        return count_eqns(jax.make_jaxpr(fn)(*args).jaxpr)

    # the batch and the single state both run the unrolled program
    assert size(jax.vmap(f("unrolled")), q, v) > 2 * size(jax.vmap(f("vectorised")), q, v)
    assert size(f("unrolled"), q[0], v[0]) > 2 * size(f("vectorised"), q[0], v[0])
    loss = lambda k: lambda q, v: jnp.sum(jnp.sin(f(k)(q, v)))
    g_auto = jax.jit(jax.vmap(jax.grad(loss("unrolled"), argnums=(0, 1))))(q[:8], v[:8])
    g_vec = jax.jit(jax.vmap(jax.grad(loss("vectorised"), argnums=(0, 1))))(q[:8], v[:8])
    for x, y in zip(g_auto, g_vec):
        assert float(jnp.max(jnp.abs(x - y))) <= 1e-9 * float(jnp.max(jnp.abs(y)))


def test_unrolled_gradients_match_finite_differences(models_dir):
    model = jb.from_mjcf(str(models_dir / "ur5e.xml"))
    rng = np.random.default_rng(7)
    q, v = _state(model, rng)
    fun = lambda q, v, mass: backends.acceleration(
        eqx_mass(model, mass), q, v, gravity=model.gravity, kernel="unrolled"
    )
    check_grads(fun, (q, v, model.body_mass), order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5)


def eqx_mass(model, mass):
    import equinox as eqx

    return eqx.tree_at(lambda m: m.body_mass, model, mass)


def test_unrolled_float32_within_1e4_of_float64(models_dir):
    import subprocess
    import sys

    code = f"""
import warnings; warnings.simplefilter('ignore')
import jax, jax.numpy as jnp, numpy as np
import jaxbody as jb
from jaxbody import backends
m = jb.from_mjcf({str(models_dir / 'panda.xml')!r})
rng = np.random.default_rng(0)
q = np.asarray(m.qpos0) + 0.4 * rng.standard_normal(m.nq); v = rng.standard_normal(m.nv)
a = backends.acceleration(m, jnp.asarray(q, jnp.float32), jnp.asarray(v, jnp.float32), gravity=m.gravity, kernel='unrolled')
assert a.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(a)))
np.save('/dev/stdout', np.asarray(a, np.float64)) if False else print(' '.join(repr(float(x)) for x in a))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    a32 = np.array([float(x) for x in out.stdout.split()])
    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    rng = np.random.default_rng(0)
    q = np.asarray(model.qpos0) + 0.4 * rng.standard_normal(model.nq)
    v = rng.standard_normal(model.nv)
    a64 = np.asarray(backends.acceleration(model, q, v, gravity=model.gravity, kernel="vectorised"))
    assert np.max(np.abs(a32 - a64)) <= 1e-4 * max(1.0, np.abs(a64).max())


def test_auto_threshold_and_bad_kernel_name():
    from test_scene import chain_model

    assert unrolled.applies(chain_model(unrolled.MAX_BODIES))
    assert not unrolled.applies(chain_model(unrolled.MAX_BODIES + 1))
    with pytest.raises(ValueError, match="kernel must be one of"):
        backends.acceleration(chain_model(2), jnp.zeros(2), jnp.zeros(2), kernel="fast")
    with pytest.raises(ValueError, match="scene: kernel must be one of"):
        jb.scene(chain_model(2), kernel="fast")


@pytest.mark.slow
def test_rk4_writes_its_stages_out_for_the_unrolled_kernel():
    """``"rk4"`` on a scene that runs the unrolled kernel is :class:`RK4Stages` (stages written
    out); it gives the tableau RK4's trajectory and dense output, batched and single."""
    from test_scene import chain_model

    from jaxbody import simulation

    model = chain_model(3, axis=(0.3, -1.0, 0.2), damping=0.05)
    auto, vec = jb.scene(model, kernel="unrolled"), jb.scene(model, kernel="vectorised")
    pick = lambda sc: simulation.choose_solver("rk4", sc, jnp.float64, 1e-8, 1e-8, 1e-3, None)[0].solver
    assert type(pick(auto)) is simulation.RK4Stages
    assert type(pick(vec)) is simulation.RK4
    assert type(pick(jb.scene(chain_model(unrolled.MAX_BODIES + 2), kernel="vectorised"))) is simulation.RK4
    q0, v0 = jnp.array([0.4, -0.3, 0.8]), jnp.array([1.0, 0.5, -2.0])
    run = lambda sc, q, v: jb.simulate(sc, q, v, 0.2, solver="rk4", dt0=1e-3, n_save=5, dense=True)
    s_a, s_v = run(auto, q0, v0), run(vec, q0, v0)
    np.testing.assert_allclose(s_a.q, s_v.q, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(s_a.v, s_v.v, rtol=1e-12, atol=1e-12)
    for t in (0.0123, 0.1337):
        for x, y in zip(s_a.evaluate(t), s_v.evaluate(t)):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)
    qb = q0 + 0.1 * jnp.arange(4.0)[:, None]
    b_a = jax.vmap(lambda q: run(auto, q, v0).q)(qb)
    b_v = jax.vmap(lambda q: run(vec, q, v0).q)(qb)
    np.testing.assert_allclose(b_a, b_v, rtol=1e-12, atol=1e-12)
