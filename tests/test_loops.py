"""A robot with loops as imported: the Cassie-like biped (floating base, ball joints, four
MJCF ``<connect>`` loops, joint springs, a ``home`` keyframe) loads, gets independent loop rows
in each loop's own frame, builds a scene and agrees with MuJoCo; initial states are projected
onto the loops on request and checked otherwise; the command line runs it.

The traps it holds: a planar four-bar at each foot whose out-of-plane direction turns with the
floating base and the hips (world directions would be redundant at some configurations), a
spatial loop through a ball joint, and a keyframe far from ``qpos0``.
"""

import pathlib
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody import constraints as jc
from jaxbody import maggi
from jaxbody.cli import main as cli_main
from jaxbody.kinematics import integrate_qpos

jax.config.update("jax_enable_x64", True)

CASSIE = pathlib.Path(jb.__file__).parent / "models" / "cassie_like.xml"
# MuJoCo's connect made nearly hard (and no contacts), to compare with the exact loop closures
STIFF = ('solref="0.0002 1" solimp="0.99999 0.99999 0.001"/>', '<option timestep="0.0005"><flag contact="disable"/></option>')


def _load():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # contacts and motors are not modelled
        return jb.from_mjcf(str(CASSIE))


def _stiff_mujoco():
    import mujoco

    xml = CASSIE.read_text().replace('anchor="0 0 -0.35"/>', f'anchor="0 0 -0.35" {STIFF[0]}')
    xml = xml.replace('anchor="-0.06 0 -0.5"/>', f'anchor="-0.06 0 -0.5" {STIFF[0]}')
    xml = xml.replace('<option timestep="0.0005"/>', STIFF[1])
    return mujoco.MjModel.from_xml_string(xml)


@pytest.fixture(scope="module")
def cassie():
    model = _load()
    return model, jb.scene(model)


def test_loop_rows_found_at_import_in_each_loops_frame():
    """Each loop's rows are in the frame of the lowest common ancestor of its bodies; the planar
    foot four-bars keep their two in-plane rows and report the dropped one; a direction dropped
    at qpos0 stays a zero row of MuJoCo's Jacobian at the keyframe (hips turned, base rotated)."""
    import mujoco

    model = _load()
    assert [s.label for s in model.loops] == ["left-achilles", "left-plantar", "right-achilles", "right-plantar"]
    frames = {s.label: model.body_names[s.frame] for s in model.loops}
    assert frames == {"left-achilles": "left-hip-pitch", "left-plantar": "left-tarsus",
                      "right-achilles": "right-hip-pitch", "right-plantar": "right-tarsus"}
    rows = {s.label: np.asarray(s.axes) for s in model.loops}
    np.testing.assert_array_equal(rows["left-achilles"], np.eye(3))
    np.testing.assert_array_equal(rows["left-plantar"], np.eye(3)[[0, 2]])
    (why,) = model.loops[1].dropped
    assert why.startswith("along (0, 1, 0) in the frame of body 'left-tarsus': the loop cannot open")
    assert model.loops[0].dropped == ()
    # independently, with MuJoCo's Jacobians at the keyframe: the kept rows are independent and
    # the dropped ones vanish there too
    m = mujoco.MjModel.from_xml_path(str(CASSIE))
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(model.keyframe("home")[0])
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    kept, dropped = [], []
    for s in model.loops:
        jac = []
        for body, point in ((s.body_a, s.point_a), (s.body_b, s.point_b)):
            X = d.xpos[body + 1] + d.xmat[body + 1].reshape(3, 3) @ np.asarray(point)
            J = np.zeros((3, m.nv))
            mujoco.mj_jac(m, d, J, None, X, body + 1)
            jac.append(J)
        Jf = d.xmat[s.frame + 1].reshape(3, 3).T @ (jac[0] - jac[1])
        kept.append(np.asarray(s.axes) @ Jf)
        dropped += [row for k, row in enumerate(Jf) if not np.any(np.asarray(s.axes)[:, k])]
    assert np.linalg.matrix_rank(np.concatenate(kept), tol=1e-9) == 10
    assert len(dropped) == 2 and np.abs(dropped).max() < 1e-12
    # the gap of every loop vanishes at the keyframe (it closes them)
    np.testing.assert_allclose(d.qpos, np.asarray(jc.loop_reference(model, d.qpos)), atol=0)


