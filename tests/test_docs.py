"""The documentation site builds, its code runs, and the README stays inside the repository."""

import os
import pathlib
import re
import subprocess
import sys

import pytest
from jaxbody._xla import default_xla_flags

REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.timeout(600)
def test_mkdocs_build_strict(tmp_path):
    site = tmp_path / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    r = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=600,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    for page in ("index.html", "getting-started/index.html", "conventions/index.html",
                 "mathematics/index.html", "cli/index.html", "performance/index.html",
                 "api/dynamics/index.html", "notebooks/01_paper_examples/index.html"):
        assert (site / page).is_file(), page
    # the API reference is generated from the docstrings
    api = (site / "api" / "dynamics" / "index.html").read_text()
    assert "Joint forces" in api and "inverse_dynamics" in api
    # equation numbers survive into the page
    assert r"\tag{5}" in (site / "mathematics" / "index.html").read_text()


def python_blocks(path):
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def test_getting_started_code_runs(monkeypatch):
    monkeypatch.chdir(REPO)
    blocks = python_blocks(REPO / "docs" / "getting-started.md")
    assert len(blocks) >= 3
    namespace = {}
    with pytest.warns(UserWarning, match="does not model"):
        for block in blocks:
            exec(compile(block, "getting-started.md", "exec"), namespace)
    assert namespace["sols"].q.shape == (16, 101, 2)


def test_readme_links_stay_in_the_repository():
    text = (REPO / "README.md").read_text()
    assert "../shared" not in text and "spec/equations" not in text and "DESIGN.md" not in text
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if re.match(r"[a-z]+://", target):
            continue
        assert (REPO / target).exists(), f"README links to {target}, which is not in the repository"
    assert "docs/" in text and "mkdocs" in text


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_multihost_script_runs_on_localhost(tmp_path):
    """The multi-host script of docs/simulation.md, launched as documented (two processes, coordinator
    address, process count and id on the command line), runs and splits the batch between the processes."""
    import socket

    import numpy as np

    blocks = [b for b in python_blocks(REPO / "docs" / "simulation.md") if b.startswith("# run_batch.py")]
    assert len(blocks) == 1
    script = blocks[0].replace("n = 100_000", "n = 6").replace(", 1.0,\n", ", 0.05,\n")
    assert "n = 6" in script and ", 0.05," in script
    (tmp_path / "run_batch.py").write_text(script)
    with socket.socket() as s:  # a free port
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, XLA_FLAGS=default_xla_flags())
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    procs = [subprocess.Popen([sys.executable, "run_batch.py", f"localhost:{port}", "2", str(i)], cwd=tmp_path,
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for i in range(2)]
    outs = [p.communicate(timeout=540)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], "\n".join(o[-3000:] for o in outs)
    parts = [np.load(tmp_path / f"part{i:03d}.npz") for i in range(2)]
    assert [p["q"].shape for p in parts] == [(3, 11, 7), (3, 11, 7)]
    assert all(p["success"].all() for p in parts)
    # member i of the global batch is in part i % 2, row i // 2: the initial states are the global ones
    rng = np.random.default_rng(0)
    import mujoco

    qpos0 = mujoco.MjModel.from_xml_path(str(REPO / "jaxbody" / "models" / "panda.xml")).qpos0
    q0s = np.tile(qpos0, (6, 1)) + 0.1 * rng.standard_normal((6, 7))
    for i in range(6):
        np.testing.assert_allclose(parts[i % 2]["q"][i // 2, 0], q0s[i], rtol=0, atol=1e-12)
