"""What a quick first compile saves and what its program costs to run: every program quick
against every program optimised.

    python benchmarks/tiered_compilation.py [--name NAME] [--cases C] [--calls N]

jaxbody compiles a first call's programs quickly (XLA's backend optimisation level 0, the native
kernel's C++ at -O0) and their optimised programs in the background (jaxbody.tiered_compilation).
This measures the two ends in fresh processes, each with an empty cache and tiering switched
off so that one kind of program runs throughout: **quick** (every XLA program at level 0 in
one code-generation part, every native library at -O0) and **optimised** (the defaults). Per
case (those of ``benchmarks/first_call.py``): the first ``jb.simulate`` of 1 s, the median of
``--calls`` later ones (the run alone), the first ``jax.grad`` of the case's loss and the median
of later ones. Writes ``NAME.json`` and ``NAME.md`` (default ``tiered_compilation``) to
``benchmarks/results``.
"""

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import load_average, stamp, write_record  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
CASES = ("panda", "iiwa", "disk", "four-bar")
QUICK_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_cpu_parallel_codegen_split_count=1"


def _worker(case: str, calls: int) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxbody as jb
    from first_call import case_setup

    system, q0, v0, loss, arg = case_setup(case)
    out = {"case": case}

    def timed(fn):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        return time.perf_counter() - t

    out["first_simulate_s"] = timed(lambda: jb.simulate(system, q0, v0, 1.0).q)
    out["simulate_s"] = statistics.median(timed(lambda: jb.simulate(system, q0, v0, 1.0).q) for _ in range(calls))
    out["first_grad_s"] = timed(lambda: jax.grad(loss)(arg))
    out["grad_s"] = statistics.median(timed(lambda: jax.grad(loss)(arg)) for _ in range(calls))
    return out


def _run(case: str, kind: str, calls: int) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "JAXBODY_KERNEL", "JAXBODY_JAX_CACHE",
                                                            "JAXBODY_NATIVE_OPTIMISATION")}
    env["JAXBODY_TIERED_COMPILE"] = "0"
    if kind == "quick":
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {QUICK_XLA_FLAGS}".strip()
        env["JAXBODY_NATIVE_OPTIMISATION"] = "-O0"
    with tempfile.TemporaryDirectory(prefix="jaxbody-tiered-") as cache:
        env["JAXBODY_CACHE_DIR"] = cache
        proc = subprocess.run([sys.executable, str(pathlib.Path(__file__).resolve()), "--worker", case, "--calls", str(calls)],
                              capture_output=True, text=True, env=env, timeout=1800)
    if proc.returncode != 0:
        raise SystemExit(f"{case} ({kind}) failed:\n{proc.stderr[-3000:]}")
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]), kind=kind)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", default="tiered_compilation")
    p.add_argument("--cases", default=",".join(CASES))
    p.add_argument("--calls", type=int, default=5, help="later calls timed (their median)")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(_worker(args.worker, args.calls)))
        return
    record = {"stamp": stamp(), "calls": args.calls, "runs": []}
    for case in args.cases.split(","):
        for kind in ("quick", "optimised"):
            record["runs"].append(_run(case, kind, args.calls))
            print(record["runs"][-1], flush=True)
    record["stamp"]["load_average_end"] = load_average()
    rows = []
    by = {(r["case"], r["kind"]): r for r in record["runs"]}
    for case in args.cases.split(","):
        q, o = by[(case, "quick")], by[(case, "optimised")]
        rows.append((case, f"{q['first_simulate_s']:.2f}", f"{o['first_simulate_s']:.2f}",
                     f"{1e3 * q['simulate_s']:.1f}", f"{1e3 * o['simulate_s']:.1f}", f"{q['simulate_s'] / o['simulate_s']:.2f}",
                     f"{q['first_grad_s']:.2f}", f"{o['first_grad_s']:.2f}",
                     f"{1e3 * q['grad_s']:.1f}", f"{1e3 * o['grad_s']:.1f}", f"{q['grad_s'] / o['grad_s']:.2f}"))
    text = ("Fresh processes, empty caches, tiering off: `quick` compiles every XLA program at backend optimisation "
            "level 0 in one code-generation part and builds every native library at -O0; `optimised` uses the "
            f"defaults. First calls in seconds; later calls: the median of {args.calls}, in milliseconds; `ratio`: "
            "quick / optimised.")
    print(write_record(args.name, record, "Quick against optimised programs: first calls and later runs", text,
                       ["case", "first simulate quick", "optimised", "later simulate quick (ms)", "optimised (ms)", "ratio",
                        "first gradient quick", "optimised", "later gradient quick (ms)", "optimised (ms)", "ratio"], rows))


if __name__ == "__main__":
    main()
