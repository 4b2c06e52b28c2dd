"""External loads on bodies (MuJoCo ``xfrc_applied``) and deep chains, against MuJoCo."""

import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb

mujoco = pytest.importorskip("mujoco")
sys.path.insert(0, str(pathlib.Path(__file__).parent))
from mjcf_random import random_mjcf  # noqa: E402

RIGID = (
    mujoco.mjtDisableBit.mjDSBL_SPRING
    | mujoco.mjtDisableBit.mjDSBL_DAMPER
    | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    | mujoco.mjtDisableBit.mjDSBL_CONTACT
    | mujoco.mjtDisableBit.mjDSBL_ACTUATION
)


def rel(x, ref):
    ref = np.asarray(ref)
    return float(np.abs(np.asarray(x) - ref).max() / max(np.abs(ref).max(), 1e-300))


def mujoco_pair(xml):
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.disableflags |= RIGID
    return m, mujoco.MjData(m), jb.from_mujoco(m)


@pytest.mark.parametrize("seed", [3, 4])
def test_external_loads_match_xfrc_applied(seed):
    m, d, model = mujoco_pair(random_mjcf(seed, n_body=6, rigid_only=True))
    rng = np.random.default_rng(seed)
    q = np.asarray(jb.normalize_qpos(model, jnp.asarray(m.qpos0 + 0.4 * rng.standard_normal(m.nq))))
    v, tau = rng.standard_normal(m.nv), rng.standard_normal(m.nv)
    xfrc = rng.standard_normal((m.nbody - 1, 6))
    d.qpos[:], d.qvel[:], d.qfrc_applied[:] = q, v, tau
    d.xfrc_applied[1:] = xfrc
    mujoco.mj_forward(m, d)
    fwd = jax.jit(lambda m, q, v, t, e: jb.forward_dynamics(m, q, v, t, external=e))
    assert rel(fwd(model, q, v, tau, jnp.asarray(xfrc)), d.qacc) < 1e-9
    a = d.qacc.copy()
    d.qacc[:] = a
    mujoco.mj_inverse(m, d)  # qfrc_inverse = M a + bias = qfrc_applied + Jᵀ xfrc (passive off)
    inv = jax.jit(lambda m, q, v, a, e=None: jb.inverse_dynamics(m, q, v, a, external=e))
    assert rel(inv(model, q, v, jnp.asarray(a)), d.qfrc_inverse) < 1e-10
    assert rel(inv(model, q, v, jnp.asarray(a), jnp.asarray(xfrc)), tau) < 1e-9


def chain_mjcf(n):
    body = ""
    for k in range(n):
        body += (
            f'<body name="l{k}" pos="0 0 {-0.3 if k else 0}">'
            f'<joint type="hinge" axis="{"0 1 0" if k % 2 else "1 0 0"}"/>'
            f'<inertial pos="0.01 0.005 -0.15" mass="{1 + 0.01 * k}" diaginertia="0.01 0.011 0.002"/>'
        )
    body += "</body>" * n
    return f"<mujoco><worldbody>{body}</worldbody></mujoco>"


def test_deep_chain_matches_mujoco():
    """60 links: deep recursion handled by pointer jumping and dense sums, still exact."""
    m, d, model = mujoco_pair(chain_mjcf(60))
    rng = np.random.default_rng(0)
    q, v = 0.3 * rng.standard_normal(m.nv), rng.standard_normal(m.nv)
    d.qpos[:], d.qvel[:] = q, v
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    assert rel(jax.jit(jb.mass_matrix)(model, q), M) < 1e-10
    assert rel(jax.jit(jb.bias_forces)(model, q, v), d.qfrc_bias) < 1e-10
    assert rel(jax.jit(jb.forward_dynamics)(model, q, v), d.qacc) < 1e-8
