"""What does each declared effect cost in a scene's vector field, and what does the planar path save?

For the menagerie panda (spatial path) and a 7-link planar chain (planar absolute-angle path
next to the spatial path of the same model), for each effect set from "everything" down to
"nothing", this measures one evaluation of the scene's vector field ``(t, q, v) -> a``:

* jaxpr equation count (including the equations inside nested calls and loops) and XLA
  ``cost_analysis`` flops of the compiled program;
* compile time (lower + XLA compile) and warm time per call (median, ``block_until_ready``);
* warm time per state of a ``vmap`` over ``--batch`` states (throughput regime).

The effect sets, from the largest down: a Maggi constraint (the last body's origin on a
vertical plane x = 0), a prescribed support motion, body loads, actuation, dampers, springs, gravity.
Sets with loads or a constraint run on the spatial path only.

Results go to ``benchmarks/results/effects.{md,json}`` (``--out`` picks another folder) stamped
with commit, machine, versions, date and command.

Usage::

    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false .venv/bin/python benchmarks/effects.py
    .venv/bin/python benchmarks/effects.py --batch 256 --min-time 0.2 --tag quick
    .venv/bin/python benchmarks/effects.py --only chain7:planar --batch 4 --min-time 0.01 --out /tmp/fx
"""

import argparse
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _common  # noqa: E402


def effect_sets(jb, model, jnp):
    nv, nb = model.nv, model.n_body

    def tau(t, q, v):
        return -2.0 * q[:nv] - 0.5 * v

    def wrench(t, q, v):
        return jnp.zeros((nb, 6)).at[-1, 2].set(3.0 * jnp.sin(t))

    stiff = jnp.full((model.n_joint,), 4.0)
    damp = jnp.full((nv,), 0.3)
    def support(t):
        return jnp.stack([0.1 * jnp.sin(3.0 * t), 0.0 * t, 0.05 * t])

    from jaxbody import constraints as jc

    # the last body's origin on the plane x = 0 (vertical, through the base; admissible at qpos0 for the
    # chain, whose x-motion of the tip is not singular there)
    on_plane = jc.PointOnPlane(model, model.body_names[-1], (0.0, 0.0, 0.0), normal=(1.0, 0.0, 0.0))
    full = dict(gravity=True, springs=stiff, dampers=damp, actuation=tau, loads=wrench)
    return [
        ("gravity+springs+dampers+actuation+loads+support+constraint", {**full, "support": support,
                                                                        "constraints": [on_plane]}),
        ("gravity+springs+dampers+actuation+loads+support", {**full, "support": support}),
        ("gravity+springs+dampers+actuation+loads", full),
        ("gravity+springs+dampers+actuation", {**full, "loads": None}),
        ("gravity+springs+dampers", {**full, "loads": None, "actuation": None}),
        ("gravity+springs", {**full, "loads": None, "actuation": None, "dampers": False}),
        ("gravity", {**full, "loads": None, "actuation": None, "dampers": False, "springs": False}),
        ("(none)", {**full, "loads": None, "actuation": None, "dampers": False, "springs": False, "gravity": False}),
    ]


def chain7(jb, np):
    rng = np.random.default_rng(0)
    b = jb.ModelBuilder(gravity=np.array([0.0, 0.0, -9.81]))
    for i in range(7):
        b.add_body(f"link{i}", parent=f"link{i - 1}" if i else None,
                   pos=np.array([0.0, 0.0, -0.4]) if i else np.zeros(3),
                   mass=1.0 + 0.3 * rng.random(), com=np.array([0.02, 0.01, -0.2]),
                   inertia=np.array([0.02, 0.015 + 0.01 * rng.random(), 0.01]),
                   joints=[jb.Hinge(axis=np.array([0.0, -1.0, 0.0]))])
    return b.build()