def test_redundant_rows_across_loops_are_dropped_with_a_report():
    """A connect repeated on a planar four-bar: the second one's rows repeat the first's and are
    all dropped, naming the rows they depend on; the scene imposes the first loop's two rows."""
    from test_constraints import four_bar_angles, four_bar_mjcf

    xml = four_bar_mjcf(four_bar_angles(0.6))
    line = next(s for s in xml.splitlines() if "<connect" in s)
    xml = xml.replace(line, line + line.replace('name="loop"', 'name="again"'))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mjcf(xml)
    first, again = model.loops
    assert len(first.axes) == 2 and first.frame == -1 and again.axes == ()
    assert len(again.dropped) == 3, again.dropped  # across the plane, then the two repeated rows
    assert again.dropped[1] == ("along (1, 0, 0) in the frame of the world: it depends on the rows kept before it "
                                "(loop[0]) at the reference configuration")
    assert again.dropped[2].endswith("depends on the rows kept before it (loop[1]) at the reference configuration")
    assert [c.label for c in jc.loop_closures(model)] == ["loop"]


def test_scene_forward_dynamics_against_mujoco_connect(cassie):
    """``jb.scene(model)`` imposes the four loops (10 rows); its accelerations at the keyframe
    with admissible rates match MuJoCo's ``mj_forward`` with the connects made stiff (within
    their softness), and the constraint forces hold the loops (MuJoCo's world forces on body1,
    turned into each loop's frame)."""
    import mujoco

    model, scene = cassie
    cs = scene.constraints
    assert cs.n_constraint == 10 and cs.constraint_names[3:5] == ("left-plantar[0]", "left-plantar[1]")
    q, _ = model.keyframe("home")
    # admissible rates from the null space of G (NumPy: no program compiled for the projection)
    G = np.asarray(cs.constraint_jacobian(0.0, q, jnp.zeros(model.nv)))
    null = np.linalg.svd(G)[2][G.shape[0]:].T
    v = jnp.asarray(null @ np.random.default_rng(3).normal(size=null.shape[1]))
    np.testing.assert_allclose(cs.constraint_residual(0.0, q, v), 0.0, atol=1e-11)
    a, _, lam = scene.evaluate(0.0, q, v)
    m = _stiff_mujoco()
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = np.asarray(q), np.asarray(v)
    mujoco.mj_forward(m, d)
    scale = float(jnp.max(jnp.abs(a)))
    np.testing.assert_allclose(d.qacc, a, rtol=0, atol=2e-3 * scale)
    # MuJoCo's rows: three world components of the force on body1 per connect, in eq order
    f_world = np.asarray(d.efc_force[: 3 * len(model.loops)]).reshape(-1, 3)
    ours = np.split(np.asarray(lam), np.cumsum([len(s.axes) for s in model.loops])[:-1])
    for s, fw, f in zip(model.loops, f_world, ours):
        R = d.xmat[s.frame + 1].reshape(3, 3)
        np.testing.assert_allclose(np.asarray(s.axes) @ R.T @ fw, f, rtol=0, atol=2e-3 * np.abs(f_world).max())


