"""One engine with one state: Data and kernels, the DynamicalSystem protocol, layered errors,
static structure, traversal strategies and the size of the compiled program."""

import inspect
import pathlib
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from jaxpr_tools import count_eqns  # noqa: E402
from random_models import hinge_chain, random_model, random_state  # noqa: E402


# ----------------------------------------------------------------------------- Data + kernels
def test_kernels_on_data_equal_the_convenience_functions():
    model = random_model(5, n_body=6)
    q, v, a = random_state(model, 1)
    tau = a[::-1]
    ext = jnp.asarray(np.random.default_rng(2).standard_normal((model.n_body, 6)))
    data = jax.jit(jb.compute_data)(model, q, v)
    assert isinstance(data, jb.Data) and isinstance(data, jb.kinematics.Kinematics)
    K = jb.kernels
    pairs = [
        (K.mass_matrix(model, data), jb.mass_matrix(model, q)),
        (K.bias_forces(model, data), jb.bias_forces(model, q, v)),
        (K.inverse_dynamics(model, data, a, external=ext), jb.inverse_dynamics(model, q, v, a, external=ext)),
        (K.forward_dynamics(model, data, tau, external=ext), jb.forward_dynamics(model, q, v, tau, external=ext)),
        (K.joint_reactions(model, data, a), jb.joint_reactions(model, q, v, a)),
        (K.kinetic_energy(model, data), jb.kinetic_energy(model, q, v)),
        (K.potential_energy(model, data), jb.potential_energy(model, q)),
        (K.passive_forces(model, data), jb.passive_forces(model, q, v)),
        (data.augmented, jb.augmented_bodies(model, q)),
    ]
    for got, ref in pairs:
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-13, atol=1e-13), got, ref)
    # data holds the body velocities: T = ½ vᵀ M v from them
    np.testing.assert_allclose(
        K.kinetic_energy(model, data), 0.5 * v @ K.mass_matrix(model, data) @ v, rtol=1e-12
    )


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


def test_model_scene_is_a_dynamical_system():
    model = random_model(3, n_body=5)
    q, v, a = random_state(model, 4)
    system = jb.scene(model)  # a Model is data; its scene carries the protocol
    for name in ("nq", "nv", "qdot", "acceleration", "total_energy"):
        assert hasattr(system, name)
    np.testing.assert_allclose(system.qdot(q, v), jb.qpos_rate(model, q, v))
    np.testing.assert_allclose(
        system.acceleration(0.0, q, v, a),
        jb.forward_dynamics(model, q, v, a + jb.passive_forces(model, q, v)),
        rtol=1e-12, atol=1e-12,
    )
    np.testing.assert_allclose(
        system.total_energy(q, v), jb.kinetic_energy(model, q, v) + jb.potential_energy(model, q), rtol=1e-13
    )
    s = jb.examples.double_pendulum()
    assert s.acceleration(0.0, jnp.array([0.3, 0.1]), jnp.zeros(2), None).shape == (2,)


def test_unchecked_kernels_keep_a_batch_alive():
    """A NaN member of a vmapped batch gives NaN for itself only: no raise in the kernels."""
    model = hinge_chain(3)
    q = jnp.array([[0.1, 0.2, 0.3], [jnp.nan, 0.0, 0.0], [0.3, -0.2, 0.1]])
    v = jnp.zeros((3, 3))

    system = jb.scene(model)

    def field(q, v):
        return system.acceleration(0.0, q, v, None), jb.kernels.mass_matrix(model, jb.compute_data(model, q, v))

    acc, M = jax.jit(jax.vmap(field))(q, v)
    assert bool(jnp.all(jnp.isnan(acc[1])))
    assert bool(jnp.all(jnp.isfinite(acc[0]))) and bool(jnp.all(jnp.isfinite(acc[2])))
    np.testing.assert_allclose(acc[0], jb.forward_dynamics(model, q[0], v[0], include_passive=True), rtol=1e-12)
    assert bool(jnp.all(jnp.isfinite(M[2])))
    planar = jb.examples.double_pendulum()
    pacc = jax.vmap(lambda q: planar.acceleration(0.0, q, jnp.zeros(2), None))(q[:, :2])
    assert bool(jnp.all(jnp.isnan(pacc[1]))) and bool(jnp.all(jnp.isfinite(pacc[0])))


