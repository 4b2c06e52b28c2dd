"""Phased scenes joined into one Solution, constraint checks of v0, failures that say when and where.

* ``jb.Phases`` runs carry the work of the non-conservative effects across switches and report the
  energy change at each switch: the balance ``E − E0 − Σ work`` closes across the whole run, the
  energy an impulsive constraint takes equals ``½ΔvᵀMΔv`` computed here with numpy from the mass
  matrix and the constraint Jacobian, and a phase with an added spring jumps by ``½k q²``;
* reactions and residuals are joined across phases (padded with NaN to the largest row count); in
  the smooth → ice → rough disk run they equal each phase's Maggi reactions at the saved states (slow);
* ``jb.simulate`` checks ``v0`` against a scene's constraints (or projects it on request), eagerly
  and under ``jit``;
* a failed solve under ``jit`` names the time reached and the state there (max steps, NaN blow-up).
"""

import functools
import re

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody import constraints as jc
from jaxbody import maggi

Y_DOWN = (0.0, -1.0, 0.0)
L1, L2, WALL = 0.8, 0.6, 0.5
TOL = dict(rtol=1e-10, atol=1e-10)


def pendulum(g=9.81):
    b = jb.ModelBuilder(gravity=np.array([0.0, 0.0, -g]))
    b.add_body("link", mass=1.3, com=np.array([0.0, 0.0, -0.4]), inertia=np.array([0.03, 0.02, 0.01]),
               joints=[jb.Hinge(axis=np.array([0.0, -1.0, 0.0]))])
    return b.build()


def double_pendulum():
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    b.add_body("link1", mass=1.0, com=(0, 0, -0.4), inertia=(0.05, 0.05, 0.1), joints=[jb.Hinge(axis=Y_DOWN)])
    b.add_body("link2", parent="link1", pos=(0, 0, -L1), mass=0.6, com=(0, 0, -0.3), inertia=(0.02, 0.02, 0.04),
               joints=[jb.Hinge(axis=Y_DOWN)])
    return b.build()


def tip(model, q):
    return jc.body_point(model, q, 1, jnp.array([0.0, 0.0, -L2]))


@functools.lru_cache
def wall_phases():
    """A double pendulum swinging freely until its tip reaches the wall x = WALL, then sliding
    along it (a point-on-plane constraint: 0 rows, then 1)."""
    model = double_pendulum()
    wall = jc.PointOnPlane(model, "link2", (0, 0, -L2), normal=(1, 0, 0), origin=(WALL, 0, 0))
    free = jb.scene(model)
    on_wall = jb.scene(model, constraints=[wall])
    hits = jb.Event(lambda t, q, v: tip(model, q)[0] - WALL, direction=True)
    return model, wall, jb.Phases(scenes=(free, on_wall), events=(hits,))


def wall_state():
    return jnp.array([0.1, 0.2]), jnp.array([2.5, 1.0])


@functools.lru_cache
def wall_run():
    q0, v0 = wall_state()
    return jb.simulate(wall_phases()[2], q0, v0, 1.0, n_save=41, **TOL)


class PlaneMass(eqx.Module):
    """A point mass in a vertical plane, q = (x, z), quasi-velocities x = q̇: a base system for
    jaxbody.maggi (bracket 𝓔 = D ẋ + h with D = m·1, h = (0, m g))."""

    mass: jax.Array
    nq: int = eqx.field(static=True, default=2)
    nv: int = eqx.field(static=True, default=2)

    def qdot(self, q, x):
        return x

    def bracket_terms(self, t, q, x, tau=None):
        h = jnp.stack([jnp.zeros_like(self.mass), self.mass * 9.81])
        return self.mass * jnp.eye(2, dtype=x.dtype), h if tau is None else h - tau

    def total_energy(self, q, x):
        return 0.5 * self.mass * (x @ x) + self.mass * 9.81 * q[1]


INCLINE = np.array([np.cos(0.4), np.sin(0.4)])


def on_incline():
    normal_rate = maggi.VelocityConstraint(lambda b, t, q, x: jnp.stack([INCLINE[0] * x[1] - INCLINE[1] * x[0]]),
                                           size=1, label="on the incline")
    return maggi.constrain(PlaneMass(jnp.asarray(2.0)), [normal_rate], q_ref=jnp.zeros(2))



G = 9.81
MASS = 2.0
ANGLE = 0.4