def test_loop_velocity_bias_in_closed_form_equals_forward_mode(cassie):
    """``γ = Ġ v`` of every loop row, in closed form from the bodies' accelerations, equals
    forward-mode differentiation of the rows along ``q̇ = π(q, v)``: at random states off the
    loops (ball joints, the floating base, rows in the frames of the loops' common ancestors),
    and for loops closed to the world and between two bodies in world axes."""
    from jaxbody.kinematics import normalize_qpos

    model, scene = cassie
    cs = scene.constraints.on_model(model)
    foot = model.loops[0].body_b
    extra = [jc.LoopClosure(model, foot, (0.01, -0.02, 0.03), -1, (0.1, 0.2, 0.3)),
             jc.LoopClosure(model, foot, (0.0, 0.05, 0.0), 1, (0.02, 0.0, -0.1), axes=((1.0, 1.0, 0.0), (0.0, 0.0, 1.0)))]
    rng = np.random.default_rng(5)
    t = jnp.asarray(0.0)
    for _ in range(3):
        q = normalize_qpos(model, model.qpos0 + 0.4 * rng.standard_normal(model.nq))
        v = jnp.asarray(rng.standard_normal(model.nv))
        qd = cs.base.qdot(q, v)
        forward = jax.jvp(lambda tt, qq: cs.constraint_residual(tt, qq, v), (t, q), (jnp.ones_like(t), qd))[1]
        closed = cs.constraint_velocity_bias(t, q, v)
        assert float(jnp.max(jnp.abs(forward))) > 0.1
        np.testing.assert_allclose(closed, forward, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(forward))))
        for c in extra:
            reference = jax.jvp(lambda qq: c.velocity(cs.base, t, qq, v), (q,), (qd,))[1]
            np.testing.assert_allclose(c.velocity_bias(cs.base, t, q, v), reference, rtol=0,
                                       atol=1e-12 * float(jnp.max(jnp.abs(reference))))


def test_initial_positions_checked_and_projected(cassie):
    """Off the loops: ``maggi.initial_state`` names the rows at fault; with ``project_initial``
    Newton's method in the joint velocities puts ``q`` back on them with unit quaternions."""
    model, scene = cassie
    cs = scene.constraints
    q, v = model.keyframe("home")
    off = integrate_qpos(model, q, jnp.asarray(np.random.default_rng(0).normal(size=model.nv)), 0.05)
    with pytest.raises(ValueError, match=r"initial positions violate the constraints \['left-achilles\[0\]'"):
        maggi.initial_state(cs, off, v, check_positions=True)
    maggi.initial_state(cs, off, v)  # velocities only, unless asked
    qp, vp, _ = maggi.initial_state(cs, off, v, project_initial=True)
    np.testing.assert_allclose(cs.position_residual(0.0, qp), 0.0, atol=1e-10)
    for a in (3, 10, 24):  # the free joint's and the two ball joints' quaternions
        assert abs(float(jnp.linalg.norm(qp[a:a + 4])) - 1.0) < 1e-14
    assert float(jnp.max(jnp.abs(qp - off))) < 0.1  # a small correction, not another pose


def test_cli_info_reports_the_loop_rows(cassie, capsys):
    assert cli_main(["info", str(CASSIE)]) == 0
    out = capsys.readouterr().out
    assert "constraints      10 rows (Maggi): loop closures left-achilles, left-plantar, right-achilles, right-plantar" in out
    assert "left-plantar: point (0, 0, -0.35) of 'left-plantar-rod' on point" in out
    assert "2 rows along (1, 0, 0), (0, 0, 1) (axes of body 'left-tarsus')" in out
    assert "dropped along (0, 1, 0) in the frame of body 'left-tarsus'" in out


@pytest.mark.slow  # compiles the constrained solve of a 32-DoF model (about a minute)
def test_cli_simulate_keyframe_one_second(tmp_path, capsys):
    """``jaxbody simulate cassie_like.xml --keyframe home --t1 1`` runs; the loops stay closed;
    a keyframe rounded off the loops stops with a message naming --project-initial, which
    projects it."""
    out = tmp_path / "c.npz"
    assert cli_main(["simulate", str(CASSIE), "--keyframe", "home", "--t1", "1", "--no-progress", "--out", str(out)]) == 0
    data = np.load(out)
    model = _load()
    cs = jc.loop_system(model)
    assert data["t"][-1] == 1.0
    assert max(float(jnp.max(jnp.abs(cs.position_residual(0.0, jnp.asarray(q))))) for q in data["q"]) < 1e-7
    capsys.readouterr()
    q = np.asarray(model.keyframe("home")[0]).round(3)
    args = ["simulate", str(CASSIE), "--q0", ",".join(map(str, q)), "--t1", "0.01", "--no-progress", "--out", str(out)]
    assert cli_main(args) == 2
    assert "initial positions violate the constraints" in capsys.readouterr().err
    assert cli_main(args + ["--project-initial"]) == 0
    assert "projected onto the constraints (--project-initial): max|Δq| =" in capsys.readouterr().out
