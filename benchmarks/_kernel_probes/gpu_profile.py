"""Where a batched RK4 rollout's time goes on an accelerator: XLA's cost analysis and
one profiled call.

For each dtype and batch this compiles the rollout ``benchmarks/throughput.py`` times (Panda,
``jb.simulate(jb.scene(model, kernel=KERNEL), ..., solver="rk4", dt0=1e-3,
saveat=SaveAt(t1=True))`` under ``jax.jit(jax.vmap(...))``, the model closed over, where
``throughput.py`` passes it as an argument)
and records, per state and step:

* the time of a call (median of a few) and system-steps/s;
* XLA's cost analysis of the compiled program: floating-point operations and bytes accessed
  (a ``while`` body counted once);
* the operations of one iteration of the step loop (``_common.loop_body_ops``);
* one call under ``jax.profiler.trace``: the device's kernels grouped by name (launches, total
  time), the share of the call's wall time the device was busy, the largest kernels.

Writes ``OUT/NAME.{md,json}``. On a GPU::

    python benchmarks/kernels.py gpu-profile --cases float32:65536,float32:1048576,float64:65536 --out OUT

(``jax_enable_x64`` is on for every case: float32 cases run a float32 model and state.)
"""

import argparse
import json
import pathlib
import statistics
import sys
import tempfile
import time
import warnings

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # benchmarks/: _common, dynamics
import _common  # noqa: E402
from _common import set_default_xla_flags  # noqa: E402

DT = 1e-3


def _device_kernels(trace_dir: pathlib.Path) -> dict:
    """Kernels of the device planes of the trace in ``trace_dir``, grouped by name."""
    from jax.profiler import ProfileData

    files = sorted(trace_dir.rglob("*.xplane.pb"))
    if not files:
        return {"error": "no trace written"}
    data = ProfileData.from_file(str(files[-1]))
    groups, busy, first, last, planes = {}, 0, None, None, []
    for plane in data.planes:
        if not plane.name.startswith("/device:"):
            continue
        planes.append(plane.name)
        for line in plane.lines:
            # the stream lines hold the kernels and copies; XLA's op and module lines repeat them
            if "stream" not in line.name.lower() or "xla" in line.name.lower():
                continue
            for ev in line.events:
                g = groups.setdefault(ev.name, {"launches": 0, "total_ns": 0})
                g["launches"] += 1
                g["total_ns"] += ev.duration_ns
                busy += ev.duration_ns
                first = ev.start_ns if first is None else min(first, ev.start_ns)
                last = ev.end_ns if last is None else max(last, ev.end_ns)
    top = sorted(groups.items(), key=lambda kv: -kv[1]["total_ns"])
    return {
        "planes": planes,
        "kernels": len(groups),
        "launches": sum(g["launches"] for g in groups.values()),
        "busy_ns": busy,
        "span_ns": (last - first) if first is not None else 0,
        "top": [{"name": k[:120], **v} for k, v in top[:15]],
    }


def run_case(jax, jb, model_file, dtype_name, batch, steps, kernel, repeats):
    import diffrax
    import jax.numpy as jnp

    from dynamics import _compile, _states
    from throughput import _rigid_rk4

    dtype = jnp.float64 if dtype_name == "float64" else jnp.float32
    m = _rigid_rk4(model_file)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mujoco(m, dtype=dtype)
    q, v, _, _ = _states(m, batch, 0)
    q, v = jnp.asarray(q, dtype), jnp.asarray(v, dtype)

    def rollout(q0, v0):
        sol = jb.simulate(jb.scene(model, kernel=kernel), q0, v0, steps * DT, solver="rk4", dt0=DT,
                          saveat=diffrax.SaveAt(t1=True), max_steps=steps + 16)
        return sol.q[-1], sol.v[-1]

    jitted, compiled, _, compile_times = _compile(jax, jax.vmap(rollout), (q, v))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(jitted(q, v))
        times.append(time.perf_counter() - t0)
    median = statistics.median(times)
    state_steps = batch * steps
    row = {"dtype": dtype_name, "batch": batch, "steps": steps, "kernel": kernel,
           "compile_s": compile_times["compile_total_s"], "call_s": median, "times_s": times,
           "steps_per_s": state_steps / median, "ns_per_state_step": median / state_steps * 1e9,
           "loop_body_ops": _common.loop_body_ops(compiled.as_text())}
    try:
        cost = compiled.cost_analysis()
        cost = cost[0] if isinstance(cost, (list, tuple)) else cost
        flops, nbytes = float(cost.get("flops", 0.0)), float(cost.get("bytes accessed", 0.0))
        # a while loop's body is counted once by the analysis: scale by the steps it runs
        row["cost_analysis"] = {"flops": flops, "bytes_accessed": nbytes,
                                "note": "XLA counts a while loop's body once"}
    except Exception as e:  # noqa: BLE001 - not every backend has it
        row["cost_analysis"] = {"error": f"{e.__class__.__name__}: {e}"[:200]}
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp):
            t0 = time.perf_counter()
            jax.block_until_ready(jitted(q, v))
            traced_s = time.perf_counter() - t0
        row["trace"] = {"call_s": traced_s, **_device_kernels(pathlib.Path(tmp))}
    tr = row["trace"]
    if tr.get("launches"):
        tr["launches_per_step"] = tr["launches"] / steps
        tr["busy_share_of_call"] = tr["busy_ns"] * 1e-9 / traced_s
    return row


