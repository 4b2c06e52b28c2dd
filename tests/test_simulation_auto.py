"""``solver="auto"``: the stiffness estimate against a closed form, the choice and its reason for
each kind of scene, tolerances from a target error, dtype-dependent defaults and the warning
below a dtype's resolution, and what a solve records in its ``Solution``.

Cheap: one-link and two-link models; the only compilations are one mass matrix per model and
one small solve.
"""

import math
import pathlib
import warnings

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jaxbody as jb
from jaxbody.kernels import spring_displacements, spring_dofs
from jaxbody.simulation import auto

M, COM, IC = 0.5, 0.1, 0.002  # link mass (kg), hinge-to-centre distance (m), central inertia (kg·m²)


def _chain_xml(stiffness, damping):
    body = ""
    for i, (k, c) in reversed(list(enumerate(zip(stiffness, damping)))):
        pos = "0 0 0" if i == 0 else "0 0 -0.2"
        body = (f'<body name="l{i}" pos="{pos}"><joint name="j{i}" type="hinge" axis="0 1 0" stiffness="{k:g}" '
                f'damping="{c:g}"/><inertial pos="0 0 -{COM}" mass="{M}" diaginertia="{IC} {IC} {IC}"/>{body}</body>')
    return f'<mujoco><option gravity="0 0 -9.81"/><worldbody>{body}</worldbody></mujoco>'


def _scene(stiffness, damping, dtype=None):
    # every stiffness test uses two links: one compilation of the mass matrix serves them all
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return jb.scene(jb.from_mjcf(_chain_xml(stiffness, damping), dtype=dtype))


@pytest.fixture(scope="module")
def pendulum():
    # no springs, no dampers: no stiffness estimate, nothing compiled by the choice
    return _scene([0.0], [0.0])


def test_stiffness_estimate_matches_the_closed_form_of_two_links():
    k, c = np.array([30.0, 400.0]), np.array([0.02, 0.3])
    est = auto.stiffness_estimate(_scene(k, c), jnp.zeros(2))
    # two links hanging straight (q = 0), hinges 0.2 m apart, centres COM below each hinge:
    # the mass matrix in the joint angles
    L = 0.2
    m22 = IC + M * COM**2
    m12 = m22 + M * COM * L
    m11 = IC + M * COM**2 + IC + M * ((L + COM) ** 2)
    mass = np.array([[m11, m12], [m12, m22]])
    w2, phi = scipy.linalg.eigh(np.diag(k), mass)
    assert est["omega"] == pytest.approx(math.sqrt(w2[-1]), rel=1e-10)
    assert est["omega_min"] == pytest.approx(math.sqrt(w2[0]), rel=1e-10)
    assert est["zeta"] == pytest.approx(phi[:, -1] @ np.diag(c) @ phi[:, -1] / (2 * math.sqrt(w2[-1])), rel=1e-10)
    assert est["decay"] == pytest.approx(scipy.linalg.eigh(np.diag(c), mass, eigvals_only=True)[-1], rel=1e-10)


def test_no_springs_or_dampers_no_estimate(pendulum):
    assert auto.stiffness_estimate(pendulum, jnp.zeros(1)) is None


def test_non_stiff_default_is_tsit5_at_the_default_tolerance(pendulum):
    choice = auto.choose_auto(pendulum, jnp.zeros(1), 0.0, 10.0, jnp.float64, None, None, None)
    assert (choice.solver, choice.rtol, choice.atol) == ("tsit5", 1e-8, 1e-8)
    assert "tsit5 is fastest" in choice.reason


def test_given_tight_tolerance_keeps_tsit5_and_says_how_to_get_dopri8(pendulum):
    choice = auto.choose_auto(pendulum, jnp.zeros(1), 0.0, 10.0, jnp.float64, 1e-11, 1e-11, None)
    assert choice.solver == "tsit5" and choice.rtol == 1e-11
    assert "give target_error to let auto take dopri8" in choice.reason


@pytest.mark.parametrize("target, solver", [(1e-4, "tsit5"), (1e-10, "dopri8")])
def test_target_error_sets_solver_and_tolerances(pendulum, target, solver):
    choice = auto.choose_auto(pendulum, jnp.zeros(1), 0.0, 10.0, jnp.float64, None, None, target)
    assert choice.solver == solver
    assert choice.rtol == choice.atol == pytest.approx(target / auto.ERROR_PER_TOLERANCE[solver])
    assert f"target error {target:g}" in choice.reason


