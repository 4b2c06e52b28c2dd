"""A robot with loops as imported: the Cassie-like biped (``jaxbody/models/cassie_like.xml``,
floating base, ball joints, four ``<connect>`` loops, joint springs), in a fresh process.

    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python benchmarks/loops.py

Measures: ``jb.from_mjcf`` (import, the loops' directions included), ``jb.scene`` (the loops
checked and partitioned), the first ``jb.simulate`` of 1 s from the ``home`` keyframe (compile
and run), the same simulation again (after compilation), one evaluation of the constrained
vector field against the same scene without its loops (``constraints=None``), and the vector
field's XLA compile and evaluation with the loops' rate term in closed form against the same
term differentiated in forward mode. Writes
``benchmarks/results/loops.json`` and ``loops.md``.
"""

import argparse
import json
import pathlib
import subprocess
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import RESULTS, load_average, markdown_table, stamp, stamp_markdown, time_per_call  # noqa: E402

MODEL = pathlib.Path(__file__).resolve().parents[1] / "jaxbody" / "models" / "cassie_like.xml"

# A planar four-bar closed by a <connect> (crank, coupler, rocker; qpos = 0 closes it)
FOUR_BAR = """<mujoco><option gravity="0 0 -9.81"><flag contact="disable"/></option><worldbody>
  <body name="crank" euler="0 -0.6 0"><joint type="hinge" axis="0 -1 0"/>
    <inertial pos="0.2 0 0" mass="0.5" diaginertia="0.0007 0.007 0.007"/>
    <body name="coupler" pos="0.4 0 0" euler="0 0.7 0"><joint type="hinge" axis="0 -1 0"/>
      <inertial pos="0.5 0 0" mass="1.2" diaginertia="0.01 0.1 0.1"/></body></body>
  <body name="rocker" pos="1 0 0"><joint type="hinge" axis="0 -1 0"/>
    <inertial pos="0.35 0 0" mass="0.9" diaginertia="0.004 0.04 0.04"/></body>
  </worldbody><equality><connect body1="coupler" body2="rocker" anchor="1 0 0"/></equality></mujoco>"""


