"""Identities of the joint-space dynamics on random trees drawn from a seed.

References that are not the code under test: the kinetic energy summed body by body, the
Christoffel symbols of the mass matrix, energy balance, finite differences.
"""


import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxbody as jb

from _support.jaxpr_tools import count_eqns
from _support.random_models import hinge_chain, random_model, random_state

SEEDS = [0, 1, 2, 3]


@pytest.fixture(scope="module", params=SEEDS)
def model(request):
    return random_model(request.param, n_body=6)


def test_mass_matrix_is_the_jacobian_of_inverse_dynamics(model):
    q, v, a = random_state(model, 11)
    M = jax.jit(jb.mass_matrix)(model, q)
    J = jax.jit(jax.jacfwd(lambda acc: jb.inverse_dynamics(model, q, v, acc)))(a)
    np.testing.assert_allclose(M, J, rtol=1e-12, atol=1e-12 * float(jnp.abs(M).max()))
    np.testing.assert_allclose(M, M.T, atol=1e-14 * float(jnp.abs(M).max()))
    assert float(jnp.linalg.eigvalsh(M).min()) > 0


def test_kinetic_energy_is_half_vMv(model):
    q, v, _ = random_state(model, 12)
    M = jax.jit(jb.mass_matrix)(model, q)
    T = jax.jit(jb.kinetic_energy)(model, q, v)
    np.testing.assert_allclose(0.5 * v @ M @ v, T, rtol=1e-12)


def test_kinetic_energy_from_differentiated_positions(model):
    """T from CM velocities obtained by differentiating positions along q(t) = q ⊕ v t."""
    q, v, _ = random_state(model, 13)

    def com_and_rotation(t):
        qt = jb.integrate_qpos(model, q, v, t)
        kin = jb.forward_kinematics(model, qt)
        return kin.com, kin.body_rotation

    (c, R), (cdot, Rdot) = jax.jit(lambda: jax.jvp(com_and_rotation, (0.0,), (1.0,)))()
    W = Rdot @ jnp.swapaxes(R, -1, -2)  # [ω]×
    w = jnp.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=-1)
    Ic = R @ model.body_inertia @ jnp.swapaxes(R, -1, -2)
    T = 0.5 * jnp.sum(model.body_mass * jnp.sum(cdot**2, -1)) + 0.5 * jnp.sum(w * jnp.einsum("nij,nj->ni", Ic, w))
    T = T + 0.5 * jnp.sum(model.dof_armature * v * v)
    np.testing.assert_allclose(jax.jit(jb.kinetic_energy)(model, q, v), T, rtol=1e-11)


def test_forward_then_inverse_is_identity(model):
    q, v, a = random_state(model, 14)
    tau = jax.jit(jb.inverse_dynamics)(model, q, v, a)
    np.testing.assert_allclose(jax.jit(jb.forward_dynamics)(model, q, v, tau), a, rtol=1e-9, atol=1e-10)