def markdown(rec) -> str:
    lines = ["# Where a batched RK4 step's time goes (XLA cost analysis, one profiled call)", "",
             _common.stamp_markdown(rec["stamp"]), ""]
    rows = []
    for r in rec["rows"]:
        if "error" in r:
            rows.append([r["dtype"], r["batch"], "error: " + r["error"][:80]] + [""] * 7)
            continue
        tr = r.get("trace", {})
        rows.append([r["dtype"], r["batch"], f"{r['steps_per_s'] / 1e6:.3g}M", f"{r['ns_per_state_step']:.3g}",
                     r["loop_body_ops"]["max"], f"{tr.get('launches_per_step', float('nan')):.3g}",
                     f"{tr.get('busy_share_of_call', float('nan')):.2f}",
                     f"{r['cost_analysis'].get('flops', float('nan')):.3g}",
                     f"{r['cost_analysis'].get('bytes_accessed', float('nan')):.3g}", f"{r['compile_s']:.0f}"])
    lines.append(_common.markdown_table(
        ["dtype", "batch", "steps/s", "ns / state-step", "loop body ops", "launches / step",
         "device busy / call", "XLA flops", "XLA bytes", "compile s"], rows))
    for r in rec["rows"]:
        top = r.get("trace", {}).get("top") or []
        if top:
            lines += ["", f"Largest kernels, {r['dtype']} B = {r['batch']} (one call of {r['steps']} steps):", ""]
            lines.append(_common.markdown_table(
                ["kernel", "launches", "total ms", "µs / launch"],
                [[k["name"][:60], k["launches"], f"{k['total_ns'] / 1e6:.3g}",
                  f"{k['total_ns'] / k['launches'] / 1e3:.3g}"] for k in top[:10]]))
    return "\n".join(lines) + "\n"


def main(argv=None):
    p = argparse.ArgumentParser(prog="kernels.py gpu-profile", description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="float32:65536,float32:1048576,float64:65536",
                   help="comma-separated dtype:batch")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--kernel", default="auto")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--model", default=str(_common.REPO / "jaxbody" / "models" / "panda.xml"))
    p.add_argument("--out", default=str(_common.RESULTS))
    p.add_argument("--name", default="step_profile")
    args = p.parse_args(argv)
    set_default_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxbody as jb

    rec = {"stamp": _common.stamp(), "device": str(jax.devices()[0]),
           "device_kind": jax.devices()[0].device_kind, "rows": []}
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for case in args.cases.split(","):
        dtype_name, batch = case.split(":")
        try:
            row = run_case(jax, jb, args.model, dtype_name, int(batch), args.steps, args.kernel, args.repeats)
        except Exception as e:  # noqa: BLE001 - recorded, the next case still runs
            row = {"dtype": dtype_name, "batch": int(batch), "error": f"{e.__class__.__name__}: {e}"[:600]}
        rec["rows"].append(row)
        print(json.dumps({k: v for k, v in row.items() if k not in ("trace", "loop_body_ops")}, default=str)[:400],
              flush=True)
        (out / f"{args.name}.json").write_text(json.dumps(rec, indent=1, default=str))
        (out / f"{args.name}.md").write_text(markdown(rec))
    print(f"wrote {out / args.name}.md, .json")


if __name__ == "__main__":
    main()