@functools.lru_cache
def incline_phases():
    """A point mass thrown sideways falls freely until it meets the incline z = x·tan(0.4), then
    slides on it (the normal rate is constrained to zero: an impulsive constraint at landing)."""
    base = PlaneMass(jnp.asarray(MASS))
    free = maggi.constrain(base, (), q_ref=jnp.zeros(2))
    lands = jb.Event(lambda t, q, v: q[1] - q[0] * np.tan(ANGLE), direction=False)
    return jb.Phases(scenes=(jb.scene(free), jb.scene(on_incline())), events=(lands,))


@functools.lru_cache
def incline_run():
    return jb.simulate(incline_phases(), jnp.array([0.0, 1.0]), jnp.array([1.0, 0.0]), 1.0, n_save=21, **TOL)


def landing():
    """Closed form of the free flight x = t, z = 1 − g t²/2 down to the incline: (t, v⁻)."""
    t = (-np.tan(ANGLE) + np.sqrt(np.tan(ANGLE) ** 2 + 2 * G)) / G
    return t, np.array([1.0, -G * t])


def test_energy_lost_at_a_constraint_switch_equals_the_reported_jump():
    """Landing on the incline: the normal rate n·v⁻ is removed, so ½m(n·v⁻)² is lost (closed form),
    the reported jump is minus that, and the balance with work["switches"] closes across the run."""
    sol = incline_run()
    t_land, v_minus = landing()
    normal = np.array([-np.sin(ANGLE), np.cos(ANGLE)])
    lost = 0.5 * MASS * (normal @ v_minus) ** 2
    assert bool(sol.success) and bool(sol.stats["switch_occurred"][0])
    np.testing.assert_allclose(sol.stats["switch_time"], [t_land], rtol=1e-12)
    np.testing.assert_allclose(sol.stats["switch_energy_lost"], [lost], rtol=1e-10)
    np.testing.assert_allclose(sol.stats["switch_energy_jump"], [-lost], rtol=1e-10)
    ph = np.asarray(sol.stats["phase"])
    np.testing.assert_array_equal(ph, (np.asarray(sol.t) > t_land).astype(int))
    E = np.asarray(sol.energy)
    np.testing.assert_allclose(E[ph == 0], E[0], rtol=1e-10)
    np.testing.assert_allclose(E[ph == 1], E[0] - lost, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(sol.work["switches"]), np.where(ph == 1, -lost, 0.0), rtol=1e-12)
    np.testing.assert_allclose(sol.energy_balance, 0.0, atol=1e-9 * abs(E[0]))
    assert float(sol.energy_drift) < 1e-9


def test_an_event_that_never_triggers_leaves_the_later_phases_empty():
    """Thrown from 10 m the mass is still in flight at t1: one phase, no switch, plain free fall."""
    sol = jb.simulate(incline_phases(), jnp.array([0.0, 10.0]), jnp.array([1.0, 0.0]), 1.0, n_save=21, **TOL)
    assert bool(sol.success) and not bool(sol.stats["switch_occurred"][0])
    assert np.isnan(float(sol.stats["switch_time"][0]))
    np.testing.assert_array_equal(sol.stats["phase"], 0)
    np.testing.assert_array_equal(sol.stats["switch_energy_jump"], 0.0)
    assert np.all(np.isnan(np.asarray(sol.reactions)))
    t = np.asarray(sol.t)
    np.testing.assert_allclose(sol.q[:, 1], 10.0 - 0.5 * G * t**2, rtol=1e-10)
    np.testing.assert_allclose(float(sol.t_final), 1.0)


def test_reactions_and_residuals_are_joined_and_padded():
    """0 constraint rows in flight, 1 on the incline: one column, NaN in flight; on the incline the
    reaction is the normal force m g cos(0.4) (the acceleration is along the incline)."""
    sol = incline_run()
    ph = np.asarray(sol.stats["phase"])
    assert set(ph.tolist()) == {0, 1}
    assert sol.reactions.shape == (21, 1)
    assert sol.constraint_drift["position"].shape == sol.constraint_drift["velocity"].shape == (21, 1)
    lam = np.asarray(sol.reactions)
    assert np.all(np.isnan(lam[ph == 0])) and np.all(np.isnan(np.asarray(sol.constraint_drift["velocity"])[ph == 0]))
    np.testing.assert_allclose(lam[ph == 1, 0], MASS * G * np.cos(ANGLE), rtol=1e-9)
    assert float(np.max(np.abs(np.asarray(sol.constraint_drift["velocity"])[ph == 1]))) < 1e-10
    lay = dict(sol.layout)
    assert lay["phase_constraint_names"] == ((), ("on the incline[0]",)) and "constraint_names" not in lay
    # on the incline the mass slides with s'' = −g sin(0.4) from the projected rate
    t_land, v_minus = landing()
    along = np.array([np.cos(ANGLE), np.sin(ANGLE)])
    t = np.asarray(sol.t)[ph == 1] - t_land
    s = (np.asarray(sol.q)[ph == 1] - np.array([t_land, 1 - 0.5 * G * t_land**2])) @ along
    np.testing.assert_allclose(s, (along @ v_minus) * t - 0.5 * G * np.sin(ANGLE) * t**2, atol=1e-9)


