"""The unrolled forward-dynamics kernel against the vectorised one and MuJoCo.

The vectorised kernel agrees with MuJoCo to ~1e-14 (test_mujoco_reference.py); here the
unrolled kernel is compared with both on the shipped robots and on seeded random MJCF trees
with every joint kind, in float64 and float32, single and batched, with derivatives.
"""

import jax
import jax.numpy as jnp
import mujoco
from jax.test_util import check_grads
import numpy as np
import pytest
from jaxpr_tools import count_eqns

import jaxbody as jb
from jaxbody import kernels, unrolled

pytestmark = pytest.mark.filterwarnings("ignore:from_mjcf")


def _state(model, rng, batch=None):
    shape = () if batch is None else (batch,)
    q = np.asarray(model.qpos0) + 0.4 * rng.standard_normal(shape + (model.nq,))
    q = jnp.asarray(q)
    q = jax.vmap(lambda x: jb.kinematics.normalize_qpos(model, x))(q.reshape(-1, model.nq)).reshape(q.shape)
    v = jnp.asarray(rng.standard_normal(shape + (model.nv,)))
    return q, v


@pytest.mark.parametrize("name", ["panda", "ur5e", "anymal_c"])
def test_unrolled_equals_vectorised_and_mujoco(models_dir, name):
    model = jb.from_mjcf(str(models_dir / f"{name}.xml"))
    rng = np.random.default_rng(3)
    q, v = _state(model, rng)
    tau = jnp.asarray(rng.standard_normal(model.nv))
    ext = jnp.asarray(rng.standard_normal((model.n_body, 6)))
    a = {k: kernels.acceleration(model, q, v, tau, gravity=model.gravity, external=ext, kernel=k) for k in ("unrolled", "vectorised")}
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
    from mjcf_random import random_mjcf

    model = jb.from_mjcf(random_mjcf(seed))
    rng = np.random.default_rng(seed)
    q, v = _state(model, rng)
    tau = jnp.asarray(rng.standard_normal(model.nv))
    args = dict(gravity=model.gravity)
    a_u = kernels.acceleration(model, q, v, tau, kernel="unrolled", **args)
    a_v = kernels.acceleration(model, q, v, tau, kernel="vectorised", **args)
    assert float(jnp.max(jnp.abs(a_u - a_v))) <= 1e-9 * float(jnp.max(jnp.abs(a_v)))
    M_u = unrolled.mass_matrix(model, q)
    M_v = kernels.mass_matrix(model, jb.compute_data(model, q))
    assert float(jnp.max(jnp.abs(M_u - M_v))) <= 1e-12 * float(jnp.max(jnp.abs(M_v)))


def test_auto_routes_batches_and_derivatives_consistently(models_dir):
    """``auto``: unrolled for one state, vectorised under vmap; values and derivatives agree."""
    model = jb.from_mjcf(str(models_dir / "panda.xml"))
    rng = np.random.default_rng(5)
    q, v = _state(model, rng, batch=64)

    def f(kernel):
        return lambda q, v: kernels.acceleration(model, q, v, -v, gravity=model.gravity, kernel=kernel)

    a_auto = jax.jit(jax.vmap(f("auto")))(q, v)
    a_vec = jax.jit(jax.vmap(f("vectorised")))(q, v)
    assert float(jnp.max(jnp.abs(a_auto - a_vec))) <= 1e-11 * float(jnp.max(jnp.abs(a_vec)))
    # the batched program is the vectorised kernel (custom_vmap rule), not the unrolled one
    n_auto = count_eqns(jax.make_jaxpr(jax.vmap(f("auto")))(q, v).jaxpr)
    n_unrolled = count_eqns(jax.make_jaxpr(jax.vmap(f("unrolled")))(q, v).jaxpr)
    assert n_auto < n_unrolled
    loss = lambda k: lambda q, v: jnp.sum(jnp.sin(f(k)(q, v)))
    g_auto = jax.vmap(jax.grad(loss("auto"), argnums=(0, 1)))(q[:8], v[:8])
    g_vec = jax.vmap(jax.grad(loss("vectorised"), argnums=(0, 1)))(q[:8], v[:8])
    for x, y in zip(g_auto, g_vec):
        assert float(jnp.max(jnp.abs(x - y))) <= 1e-9 * float(jnp.max(jnp.abs(y)))


def test_unrolled_gradients_match_finite_differences(models_dir):
    model = jb.from_mjcf(str(models_dir / "ur5e.xml"))
    rng = np.random.default_rng(7)
    q, v = _state(model, rng)
    fun = lambda q, v, mass: kernels.acceleration(
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
from jaxbody import kernels
m = jb.from_mjcf({str(models_dir / 'panda.xml')!r})
rng = np.random.default_rng(0)
q = np.asarray(m.qpos0) + 0.4 * rng.standard_normal(m.nq); v = rng.standard_normal(m.nv)
a = kernels.acceleration(m, jnp.asarray(q, jnp.float32), jnp.asarray(v, jnp.float32), gravity=m.gravity, kernel='unrolled')
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
    a64 = np.asarray(kernels.acceleration(model, q, v, gravity=model.gravity, kernel="vectorised"))
    assert np.max(np.abs(a32 - a64)) <= 1e-4 * max(1.0, np.abs(a64).max())


def test_auto_threshold_and_bad_kernel_name():
    from test_scene import chain_model

    assert unrolled.applies(chain_model(unrolled.MAX_BODIES))
    assert not unrolled.applies(chain_model(unrolled.MAX_BODIES + 1))
    with pytest.raises(ValueError, match="kernel must be one of"):
        kernels.acceleration(chain_model(2), jnp.zeros(2), jnp.zeros(2), kernel="fast")
    with pytest.raises(ValueError, match="scene: kernel must be one of"):
        jb.scene(chain_model(2), kernel="fast")
