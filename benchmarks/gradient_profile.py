"""Where does the time of a rollout gradient go? One forward-dynamics evaluation and its
derivatives, per kernel, for a single state (issue 7, T3).

A checkpointed gradient of an RK4 rollout evaluates, per stage, the forward dynamics once more
(recomputation) and its linearisation and transpose (the vector-Jacobian product). This times
each piece on one state of the Panda arm, jitted, for the native kernel (whose derivatives with
respect to the state are its generated forward- and reverse-mode programs) and the vectorised
kernel:

    .venv/bin/python benchmarks/gradient_profile.py [--model panda] [--min-time 0.5]

Writes ``benchmarks/results/gradient_profile.{md,json}``.
"""

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
from _common import RESULTS, load_average, markdown_table, stamp, stamp_markdown, time_per_call  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="panda", help="a robot shipped in jaxbody/models")
    p.add_argument("--kernels", default="native,vectorised")
    p.add_argument("--min-time", type=float, default=0.5)
    p.add_argument("--out", default=str(RESULTS))
    p.add_argument("--name", default="gradient_profile")
    args = p.parse_args(argv)
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    rec = {"stamp": stamp(), "model": args.model, "rows": []}

    import pathlib
    import warnings

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody import kernels

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mjcf(str(pathlib.Path(jb.__file__).parent / "models" / f"{args.model}.xml"))
    rng = np.random.default_rng(0)
    q = jb.normalize_qpos(model, jnp.asarray(np.asarray(model.qpos0) + 0.3 * rng.standard_normal(model.nq)))
    v = jnp.asarray(rng.standard_normal(model.nv))
    tau = jnp.asarray(rng.standard_normal(model.nv))
    w = jnp.asarray(rng.standard_normal(model.nv))

    for kernel in args.kernels.split(","):
        def fd(q, v, kernel=kernel):
            return kernels.acceleration(model, q, v, tau, gravity=model.gravity, kernel=kernel)

        pieces = {
            "forward": jax.jit(fd),
            "jvp (value and tangent)": jax.jit(lambda q, v, dq, dv: jax.jvp(fd, (q, v), (dq, dv))),
            "vjp (value and cotangent)": jax.jit(lambda q, v, w: jax.vjp(fd, q, v)[1](w)),
        }
        calls = {
            "forward": lambda f: f(q, v),
            "jvp (value and tangent)": lambda f: f(q, v, q, v),
            "vjp (value and cotangent)": lambda f: f(q, v, w),
        }
        base = None
        for name, f in pieces.items():
            run = lambda f=f, name=name: jax.block_until_ready(calls[name](f))  # noqa: E731
            t = time_per_call(run, min_time=args.min_time)["median_s"]
            base = t if name == "forward" else base
            rec["rows"].append({"kernel": kernel, "piece": name, "us": 1e6 * t, "ratio": t / base})
            print(f"{kernel:10s} {name:28s} {1e6 * t:9.2f} us  {t / base:6.1f}x", flush=True)

    rec["stamp"]["load_average_end"] = load_average()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps(rec, indent=1))
    rows = [(r["kernel"], r["piece"], f"{r['us']:.2f}", f"{r['ratio']:.1f}") for r in rec["rows"]]
    md = [
        "# One forward-dynamics evaluation and its derivatives, single state",
        "",
        stamp_markdown(rec["stamp"]),
        "",
        f"Model `{args.model}`, float64, jitted, one state; median of warm calls (dispatch included). "
        "The native kernel's jvp/vjp rows are a native evaluation (the value) plus its generated "
        "forward-mode (jvp) or reverse-mode (vjp) program, which runs the forward program again.",
        "",
        markdown_table(["kernel", "piece", "µs", "× forward of that kernel"], rows),
        "",
    ]
    (out / f"{args.name}.md").write_text("\n".join(md))


if __name__ == "__main__":
    main()
