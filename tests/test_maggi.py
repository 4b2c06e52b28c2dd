"""Maggi's equations as a general mechanism: parametrisation independence, nonlinear
constraints against Lagrange multipliers, batching, switching kinematic structure, phases."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody import maggi
from jaxbody.examples import disk as dk

RHO, TH = 0.3, 1.2


@functools.lru_cache
def regimes():
    return dk.sliding_disk(), dk.skating_disk(), dk.rolling_disk()


def rolling_state(rng):
    q = jnp.asarray(rng.uniform(-1, 1, 5)).at[3].set(rng.uniform(0.4, 2.7))
    e = rng.normal(size=3) * 2
    x = jnp.array([e[0], e[1], e[2], -RHO * e[2], -RHO * np.sin(float(q[3])) * e[0]])
    return q, x


def test_solve_general_against_numpy():
    rng = np.random.default_rng(0)
    for n in (1, 3, 7):
        M = rng.normal(size=(n, n))
        B = rng.normal(size=(n, 2))
        X, ratio = maggi.solve_general(jnp.asarray(M), jnp.asarray(B))
        np.testing.assert_allclose(X, np.linalg.solve(M, B), rtol=1e-10, atol=1e-12)
        assert float(ratio) > 0
    _, ratio = maggi.solve_general(jnp.ones((3, 3)), jnp.eye(3))
    assert float(ratio) < maggi.SINGULAR_PIVOT


def test_results_do_not_depend_on_the_choice_of_epsilon():
    """User ε̃ of the paper vs automatic partitioning: same ẋ and Λ; A and K differ."""
    user = regimes()[2]
    auto = maggi.constrain(user.base, user.constraints, q_ref=jnp.array([0.0, 0.0, 0.0, TH, 0.0]))
    assert auto.epsilon is None and len(auto.free) == 3
    rng = np.random.default_rng(1)
    for _ in range(4):
        q, x = rolling_state(rng)
        ru, ra = user.solve(0.0, q, x), auto.solve(0.0, q, x)
        np.testing.assert_allclose(ra.xdot, ru.xdot, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(ra.reactions, ru.reactions, rtol=1e-11, atol=1e-12)
        G = user.constraint_jacobian(0.0, q, x)
        for r in (ru, ra):
            np.testing.assert_allclose(G @ r.A, 0.0, atol=1e-12)
            np.testing.assert_allclose(G @ r.K, np.eye(2), atol=1e-12)


def test_partitioned_parametrisation_is_the_inverse_of_e_over_g():
    """With ε chosen by partitioning, [A | K] comes from the s × s block of the dependent
    velocities: it must still be the inverse of [E; G] (regular partitions of the rolling disk),
    and a partition that repeats an index is reported singular, not inverted."""
    user = regimes()[2]
    auto = maggi.constrain(user.base, user.constraints, q_ref=jnp.array([0.0, 0.0, 0.0, TH, 0.0]))
    q, x = rolling_state(np.random.default_rng(3))
    G = np.asarray(auto.constraint_jacobian(0.0, q, x))
    for free in ((0, 1, 2), (1, 3, 4), (0, 1, 3), (1, 2, 4)):  # x[1] is in no row: always free
        system = auto.with_partition(free)
        A, K, ratio = system.parametrisation(0.0, q, x)
        J = np.vstack([np.asarray(system.selection(x)), G])
        np.testing.assert_allclose(np.hstack([A, K]), np.linalg.inv(J), rtol=1e-12, atol=1e-13)
        assert float(ratio) > maggi.SINGULAR_PIVOT
        # the same dynamics whatever the partition
        np.testing.assert_allclose(system.solve(0.0, q, x).xdot, user.solve(0.0, q, x).xdot, rtol=1e-11, atol=1e-12)
    for free in ((0, 0, 1), (0, 1, 7)):
        assert float(auto.with_partition(free).parametrisation(0.0, q, x)[2]) == 0.0
    # x[1] appears in no constraint row: leaving it dependent makes G's dependent block singular
    singular = auto.with_partition((0, 3, 4))
    assert abs(np.linalg.det(np.vstack([np.asarray(singular.selection(x)), G]))) < 1e-12
    assert not float(singular.parametrisation(0.0, q, x)[2]) > maggi.SINGULAR_PIVOT


def test_partition_qualities_through_the_dependent_block_equal_the_full_determinant():
    """partition_qualities (s × s blocks, one Gram determinant) against selection_quality
    (the n × n determinant of [E; G]) for every choice of free columns of random Jacobians, in
    ascending and in shuffled order (the sign follows the order of E's rows), singular choices
    included."""
    import itertools

    from jaxbody.maggi.constrained import partition_qualities, selection_quality

    fast_quality = jax.jit(lambda G, free: partition_qualities(G, free)[0])
    full_quality = jax.jit(selection_quality)
    rng = np.random.default_rng(5)
    for s, n in ((1, 3), (2, 5), (3, 6)):
        G = jnp.asarray(rng.normal(size=(s, n)))
        G = G.at[:, 0].set(0.0) if s == 2 else G  # a column in no row: choices leaving it dependent are singular
        for free in itertools.combinations(range(n), n - s):
            for order in (free, tuple(rng.permutation(free))):
                E = jnp.eye(n)[jnp.asarray(order)]
                np.testing.assert_allclose(fast_quality(G, jnp.asarray(order)), full_quality(E, G), rtol=1e-12, atol=1e-14)
    G = jnp.asarray(rng.normal(size=(2, 5)))
    a, b = partition_qualities(G, jnp.array([0, 1, 2]), jnp.array([2, 3, 4]))
    np.testing.assert_allclose([a, b], [selection_quality(jnp.eye(5)[:3], G), selection_quality(jnp.eye(5)[2:], G)],
                               rtol=1e-12)
    assert float(partition_qualities(G, jnp.array([0, 0, 1]))[0]) == 0.0  # a repeated index: singular


def test_nonlinear_constraint_against_lagrange_multipliers():
    """A sliding disk whose angular speed is held constant (f* = |ω|² − ω₀² = 0, nonlinear
    in x): Maggi with A = ∂x/∂ε (AD) vs the multiplier solution written here."""
    base = dk.disk_on_plane()
    speed = maggi.VelocityConstraint(
        lambda b, t, q, x: x[0] ** 2 + x[1] ** 2 + x[2] ** 2 - 26.0, size=1, label="spin rate", linear=False
    )
    q0 = jnp.array([0.0, 0.0, 0.0, TH, 0.0])
    x0 = jnp.array([0.4, -0.7, jnp.sqrt(26.0 - 0.65), 0.6, 0.8])
    s = maggi.constrain(base, [speed], q_ref=q0, x_ref=x0)
    r = s.solve(0.0, q0, x0)
    D, h = base.bracket_terms(0.0, q0, x0)
    G = jnp.array([[2 * x0[0], 2 * x0[1], 2 * x0[2], 0.0, 0.0]])
    # KKT: D ẋ + h = Gᵀλ, G ẋ = 0 (f* does not depend on t, q)
    K = jnp.block([[D, -G.T], [G, jnp.zeros((1, 1))]])
    sol = np.linalg.solve(np.asarray(K), np.concatenate([-np.asarray(h), [0.0]]))
    np.testing.assert_allclose(r.xdot, sol[:5], rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(r.reactions, sol[5:], rtol=1e-11)
    traj = jb.simulate(s, q0, x0, 2.0, rtol=1e-10, atol=1e-10, n_save=5)
    np.testing.assert_allclose(jnp.sum(traj.v[:, :3] ** 2, axis=1), 26.0, rtol=1e-9)
    assert abs(float(r.reactions[0])) > 1e-2


def test_vmap_over_1024_disk_states():
    s = regimes()[2]
    rng = np.random.default_rng(2)
    states = [rolling_state(rng) for _ in range(1024)]
    qs = jnp.stack([q for q, _ in states])
    xs = jnp.stack([x for _, x in states])
    f = jax.jit(jax.vmap(lambda q, x: s.solve(0.0, q, x)))
    out = f(qs, xs)
    assert out.A.shape == (1024, 5, 3) and out.K.shape == (1024, 5, 2) and out.reactions.shape == (1024, 2)
    assert bool(jnp.all(out.result._value == 0))
    for i in (0, 511, 1023):
        one = s.solve(0.0, qs[i], xs[i])
        np.testing.assert_allclose(out.xdot[i], one.xdot, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(out.reactions[i], one.reactions, rtol=1e-12, atol=1e-12)
    # parameters batch too: reactions scale with the mass
    masses = jnp.linspace(1.0, 3.0, 8)
    lam = jax.vmap(lambda m: dk.rolling_disk(base=dk.DiskOnPlane(mass=m, radius=jnp.asarray(RHO), gravity=jnp.asarray(9.81))).solve(0.0, qs[0], xs[0]).reactions)(masses)
    np.testing.assert_allclose(lam / masses[:, None], np.broadcast_to(lam[:1] / masses[0], lam.shape), rtol=1e-12)


@pytest.mark.parametrize("to", [1, 2])
def test_switch_projection_energy_and_impulse(to):
    """Sliding → skating / rolling: x⁺ = A(AᵀDA)⁻¹AᵀD x⁻, energy lost = ½ΔxᵀDΔx ≥ 0."""
    new = regimes()[to]
    rng = np.random.default_rng(4)
    for _ in range(3):
        q = jnp.asarray(rng.uniform(-1, 1, 5)).at[3].set(rng.uniform(0.5, 2.6))
        x = jnp.asarray(rng.normal(size=5))
        rep = maggi.switch_constraints(new, 0.0, q, x)
        np.testing.assert_allclose(new.constraint_residual(0.0, q, rep.x_after), 0.0, atol=1e-12)
        D = new.kinetic_metric(0.0, q, x)
        A = new.solve(0.0, q, x).A
        expected = A @ np.linalg.solve(A.T @ D @ A, A.T @ D @ x)
        np.testing.assert_allclose(rep.x_after, expected, rtol=1e-10, atol=1e-12)
        dx = x - rep.x_after
        assert float(rep.energy_lost) >= 0.0
        np.testing.assert_allclose(rep.energy_lost, 0.5 * dx @ D @ dx, rtol=1e-12)
        np.testing.assert_allclose(rep.energy_before - rep.energy_after, rep.energy_lost, rtol=1e-10, atol=1e-12)
        # the generalized impulse is carried by the constraints: D Δx = Gᵀ Π
        G = new.constraint_jacobian(0.0, q, x)
        np.testing.assert_allclose(rep.generalized_impulse, G.T @ rep.impulse, atol=1e-12)
        # switching back to a looser set keeps the velocity
        back = maggi.switch_constraints(regimes()[to - 1], 0.0, q, rep.x_after)
        np.testing.assert_allclose(back.x_after, rep.x_after, atol=1e-13)
        np.testing.assert_allclose(back.energy_lost, 0.0, atol=1e-13)


def smooth_ice_rough_phases(x_ice=0.5, x_rough=1.2, transitions=()):
    """Sliding until the contact point reaches the ice at ``x_ice``, skating until the rough
    ground at ``x_rough``, then rolling: the phases ``jb.simulate`` runs."""
    slide, skate, roll = regimes()
    return jb.Phases(
        scenes=(jb.scene(slide), jb.scene(skate), jb.scene(roll)),
        events=(jb.Event(lambda t, q, x: slide.base.contact_point(q)[0] - x_ice),
                jb.Event(lambda t, q, x: skate.base.contact_point(q)[0] - x_rough)),
        transitions=transitions,
    )


@pytest.mark.slow  # about 45 s; the Maggi switching tests cover the default job
def test_smooth_ice_rough_run():
    slide, skate, roll = regimes()
    at_switch = []  # (t, q, x⁻) at each switch, as the phases hand it to the next constraint set

    def record(t, q, x):
        at_switch.append((t, q, x))
        return q, x

    phases = smooth_ice_rough_phases(transitions=(record, record))
    q0 = jnp.array([0.0, 0.0, 0.3, 1.3, 0.0])
    x0 = jnp.array([0.0, 0.5, 12.0, 1.0, 0.4])  # slides forward with lateral slip
    run = jb.simulate(phases, q0, x0, 3.0, n_save=61, rtol=1e-10, atol=1e-10)
    assert np.asarray(run.stats["switch_occurred"]).tolist() == [True, True] and len(at_switch) == 2
    t_ice, t_rough = (float(t) for t in run.stats["switch_time"])
    assert 0 < t_ice < t_rough < 3.0
    base = slide.base
    # the switches happen where the contact point enters the regions
    for (t_sw, q_sw, _), t_reported, edge in zip(at_switch, (t_ice, t_rough), (0.5, 1.2)):
        assert float(t_sw) == t_reported
        np.testing.assert_allclose(base.contact_point(q_sw)[0], edge, atol=1e-8)
    lost = np.asarray(run.stats["switch_energy_lost"])
    for (t_sw, q_sw, x_before), new, lost_k in zip(at_switch, (skate, roll), lost):
        assert float(lost_k) > 0.0
        # x⁺: the impulsive projection onto the new constraints at the switch state
        x_after = maggi.switch_constraints(new.repartition(q_sw, x_before, t_sw), t_sw, q_sw, x_before).x_after
        dx = x_before - x_after
        D = slide.kinetic_metric(0.0, q_sw, x_before)
        np.testing.assert_allclose(lost_k, 0.5 * dx @ D @ dx, rtol=1e-12)
    # energy is conserved within each phase and drops by the reported amount at switches
    E = np.asarray(run.energy)
    ph = np.asarray(run.stats["phase"])
    for k in range(3):
        Ek = E[ph == k]
        np.testing.assert_allclose(Ek, Ek[0], rtol=1e-8)
    np.testing.assert_allclose(E[ph == 0][-1] - E[ph == 1][0], lost[0], rtol=1e-8)
    np.testing.assert_allclose(E[ph == 1][-1] - E[ph == 2][0], lost[1], rtol=1e-8)
    np.testing.assert_allclose(-np.asarray(run.stats["switch_energy_jump"]), lost, rtol=1e-8)
    for k, (t_sw, q_sw, x_before) in enumerate(at_switch):  # E just before each switch
        np.testing.assert_allclose(E[ph == k], float(regimes()[k].total_energy(q_sw, x_before)), rtol=1e-8)
    # constraints of each phase hold along it
    for k, sys in enumerate((slide, skate, roll)):
        m = ph == k
        vel = jax.vmap(sys.constraint_residual)(run.t[m], run.q[m], run.v[m])
        assert float(jnp.max(jnp.abs(vel), initial=0.0)) < 1e-8


@pytest.mark.slow
def test_time_triggered_switch():
    slide, _, roll = regimes()
    q0 = jnp.array([0.0, 0.0, 0.3, 1.3, 0.0])
    x0 = jnp.array([0.0, 0.5, 4.0, 1.0, 0.4])
    at_04 = jb.Phases(scenes=(jb.scene(slide), jb.scene(roll)), events=(jb.Event(lambda t, q, x: t - 0.4),))
    run = jb.simulate(at_04, q0, x0, 1.0, n_save=11, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(run.stats["switch_time"], [0.4])
    assert float(run.stats["switch_energy_lost"][0]) > 0
    with pytest.raises(ValueError, match="initial velocities violate the constraints"):
        jb.simulate(jb.Phases(scenes=(jb.scene(roll),), events=()), q0, x0, 1.0, rtol=1e-9, atol=1e-9)


def test_bad_epsilon_is_rejected_at_build_time():
    base = dk.disk_on_plane()
    q = jnp.array([0.0, 0.0, 0.0, TH, 0.0])
    roll = dk.rolling_disk().constraints
    with pytest.raises(ValueError, match=r"epsilon must give n - s = 5 - 2 = 3 characteristics, got 4"):
        maggi.constrain(base, roll, q_ref=q, epsilon=lambda b, t, q, x: x[:4])
    # (x1, x2, x5) with rolling: x5 follows from x1 already, x3 and x4 stay undetermined
    with pytest.raises(ValueError, match=r"epsilon does not complete the constraints to solvable extended characteristics"):
        maggi.constrain(base, roll, q_ref=q, epsilon=lambda b, t, q, x: jnp.stack([x[0], x[1], x[4]]))
    with pytest.raises(ValueError, match="constraints must be jaxbody.maggi.Constraint instances"):
        maggi.constrain(base, [lambda t, q, x: x[0]], q_ref=q)


from test_simulation_constrained import PointMass as _Particle  # noqa: E402  (one particle model for both files)


def test_phases_report_the_initial_velocity_correction():
    """project_initial=True: the projected start is the kinetic-metric closest admissible
    velocity, and the correction is returned (not thrown away)."""
    L = 1.3
    rod = maggi.VelocityConstraint(lambda b, t, q, x: (q @ x)[None] / L, size=1, label="rod",
                                   position=lambda b, t, q: ((q @ q - L**2) / (2 * L))[None])
    q0 = jnp.array([L * np.sin(0.3), -L * np.cos(0.3)])
    pend = maggi.constrain(_Particle(jnp.asarray(0.7)), [rod], q_ref=q0)
    one = jb.Phases(scenes=(jb.scene(pend),), events=())
    tol = dict(rtol=1e-9, atol=1e-9)
    bad = jnp.array([1.0, 2.0])  # has a radial component
    with pytest.raises(ValueError, match=r"initial velocities violate the constraints \['rod\[0\]'\]"):
        jb.simulate(one, q0, bad, 0.1, n_save=3, **tol)
    run = jb.simulate(one, q0, bad, 0.1, n_save=3, project_initial=True, **tol)
    correction = run.stats["v0_correction"]
    # the radial part removed: the tangential velocity kept (equal masses: Euclidean projection)
    radial = q0 / L
    np.testing.assert_allclose(correction, -(bad @ radial) * radial, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(run.v[0], bad + correction, rtol=1e-12)
    np.testing.assert_allclose(pend.constraint_residual(0.0, q0, run.v[0]), 0.0, atol=1e-12)
    # admissible velocities pass untouched (and are not corrected when projection is asked for)
    jb.simulate(one, q0, run.v[0], 0.1, n_save=3, **tol)
    ok = jb.simulate(one, q0, run.v[0], 0.1, n_save=3, project_initial=True, **tol)
    np.testing.assert_array_equal(ok.stats["v0_correction"], 0.0)
    # positions off the rod: an error naming it, or projected onto it on request
    off = 1.05 * q0
    with pytest.raises(ValueError, match=r"initial positions violate the constraints \['rod\[0\]'\]"):
        jb.simulate(one, off, bad, 0.1, n_save=3, **tol)
    moved = jb.simulate(one, off, bad, 0.1, n_save=3, project_initial=True, **tol)
    assert float(jnp.linalg.norm(moved.q[0])) == pytest.approx(L, rel=1e-10)
    np.testing.assert_allclose(pend.constraint_residual(0.0, moved.q[0], moved.v[0]), 0.0, atol=1e-12)
