"""The hand-derived adjoint of inverse dynamics (trees of hinges and slides).

``jaxbody.backends.scalar.inverse_dynamics_vjp`` gives ``λᵀ ∂τ/∂q`` and ``λᵀ ∂τ/∂v`` of the
Newton–Euler passes in closed form; the native kernel's reverse-mode programs use it in place
of reversing the passes operation by operation. It is checked against JAX's reverse mode
through the same passes (an independent derivation), and the native programs that use it
against the vectorised kernel.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _support.mjcf_random import random_mjcf
from _support.random_models import hinge_chain, random_model, random_state

import jaxbody as jb
from jaxbody import backends
from jaxbody.backends import native, scalar, unrolled
from jaxbody.backends.native import codegen

pytestmark = pytest.mark.filterwarnings("ignore:from_mjcf")

KINDS = ("hinge", "slide", "hinge2", "slide_hinge")


def _models():
    """Branching trees with slides, several joints on a body, armature and rotated frames; MJCF
    trees with two bodies on the world (seed 14: two joints on a body; seed 19: bodies welded to
    their parents); a hinge chain."""
    out = [(f"tree{seed}", random_model(seed, n_body=7, kinds=KINDS, free_root=False)) for seed in range(3)]
    for seed in (14, 19):
        out.append((f"mjcf{seed}", jb.from_mjcf(random_mjcf(seed, n_body=7, free_root=False, n_root=2, max_joints=2))))
    out.append(("chain", hinge_chain(6)))
    return out


@pytest.mark.parametrize("name, model", _models(), ids=[n for n, _ in _models()])
@pytest.mark.parametrize("gravity", [True, False])
def test_adjoint_equals_reverse_mode_through_the_passes(name, model, gravity):
    jax.config.update("jax_enable_x64", True)
    assert scalar.adjoint_applies(model.joints), name
    q, v, a = random_state(model, 5)
    lam = jnp.asarray(np.random.default_rng(6).standard_normal(model.nv))
    g = jnp.asarray(model.gravity) if gravity else None

    def tau(q, v):
        qs, vs, gs, _ = unrolled._scalar_inputs(model, q, v, g, None)
        return jnp.stack(scalar.inverse_dynamics(model, qs, vs, scalar.scalars(a), gs, None))

    q_ref, v_ref = jax.vjp(tau, q, v)[1](lam)
    qs, vs, gs, _ = unrolled._scalar_inputs(model, q, v, g, None)
    q_bar, v_bar = scalar.inverse_dynamics_vjp(model, qs, vs, scalar.scalars(a), gs, scalar.scalars(lam))
    q_bar = jnp.stack([jnp.asarray(x, jnp.float64) for x in q_bar])
    v_bar = jnp.stack([jnp.asarray(x, jnp.float64) for x in v_bar])
    for got, ref in ((q_bar, q_ref), (v_bar, v_ref)):
        assert float(jnp.max(jnp.abs(got - ref))) <= 1e-12 * float(jnp.max(jnp.abs(ref)))


def test_quaternion_joints_keep_reverse_mode():
    """Ball and free joints (a moving reference point) are not served: the programs reverse the
    passes as before (checked in test_backends_native.py on a free base with a ball)."""
    assert not scalar.adjoint_applies(random_model(0, n_body=2, kinds=("ball",)).joints)
    assert not scalar.adjoint_applies(random_model(0, n_body=3, kinds=("hinge",), free_root=True).joints)
    model = random_model(0, n_body=2, kinds=("ball",))
    assert "inverse dynamics" not in codegen.generate(model.tree, model.joints, False, np.float64, "vjp")


def test_reverse_mode_programs_use_it_and_are_shorter(monkeypatch):
    """The reverse-mode programs of a hinge tree contain the hand-derived block, and are shorter
    than the operation-by-operation reverse of the same passes (a 5-link chain: about three
    quarters of the operations)."""
    model = hinge_chain(5)

    def size(mode):
        return sum(1 for line in codegen.generate(model.tree, model.joints, False, np.float64, mode).splitlines() if "const U" in line)

    hand = {mode: size(mode) for mode in ("vjp", "rk4_vjp")}
    assert "inverse dynamics" in codegen.generate(model.tree, model.joints, False, np.float64, "rk4_vjp")
    monkeypatch.setattr(scalar, "adjoint_applies", lambda joints: False)
    generic = {mode: size(mode) for mode in ("vjp", "rk4_vjp")}
    for mode in hand:
        assert hand[mode] < 0.85 * generic[mode], (mode, hand[mode], generic[mode])
    # with body loads the block does not apply (their moments move with the bodies)
    assert "inverse dynamics" not in codegen.generate(model.tree, model.joints, True, np.float64, "vjp")


def _native_case():
    jax.config.update("jax_enable_x64", True)
    model = random_model(1, n_body=4, kinds=KINDS, free_root=False)
    assert scalar.adjoint_applies(model.joints)
    rng = np.random.default_rng(3)
    q = jnp.stack([random_state(model, s)[0] for s in range(3)])
    v, tau, ct = (jnp.asarray(rng.standard_normal((3, model.nv))) for _ in range(3))
    return model, rng, q, v, tau, ct, jnp.asarray(model.gravity)


def _close(x, y):
    for a, b in zip(jax.tree.leaves(x), jax.tree.leaves(y)):
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-10 * max(float(jnp.max(jnp.abs(b))), 1.0)


def test_native_reverse_mode_equals_the_vectorised_kernel():
    """The native forward dynamics' reverse-mode program built with the hand-derived block,
    against the vectorised kernel, batched and single (the RK4 step's: in the slow job, and
    through a rollout gradient in test_backends_native_step.py)."""
    model, _, q, v, tau, ct, g = _native_case()

    def vjp_fd(kernel):
        def one(q, v, t, c):
            fd = lambda q, v, t: backends.acceleration(model, q, v, t, gravity=g, kernel=kernel)  # noqa: E731
            return jax.vjp(fd, q, v, t)[1](c)

        return one

    # a batch (the vector build) and a single state (the scalar build)
    _close(jax.jit(jax.vmap(vjp_fd("native")))(q, v, tau, ct), jax.jit(jax.vmap(vjp_fd("vectorised")))(q, v, tau, ct))
    _close(jax.jit(vjp_fd("native"))(q[0], v[0], tau[0], ct[0]), jax.jit(vjp_fd("vectorised"))(q[0], v[0], tau[0], ct[0]))


@pytest.mark.slow  # about 40 s: the step's programs for this tree
def test_native_step_reverse_mode_equals_the_vectorised_kernel():
    """The RK4 step's reverse-mode program (springs and dampers) built with the hand-derived block."""
    model, rng, q, v, tau, ct, g = _native_case()
    stiffness = jnp.asarray(rng.uniform(1.0, 3.0, model.joints.n_joint))
    damping = jnp.asarray(rng.uniform(0.1, 0.5, model.nv))
    reference = jnp.asarray(model.qpos0) + 0.1

    def step_native(q, v, t):
        return native.rk4_step(model, q, v, 0.01, t, gravity=g, stiffness=stiffness, reference=reference, damping=damping)

    def step_reference(q, v, t):
        def field(q, v):
            total = t - stiffness * (q - reference) - damping * v  # hinges and slides: one q per DoF
            return v, backends.acceleration(model, q, v, total, gravity=g, kernel="vectorised")

        k1 = field(q, v)
        k2 = field(q + 0.005 * k1[0], v + 0.005 * k1[1])
        k3 = field(q + 0.005 * k2[0], v + 0.005 * k2[1])
        k4 = field(q + 0.01 * k3[0], v + 0.01 * k3[1])
        return q + 0.01 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]) / 6, v + 0.01 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]) / 6

    def vjp_step(step):
        return jax.jit(lambda q, v, t, c: jax.vjp(lambda *x: step(*x)[:2], q, v, t)[1]((c, c[::-1])))

    for i in range(2):
        _close(vjp_step(step_native)(q[i], v[i], tau[i], ct[i]), vjp_step(step_reference)(q[i], v[i], tau[i], ct[i]))
