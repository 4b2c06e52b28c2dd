"""A planar tree built as a planar system and as a spatial Model gives the same dynamics.

The planar system (absolute angles, spec §9) is embedded in the xy-plane of a spatial model:
hinges about z, gravity along -y, a translating base as two slide joints along x and y.
The spatial model works in joint (relative) angles, so the planar results are mapped with
α = T q (spec §9.4): joint-space mass matrix Tᵀℳ T, bias Tᵀh, torques in the same layout.
"""

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
    planar = jb.planar.tree(parent, mass, com, hinge, inertia, gravity=g, base_mass=base_mass)

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
    q_rel = jb.planar.absolute_to_relative(planar, q_abs)
    v_rel = jb.planar.absolute_to_relative(planar, v_abs)

    M_planar = jax.jit(jb.planar.joint_mass_matrix)(planar, q_abs)
    M_spatial = jax.jit(jb.mass_matrix)(model, q_rel)
    np.testing.assert_allclose(M_spatial, M_planar, rtol=1e-12, atol=1e-13)

    h_planar = jax.jit(jb.planar.joint_bias_forces)(planar, q_abs, v_abs)
    h_spatial = jax.jit(jb.bias_forces)(model, q_rel, v_rel)
    np.testing.assert_allclose(h_spatial, h_planar, rtol=1e-11, atol=1e-12)

    a_abs = jax.jit(jb.planar.forward_dynamics)(planar, q_abs, v_abs, tau)
    a_rel = jax.jit(jb.forward_dynamics)(model, q_rel, v_rel, tau)
    np.testing.assert_allclose(jb.planar.relative_to_absolute(planar, a_rel), a_abs, rtol=1e-10, atol=1e-10)

    E_planar = jb.planar.total_energy(planar, q_abs, v_abs)
    E_spatial = jb.kinetic_energy(model, q_rel, v_rel) + jb.potential_energy(model, q_rel)
    np.testing.assert_allclose(E_spatial, E_planar, rtol=1e-12)

    # joint forces of Statement 1 (eq. 1), planar vs spatial (world x, y components)
    F_planar = jb.planar.joint_forces(planar, q_abs, v_abs, a_abs)
    F_spatial, M_spatial_k = jax.jit(jb.joint_reactions)(model, q_rel, v_rel, a_rel)
    bodies = np.arange(n) + (1 if spec["base"] else 0)
    np.testing.assert_allclose(F_spatial[bodies, :2], F_planar, rtol=1e-10, atol=1e-10)
    # the z-moment of the reaction about the hinge is the drive torque M_k
    np.testing.assert_allclose(M_spatial_k[bodies, 2], tau[nb:], rtol=1e-10, atol=1e-10)
