"""Fixed-step RK4 saving at many times: the one native call against diffrax's loop.

``jb.simulate(scene, q0, v0, T, solver="rk4", dt0=...)`` on the native kernel, the papers'
double pendulum (Example 1) released from the horizontal, float64, saving the state at
``--saves`` evenly spaced times from 0 to ``T`` (each from its step's dense output) or the end
state alone (``saveat=SaveAt(t1=True)``). Each is timed as one native call
(``jaxbody.backends.native.rk4_rollout``) and as diffrax's step-by-step loop
(``$JAXBODY_NATIVE_SOLVE=0``), in one process, compiled beforehand, fastest of several calls:

* one trajectory, the solve;
* one trajectory, the gradient with respect to ``(q0, v0)`` of a loss over every saved state
  (the native reverse sweep ``rk4_rollout_vjp`` against diffrax's checkpointed adjoint);
* a ``vmap`` batch of ``--batch`` trajectories, the solve.

The largest difference between the two paths' saved states is reported beside the times (the
same steps and dense output: rounding). Results go to ``benchmarks/results/rk4_saves.{md,json}``
(``--out``), stamped with commit, machine, versions, date and command::

    .venv/bin/python benchmarks/rk4_saves.py
    .venv/bin/python benchmarks/rk4_saves.py --t1 1 --saves 100 --batch 16 --out /tmp/r
"""

import argparse
import json
import os
import pathlib
import sys
import tempfile

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _common  # noqa: E402

PATHS = {"native": "1", "diffrax loop": "0"}


def best_time(fn, repeats):
    """The fastest of ``repeats`` timed calls after a warm-up (on a shared machine the fastest
    call is the least disturbed one; every case is timed the same way)."""
    return _common.time_per_call(fn, min_time=0.0, repeats=repeats, budget=float("inf"))["min_s"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--t1", type=float, default=10.0, help="end time T (s)")
    p.add_argument("--dt0", type=float, default=1e-3, help="the RK4 step (s)")
    p.add_argument("--saves", type=int, default=1000, help="evenly spaced save times from 0 to T")
    p.add_argument("--batch", type=int, default=256, help="trajectories of the batched solve")
    p.add_argument("--repeats", type=int, default=7, help="timed calls of each case (the fastest is kept)")
    p.add_argument("--out", default=str(pathlib.Path(__file__).resolve().parent / "results"))
    args = p.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import diffrax
    import jax.numpy as jnp

    import jaxbody as jb

    stamp = _common.stamp(argv=None if argv is None else [__file__, *argv])
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "double_pendulum.xml"
        path.write_text(_common.DOUBLE_PENDULUM_MJCF)
        model = jb.from_mjcf(str(path))
    scene = jb.scene(model, kernel="native", planar=False)
    steps = int(round(args.t1 / args.dt0))
    ts = jnp.linspace(0.0, args.t1, args.saves)
    saves = {f"{args.saves} times": diffrax.SaveAt(ts=ts), "end state": diffrax.SaveAt(t1=True)}
    q0, v0 = jnp.array([np.pi / 2, 0.0]), jnp.zeros(2)
    rng = np.random.default_rng(0)
    qs = jnp.asarray(np.asarray(q0) + 1e-3 * rng.standard_normal((args.batch, 2)))
    vs = jnp.zeros((args.batch, 2))

    def solve(saveat):
        def one(q, v):
            sol = jb.simulate(scene, q, v, args.t1, solver="rk4", dt0=args.dt0, saveat=saveat, max_steps=steps)
            return sol.q, sol.v

        def loss(q, v):
            q_saved, v_saved = one(q, v)
            return jnp.sum(jnp.sin(q_saved)) + jnp.sum(v_saved ** 2)

        return {"solve": jax.jit(one), "gradient": jax.jit(jax.grad(loss, argnums=(0, 1))),
                "batch": jax.jit(jax.vmap(one))}

    rows, record = [], {}
    for save, saveat in saves.items():
        results = {}
        for label, flag in PATHS.items():
            # the switch is read when a solve is traced: each path compiles its own programs
            os.environ["JAXBODY_NATIVE_SOLVE"] = flag
            fns = solve(saveat)
            out = {"values": fns["solve"](q0, v0)}
            times = {}
            for case, fn, call_args in (("solve", fns["solve"], (q0, v0)), ("gradient", fns["gradient"], (q0, v0)),
                                        ("batch", fns["batch"], (qs, vs))):
                times[case] = best_time(lambda: jax.block_until_ready(fn(*call_args)),
                                        args.repeats if flag == "1" or case != "batch" else 3)
                print(save, label, case, f"{times[case] * 1e3:.2f} ms", flush=True)
            out["gradient"] = fns["gradient"](q0, v0)
            results[label] = (out, times)
        os.environ["JAXBODY_NATIVE_SOLVE"] = "1"
        (a, ta), (b, tb) = results["native"], results["diffrax loop"]
        difference = max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(a["values"], b["values"]))
        # relative: a chaotic motion's gradients grow with the time span
        gradient_difference = max(float(jnp.max(jnp.abs(x - y)) / jnp.max(jnp.abs(y)))
                                  for x, y in zip(a["gradient"], b["gradient"]))
        record[save] = {"native_s": ta, "diffrax_loop_s": tb, "max_state_difference": difference,
                        "max_relative_gradient_difference": gradient_difference,
                        "ratio": {k: tb[k] / ta[k] for k in ta}}
        for case in ("solve", "gradient", "batch"):
            n = args.batch if case == "batch" else 1
            rows.append([save, case if case != "batch" else f"batch of {args.batch}", f"{ta[case] * 1e3:.2f}",
                         f"{tb[case] * 1e3:.2f}", f"{tb[case] / ta[case]:.1f}",
                         f"{ta[case] / (n * steps) * 1e9:.0f} / {tb[case] / (n * steps) * 1e9:.0f}",
                         f"{difference:.1e}" if case != "gradient" else f"{gradient_difference:.1e}"])
    stamp["load_average_end"] = _common.load_average()
    out_dir = pathlib.Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    settings = {"t1": args.t1, "dt0": args.dt0, "steps": steps, "saves": args.saves, "batch": args.batch,
                "repeats": args.repeats}
    (out_dir / "rk4_saves.json").write_text(json.dumps({"stamp": stamp, "settings": settings, "results": record},
                                                        indent=1))
    md = ["# Fixed-step RK4 saving at many times: one native call against diffrax's loop", "",
          _common.stamp_markdown(stamp), "",
          f"The papers' double pendulum (Example 1) from the horizontal, float64, {args.t1:g} s in RK4 steps of "
          f"{args.dt0:g} s ({steps} steps) on the native kernel, saving {args.saves} evenly spaced times from each "
          "step's dense output, or the end state alone. Wall time of a compiled call, fastest of several, of the "
          "one native call (`rk4_rollout`; the gradient by its reverse sweep `rk4_rollout_vjp`) and of diffrax's "
          "loop (`JAXBODY_NATIVE_SOLVE=0`; the gradient by its checkpointed adjoint), measured in one process. "
          "Gradient: with respect to (q0, v0) of a loss over every saved state. Difference: the largest between "
          "the two paths' saved states (for the gradient: relative to its largest entry); the same steps and dense "
          "output, so rounding, which the chaotic motion amplifies over the run.", "",
          _common.markdown_table(["saves", "case", "native ms", "diffrax loop ms", "loop / native",
                                  "ns per step (native / loop)", "difference"], rows), ""]
    (out_dir / "rk4_saves.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
