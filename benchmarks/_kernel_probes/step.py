"""How much of a batched RK4 step is the generated step itself, in float64 and float32?

For each model and batch this times, per state and step:

* ``kernel``: a jitted ``lax.fori_loop`` of ``jaxbody.backends.native.rk4_step`` over the batch (one
  native call per step and nothing else: the generated program, the FFI call, the thread pool);
* ``simulate``: ``jb.simulate(jb.scene(model, kernel="auto"), ..., solver="rk4")`` vmapped
  over the same batch, the model a traced argument as in ``throughput.py`` (the same step plus
  diffrax's loop, its bookkeeping on the batch and the saved state);
* ``energy``: the scene's total energy at one state, vmapped over the batch (what
  ``jb.simulate`` evaluates at each saved time; per state, not per step),

in float64 and float32 in one process (x64 on; the float32 model's state and step are float32,
diffrax's time is float64), and the float32/float64 ratio of each: the kernel's ratio is what
the precision buys, the gap to the simulate ratio is the part of the step that does not shrink
with it.

    .venv/bin/python benchmarks/kernels.py step [--models panda,anymal_c] [--batches 1024,8192] [--rounds 3]

Models: the robots shipped in ``jaxbody/models``, ``chainN`` (N hinge links, as in
``benchmarks/dynamics.py``) or ``double_pendulum`` (= ``chain2``).

Writes ``benchmarks/results/step_kernel.{md,json}``.
"""

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common, dynamics
from _common import RESULTS, load_average, markdown_table, stamp, stamp_markdown, time_per_call  # noqa: E402
from _common import set_default_xla_flags  # noqa: E402

STEPS = 50
DT = 1e-3