def measure(jax, jnp, np, scene, batch, min_time):
    rng = np.random.default_rng(1)
    q = jnp.asarray(rng.uniform(-0.5, 0.5, scene.nq))
    if scene.has_quaternions:
        q = q.at[:4].set(jnp.array([1.0, 0, 0, 0]))
    v = jnp.asarray(rng.uniform(-0.5, 0.5, scene.nv))
    t = jnp.asarray(0.1)

    def f(t, q, v):
        return scene.acceleration(t, q, v)

    eqns = _common.count_eqns(jax, jax.make_jaxpr(f)(t, q, v).jaxpr)
    t0 = time.perf_counter()
    compiled = jax.jit(f).lower(t, q, v).compile()
    compile_s = time.perf_counter() - t0
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    one = _common.time_per_call(lambda: compiled(t, q, v).block_until_ready(), min_time=min_time)
    qs = jnp.broadcast_to(q, (batch, scene.nq))
    vs = jnp.broadcast_to(v, (batch, scene.nv)) * jnp.linspace(0.5, 1.5, batch)[:, None]
    batched = jax.jit(jax.vmap(f, in_axes=(None, 0, 0))).lower(t, qs, vs).compile()
    many = _common.time_per_call(lambda: batched(t, qs, vs).block_until_ready(), min_time=min_time)
    return {
        "jaxpr_eqns": eqns,
        "flops": float(cost.get("flops", float("nan"))),
        "compile_s": compile_s,
        "call_us": one["median_s"] * 1e6,
        "batched_us_per_state": many["median_s"] / batch * 1e6,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--min-time", type=float, default=0.5)
    ap.add_argument("--tag", default="", help="suffix of the result files (effects_<tag>.*)")
    ap.add_argument("--models-dir", type=pathlib.Path, default=_common.REPO / "jaxbody" / "models")
    ap.add_argument("--out", type=pathlib.Path, default=_common.RESULTS, help="folder of the result files")
    ap.add_argument("--only", default="", help="comma-separated cases to run, e.g. chain7:planar "
                    "(cases: panda:spatial, chain7:planar, chain7:spatial; default all)")
    ap.add_argument("--max-sets", type=int, default=None, help="measure at most this many effect sets per case")
    args = ap.parse_args()
    st = _common.stamp()

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb

    rows = []
    only = [c for c in args.only.split(",") if c]
    cases = [("panda", "spatial", False), ("chain7", "planar", None), ("chain7", "spatial", False)]
    unknown = set(only) - {f"{n}:{p}" for n, p, _ in cases}
    if unknown:
        ap.error(f"--only: unknown cases {sorted(unknown)}")
    cases = [c for c in cases if not only or f"{c[0]}:{c[1]}" in only]
    models = {}
    for name, path, planar in cases:
        if name not in models:
            models[name] = jb.from_mjcf(str(args.models_dir / "panda.xml")) if name == "panda" else chain7(jb, np)
        model = models[name]
        sets = [(label, kw) for label, kw in effect_sets(jb, model, jnp)
                if path != "planar" or (kw.get("loads") is None and kw.get("constraints") is None)]
        # (loads and constraints take the spatial path)
        for label, kw in sets[:args.max_sets]:
            sc = jb.scene(model, planar=planar, **kw)
            assert sc.path == path, (name, label, sc.path)
            r = measure(jax, jnp, np, sc, args.batch, args.min_time)
            r.update(model=name, path=path, effects=label)
            rows.append(r)
            print(json.dumps(r), flush=True)
    st["load_average_end"] = _common.load_average()
    st["device"] = str(jax.devices()[0])
    stem = "effects" + (f"_{args.tag}" if args.tag else "")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{stem}.json").write_text(json.dumps({"stamp": st, "batch": args.batch, "rows": rows}, indent=1))
    headers = ["model", "path", "effects", "jaxpr eqns", "flops", "compile (s)", "one call (µs)", f"vmap {args.batch} (µs/state)"]
    table = _common.markdown_table(headers, [
        [r["model"], r["path"], r["effects"], r["jaxpr_eqns"], f"{r['flops']:.0f}", f"{r['compile_s']:.2f}",
         f"{r['call_us']:.1f}", f"{r['batched_us_per_state']:.2f}"] for r in rows
    ])
    md = [
        "# Cost of each declared effect in a scene's vector field",
        "",
        _common.stamp_markdown(st),
        f"- device: {st['device']}",
        "",
        "One evaluation of `scene.acceleration(t, q, v)`; jaxpr equations counted into nested calls and loops;",
        "flops from XLA `cost_analysis` of the compiled program. The constraint is the last body's origin on a",
        "vertical plane x = 0 (Maggi layer); the support moves as s(t) = (0.1 sin 3t, 0, 0.05 t).",
        "The planar path of `chain7` runs the absolute-angle equations; the spatial rows are the same model with `planar=False`.",
        "Equation counts and flops are exact; times on a shared machine are noisy (see the load average above):",
        "compare them only within one run, and prefer the flops column for the cost of an effect.",
        "",
        table,
        "",
    ]
    (args.out / f"{stem}.md").write_text("\n".join(md))
    print(f"wrote {args.out / (stem + '.md')}")


if __name__ == "__main__":
    main()
