"""The public joint-space functions (dynamics.py): one compiled program for eager calls,
passive forces against MuJoCo's ``mj_inverse``, the same functions serving planar systems, and
keyword-only options."""

import inspect

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb

from _support.random_models import random_model, random_state



def test_eager_calls_run_one_compiled_program(monkeypatch):
    # A notebook calls the public functions eagerly, state after state. The first call for a
    # model structure traces and compiles the checks and the dynamics; later calls, with new
    # states and new parameter values, run no Python of either (they were op by op before:
    # hundreds of operations a call). The values stay those of the kernels, errors still name
    # the input at the call.
    from jaxbody import dynamics, validation

    traced = {"dynamics": 0, "checks": 0}
    inverse, check = dynamics._inverse_dynamics, validation._parameter_check

    def counted_inverse(*args):
        traced["dynamics"] += 1
        return inverse(*args)

    def counted_check(system):
        traced["checks"] += 1
        return check(system)

    monkeypatch.setattr(dynamics, "_inverse_dynamics", counted_inverse)
    monkeypatch.setattr(validation, "_parameter_check", counted_check)
    model = random_model(3, n_body=3)
    heavier = eqx.tree_at(lambda m: m.body_mass, model, model.body_mass * 1.7)
    for i, m in enumerate((model, heavier, model)):
        q, v, a = random_state(m, 10 + i)
        got = jb.inverse_dynamics(m, q, v, a)
        ref = jb.kernels.inverse_dynamics(m, jb.compute_data(m, q, v), a)
        np.testing.assert_allclose(got, ref, rtol=1e-13, atol=1e-13)
    assert traced == {"dynamics": 1, "checks": 1}
    # a bad value is still reported eagerly, naming the input or the parameter
    with pytest.raises(ValueError, match="a contains NaN or inf"):
        jb.inverse_dynamics(model, q, v, a.at[0].set(jnp.nan))
    with pytest.raises(ValueError, match="body_mass is negative"):
        jb.inverse_dynamics(eqx.tree_at(lambda m: m.body_mass, model, -model.body_mass), q, v, a)
    # a planar system's functions too
    from jaxbody import planar
    from jaxbody.examples import telegin

    planar_traces = []
    planar_mass_matrix = planar.mass_matrix
    monkeypatch.setattr(planar, "mass_matrix", lambda *a: planar_traces.append(1) or planar_mass_matrix(*a))
    system = telegin.three_link_manipulator()
    for angles in (np.array([0.1, 0.2, 0.3]), np.array([0.4, -0.2, 1.0])):
        np.testing.assert_allclose(jb.mass_matrix(system, angles), planar_mass_matrix(system, jnp.asarray(angles)),
                                   rtol=1e-14)
    assert len(planar_traces) == 1


def test_passive_forces_are_explicit_and_mj_inverse_is_include_passive():
    import mujoco

    xml = """<mujoco><option gravity="0.3 -0.2 -9.81"/><worldbody>
      <body name="a"><joint name="h1" axis="0 1 0" damping="0.7" stiffness="2" springref="0.3"/>
        <inertial pos="0.1 0 -0.3" mass="1.2" diaginertia="0.02 0.03 0.01"/>
        <body name="b" pos="0 0 -0.5"><joint name="h2" axis="1 0 0" damping="0.4" armature="0.05"/>
          <inertial pos="0 0.1 -0.2" mass="0.8" diaginertia="0.01 0.02 0.01"/></body></body>
    </worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:] = [0.4, -0.7]
    d.qvel[:] = [1.1, -0.5]
    d.qacc[:] = [0.3, 2.0]
    mujoco.mj_inverse(m, d)
    model = jb.from_mujoco(m)
    q, v, a = (jnp.asarray(x) for x in (d.qpos, d.qvel, d.qacc))
    with_passive = jb.inverse_dynamics(model, q, v, a, include_passive=True)
    np.testing.assert_allclose(with_passive, d.qfrc_inverse, rtol=1e-12, atol=1e-12)
    without = jb.inverse_dynamics(model, q, v, a)
    np.testing.assert_allclose(without - with_passive, jb.passive_forces(model, q, v), rtol=1e-12)
    # forward dynamics with passive forces inverts inverse dynamics with them, and is what
    # the model's scene (its DynamicalSystem) integrates
    acc = jb.forward_dynamics(model, q, v, with_passive, include_passive=True)
    np.testing.assert_allclose(acc, a, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(jb.scene(model).acceleration(0.0, q, v, with_passive), a, rtol=1e-11, atol=1e-12)


def test_same_functions_serve_planar_systems_or_say_what_to_call():
    s = jb.examples.double_pendulum()
    q, v, a = jnp.array([0.3, -0.2]), jnp.array([0.5, 1.0]), jnp.array([0.1, -0.4])
    np.testing.assert_allclose(jb.mass_matrix(s, q), jb.planar.mass_matrix(s, q))
    np.testing.assert_allclose(jb.bias_forces(s, q, v), jb.planar.bias_forces(s, q, v))
    np.testing.assert_allclose(jb.forward_dynamics(s, q, v, a), jb.planar.forward_dynamics(s, q, v, a))
    np.testing.assert_allclose(jb.inverse_dynamics(s, q, v, a), jb.planar.inverse_dynamics(s, q, v, a))
    np.testing.assert_allclose(jb.kinetic_energy(s, q, v), jb.planar.kinetic_energy(s, q, v))
    np.testing.assert_allclose(jb.potential_energy(s, q), jb.planar.potential_energy(s, q))
    f, m = jb.joint_reactions(s, q, v, a)
    assert f.shape == (2, 2) and m.shape == (2,)
    np.testing.assert_allclose(m, jb.inverse_dynamics(s, q, v, a), rtol=1e-12)  # hinge: moment = drive
    np.testing.assert_allclose(jb.augmented_bodies(s, q).augmented_inertia,
                               jb.planar.augmented_bodies(s, q).augmented_inertia)
    with pytest.raises(ValueError, match=r"passive_forces: a planar system has no joint springs or dampers"):
        jb.passive_forces(s, q, v)
    with pytest.raises(ValueError, match=r"call jaxbody.planar.inverse_dynamics\(system, ..., external_force="):
        jb.inverse_dynamics(s, q, v, a, external=jnp.zeros((2, 6)))
    import jaxtyping

    # the runtime shape checker of the test run would answer first; users see this message
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        with pytest.raises(TypeError, match=r"expected a jaxbody.Model or a jaxbody.planar.PlanarSystem, got "
                                            r"CartPendulum; for a constrained example call its own methods"):
            jb.mass_matrix(jb.examples.cart_pendulum(), q)
    finally:
        jaxtyping.config.update("jaxtyping_disable", False)


def test_public_signatures_have_no_private_or_positional_options():
    assert "_caller" not in inspect.signature(jb.from_mujoco).parameters
    for fn in (jb.inverse_dynamics, jb.forward_dynamics, jb.joint_reactions):
        for name in ("external", "include_passive"):
            if name in inspect.signature(fn).parameters:
                assert inspect.signature(fn).parameters[name].kind is inspect.Parameter.KEYWORD_ONLY
    import jaxbody.dynamics

    for name in jaxbody.dynamics.__all__:
        assert hasattr(jb, name), name
    import types

    modules = {n for n, x in vars(jb).items() if isinstance(x, types.ModuleType)}
    functions = {n for n, x in vars(jb).items() if callable(x) and not isinstance(x, types.ModuleType)}
    assert not (modules & functions - {"simulate"})
