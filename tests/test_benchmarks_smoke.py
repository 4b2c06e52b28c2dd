"""Every benchmark script runs end to end at a tiny size and leaves a sane record.

Not a timing test (tests never assert timings): it checks that the harness runs
through the public API, writes its Markdown/JSON/PNG records with a stamp, and that the
numbers in them are consistent (positive rates, the steps it claims, finite states, the
three adjoints agreeing). The fast case runs the double pendulum (chain2) at batches 1 and
4 for 10 steps; the slow one adds float32, accuracy runs and the reverse-mode adjoints.
"""

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest
from jaxbody._xla import default_xla_flags

REPO = pathlib.Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks"


def _run(script, out, *args, timeout=300):
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg")
    env.setdefault("XLA_FLAGS", default_xla_flags())
    env.pop("JAX_ENABLE_X64", None)
    cmd = [sys.executable, str(BENCH / script), "--out", str(out), "--name", "rec",
           "--min-time", "0.01", "--repeats", "1", *args]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    for ext in ("md", "json", "png"):
        assert (out / f"rec.{ext}").stat().st_size > 0
    rec = json.loads((out / "rec.json").read_text())
    assert rec["stamp"]["commit"] and rec["stamp"]["command"].endswith(" ".join(args[-2:]))
    assert "jax" in rec["stamp"]["versions"] and rec["stamp"]["load_average_start"] is not None
    md = (out / "rec.md").read_text()
    assert "## Targets" in md and rec["stamp"]["commit"] in md
    return rec, md


def _check_throughput(rec, impls):
    runs = rec["runs"]["chain2"]
    for impl in impls:
        w = runs[impl]
        assert w["status"] == "ok", w.get("stderr_tail")
        for b in ("1", "4"):
            row = w["batches"][b]
            if impl == "mujoco":
                assert row["steps"] == 10
                for key in ("mj1", "mjN"):
                    assert 0 < row[key]["steps_per_s"] < 1e9
            else:
                assert row["steps"] == 10 and row["finite"], row  # RK4 took exactly t1/dt steps
                assert 0 < row["run"]["steps_per_s"] < 1e9
                assert row["compile"]["compile_total_s"] > 0
        if impl != "mujoco":
            assert w["batches"]["4"]["path"].startswith("jb.vmap_chunked")  # --chunk 2: the chunked path ran
            assert w["single"]["steps"] == 10 and w["single"]["per_step_s"] > 0
    assert runs["mujoco"]["mjcb_time_at_start"] == "None"
    ids = {t["id"] for t in rec["targets"]}
    assert {"batch-vs-mujoco", "single-trajectory", "compile-scaling", "float32-speed"} <= ids


@pytest.mark.slow  # about 35 s; test_throughput_and_gradients_full_smoke (slow) runs the same scripts further
def test_throughput_and_gradients_smoke(tmp_path):
    rec, md = _run("throughput.py", tmp_path / "t", "--impls", "jb64,mujoco", "--no-accuracy",
                   "--single-steps", "10", "--chunk", "2", "--models", "chain2", "--batches", "1,4", "--steps", "10")
    _check_throughput(rec, ("jb64", "mujoco"))
    assert "| chain2 | 4 | 10 |" in md

    rec, md = _run("gradients.py", tmp_path / "g", "--modes", "forward,forward_mode", "--horizon-factor", "1",
                   "--fwd-params", "2", "--models", "chain2", "--steps", "10")
    runs = rec["runs"]["chain2"]
    assert runs["forward"]["status"] == "ok" and runs["forward_mode"]["status"] == "ok"
    assert runs["forward"]["finite"] and len(runs["forward_mode"]["value"]) == 2
    assert runs["forward"]["memory"]["temp_size_in_bytes"] >= 0 and runs["forward"]["peak_rss_bytes"] > 0
    assert rec["analysis"]["chain2"]["forward"]["time_ratio"] == pytest.approx(1.0)


