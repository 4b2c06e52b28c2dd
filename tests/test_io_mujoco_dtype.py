"""`from_mjcf`/`from_urdf`/`from_mujoco` refuse float64 when JAX runs without x64.

JAX narrows a requested float64 to float32 silently (a warning at most) when
``jax_enable_x64`` is off; a model loaded that way would run in float32 while its user
believes in float64 results. The loaders raise instead. The test suite itself runs with x64
on (conftest), so the check runs in a fresh interpreter without it.
"""

import os
import subprocess
import sys
import textwrap

import jax.numpy as jnp
import pytest

from jaxbody.io.mujoco import from_mjcf
from jaxbody._xla import default_xla_flags

PENDULUM = (
    '<mujoco model="p"><worldbody><body name="b"><joint name="j" type="hinge" axis="0 1 0"/>'
    '<inertial pos="0 0 -0.5" mass="1" diaginertia="0.1 0.1 0.01"/></body></worldbody></mujoco>'
)
URDF = (
    '<robot name="r"><link name="base"/><link name="l"><inertial><origin xyz="0 0 -0.5"/>'
    '<mass value="1"/><inertia ixx="0.1" iyy="0.1" izz="0.01" ixy="0" ixz="0" iyz="0"/>'
    '</inertial></link><joint name="j" type="continuous"><parent link="base"/><child link="l"/>'
    '<axis xyz="0 1 0"/></joint></robot>'
)


def _run_without_x64(code):
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["JAX_ENABLE_X64"] = "0"
    env.setdefault("XLA_FLAGS", default_xla_flags())
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True, text=True, timeout=120, env=env,
    )


def test_float64_without_x64_raises_in_a_fresh_process():
    code = f"""
        import warnings
        import jax, jax.numpy as jnp, mujoco, pytest
        import jaxbody as jb
        assert not jax.config.jax_enable_x64
        mjcf, urdf = {PENDULUM!r}, {URDF!r}
        with pytest.raises(ValueError, match=r"from_mjcf: dtype=float64 needs 64-bit JAX, which is off"):
            jb.from_mjcf(mjcf, dtype=jnp.float64)
        with pytest.raises(ValueError, match=r"from_urdf: dtype=float64 needs 64-bit JAX"):
            jb.from_urdf(urdf, dtype="float64")
        with pytest.raises(ValueError, match=r"from_mujoco: dtype=float64 needs 64-bit JAX"):
            jb.from_mujoco(mujoco.MjModel.from_xml_string(mjcf), dtype=jnp.float64)
        # what still works without x64: the default and an explicit float32
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert jb.from_mjcf(mjcf).body_mass.dtype == jnp.float32
            assert jb.from_mjcf(mjcf, dtype=jnp.float32).body_mass.dtype == jnp.float32
        print("checked")
    """
    out = _run_without_x64(code)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().endswith("checked")


def test_non_floating_dtype_raises():
    with pytest.raises(ValueError, match=r"from_mjcf: dtype must be a floating dtype, got int32"):
        from_mjcf(PENDULUM, dtype=jnp.int32)


def test_float64_with_x64_is_float64():
    assert from_mjcf(PENDULUM, dtype=jnp.float64).body_mass.dtype == jnp.float64
    assert from_mjcf(PENDULUM).body_mass.dtype == jnp.float64  # conftest enables x64
