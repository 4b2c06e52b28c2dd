"""What the first call of a constrained simulation costs: tracing, lowering, XLA's compile.

    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python benchmarks/first_call.py [--name NAME] [--repeats N] [--cases C]

Each case is one ``jax.jit`` of a ``jb.simulate`` (adaptive Tsit5, 1 s, five saved times),
split with JAX's ahead-of-time stages: ``.trace`` (Python runs jaxbody and diffrax and records
the program), ``.lower`` (to StableHLO), ``.compile`` (XLA), and the size of the traced program
(its equations, counting a nested function's once per call, as XLA inlines them). Every repeat runs in a fresh
process, so no trace or compile cache is shared between repeats; medians are reported.
Writes ``NAME.json`` and ``NAME.md`` (default ``first_call``) to ``--out`` (default
``benchmarks/results``). ``--baseline DIR`` also times jaxbody from another checkout (``DIR``,
e.g. a ``git worktree`` of an older commit) in the same run, its workers alternating with this
tree's, so that a drift of the machine's speed hits both alike.

Cases: the four-bar linkage (three hinged bodies, a loop closure; ``benchmarks/maggi.py``),
the same linkage driven by a prescribed crank angle, and the rolling disk of Maggi's paper
(``jaxbody.examples.disk``).
"""

import argparse
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import RESULTS, alternate, checkouts, count_eqns, load_average, markdown_table, stamp, stamp_markdown  # noqa: E402

CASES = ("four-bar", "driven four-bar", "rolling disk")


def _one(case: str) -> dict:
    """Time the three stages of one case in this process (a fresh one)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxbody as jb
    from jaxbody import constraints as jc
    from jaxbody import maggi
    from maggi import disk_states, four_bar

    if case == "rolling disk":
        _, system, q0, v0 = disk_states()[2]
    else:
        system, q0, v0 = four_bar()
        if case == "driven four-bar":
            model = system.base.model
            drive = jc.PrescribedCoordinate(model, "crank_hinge0", lambda t, p: q0[0] + 2.0 * t)
            system = maggi.constrain(system, [drive], q_ref=q0)

    def run(q0, v0):
        sol = jb.simulate(system, q0, v0, 1.0, rtol=1e-10, atol=1e-10, n_save=5)
        return sol.q[-1], sol.v[-1]

    q0, v0 = jnp.asarray(q0), jnp.asarray(v0)
    t0 = time.perf_counter()
    traced = jax.jit(run).trace(q0, v0)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    compiled = lowered.compile()
    t3 = time.perf_counter()
    q1, _ = compiled(q0, v0)
    jax.block_until_ready(q1)
    return dict(case=case, trace_s=t1 - t0, lower_s=t2 - t1, compile_s=t3 - t2, q_final=[float(x) for x in q1],
                eqns=count_eqns(jax, traced.jaxpr.jaxpr), jaxbody=str(pathlib.Path(jb.__file__).parent))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", default="first_call")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--cases", default=",".join(CASES), help=f"comma-separated of {CASES}")
    p.add_argument("--baseline", type=pathlib.Path, help="another checkout whose jaxbody is timed alongside")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(_one(args.worker)))
        return
    record = {"stamp": stamp(), "runs": []}
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    for case in cases:
        if case not in CASES:
            raise SystemExit(f"unknown case {case!r}: one of {CASES}")
    trees, baseline = checkouts(args.baseline)
    if baseline:
        record["baseline"] = baseline
    record["runs"] = alternate(__file__, cases, trees, args.repeats)
    import numpy as np

    rows = []
    for case in cases:
        for tree in trees:
            runs = [r for r in record["runs"] if r["case"] == case and r["tree"] == tree]
            med = {k: float(np.median([r[k] for r in runs])) for k in ("trace_s", "lower_s", "compile_s")}
            rows.append((case, tree, runs[0]["eqns"], f"{med['trace_s']:.2f}", f"{med['lower_s']:.2f}",
                         f"{med['compile_s']:.2f}", f"{sum(med.values()):.2f}", len(runs)))
    record["stamp"]["load_average_end"] = load_average()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(record, indent=1))
    md = ["# First call of a constrained simulation: trace, lower, compile", "", stamp_markdown(record["stamp"]), "",
          "One `jax.jit` of `jb.simulate` (Tsit5, rtol = atol = 1e-10, 1 s, five saved times), each repeat in a fresh "
          "process; medians in seconds.", "",
          markdown_table(["case", "jaxbody", "traced equations", "trace", "lower", "XLA compile", "total", "repeats"], rows), "",
          "Traced equations: every equation of the traced program, those of nested functions once per call.", ""]
    (args.out / f"{args.name}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