@pytest.mark.slow
def test_throughput_and_gradients_full_smoke(tmp_path):
    rec, md = _run("throughput.py", tmp_path / "t", "--impls", "jb64,jb32,mujoco", "--accuracy-models", "chain2",
                   "--accuracy-states", "2", "--single-steps", "10", "--chunk", "2", "--models", "chain2",
                   "--batches", "1,4", "--steps", "10", timeout=900)
    _check_throughput(rec, ("jb64", "jb32", "mujoco"))
    acc = rec["accuracy"]["chain2"]
    assert acc["rk4_f64_vs_mujoco_rk4"] < 1e-10  # same method, same model: the harness compares like with like
    assert 0 < acc["rk4_f32_vs_rk4_f64"] < 1e-4
    assert "## float32 against float64 (after 1 s)" in md

    rec, md = _run("gradients.py", tmp_path / "g", "--fwd-params", "2", "--models", "chain2", "--steps", "10",
                   timeout=900)
    a = rec["analysis"]["chain2"]
    assert a["forward_mode_vs_checkpoint_rel"] < 1e-10
    assert a["backsolve_vs_checkpoint_rel"] < 1e-6
    assert rec["runs"]["chain2"]["checkpoint"]["longer_horizon"]["steps"] == 160  # --horizon-factor 16
    paired = rec["runs"]["chain2"]["checkpoint"]["paired"]  # the gradient-cost ratio: interleaved pairs in one worker
    assert len(paired["ratios"]) == 5 and all(r > 0 for r in paired["ratios"])
    assert "interleaved pairs" in next(t["detail"] for t in rec["targets"] if t["id"] == "gradient-cost")


@pytest.mark.slow  # about 20 s
def test_throughput_float32_pairs_smoke(tmp_path):
    # --float32-pairs: float64 and float32 compiled in one process and timed one after the other
    rec, md = _run("throughput.py", tmp_path / "t", "--impls", "jb64,jb32", "--no-accuracy", "--single-steps", "0",
                   "--models", "chain2", "--batches", "1024", "--steps", "10", "--kernel", "auto", "--float32-pairs", "2")
    w = rec["runs"]["chain2"]["pairs"]
    assert w["status"] == "ok", w.get("stderr_tail")
    row = w["batches"]["1024"]
    assert row["steps_float64"] == row["steps_float32"] == 10 and row["finite_float64"] and row["finite_float32"]
    assert len(row["pairs"]) == 2 and all(p["float64"] > 0 and p["float32"] > 0 for p in row["pairs"])
    assert all(p["ratio"] == pytest.approx(p["float32"] / p["float64"]) for p in row["pairs"])
    assert min(p["ratio"] for p in row["pairs"]) <= row["median_ratio"] <= max(p["ratio"] for p in row["pairs"])
    t5 = next(t for t in rec["targets"] if t["id"] == "float32-speed")
    assert "interleaved pairs" in t5["target"] and "separate workers" in t5["detail"]
    assert "## float32 against float64 in pairs" in md and "| chain2 | 1024 | 10 |" in md


@pytest.mark.slow  # about 35 s: compiles the unrolled kernel; throughput.py's smoke test stays in the default suite
def test_kernels_benchmark_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "kernels.py"), "compare", "--out", str(tmp_path), "--name", "rec",
           "--models", "chain2", "--batch", "4", "--steps", "3", "--min-time", "0.01",
           "--simulate-models", "chain2"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rec.json").read_text())
    row = rec["results"][0]
    for k in ("unrolled", "vectorised", "auto"):
        assert row[k]["single_step_us"] > 0 and row[k]["batch_steps_per_s"] > 0
    for k in ("unrolled", "vectorised"):
        assert row[k]["simulate rk4 preset"]["batch_steps_per_s"] > 0 and row[k]["simulate tableau RK4"]["compile_s"] > 0
    assert row["mj_step_us"] > 0 and "| chain2 |" in (tmp_path / "rec.md").read_text()
    assert "| chain2 | unrolled | rk4 preset |" in (tmp_path / "rec.md").read_text()


