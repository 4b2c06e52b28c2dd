"""Forward against reverse mode for a gradient of a simulation with respect to a few scalars:
what the first gradient waits for and what a later one runs, as the number of scalars grows.

    python benchmarks/forward_derivative.py [--name NAME] [--sizes 1,2,4,8,14] [--calls N]

jaxbody's program store takes the derivative of a solve in forward mode when at most
``jaxbody.program_store.FORWARD_MAX_INPUTS`` input scalars are differentiated (one stored
program of the outputs and their Jacobians) and in reverse mode otherwise (a stored reverse
program). This times both on the same losses, each in a fresh process with an empty cache and
jaxbody's defaults otherwise, the threshold set so that one mode serves throughout:

* ``arm k``: the 7-DoF iiwa-like arm of ``benchmarks/first_call.py`` under a PD law whose 14
  gains are drawn from ``k`` parameters (gain ``j`` of the stiffness reads parameter
  ``j mod k``, of the damping ``(j + 7) mod k``), the loss the squared final state of a 1 s
  simulation, its gradient with respect to the ``k`` parameters;
* ``disk``: the rolling disk's loss of ``benchmarks/first_call.py`` (a scale of the initial
  velocity: the solve sees the 5 velocities differentiated).

Columns: the first ``jax.grad`` (tracing, compiling and running), and the median of ``--calls``
later ones (the run alone, once the optimised programs compiled in the background replaced
the quick first ones), in each mode. Writes ``NAME.json`` and ``NAME.md`` (default
``forward_derivative``) to ``benchmarks/results``.
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
from _common import RESULTS, load_average, stamp, write_record  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent

# the record's columns and the paragraph above its table
COLUMNS = ["case", "k", "first forward (s)", "first reverse (s)", "later forward (ms)", "later reverse (ms)", "ratio",
           "agree"]
LEGEND = ("Fresh processes, empty caches, jaxbody's defaults except the threshold of forward mode, set so that one mode "
          "serves throughout. First gradient in seconds (trace, compile, run); later gradients: the median of {calls}, "
          "in milliseconds; `ratio`: forward / reverse of the later ones; `agree`: the largest relative difference of "
          "the two gradients.")


def _loss(case: str, size: int):
    """``(loss, argument)`` of a case (see the module docstring)."""
    import jax.numpy as jnp

    import jaxbody as jb
    from first_call import case_setup

    if case == "disk":
        _, _, _, loss, arg = case_setup("disk")
        return loss, arg
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mjcf(str(HERE / "models" / "iiwa_like.xml"))
    q_ref, q0, v0 = model.qpos0, model.qpos0 + 0.3, jnp.zeros(model.nv)
    stiffness = jnp.arange(model.nv) % size
    damping = (jnp.arange(model.nv) + model.nv) % size

    def pd(t, q, v, p):
        return 20.0 * p[stiffness] * (q_ref - q) - 2.0 * p[damping] * v

    def loss(p):
        sol = jb.simulate(jb.scene(model, actuation=(pd, p)), q0, v0, 1.0)
        return jnp.sum(sol.q[-1] ** 2) + jnp.sum(sol.v[-1] ** 2)

    return loss, jnp.ones(size)


def _worker(case: str, size: int, mode: str, calls: int) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxbody import program_store

    # the threshold set so that the one mode serves every derivative of this process
    program_store.FORWARD_MAX_INPUTS = 10**6 if mode == "forward" else 0
    loss, arg = _loss(case, size)

    def timed():
        t = time.perf_counter()
        g = jax.block_until_ready(jax.grad(loss)(arg))
        return time.perf_counter() - t, g

    first, grad = timed()
    program_store.wait()  # the optimised programs, compiled in the background, run the later calls
    timed()
    later = statistics.median(timed()[0] for _ in range(calls))
    return {"case": case, "size": size, "mode": mode, "first_grad_s": first, "grad_s": later,
            "grad": [float(x) for x in jax.numpy.atleast_1d(grad)], "counts": program_store.counts()}


def _run(case: str, size: int, mode: str, calls: int) -> dict:
    # jaxbody's defaults: the program store on (it takes the derivatives this compares)
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAX_COMPILATION_CACHE_DIR", "JAXBODY_KERNEL", "JAXBODY_JAX_CACHE", "JAXBODY_PROGRAM_STORE")}
    with tempfile.TemporaryDirectory(prefix="jaxbody-forward-") as cache:
        env["JAXBODY_CACHE_DIR"] = cache
        cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--worker", case, "--size", str(size), "--mode", mode,
               "--calls", str(calls)]
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    if proc.returncode != 0:
        raise SystemExit(f"{case} k={size} ({mode}) failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", default="forward_derivative")
    p.add_argument("--sizes", default="1,2,4,8,14", help="numbers of parameters of the arm's law")
    p.add_argument("--calls", type=int, default=5, help="later gradients timed (their median)")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS, help="where the record is written")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    p.add_argument("--size", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--mode", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(_worker(args.worker, args.size, args.mode, args.calls)))
        return
    record = {"stamp": stamp(), "calls": args.calls, "runs": []}
    cases = [("arm", int(k)) for k in args.sizes.split(",") if k] + [("disk", 5)]
    for case, size in cases:
        for mode in ("forward", "reverse"):  # alternating: the two modes see the same load
            record["runs"].append(_run(case, size, mode, args.calls))
            print(record["runs"][-1], flush=True)
    record["stamp"]["load_average_end"] = load_average()
    by = {(r["case"], r["size"], r["mode"]): r for r in record["runs"]}
    rows = []
    for case, size in cases:
        f, r = by[(case, size, "forward")], by[(case, size, "reverse")]
        agree = max(abs(a - b) / max(abs(b), 1e-300) for a, b in zip(f["grad"], r["grad"]))
        rows.append((case, size, f"{f['first_grad_s']:.2f}", f"{r['first_grad_s']:.2f}", f"{1e3 * f['grad_s']:.1f}",
                     f"{1e3 * r['grad_s']:.1f}", f"{f['grad_s'] / r['grad_s']:.2f}", f"{agree:.1e}"))
    print(write_record(args.name, record, "Forward against reverse mode: a gradient with respect to k scalars",
                       LEGEND.format(calls=args.calls), COLUMNS, rows, args.out))


if __name__ == "__main__":
    main()
