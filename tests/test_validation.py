"""Parameter and input checks (validation.py): messages that name the input, the body or the
joint at fault, eagerly and under ``jit``, for spatial models and planar systems."""

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest

import jaxbody as jb

from _support.random_models import hinge_chain
from test_model import good_builder

# a failed run-time check: JAX's runtime error, or a ValueError from a compiled program's fast path
FAILED = (jax.errors.JaxRuntimeError, ValueError)



def test_nan_parameters_in_a_model_are_reported_by_field():
    model = good_builder().build()
    bad = jax.tree_util.tree_map(lambda x: x, model)
    import equinox as eqx

    bad = eqx.tree_at(lambda m: m.body_mass, model, jnp.array([jnp.nan]))
    with pytest.raises(ValueError, match=r"body 0 \('base'\): body_mass is not finite"):
        jb.validate_parameters(bad)


# ----------------------------------------------------------------------------- errors
def test_boundary_messages_name_the_input_at_fault():
    model = hinge_chain(2)
    q, v = jnp.array([0.1, 0.2]), jnp.zeros(2)
    # eager calls: plain ValueErrors; under (filter_)jit JAX's runtime error carries the same text
    # on its first line, and under vmap it names the batch member (raised when the result is
    # read, as any error of a running program)
    with pytest.raises(ValueError, match="^tau contains NaN or inf$"):
        jb.forward_dynamics(model, q, v, jnp.array([jnp.nan, 0.0]))
    with pytest.raises(FAILED, match=r"^INVALID_ARGUMENT: tau contains NaN or inf(\n|$)"):
        jax.block_until_ready(eqx.filter_jit(jb.forward_dynamics)(model, q, v, jnp.array([jnp.nan, 0.0])))
    taus = jnp.array([[0.0, 0.0], [0.0, 0.0], [jnp.nan, 0.0]])
    with pytest.raises(FAILED, match=r"^INVALID_ARGUMENT: tau contains NaN or inf \(batch member 2 of 3\)(\n|$)"):
        jax.block_until_ready(jax.jit(jax.vmap(lambda t: jb.forward_dynamics(model, q, v, t)))(taus))
    # an eager vmap over concrete inputs: a plain error naming the member, before anything runs
    with pytest.raises(ValueError, match=r"^tau contains NaN or inf \(batch member 2 of 3\)"):
        jax.vmap(lambda t: jb.forward_dynamics(model, q, v, t))(taus)
    with pytest.raises(ValueError, match="^v contains NaN or inf$"):
        jb.forward_dynamics(model, q, jnp.array([0.0, jnp.inf]))
    with pytest.raises(ValueError, match="^a contains NaN or inf$"):
        jb.inverse_dynamics(model, q, v, jnp.array([jnp.nan, 0.0]))
    with pytest.raises(ValueError, match="^external contains NaN or inf$"):
        jb.inverse_dynamics(model, q, v, v, external=jnp.full((2, 6), jnp.nan))
    with pytest.raises(ValueError, match=r"tau has shape \(3,\), expected \(2,\)"):
        jb.forward_dynamics(model, q, v, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"external has shape \(2, 3\), expected \(2, 6\)"):
        jb.inverse_dynamics(model, q, v, v, external=jnp.zeros((2, 3)))
    # parameters set after building (eqx.tree_at) are checked at the boundary, naming the body
    bad = eqx.tree_at(lambda m: m.body_mass, model, jnp.array([1.0, -0.5]))
    with pytest.raises(ValueError, match=r"^body 1 \('link1'\): body_mass is negative$"):
        jb.forward_dynamics(bad, q, v)
    bad = eqx.tree_at(lambda m: m.dof_damping, model, jnp.array([0.0, jnp.nan]))
    with pytest.raises(FAILED, match=r"^INVALID_ARGUMENT: joint 1 \('link1_hinge0'\): dof_damping is not finite"):
        jax.block_until_ready(eqx.filter_jit(lambda m: jb.mass_matrix(m, q))(bad))
    # a batch of models: the member whose parameter is bad
    masses = jnp.array([[1.0, 1.0], [1.0, 1.0], [1.0, -2.0]])
    with pytest.raises(FAILED, match=r"^INVALID_ARGUMENT: body 1 \('link1'\): body_mass is negative \(batch member 2 of 3\)"):
        jax.block_until_ready(jax.jit(jax.vmap(lambda m: jb.mass_matrix(eqx.tree_at(lambda x: x.body_mass, model, m), q)))(masses))
    bad = eqx.tree_at(lambda m: m.body_com, model, model.body_com.at[0, 2].set(jnp.nan))
    with pytest.raises(ValueError, match=r"body 0 \('link0'\): body_com is not finite"):
        jb.check_inputs(bad)
    # planar systems: same boundary, their own parameter names
    s = jb.examples.double_pendulum()
    with pytest.raises(ValueError, match=r"q contains NaN or inf"):
        jb.check_inputs(s, q=jnp.array([jnp.nan, 0.0]))
    bad = eqx.tree_at(lambda m: m.body_mass, s, jnp.array([1.0, -0.6]))
    with pytest.raises(FAILED, match=r"^INVALID_ARGUMENT: planar body 1 \('link2'\): body_mass is negative"):
        jax.block_until_ready(eqx.filter_jit(lambda s: jb.check_inputs(s, q=jnp.zeros(2)))(bad))
    # no input given: the check travels with the masses
    with pytest.raises(FAILED, match=r"^INVALID_ARGUMENT: planar body 1 \('link2'\): body_mass is negative"):
        jax.block_until_ready(jax.jit(lambda s: jb.check_inputs(s)[0].body_mass)(bad))
    with pytest.raises(ValueError, match=r"planar system: tau has shape \(3,\), expected \(2,\)"):
        jb.check_inputs(s, tau=jnp.zeros(3))
    with pytest.raises(ValueError, match=r"planar system: external loads are external_force \(n_body, 2\)"):
        jb.check_inputs(s, external=jnp.zeros((2, 6)))


def test_check_inputs_returns_checked_values_and_passes_good_ones():
    model = hinge_chain(2)
    q, v, tau = jnp.array([0.1, 0.2]), jnp.array([1, 2]), jnp.zeros(2)
    out = jax.jit(lambda m, q, v, t: jb.check_inputs(m, q=q, v=v, tau=t))(model, q, v, tau)
    assert len(out) == 4 and out[0] == model and out[2].dtype == model.body_mass.dtype
    assert jb.check_inputs(model, q=q)[1].shape == (2,)
