"""Scenes: only declared effects are traced, structural specialisations, effect correctness.

References: the public joint-space functions of the spatial engine (``jb.forward_dynamics``,
``jb.passive_forces``, external loads), MuJoCo's RK4 integrator on the shipped models, and the
spec's equations of the paper examples written out here and integrated by SciPy's DOP853.
"""


import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from _support.jaxpr_tools import count_eqns
from _support.random_models import random_model, random_state

import jaxbody as jb
from jaxbody import constraints as jc

pytestmark = pytest.mark.filterwarnings("ignore:from_mjcf")


def chain_model(n, axis=(0.0, -1.0, 0.0), damping=0.0, stiffness=0.0, gravity=(0.0, 0.0, -9.81), seed=0):
    """``n`` hinged links hanging along -z, hinge axes ``axis`` (parallel: a planar chain)."""
    rng = np.random.default_rng(seed)
    b = jb.ModelBuilder(gravity=np.array(gravity))
    for i in range(n):
        b.add_body(
            f"link{i}", parent=f"link{i - 1}" if i else None,
            pos=np.array([0.0, 0.0, -0.4]) if i else np.zeros(3),
            mass=1.0 + 0.3 * rng.random(), com=np.array([0.02 * rng.standard_normal(), 0.01, -0.2]),
            inertia=np.array([0.02, 0.015 + 0.01 * rng.random(), 0.01]),
            joints=[jb.Hinge(axis=np.array(axis), damping=damping, stiffness=stiffness)],
        )
    return b.build()


def eqn_count(scene):
    q = jnp.zeros(scene.nq).at[0].set(1.0) if scene.has_quaternions else jnp.zeros(scene.nq)
    return count_eqns(jax.make_jaxpr(lambda q, v: scene.acceleration(0.0, q, v))(q, jnp.zeros(scene.nv)).jaxpr)


def flops(scene):
    q = jnp.zeros(scene.nq)
    lowered = jax.jit(lambda q, v: scene.acceleration(0.0, q, v)).lower(q, jnp.zeros(scene.nv))
    return lowered.compile().cost_analysis()["flops"]


@pytest.fixture(scope="module")
def panda(models_dir):
    return jb.from_mjcf(str(models_dir / "panda.xml"))


# ----------------------------------------------------------------------------- only what is declared
@pytest.mark.parametrize("kernel", ["vectorised", "unrolled"])
def test_trace_shrinks_as_each_effect_is_removed(panda, kernel):
    """Both forward-dynamics kernels: each removed effect removes equations from the program.

    The removed effects, in order: a Maggi constraint (end effector on a plane), the prescribed
    support motion, body loads, actuation, dampers, springs, gravity. Constraints, support motion
    and body loads need the scene's shared kinematics (their power enters the energy balance),
    so a scene with any of them runs the vectorised kernel whatever ``kernel`` says; the unrolled
    kernel is checked on the other effects.
    """
    nv, nb = panda.nv, panda.n_body

    def tau(t, q, v):
        return -2.0 * q[:nv]

    def wrench(t, q, v):
        return jnp.zeros((nb, 6)).at[-1, 2].set(3.0)

    def support(t):
        return jnp.stack([0.1 * jnp.sin(3.0 * t), 0.0 * t, 0.05 * t])

    stiff = jnp.full((panda.n_joint,), 4.0)
    on_plane = jc.PointOnPlane(panda, panda.body_names[-1], (0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0))
    sets = [
        dict(gravity=True, springs=stiff, dampers=True, actuation=tau, loads=wrench, support=support,
             constraints=[on_plane]),
        dict(gravity=True, springs=stiff, dampers=True, actuation=tau, loads=wrench, support=support),
        dict(gravity=True, springs=stiff, dampers=True, actuation=tau, loads=wrench),
        dict(gravity=True, springs=stiff, dampers=True, actuation=tau),
        dict(gravity=True, springs=stiff, dampers=True),
        dict(gravity=True, springs=stiff, dampers=False),
        dict(gravity=True, springs=False, dampers=False),
        dict(gravity=False, springs=False, dampers=False),
    ]
    if kernel == "unrolled":
        sets = sets[3:]
    counts = [eqn_count(jb.scene(panda, planar=False, kernel=kernel, **kw)) for kw in sets]
    assert all(a > b for a, b in zip(counts, counts[1:])), counts
    if kernel == "unrolled":
        return
    scenes = [jb.scene(panda, planar=False, **kw) for kw in sets]
    assert scenes[0].constraints is not None and all(sc.constraints is None for sc in scenes[1:])
    names = [sc.effect_names for sc in scenes]
    assert names[0] == names[1] == ("gravity", "springs", "dampers", "actuation", "loads", "support")
    assert names[2] == ("gravity", "springs", "dampers", "actuation", "loads") and names[-1] == ()