def main(argv=None):
    p = argparse.ArgumentParser(prog="kernels.py step", description=__doc__.splitlines()[0])
    p.add_argument("--models", default="panda,anymal_c", help="robots shipped in jaxbody/models, chainN, double_pendulum")
    p.add_argument("--batches", default="1024,8192")
    p.add_argument("--min-time", type=float, default=0.5)
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds of both precisions; medians reported")
    p.add_argument("--out", default=str(RESULTS))
    p.add_argument("--name", default="step_kernel")
    args = p.parse_args(argv)
    set_default_xla_flags()  # before JAX starts: the CPU fusion flag on jaxlib 0.10
    rec = {"stamp": stamp(), "steps": STEPS, "rows": []}

    import pathlib
    import warnings

    import jax

    jax.config.update("jax_enable_x64", True)
    import diffrax
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody.backends import native

    rec["native_threads"] = native.threads()
    rec["native_spin_ns"] = int(os.environ.get("JAXBODY_NATIVE_SPIN_NS", native.SPIN_NS))

    import tempfile

    from dynamics import MENAGERIE, model_path

    shipped = pathlib.Path(jb.__file__).parent / "models"
    chains = pathlib.Path(tempfile.mkdtemp())
    for name in args.models.split(","):
        name = "chain2" if name == "double_pendulum" else name
        path = shipped / f"{name}.xml" if name in MENAGERIE else model_path(name, shipped, chains)
        for batch in (int(b) for b in args.batches.split(",")):
            fns = {}
            for dtype in (jnp.float64, jnp.float32):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    model = jb.from_mjcf(str(path), dtype=dtype)
                rng = np.random.default_rng(0)
                q = jax.vmap(lambda x, model=model: jb.normalize_qpos(model, x))(
                    jnp.asarray(np.asarray(model.qpos0) + 0.3 * rng.standard_normal((batch, model.nq)), dtype))
                v = jnp.asarray(rng.standard_normal((batch, model.nv)), dtype)
                scene = jb.scene(model, kernel="native")
                effects = {type(e).__name__: e for e in scene.effects}
                passive = {}
                if "JointSprings" in effects:
                    passive.update(stiffness=effects["JointSprings"].stiffness, reference=effects["JointSprings"].reference)
                if "JointDampers" in effects:
                    passive.update(damping=effects["JointDampers"].damping)
                gravity = jnp.asarray(model.gravity, dtype)

                def kernel_loop(q, v, model=model, gravity=gravity, passive=passive):
                    def body(i, s):
                        q1, v1 = native.rk4_step(model, s[0], s[1], DT, gravity=gravity, **passive)[:2]
                        return jb.normalize_qpos(model, q1), v1

                    return jax.lax.fori_loop(0, STEPS, body, (q, v))

                def rollout(model, q0, v0):
                    sol = jb.simulate(jb.scene(model, kernel="auto"), q0, v0, STEPS * DT, solver="rk4", dt0=DT,
                                      saveat=diffrax.SaveAt(t1=True), max_steps=STEPS + 8)
                    return sol.q[-1], sol.v[-1]

                def energy(model, q, v):
                    return jb.scene(model, kernel="auto").total_energy(q, v)

                for piece, (f, a) in {
                    "kernel": (jax.jit(jax.vmap(kernel_loop)), (q, v)),
                    "simulate": (jax.jit(jax.vmap(rollout, in_axes=(None, 0, 0))), (model, q, v)),
                    "energy": (jax.jit(jax.vmap(energy, in_axes=(None, 0, 0))), (model, q, v)),
                }.items():
                    jax.block_until_ready(f(*a))
                    fns[(piece, dtype.__name__)] = (f, a)
            # the two precisions of each piece one after the other, round after round: this
            # machine's speed drifts by more than the ratios' margins between separate runs
            rounds = []
            for _ in range(args.rounds):
                per = {}
                for (piece, dtype), (f, a) in fns.items():
                    t = time_per_call(lambda f=f, a=a: jax.block_until_ready(f(*a)), min_time=args.min_time)["median_s"]
                    per[(piece, dtype)] = 1e9 * t / (batch * (1 if piece == "energy" else STEPS))
                rounds.append(per)
                print(f"{name:9s} B={batch:6d} " + " ".join(
                    f"{p}: {per[(p, 'float64')]:.1f}/{per[(p, 'float32')]:.1f} ns" for p in ("kernel", "simulate", "energy")),
                    flush=True)
            for piece in ("kernel", "simulate", "energy"):
                ratios = [r[(piece, "float64")] / r[(piece, "float32")] for r in rounds]
                rec["rows"].append({"model": name, "batch": batch, "piece": piece,
                                    "float64_ns": float(np.median([r[(piece, "float64")] for r in rounds])),
                                    "float32_ns": float(np.median([r[(piece, "float32")] for r in rounds])),
                                    "ratio": float(np.median(ratios)), "round_ratios": ratios})

    rec["stamp"]["load_average_end"] = load_average()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps(rec, indent=1))
    rows = [(r["model"], r["batch"], r["piece"], f"{r['float64_ns']:.1f}", f"{r['float32_ns']:.1f}", f"{r['ratio']:.2f}",
             " ".join(f"{x:.2f}" for x in r["round_ratios"])) for r in rec["rows"]]
    md = [
        "# The generated RK4 step alone and inside jb.simulate, float64 and float32",
        "",
        stamp_markdown(rec["stamp"]),
        "",
        f"Nanoseconds per state and step, {STEPS} steps per call, dt = {DT}. `kernel`: a jitted "
        "`lax.fori_loop` of `jaxbody.backends.native.rk4_step` over the batch. `simulate`: `jb.simulate` "
        "(RK4, the model a traced argument) vmapped over the batch. `energy`: one evaluation of the "
        "scene's total energy per state (nanoseconds per state, not per step), which `jb.simulate` "
        "evaluates at every saved time (here once, at t1). Both precisions of each piece are timed "
        f"one after the other in each of {args.rounds} rounds; medians over the rounds. Speed-up: float64 "
        "time / float32 time (median of the rounds' ratios). "
        f"Native thread pool: {rec['native_threads']} threads, spinning {rec['native_spin_ns']} ns "
        "between calls (`$JAXBODY_NATIVE_THREADS`, `$JAXBODY_NATIVE_SPIN_NS`).",
        "",
        markdown_table(["model", "batch", "piece", "float64 ns", "float32 ns", "float32 speed-up", "per round"], rows),
        "",
    ]
    (out / f"{args.name}.md").write_text("\n".join(md))


if __name__ == "__main__":
    main()
