"""The kernels on one computed state (kernels.py, data.py): equal to the convenience functions,
unchecked inside a batch, and the size of the compiled program (linear in the bodies, terms the
joints make zero left out)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxbody as jb

from _support.jaxpr_tools import count_eqns
from _support.random_models import hinge_chain, random_model, random_state


# ----------------------------------------------------------------------------- Data + kernels
def test_kernels_on_data_equal_the_convenience_functions():
    model = random_model(5, n_body=6)
    q, v, a = random_state(model, 1)
    tau = a[::-1]
    ext = jnp.asarray(np.random.default_rng(2).standard_normal((model.n_body, 6)))
    data = jax.jit(jb.compute_data)(model, q, v)
    assert isinstance(data, jb.Data) and isinstance(data, jb.kinematics.Kinematics)
    K = jb.kernels

    # the kernels as they are meant to run: inside one compiled program (a vector field, a loop)
    @jax.jit
    def kernels(data, a, tau, ext):
        return (K.mass_matrix(model, data), K.bias_forces(model, data), K.inverse_dynamics(model, data, a, external=ext),
                K.forward_dynamics(model, data, tau, external=ext), K.joint_reactions(model, data, a),
                K.kinetic_energy(model, data), K.potential_energy(model, data), K.passive_forces(model, data))

    refs = (jb.mass_matrix(model, q), jb.bias_forces(model, q, v), jb.inverse_dynamics(model, q, v, a, external=ext),
            jb.forward_dynamics(model, q, v, tau, external=ext), jb.joint_reactions(model, q, v, a),
            jb.kinetic_energy(model, q, v), jb.potential_energy(model, q), jb.passive_forces(model, q, v))
    pairs = [*zip(kernels(data, a, tau, ext), refs), (data.augmented, jb.augmented_bodies(model, q))]
    for got, ref in pairs:
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-13, atol=1e-13), got, ref)
    # data holds the body velocities: T = ½ vᵀ M v from them
    np.testing.assert_allclose(pairs[5][0], 0.5 * v @ pairs[0][0] @ v, rtol=1e-12)


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
    pacc = jax.jit(jax.vmap(lambda q: planar.acceleration(0.0, q, jnp.zeros(2), None)))(q[:, :2])
    assert bool(jnp.all(jnp.isnan(pacc[1]))) and bool(jnp.all(jnp.isfinite(pacc[0])))


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
