"""The ``jaxbody`` command: end to end, errors, info, examples, demo.

Most commands run in this process through :func:`jaxbody.cli.main` (the ``cli`` fixture), which
shares the programs other tests compiled; a few run in a subprocess, where what matters is what
a shell sees: the whole command from start to finish, exit statuses, and an interrupt.

References that the command does not compute itself: scipy's ``solve_ivp`` on the
double-pendulum equations in absolute angles written out below (Example 1, eq. 14), MuJoCo's
RK4 integrator on the same MJCF, and MuJoCo's ``body_subtreemass``.
"""

import csv
import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import time
from typing import NamedTuple

import mujoco
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxbody
from jaxbody.cli import EXAMPLES, MODELS_DIR, ROBOT_MODELS, main
from jaxbody._xla import default_xla_flags

REPO = pathlib.Path(__file__).resolve().parents[1]

PENDULUM_XML = """<mujoco model="test pendulum">
  <option gravity="0 0 -9.81"/>
  <worldbody>
    <body name="upper" pos="0 0 1">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.05"/>
      <inertial pos="0 0 -0.3" mass="1.2" diaginertia="0.03 0.02 0.01"/>
      <body name="lower" pos="0 0 -0.6">
        <joint name="elbow" type="hinge" axis="1 0 0"/>
        <inertial pos="0.05 0 -0.25" mass="0.7" diaginertia="0.01 0.012 0.004"/>
      </body>
    </body>
  </worldbody>
  <keyframe>
    <key name="swing" qpos="0.7 -0.4" qvel="0.5 1.5"/>
  </keyframe>
</mujoco>
"""


def run_cli(*args, cwd=None, timeout=300, **popen):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.setdefault("XLA_FLAGS", default_xla_flags())
    env["MPLBACKEND"] = "Agg"
    env.pop("JAXBODY_DEBUG", None)
    cmd = [sys.executable, "-m", "jaxbody.cli", *map(str, args)]
    if popen:
        return subprocess.Popen(cmd, cwd=cwd, env=env, text=True, **popen)
    return subprocess.run(cmd, cwd=cwd, env=env, text=True, capture_output=True, timeout=timeout)


def main_status(args) -> int:
    """The command's exit status, run in this process (argparse's own errors exit through SystemExit)."""
    try:
        return main(args)
    except SystemExit as exc:
        return exc.code


class CliRun(NamedTuple):
    returncode: int
    stdout: str
    stderr: str