def test_effects_benchmark_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "effects.py"), "--out", str(tmp_path), "--tag", "rec",
           "--only", "chain7:planar", "--max-sets", "2", "--batch", "4", "--min-time", "0.01"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "effects_rec.json").read_text())
    assert rec["stamp"]["commit"] and rec["stamp"]["command"].endswith("--min-time 0.01")
    rows = rec["rows"]
    # the planar path skips the sets with loads or a constraint (they need the spatial path)
    assert [(r["model"], r["path"]) for r in rows] == [("chain7", "planar")] * 2
    assert [r["effects"] for r in rows] == ["gravity+springs+dampers+actuation", "gravity+springs+dampers"]
    assert rows[0]["jaxpr_eqns"] > rows[1]["jaxpr_eqns"] > 0  # actuation adds equations
    assert rows[0]["flops"] > 0 and rows[1]["flops"] > 0
    assert all(r["call_us"] > 0 and r["batched_us_per_state"] > 0 for r in rows)
    md = (tmp_path / "effects_rec.md").read_text()
    assert rec["stamp"]["commit"] in md and "| chain7 | planar |" in md


def _run_small(script, tmp_path, *args, timeout=300):
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg")
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / script), "--smoke", "--out", str(tmp_path), "--name", "rec", *args]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rec.json").read_text())
    md = (tmp_path / "rec.md").read_text()
    assert rec["stamp"]["commit"] and rec["stamp"]["commit"] in md and rec["stamp"]["command"].endswith("--name rec")
    return rec, md


def test_design_benchmark_smoke(tmp_path):
    rec, md = _run_small("design.py", tmp_path)
    assert (tmp_path / "rec.png").stat().st_size > 0
    methods = [c["method"] for c in rec["cases"]]
    assert len(methods) == 3 and methods[0].startswith("closed form") and "link extensions" in methods[2]
    for c in rec["cases"]:
        assert c["system"].startswith("3-link arm") and c["bodies"] == [1, 2]
        assert c["coupling_before"] > 0.1 and c["residual_coupling"] < 1e-10
    # closed form and mass-penalised synthesis agree (3.15); extensions to twice the reach: 1.375
    assert abs(rec["cases"][0]["added_mass"] - 3.15) < 1e-9 and abs(rec["cases"][1]["added_mass"] - 3.15) < 1e-6
    assert abs(rec["cases"][2]["added_mass"] - 1.375) < 1e-6 and rec["cases"][2]["extension_length"] == [1.0, 0.3]
    t = rec["tradeoff"]
    assert len(t["coupling_weight"]) == 2 and t["residual_coupling"][1] < t["residual_coupling"][0]
    assert "## Trade-off" in md and "link extensions" in md


@pytest.mark.slow  # about 40 s on 2 busy cores (Panda's regressor compiles, one LM fit)
def test_identify_benchmark_smoke(tmp_path):
    rec, md = _run_small("identify.py", tmp_path)
    pd = rec["panda"]
    assert (pd["n_param"], pd["rank"], pd["n_states"]) == (90, 43, 100)
    assert pd["noise_free_max_rel_error"] < 1e-8 and 0.5 < pd["noisy_mean_z2"] < 2.0
    (fit,) = rec["fits"]
    assert fit["optimizer"] == "levenberg_marquardt" and 0 < fit["iterations"] < 30
    assert fit["loss"] < 1e-14 * fit["loss0"] and fit["max_rel_param_error"] < 1e-6
    assert "| double pendulum 1 s, masses + CM, +-30 % | LM |" in md


