"""The compiled program of a constrained simulation: its size, its compile and its run.

    python benchmarks/constrained_program.py [--cases four-bar,cassie] [--cassie PATH] [--baseline DIR] [--name NAME]

Each case runs in a fresh process per checkout (this tree, and ``--baseline DIR``, e.g. ``git
archive`` of an older commit, alternating with it): ``jax.jit`` of one ``jb.simulate`` of 1 s
with jaxbody's defaults, lowered (``trace``: seconds to trace and lower it), its size (lines
of StableHLO text, and the copies of forward kinematics in its jaxpr), then compiled twice
from the same lowering: quickly (XLA's backend optimisation level 0, as the first call of a
solve is, ``jaxbody.tiered_compilation.QUICK_OPTIONS``) and optimised (XLA's defaults), each
compile timed and its program run (the best of three runs). JAX's persistent compilation cache
is off in the workers, so every compile is a compile. Cases: ``four-bar`` (three hinged bodies
and a loop closure, ``benchmarks/maggi.py``) and ``cassie`` (a floating base with ball joints
and ``<connect>`` loops; only with ``--cassie PATH``, its MJCF). Writes ``NAME.json`` and
``NAME.md`` (default ``constrained_program``) to ``--out`` (default ``benchmarks/results``).
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import REPO, RESULTS, checkouts, parse_cases, stamp, write_record  # noqa: E402

sys.path.insert(0, str(REPO / "tests"))
from _support.jaxpr_tools import count_eqns  # noqa: E402

CASES = ("four-bar", "cassie")


def _is_kinematics(eqn) -> bool:
    """A call of forward kinematics (its nested jit) in a jaxpr."""
    return eqn.primitive.name in ("pjit", "jit") and eqn.params.get("name") == "_forward_kinematics"


def _best_run(compiled, *args) -> float:
    import jax

    jax.block_until_ready(compiled(*args))
    times = []
    for _ in range(3):
        t = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t)
    return min(times)


def _worker(case: str, cassie: str | None) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxbody as jb
    from first_call import case_setup

    system, q0, v0, _, _ = case_setup(case, cassie)
    simulate = jax.jit(lambda q, v: jb.simulate(system, q, v, 1.0).q)
    t = time.perf_counter()
    lowered = simulate.lower(q0, v0)
    out = {"case": case, "trace_s": time.perf_counter() - t, "hlo_lines": len(lowered.as_text().splitlines())}
    jaxpr = jax.make_jaxpr(lambda q, v: jb.simulate(system, q, v, 1.0).q)(q0, v0).jaxpr
    out["kinematics_copies"] = count_eqns(jaxpr, _is_kinematics)
    for label, options in (("quick", {"xla_backend_optimization_level": 0, "xla_cpu_parallel_codegen_split_count": 1}),
                           ("optimised", {})):
        t = time.perf_counter()
        compiled = lowered.compile(compiler_options=options)
        out[f"{label}_compile_s"] = time.perf_counter() - t
        out[f"{label}_run_s"] = _best_run(compiled, q0, v0)
        out[f"{label}_q_final_sum"] = float(jnp.sum(compiled(q0, v0)[-1]))
    return out


def _run(case, cassie, tree_path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("JAXBODY_KERNEL",)}
    env["JAX_ENABLE_COMPILATION_CACHE"] = "false"
    if tree_path is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(tree_path), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--worker", case] + (["--cassie", cassie] if cassie else [])
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    if proc.returncode != 0:
        return {"case": case, "error": proc.stderr[-2000:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", default="constrained_program")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    p.add_argument("--cases", default="four-bar", help=f"comma-separated of {CASES}")
    p.add_argument("--cassie", help="MJCF of a Cassie-like model (floating base, ball joints, <connect> loops)")
    p.add_argument("--baseline", type=pathlib.Path, help="another checkout timed alongside this tree")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(_worker(args.worker, args.cassie)))
        return
    cases = parse_cases(args.cases, CASES, args.cassie)
    trees, baseline = checkouts(args.baseline)
    record = {"stamp": stamp(), "runs": []}
    if baseline:
        record["baseline"] = baseline
    rows = []
    for case in cases:
        for tree, path in trees.items():
            r = dict(_run(case, args.cassie, path), tree=tree)
            record["runs"].append(r)
            print(r, flush=True)
            if "error" in r:
                rows.append((case, tree, "failed: " + r["error"].strip().splitlines()[-1][:80], "", "", "", "", "", "", ""))
                continue
            rows.append((case, tree, f"{r['trace_s']:.2f}", str(r["hlo_lines"]), str(r["kinematics_copies"]),
                         f"{r['quick_compile_s']:.2f}", f"{r['quick_run_s']:.3f}", f"{r['optimised_compile_s']:.2f}",
                         f"{r['optimised_run_s']:.3f}", f"{r['optimised_q_final_sum']:.12g}"))
    text = ("One `jb.simulate` of 1 s under `jax.jit`, fresh process per row, JAX's persistent cache off. Seconds; "
            "`trace`: trace and lower; `HLO lines`: the lowered StableHLO's; `kinematics copies`: calls of forward "
            "kinematics in the jaxpr; `quick`: compiled at XLA's backend optimisation level 0 (a first call's program), "
            "`optimised`: XLA's defaults; `run`: the best of three runs of that program; `Σ q(1)`: the final "
            "configuration's sum (the same physics in both trees).")
    write_record(args.name, record, "The compiled program of a constrained simulation", text,
                 ("case", "jaxbody", "trace", "HLO lines", "kinematics copies", "quick compile", "quick run",
                  "optimised compile", "optimised run", "Σ q(1)"), rows, args.out)


if __name__ == "__main__":
    main()
