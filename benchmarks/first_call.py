"""What a new user waits for: the first model import, simulation and gradient, cold and warm.

    python benchmarks/first_call.py [--name NAME] [--cases C] [--repeats N] [--baseline DIR] [--cassie PATH]
        [--xla-flags FLAGS] [--baseline-xla-flags FLAGS]
    python benchmarks/first_call.py --merge A.json B.json ... [--name NAME]   # one record from several runs

Each case runs in fresh processes, as a user's script would, with jaxbody's defaults (no
kernel or solver named): ``import jaxbody``; the model (``jb.from_mjcf`` or the builder);
the first ``jb.simulate`` of 1 s; then the first ``jax.grad`` of a loss of the final state.
The two phases of a case share one cache directory (``$JAXBODY_CACHE_DIR``, holding the native
kernel's libraries and JAX's persistent compilation cache): **cold**, the first process, with
the directory empty; **warm**, a second process after it. Each worker also records what
compiled (JAX's monitoring events: programs traced and compiled, seconds of XLA compilation,
persistent-cache hits; seconds spent building native libraries), which is the profile to read
where a target is missed; ``--log-compiles`` also keeps each worker's log of every program
traced and compiled, with the reason of each persistent-cache miss. ``--baseline DIR`` times another checkout (e.g. ``git archive`` of an
older commit) in the same run, alternating with this tree (``--trees baseline`` times it alone,
``--baseline-phases cold`` only its empty-cache phase). Runs split over several processes
(each its own ``--name``) are joined by ``--merge``. ``--xla-flags`` sets the workers'
``XLA_FLAGS``, ``--baseline-xla-flags`` the baseline's alone (a copy of this tree as the
baseline then times a flag A/B). Writes ``NAME.json`` and
``NAME.md`` (default ``first_call``) to ``--out`` (default ``benchmarks/results``).

Targets (docs/performance.md, "First calls and compile time"): with an empty cache, import ≤ 1 s, first
simulation ≤ 3 s, first gradient ≤ 10 s; with a warm cache ≤ 1 s each.

Cases: ``panda`` and ``iiwa`` (a 7-DoF arm, ``benchmarks/models/iiwa_like.xml``) under a PD
law whose gains the gradient is taken with respect to; ``disk`` (the rolling disk of Maggi's
paper, ``jaxbody.examples.disk``) and ``four-bar`` (three hinged bodies and a loop closure,
``benchmarks/maggi.py``), whose gradient is with respect to a scale of the initial velocity
(which keeps it admissible); ``cassie`` (a floating base with ball joints and ``<connect>``
loops; only with ``--cassie PATH``, its MJCF).
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import RESULTS, checkouts, load_average, markdown_table, parse_cases, stamp, stamp_markdown  # noqa: E402

CASES = ("panda", "iiwa", "disk", "four-bar", "cassie")
HERE = pathlib.Path(__file__).resolve().parent
TARGETS = {"cold": {"model_s": 1.0, "simulate_s": 3.0, "grad_s": 10.0}, "warm": {"model_s": 1.0, "simulate_s": 1.0, "grad_s": 1.0}}


def _profile(jax):
    """JAX's compile events of this process, summed: {event: [count, seconds]}."""
    events: dict = {}

    def duration(name, secs, **_):
        c = events.setdefault(name, [0, 0.0])
        c[0] += 1
        c[1] += secs

    def event(name, **_):
        events.setdefault(name, [0, 0.0])[0] += 1

    jax.monitoring.register_event_duration_secs_listener(duration)
    jax.monitoring.register_event_listener(event)
    return events


