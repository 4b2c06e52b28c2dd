"""Which SPD factorisation/solve should jaxbody use on CPU in batch?

Times ``jaxbody.linalg.solve_spd`` (methods ``crout``, ``right_looking``, ``unrolled``;
the default ``auto`` is ``unrolled`` for n <= 8 and ``crout`` above) against LAPACK
through ``jnp.linalg.solve`` (LU, ``lapack_lu``) and
``jax.scipy.linalg.cho_solve(cho_factor(...))`` (``lapack_cholesky``), all as
``jit(vmap(solve))`` over a batch of random well-conditioned SPD systems ``A x = b``;
``lapack_lu_grad`` is ``jit(vmap(grad(sum(jnp.linalg.solve(A, b)), (A, b))))`` (the
reverse pass adds batched transposed LU solves; compare with the ``grad ms`` column).

* Compile time (``lower`` + ``compile``) and run time are measured separately; the run is
  warmed up and every call ends with ``block_until_ready``. Throughput = batch / fastest
  repeat (the machine may be shared; the stamp records the load average).
* ``grad ms``: ``jit(vmap(grad(sum(solve(A, b)), (A, b))))``, jaxbody methods only.
* Every (XLA-flag setting, dtype, method, n) runs in its own worker process; every LAPACK
  (n, batch) case too, calling the solve ``--lapack-calls`` times with a timeout
  (``--lapack-timeout``), because batched LAPACK calls under ``vmap`` intermittently
  deadlock XLA's CPU thread pool with jax/jaxlib 0.10.2. A killed worker is recorded as
  ``deadlock/timeout after k/N calls``, not a hang.
* Runs with ``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false`` and with ``XLA_FLAGS`` unset
  (``--flags``).
* ``unrolled`` above ``UNROLLED_MAX_N`` (16, the public limit) is timed through the private
  core, at the largest batch only, to record its compile time.

Outputs ``benchmarks/results/linalg.md`` and ``linalg.json`` (``--quick``:
``linalg_quick.*``), stamped with commit, CPU, versions, date, flags, load and command.

    .venv/bin/python benchmarks/linalg.py            # full record (~15-25 min on 2 cores)
    .venv/bin/python benchmarks/linalg.py --quick    # harness check (~2 min)
    .venv/bin/python benchmarks/linalg.py --n 7,20 --batch 8192 --flags off
"""

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    REPO,
    RESULTS,
    load_average,
    markdown_table,
    run_worker,
    stamp,
    stamp_markdown,
    time_per_call,
)

OURS = ("crout", "right_looking", "unrolled")
LAPACK = ("lapack_lu", "lapack_cholesky", "lapack_lu_grad")
FLAG_MODES = {"off": "--xla_cpu_use_fusion_emitters=false", "default": ""}


# ----------------------------------------------------------------------------- worker
def _problem(n, batch, dtype, seed=0):
    import numpy as np

    rng = np.random.default_rng(seed)
    X = rng.standard_normal((batch, n, n))
    A = X @ X.transpose(0, 2, 1) / n + np.eye(n)  # eigenvalues in about [1, 5]
    b = rng.standard_normal((batch, n))
    return A.astype(dtype), b.astype(dtype)


def _solver(method, n):
    import jax
    import jax.numpy as jnp

    from jaxbody import linalg

    if method == "lapack_lu":
        return jnp.linalg.solve
    if method == "lapack_lu_grad":  # reverse mode: LU solve plus transposed solve
        return jax.grad(lambda A, b: jnp.linalg.solve(A, b).sum(), argnums=(0, 1))
    if method == "lapack_cholesky":
        return lambda A, b: jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(A, lower=True), b)
    if method == "unrolled" and n > linalg.UNROLLED_MAX_N:
        return lambda A, b: linalg._solve(A, b, "unrolled")[0]  # past the public limit
    return lambda A, b: linalg.solve_spd(A, b, method=method)


