"""Augmented body quantities (augmented.py): the traced program does not grow with the body count.

The values against the spec's table T-9a are checked in ``test_spatial.py``."""

import jax.numpy as jnp
import pytest

import jaxbody as jb
from jaxbody.augmented import augmented_inertia, static_moment



@pytest.mark.parametrize("fn", ["static_moment", "augmented_inertia"])
def test_augmented_trace_size_independent_of_body_count(fn):
    import jax

    def eqns(n):
        tree = jb.BodyTree([-1] + list(range(n - 1)))
        args = (jnp.ones(n), jnp.ones((n, 3)), jnp.ones((n, 3)))
        if fn == "static_moment":
            f = lambda m, r, R: static_moment(tree, m, r, R)
        else:
            f = lambda m, r, R: augmented_inertia(tree, m, jnp.broadcast_to(jnp.eye(3), (n, 3, 3)), r, R)
        return len(jax.make_jaxpr(f)(*args).jaxpr.eqns)

    assert eqns(4) == eqns(64)