def test_gradient_profile_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "kernels.py"), "gradient", "--kernels", "vectorised", "--min-time", "0.01", "--no-rollout",
           "--out", str(tmp_path), "--name", "rec"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rec.json").read_text())
    assert [r["piece"] for r in rec["rows"]] == ["forward", "jvp (value and tangent)", "vjp (value and cotangent)"]
    assert all(r["us"] > 0 for r in rec["rows"]) and rec["rows"][0]["ratio"] == 1.0
    assert "| vectorised | vjp (value and cotangent) |" in (tmp_path / "rec.md").read_text()


def test_native_build_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "kernels.py"), "build", "--models", "chain2", "--out", str(tmp_path), "--name", "rec"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rec.json").read_text())
    assert [r["program"] for r in rec["rows"]] == ["fd", "jvp", "vjp"]
    fd, jvp, vjp = rec["rows"]
    assert fd["nv"] == 2 and all(r["compile_s"] > 0 for r in rec["rows"])
    assert jvp["lines"] > fd["lines"] and vjp["lines"] > fd["lines"]  # the derivative programs contain the forward one
    assert "| chain2 | 2 | vjp |" in (tmp_path / "rec.md").read_text()
    # the kernel's own level ($JAXBODY_NATIVE_OPTIMISATION, which the suite sets) and build
    assert fd["level"] == os.environ.get("JAXBODY_NATIVE_OPTIMISATION", "-O2") and fd["build"] == "narrow"
    # another optimisation level and build: the quick build of a single state
    cmd = [sys.executable, str(BENCH / "kernels.py"), "build", "--models", "chain2", "--modes", "fd", "--level=-O0",
           "--build", "one", "--out", str(tmp_path), "--name", "quick"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    (row,) = json.loads((tmp_path / "quick.json").read_text())["rows"]
    assert (row["program"], row["level"], row["build"]) == ("fd", "-O0", "one") and row["compile_s"] > 0


@pytest.mark.slow  # builds the Panda arm's RK4 step for batches and for single states
def test_step_kernel_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "kernels.py"), "step", "--models", "panda,double_pendulum", "--batches", "16",
           "--min-time", "0.01", "--rounds", "2", "--out", str(tmp_path), "--name", "rec"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rec.json").read_text())
    assert [r["piece"] for r in rec["rows"]] == ["kernel", "simulate", "energy"] * 2
    assert [r["model"] for r in rec["rows"]] == ["panda"] * 3 + ["chain2"] * 3
    assert all(r["float64_ns"] > 0 and r["float32_ns"] > 0 and r["ratio"] > 0 for r in rec["rows"])
    assert all(len(r["round_ratios"]) == 2 and min(r["round_ratios"]) <= r["ratio"] <= max(r["round_ratios"])
               for r in rec["rows"])
    md = (tmp_path / "rec.md").read_text()
    assert "| panda | 16 | kernel |" in md and "| chain2 | 16 | simulate |" in md
    # the same loop alone, for a profiler (kernels.py loop), on the kernels just built
    cmd = [sys.executable, str(BENCH / "kernels.py"), "loop", "--dtype", "float32", "--batch", "16", "--seconds", "0.01"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    assert "panda float32 B=16:" in p.stdout and "ns/state-step" in p.stdout
    cmd[3:3] = ["--model", "chain2"]  # a generated hinge chain
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    assert "chain2 float32 B=16:" in p.stdout


@pytest.mark.slow  # builds a 2-link chain's RK4 step and its reverse-mode program twice (256-bit, scalar)
def test_single_state_builds_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "kernels.py"), "single-state", "--models", "chain2", "--pairs", "1", "--min-time", "0.01",
           "--out", str(tmp_path), "--name", "rec"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rec.json").read_text())
    assert [r["piece"] for r in rec["rows"]] == ["step", "step_vjp", "simulate", "gradient"]
    assert all(r["us_256"] > 0 and r["us_scalar"] > 0 and len(r["pair_ratios"]) == 1 for r in rec["rows"])
    assert "| chain2 | step_vjp |" in (tmp_path / "rec.md").read_text()