def test_model_defaults_declare_only_nonzero_effects():
    m = chain_model(3)  # no damping, no stiffness
    assert jb.scene(m).effect_names == ("gravity",)
    m2 = chain_model(3, damping=0.2, stiffness=1.0)
    assert jb.scene(m2).effect_names == ("gravity", "springs", "dampers")
    assert jb.scene(m2, gravity=False, springs=False).effect_names == ("dampers",)


def test_planar_path_chosen_and_cheaper_with_identical_trajectories():
    m = chain_model(7, damping=0.05, stiffness=0.5)
    planar, spatial = jb.scene(m), jb.scene(m, planar=False)
    assert planar.path == "planar" and spatial.path == "spatial"
    assert flops(planar) < flops(spatial)
    assert eqn_count(planar) < eqn_count(spatial)
    rng = np.random.default_rng(1)
    q0, v0 = jnp.asarray(rng.uniform(-1, 1, 7)), jnp.asarray(rng.uniform(-1, 1, 7))
    # The two paths are different floating-point programs (absolute-angle equations with a
    # mass matrix of augmented-body constants vs the spatial tree), so they agree to rounding,
    # not bit for bit: one evaluation of the accelerations differs by ~1e-13 of their size
    # (measured 5e-12 at |a| ~ 70), and 500 RK4 steps of this 7-link chain carry that to
    # ~1e-12 in v (measured 1.3e-12 at |v| ~ 15; q, with one more integration, 3e-14). So the
    # bound is 1e-12 absolute for q and energy and 1e-12 relative to the largest rate for v.
    qs, vs = jnp.asarray(rng.uniform(-1, 1, (8, 7))), jnp.asarray(rng.uniform(-1, 1, (8, 7)))
    acc = [jax.jit(jax.vmap(lambda q, v, sc=sc: sc.acceleration(0.0, q, v)))(qs, vs) for sc in (planar, spatial)]
    np.testing.assert_allclose(acc[0], acc[1], rtol=0, atol=1e-12 * float(jnp.abs(acc[1]).max()))
    kw = dict(solver="rk4", dt0=1e-3, n_save=11)
    a = jb.simulate(planar, q0, v0, 0.5, **kw)
    b = jb.simulate(spatial, q0, v0, 0.5, **kw)
    np.testing.assert_allclose(a.q, b.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.v, b.v, rtol=0, atol=1e-12 * float(jnp.abs(b.v).max()))
    np.testing.assert_allclose(a.energy - a.energy[0], b.energy - b.energy[0], atol=1e-12)


def _ball_chain():
    """``chain_model(3)`` with the middle hinge replaced by a ball joint (quaternion coordinates)."""
    b = jb.ModelBuilder(gravity=np.array([0.0, 0.0, -9.81]))
    for i in range(3):
        b.add_body(f"link{i}", parent=f"link{i - 1}" if i else None, pos=np.array([0.0, 0.0, -0.4]) if i else np.zeros(3),
                   mass=1.0 + 0.1 * i, com=np.array([0.01, 0.01, -0.2]), inertia=np.array([0.02, 0.015, 0.01]),
                   joints=[jb.Ball() if i == 1 else jb.Hinge(axis=np.array([0.0, -1.0, 0.0]))])
    return b.build()


