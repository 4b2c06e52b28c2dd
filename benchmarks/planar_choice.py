"""Which path the scene builder picks for a planar chain, and what each path costs.

    python benchmarks/planar_choice.py [--name NAME] [--steps N]

The double pendulum (two parallel hinges) as a :class:`jaxbody.Model`, from the horizontal:
``N`` (default 10^4) fixed RK4 steps of ``dt = 1e-4`` keeping the final state, one process,
float64, compile excluded (medians of repeated calls). Rows: the planar absolute-angle path
(``planar=True``), the spatial path with the native and the vectorised kernel
(``planar=False``), and the builder's own choice (``planar=None``, the default kernel): a
specialisation must never be slower than the general path, so the default must be the fastest
row available. Writes ``NAME.json`` and ``NAME.md`` (default ``planar_choice``) to
``benchmarks/results``.
"""

import argparse
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import RESULTS, load_average, markdown_table, set_default_xla_flags, stamp, stamp_markdown, time_per_call  # noqa: E402

DOUBLE_PENDULUM = """<mujoco model="double_pendulum">
  <option gravity="0 0 -9.81"/>
  <worldbody>
    <body name="link1">
      <joint name="hinge1" type="hinge" axis="0 1 0"/>
      <inertial pos="0.5 0 0" mass="1" diaginertia="0.001 0.0843 0.0843"/>
      <body name="link2" pos="1 0 0">
        <joint name="hinge2" type="hinge" axis="0 1 0"/>
        <inertial pos="0.5 0 0" mass="1" diaginertia="0.001 0.0843 0.0843"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""

ROWS = (("planar path", dict(planar=True)), ("spatial, native kernel", dict(planar=False, kernel="native")),
        ("spatial, vectorised kernel", dict(planar=False, kernel="vectorised")), ("builder's choice (defaults)", {}))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", default="planar_choice")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    p.add_argument("--steps", type=int, default=10_000)
    args = p.parse_args(argv)
    set_default_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    import diffrax
    import jax.numpy as jnp

    import jaxbody as jb

    model = jb.from_mjcf(DOUBLE_PENDULUM)
    q0, v0 = jnp.zeros(2), jnp.zeros(2)
    dt = 1e-4
    record = {"stamp": stamp(), "steps": args.steps, "dt": dt, "rows": []}
    for label, kw in ROWS:
        sc = jb.scene(model, **kw)
        run = jax.jit(lambda q0, v0, sc=sc: jb.simulate(sc, q0, v0, args.steps * dt, solver="rk4", dt0=dt,
                                                        saveat=diffrax.SaveAt(t1=True)).q[-1])
        jax.block_until_ready(run(q0, v0))
        t = time_per_call(lambda: jax.block_until_ready(run(q0, v0)), min_time=1.0, repeats=5)
        row = {"row": label, "path": sc.path, "kernel": sc.runs, "seconds": t["median_s"], "q_final": [float(x) for x in run(q0, v0)]}
        record["rows"].append(row)
        print(row, flush=True)
    record["stamp"]["load_average_end"] = load_average()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(record, indent=1))
    rows = [(r["row"], r["path"], r["kernel"], f"{1e3 * r['seconds']:.2f}") for r in record["rows"]]
    md = [f"# The planar specialisation against the spatial path: {args.steps} RK4 steps of the double pendulum", "",
          stamp_markdown(record["stamp"]), "",
          f"Fixed-step RK4, dt = {dt}, {args.steps} steps, final state only, float64, one process; median of "
          "repeated calls after compilation. The builder's choice must be the fastest row available.", "",
          markdown_table(["scene", "path", "kernel", "ms"], rows), ""]
    (args.out / f"{args.name}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
