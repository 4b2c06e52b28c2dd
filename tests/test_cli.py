"""The ``jaxbody`` command, run in-process."""

import csv
import json
import re

import pytest

import jaxbody
from jaxbody.cli import main


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


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxbody {jaxbody.__version__}"


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "demo" in capsys.readouterr().out


def test_bad_option_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--solver", "rk45"])
    assert exc.value.code == 2
    assert "invalid choice: 'rk45'" in capsys.readouterr().err