def test_no_quaternion_kinematics_without_ball_or_free_joints(monkeypatch):
    """Hinge-only model: q̇ = v is the identity (no equation at all) and the solver step carries no
    quaternion projection; with a ball joint q̇ holds the quaternion kinematics ½ q ⊗ (0, ω)."""
    hinge = jb.scene(chain_model(3), planar=False)
    ball = jb.scene(_ball_chain(), planar=False)
    assert not hinge.has_quaternions and ball.has_quaternions
    q, v = jnp.array([0.1, 0.2, 0.3]), jnp.array([0.3, -0.1, 0.2])
    jx = jax.make_jaxpr(hinge.qdot)(q, v).jaxpr
    assert count_eqns(jx) == 0 and jx.outvars[0] is jx.invars[1]  # returns v itself

    quat = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
    qb, vb = jnp.asarray(np.concatenate([[0.1], quat, [0.3]])), jnp.array([0.3, 0.5, -0.2, 0.4, 0.2])
    jb_ = jax.make_jaxpr(ball.qdot)(qb, vb).jaxpr
    assert count_eqns(jb_) > 0
    w, x, y, z = quat
    omega = np.array([0.5, -0.2, 0.4])  # body-frame angular velocity of the ball (MuJoCo layout)
    ref = 0.5 * np.array([[-x, -y, -z], [w, -z, y], [z, w, -x], [-y, x, w]]) @ omega  # ½ q ⊗ (0, ω)
    np.testing.assert_allclose(ball.qdot(qb, vb), np.concatenate([[0.3], ref, [0.2]]), rtol=0, atol=1e-15)

    # the unit-quaternion projection of each step is left out of a hinge-only solve: forcing the
    # quaternion path in adds equations and changes nothing
    def solve_eqns(sc):
        run = lambda q, v: jb.simulate(sc, q, v, 0.01, solver="rk4", dt0=1e-3, n_save=2).q  # noqa: E731
        return count_eqns(jax.make_jaxpr(run)(q, v).jaxpr), run(q, v)

    n_special, q_special = solve_eqns(hinge)
    monkeypatch.setattr(jb.Scene, "has_quaternions", property(lambda self: True))
    n_general, q_general = solve_eqns(jb.scene(chain_model(3), planar=False))
    assert n_special < n_general, (n_special, n_general)
    np.testing.assert_array_equal(q_special, q_general)