def case_setup(case: str, cassie: str | None = None, times: dict | None = None):
    """``(system, q0, v0, loss, arg)`` of a case (see the module docstring): the model or system
    made, its initial state, and the loss whose gradient at ``arg`` is taken. ``times`` receives
    ``model_s`` (the MJCF import; the Maggi systems' construction) and ``scene_s`` (the scene's)."""
    import jax.numpy as jnp

    import jaxbody as jb

    times = {} if times is None else times
    t = time.perf_counter()
    if case in ("panda", "iiwa", "cassie"):
        path = {"panda": HERE.parent / "jaxbody" / "models" / "panda.xml", "iiwa": HERE / "models" / "iiwa_like.xml"}.get(case, cassie)
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = jb.from_mjcf(str(path))
        times["model_s"] = time.perf_counter() - t
        t = time.perf_counter()
        q0, v0 = model.qpos0 + (0.3 if case != "cassie" else 0.0), jnp.zeros(model.nv)
        if case == "cassie":
            system = jb.scene(model)
            times["scene_s"] = time.perf_counter() - t

            def loss(s):  # with respect to a scale of gravity (any velocity would have to satisfy the loops)
                sc = jb.scene(model, gravity=s * model.gravity)
                return jnp.sum(jb.simulate(sc, q0, v0, 1.0).q[-1] ** 2)

            return system, q0, v0, loss, jnp.asarray(1.0)
        q_ref = model.qpos0

        def pd(t, q, v, gains):
            return gains[0] * (q_ref - q) - gains[1] * v

        gains = jnp.asarray([20.0, 2.0])
        system = jb.scene(model, actuation=(pd, gains))
        times["scene_s"] = time.perf_counter() - t

        def loss(g):
            sc = jb.scene(model, actuation=(pd, g))
            return jnp.sum(jb.simulate(sc, q0, v0, 1.0).q[-1] ** 2)

        return system, q0, v0, loss, gains
    from maggi import disk_state, four_bar

    if case == "disk":
        _, system, q0, v0 = disk_state("rolling")
    else:
        system, q0, v0 = four_bar()
    times["model_s"], times["scene_s"] = time.perf_counter() - t, 0.0

    def loss(s):
        return jnp.sum(jb.simulate(system, q0, s * v0, 1.0).q[-1] ** 2)

    return system, q0, v0, loss, jnp.asarray(1.0)


def _worker(case: str, cassie: str | None) -> dict:
    """One fresh process: import, model, first simulate, first gradient."""
    t = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxbody as jb

    out = {"case": case, "import_s": time.perf_counter() - t, "jaxbody": str(pathlib.Path(jb.__file__).parent)}
    if os.environ.get("FIRST_CALL_LOG_COMPILES"):
        # every program traced and compiled, and why the persistent cache missed, on stderr
        import logging

        logging.basicConfig(level=logging.WARNING, format="%(message)s")
        jax.config.update("jax_log_compiles", True)
        jax.config.update("jax_explain_cache_misses", True)
    events = _profile(jax)
    # the native kernel's C++ builds, timed around the one function that runs the compiler
    build = getattr(getattr(getattr(jb, "backends", None), "native", None), "build", None)
    native_s = [0.0, 0]
    if build is not None and hasattr(build, "build_library"):
        original = build.build_library

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            path = original(*args, **kwargs)
            native_s[0] += time.perf_counter() - t0
            native_s[1] += 1
            return path

        build.build_library = timed

    system, q0, v0, loss, arg = case_setup(case, cassie, out)
    out["scene"] = repr(system) if case in ("panda", "iiwa", "cassie") else type(system).__name__
    stage = {k: list(v) for k, v in events.items()}
    t = time.perf_counter()
    sol = jb.simulate(system, q0, v0, 1.0)
    jax.block_until_ready(sol.q)
    out["simulate_s"] = time.perf_counter() - t
    out["q_final"] = [float(x) for x in sol.q[-1]]
    out["profile_simulate"] = {k: [v[0] - stage.get(k, [0, 0.0])[0], v[1] - stage.get(k, [0, 0.0])[1]] for k, v in events.items()}
    out["native_build_simulate"] = list(native_s)
    stage = {k: list(v) for k, v in events.items()}
    native_before = list(native_s)
    t = time.perf_counter()
    g = jax.grad(loss)(arg)
    jax.block_until_ready(g)
    out["grad_s"] = time.perf_counter() - t
    out["grad"] = [float(x) for x in jnp.atleast_1d(g)]
    out["profile_grad"] = {k: [v[0] - stage.get(k, [0, 0.0])[0], v[1] - stage.get(k, [0, 0.0])[1]] for k, v in events.items()}
    out["native_build_grad"] = [native_s[0] - native_before[0], native_s[1] - native_before[1]]
    return out