def worker(cfg):
    out = pathlib.Path(cfg["result"])
    record = {"cases": []}

    def save():
        out.write_text(json.dumps(record))

    import jax

    jax.config.update("jax_enable_x64", cfg["dtype"] == "float64")
    import jax.numpy as jnp
    import numpy as np

    jax.jit(lambda x: x + 1)(jnp.ones(())).block_until_ready()  # XLA start-up, not counted
    n, method = cfg["n"], cfg["method"]
    solve = _solver(method, n)
    for batch in cfg["batches"]:
        case = {"batch": batch, "status": "started"}
        record["cases"].append(case)
        save()
        A_np, b_np = _problem(n, batch, cfg["dtype"])
        A, b = jnp.asarray(A_np), jnp.asarray(b_np)
        f = jax.jit(jax.vmap(solve))
        t0 = time.perf_counter()
        compiled = f.lower(A, b).compile()
        case["compile_s"] = time.perf_counter() - t0
        save()
        if method in LAPACK:
            # Count calls as they complete: on a deadlock the parent kills us and keeps this.
            case["calls_done"] = 0
            save()
            times = []
            for _ in range(cfg["lapack_calls"]):
                t0 = time.perf_counter()
                x = jax.block_until_ready(compiled(A, b))
                times.append(time.perf_counter() - t0)
                case["calls_done"] += 1
                save()
            times = times[1:] or times  # first call is the warm-up
            case["run"] = {"min_s": min(times), "median_s": float(np.median(times)), "repeats": len(times)}
        else:
            x = compiled(A, b).block_until_ready()
            case["run"] = time_per_call(
                lambda: compiled(A, b).block_until_ready(), min_time=cfg["min_time"], warmup=False
            )
            if cfg["grad"]:
                g = jax.jit(jax.vmap(jax.grad(lambda A, b: solve(A, b).sum(), argnums=(0, 1))))
                cg = g.lower(A, b).compile()
                case["grad"] = time_per_call(lambda: jax.block_until_ready(cg(A, b)), min_time=cfg["min_time"])
        if method.endswith("_grad"):
            case["finite"] = all(bool(np.isfinite(np.asarray(g)).all()) for g in x)
        else:
            x = np.asarray(x, np.float64)
            r = np.einsum("bij,bj->bi", A_np.astype(np.float64), x) - b_np
            case["max_rel_residual"] = float(np.max(np.linalg.norm(r, axis=1) / np.linalg.norm(b_np, axis=1)))
            case["finite"] = bool(np.isfinite(x).all())
        case["status"] = "ok"
        save()


# ----------------------------------------------------------------------------- parent
def _run(cfg, timeout, flags, tmp):
    result = pathlib.Path(tmp) / f"w{time.monotonic_ns()}.json"
    cfg = {**cfg, "result": str(result)}
    env = {**os.environ, "XLA_FLAGS": flags, "PYTHONPATH": str(REPO)}
    if not flags:
        env.pop("XLA_FLAGS")
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--worker", json.dumps(cfg)]
    return run_worker(cmd, timeout=timeout, result_file=result, env=env)