def test_energy_balance_power_equals_dE_dt(model):
    """dE/dt = τ·v − damping power along the exact motion (E includes joint springs)."""
    q, v, _ = random_state(model, 15)
    tau = jnp.asarray(np.random.default_rng(0).standard_normal(model.nv))
    E = lambda q_, v_: jb.kinetic_energy(model, q_, v_) + jb.potential_energy(model, q_)

    @jax.jit
    def rate():
        acc = jb.forward_dynamics(model, q, v, tau + jb.passive_forces(model, q, v))
        return jax.jvp(E, (q, v), (jb.qpos_rate(model, q, v), acc))[1]

    dE = rate()
    power = tau @ v - jnp.sum(model.dof_damping * v * v)
    np.testing.assert_allclose(dE, power, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("seed", [5, 6])
def test_christoffel_form_and_skew_symmetry(seed):
    """Hinge/slide trees: C v = bias(v) − bias(0) with Christoffel C, and Ṁ − 2C skew."""
    model = random_model(seed, n_body=5, kinds=("hinge", "slide", "hinge2", "slide_hinge"), free_root=False)
    q, v, _ = random_state(model, 16)
    dM = jax.jit(jax.jacfwd(lambda x: jb.mass_matrix(model, x)))(q)  # dM[i, j, k] = ∂M_ij/∂q_k
    C = 0.5 * (jnp.einsum("ijk,k->ij", dM, v) + jnp.einsum("ikj,k->ij", dM, v) - jnp.einsum("jki,k->ij", dM, v))
    bias = jax.jit(jb.bias_forces)
    Cv = bias(model, q, v) - bias(model, q, jnp.zeros_like(v))
    np.testing.assert_allclose(C @ v, Cv, rtol=1e-10, atol=1e-11)
    Mdot = jnp.einsum("ijk,k->ij", dM, v)
    S = Mdot - 2 * C
    np.testing.assert_allclose(S, -S.T, atol=1e-11)


def test_joint_reactions_balance_the_momentum_of_each_subsystem(model):
    """F_k = d/dt(momentum of subsystem k) − weight − (nothing else), from CM accelerations."""
    q, v, a = random_state(model, 17)
    F, _ = jax.jit(jb.joint_reactions)(model, q, v, a)

    def com(t):
        # second-order expansion q(t) with q̈ = a: CM positions along the motion
        qt = jb.integrate_qpos(model, q, v * t + 0.5 * a * t * t, 1.0)
        return jb.forward_kinematics(model, qt).com

    acc = jax.jit(jax.jacfwd(jax.jacfwd(com)))(0.0)
    ma = model.body_mass[:, None] * (acc - model.gravity)
    ref = np.asarray(model.tree.subtree_mask, float) @ np.asarray(ma)
    np.testing.assert_allclose(F, ref, rtol=1e-9, atol=1e-9 * float(jnp.abs(ref).max()))


def test_vmap_and_jit_agree_with_single_calls(model):
    states = [random_state(model, s) for s in range(4)]
    Q = jnp.stack([s[0] for s in states])
    V = jnp.stack([s[1] for s in states])
    fd = jax.jit(jax.vmap(lambda q, v: jb.forward_dynamics(model, q, v)))(Q, V)
    for i, (q, v, _) in enumerate(states):
        ref = jax.jit(jb.forward_dynamics)(model, q, v)
        np.testing.assert_allclose(fd[i], ref, rtol=1e-11, atol=1e-12 * float(jnp.abs(ref).max()))


def test_gradients_wrt_parameters_match_finite_differences():
    model = random_model(7, n_body=4)
    q, v, _ = random_state(model, 18)
    tau = jnp.ones(model.nv)
    fields = ("body_mass", "body_com", "body_inertia")
    x0 = tuple(getattr(model, f) for f in fields)

    def with_fields(xs):
        return eqx.tree_at(lambda m_: tuple(getattr(m_, f) for f in fields), model, xs)

    def fwd(*xs):
        return jb.forward_dynamics(with_fields(xs), q, v, tau)

    def mm(*xs):
        return jb.mass_matrix(with_fields(xs), q)

    # masses, centres of mass and inertias together (one compilation per derivative mode)
    check_grads(jax.jit(mm), x0, order=1, modes=["rev"], eps=1e-6, atol=1e-5, rtol=1e-5)
    check_grads(jax.jit(fwd), x0, order=1, modes=["rev", "fwd"], eps=1e-6, atol=1e-5, rtol=1e-5)


def test_float32_matches_float64_within_float32_tolerance():
    m64 = random_model(8, n_body=6)
    m32 = random_model(8, n_body=6, dtype=jnp.float32)
    assert m32.body_mass.dtype == jnp.float32
    for s in range(3):
        q, v, _ = random_state(m64, s)
        a64 = jax.jit(jb.forward_dynamics)(m64, q, v)
        a32 = jax.jit(jb.forward_dynamics)(m32, q.astype(jnp.float32), v.astype(jnp.float32))
        assert a32.dtype == jnp.float32
        assert bool(jnp.all(jnp.isfinite(a32)))
        err = float(jnp.abs(a32.astype(jnp.float64) - a64).max() / jnp.abs(a64).max())
        assert err < 1e-4, err


@pytest.mark.parametrize("fn", ["mass_matrix", "inverse_dynamics", "forward_dynamics"])
def test_trace_size_does_not_grow_with_body_count(fn):
    def eqns(n):
        model = hinge_chain(n)
        q = jnp.zeros(n)
        if fn == "mass_matrix":
            f = lambda q_: jb.mass_matrix(model, q_)
        elif fn == "inverse_dynamics":
            f = lambda q_: jb.inverse_dynamics(model, q_, q_, q_)
        else:
            f = lambda q_: jb.forward_dynamics(model, q_, q_, q_)
        return count_eqns(jax.make_jaxpr(f)(q).jaxpr)

    # forward_dynamics: trees up to unrolled.MAX_BODIES run the unrolled kernel (a program
    # that grows with the tree, by design, test_backends_unrolled.py bounds it); above it the
    # vectorised kernel, whose solve loops: compare two sizes on that path
    from jaxbody.backends import unrolled

    small = 4 if fn != "forward_dynamics" else unrolled.MAX_BODIES + 4
    assert eqns(small) == eqns(64)


def test_equal_models_share_the_jit_cache():
    f = jax.jit(lambda m, q: jb.mass_matrix(m, q))
    m1, m2 = hinge_chain(3), hinge_chain(3)
    assert m1.tree == m2.tree and hash(m1.joints) == hash(m2.joints)
    np.testing.assert_allclose(f(m1, jnp.zeros(3)), f(m2, jnp.zeros(3)))


def test_bad_state_is_reported():
    model = hinge_chain(2)
    with pytest.raises(ValueError, match=r"q has shape \(3,\), expected \(2,\)"):
        jb.mass_matrix(model, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"v has shape"):
        jb.bias_forces(model, jnp.zeros(2), jnp.zeros(5))
    with pytest.raises(Exception, match="q contains NaN or inf"):
        # a running program's error is raised when its result is read
        jax.jit(lambda q: jb.forward_dynamics(model, q, jnp.zeros(2)))(jnp.array([0.0, jnp.nan])).block_until_ready()
