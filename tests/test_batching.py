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