def _fmt(x, digits=3):
    return None if x is None else f"{x:.{digits}g}"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="small harness check; writes linalg_quick.*")
    p.add_argument("--n", default=None, help="matrix sizes (default 7,20,50,100; quick 7,20)")
    p.add_argument("--batch", default=None, help="batch sizes (default 1,64,1024,8192; quick 1,1024)")
    p.add_argument("--dtypes", default=None, help="float32,float64 (default both; quick float32)")
    p.add_argument("--flags", default=None, help="XLA flag settings: off,default (default both; quick off)")
    p.add_argument("--methods", default=",".join(OURS + LAPACK))
    p.add_argument("--max-elements", type=float, default=3e7, help="skip cases with batch*n*n above this")
    p.add_argument("--unrolled-max-n", type=int, default=20, help="largest n timed for 'unrolled'")
    p.add_argument("--lapack-calls", type=int, default=None, help="LAPACK calls per case (default 20; quick 5)")
    p.add_argument("--lapack-timeout", type=float, default=60.0, help="seconds per LAPACK case")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per jaxbody worker")
    p.add_argument("--min-time", type=float, default=None, help="seconds of timing per case")
    p.add_argument("--no-grad", action="store_true", help="skip gradient timing")
    p.add_argument("--out", default=str(RESULTS))
    p.add_argument("--name", default=None)
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker is not None:
        return worker(json.loads(args.worker))

    q = args.quick
    ns = [int(v) for v in (args.n or ("7,20" if q else "7,20,50,100")).split(",")]
    batches = [int(v) for v in (args.batch or ("1,1024" if q else "1,64,1024,8192")).split(",")]
    dtypes = (args.dtypes or ("float32" if q else "float32,float64")).split(",")
    flag_modes = (args.flags or ("off" if q else "off,default")).split(",")
    methods = args.methods.split(",")
    lapack_calls = args.lapack_calls or (5 if q else 20)
    min_time = args.min_time or (0.1 if q else 0.3)
    name = args.name or ("linalg_quick" if q else "linalg")
    info = stamp(argv if argv is not None else sys.argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for mode in flag_modes:
            flags = FLAG_MODES[mode]
            for dtype in dtypes:
                for n in ns:
                    fits = [B for B in batches if B * n * n <= args.max_elements]
                    for method in methods:
                        base = {"flags": mode, "dtype": dtype, "n": n, "method": method}
                        skipped = [B for B in batches if B not in fits]
                        todo = fits
                        if method == "unrolled" and n > args.unrolled_max_n:
                            skipped, todo = batches, []
                        elif method == "unrolled" and n > 16:
                            todo = fits[-1:]
                            skipped = [B for B in batches if B not in todo]
                        for B in skipped:
                            rows.append({**base, "batch": B, "status": "skipped"})
                        if not todo:
                            continue
                        cfg = {
                            "n": n, "method": method, "dtype": dtype, "min_time": min_time,
                            "grad": not args.no_grad and method in OURS, "lapack_calls": lapack_calls,
                        }
                        if method in LAPACK:
                            groups, timeout = [[B] for B in todo], args.lapack_timeout
                        else:
                            groups, timeout = [todo], args.timeout
                        for group in groups:
                            res = _run({**cfg, "batches": group}, timeout, flags, tmp)
                            cases = {c["batch"]: c for c in res.get("cases", [])}
                            for B in group:
                                c = cases.get(B, {})
                                status = c.get("status", "not started")
                                if status != "ok":
                                    if res["status"] == "timeout" and method in LAPACK and "calls_done" in c:
                                        status = f"deadlock/timeout after {c['calls_done']}/{lapack_calls} calls"
                                    elif res["status"] == "timeout":
                                        status = f"timeout ({status})"
                                    else:
                                        status = f"{res['status']} ({status})"
                                elif method in LAPACK:
                                    status = f"ok ({lapack_calls} calls)"
                                if not c.get("finite", True):
                                    status += ", non-finite result"
                                run = c.get("run", {})
                                row = {
                                    **base, "batch": B, "status": status,
                                    "compile_s": c.get("compile_s"),
                                    "run_min_s": run.get("min_s"), "run_median_s": run.get("median_s"),
                                    "throughput": B / run["min_s"] if run.get("min_s") else None,
                                    "grad_min_s": c.get("grad", {}).get("min_s"),
                                    "max_rel_residual": c.get("max_rel_residual"),
                                    "stderr_tail": res.get("stderr_tail") if status.startswith("error") else None,
                                }
                                rows.append(row)
                                print(
                                    f"[{mode:7s} {dtype} n={n:3d} B={B:5d}] {method:16s} {status:28s}"
                                    f" compile {_fmt(row['compile_s'])} s  run {_fmt(row['run_min_s'] and row['run_min_s'] * 1e3)} ms"
                                    f"  {_fmt(row['throughput'] and row['throughput'] / 1e6)} M/s",
                                    flush=True,
                                )
    info["load_average_end"] = load_average()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps({"stamp": info, "rows": rows}, indent=1))
    (out / f"{name}.md").write_text(_report(info, rows))
    print(f"\nwrote {out / (name + '.md')} and {out / (name + '.json')}")


