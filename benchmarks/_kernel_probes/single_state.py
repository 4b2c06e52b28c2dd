"""What does the native kernel's scalar one-state build buy over vector lanes for single states?

The native kernel builds each generated program twice: for batches in the widest vector lanes
the processor has, and for a single state in scalar code. Before the scalar build, single states
ran the program in 256-bit lanes (one lane used). This times, per step of a 1000-step rollout of
one state (float64, dt = 1e-3), the two ways of running a single state, compiled in one process
and timed in interleaved pairs:

* ``step``: a jitted ``lax.fori_loop`` of ``jaxbody.backends.native.rk4_step`` (the generated RK4 step);
* ``step_vjp``: the same loop through ``jax.vjp`` of the step (its generated reverse-mode
  program; the value is unused);
* ``simulate``: ``jb.simulate(jb.scene(model, kernel="native"), ..., solver="rk4")`` with
  ``SaveAt(t1=True)``, and ``gradient``: ``jax.grad`` of a loss on its final state (the default
  checkpointed adjoint), the rollout gradient of ``gradients.py``.

``256-bit``: the same source built with 256-bit lanes (what single states ran before);
``scalar``: the build single states run now. Ratio: 256-bit time / scalar time (above 1: the
scalar build is faster).

    .venv/bin/python benchmarks/kernels.py single-state [--models panda,chain20,anymal_c] [--pairs 5]

Writes ``benchmarks/results/single_state_builds.{md,json}``.
"""

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common, dynamics
from _common import RESULTS, load_average, markdown_table, stamp, stamp_markdown, time_per_call  # noqa: E402
from _common import set_default_xla_flags  # noqa: E402

STEPS = 1000
DT = 1e-3
PIECES = ("step", "step_vjp", "simulate", "gradient")


def main(argv=None):
    p = argparse.ArgumentParser(prog="kernels.py single-state", description=__doc__.splitlines()[0])
    p.add_argument("--models", default="panda,chain20,anymal_c", help="robots shipped in jaxbody/models, or chainN")
    p.add_argument("--pairs", type=int, default=5, help="interleaved timing pairs per piece")
    p.add_argument("--min-time", type=float, default=0.4)
    p.add_argument("--out", default=str(RESULTS))
    p.add_argument("--name", default="single_state_builds")
    args = p.parse_args(argv)
    set_default_xla_flags()  # before JAX starts: the CPU fusion flag on jaxlib 0.10
    rec = {"stamp": stamp(), "steps": STEPS, "rows": []}

    import pathlib
    import tempfile
    import warnings

    import jax

    jax.config.update("jax_enable_x64", True)
    import diffrax
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody.backends import native

    from dynamics import model_path

    address = native.build.Kernel.address  # picks the scalar build for one state

    def lanes_256(self, build):
        return address(self, "narrow")  # 256-bit lanes: how single states ran before

    for name in args.models.split(","):
        with warnings.catch_warnings(), tempfile.TemporaryDirectory() as tmp:
            warnings.simplefilter("ignore")
            model = jb.from_mjcf(str(model_path(name, pathlib.Path(jb.__file__).parent / "models", pathlib.Path(tmp))))
        rng = np.random.default_rng(0)
        q = jb.normalize_qpos(model, jnp.asarray(np.asarray(model.qpos0) + 0.3 * rng.standard_normal(model.nq)))
        v = jnp.asarray(rng.standard_normal(model.nv))
        tau = jnp.asarray(rng.standard_normal(model.nv))
        scene = jb.scene(model, kernel="native")

        def compiled():
            # compiled ahead of time: the executables keep the build they were traced with
            def step(q, v):
                return native.rk4_step(model, q, v, DT, tau, gravity=model.gravity)[:2]

            def vjp_body(i, c):
                _, pullback = jax.vjp(step, c[0], c[1])
                dq, dv = pullback((c[0], c[1]))
                return c[0] + 1e-9 * dq, c[1] + 1e-9 * dv

            def loss(q0, v0):
                sol = jb.simulate(scene, q0, v0, STEPS * DT, solver="rk4", dt0=DT, saveat=diffrax.SaveAt(t1=True),
                                  max_steps=STEPS + 16)
                return jnp.sum(sol.q[-1] ** 2) + jnp.sum(sol.v[-1] ** 2)

            fns = {
                "step": lambda q, v: jax.lax.fori_loop(0, STEPS, lambda i, c: step(*c), (q, v)),
                "step_vjp": lambda q, v: jax.lax.fori_loop(0, STEPS, vjp_body, (q, v)),
                "simulate": loss,
                "gradient": jax.grad(loss, argnums=(0, 1)),
            }
            return {k: jax.jit(f).lower(q, v).compile() for k, f in fns.items()}

        jax.clear_caches()
        native.build.Kernel.address = lanes_256
        try:
            before = compiled()
        finally:
            native.build.Kernel.address = address
        jax.clear_caches()
        now = compiled()
        for piece in PIECES:
            times = {"256": [], "scalar": []}
            for _ in range(args.pairs):
                for key, fns in (("256", before), ("scalar", now)):
                    f = fns[piece]
                    t = time_per_call(lambda f=f: jax.block_until_ready(f(q, v)), min_time=args.min_time)["median_s"]
                    times[key].append(1e6 * t / STEPS)
            a, b = float(np.median(times["256"])), float(np.median(times["scalar"]))
            row = {"model": name, "piece": piece, "us_256": a, "us_scalar": b, "ratio": a / b,
                   "pair_ratios": [x / y for x, y in zip(times["256"], times["scalar"])]}
            rec["rows"].append(row)
            print(f"{name:9s} {piece:9s} 256-bit {a:8.2f}  scalar {b:8.2f} us/step  ratio {a / b:5.2f}", flush=True)

    rec["stamp"]["load_average_end"] = load_average()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps(rec, indent=1))
    rows = [(r["model"], r["piece"], f"{r['us_256']:.2f}", f"{r['us_scalar']:.2f}", f"{r['ratio']:.2f}",
             " ".join(f"{x:.2f}" for x in r["pair_ratios"])) for r in rec["rows"]]
    md = [
        "# Single states: 256-bit lanes against the scalar one-state build",
        "",
        stamp_markdown(rec["stamp"]),
        "",
        f"Microseconds per step of a {STEPS}-step rollout of one state, float64, dt = {DT}; medians of "
        f"{args.pairs} interleaved pairs. `step`: a jitted `lax.fori_loop` of `jaxbody.backends.native.rk4_step`; "
        "`step_vjp`: the same through `jax.vjp` (the step's reverse-mode program); `simulate`: "
        "`jb.simulate` (RK4, `SaveAt(t1=True)`, native kernel); `gradient`: `jax.grad` of a loss on its "
        "final state (checkpointed adjoint). `256-bit`: the generated source built with 256-bit lanes "
        "(one lane used: how single states ran before); `scalar`: the one-state build. Ratio: 256-bit / "
        "scalar.",
        "",
        markdown_table(["model", "piece", "256-bit µs", "scalar µs", "ratio", "pair ratios"], rows),
        "",
    ]
    (out / f"{args.name}.md").write_text("\n".join(md))


if __name__ == "__main__":
    main()