def field_ratio(repeats: int = 5) -> dict:
    """µs per evaluation of the constrained vector field of the imported four-bar and of the
    same scene without its loop, interleaved ``repeats`` times (medians)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxbody as jb

    model = jb.from_mjcf(FOUR_BAR)
    q = model.qpos0
    v = jnp.zeros(model.nv)
    fs = {}
    for name, sc in (("constrained", jb.scene(model)), ("open", jb.scene(model, constraints=None, planar=False))):
        f = jax.jit(lambda q, v, sc=sc: sc.evaluate(0.0, q, v)[0])
        f(q, v).block_until_ready()
        fs[name] = f
    samples = {name: [] for name in fs}
    for _ in range(repeats):
        for name, f in fs.items():
            samples[name].append(1e6 * time_per_call(lambda f=f: f(q, v).block_until_ready())["median_s"])
    med = {name: sorted(x)[len(x) // 2] for name, x in samples.items()}
    return {"four_bar_constrained_us": med["constrained"], "four_bar_open_us": med["open"],
            "four_bar_ratio": med["constrained"] / med["open"]}


def child(t1: float) -> dict:
    """The measurements, in this (fresh) process."""
    import warnings

    t = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxbody as jb

    out = {"import_jaxbody_s": time.perf_counter() - t}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # contacts and motors are reported as not modelled
        t = time.perf_counter()
        model = jb.from_mjcf(str(MODEL))
        out["from_mjcf_s"] = time.perf_counter() - t
    t = time.perf_counter()
    scene = jb.scene(model)
    out["scene_s"] = time.perf_counter() - t
    out["constraint_rows"] = scene.constraints.n_constraint
    q0, v0 = model.keyframe("home")

    def run():
        sol = jb.simulate(scene, q0, v0, t1, n_save=11)
        sol.q.block_until_ready()
        return sol

    t = time.perf_counter()
    sol = run()
    out["first_simulate_s"] = time.perf_counter() - t
    t = time.perf_counter()
    sol = run()
    out["simulate_after_compile_s"] = time.perf_counter() - t
    out["steps"] = int(sol.stats["num_accepted_steps"]) + int(sol.stats["num_rejected_steps"])
    pos = jnp.max(jnp.abs(sol.constraint_drift["position"]))
    out["max_position_residual"] = float(pos)
    open_scene = jb.scene(model, constraints=None)
    for name, sc in (("constrained", scene), ("open", open_scene)):
        f = jax.jit(lambda q, v, sc=sc: sc.evaluate(0.0, q, v)[0])
        f(q0, v0).block_until_ready()
        out[f"field_{name}_us"] = 1e6 * time_per_call(lambda f=f: f(q0, v0).block_until_ready())["median_s"]
    out["field_ratio"] = out["field_constrained_us"] / out["field_open_us"]
    # rates that keep the loops closed (the null space of G at home), where γ is not zero
    import numpy as np

    G = np.asarray(scene.constraints.constraint_jacobian(0.0, q0, jnp.zeros(model.nv)))
    null = np.linalg.svd(G)[2][G.shape[0]:].T
    out.update(bias_forms(scene, q0, jnp.asarray(null @ np.random.default_rng(3).normal(size=null.shape[1]))))
    out.update(field_ratio())
    return out


def bias_forms(scene, q, v) -> dict:
    """XLA compile seconds and µs per evaluation of the constrained vector field at ``(q, v)``
    with the loops' rate term ``γ`` in closed form (the loop closures as they are) and
    differentiated in forward mode (each wrapped in a constraint that gives no closed form),
    JAX's compilation cache off."""
    import equinox as eqx
    import jax

    from jaxbody import maggi

    class Differentiated(maggi.Constraint):
        inner: maggi.Constraint

        def velocity(self, base, t, q, x):
            return self.inner.velocity(base, t, q, x)

        def position(self, base, t, q):
            return self.inner.position(base, t, q)

        @property
        def size(self):
            return self.inner.size

        @property
        def names(self):
            return self.inner.names

    differentiated = eqx.tree_at(lambda s: s.constraints.constraints, scene,
                                 tuple(Differentiated(c) for c in scene.constraints.constraints))
    out = {}
    cached = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        for name, sc in (("closed", scene), ("differentiated", differentiated)):
            lowered = jax.jit(lambda q, v, sc=sc: sc.evaluate(0.0, q, v)[0]).lower(q, v)
            t = time.perf_counter()
            f = lowered.compile()
            out[f"bias_{name}_compile_s"] = time.perf_counter() - t
            f(q, v).block_until_ready()
            out[f"bias_{name}_us"] = 1e6 * time_per_call(lambda f=f: f(q, v).block_until_ready())["median_s"]
            out[f"bias_{name}_acceleration"] = [float(x) for x in f(q, v)]
    finally:
        jax.config.update("jax_enable_compilation_cache", cached)
    a, b = out["bias_closed_acceleration"], out["bias_differentiated_acceleration"]
    out["bias_max_difference"] = max(abs(x - y) for x, y in zip(a, b)) / max(abs(x) for x in b)
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--t1", type=float, default=1.0, help="simulated time (s)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--name", default="loops")
    p.add_argument("--field-only", action="store_true",
                   help="only the four-bar's vector field with and without its loop (runs on older checkouts too)")
    args = p.parse_args()
    if args.child:
        print(json.dumps(child(args.t1)))
        return
    if args.field_only:
        print(json.dumps(field_ratio()))
        return
    load0 = load_average()
    res = subprocess.run([sys.executable, __file__, "--child", "--t1", str(args.t1)], capture_output=True, text=True,
                         check=True)
    r = json.loads(res.stdout.strip().splitlines()[-1])
    record = {"stamp": stamp(), "load_start": load0, "load_end": load_average(), "t1": args.t1, "result": r}
    (RESULTS / f"{args.name}.json").write_text(json.dumps(record, indent=1))
    rows = [
        ("import jaxbody", f"{r['import_jaxbody_s']:.2f} s"),
        ("`jb.from_mjcf` (loop directions included)", f"{r['from_mjcf_s']:.3f} s"),
        (f"`jb.scene` ({r['constraint_rows']} loop rows checked and partitioned)", f"{r['scene_s']:.2f} s"),
        (f"first `jb.simulate`, {args.t1:g} s from `home` (compile and run)", f"{r['first_simulate_s']:.1f} s"),
        (f"the same simulation after compilation ({r['steps']} steps)", f"{r['simulate_after_compile_s']:.2f} s"),
        ("max loop position residual along it", f"{r['max_position_residual']:.1e}"),
        ("vector field with the loops / without (µs per evaluation)",
         f"{r['field_constrained_us']:.0f} / {r['field_open_us']:.0f} = {r['field_ratio']:.1f}x"),
        ("loops' rate term γ in closed form / differentiated: XLA compile of the vector field",
         f"{r['bias_closed_compile_s']:.2f} / {r['bias_differentiated_compile_s']:.2f} s"),
        ("loops' rate term γ in closed form / differentiated: one evaluation (µs)",
         f"{r['bias_closed_us']:.0f} / {r['bias_differentiated_us']:.0f} (accelerations agree to "
         f"{r['bias_max_difference']:.0e} of their largest)"),
        ("imported four-bar: vector field with its loop / without (µs, interleaved medians)",
         f"{r['four_bar_constrained_us']:.0f} / {r['four_bar_open_us']:.0f} = {r['four_bar_ratio']:.1f}x"),
    ]
    md = [f"# Cassie-like biped with four loops ({MODEL.name})", "", stamp_markdown(record["stamp"]), "",
          f"Load average {load0} at start, {record['load_end']} at end; one fresh process.", "",
          markdown_table(["what", "time"], rows), ""]
    (RESULTS / f"{args.name}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