def _run(case, cassie, tree_path, cache_dir, phase, log: pathlib.Path | None = None, xla_flags: str | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "JAXBODY_KERNEL", "JAXBODY_JAX_CACHE")}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    env["JAXBODY_CACHE_DIR"] = str(cache_dir)
    if tree_path is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(tree_path), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--worker", case]
    if cassie:
        cmd += ["--cassie", cassie]
    t = time.perf_counter()
    if log is not None:
        env["FIRST_CALL_LOG_COMPILES"] = "1"
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    if log is not None:
        log.write_text(proc.stderr)
    if proc.returncode != 0:
        return {"case": case, "phase": phase, "error": proc.stderr[-2000:], "process_s": time.perf_counter() - t}
    rec = json.loads(proc.stdout.strip().splitlines()[-1])
    rec.update(phase=phase, process_s=time.perf_counter() - t)
    return rec


def _compiles(profile: dict) -> str:
    """``programs compiled / XLA seconds / cache hits`` from a worker's profile."""
    if not profile:
        return "not recorded"
    n, secs = profile.get("/jax/core/compile/backend_compile_duration", [0, 0.0])
    hits = profile.get("/jax/compilation_cache/cache_hits", [0, 0.0])[0]
    return f"{n} / {secs:.1f} s / {hits}"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", default="first_call")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--xla-flags", help="XLA_FLAGS of the workers (default: this process's)")
    p.add_argument("--baseline-xla-flags", help="XLA_FLAGS of the baseline checkout's workers (default: --xla-flags)")
    p.add_argument("--cases", default="panda,iiwa,disk,four-bar", help=f"comma-separated of {CASES}")
    p.add_argument("--cassie", help="MJCF of a Cassie-like model (floating base, ball joints, <connect> loops)")
    p.add_argument("--log-compiles", action="store_true",
                   help="write each worker's log of what it traced and compiled (and why JAX's cache missed) to OUT/NAME_CASE_TREE_PHASE.log")
    p.add_argument("--baseline", type=pathlib.Path, help="another checkout whose jaxbody is timed alongside")
    p.add_argument("--trees", choices=("both", "this", "baseline"), default="both", help="which checkouts to time")
    p.add_argument("--baseline-phases", default="cold,warm", help="phases of the baseline checkout")
    p.add_argument("--merge", nargs="+", type=pathlib.Path, help="records (JSON) of earlier runs to join into one")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(_worker(args.worker, args.cassie)))
        return
    if args.merge:
        records = [json.loads(f.read_text()) for f in args.merge]
        record = dict(records[0], runs=[r for rec in records for r in rec["runs"]])
        record["stamp"] = dict(records[0]["stamp"], merged_from=[dict(rec["stamp"]) for rec in records])
        _write(record, args)
        return
    cases = parse_cases(args.cases, CASES, args.cassie)
    trees, baseline = checkouts(args.baseline)
    if args.trees != "both":
        trees = {k: v for k, v in trees.items() if (v is None) == (args.trees == "this")}
    record = {"stamp": stamp(), "targets": TARGETS, "runs": []}
    if baseline:
        record["baseline"] = baseline
    if args.xla_flags is not None:
        record["stamp"]["xla_flags"] = f"{args.xla_flags} (the workers', --xla-flags)"
    if args.baseline_xla_flags is not None:
        record["stamp"]["xla_flags"] = (f"{record['stamp'].get('xla_flags', '(unset)')}; the baseline's workers: "
                                        f"{args.baseline_xla_flags} (--baseline-xla-flags)")
    args.out.mkdir(parents=True, exist_ok=True)
    for _ in range(args.repeats):
        for case in cases:
            for tree, path in trees.items():
                phases = ("cold", "warm") if path is None else tuple(args.baseline_phases.split(","))
                with tempfile.TemporaryDirectory(prefix="jaxbody-first-call-") as cache:
                    for phase in phases:
                        log = (args.out / f"{args.name}_{case}_{'this' if path is None else 'baseline'}_{phase}.log"
                               if args.log_compiles else None)
                        flags = args.baseline_xla_flags if path is not None and args.baseline_xla_flags is not None \
                            else args.xla_flags
                        rec = dict(_run(case, args.cassie, path, cache, phase, log, flags), tree=tree)
                        record["runs"].append(rec)
                        print({k: v for k, v in rec.items() if not k.startswith("profile") and k not in ("q_final", "grad")}, flush=True)
                        # kept as it goes: a long run stopped early leaves what it measured
                        (args.out / f"{args.name}.json").write_text(json.dumps(record, indent=1))
    record["stamp"]["load_average_end"] = load_average()
    _write(record, args)