def test_saving_benchmark_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "saving.py"), "--models", "double_pendulum", "--batch", "4", "--steps", "20",
           "--rounds", "1", "--min-time", "0.01", "--out", str(tmp_path), "--name", "rec"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rec.json").read_text())
    assert rec["stamp"]["commit"] and rec["results"]["steps"] == 20
    rows = rec["results"]["models"]["double_pendulum"]
    assert list(rows) == ["t1", "n_save=101", "n_save=1001"] and rows["t1"]["over_t1"] == 1.0
    assert all(r["ns_per_state_step"] > 0 and len(r["samples_ns"]) == 1 for r in rows.values())
    assert "| double_pendulum | n_save=1001 |" in (tmp_path / "rec.md").read_text()


@pytest.mark.slow  # compiles the solve, its gradient and a batch, each saving two ways, native and in diffrax's loop
def test_rk4_saves_benchmark_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "rk4_saves.py"), "--t1", "0.05", "--saves", "7", "--batch", "3",
           "--repeats", "1", "--out", str(tmp_path)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rk4_saves.json").read_text())
    assert rec["stamp"]["commit"] and rec["settings"]["steps"] == 50
    rows = rec["results"]
    assert list(rows) == ["7 times", "end state"]
    for row in rows.values():
        assert all(row[k][case] > 0 for k in ("native_s", "diffrax_loop_s") for case in ("solve", "gradient", "batch"))
        # the same steps and dense output: rounding apart
        assert row["max_state_difference"] < 1e-12 and row["max_relative_gradient_difference"] < 1e-10
    assert "| 7 times | batch of 3 |" in (tmp_path / "rk4_saves.md").read_text()


def test_throughput_rerender_of_the_gpu_record(tmp_path):
    # The GPU record was measured on a lent machine; --rerender re-analyses it here. The
    # GPU targets come out of its numbers, and targets a run did not measure say so.
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg")
    for name in ("throughput_gpu",):
        cmd = [sys.executable, str(BENCH / "throughput.py"), "--rerender", str(BENCH / "results" / f"{name}.json"),
               "--out", str(tmp_path), "--name", name]
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
        assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
        rec = json.loads((tmp_path / f"{name}.json").read_text())
        assert rec["stamp"]["gpu"].startswith("NVIDIA") and rec["runs"]["panda"]["jb32"]["backend"] == "gpu"
        targets = {(t["id"], t["target"][:20]): t for t in rec["targets"]}
        t1 = targets[("batch-vs-mujoco", "panda: jaxbody float")]
        assert t1["verdict"] == "NOT MEASURED"  # no MuJoCo CPU rollout in a GPU run
        gpu = [t for t in rec["targets"] if t["id"] == "GPU"]
        assert len(gpu) == 2
        rate = max(w["run"]["steps_per_s"] for w in rec["runs"]["panda"]["jb32"]["batches"].values())
        assert gpu[0]["verdict"] == ("MET" if rate >= 1e7 else "NOT MET")
        mjx = {b: w["run"]["steps_per_s"] for b, w in rec["runs"]["panda"]["mjx"].items()}
        ratios = [rec["runs"]["panda"]["jb32"]["batches"][b]["run"]["steps_per_s"] / y for b, y in mjx.items()]
        assert gpu[1]["verdict"] == ("MET" if min(ratios) >= 10 else "NOT MET")
        md = (tmp_path / f"{name}.md").read_text()
        assert "kernel" in md and "Where it ran: jb32 on NVIDIA H200" in md


def test_kernels_script_lists_its_subcommands():
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.run([sys.executable, str(BENCH / "kernels.py"), "--help"], capture_output=True, text=True,
                       timeout=120, env=env, cwd=REPO)
    assert p.returncode == 0, p.stderr[-3000:]
    for sub in ("compare", "build", "step", "loop", "single-state", "gradient", "gpu-profile"):
        assert f"  {sub} " in p.stdout, sub