@pytest.fixture
def cli(monkeypatch, capsys, tmp_path):
    """``cli(*args)`` runs ``jaxbody ARGS`` in this process, in ``tmp_path``, and returns its exit
    status and what it printed."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")

    def run(*args):
        capsys.readouterr()
        status = main_status([str(a) for a in args])
        out, err = capsys.readouterr()
        return CliRun(status, out, err)

    return run


def read_csv(path):
    with open(path) as f:
        rows = list(csv.reader(f))
    return rows[0], np.array(rows[1:], dtype=float)


# ------------------------------------------------------------------ end to end
def double_pendulum_reference(q0, v0, ts, Q=(0.0, 0.0)):
    """Example 1 in absolute angles from the downward vertical (eq. 14), scipy DOP853, with
    constant generalized forces ``Q`` conjugate to the absolute angles."""
    m1, m2, a1, a2, L1, I1, I2, g = 1.0, 0.6, 0.4, 0.3, 0.8, 0.05, 0.02, 9.81
    md1, md2 = m1 * a1 + m2 * L1, m2 * a2
    J1, J2 = I1 + m1 * a1**2 + m2 * L1**2, I2 + m2 * a2**2

    def rhs(t, y):
        x1, x2, w1, w2 = y
        c, s = np.cos(x1 - x2), np.sin(x1 - x2)
        M = np.array([[J1, L1 * md2 * c], [L1 * md2 * c, J2]])
        h = np.array([L1 * md2 * s * w2**2 + md1 * g * np.sin(x1),
                      -L1 * md2 * s * w1**2 + md2 * g * np.sin(x2)])
        return [w1, w2, *np.linalg.solve(M, np.asarray(Q) - h)]

    sol = solve_ivp(rhs, (ts[0], ts[-1]), [*q0, *v0], method="DOP853", rtol=1e-12, atol=1e-12,
                    t_eval=ts)
    return sol.y[:2].T, sol.y[2:].T


def test_simulate_example_end_to_end(tmp_path):
    out = tmp_path / "run"
    r = run_cli("simulate", "double_pendulum", "--t1", "0.6", "--saves", "31", "--chunks", "3",
                "--rtol", "1e-11", "--atol", "1e-11", "--out", out / "traj.npz",
                "--csv", out / "traj.csv", "--plot", out / "traj.png", "--animate", out / "traj.gif",
                "--frames", "8", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert "simulated time" in r.stderr  # the progress bar
    for name in ("traj.npz", "traj.csv", "traj.png", "traj.gif"):
        assert f"wrote {out / name}" in r.stdout
    assert (out / "traj.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "traj.gif").read_bytes()[:6] == b"GIF89a"
    from PIL import Image

    assert Image.open(out / "traj.gif").n_frames == 8

    d = np.load(out / "traj.npz")
    assert bool(d["complete"]) and str(d["status"]) == "complete"
    np.testing.assert_allclose(d["t"], np.linspace(0, 0.6, 31), rtol=0, atol=1e-15)
    assert list(d["q_labels"]) == ["alpha1", "alpha2"]
    meta = json.loads(str(d["meta"]))
    assert meta["solver"] == "tsit5" and meta["t1"] == 0.6
    q_ref, v_ref = double_pendulum_reference((1.0, -0.5), (0.0, 0.0), d["t"])
    np.testing.assert_allclose(d["q"], q_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(d["v"], v_ref, rtol=0, atol=1e-8)
    energy = d["energy"]
    assert np.max(np.abs(energy - energy[0])) < 1e-8 * abs(energy[0])

    header, rows = read_csv(out / "traj.csv")
    assert header == ["t", "q:alpha1", "q:alpha2", "v:alpha1", "v:alpha2", "energy"]
    np.testing.assert_array_equal(rows, np.column_stack([d["t"], d["q"], d["v"], d["energy"]]))
    assert re.search(r"accepted \d+, rejected \d+", r.stdout)


def test_simulate_mjcf_keyframe_matches_mujoco_rk4(tmp_path, cli):
    xml = tmp_path / "pendulum.xml"
    xml.write_text(PENDULUM_XML)
    # 5 intervals in chunks of 2, 2 and 1 (the last one padded to the same length)
    r = cli("simulate", xml, "--keyframe", "swing", "--t1", "0.25", "--saves", "6",
                "--chunks", "3", "--rtol", "1e-12", "--atol", "1e-12", "--csv", tmp_path / "p.csv",
                "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "in 3 chunks" in r.stdout
    header, rows = read_csv(tmp_path / "p.csv")
    assert header == ["t", "q:shoulder", "q:elbow", "v:shoulder", "v:elbow", "energy"]
    # Without --out a .npz is not written unless no output at all is asked for.
    assert not (tmp_path / "outputs").exists()

    m = mujoco.MjModel.from_xml_string(PENDULUM_XML)
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    m.opt.timestep = 1e-4
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    np.testing.assert_array_equal(rows[0, 1:5], [0.7, -0.4, 0.5, 1.5])
    np.testing.assert_allclose(rows[:, 0], np.linspace(0, 0.25, 6), atol=1e-15)
    for i in range(1, 6):
        while d.time < rows[i, 0] - 1e-9:
            mujoco.mj_step(m, d)
        np.testing.assert_allclose(rows[i, 1:3], d.qpos, rtol=0, atol=1e-9)
        np.testing.assert_allclose(rows[i, 3:5], d.qvel, rtol=0, atol=1e-8)


ARM_URDF = """<robot name="arm">
  <link name="base"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="upper"><inertial><origin xyz="0.02 0 -0.25"/><mass value="1.1"/><inertia ixx="0.02" iyy="0.022" izz="0.004" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="lower"><inertial><origin xyz="0 0.03 -0.2"/><mass value="0.6"/><inertia ixx="0.008" iyy="0.009" izz="0.002" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="shoulder" type="continuous"><parent link="base"/><child link="upper"/><axis xyz="0 1 0"/></joint>
  <joint name="elbow" type="continuous"><parent link="upper"/><child link="lower"/><origin xyz="0 0 -0.5"/><axis xyz="1 0 0"/></joint>