def test_target_error_with_tolerances_or_bad_values_is_an_error(pendulum):
    with pytest.raises(ValueError, match="target_error or rtol/atol, not both"):
        auto.choose_auto(pendulum, jnp.zeros(1), 0.0, 1.0, jnp.float64, 1e-6, None, 1e-6)
    with pytest.raises(ValueError, match="target_error must be a positive finite number"):
        auto.choose_auto(pendulum, jnp.zeros(1), 0.0, 1.0, jnp.float64, None, None, -1.0)
    with pytest.raises(ValueError, match="target_error needs solver='auto'"):
        jb.simulate(pendulum, jnp.zeros(1), jnp.zeros(1), 1.0, solver="rk4", dt0=0.1, target_error=1e-6)


def test_stiff_lightly_damped_stays_explicit_with_the_reason():
    scene = _scene([1.0, 1e6], [0.01, 0.01])
    choice = auto.choose_auto(scene, jnp.zeros(2), 0.0, 5.0, jnp.float64, None, None, None)
    assert choice.solver == "tsit5"
    assert "lightly damped" in choice.reason and "any solver must resolve its oscillation" in choice.reason


def test_stiff_well_damped_picks_the_implicit_solver():
    # damping ratio about 1 on the stiff joint: the fast mode decays within a few of its periods
    scene = _scene([1.0, 1e6], [0.01, 2 * math.sqrt(1e6 * (IC + M * COM**2))])
    choice = auto.choose_auto(scene, jnp.zeros(2), 0.0, 5.0, jnp.float64, None, None, None)
    assert choice.solver == "kvaerno5"
    assert "stiff" in choice.reason and "damping ratio" in choice.reason
    # under jit/vmap the initial state is traced: the estimate is made at the model's qpos0
    seen = {}

    def traced(q):
        seen["choice"] = auto.choose_auto(scene, q, 0.0, 5.0, jnp.float64, None, None, None)
        return q

    jax.jit(traced)(jnp.zeros(2))
    assert seen["choice"] == choice