def _report(info, rows):
    headers = ["XLA flags", "dtype", "n", "batch", "method", "status", "compile s", "run ms (min)",
               "run ms (median)", "M solves/s", "grad ms", "max rel. residual"]
    table = [
        [r["flags"], r["dtype"], r["n"], r["batch"], r["method"], r["status"], _fmt(r.get("compile_s")),
         _fmt(r.get("run_min_s") and r["run_min_s"] * 1e3), _fmt(r.get("run_median_s") and r["run_median_s"] * 1e3),
         _fmt(r.get("throughput") and r["throughput"] / 1e6), _fmt(r.get("grad_min_s") and r["grad_min_s"] * 1e3),
         _fmt(r.get("max_rel_residual"), 2)]
        for r in rows
    ]
    # Summary: for each (flags, dtype, n, batch), throughput of each method and ratio to crout.
    keys = sorted({(r["flags"], r["dtype"], r["n"], r["batch"]) for r in rows},
                  key=lambda k: (k[0], k[1], k[2], k[3]))
    present = [m for m in OURS + LAPACK if any(r["method"] == m for r in rows)]
    summary = []
    for k in keys:
        by = {r["method"]: r for r in rows if (r["flags"], r["dtype"], r["n"], r["batch"]) == k}
        ref = by.get("crout", {}).get("throughput")
        cells = []
        for m in present:
            r = by.get(m)
            if r is None:
                cells.append("")
            elif r.get("throughput"):
                ratio = f" ({r['throughput'] / ref:.2g}×)" if ref and m != "crout" else ""
                cells.append(f"{r['throughput'] / 1e6:.3g}{ratio}")
            else:
                cells.append(r["status"])
        summary.append([*k, *cells])
    compile_rows = []
    for k in sorted({(r["flags"], r["dtype"], r["n"]) for r in rows}):
        cells = []
        for m in present:
            cs = [r["compile_s"] for r in rows if (r["flags"], r["dtype"], r["n"]) == k and r["method"] == m
                  and r.get("compile_s") is not None]
            cells.append(_fmt(max(cs)) if cs else "")
        compile_rows.append([*k, *cells])
    lapack = [r for r in rows if r["method"] in LAPACK]
    dead = [r for r in lapack if "deadlock" in r["status"] or "timeout" in r["status"]]
    parts = [
        "# SPD solve on CPU in batch: jaxbody.linalg vs LAPACK",
        "",
        "Question: which factorisation should `jaxbody.linalg.solve_spd` use by default, and does "
        "batched LAPACK (`jnp.linalg.solve`, `cho_solve`, and the gradient of `jnp.linalg.solve`) "
        "under `vmap` deadlock here? "
        "`jit(vmap(solve))` over random SPD systems (eigenvalues in about [1, 5]); compile and run "
        "timed separately; throughput from the fastest repeat. Compare numbers within this run only.",
        "",
        stamp_markdown(info),
        "",
        f"LAPACK cases: {len(lapack)}, of which deadlocked/timed out: {len(dead)}"
        + ("" if not dead else " — " + "; ".join(
            f"{r['method']} {r['flags']} {r['dtype']} n={r['n']} B={r['batch']}: {r['status']}" for r in dead)),
        "",
        "## Throughput (million solves/s; ratio to `crout` in parentheses)",
        "",
        markdown_table(["XLA flags", "dtype", "n", "batch", *present], summary),
        "",
        "## Compile time (s, `lower` + `compile` of `jit(vmap(solve))`, largest over batch sizes)",
        "",
        markdown_table(["XLA flags", "dtype", "n", *present], compile_rows),
        "",
        "## All cases",
        "",
        markdown_table(headers, table),
        "",
    ]
    return "\n".join(parts)


if __name__ == "__main__":
    main()