</robot>
"""


def test_simulate_urdf_matches_mujoco_rk4(tmp_path, cli):
    """`jaxbody simulate ARM.urdf` end to end: the CSV trajectory against MuJoCo's RK4 on the same URDF."""
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(ARM_URDF)
    r = cli("simulate", urdf, "--q0", "0.7,-0.4", "--v0", "0.5,1.5", "--t1", "0.25", "--saves", "6",
                "--rtol", "1e-12", "--atol", "1e-12", "--csv", tmp_path / "a.csv", "--out", tmp_path / "a.npz",
                "--no-progress")
    assert r.returncode == 0, r.stderr
    header, rows = read_csv(tmp_path / "a.csv")
    assert header == ["t", "q:shoulder", "q:elbow", "v:shoulder", "v:elbow", "energy"]
    assert (tmp_path / "a.npz").stat().st_size > 0

    m = mujoco.MjModel.from_xml_path(str(urdf))
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    m.opt.timestep = 1e-4
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = [0.7, -0.4], [0.5, 1.5]
    np.testing.assert_array_equal(rows[0, 1:5], [0.7, -0.4, 0.5, 1.5])
    for i in range(1, 6):
        while d.time < rows[i, 0] - 1e-9:
            mujoco.mj_step(m, d)
        np.testing.assert_allclose(rows[i, 1:3], d.qpos, rtol=0, atol=1e-9)
        np.testing.assert_allclose(rows[i, 3:5], d.qvel, rtol=0, atol=1e-8)
    assert np.abs(rows[-1, 1:3] - rows[0, 1:3]).max() > 0.05  # it did move


