"""A planar tree built as a planar system and as a spatial Model gives the same dynamics.

The planar system (absolute angles, spec §9) is embedded in the xy-plane of a spatial model:
hinges about z, gravity along -y, a translating base as two slide joints along x and y.
The spatial model works in joint (relative) angles, so the planar results are mapped with
α = T q (spec §9.4): joint-space mass matrix Tᵀℳ T, bias Tᵀh, torques in the same layout.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb

CASES = {
    "chain3": dict(parent=[-1, 0, 1], base=False),
    "tree4": dict(parent=[-1, 0, 0, 1], base=False),
    "tree4_on_base": dict(parent=[-1, 0, 0, 2], base=True),
    "two_roots_on_base": dict(parent=[-1, -1, 1], base=True),
}


def build_pair(parent, base, seed):
    rng = np.random.default_rng(seed)
    n = len(parent)
    mass = rng.uniform(0.5, 2.0, n)
    com = rng.uniform(-0.3, 0.3, (n, 2))
    hinge = rng.uniform(-0.5, 0.5, (n, 2))
    inertia = rng.uniform(0.01, 0.1, n)
    base_mass = 1.7 if base else None
    g = np.array([0.0, -9.81])
    planar = jb.planar.from_parents(parent, mass, com, hinge, inertia, gravity=g, base_mass=base_mass)

    b = jb.ModelBuilder(gravity=(0.0, -9.81, 0.0))
    if base:
        b.add_body(
            "base", mass=base_mass, inertia=(0.1, 0.1, 0.1),
            joints=[jb.Slide(axis=(1, 0, 0)), jb.Slide(axis=(0, 1, 0))],
        )
    for k in range(n):
        p = parent[k]
        pname = (None if not base else "base") if p < 0 else f"b{p}"
        b.add_body(
            f"b{k}", pname,
            pos=(hinge[k, 0], hinge[k, 1], 0.0),
            mass=mass[k],
            com=(com[k, 0], com[k, 1], 0.0),
            inertia=(inertia[k], inertia[k], inertia[k]),
            joints=[jb.Hinge(axis=(0, 0, 1))],
        )
    return planar, b.build(), rng


@pytest.mark.parametrize("case", list(CASES))
def test_planar_and_spatial_paths_agree(case):
    spec = CASES[case]
    planar, model, rng = build_pair(spec["parent"], spec["base"], seed=len(case))
    nb = 2 if spec["base"] else 0
    n = len(spec["parent"])
    q_abs = jnp.asarray(np.concatenate([rng.standard_normal(nb), rng.uniform(-np.pi, np.pi, n)]))
    v_abs = jnp.asarray(rng.standard_normal(nb + n))
    tau = jnp.asarray(rng.standard_normal(nb + n))  # (F_x, F_y, M_1..M_n): same layout both ways
    # every function compiled (called eagerly each would compile its operations one by one)
    to_relative = jax.jit(jb.planar.absolute_to_relative)
    q_rel, v_rel = to_relative(planar, q_abs), to_relative(planar, v_abs)

    M_planar = jax.jit(jb.planar.joint_mass_matrix)(planar, q_abs)
    M_spatial = jax.jit(jb.mass_matrix)(model, q_rel)
    np.testing.assert_allclose(M_spatial, M_planar, rtol=1e-12, atol=1e-13)

    h_planar = jax.jit(jb.planar.joint_bias_forces)(planar, q_abs, v_abs)
    h_spatial = jax.jit(jb.bias_forces)(model, q_rel, v_rel)
    np.testing.assert_allclose(h_spatial, h_planar, rtol=1e-11, atol=1e-12)

    a_abs = jax.jit(jb.planar.forward_dynamics)(planar, q_abs, v_abs, tau)
    a_rel = jax.jit(jb.forward_dynamics)(model, q_rel, v_rel, tau)
    np.testing.assert_allclose(jax.jit(jb.planar.relative_to_absolute)(planar, a_rel), a_abs, rtol=1e-10, atol=1e-10)

    E_planar = jax.jit(jb.planar.total_energy)(planar, q_abs, v_abs)
    E_spatial = jb.kinetic_energy(model, q_rel, v_rel) + jb.potential_energy(model, q_rel)
    np.testing.assert_allclose(E_spatial, E_planar, rtol=1e-12)

    # joint forces of Statement 1 (eq. 1), planar vs spatial (world x, y components)
    F_planar = jax.jit(jb.planar.joint_reactions)(planar, q_abs, v_abs, a_abs)[0]
    F_spatial, M_spatial_k = jax.jit(jb.joint_reactions)(model, q_rel, v_rel, a_rel)
    bodies = np.arange(n) + (1 if spec["base"] else 0)
    np.testing.assert_allclose(F_spatial[bodies, :2], F_planar, rtol=1e-10, atol=1e-10)
    # the z-moment of the reaction about the hinge is the drive torque M_k
    np.testing.assert_allclose(M_spatial_k[bodies, 2], tau[nb:], rtol=1e-10, atol=1e-10)


# ----------------------------------------------------------------------------- from_model
def _tilted_model(parent, seed, damping=0.0):
    """A spatial model whose hinges are parallel to a tilted axis n, gravity in their plane,
    with full inertia tensors, out-of-plane offsets and non-zero joint references."""
    from _support.random_models import random_inertia, random_rotation_quat

    rng = np.random.default_rng(seed)
    R0 = np.asarray(jb.kinematics.quat_to_matrix(jnp.asarray(random_rotation_quat(rng))))
    n_axis = R0 @ np.array([0.0, 0.0, 1.0])
    b = jb.ModelBuilder(gravity=R0 @ np.array([0.3, -9.81, 0.0]))
    for k, p in enumerate(parent):
        b.add_body(
            f"b{k}", None if p < 0 else f"b{p}",
            pos=R0 @ np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.2, 0.2)]),
            mass=float(rng.uniform(0.5, 2.0)),
            com=R0 @ rng.uniform(-0.3, 0.3, 3),
            inertia=random_inertia(rng, 0.2),
            joints=[jb.Hinge(axis=n_axis, pos=R0 @ rng.uniform(-0.1, 0.1, 3),
                             ref=float(rng.uniform(-1, 1)), damping=damping)],
        )
    return b.build()


@pytest.mark.parametrize("parent", [[-1, 0, 1], [-1, 0, 0, 1], [-1, -1, 1]])
def test_from_model_gives_the_same_dynamics(parent):
    model = _tilted_model(parent, seed=len(parent) + parent[1])
    system = jb.planar.from_model(model)
    rng = np.random.default_rng(3)
    q = model.qpos0 + jnp.asarray(rng.uniform(-2, 2, model.nq))
    v = jnp.asarray(rng.standard_normal(model.nv))
    tau = jnp.asarray(rng.standard_normal(model.nv))
    q2 = q + 0.3
    P = _planar_quantities(system, q - model.qpos0, v, tau, q2 - model.qpos0)
    np.testing.assert_allclose(P["mass_matrix"], jb.mass_matrix(model, q), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(P["bias_forces"], jb.bias_forces(model, q, v), rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(P["acceleration"], jb.forward_dynamics(model, q, v, tau), rtol=1e-10, atol=1e-11)
    # the drive torques are the hinge torques, and the reaction moment about n is the drive
    np.testing.assert_allclose(P["drive"], tau, rtol=1e-10, atol=1e-11)
    _, moment = jb.joint_reactions(model, q, v, jb.forward_dynamics(model, q, v, tau))
    n_axis = np.asarray(model.joint_axis[0])
    np.testing.assert_allclose(np.asarray(moment) @ n_axis, tau, rtol=1e-10, atol=1e-11)
    # kinetic energy and potential energy differences agree
    np.testing.assert_allclose(P["kinetic_energy"], jb.kinetic_energy(model, q, v), rtol=1e-12)
    np.testing.assert_allclose(P["potential_rise"], jb.potential_energy(model, q2) - jb.potential_energy(model, q),
                               rtol=1e-10, atol=1e-12)


@eqx.filter_jit  # the planar functions in one program (called one by one they compile each operation)
def _planar_quantities(system, q_rel, v, tau, q2_rel):
    """The planar side of the comparison, in absolute angles, mapped back to the hinge coordinates."""
    theta = jb.planar.relative_to_absolute(system, q_rel)
    omega = jb.planar.relative_to_absolute(system, v)
    a_abs = jb.planar.forward_dynamics(system, theta, omega, tau)
    theta2 = jb.planar.relative_to_absolute(system, q2_rel)
    return {
        "mass_matrix": jb.planar.joint_mass_matrix(system, theta),
        "bias_forces": jb.planar.joint_bias_forces(system, theta, omega),
        "acceleration": jb.planar.absolute_to_relative(system, a_abs),
        "drive": jb.planar.inverse_dynamics(system, theta, omega, a_abs),
        "kinetic_energy": jb.planar.kinetic_energy(system, theta, omega),
        "potential_rise": jb.planar.potential_energy(system, theta2) - jb.planar.potential_energy(system, theta),
    }


def test_from_model_rejects_what_is_not_planar():
    with pytest.raises(ValueError, match=r"joint 0 \('b0_hinge0'\) has dof_damping 0.5; a planar system has no"):
        jb.planar.from_model(_tilted_model([-1, 0], seed=1, damping=0.5))
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    b.add_body("a", mass=1.0, inertia=(0.1, 0.1, 0.1), com=(0.1, 0, 0), joints=[jb.Hinge(axis=(0, 1, 0))])
    b.add_body("s", "a", mass=1.0, inertia=(0.1, 0.1, 0.1), joints=[jb.Slide(axis=(1, 0, 0))])
    with pytest.raises(ValueError, match=r"body 1 \('s'\) must carry exactly one hinge joint \(it has 1 joint\(s\), the first a slide\)"):
        jb.planar.from_model(b.build())
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    b.add_body("a", mass=1.0, inertia=(0.1, 0.1, 0.1), com=(0.1, 0, 0), joints=[jb.Hinge(axis=(0, 1, 0))])
    b.add_body("c", "a", mass=1.0, inertia=(0.1, 0.1, 0.1), com=(0.1, 0, 0), joints=[jb.Hinge(axis=(1, 0, 0))])
    with pytest.raises(ValueError, match=r"the axis of joint 1 \('c_hinge0'\) is \[1.0, 0.0, 0.0\] in world axes, not \[0.0, 1.0, 0.0\]"):
        jb.planar.from_model(b.build())
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    b.add_body("a", mass=1.0, inertia=(0.1, 0.1, 0.1), com=(0.1, 0, 0), joints=[jb.Hinge(axis=(0, 0, 1))])
    with pytest.raises(ValueError, match=r"gravity \[0.0, 0.0, -9.81\] is not in the plane of motion"):
        jb.planar.from_model(b.build())


def test_aligned_system_is_from_model_with_hinges_turned_and_no_passive_effects():
    """The scene's planar conversion (jb.planar.aligned_system): the planarity test of from_model,
    either sense of the hinges, springs, dampers and gravity left to the scene."""
    model = _tilted_model([-1, 0, 1], seed=4, damping=0.5)
    system, plane, signs = jb.planar.aligned_system(model, model.gravity)
    assert signs == (1.0, 1.0, 1.0) and plane.shape == (2, 3)
    undamped = jb.planar.from_model(_tilted_model([-1, 0, 1], seed=4))
    np.testing.assert_array_equal(system.body_mass, undamped.body_mass)
    np.testing.assert_allclose(system.body_com, undamped.body_com, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(system.hinge_pos, undamped.hinge_pos, rtol=1e-14, atol=1e-15)
    np.testing.assert_array_equal(system.gravity, np.zeros(2))
    # a hinge turned the other way is recorded in its sense; from_model rejects it
    flipped = eqx.tree_at(lambda m: m.joint_axis, model, model.joint_axis.at[1].multiply(-1.0))
    assert jb.planar.aligned_system(flipped, model.gravity)[2] == (1.0, -1.0, 1.0)
    with pytest.raises(ValueError, match=r"the axis of joint 1 .* all hinges must be parallel and point the same way"):
        jb.planar.from_model(eqx.tree_at(lambda m: m.dof_damping, flipped, jnp.zeros(3)))
    # gravity off the plane: not planar
    assert jb.planar.aligned_system(model, np.asarray(model.gravity) + np.asarray(model.joint_axis[0])) is None
    with pytest.raises(jb.planar.NotPlanar, match="gravity .* is not in the plane of motion"):
        jb.planar.planarity(model, np.asarray(model.gravity) + np.asarray(model.joint_axis[0]))