def test_loop_body_ops_counts_the_top_level_operations_of_each_while_body():
    sys.path.insert(0, str(BENCH))
    import _common

    hlo = """HloModule m

%fused_computation (p: f32[4]) -> f32[4] {
  %p = f32[4]{0} parameter(0)
  ROOT %n = f32[4]{0} negate(%p)
}

%body (arg: (s32[], f32[4])) -> (s32[], f32[4]) {
  %arg = (s32[], f32[4]{0}) parameter(0)
  %i = s32[] get-tuple-element(%arg), index=0
  %x = f32[4]{0} get-tuple-element(%arg), index=1
  %one = s32[] constant(1)
  %j = s32[] add(%i, %one)
  %y = f32[4]{0} fusion(%x), kind=kLoop, calls=%fused_computation
  %z = f32[4]{0} custom-call(%y), custom_call_target="k"
  %b = f32[2,2]{1,0} bitcast(%z)
  ROOT %t = (s32[], f32[4]{0}) tuple(%j, %z)
}

%cond (arg: (s32[], f32[4])) -> pred[] {
  %arg = (s32[], f32[4]{0}) parameter(0)
  %i = s32[] get-tuple-element(%arg), index=0
  %n = s32[] constant(10)
  ROOT %lt = pred[] compare(%i, %n), direction=LT
}

ENTRY %main (x: f32[4]) -> (s32[], f32[4]) {
  %x = f32[4]{0} parameter(0)
  %zero = s32[] constant(0)
  %init = (s32[], f32[4]{0}) tuple(%zero, %x)
  ROOT %w = (s32[], f32[4]{0}) while(%init), condition=%cond, body=%body
}
"""
    out = _common.loop_body_ops(hlo)
    assert out["max"] == 3
    assert out["bodies"] == [{"body": "body", "ops": 3, "by_opcode": {"add": 1, "fusion": 1, "custom-call": 1}}]
    assert _common.loop_body_ops("HloModule m\n") == {"max": 0, "bodies": []}


@pytest.mark.slow
def test_step_profile_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "kernels.py"), "gpu-profile", "--cases", "float64:4,float32:4", "--steps", "3",
           "--kernel", "vectorised", "--repeats", "1", "--out", str(tmp_path), "--name", "rec"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rec.json").read_text())
    assert [(r["dtype"], r["batch"]) for r in rec["rows"]] == [("float64", 4), ("float32", 4)]
    for r in rec["rows"]:
        assert r["steps_per_s"] > 0 and r["loop_body_ops"]["max"] > 0
        assert r["cost_analysis"]["flops"] > 0 and r["trace"]["call_s"] > 0
    assert "| float32 | 4 |" in (tmp_path / "rec.md").read_text()


def _run_fresh(script, tmp_path, *args):
    """A before/after benchmark (fresh worker processes) with one repeat: its record and table."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / script), *args, "--repeats", "1", "--out", str(tmp_path), "--name", "rec"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    return json.loads((tmp_path / "rec.json").read_text()), (tmp_path / "rec.md").read_text()


@pytest.mark.slow  # fresh processes, cold and warm, each compiling a simulation and its gradient
def test_first_call_benchmark_smoke(tmp_path):
    """benchmarks/first_call.py: the disk in fresh processes, cold and warm cache, each stage timed."""
    rec, md = _run_fresh("first_call.py", tmp_path, "--cases", "disk", "--trees", "this")
    assert {r["phase"] for r in rec["runs"]} >= {"cold", "warm"}
    for run in rec["runs"]:
        assert run["case"] == "disk" and "error" not in run, run
        assert all(run[k] > 0 for k in ("import_s", "simulate_s", "grad_s"))
    assert "| disk |" in md


@pytest.mark.slow  # four fresh processes, each compiling a gradient from an empty cache
def test_forward_derivative_benchmark_smoke(tmp_path):
    """benchmarks/forward_derivative.py: the arm with one gain and the disk, in each mode."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "forward_derivative.py"), "--sizes", "1", "--calls", "1", "--out", str(tmp_path),
           "--name", "rec"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "rec.json").read_text())
    assert {(r["case"], r["mode"]) for r in rec["runs"]} == {(c, m) for c in ("arm", "disk") for m in ("forward", "reverse")}
    for run in rec["runs"]:  # each mode served every derivative of its process
        assert run["counts"]["forward"] > 0 if run["mode"] == "forward" else run["counts"]["forward"] == 0, run
    forward = {r["case"]: r["grad"] for r in rec["runs"] if r["mode"] == "forward"}
    reverse = {r["case"]: r["grad"] for r in rec["runs"] if r["mode"] == "reverse"}
    for case in forward:
        np.testing.assert_allclose(forward[case], reverse[case], rtol=1e-10)
    assert "| arm | 1 |" in (tmp_path / "rec.md").read_text()