def test_fixed_base_program_has_no_free_base_terms():
    """Fixed base: the carrier (free-base) acceleration terms of Cor. 1 are absent from the traced
    vector field. Marking the root of a hinge chain as free forces them in: they add equations and,
    the root's anchor being at rest, change no acceleration."""
    import copy

    m = chain_model(4)
    assert not any(m.joints.body_is_free)
    joints = copy.copy(m.joints)
    object.__setattr__(joints, "body_is_free", (1,) + tuple(m.joints.body_is_free[1:]))
    forced = copy.copy(m)
    object.__setattr__(forced, "joints", joints)
    fixed_sc = jb.scene(m, planar=False, kernel="vectorised")
    forced_sc = jb.scene(forced, planar=False, kernel="vectorised")
    assert eqn_count(fixed_sc) < eqn_count(forced_sc)
    rng = np.random.default_rng(4)
    q, v = jnp.asarray(rng.uniform(-1, 1, 4)), jnp.asarray(rng.uniform(-1, 1, 4))
    np.testing.assert_allclose(fixed_sc.acceleration(0.0, q, v), forced_sc.acceleration(0.0, q, v), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(fixed_sc.acceleration(0.0, q, v), jb.forward_dynamics(m, q, v), rtol=1e-12, atol=1e-12)


def test_planar_path_needs_parallel_axes_and_in_plane_gravity():
    tilted = chain_model(3, axis=(0.0, -1.0, 0.0), gravity=(0.0, 3.0, -9.0))  # gravity off the plane
    assert jb.scene(tilted).path == "spatial"
    assert jb.scene(tilted, gravity=False).path == "planar"
    b = jb.ModelBuilder()
    b.add_body("a", mass=1.0, com=np.array([0, 0, -0.3]), inertia=np.array([0.1, 0.1, 0.1]), joints=[jb.Hinge(axis=np.array([0.0, 1.0, 0.0]))])
    b.add_body("b", parent="a", pos=np.array([0, 0, -0.5]), mass=1.0, com=np.array([0, 0, -0.3]),
               inertia=np.array([0.1, 0.1, 0.1]), joints=[jb.Hinge(axis=np.array([1.0, 0.0, 0.0]))])
    skew = b.build()
    assert jb.scene(skew).path == "spatial"
    with pytest.raises(ValueError, match="planar=True needs hinge joints only"):
        jb.scene(skew, planar=True)


# ----------------------------------------------------------------------------- effects against the engine
def test_effects_match_forward_dynamics_with_passive_and_external_loads(panda):
    rng = np.random.default_rng(3)
    q, v = jnp.asarray(rng.uniform(-1, 1, panda.nq)), jnp.asarray(rng.uniform(-1, 1, panda.nv))
    ext = jnp.asarray(rng.standard_normal((panda.n_body, 6)))
    tau = jnp.asarray(rng.standard_normal(panda.nv))
    sc = jb.scene(panda, springs=jnp.full((panda.n_joint,), 3.0), actuation=lambda t, q, v: tau, loads=lambda t, q, v: ext)
    stiff = jb.scene(panda, springs=jnp.full((panda.n_joint,), 3.0)).effects[1]
    springs_model = panda.__class__(**{**{k: getattr(panda, k) for k in panda.__dataclass_fields__}, "joint_stiffness": stiff.stiffness})
    ref = jb.forward_dynamics(springs_model, q, v, jb.passive_forces(springs_model, q, v) + tau, external=ext)
    np.testing.assert_allclose(sc.acceleration(0.0, q, v), ref, rtol=1e-10, atol=1e-10)
    # gravity as a vector effect = the model with that gravity
    g = jnp.array([1.0, -2.0, -9.0])
    sc = jb.scene(panda, gravity=g, springs=False, dampers=False)
    m_g = panda.__class__(**{**{k: getattr(panda, k) for k in panda.__dataclass_fields__}, "gravity": g})
    np.testing.assert_allclose(sc.acceleration(0.0, q, v), jb.forward_dynamics(m_g, q, v), rtol=1e-10, atol=1e-10)
    e = sc.total_energy(q, v)
    np.testing.assert_allclose(e, jb.kinetic_energy(m_g, q, v) + jb.potential_energy(m_g, q), rtol=1e-12)


def test_actuation_shape_errors_name_tau():
    m = chain_model(2)
    with pytest.raises(ValueError, match=r"actuation: tau\(t, q, v\) returned shape \(3,\), expected \(2,\)"):
        jb.scene(m, actuation=lambda t, q, v: jnp.zeros(3))
    with pytest.raises(ValueError, match=r"loads: wrench\(t, q, v\) returned shape \(2, 3\), expected \(2, 6\)"):
        jb.scene(m, loads=lambda t, q, v: jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match="springs needs a spatial jaxbody.Model"):
        jb.scene(jb.examples.double_pendulum(), springs=jnp.ones(2))


# ----------------------------------------------------------------------------- paper examples
def _example1_rhs(m1, m2, a1, a2, l1, ic1, ic2, g, M=(0.0, 0.0)):
    md1, md2 = m1 * a1 + m2 * l1, m2 * a2
    j1, j2 = ic1 + m1 * a1**2 + m2 * l1**2, ic2 + m2 * a2**2

    def rhs(t, y):
        x1, x2, w1, w2 = y
        c, s = np.cos(x2 - x1), np.sin(x2 - x1)
        mass = np.array([[j1, l1 * md2 * c], [md2 * l1 * c, j2]])
        force = np.array([l1 * md2 * s * w2**2 - md1 * g * np.sin(x1) + M[0] - M[1],
                          -md2 * l1 * s * w1**2 - md2 * g * np.sin(x2) + M[1]])
        return np.concatenate([[w1, w2], np.linalg.solve(mass, force)])

    return rhs


def pendulum_chain(masses, coms, lengths, inertias, g=9.81):
    """Links in the x-z plane hanging along -z, angles from the downward vertical, counter-clockwise
    seen with x to the right and z up (hinge axis -y)."""
    b = jb.ModelBuilder(gravity=np.array([0.0, 0.0, -g]))
    for i, (m, a, ic) in enumerate(zip(masses, coms, inertias)):
        b.add_body(f"l{i}", parent=f"l{i - 1}" if i else None,
                   pos=np.array([0.0, 0.0, -lengths[i - 1]]) if i else np.zeros(3),
                   mass=m, com=np.array([0.0, 0.0, -a]), inertia=np.array([ic, ic, ic]),
                   joints=[jb.Hinge(axis=np.array([0.0, -1.0, 0.0]))])
    return b.build()


def test_example1_double_pendulum_model_scene_vs_eq15():
    p = dict(m1=1.0, m2=0.6, a1=0.4, a2=0.3, l1=0.8, ic1=0.05, ic2=0.02, g=9.81)
    model = pendulum_chain([1.0, 0.6], [0.4, 0.3], [0.8, 0.8], [0.05, 0.02])
    sc = jb.scene(model)
    assert sc.path == "planar"
    y0 = np.array([1.0, -0.5, 0.3, 0.0])  # absolute angles and rates
    ts = np.linspace(0.0, 2.0, 21)
    ref = solve_ivp(_example1_rhs(**p), (0, 2), y0, method="DOP853", t_eval=ts, rtol=1e-12, atol=1e-12)
    # joint coordinates are relative: q2 = α2 − α1
    rel = np.array([[1.0, 0.0], [-1.0, 1.0]])
    sol = jb.simulate(sc, rel @ y0[:2], rel @ y0[2:], 2.0, n_save=21, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.cumsum(sol.q, axis=1), ref.y[:2].T, atol=1e-9)
    assert float(sol.energy_drift) < 1e-10


def test_example2_three_link_manipulator_with_actuation_vs_eq16():
    m, a, L, ic = (2.0, 1.5, 0.8), (0.35, 0.25, 0.15), (0.7, 0.5), (0.09, 0.04, 0.01)
    md = (m[0] * a[0] + (m[1] + m[2]) * L[0], m[1] * a[1] + m[2] * L[1], m[2] * a[2])
    J = (ic[0] + m[0] * a[0] ** 2 + (m[1] + m[2]) * L[0] ** 2, ic[1] + m[1] * a[1] ** 2 + m[2] * L[1] ** 2, ic[2] + m[2] * a[2] ** 2)
    torque = lambda t: np.array([0.5 * np.cos(t), 0.2, -0.1 * np.sin(2 * t)])

    def rhs(t, y):
        al, w = y[:3], y[3:]
        c = lambda i, j: np.cos(al[i] - al[j])
        s = lambda i, j: np.sin(al[i] - al[j])
        Mm = np.array([
            [J[0], L[0] * md[1] * c(1, 0), L[0] * md[2] * c(2, 0)],
            [md[1] * L[0] * c(1, 0), J[1], L[1] * md[2] * c(2, 1)],
            [md[2] * L[0] * c(2, 0), md[2] * L[1] * c(2, 1), J[2]],
        ])
        Mt = torque(t)
        rhs_ = np.array([
            Mt[0] - Mt[1] + L[0] * (md[1] * s(1, 0) * w[1] ** 2 + md[2] * s(2, 0) * w[2] ** 2),
            Mt[1] - Mt[2] - md[1] * L[0] * s(1, 0) * w[0] ** 2 + L[1] * md[2] * s(2, 1) * w[2] ** 2,
            Mt[2] - md[2] * (L[0] * s(2, 0) * w[0] ** 2 + L[1] * s(2, 1) * w[1] ** 2),
        ])
        return np.concatenate([w, np.linalg.solve(Mm, rhs_)])

    model = pendulum_chain(m, a, L + (0.3,), ic, g=0.0)
    sc = jb.scene(model, actuation=lambda t, q, v: jnp.stack([0.5 * jnp.cos(t), 0.2 + 0 * t, -0.1 * jnp.sin(2 * t)]))
    assert sc.path == "planar" and sc.effect_names == ("actuation",)
    y0 = np.array([0.2, 0.5, -0.3, 0.0, 0.4, -0.2])
    ref = solve_ivp(rhs, (0, 1.5), y0, method="DOP853", t_eval=np.linspace(0, 1.5, 16), rtol=1e-12, atol=1e-12)
    P = np.tril(np.ones((3, 3)))
    sol = jb.simulate(sc, np.linalg.solve(P, y0[:3]), np.linalg.solve(P, y0[3:]), 1.5, n_save=16, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.q @ P.T, ref.y[:3].T, atol=1e-9)
    # energy balance with the actuation work closes
    assert float(sol.energy_drift) < 1e-9 and "actuation" in sol.work


def test_example3_cart_pendulum_spatial_model_vs_eq17():
    mc, m, a, ic, g = 3.0, 0.5, 0.4, 0.01, 9.81
    b = jb.ModelBuilder(gravity=np.array([0.0, 0.0, -g]))
    b.add_body("cart", mass=mc, inertia=np.array([0.1, 0.1, 0.1]), joints=[jb.Slide(axis=np.array([1.0, 0.0, 0.0]))])
    b.add_body("pend", parent="cart", mass=m, com=np.array([0.0, 0.0, -a]), inertia=np.array([ic, ic, ic]),
               joints=[jb.Hinge(axis=np.array([0.0, -1.0, 0.0]))])
    sc = jb.scene(b.build())
    assert sc.path == "spatial"
    M, md, J = mc + m, m * a, ic + m * a * a

    def rhs(t, y):
        x, p, xd, pd = y
        A = np.array([[M, md * np.cos(p)], [md * np.cos(p), J]])
        f = np.array([md * pd**2 * np.sin(p), -md * g * np.sin(p)])
        return np.concatenate([[xd, pd], np.linalg.solve(A, f)])

    y0 = np.array([0.1, 1.0, -0.2, 0.5])
    ref = solve_ivp(rhs, (0, 2), y0, method="DOP853", t_eval=np.linspace(0, 2, 21), rtol=1e-12, atol=1e-12)
    sol = jb.simulate(sc, y0[:2], y0[2:], 2.0, n_save=21, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.q, ref.y[:2].T, atol=1e-9)
    np.testing.assert_allclose(sol.v, ref.y[2:].T, atol=1e-8)


def test_example4_pivot_moving_along_a_line_vs_spec():
    m, a, ic, a0, w, beta, g = 0.5, 0.4, 0.01, 0.05, 12.0, 0.5, 9.81
    model = pendulum_chain([m], [a], [1.0], [ic], g=g)
    sc = jb.scene(model, support=lambda t: a0 * jnp.sin(w * t) * jnp.stack([jnp.cos(beta), 0.0 * t, jnp.sin(beta)]))
    assert sc.path == "planar" and sc.effect_names == ("gravity", "support")
    J, md = ic + m * a * a, m * a

    def rhs(t, y):
        p, pd = y
        return [pd, (md * a0 * w**2 * np.sin(w * t) * np.cos(p - beta) - md * g * np.sin(p)) / J]

    ref = solve_ivp(rhs, (0, 2), [0.3, 0.0], method="DOP853", t_eval=np.linspace(0, 2, 21), rtol=1e-12, atol=1e-12)
    sol = jb.simulate(sc, jnp.array([0.3]), jnp.array([0.0]), 2.0, n_save=21, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.q[:, 0], ref.y[0], atol=1e-9)
    # the spatial path gives the same motion; the energy relative to the support balances
    sol2 = jb.simulate(jb.scene(model, planar=False, support=sc.effects[1]), jnp.array([0.3]), jnp.array([0.0]), 2.0,
                       n_save=21, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol2.q, sol.q, atol=1e-10)
    assert float(sol.energy_drift) < 1e-9 and float(jnp.max(jnp.abs(sol.work["support"]))) > 1e-3


@pytest.mark.slow  # 20-28 s; Example 5 is checked against the spec in test_constraints and through scenes in test_simulation_constrained
def test_example5_end_on_vertical_line_through_the_constraint_slot():
    m, a, L, ic, g = (1.0, 0.6), (0.4, 0.3), 0.8, (0.05, 0.02), 9.81
    model = pendulum_chain(m, a, (L, L), ic, g=g)

    # the end A of link 2 stays on the vertical x = 0 through the first joint (Maggi layer,
    # built from the ready constraint at the model's reference configuration)
    end_on_vertical = jc.PointOnPlane(model, "l1", (0.0, 0.0, -L), normal=(1.0, 0.0, 0.0))
    sc = jb.scene(model, constraints=[end_on_vertical])
    assert sc.path == "spatial"
    md1, md2 = m[0] * a[0] + m[1] * L, m[1] * a[1]
    J1, J2 = ic[0] + m[0] * a[0] ** 2 + m[1] * L**2, ic[1] + m[1] * a[1] ** 2

    def rhs(t, y):
        p, pd = y
        num = -(md1 + md2) * g * np.sin(p) - 2 * L * md2 * pd**2 * np.sin(2 * p)
        return [pd, num / (J1 + J2 - 2 * L * md2 * np.cos(2 * p))]

    ref = solve_ivp(rhs, (0, 1), [0.4, 0.0], method="DOP853", t_eval=np.linspace(0, 1, 11), rtol=1e-12, atol=1e-12)
    sol = jb.simulate(sc, jnp.array([0.4, -0.8]), jnp.array([0.0, 0.0]), 1.0, n_save=11, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.q[:, 0], ref.y[0], atol=1e-8)
    np.testing.assert_allclose(sol.q[:, 1], -2 * ref.y[0], atol=1e-8)
    assert float(jnp.max(jnp.abs(sol.constraint_drift["position"]))) < 1e-8
    assert float(jnp.max(jnp.abs(sol.constraint_drift["velocity"]))) < 1e-8
    # the reaction is the force F_r i on A (spec closed form), one column per constraint row
    pdd = np.array([rhs(0, [p, pd])[1] for p, pd in ref.y.T])
    Fr = (J1 - J2) * pdd / (2 * L * np.cos(ref.y[0])) + (md1 - md2) * g * np.tan(ref.y[0]) / (2 * L)
    assert sol.reactions.shape == (11, 1)
    np.testing.assert_allclose(sol.reactions[:, 0], Fr, atol=1e-7)


def test_example6_wheelset_pendulum_vs_corrected_eq19():
    mw, Jw, R, m, a, ic, g = 4.0, 0.12, 0.25, 0.7, 0.35, 0.015, 9.81
    sys_ = jb.examples.wheelset_pendulum()
    M, md, J2 = mw + m, m * a, ic + m * a * a

    def rhs(t, y):
        x, p, xd, pd = y
        A = np.array([[M + Jw / R**2, md * np.cos(p)], [md * np.cos(p), J2]])
        f = np.array([md * pd**2 * np.sin(p), -md * g * np.sin(p)])
        return np.concatenate([[xd, pd], np.linalg.solve(A, f)])

    y0 = np.array([0.0, 0.8, 0.3, 0.0])
    ref = solve_ivp(rhs, (0, 2), y0, method="DOP853", t_eval=np.linspace(0, 2, 21), rtol=1e-12, atol=1e-12)
    sol = jb.simulate(jb.scene(sys_), y0[:2], y0[2:], 2.0, n_save=21, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.q, ref.y[:2].T, atol=1e-9)
    assert float(sol.energy_drift) < 1e-10


def test_example_systems_cart_and_vertical_line_vs_spec():
    """Examples 3 and 5 as the ready systems of ``jb.examples`` (embedded planar systems)."""
    mc, m, a, ic, g = 3.0, 0.5, 0.4, 0.01, 9.81
    M, md, J = mc + m, m * a, ic + m * a * a

    def cart(t, y):
        x, p, xd, pd = y
        A = np.array([[M, md * np.cos(p)], [md * np.cos(p), J]])
        return np.concatenate([[xd, pd], np.linalg.solve(A, [md * pd**2 * np.sin(p), -md * g * np.sin(p)])])

    y0 = np.array([0.1, 1.0, -0.2, 0.5])
    ref = solve_ivp(cart, (0, 1), y0, method="DOP853", t_eval=np.linspace(0, 1, 11), rtol=1e-12, atol=1e-12)
    sol = jb.simulate(jb.examples.cart_pendulum(), y0[:2], y0[2:], 1.0, n_save=11, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.q, ref.y[:2].T, atol=1e-9)
    sol4 = jb.simulate(jb.examples.oscillating_support_pendulum(), jnp.array([0.3]), jnp.array([0.0]), 1.0, n_save=11,
                       rtol=1e-12, atol=1e-12)
    assert float(sol4.energy_drift) < 1e-9  # rheonomic: the system's power closes the balance


# ----------------------------------------------------------------------------- MuJoCo RK4
@pytest.mark.parametrize("name", ["panda", "anymal_c"])
def test_robot_matches_mujoco_rk4(name, models_dir):
    D = mujoco.mjtDisableBit
    mj = mujoco.MjModel.from_xml_path(str(models_dir / f"{name}.xml"))
    mj.opt.disableflags |= (D.mjDSBL_CONSTRAINT | D.mjDSBL_CONTACT | D.mjDSBL_EQUALITY | D.mjDSBL_LIMIT
                            | D.mjDSBL_FRICTIONLOSS | D.mjDSBL_ACTUATION)
    mj.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    dt, n = 1e-3, 50
    mj.opt.timestep = dt
    d = mujoco.MjData(mj)
    rng = np.random.default_rng(7)
    d.qpos[:] = mj.qpos0
    if name == "anymal_c":
        d.qpos[2] += 0.5
    d.qvel[:] = 0.3 * rng.standard_normal(mj.nv)
    q0, v0 = d.qpos.copy(), d.qvel.copy()
    for _ in range(n):
        mujoco.mj_step(mj, d)
    model = jb.from_mjcf(str(models_dir / f"{name}.xml"))
    sol = jb.simulate(model, q0, v0, n * dt, solver="rk4", dt0=dt, n_save=2)
    np.testing.assert_allclose(sol.q[-1], d.qpos, atol=1e-9)
    np.testing.assert_allclose(sol.v[-1], d.qvel, atol=1e-8)


def test_planar_path_handles_opposite_hinges_and_dampers():
    """Hinges pointing against the plane normal and joint dampers/springs: the planar path
    (planar.from_model of the aligned mechanism) gives the spatial path's accelerations."""
    b = jb.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    axes = [(0, 1, 0), (0, -1, 0), (0, 1, 0)]
    for k, ax in enumerate(axes):
        b.add_body(f"l{k}", None if k == 0 else f"l{k - 1}", pos=(0, 0, 0) if k == 0 else (0.0, 0.0, -0.5),
                   joints=[jb.Hinge(axis=ax, damping=0.1 * (k + 1), stiffness=0.5 * k)],
                   mass=1.0 + k, com=(0.05 * k, 0.0, -0.25), inertia=(0.02, 0.03 + 0.005 * k, 0.025))
    model = b.build()
    planar_scene = jb.scene(model)
    spatial_scene = jb.scene(model, planar=False)
    assert planar_scene.path == "planar" and spatial_scene.path == "spatial"
    rng = np.random.default_rng(5)
    for _ in range(3):
        q, v = jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=3))
        np.testing.assert_allclose(planar_scene.acceleration(0.0, q, v), spatial_scene.acceleration(0.0, q, v),
                                   rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(planar_scene.total_energy(q, v), spatial_scene.total_energy(q, v), rtol=1e-12)


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


def test_default_kernel_is_native_and_wins_over_the_planar_path(monkeypatch):
    """The real default (the suite pins the vectorised kernel, conftest.py): ``kernel=None`` is
    ``"auto"``, the native kernel where it can be built; a planar chain then takes the spatial
    path, whose one native call is faster than the planar path's JAX code
    (benchmarks/planar_choice.py), and ``repr`` names the path and the kernel. Without the native
    kernel the planar path stays. Nothing is compiled here: the choice is made when the scene is built."""
    monkeypatch.delenv("JAXBODY_KERNEL", raising=False)
    assert jb.backends.default_kernel() == "auto"
    m = chain_model(2)
    if jb.backends.native.available():
        default = jb.scene(m)
        assert (default.path, default.runs) == ("spatial", "native")
        assert repr(default) == "Scene(Model, path='spatial', kernel='native', effects=['gravity'])"
    # asked for, or without the native kernel, the planar path stays
    assert jb.scene(m, planar=True).path == "planar"
    assert repr(jb.scene(m, kernel="vectorised")) == "Scene(Model, path='planar', kernel='jax', effects=['gravity'])"
    monkeypatch.setenv("JAXBODY_KERNEL", "vectorised")
    assert jb.scene(m).path == "planar"
    assert jb.scene(m, planar=False, kernel="vectorised").runs == "vectorised"
    monkeypatch.setenv("JAXBODY_KERNEL", "fastest")
    with pytest.raises(ValueError, match=r"\$JAXBODY_KERNEL must be one of"):
        jb.scene(m)