@pytest.mark.slow  # ~15 s (40 s on a loaded machine): both phases compiled again under vmap
def test_phases_under_jit_and_vmap_equal_the_eager_run():
    """Two throws from different heights in one vmapped program: the member equal to the eager
    run matches it, the other lands later; switch reports come per member."""
    q0s = jnp.array([[0.0, 1.0], [0.0, 1.5]])
    v0 = jnp.array([1.0, 0.0])
    phases = incline_phases()  # built outside the trace (the constraints are checked at build time)
    run = jax.jit(jax.vmap(lambda q0: jb.simulate(phases, q0, v0, 1.0, n_save=21, **TOL)))
    both = run(q0s)
    one = incline_run()
    assert both.stats["switch_energy_lost"].shape == (2, 1) and both.reactions.shape == (2, 21, 1)
    np.testing.assert_allclose(both.q[0], one.q, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(both.stats["switch_energy_lost"][0], one.stats["switch_energy_lost"], rtol=1e-12)
    np.testing.assert_allclose(both.reactions[0], one.reactions, rtol=1e-9)
    assert float(both.stats["switch_time"][1, 0]) > float(both.stats["switch_time"][0, 0])
    assert bool(jnp.all(both.energy_drift < 1e-9))


# ----------------------------------------------------------------------------- energy across switches
def test_two_phase_energy_balance_closes_across_the_switch():
    """Pendulum: gravity only, then a damper from the first downward zero crossing on."""
    m = pendulum()
    free, damped = jb.scene(m), jb.scene(m, dampers=jnp.array([0.5]))
    ph = jb.Phases(scenes=(free, damped), events=(jb.Event(lambda t, q, v: q[0], direction=False),))
    sol = jb.simulate(ph, jnp.array([0.5]), jnp.array([0.0]), 2.0, n_save=41, **TOL)
    assert set(sol.work) == {"dampers", "switches"}
    assert bool(sol.stats["switch_occurred"][0])
    t_sw = float(sol.stats["switch_time"][0])
    assert 0.0 < t_sw < 2.0
    # same energy function on both sides: no jump, nothing lost
    np.testing.assert_allclose(sol.stats["switch_energy_jump"], 0.0, atol=1e-14)
    np.testing.assert_allclose(sol.work["switches"], 0.0, atol=1e-14)
    before = np.asarray(sol.t) <= t_sw
    np.testing.assert_array_equal(np.asarray(sol.stats["phase"]), (~before).astype(int))
    # the damper works only after the switch, and it dissipates
    np.testing.assert_allclose(np.asarray(sol.dissipation)[before], 0.0, atol=1e-14)
    assert float(sol.dissipation[-1]) > 0.1
    # the balance closes over the whole run to the tolerance asked
    assert float(sol.energy_drift) < 1e-8
    np.testing.assert_allclose(sol.energy_balance, 0.0, atol=1e-8 * abs(float(sol.energy[0])))
    # the dissipation is the integral of c v² over the damped part (trapezoid on the saved grid)
    t = np.asarray(sol.t)[~before]
    v = np.asarray(sol.v[:, 0])[~before]
    np.testing.assert_allclose(float(sol.dissipation[-1] - sol.dissipation[~before][0]), 0.5 * np.trapezoid(v**2, t), rtol=5e-3)


def test_switch_to_a_phase_with_another_potential_reports_the_jump():
    """A spring of stiffness k appears at t = 0.3: E jumps by ½k q(0.3)² and the balance still closes."""
    m = pendulum()
    k = 3.0
    ph = jb.Phases(scenes=(jb.scene(m), jb.scene(m, springs=jnp.array([k]))),
                   events=(jb.Event(lambda t, q, v: t - 0.3),))
    sol = jb.simulate(ph, jnp.array([0.5]), jnp.array([0.0]), 1.0, n_save=11, **TOL)
    np.testing.assert_allclose(sol.stats["switch_time"], [0.3], atol=1e-12)
    i = int(np.flatnonzero(np.isclose(np.asarray(sol.t), 0.3))[0])
    q_sw = float(sol.q[i, 0])
    np.testing.assert_allclose(sol.stats["switch_energy_jump"], [0.5 * k * q_sw**2], rtol=1e-9)
    np.testing.assert_allclose(sol.stats["switch_energy_lost"], [0.0], atol=0)
    # E itself jumps; the reported jump accounts for it in the balance
    E = np.asarray(sol.energy)
    np.testing.assert_allclose(E[i + 1:] - E[0], 0.5 * k * q_sw**2, rtol=1e-7)
    assert float(sol.energy_drift) < 1e-8


@pytest.mark.slow  # ~30 s: compiles the free (planar) and the constrained (spatial) double pendulum
def test_energy_lost_when_a_pendulum_tip_hits_a_wall_equals_the_reported_jump():
    """Tip hits a wall: the velocity is projected on the plane (impulsive constraint); the energy
    lost is ½ΔvᵀMΔv with Δv = M⁻¹Gᵀ(GM⁻¹Gᵀ)⁻¹Gv⁻ computed here, and equals −(reported jump)."""
    model, wall, _ = wall_phases()
    sol = wall_run()
    assert bool(sol.stats["switch_occurred"][0]) and bool(sol.success)
    t_sw = float(sol.stats["switch_time"][0])
    ph = np.asarray(sol.stats["phase"])
    # the state just before the switch: the free run stopped by the same event
    q0, v0 = wall_state()
    first = jb.simulate(wall_phases()[2].scenes[0], q0, v0, 1.0, event=wall_phases()[2].events[0], n_save=41, **TOL)
    np.testing.assert_allclose(float(first.t_final), t_sw, atol=1e-12)
    q, v = np.asarray(first.q_final), np.asarray(first.v_final)
    np.testing.assert_allclose(tip(model, q)[0], WALL, atol=1e-10)
    M = np.asarray(jb.mass_matrix(model, q))
    G = np.asarray(jax.jacfwd(lambda qq: tip(model, qq)[0])(jnp.asarray(q)))[None, :]
    Mi_Gt = np.linalg.solve(M, G.T)
    dv = Mi_Gt @ np.linalg.solve(G @ Mi_Gt, G @ v)
    lost = 0.5 * dv @ M @ dv
    assert lost > 1e-3
    np.testing.assert_allclose(sol.stats["switch_energy_lost"], [lost], rtol=1e-9)
    np.testing.assert_allclose(sol.stats["switch_energy_jump"], [-lost], rtol=1e-9)
    # E drops by that amount at the switch; with work["switches"] the balance closes
    E = np.asarray(sol.energy)
    np.testing.assert_allclose(E[ph == 1] - E[0], -lost, rtol=1e-7)
    np.testing.assert_allclose(np.asarray(sol.work["switches"])[ph == 1], -lost, rtol=1e-12)
    assert float(sol.energy_drift) < 1e-8


# ----------------------------------------------------------------------------- reactions across phases
@pytest.mark.slow  # shares the run of the test above
def test_wall_reactions_and_residuals_are_joined_and_padded():
    model, wall, phases = wall_phases()
    sol = wall_run()
    ph = np.asarray(sol.stats["phase"])
    assert set(ph.tolist()) == {0, 1}
    assert sol.reactions.shape == (41, 1)
    assert sol.constraint_drift["position"].shape == sol.constraint_drift["velocity"].shape == (41, 1)
    # no constraint rows before the wall: NaN padding; after it: the wall's row
    assert np.all(np.isnan(np.asarray(sol.reactions)[ph == 0]))
    assert np.all(np.isfinite(np.asarray(sol.reactions)[ph == 1]))
    lay = dict(sol.layout)
    assert lay["phase_constraint_names"] == ((), wall.names)
    assert "constraint_names" not in lay
    # the tip stays on the wall after the switch
    assert float(np.max(np.abs(np.asarray(sol.constraint_drift["position"])[ph == 1]))) < 1e-9
    assert float(np.max(np.abs(np.asarray(sol.constraint_drift["velocity"])[ph == 1]))) < 1e-8
    tips = np.asarray(jax.jit(jax.vmap(lambda q: tip(model, q)))(sol.q))
    np.testing.assert_allclose(tips[ph == 1, 0], WALL, atol=1e-9)
    # the reaction is the wall's normal force: the Maggi solve of the constrained system at the saved states
    cs = phases.scenes[1].constraints
    lam = jax.jit(jax.vmap(lambda t, q, v: cs.solve(t, q, v, stabilise=True).reactions))(sol.t[ph == 1], sol.q[ph == 1], sol.v[ph == 1])
    np.testing.assert_allclose(np.asarray(sol.reactions)[ph == 1], lam, rtol=1e-7, atol=1e-8)


def test_phased_solution_round_trips_through_a_file(tmp_path):
    sol = incline_run()
    sol.save(tmp_path / "wall.npz")
    back = jb.load_solution(tmp_path / "wall.npz")
    assert dict(back.layout)["phase_constraint_names"] == dict(sol.layout)["phase_constraint_names"] == ((), ("on the incline[0]",))
    hash(back.layout)
    np.testing.assert_array_equal(back.reactions, sol.reactions)
    np.testing.assert_array_equal(back.work["switches"], sol.work["switches"])
    np.testing.assert_array_equal(back.stats["switch_energy_jump"], sol.stats["switch_energy_jump"])


@pytest.mark.slow  # ~45 s: compiles the disk's autodiff bracket for three regimes
def test_disk_smooth_ice_rough_run():
    """The smooth → ice → rough disk run joined into one Solution: grid saves with their phase,
    reactions equal Λ = Kᵀ𝓔 of each phase's system at the saved states (padded with NaN),
    switch energies, constraints held."""
    from jaxbody.examples import disk as dk

    slide, skate, roll = dk.sliding_disk(), dk.skating_disk(), dk.rolling_disk()
    to_ice = lambda t, q, x: slide.base.contact_point(q)[0] - 0.5  # noqa: E731
    to_rough = lambda t, q, x: skate.base.contact_point(q)[0] - 1.2  # noqa: E731
    q0 = jnp.array([0.0, 0.0, 0.3, 1.3, 0.0])
    x0 = jnp.array([0.0, 0.5, 12.0, 1.0, 0.4])
    n = 61
    ph = jb.Phases(scenes=(jb.scene(slide), jb.scene(skate), jb.scene(roll)), events=(jb.Event(to_ice), jb.Event(to_rough)))
    sol = jb.simulate(ph, q0, x0, 3.0, n_save=n, **TOL)
    np.testing.assert_allclose(sol.t, np.linspace(0.0, 3.0, n), rtol=0, atol=1e-13)
    t_sw = np.asarray(sol.stats["switch_time"])
    assert np.asarray(sol.stats["switch_occurred"]).tolist() == [True, True] and 0 < t_sw[0] < t_sw[1] < 3.0
    phase = np.asarray(sol.stats["phase"])
    np.testing.assert_array_equal(phase, np.searchsorted(t_sw, np.asarray(sol.t), side="left"))
    # reactions: 0, 1 and 2 rows; padded with NaN to 2 columns
    lam_ref = np.full((n, 2), np.nan)
    for k, system in enumerate((slide, skate, roll)):
        rows = np.flatnonzero(phase == k)
        if system.n_constraint:
            lam = maggi.reactions(system, sol.t[rows], sol.q[rows], sol.v[rows])
            lam_ref[rows, : lam.shape[1]] = np.asarray(lam)
    np.testing.assert_array_equal(np.isnan(np.asarray(sol.reactions)), np.isnan(lam_ref))
    # jb reports the reactions of its (Baumgarte-stabilised) vector field, maggi.reactions the
    # plain ones: they differ by the stabilisation terms, ω times residuals of ~1e-11
    scale = np.nanmax(np.abs(lam_ref))
    np.testing.assert_allclose(np.asarray(sol.reactions), lam_ref, rtol=0, atol=1e-10 * scale)
    assert dict(sol.layout)["phase_constraint_names"] == (slide.constraint_names, skate.constraint_names, roll.constraint_names)
    # switches: energy lost by the projection, and the jump of E it causes
    lost = np.asarray(sol.stats["switch_energy_lost"])
    assert np.all(lost > 0)
    np.testing.assert_allclose(sol.stats["switch_energy_jump"], -lost, rtol=1e-9)
    assert float(sol.energy_drift) < 1e-8
    vel = np.asarray(sol.constraint_drift["velocity"])
    assert float(np.nanmax(np.abs(vel))) < 1e-8


# ----------------------------------------------------------------------------- v0 against constraints
def wall_at(model, q):
    """A point-on-plane constraint through the tip at ``q`` (a scene built at that state)."""
    x_tip = float(tip(model, q)[0])
    wall = jc.PointOnPlane(model, "link2", (0, 0, -L2), normal=(1, 0, 0), origin=(x_tip, 0, 0))
    return wall, jb.scene(model, constraints=maggi.constrain(model, [wall], q_ref=q))


def test_v0_violating_a_scene_constraint_slot_is_named():
    model = double_pendulum()
    q_on = jnp.array([0.6, -0.4])
    wall, sc = wall_at(model, q_on)
    name = re.escape(repr(list(wall.names)))
    with pytest.raises(ValueError, match=r"simulate: v0: initial velocities violate the constraints " + name + r" \(residuals \["):
        jb.simulate(sc, q_on, jnp.array([1.0, 0.5]), 0.2, n_save=3)


@pytest.mark.slow  # ~25 s: compiles the constrained spatial double pendulum
def test_v0_projected_on_a_scene_constraint_slot():
    """The closest admissible rates in kinetic energy, v − M⁻¹Gᵀ(GM⁻¹Gᵀ)⁻¹Gv (numpy here), with the
    correction reported; admissible rates pass untouched."""
    model = double_pendulum()
    q_on = jnp.array([0.6, -0.4])
    _, sc = wall_at(model, q_on)
    bad = jnp.array([1.0, 0.5])
    sol = jb.simulate(sc, q_on, bad, 1.0, n_save=41, project_initial=True, **TOL)
    M = np.asarray(jb.mass_matrix(model, q_on))
    G = np.asarray(jax.jacfwd(lambda qq: tip(model, qq)[0])(q_on))[None, :]
    Mi_Gt = np.linalg.solve(M, G.T)
    expected = np.asarray(bad) - Mi_Gt @ np.linalg.solve(G @ Mi_Gt, G @ np.asarray(bad))
    np.testing.assert_allclose(sol.v[0], expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.stats["v0_correction"], expected - np.asarray(bad), rtol=1e-12, atol=1e-12)
    _, _, corr = maggi.initial_state(sc.constraints, q_on, bad, project_initial=True)
    np.testing.assert_allclose(sol.stats["v0_correction"], corr, rtol=1e-12, atol=1e-14)
    assert float(np.max(np.abs(np.asarray(sol.constraint_drift["velocity"])))) < 1e-9
    again = jb.simulate(sc, q_on, sol.v[0], 1.0, n_save=41, project_initial=True, **TOL)
    np.testing.assert_array_equal(again.stats["v0_correction"], 0.0)


def test_v0_check_and_projection_eager_and_under_jit():
    """Concrete v0: ValueError naming the row; traced v0: the same message from eqx.error_if;
    throw=False gives the result code; the projection (here the orthogonal one: D = m·1) is
    reported eagerly and runs inside jit too."""
    cs = on_incline()
    q0 = jnp.zeros(2)
    bad = jnp.array([1.0, 0.0])
    along = float(bad @ INCLINE) * INCLINE
    run = jax.jit(lambda v, throw: jb.simulate(cs, q0, v, 0.5, n_save=3, throw=throw, **TOL), static_argnums=1)
    message = re.escape(f"simulate: v0: initial velocities violate the constraints {list(cs.constraint_names)}")
    assert cs.constraint_names == ("on the incline[0]",)
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(run(bad, True).q)
    codes = jax.vmap(lambda v: run(v, False).result._value)(jnp.stack([jnp.asarray(along), bad]))
    assert codes.tolist() == [int(jb.RESULTS.successful._value), int(jb.RESULTS.invalid_input._value)]
    with pytest.raises(ValueError, match=message):
        jb.simulate(cs, q0, bad, 0.5)
    eager = jb.simulate(cs, q0, bad, 0.5, n_save=3, project_initial=True, **TOL)
    np.testing.assert_allclose(eager.stats["v0_correction"], along - np.asarray(bad), rtol=1e-13, atol=1e-15)
    proj = jax.jit(lambda v: jb.simulate(cs, q0, v, 0.5, n_save=3, project_initial=True, **TOL))(bad)
    np.testing.assert_allclose(proj.q, eager.q, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(proj.v[0], along, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(proj.stats["v0_correction"], along - np.asarray(bad), rtol=1e-13, atol=1e-15)
    # then it slides down the incline: s'' = −g sin(0.4) along it
    s = np.asarray(proj.q) @ INCLINE
    t = np.asarray(proj.t)
    np.testing.assert_allclose(s, float(bad @ INCLINE) * t - 0.5 * 9.81 * INCLINE[1] * t**2, atol=1e-9)


def test_v0_checked_against_a_constrained_system_and_the_first_phase():
    """A phased run checks v0 against its first phase only (later phases get projected rates)."""
    model, wall, phases = wall_phases()
    q0, v0 = wall_state()
    wall_first = jb.Phases(scenes=(phases.scenes[1], phases.scenes[0]), events=(jb.Event(lambda t, q, v: t - 0.1),))
    # the wall phase first: its start is off the wall, which the position check names before v0's
    with pytest.raises(ValueError, match=r"simulate: q0: initial positions violate the constraints " + re.escape(repr(list(wall.names)))):
        jb.simulate(wall_first, q0, v0, 0.2)
    with pytest.raises(ValueError, match=r"simulate: tau, event cannot be given with jaxbody.Phases"):
        jb.simulate(phases, q0, v0, 0.2, tau=jnp.zeros(2), event=lambda t, q, v: q[0])


# ----------------------------------------------------------------------------- failures under jit
def test_max_steps_failure_under_jit_says_when_and_where():
    m = pendulum()
    q0, v0 = jnp.array([0.5]), jnp.array([0.0])
    kw = dict(max_steps=5, **TOL)
    soft = jax.jit(lambda q: jb.simulate(m, q, v0, 2.0, throw=False, **kw))(q0)
    assert bool(soft.result == jb.RESULTS.max_steps_reached)
    t_fail = float(soft.t_final)
    assert 0.0 < t_fail < 2.0 and np.all(np.isfinite(np.asarray(soft.q_final)))
    reached = np.isfinite(np.asarray(soft.t)) & np.isfinite(np.asarray(soft.q[:, 0]))
    assert np.asarray(soft.t)[reached].max() <= t_fail
    expected = (rf"simulate: the solve failed at t = {t_fail:.6g}: The maximum number of solver steps was reached"
                rf".*\n  state at the failure: q = \[{float(soft.q_final[0]):.6g}")
    with pytest.raises(Exception, match=expected):
        jax.block_until_ready(jax.jit(lambda q: jb.simulate(m, q, v0, 2.0, **kw).q)(q0))
    # eagerly: the same text as a SimulationError
    with pytest.raises(jb.SimulationError, match=expected):
        jb.simulate(m, q0, v0, 2.0, **kw)

    # a vmapped batch names the member that failed: the stiff one needs far more than 200 steps
    def member(k):
        return jb.simulate(Spring(k), jnp.array([1.0]), jnp.array([0.0]), 1.0, max_steps=200, n_save=5).q

    with pytest.raises(Exception, match=r"failed at t = [0-9.e-]+ \(batch member 1 of 3\): The maximum number"):
        jax.block_until_ready(jax.jit(jax.vmap(member))(jnp.array([1.0, 1e8, 4.0])))


class Spring(eqx.Module):
    """x'' = −k x (a protocol object: nq, nv, qdot, acceleration)."""

    k: jax.Array
    nq: int = eqx.field(static=True, default=1)
    nv: int = eqx.field(static=True, default=1)

    def qdot(self, q, v):
        return v

    def acceleration(self, t, q, v, tau):
        return -self.k * q


def test_nan_blow_up_under_jit_says_when_and_where():
    """Explicit Euler on a stiff spring (h·√k = 10) grows ~10× a step until it overflows: the solve
    stops there (result ``nonfinite``) instead of carrying inf/NaN to t1 as a success."""
    sys = Spring(jnp.asarray(1e6))
    q0, v0 = jnp.array([1.0]), jnp.array([0.0])
    kw = dict(solver="euler", dt0=0.01, n_save=11)
    soft = jax.jit(lambda q: jb.simulate(sys, q, v0, 5.0, throw=False, **kw))(q0)
    assert bool(soft.result == jb.RESULTS.nonfinite) and not bool(soft.success)
    t_fail = float(soft.t_final)
    assert 1.0 < t_fail < 5.0
    # the Euler recursion q ← q + v·h, v ← v + (−k·q)·h in numpy: the solve stops at its first
    # non-finite state (k·q overflows first, so v is −inf there while q is still finite)
    q, v, n = 1.0, 0.0, 0
    with np.errstate(over="ignore", invalid="ignore"):
        while np.isfinite(q) and np.isfinite(v):
            q, v, n = q + v * 0.01, v + (-1e6 * q) * 0.01, n + 1
    np.testing.assert_allclose(t_fail, n * 0.01, rtol=1e-12)
    np.testing.assert_allclose([float(soft.q_final[0]), float(soft.v_final[0])], [q, v], rtol=1e-12)
    # the saved trajectory before it is finite and follows the recursion's growth
    saved = np.asarray(soft.t) < t_fail
    assert saved.sum() >= 3 and np.all(np.isfinite(np.asarray(soft.q)[saved]))
    with pytest.raises(Exception, match=rf"simulate: the solve failed at t = {t_fail:.6g}: the state became NaN or inf"
                                        r".*\n  state at the failure: q = \[-?[0-9.]+e\+[0-9]+\], v = \[-inf\]"):
        jax.block_until_ready(jax.jit(lambda q: jb.simulate(sys, q, v0, 5.0, **kw).q)(q0))


@pytest.mark.parametrize("saves", ["n_save", "t1"])
def test_a_batch_member_that_blows_up_gets_its_own_outcome(saves):
    """With fixed steps under vmap, the members that blow up (explicit Euler on stiff springs)
    are recorded and the loop runs on for the others: every member's solution (result code,
    final time and state, step counts, saved times and states, padded with inf after the
    failure) equals the solve of that member alone, which stops at its failure."""
    ks = jnp.array([1.0, 1e6, 4.0, 3e5])
    save = dict(n_save=11) if saves == "n_save" else dict(saveat=diffrax.SaveAt(t1=True))

    def run(k):
        return jb.simulate(Spring(k), jnp.array([1.0]), jnp.array([0.0]), 5.0, solver="euler", dt0=0.01,
                           throw=False, **save)

    batch = jax.jit(jax.vmap(run))(ks)
    alone = jax.jit(run)
    codes = []
    for i, k in enumerate(ks):
        ref = alone(k)
        got = jax.tree.map(lambda x: x[i], batch)
        codes.append(int(got.result._value))
        assert int(got.result._value) == int(ref.result._value)
        for name in ("t_final", "q_final", "v_final", "t", "q", "v"):
            np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(ref, name)), err_msg=name)
        for name in ("num_steps", "num_accepted_steps", "num_rejected_steps"):
            assert int(got.stats[name]) == int(ref.stats[name]), name
    nonfinite, ok = int(jb.RESULTS.nonfinite._value), int(jb.RESULTS.successful._value)
    assert codes == [ok, nonfinite, ok, nonfinite]
    # the stiffer spring fails first; the others reach t1
    t_final = np.asarray(batch.t_final)
    assert t_final[1] < t_final[3] < 5.0 and t_final[0] == t_final[2] == 5.0
    # gradients: the members that did not fail get their own, untouched by the failed ones
    def final(k):
        return jb.simulate(Spring(k), jnp.array([1.0]), jnp.array([0.0]), 5.0, solver="euler", dt0=0.01,
                           throw=False, **save).q_final[0]

    grads = jax.jit(jax.vmap(jax.grad(final)))(ks)
    for i in (0, 2):
        np.testing.assert_allclose(float(grads[i]), float(jax.jit(jax.grad(final))(ks[i])), rtol=1e-12)
        assert np.isfinite(float(grads[i])) and float(grads[i]) != 0.0
    with pytest.raises(Exception, match=r"failed at t = [0-9.e-]+ \(batch member 1 of 4\): the state became NaN or inf"):
        jax.block_until_ready(jax.jit(jax.vmap(lambda k: jb.simulate(
            Spring(k), jnp.array([1.0]), jnp.array([0.0]), 5.0, solver="euler", dt0=0.01, **save).q))(ks))


@pytest.mark.slow  # about a minute (two compilations of a constrained RK4 solve)
def test_a_constrained_batch_with_fixed_steps_equals_its_members():
    """Fixed steps on a scene with Maggi constraints, where the re-partitioning solver wraps the
    guard that records failures: a vmapped batch equals its members solved alone (states,
    constraint reactions, result codes and repartition counts)."""
    model = double_pendulum()
    q0 = jnp.array([0.3, 0.5])
    x_tip = float(tip(model, q0)[0])
    wall = jc.PointOnPlane(model, "link2", (0, 0, -L2), normal=(1, 0, 0), origin=(x_tip, 0, 0))
    on_wall = jb.scene(model, constraints=[wall])
    v0s = jnp.array([[2.5, 1.0], [-1.0, 0.5], [0.3, 2.0]])

    def run(v0):
        return jb.simulate(on_wall, q0, v0, 0.3, solver="rk4", dt0=1e-3, n_save=7, project_initial=True, throw=False)

    batch = jax.jit(jax.vmap(run))(v0s)
    alone = jax.jit(run)
    for i in range(len(v0s)):
        ref = alone(v0s[i])
        assert int(batch.result._value[i]) == int(ref.result._value) == int(jb.RESULTS.successful._value)
        for name in ("q", "v", "reactions", "q_final", "v_final"):
            np.testing.assert_allclose(np.asarray(getattr(batch, name)[i]), np.asarray(getattr(ref, name)),
                                       rtol=1e-12, atol=1e-12, err_msg=name)
        assert int(batch.stats["num_repartitions"][i]) == int(ref.stats["num_repartitions"])
        # the tip stays on the wall
        np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(lambda q: tip(model, q)[0]))(batch.q[i])), x_tip, atol=1e-9)
