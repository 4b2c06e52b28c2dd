"""Execute every ``notebooks/*.ipynb`` top to bottom at a small size.

Committed outputs prove nothing: each notebook runs in a fresh kernel of *this* interpreter
(a kernelspec written to a temporary folder, so a system-wide ``python3`` kernel cannot
take its place), with ``JAXBODY_SMALL=1`` so notebooks can shrink their sizes, and the
notebooks folder as working directory. Any cell error fails the test.
"""

import json
import os
import pathlib
import sys

import nbclient
import nbformat
import pytest
from jaxbody._xla import default_xla_flags

NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
# the longest run in the slow job, the rest in the default suite: 04 and 06 (75-100 s each on 2
# cores), 01 and 07 (16-28 s; the paper's examples they show are checked in test_examples_*.py,
# test_planar*.py and test_maggi.py, the accuracy study's choices in test_simulation_auto.py)
SLOW_NOTEBOOKS = {"01_paper_examples.ipynb", "04_disk_on_a_plane.ipynb", "06_parameter_identification.ipynb",
                  "07_accuracy_vs_time.ipynb"}
CELL_TIMEOUT_S = 300
KERNEL_NAME = "jaxbody-tests"


@pytest.fixture
def kernel_env(tmp_path, monkeypatch):
    spec_dir = tmp_path / "jupyter" / "kernels" / KERNEL_NAME
    spec_dir.mkdir(parents=True)
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "jaxbody tests",
        "language": "python",
    }
    (spec_dir / "kernel.json").write_text(json.dumps(spec))
    jupyter_path = [str(tmp_path / "jupyter"), os.environ.get("JUPYTER_PATH", "")]
    monkeypatch.setenv("JUPYTER_PATH", os.pathsep.join(p for p in jupyter_path if p))
    monkeypatch.setenv("JAXBODY_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", default_xla_flags()))
    # ipykernel's debugger otherwise warns about frozen modules on stderr.
    monkeypatch.setenv("PYDEVD_DISABLE_FILE_VALIDATION", "1")


def execute(path: pathlib.Path):
    """Run a notebook top to bottom; ``pytest.fail`` naming the notebook on any cell error."""
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb, kernel_name=KERNEL_NAME, timeout=CELL_TIMEOUT_S, resources={"metadata": {"path": str(path.parent)}}
    )
    try:
        client.execute()
    except nbclient.exceptions.CellTimeoutError as err:
        pytest.fail(f"{path.name}: a cell ran longer than {CELL_TIMEOUT_S} s:\n{err}", pytrace=False)
    except nbclient.exceptions.CellExecutionError as err:
        pytest.fail(f"{path.name}: a cell failed:\n{err}", pytrace=False)
    return nb


@pytest.mark.skipif(not NOTEBOOKS, reason="no notebooks/*.ipynb yet")
@pytest.mark.timeout(1800)
@pytest.mark.parametrize(
    "path",
    [pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW_NOTEBOOKS else p for p in NOTEBOOKS],
    ids=[p.name for p in NOTEBOOKS],
)
def test_notebook_runs(path, kernel_env):
    execute(path)


def _notebook(tmp_path, *sources):
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(s) for s in sources])
    path = tmp_path / "probe.ipynb"
    nbformat.write(nb, path)
    return path


@pytest.mark.timeout(300)
def test_runner_uses_this_interpreter_and_small_sizes(tmp_path, kernel_env):
    path = _notebook(tmp_path, "import os, sys\nprint(sys.executable, os.environ['JAXBODY_SMALL'], os.getcwd())")
    nb = execute(path)
    printed = nb.cells[0].outputs[0]["text"].split()
    assert printed == [sys.executable, "1", str(tmp_path)]


@pytest.mark.timeout(300)
def test_runner_fails_on_a_cell_error(tmp_path, kernel_env):
    path = _notebook(tmp_path, "x = 1", "raise RuntimeError('boom in cell 2')")
    with pytest.raises(pytest.fail.Exception, match=r"probe.ipynb: a cell failed:(.|\n)*boom in cell 2"):
        execute(path)