def _write(record, args):
    """The record's JSON and Markdown table."""
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(record, indent=1))
    rows = []
    for r in record["runs"]:
        if "error" in r:
            rows.append((r["case"], r["tree"], r["phase"], "failed: " + r["error"].strip().splitlines()[-1][:80], "", "", "", "", "", "", "", ""))
            continue
        tgt = TARGETS[r["phase"]]
        mark = lambda k: f"{r[k]:.2f}" + ("" if r[k] <= tgt[k] else " ✗")  # noqa: E731
        rows.append((r["case"], r["tree"], r["phase"], f"{r['import_s']:.2f}", mark("model_s"),
                     f"{r['scene_s']:.2f}" if "scene_s" in r else "", mark("simulate_s"), mark("grad_s"),
                     _compiles(r["profile_simulate"]), _compiles(r["profile_grad"]),
                     f"{r['native_build_simulate'][0] + r['native_build_grad'][0]:.1f} s ({r['native_build_simulate'][1] + r['native_build_grad'][1]})",
                     f"{r['process_s']:.1f}"))
    md = ["# First results: model import, first simulation and first gradient, empty and warm cache", "",
          stamp_markdown(record["stamp"]), "",
          *([f"Joined from {len(record['stamp']['merged_from'])} runs made side by side (`--merge`); their load "
             "averages at start: " + ", ".join(str(m.get("load_average_start", "?")) for m in record["stamp"]["merged_from"]) + ".", ""]
            if "merged_from" in record["stamp"] else []),
          "Fresh processes with jaxbody's defaults; `cold`: an empty `$JAXBODY_CACHE_DIR`, `warm`: a second process "
          "after it. Seconds; `model`: the MJCF import (the Maggi systems: their construction), `scene`: `jb.scene` on the "
          "imported model (no target); ✗ marks a missed target (cold: model ≤ 1, simulate ≤ 3, gradient ≤ 10; warm: ≤ 1 each). "
          "`compiled`: XLA programs compiled / their XLA compile seconds / persistent-cache hits (JAX's monitoring "
          "events; a hit is a program loaded instead of compiled). `native builds`: seconds in the C++ compiler (libraries "
          "looked up or built), summed over the threads that ran it: a solve's builds run beside each other and beside "
          "its trace, so the sum can exceed the wall time. `process`: the worker process's whole time, start to "
          "exit (its exit waits for the optimised compiles and builds still running in the background).", "",
          markdown_table(["case", "jaxbody", "phase", "import jaxbody", "model", "scene", "first simulate", "first gradient",
                          "compiled (simulate)", "compiled (gradient)", "native builds", "process"], rows), ""]
    (args.out / f"{args.name}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