# ----------------------------------------------------------------------------- errors
def test_boundary_messages_name_the_input_at_fault():
    model = hinge_chain(2)
    q, v = jnp.array([0.1, 0.2]), jnp.zeros(2)
    # eager calls: plain ValueErrors; under (filter_)jit: EquinoxRuntimeError, same text
    with pytest.raises(ValueError, match="^tau contains NaN or inf$"):
        jb.forward_dynamics(model, q, v, jnp.array([jnp.nan, 0.0]))
    with pytest.raises(eqx.EquinoxRuntimeError, match="tau contains NaN or inf"):
        eqx.filter_jit(jb.forward_dynamics)(model, q, v, jnp.array([jnp.nan, 0.0]))
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
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"joint 1 \('link1_hinge0'\): dof_damping is not finite"):
        eqx.filter_jit(lambda m: jb.mass_matrix(m, q))(bad)
    bad = eqx.tree_at(lambda m: m.body_com, model, model.body_com.at[0, 2].set(jnp.nan))
    with pytest.raises(ValueError, match=r"body 0 \('link0'\): body_com is not finite"):
        jb.check_inputs(bad)
    # planar systems: same boundary, their own parameter names
    s = jb.examples.double_pendulum()
    with pytest.raises(ValueError, match=r"q contains NaN or inf"):
        jb.check_inputs(s, q=jnp.array([jnp.nan, 0.0]))
    bad = eqx.tree_at(lambda m: m.body_mass, s, jnp.array([1.0, -0.6]))
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"planar body 1 \('link2'\): body_mass is negative"):
        eqx.filter_jit(lambda s: jb.check_inputs(s, q=jnp.zeros(2)))(bad)
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


def test_builder_rejects_a_moving_body_without_inertia_as_mujoco_does():
    b = jb.ModelBuilder()
    b.add_body("p", mass=1.0, com=(0, 0, -1), inertia=(0.0, 0.0, 0.0), joints=[jb.Hinge()])
    with pytest.raises(ValueError, match=r"body 0 \('p'\) moves \(has joints\) but a principal moment of "
                                         r"inertia is not positive \(principal moments \[0.0, 0.0, 0.0\]\)"):
        b.build()
    # a moving body that carries a welded child with inertia is fine (MuJoCo accepts it too)
    b = jb.ModelBuilder()
    b.add_body("p", mass=1.0, com=(0, 0, -1), inertia=(0.0, 0.0, 0.0), joints=[jb.Hinge()])
    b.add_body("w", "p", mass=1.0, inertia=(0.1, 0.1, 0.1))
    b.build()


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


# ----------------------------------------------------------------------------- static structure
def test_static_structure_is_immutable():
    model = hinge_chain(3)
    with pytest.raises(AttributeError, match="JointLayout is immutable"):
        model.joints.nv = 5
    with pytest.raises(AttributeError, match="BodyTree is immutable"):
        model.tree.traversal = "segment"
    with pytest.raises(ValueError, match=r"body tree: unknown traversal 'sparse'; choose from \('dense', 'segment'\)"):
        jb.BodyTree([-1, 0], traversal="sparse")
    assert jb.BodyTree([-1, 0]) != jb.BodyTree([-1, 0], traversal="segment")
    assert jb.BodyTree([-1] + list(range(300))).traversal == "segment"