def test_simulate_example_with_constant_torques_matches_solve_ivp(tmp_path, cli):
    """--torque on a built-in example: the planar chain's drives are the hinge moments M_k
    (M_k on link k, −M_k on its parent), so the forces conjugate to the absolute angles are
    Q = (M_1 − M_2, M_2); the energy balance closes with the work of the actuation."""
    r = cli("simulate", "double_pendulum", "--t1", "0.5", "--saves", "6", "--chunks", "2",
                "--rtol", "1e-11", "--atol", "1e-11", "--torque", "alpha1=0.5", "--torque", "alpha2=-0.2",
                "--csv", tmp_path / "t.csv", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "effects         gravity, actuation" in r.stdout
    balance = float(re.search(r"energy balance  max\|E-E0-W\|/\|E0\| = (\S+)", r.stdout).group(1))
    assert balance < 1e-9
    _, rows = read_csv(tmp_path / "t.csv")
    q_ref, v_ref = double_pendulum_reference((1.0, -0.5), (0.0, 0.0), rows[:, 0], Q=(0.5 - (-0.2), -0.2))
    np.testing.assert_allclose(rows[:, 1:3], q_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(rows[:, 3:5], v_ref, rtol=0, atol=1e-8)
    # the torques change the motion: without them the reference differs
    q_free, _ = double_pendulum_reference((1.0, -0.5), (0.0, 0.0), rows[:, 0])
    assert np.max(np.abs(q_free - q_ref)) > 1e-2


def test_simulate_mjcf_scene_options_match_mujoco_rk4(tmp_path, cli):
    """--gravity, --damping, --torque and --load on an MJCF model vs MuJoCo's RK4 with the same
    opt.gravity, dof_damping, qfrc_applied and xfrc_applied (applied at the body's centre of mass)."""
    xml = tmp_path / "pendulum.xml"
    xml.write_text(PENDULUM_XML)
    r = cli("simulate", xml, "--keyframe", "swing", "--t1", "0.2", "--saves", "5", "--chunks", "1",
                "--rtol", "1e-12", "--atol", "1e-12", "--csv", tmp_path / "p.csv", "--no-progress",
                "--gravity", "0.5,0,-3", "--damping", "0.2", "--torque", "elbow=0.3",
                "--load", "lower=0.5,0.2,0,0,0.1,0.05")
    assert r.returncode == 0, r.stderr
    assert "effects         gravity, dampers, actuation, loads" in r.stdout
    _, rows = read_csv(tmp_path / "p.csv")

    m = mujoco.MjModel.from_xml_string(PENDULUM_XML)
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    m.opt.timestep = 1e-4
    m.opt.gravity[:] = (0.5, 0.0, -3.0)
    m.dof_damping[:] = 0.2
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    d.qfrc_applied[:] = (0.0, 0.3)
    d.xfrc_applied[m.body("lower").id] = (0.5, 0.2, 0.0, 0.0, 0.1, 0.05)
    for i in range(1, 5):
        while d.time < rows[i, 0] - 1e-9:
            mujoco.mj_step(m, d)
        np.testing.assert_allclose(rows[i, 1:3], d.qpos, rtol=0, atol=1e-9)
        np.testing.assert_allclose(rows[i, 3:5], d.qvel, rtol=0, atol=1e-8)


def test_info_reflects_scene_options(tmp_path, capsys):
    xml = tmp_path / "pendulum.xml"
    xml.write_text(PENDULUM_XML)
    assert main(["info", str(xml)]) == 0
    out = capsys.readouterr().out
    assert "gravity          on, (0, 0, -9.81) m/s²" in out
    assert "joint dampers    1 DoFs (v[0])" in out
    assert "actuation        none" in out and "external loads   none" in out
    assert main(["info", str(xml), "--no-gravity", "--no-dampers", "--torque", "shoulder=0.3",
                 "--load", "lower=0,0,-2"]) == 0
    out = capsys.readouterr().out
    assert "gravity          off" in out
    assert "joint dampers    0 DoFs" in out
    assert "actuation        constant generalized forces: shoulder = 0.3" in out
    assert "external load    lower: force (0, 0, -2) N, moment (0, 0, 0) N·m at the centre of mass" in out
    assert main(["info", str(xml), "--damping", "0.7", "--gravity", "0,0,-1.62"]) == 0
    out = capsys.readouterr().out
    assert "gravity          on, (0, 0, -1.62) m/s²" in out and "joint dampers    2 DoFs (v[0, 1])" in out
    assert main(["info", "double_pendulum", "--no-gravity", "--torque", "alpha2=1.5"]) == 0
    out = capsys.readouterr().out
    assert "gravity          off" in out and "actuation        constant drives: alpha2 = 1.5" in out


@pytest.mark.parametrize("n_save, n_chunks", [(201, 10), (6, 3), (31, 7), (3, 10), (2, 1)])
def test_chunks_share_end_points_and_one_length(n_save, n_chunks):
    from jaxbody.cli.simulate import chunk_times

    chunks = chunk_times(2.0, n_save, n_chunks)
    assert len(chunks) <= n_chunks
    assert len({len(ts) for ts, _ in chunks}) == 1  # one compiled solve
    real = [ts[:n] for ts, n in chunks]
    for a, b in zip(real, real[1:]):
        assert a[-1] == b[0]
    for ts, n in chunks:
        assert np.all(ts[n:] == ts[n - 1])  # padding repeats the chunk's end
    np.testing.assert_array_equal(np.concatenate([real[0]] + [r[1:] for r in real[1:]]),
                                  np.linspace(0, 2.0, n_save))


def test_default_output_is_an_npz_under_outputs(tmp_path, cli):
    r = cli("simulate", "oscillating_support_pendulum", "--t1", "0.05", "--saves", "3",
                "--chunks", "1", "--no-progress")
    assert r.returncode == 0, r.stderr
    d = np.load(tmp_path / "outputs" / "simulate" / "oscillating_support_pendulum.npz")
    assert d["q"].shape == (3, 1) and bool(d["complete"])


def test_failed_run_keeps_what_it_finished(tmp_path, cli):
    r = cli("simulate", "double_pendulum", "--t1", "2", "--max-steps", "8", "--out",
                tmp_path / "f.npz", "--csv", tmp_path / "f.csv", "--no-progress")
    assert r.returncode == 1
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in r.stderr
    assert re.match(r"jaxbody simulate: error: the solver failed after t = \S+ s: The maximum number "
                    r"of solver steps was reached", err[0]), err
    d = np.load(tmp_path / "f.npz")
    assert not bool(d["complete"]) and str(d["status"]) == "failed"
    t = d["t"]
    assert 2 < len(t) < 201 and t[0] == 0 and np.all(np.diff(t) > 0)
    assert np.all(np.isfinite(d["q"])) and np.all(np.isfinite(d["v"]))
    np.testing.assert_allclose(t, np.linspace(0, 2, 201)[: len(t)], atol=1e-15)
    _, rows = read_csv(tmp_path / "f.csv")
    np.testing.assert_array_equal(rows[:, 0], t)
    # what was kept is the true motion
    q_ref, _ = double_pendulum_reference((1.0, -0.5), (0.0, 0.0), t)
    np.testing.assert_allclose(d["q"], q_ref, atol=1e-6)


def test_interrupted_run_keeps_what_it_finished(tmp_path):
    npz = tmp_path / "long.npz"
    proc = run_cli("simulate", "double_pendulum", "--t1", "20000", "--saves", "200001",
                   "--chunks", "2000", "--rtol", "1e-8", "--atol", "1e-8", "--out", npz,
                   "--no-progress", cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                   # as from a terminal: a shell without job control starts background
                   # commands with SIGINT ignored, which the child would inherit
                   preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    # the interrupt is taken between chunks: loose tolerances keep each chunk (10 s of a chaotic
    # pendulum) short, also in the test suite's unoptimised builds
    try:
        deadline = time.monotonic() + 240
        while not npz.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert npz.exists(), "no chunk was written"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "jaxbody simulate: error: interrupted"
    assert "Traceback" not in err
    d = np.load(npz)
    assert str(d["status"]) == "interrupted" and not bool(d["complete"])
    t = d["t"]
    assert len(t) >= 101 and t[0] == 0 and np.all(np.diff(t) > 0) and t[-1] < 20000
    assert d["q"].shape == (len(t), 2) and np.all(np.isfinite(d["q"]))


def test_skeleton_points_match_mujoco_and_planar_geometry(tmp_path):
    from jaxbody.cli.plots import skeleton
    from jaxbody.cli.sources import load

    xml = tmp_path / "pendulum.xml"
    xml.write_text(PENDULUM_XML)
    src = load(str(xml), "swing")
    q = np.array([[0.7, -0.4], [-1.2, 2.0]])
    lines, dim = skeleton(src, np.zeros(2), q)
    assert dim == 3 and lines.shape == (2, 2, 3, 3)
    m = mujoco.MjModel.from_xml_string(PENDULUM_XML)
    d = mujoco.MjData(m)
    for f in range(2):
        d.qpos[:] = q[f]
        mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(lines[f, :, 2], d.xpos[1:], atol=1e-12)  # body origins
        np.testing.assert_allclose(lines[f, :, 1], d.xanchor, atol=1e-12)  # joint points
        np.testing.assert_allclose(lines[f, 1, 0], d.xpos[1], atol=1e-12)  # parent's origin
        np.testing.assert_allclose(lines[f, 0, 0], 0.0, atol=0)  # root hangs from the world

    src = load("double_pendulum")
    alpha = np.array([[0.3, -1.1]])
    lines, dim = skeleton(src, np.zeros(1), alpha)
    a1, a2 = alpha[0]
    down = lambda a: np.array([np.sin(a), -np.cos(a)])  # angles from the downward vertical
    assert dim == 2
    np.testing.assert_allclose(lines[0, 0], [[0, 0], [0, 0], 0.4 * down(a1)], atol=1e-14)
    np.testing.assert_allclose(lines[0, 1], [[0, 0], 0.8 * down(a1), 0.8 * down(a1) + 0.3 * down(a2)],
                               atol=1e-14)


# ------------------------------------------------------------------ errors
BAD_XML = '<mujoco><worldbody><body><joint type="hinge"/><geom size="0.1"/></body></worldbody'


BAD_INPUT = [
    (["simulate", "missing.xml"], "model file not found: 'missing.xml'"),
    (["simulate", "bad.xml"], "from_mjcf: MuJoCo's compiler rejected the MJCF file 'bad.xml': XML parse error"),
    (["info", "bad.xml"], "from_mjcf: MuJoCo's compiler rejected the MJCF file 'bad.xml'"),
    (["simulate", "no_such_example"], "unknown example 'no_such_example': built-in ones are double_pendulum"),
    (["simulate", "double_pendulum", "--t1", "-1"], "argument --t1: must be positive and finite, got -1"),
    (["simulate", "double_pendulum", "--solver", "rk45"], "unknown solver 'rk45'; choose from"),
    (["simulate", "double_pendulum", "--solver", "rk4"], "fixed-step solver 'rk4' needs dt0 (give --dt)"),
    (["simulate", "panda", "--keyframe", "nope"], "--keyframe: no keyframe named 'nope'; keyframes: ['home']"),
    (["simulate", "double_pendulum", "--keyframe", "home"], "--keyframe: the built-in example 'double_pendulum' has no keyframes"),
    (["simulate", "double_pendulum", "--q0", "1,2,3"], "--q0 has 3 values but double_pendulum has nq = 2 (alpha1, alpha2)"),
    (["simulate", "double_pendulum", "--saves", "1"], "argument --saves: must be at least 2, got 1"),
    (["info", "missing.urdf"], "model file not found: 'missing.urdf'"),
]
# Through a subprocess (the command's exit status and stderr as a shell sees them, with no
# runtime type checker): one error jaxbody reports from MuJoCo's compiler and one of argparse's.
# The others run in process, which starts no interpreter (about 4 s each on 2 cores).
BAD_INPUT_SUBPROCESS = [BAD_INPUT[i] for i in (1, 4)]
BAD_INPUT_IN_PROCESS = [case for case in BAD_INPUT if case not in BAD_INPUT_SUBPROCESS]


def _check_bad_input(status, out, err, tmp_path, args, message):
    assert status == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"jaxbody {args[0]}: error: ") and message in lines[0], lines[0]
    assert out == ""
    assert list(tmp_path.iterdir()) == [tmp_path / "bad.xml"]  # nothing written


@pytest.mark.parametrize("args, message", BAD_INPUT_SUBPROCESS,
                         ids=lambda x: "-".join(x) if isinstance(x, list) else None)
def test_bad_input_is_one_line_and_status_2(tmp_path, args, message):
    (tmp_path / "bad.xml").write_text(BAD_XML)
    r = run_cli(*args, cwd=tmp_path)
    _check_bad_input(r.returncode, r.stdout, r.stderr, tmp_path, args, message)


@pytest.mark.parametrize("args, message", BAD_INPUT_IN_PROCESS, ids=lambda x: "-".join(x) if isinstance(x, list) else None)
def test_bad_input_is_one_line_and_status_2_in_process(tmp_path, monkeypatch, capsys, args, message):
    (tmp_path / "bad.xml").write_text(BAD_XML)
    monkeypatch.chdir(tmp_path)
    status = main_status(args)
    out, err = capsys.readouterr()
    _check_bad_input(status, out, err, tmp_path, args, message)


@pytest.mark.parametrize(
    "args, message",
    [
        (["simulate", "panda", "--torque", "joint9=1"], "--torque: unknown joint 'joint9'; joints: joint1, joint2"),
        (["info", "panda", "--torque", "joint1=1,2"], "--torque joint1: expected 1 values, got 2"),
        (["simulate", "panda", "--torque", "joint1=1", "--torque", "joint1=2"], "--torque: joint 'joint1' given twice"),
        (["simulate", "panda", "--torque", "joint1"], "argument --torque: expected NAME=VALUE[,VALUE...], got 'joint1'"),
        (["simulate", "panda", "--torque", "joint1=x"], "argument --torque: expected numbers separated by commas"),
        (["simulate", "panda", "--load", "hand=1,2,3"], "--load: unknown body 'hand'; bodies: link0, link1"),
        (["simulate", "panda", "--load", "link7=1,2"], "--load link7: expected 3 or 6 values, got 2"),
        (["simulate", "panda", "--gravity", "0,-9.81"], "--gravity: expected 3 values GX,GY,GZ, got 2"),
        (["simulate", "panda", "--damping", "-1"], "argument --damping: must be non-negative and finite, got -1"),
        (["simulate", "panda", "--no-gravity", "--gravity", "0,0,1"], "argument --gravity: not allowed with argument --no-gravity"),
        (["simulate", "double_pendulum", "--damping", "1"], "--damping needs a spatial model"),
        (["simulate", "double_pendulum", "--torque", "phi=1"], "--torque: unknown coordinate 'phi'; coordinates: alpha1, alpha2"),
        (["info", "cart_pendulum", "--no-gravity"], "gravity cannot be switched off on CartPendulum"),
    ],
    ids=lambda x: "-".join(x) if isinstance(x, list) else None,
)
def test_bad_scene_options_are_one_line_and_status_2(tmp_path, monkeypatch, capsys, args, message):
    """In process (the subprocess path of usage errors is tested above): nothing written."""
    monkeypatch.chdir(tmp_path)
    status = main_status(args)
    out, err = capsys.readouterr()
    assert status == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"jaxbody {args[0]}: error: ") and message in lines[0], lines[0]
    assert out == "" and list(tmp_path.iterdir()) == []


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    out = capsys.readouterr().out
    for command in ("simulate", "info", "examples", "balance", "demo"):
        assert command in out


def test_bad_option_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--solver", "rk45"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "invalid choice: 'rk45'" in err[0]


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxbody {jaxbody.__version__}"


def test_balance_dispatches_to_design(monkeypatch):
    import jaxbody.cli.balance

    seen = []
    monkeypatch.setattr(jaxbody.cli.balance, "cli_balance", lambda argv: seen.append(argv) or 7)
    assert main(["balance", "panda", "--steps", "3"]) == 7
    assert seen == [["panda", "--steps", "3"]]


# ------------------------------------------------------------------ info, examples
def test_info_robot_model(capsys):
    assert main(["info", "panda", "--keyframe", "home"]) == 0
    out = capsys.readouterr().out
    m = mujoco.MjModel.from_xml_path(str(MODELS_DIR / "panda.xml"))
    assert f"total mass {m.body_subtreemass[0]:.6g} kg" in out
    rows = re.findall(r"^\s+(\d+)  (\S+)\s+([0-9.e+-]+)\s+\(([^)]*)\)$", out, flags=re.M)
    masses = {int(k): float(mk) for k, _, mk, vec in rows if vec.count(",") == 2}
    assert sorted(masses) == list(range(m.nbody - 1))
    for k, mk in masses.items():  # body k = MuJoCo body k + 1
        assert mk == pytest.approx(m.body_subtreemass[k + 1], rel=1e-5)  # printed to 6 digits
    assert "augmented bodies at keyframe 'home'" in out
    assert "hinge joint 'joint4': q[3], v[3]" in out
    assert "joint dampers    7 DoFs" in out
    assert "- joint limits (ignored): 7 limited joints" in out
    assert "- actuators (" in out


def test_info_planar_example(capsys):
    assert main(["info", "double_pendulum"]) == 0
    out = capsys.readouterr().out
    rows = re.findall(r"^\s+(\d) +(link\d) +(\S+) +\(([^)]*)\) +(\S+)$", out, flags=re.M)
    assert len(rows) == 2
    # (md)_k = |m̄_k| and J_k of a 2-link chain (Example 1 data, eq. 14 definitions)
    md = [1.0 * 0.4 + 0.6 * 0.8, 0.6 * 0.3]
    J = [0.05 + 1.0 * 0.4**2 + 0.6 * 0.8**2, 0.02 + 0.6 * 0.3**2]
    for (k, _, mk, vec, Jk), md_k, J_k, m_k in zip(rows, md, J, (1.6, 0.6)):
        assert float(mk) == pytest.approx(m_k)
        assert np.linalg.norm([float(x) for x in vec.split(",")]) == pytest.approx(md_k, rel=1e-5)
        assert float(Jk) == pytest.approx(J_k, rel=1e-6)
    assert "gravity          on" in out and "none (a built-in example)" in out


def test_info_urdf(tmp_path, capsys):
    urdf = tmp_path / "arm.urdf"
    urdf.write_text("""<robot name="arm">
  <link name="base"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="arm"><inertial><origin xyz="0 0 0.2"/><mass value="0.5"/><inertia ixx="0.002" iyy="0.002" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j1" type="continuous"><parent link="base"/><child link="arm"/><axis xyz="0 1 0"/></joint>
</robot>""")
    assert main(["info", str(urdf)]) == 0
    out = capsys.readouterr().out
    assert "hinge joint 'j1': q[0], v[0]" in out


def test_examples_lists_papers_systems_and_shipped_models(capsys):
    assert main(["examples"]) == 0
    out = capsys.readouterr().out
    for name in EXAMPLES:
        assert name in out and callable(getattr(jaxbody.examples, name))
    for name in ROBOT_MODELS:
        assert name in out
        assert (MODELS_DIR / f"{name}.xml").is_file() and (MODELS_DIR / f"{name}.LICENSE").is_file()


@pytest.mark.parametrize("name", [*EXAMPLES, *ROBOT_MODELS])
def test_every_builtin_simulates(name, tmp_path, capsys):
    out = tmp_path / f"{name}.npz"
    assert main(["simulate", name, "--t1", "0.02", "--saves", "3", "--chunks", "1",
                 "--no-progress", "--out", str(out)]) == 0
    d = np.load(out)
    assert bool(d["complete"]) and np.all(np.isfinite(d["q"])) and np.all(np.isfinite(d["energy"]))
    assert d["q"].shape[1] == len(d["q_labels"])


# ------------------------------------------------------------------ demo
def test_demo_writes_plot_trajectory_and_summary(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--t1", "0.5", "--out", str(out), "--n-save", "51"]) == 0
    printed = capsys.readouterr().out

    png, csv_path, json_path = out / "double_pendulum.png", out / "trajectory.csv", out / "summary.json"
    for path in (png, csv_path, json_path):
        assert path.is_file() and path.stat().st_size > 0, path
        assert f"wrote {path}" in printed
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    drift = re.search(r"relative drift max\|E-E0\|/\|E0\| = (\S+)", printed)
    assert drift, printed
    assert float(drift.group(1)) < 1e-8  # rtol = atol = 1e-10 by default
    assert re.search(r"accepted \d+, rejected \d+", printed)
    assert "incl. compile" in printed

    summary = json.loads(json_path.read_text())
    assert summary["t1"] == 0.5 and summary["alpha0"] == [1.0, -0.5]
    assert summary["relative_energy_drift"] == pytest.approx(float(drift.group(1)), rel=1e-3)
    assert summary["stats"]["num_accepted_steps"] > 0

    with open(csv_path) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 51
    assert float(rows[0]["t"]) == 0.0 and float(rows[-1]["t"]) == pytest.approx(0.5)
    assert (float(rows[0]["alpha1"]), float(rows[0]["alpha2"])) == (1.0, -0.5)
    assert [float(x) for x in summary["alpha_final"]] == [float(rows[-1]["alpha1"]), float(rows[-1]["alpha2"])]


def _four_bar_file(tmp_path):
    from test_constraints import four_bar_angles, four_bar_mjcf

    xml = tmp_path / "fourbar.xml"
    xml.write_text(four_bar_mjcf(four_bar_angles(0.6)))
    return xml


def test_info_lists_the_loops_of_an_mjcf_linkage(tmp_path, capsys):
    assert main(["info", str(_four_bar_file(tmp_path))]) == 0
    out = capsys.readouterr().out
    assert "constraints      2 rows (Maggi): loop closures loop" in out
    assert "content of the file that jaxbody does not model (ignored):\n  none" in out


@pytest.mark.slow  # about 45 s: two compiles of the constrained spatial path
def test_simulate_imposes_the_loops_of_an_mjcf_linkage(tmp_path, capsys):
    """A four-bar closed by <connect>: `simulate` runs in chunks (each chunk's start projected
    back onto the loop) with the loop staying closed."""
    import jaxbody as jb

    xml = _four_bar_file(tmp_path)
    assert main(["simulate", str(xml), "--t1", "0.2", "--saves", "5", "--chunks", "2", "--no-progress",
                 "--csv", str(tmp_path / "fb.csv")]) == 0
    out = capsys.readouterr().out
    assert "constraints     loop closures loop (Maggi equations)" in out
    header, data = read_csv(tmp_path / "fb.csv")
    assert data.shape[0] == 5
    model = jb.from_mjcf(str(xml))
    (loop,) = jb.constraints.loop_closures(model)
    q = data[:, [header.index(f"q:{j}") for j in ("j1", "j2", "j3")]]
    gap = [np.asarray(loop.axes @ (jb.constraints.body_point(model, qk, loop.body_a, loop.point_a)
                                   - jb.constraints.body_point(model, qk, loop.body_b, loop.point_b))) for qk in q]
    assert np.max(np.abs(gap)) < 1e-7 and np.ptp(q[:, 0]) > 1e-3  # it moved, and stayed closed
