"""jb.vmap_chunked: same results as jax.vmap, any batch size, differentiable."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb


def f(a, x, y):
    return jnp.sin(a * x) + y**2


@pytest.mark.parametrize("batch", [1, 5, 64, 130])
def test_matches_vmap(batch):
    x = jnp.linspace(0, 1, batch * 3).reshape(batch, 3)
    y = jnp.ones((batch, 3))
    ref = jax.vmap(f, in_axes=(None, 0, 0))(2.0, x, y)
    out = jax.jit(jb.vmap_chunked(f, 16, in_axes=(None, 0, 0)))(2.0, x, y)
    np.testing.assert_allclose(out, ref, rtol=1e-15)


def test_gradient_flows_through_chunks():
    x = jnp.linspace(0, 1, 40).reshape(20, 2)
    g = jax.grad(lambda a: jb.vmap_chunked(lambda a_, x_: jnp.sum(jnp.sin(a_ * x_)), 8, in_axes=(None, 0))(a, x).sum())(1.5)
    np.testing.assert_allclose(g, jnp.sum(x * jnp.cos(1.5 * x)), rtol=1e-13)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="chunk_size must be positive"):
        jb.vmap_chunked(f, 0)
    with pytest.raises(ValueError, match="in_axes entries must be 0 or None"):
        jb.vmap_chunked(f, 4, in_axes=(None, 1, 0))(1.0, jnp.ones((2, 2)), jnp.ones((2, 2)))
    with pytest.raises(ValueError, match="at least one argument must be mapped"):
        jb.vmap_chunked(f, 4, in_axes=None)(1.0, 2.0, 3.0)


def test_devices_option_splits_the_batch_and_checks_sizes():
    x = jnp.linspace(0, 1, 24).reshape(8, 3)
    ref = jax.vmap(f, in_axes=(None, 0, 0))(2.0, x, x)
    out = jax.jit(jb.vmap_chunked(f, 2, in_axes=(None, 0, 0), devices=1))(2.0, x, x)
    np.testing.assert_allclose(out, ref, rtol=1e-15)
    with pytest.raises(ValueError, match=r"devices requested, \d+ available"):
        jb.vmap_chunked(f, 2, devices=10_000)


def test_two_host_devices_in_a_subprocess():
    """With two CPU devices the sharded result equals vmap and uneven batches are named."""
    import os
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(
        """
        import jax, jax.numpy as jnp, numpy as np
        jax.config.update("jax_enable_x64", True)
        import jaxbody as jb
        assert len(jax.devices()) == 2
        f = lambda a, x: jnp.sin(a * x).sum(-1)
        x = jnp.linspace(0.0, 1.0, 48).reshape(16, 3)
        out = jax.jit(jb.vmap_chunked(f, 4, in_axes=(None, 0), devices=2))(2.0, x)
        np.testing.assert_allclose(out, jax.vmap(f, in_axes=(None, 0))(2.0, x), rtol=1e-14)
        try:
            jb.vmap_chunked(f, 4, in_axes=(None, 0), devices=2)(2.0, x[:5])
        except ValueError as e:
            print(e)
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "vmap_chunked: batch of 5 does not split over 2 devices" in res.stdout


def test_vmap_chunked_compiles_once():
    traces = []

    def f(x):
        traces.append(1)
        return x * 2.0

    g = jb.vmap_chunked(f, 4)
    g(jnp.ones(8))
    g(jnp.ones(8) * 3)
    assert len(traces) == 1
