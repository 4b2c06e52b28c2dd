"""scripts/distributed_batch.py: a batch split over two processes with ``jax.distributed`` (CPU
collectives on localhost) equals the same batch computed by one process."""

import importlib.util
import os
import pathlib
import socket
import subprocess
import sys

import numpy as np
import pytest

import jaxbody as jb

REPO = pathlib.Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "distributed_batch.py"

# a small spatial chain keeps the two processes' compilations short; the script's default is Panda
CHAIN = """<mujoco><option gravity="0 0 -9.81"/><worldbody>
<body name="a"><joint name="ha" axis="0 1 0" damping="0.1"/><inertial pos="0 0 -0.15" mass="1" diaginertia="0.008 0.008 0.001"/>
<body name="b" pos="0 0 -0.3"><joint name="hb" axis="1 0 0"/><inertial pos="0 0 -0.15" mass="0.5" diaginertia="0.004 0.004 0.0005"/>
</body></body></worldbody></mujoco>"""


def _script_module():
    spec = importlib.util.spec_from_file_location("distributed_batch", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def test_arguments_need_the_three_or_cluster():
    script = _script_module()
    assert script.arguments(["localhost:1", "2", "0"]).num_processes == 2
    assert script.arguments(["--cluster"]).cluster
    for bad in ([], ["localhost:1", "2"], ["--cluster", "localhost:1", "2", "0"]):
        with pytest.raises(SystemExit):
            script.arguments(bad)


@pytest.mark.timeout(300)
def test_two_processes_equal_one(tmp_path):
    script = _script_module()
    model_path = tmp_path / "chain.xml"
    model_path.write_text(CHAIN)
    n, options = 5, ["--n", "5", "--t1", "0.05", "--n-save", "3", "--solver", "rk4", "--dt0", "0.01"]
    env = dict(os.environ)  # the suite's XLA flags (the reduced optimisation level: tests/conftest.py)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    port = _free_port()
    procs = [subprocess.Popen([sys.executable, str(SCRIPT), f"localhost:{port}", "2", str(i), "--model", str(model_path),
                               "--out", str(tmp_path), *options],
                              cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for i in range(2)]
    outs = [p.communicate(timeout=280)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], "\n".join(o[-3000:] for o in outs)
    # each process computed its own slice: 3 and 2 members of 5
    assert [len(np.load(tmp_path / f"part{i:03d}.npz")["q"]) for i in range(2)] == [3, 2]
    joined = script.gather(tmp_path, 2)

    scene = jb.scene(jb.from_mjcf(model_path))
    q0s = script.global_initial_states(scene.system.qpos0, n)
    one = jb.simulate_batch(scene, q0s, np.zeros((n, scene.nv)), 0.05, solver="rk4", dt0=0.01, n_save=3)
    assert joined["success"].all()
    np.testing.assert_array_equal(joined["q"][:, 0], q0s)
    np.testing.assert_allclose(joined["t"], np.asarray(one.t), rtol=0, atol=0)
    # the same program on the same inputs; XLA may vectorise batches of 3 and 5 differently
    np.testing.assert_allclose(joined["q"], np.asarray(one.q), rtol=0, atol=1e-13)
    np.testing.assert_allclose(joined["v"], np.asarray(one.v), rtol=0, atol=1e-12)
