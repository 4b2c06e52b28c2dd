"""What does saving a trajectory cost a batched RK4 simulation?

``jax.jit(jax.vmap(...))`` of ``jb.simulate(jb.scene(model, kernel="auto"), q0, v0, T, solver="rk4", dt0=1e-3, ...)``
over ``--batch`` states for ``--steps`` steps, with three ways of saving: the final state only
(``saveat=SaveAt(t1=True)``, as ``throughput.py`` times it), ``n_save=101`` (the default) and
``n_save=1001``. Reports nanoseconds per state and step and each option's time over the
final-state-only time, measured in interleaved rounds (median of ``--rounds``) in one process.

With fixed steps the solve's loop does not stop trajectory by trajectory (``docs/simulation.md``,
"Errors"), so a batched loop need not select everything it carries, the saved trajectories
included, on every step: run this on a commit before that change and after it to see what that
select cost.

Results go to ``benchmarks/results/saving.{md,json}`` (``--out``, ``--name``), stamped with
commit, machine, versions, date and command::

    .venv/bin/python benchmarks/saving.py
    .venv/bin/python benchmarks/saving.py --models double_pendulum --batch 256 --rounds 3 --out /tmp/s
"""

import argparse
import json
import pathlib
import sys
import tempfile
import time
import warnings

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _common  # noqa: E402

SAVES = ("t1", "n_save=101", "n_save=1001")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", default="double_pendulum,panda",
                   help="comma-separated: robots shipped in jaxbody/models, chainN, double_pendulum (= chain2)")
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds (the median is reported)")
    p.add_argument("--min-time", type=float, default=0.3, help="seconds each option is timed for in a round")
    p.add_argument("--out", default=str(pathlib.Path(__file__).resolve().parent / "results"))
    p.add_argument("--name", default="saving")
    args = p.parse_args(argv)
    _common.set_default_xla_flags()
    stamp = _common.stamp(argv)

    import diffrax
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from dynamics import model_path

    shipped = pathlib.Path(jb.__file__).parent / "models"
    dt, steps, B = 1e-3, args.steps, args.batch
    results = {"batch": B, "steps": steps, "models": {}}
    for name in args.models.split(","):
        with warnings.catch_warnings(), tempfile.TemporaryDirectory() as tmp:
            warnings.simplefilter("ignore")
            alias = "chain2" if name == "double_pendulum" else name
            path = shipped / f"{alias}.xml"
            if not path.exists():
                path = model_path(alias, shipped, pathlib.Path(tmp))
            model = jb.from_mjcf(str(path))
        rng = np.random.default_rng(0)
        q0 = jax.vmap(lambda x: jb.normalize_qpos(model, x))(
            jnp.asarray(np.asarray(model.qpos0) + 0.1 * rng.standard_normal((B, model.nq))))
        v0 = jnp.zeros((B, model.nv))
        fns = {}
        for label in SAVES:
            kw = dict(saveat=diffrax.SaveAt(t1=True)) if label == "t1" else dict(n_save=int(label.split("=")[1]))

            def rollout(q, v, kw=kw):
                sol = jb.simulate(jb.scene(model, kernel="auto"), q, v, steps * dt, solver="rk4", dt0=dt, max_steps=steps + 16, **kw)
                return sol.q, sol.v

            f = jax.jit(jax.vmap(rollout))
            t0 = time.perf_counter()
            jax.block_until_ready(f(q0, v0))
            fns[label] = (f, time.perf_counter() - t0)
        samples = {label: [] for label in SAVES}
        for _ in range(args.rounds):
            for label, (f, _) in fns.items():
                t = _common.time_per_call(lambda f=f: jax.block_until_ready(f(q0, v0)), min_time=args.min_time, repeats=3)
                samples[label].append(t["median_s"] / (B * steps))
        per = {label: float(np.median(s)) for label, s in samples.items()}
        results["models"][name] = {
            label: {"ns_per_state_step": 1e9 * per[label], "over_t1": per[label] / per["t1"],
                    "samples_ns": [1e9 * x for x in samples[label]], "compile_s": fns[label][1]}
            for label in SAVES
        }
        print(name, {k: round(1e9 * v, 1) for k, v in per.items()}, flush=True)
    stamp["load_average_end"] = _common.load_average()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps({"stamp": stamp, "results": results}, indent=1))
    rows = [[name, label, f"{r['ns_per_state_step']:.1f}", f"{r['over_t1']:.2f}", f"{r['compile_s']:.1f}"]
            for name, m in results["models"].items() for label, r in m.items()]
    md = [f"# What saving a trajectory costs a batched RK4 simulation", "", _common.stamp_markdown(stamp), "",
          f"`jax.jit(jax.vmap(jb.simulate))`, RK4, dt = {dt}, {steps} steps, batch {B}, float64; "
          f"median of {args.rounds} interleaved rounds.", "",
          _common.markdown_table(["model", "saving", "ns per state-step", "x final state only", "compile s"], rows), ""]
    (out / f"{args.name}.md").write_text("\n".join(md))
    print(f"wrote {out / args.name}.md, .json")


if __name__ == "__main__":
    main()
