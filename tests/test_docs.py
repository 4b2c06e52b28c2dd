"""The documentation site builds, its code runs, and the README stays inside the repository."""

import os
import pathlib
import re
import subprocess
import sys

import pytest

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