@pytest.mark.slow  # about 20 s: the four-bar's solve traced and compiled twice in a fresh process
def test_constrained_program_benchmark_smoke(tmp_path):
    """benchmarks/constrained_program.py: the four-bar's solve program measured; the quick and the
    optimised program reach the same state, and the frames are computed once per evaluation (a
    handful of copies of forward kinematics in the whole solve, not one per constraint request)."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "constrained_program.py"), "--cases", "four-bar", "--out", str(tmp_path), "--name", "rec"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    (run,) = json.loads((tmp_path / "rec.json").read_text())["runs"]
    assert "error" not in run, run
    assert run["hlo_lines"] > 1000 and 1 <= run["kinematics_copies"] <= 12, run
    assert run["quick_compile_s"] > 0 and run["optimised_run_s"] > 0
    np.testing.assert_allclose(run["quick_q_final_sum"], run["optimised_q_final_sum"], rtol=1e-9)
    assert "| four-bar | this tree |" in (tmp_path / "rec.md").read_text()


def test_eager_calls_benchmark_smoke(tmp_path):
    """benchmarks/eager_calls.py: one model in a fresh process, first and later eager calls timed."""
    rec, md = _run_fresh("eager_calls.py", tmp_path, "--models", "chain2", "--calls", "2")
    (run,) = rec["runs"]
    assert run["model"] == "chain2" and set(run["times"]) == {"inverse_dynamics", "forward_dynamics", "mass_matrix",
                                                            "scene_acceleration"}
    assert all(t["first_s"] > 0 and t["later_s"] > 0 for t in run["times"].values())
    assert "| chain2 | `jb.mass_matrix` | this tree |" in md


SCRIPTS = sorted(p.name for p in BENCH.glob("*.py") if not p.name.startswith("_"))
KERNEL_PROBES = ("compare", "build", "step", "loop", "single-state", "gradient", "gpu-profile")


@pytest.mark.parametrize("args", [[s] for s in SCRIPTS if s != "kernels.py"] + [["kernels.py", k] for k in KERNEL_PROBES],
                         ids=lambda a: " ".join(a))
def test_every_benchmark_answers_help(args):
    """Every script (and every probe of kernels.py) parses its options; the ones without a run of
    their own here (dynamics, linalg, maggi) are at least imported and their flags listed."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    p = subprocess.run([sys.executable, str(BENCH / args[0]), *args[1:], "--help"], capture_output=True, text=True,
                       timeout=300, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    assert "usage:" in p.stdout


@pytest.mark.slow  # about 2 min on 2 busy cores: the shipped robots and one random tree
def test_mujoco_agreement_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.setdefault("XLA_FLAGS", default_xla_flags())
    cmd = [sys.executable, str(BENCH / "mujoco_agreement.py"), "--random", "1", "--states", "1", "--out", str(tmp_path)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads((tmp_path / "mujoco_agreement.json").read_text())
    assert rec["stamp"]["commit"] and all(float(x) < 1e-10 for x in rec["worst"].values())
    assert "| random0 |" in (tmp_path / "mujoco_agreement.md").read_text()