def test_float32_defaults_floor_and_warning(pendulum):
    assert auto.default_tolerance(jnp.float32) == auto.FLOAT32_TOLERANCE
    assert auto.default_tolerance(jnp.float64) == auto.FLOAT64_TOLERANCE
    choice = auto.choose_auto(pendulum, jnp.zeros(1, jnp.float32), 0.0, 1.0, jnp.float32, None, None, None)
    assert choice.rtol == choice.atol == auto.FLOAT32_TOLERANCE
    # a target float32 cannot reach: the tolerance stops at the floor and the reason says so
    choice = auto.choose_auto(pendulum, jnp.zeros(1, jnp.float32), 0.0, 1.0, jnp.float32, None, None, 1e-9)
    assert choice.rtol == auto.FLOAT32_TOLERANCE and "use float64" in choice.reason
    with pytest.warns(UserWarning, match=r"rtol=1e-07 is below 10 x the resolution of float32"):
        auto.warn_below_resolution(jnp.float32, 1e-7, 1e-5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        auto.warn_below_resolution(jnp.float32, 1e-5, 1e-5)
        auto.warn_below_resolution(jnp.float64, 1e-13, 1e-13)


def test_simulate_records_the_choice_and_its_reason(pendulum):
    q0, v0 = jnp.array([0.3]), jnp.zeros(1)
    sol = jb.simulate(pendulum, q0, v0, 0.5, saveat=diffrax.SaveAt(t1=True))
    expected = auto.choose_auto(pendulum, q0, 0.0, 0.5, jnp.float64, None, None, None)
    assert sol.solver == "tsit5" and sol.solver_reason == expected.reason
    # the auto solve is the tsit5 solve at the default tolerances
    ref = jb.simulate(pendulum, q0, v0, 0.5, solver="tsit5", rtol=1e-8, atol=1e-8,
                      saveat=diffrax.SaveAt(t1=True))
    np.testing.assert_array_equal(np.asarray(sol.q_final), np.asarray(ref.q_final))
    assert ref.solver == "tsit5" and ref.solver_reason == "asked for"


@pytest.mark.slow  # about 20 s: the notebook runs the same quick study in the default suite
def test_work_precision_quick_study_is_consistent(tmp_path, monkeypatch):
    import sys

    monkeypatch.syspath_prepend(str(__import__("pathlib").Path(__file__).resolve().parents[1] / "benchmarks"))
    import work_precision as wp

    rec = wp.run(["pendulum"], quick=True, methods=("tsit5", "auto", "mj_rk4"), log=lambda line: None)
    runs = rec["scenes"]["pendulum"]["runs"]
    tsit5 = sorted((r for r in runs if r["method"] == "tsit5"), key=lambda r: -r["knob"])
    mj = sorted((r for r in runs if r["method"] == "mj_rk4"), key=lambda r: -r["knob"])
    assert all(r["success"] for r in runs)
    # tighter tolerances and smaller steps reach smaller errors against the closed-form reference
    assert tsit5[1]["final_error"] < tsit5[0]["final_error"] / 100
    assert mj[1]["final_error"] < mj[0]["final_error"] / 1000  # fourth order: 10x smaller step
    for r in (r for r in runs if r["method"] == "auto"):
        assert r["solver_ran"] == "tsit5" and r["tolerance"] == pytest.approx(r["knob"] / auto.ERROR_PER_TOLERANCE["tsit5"])
    md = wp.markdown(rec)
    assert "| pendulum | 0.0001 |" in md
    wp.plot(rec, tmp_path / "wp.png")
    assert (tmp_path / "wp.png").stat().st_size > 0
    del sys.modules["work_precision"]


@pytest.mark.parametrize("name", ["panda", "anymal_c"])
def test_host_mass_matrix_of_the_estimate_equals_mujoco(models_dir, name):
    """The stiffness estimate's mass matrix, computed on host numbers by the generated kernels'
    composite-rigid-body code (nothing traced or built), equals MuJoCo's ``mj_fullM`` on the same
    file at a random configuration, a floating base's quaternion included."""
    import mujoco

    path = models_dir / f"{name}.xml"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mjcf(str(path))
    rng = np.random.default_rng(5)
    q = np.asarray(model.qpos0, np.float64) + 0.3 * rng.standard_normal(model.nq)
    if model.nq != model.nv:  # the free base's unit quaternion
        q[3:7] /= np.linalg.norm(q[3:7])
    M = _mujoco_mass_matrix(path, q)
    np.testing.assert_allclose(auto._tree_mass_matrix(model, q), M, rtol=0, atol=1e-12 * np.abs(M).max())


def _mujoco_mass_matrix(path, q):
    """MuJoCo's ``mj_fullM`` of the MJCF at ``path`` at ``qpos = q``."""
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(path))
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    return M


def test_estimate_of_a_scene_with_loops_reads_the_trees_mass_matrix():
    """A spatial scene with loops (the Cassie-like biped: ball joints, four ``<connect>`` loops,
    springs) has the tree's kinetic energy: the estimate takes the tree's mass matrix on the host
    (before, the energies of 528 velocities were traced, compiled and run, and the springs'
    displacements computed one operation at a time: 3.5 s of a warm first simulation), which
    equals MuJoCo's ``mj_fullM``; the springs' layout it reads is the one their displacements use."""
    path = pathlib.Path(jb.__file__).parent / "models" / "cassie_like.xml"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mjcf(str(path))
        scene = jb.scene(model)
    assert scene.constraints is not None and scene.path == "spatial"
    q = np.asarray(model.qpos0, np.float64)
    M = _mujoco_mass_matrix(path, q)
    np.testing.assert_allclose(auto._mass_matrix(scene, q), M, rtol=0, atol=1e-12 * np.abs(M).max())
    layout = spring_dofs(model)
    displacements = spring_displacements(model, jnp.asarray(q))
    assert len(layout) == len(displacements) and any(np.asarray(d).shape[1] == 3 for d, _ in layout)
    for (dofs, k), (dofs_d, disp, k_d) in zip(layout, displacements):
        np.testing.assert_array_equal(dofs, dofs_d)
        np.testing.assert_array_equal(k, k_d)
        assert np.shape(disp) == np.shape(dofs)
    estimate = auto.stiffness_estimate(scene, q)
    assert estimate is not None and estimate["omega"] > 0