@pytest.mark.slow  # 25 s; the segment-sum traversal serves trees of more than 256 bodies
def test_segment_sum_traversal_equals_dense():
    dense = random_model(11, n_body=7)
    seg = random_model(11, n_body=7, traversal="segment")
    assert seg.tree.traversal == "segment" and seg.joints.frame_tree.traversal == "segment"
    q, v, a = random_state(dense, 2)
    ext = jnp.asarray(np.random.default_rng(5).standard_normal((7, 6)))
    for fn in (
        lambda m: jb.mass_matrix(m, q),
        lambda m: jb.inverse_dynamics(m, q, v, a, external=ext),
        lambda m: jb.forward_dynamics(m, q, v, a, include_passive=True),
        lambda m: jb.joint_reactions(m, q, v, a),
        lambda m: jb.kinetic_energy(m, q, v),
        lambda m: jb.augmented_bodies(m, q),
    ):
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12), jax.jit(fn)(seg), jax.jit(fn)(dense))
    tree = jb.BodyTree([-1, 0, 0, 1, -1, 4, 3], traversal="segment")
    x = jnp.asarray(np.random.default_rng(0).standard_normal((7, 2)))
    d = tree.with_traversal("dense")
    for name in ("subtree_sum", "path_sum", "children_sum"):
        np.testing.assert_allclose(getattr(tree, name)(x), getattr(d, name)(x), atol=1e-14)


def test_compiled_program_grows_at_most_linearly_with_bodies():
    """Lowered HLO of forward dynamics: no n × n constants baked in (8 → 200 bodies)."""

    def size(n):
        model = hinge_chain(n)
        q = jnp.zeros(n)
        f = lambda m, q, v, t: jb.kernels.forward_dynamics(m, jb.compute_data(m, q, v), t)
        return len(jax.jit(f).lower(model, q, q, q).as_text())

    small, large = size(8), size(200)
    # linear growth bounds the ratio by 200 / 8 = 25; the index vectors make it far smaller
    # (the dense masks baked as constants made it about 70)
    assert large / small < 3.0, (small, large)


def test_vmap_chunked_compiles_once():
    traces = []

    def f(x):
        traces.append(1)
        return x * 2.0

    g = jb.vmap_chunked(f, 4)
    g(jnp.ones(8))
    g(jnp.ones(8) * 3)
    assert len(traces) == 1


def _explicit_zero_bias(model, data):
    """Statement 1 at a = 0 with every optional term passed as explicit zero arrays."""
    from jaxbody.kinematics import body_accelerations

    motion = body_accelerations(model, data, data.v, jnp.zeros_like(data.v))
    zero = jnp.zeros_like(data.base_point)
    aug = data.augmented
    f = jb.spatial.relative_force_factors(
        model.tree, aug.subtree_mass, aug.static_moment, aug.augmented_inertia, data.link,
        motion.angular_velocity, motion.angular_acceleration, zero, zero, zero, model.gravity, zero, zero,
    )
    return jb.kernels.project_force_factors(model, data, f)


def test_terms_the_joints_make_zero_are_left_out_of_the_program():
    """Without slides, bodies with several joints or a free joint, the relative pole motion
    and the carrier acceleration are identically zero: the kernel leaves them out of the
    traced program (fewer equations) and gives the same bias as the explicit-zero path;
    ``gravity=False`` drops gravity from the program too."""
    model = hinge_chain(6)
    q, v, _ = random_state(model, 3)
    data = jb.compute_data(model, q, v)
    bias = jb.kernels.bias_forces(model, data)
    np.testing.assert_allclose(bias, _explicit_zero_bias(model, data), rtol=1e-12, atol=1e-12)

    def count(f):
        return count_eqns(jax.make_jaxpr(f)(q, v).jaxpr)

    specialised = count(lambda q, v: jb.kernels.bias_forces(model, jb.compute_data(model, q, v)))
    explicit = count(lambda q, v: _explicit_zero_bias(model, jb.compute_data(model, q, v)))
    no_gravity = count(lambda q, v: jb.kernels.bias_forces(model, jb.compute_data(model, q, v), gravity=False))
    assert specialised < explicit
    assert no_gravity < specialised
    # gravity=False is the bias of the same model with zero gravity
    zero_g = eqx.tree_at(lambda m: m.gravity, model, jnp.zeros(3))
    np.testing.assert_allclose(
        jb.kernels.bias_forces(model, data, gravity=False), jb.kernels.bias_forces(zero_g, data), rtol=1e-12, atol=1e-12
    )
