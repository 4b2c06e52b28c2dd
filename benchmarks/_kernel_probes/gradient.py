"""Where does the time of a rollout gradient go? One forward-dynamics evaluation and its
derivatives, per kernel, for a single state (why a rollout gradient costs about three rollouts).

A checkpointed gradient of an RK4 rollout evaluates, per stage, the forward dynamics once more
(recomputation) and its linearisation and transpose (the vector-Jacobian product). This times
each piece on one state of the Panda arm, jitted, for the native kernel (whose derivatives with
respect to the state are its generated forward- and reverse-mode programs) and the vectorised
kernel:

    .venv/bin/python benchmarks/kernels.py gradient [--model panda|chain20] [--min-time 0.5]

Writes ``benchmarks/results/gradient_profile.{md,json}``.
"""

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common, dynamics
from _common import RESULTS, load_average, markdown_table, stamp, stamp_markdown, time_per_call  # noqa: E402
from _common import set_default_xla_flags  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(prog="kernels.py gradient", description=__doc__.splitlines()[0])
    p.add_argument("--model", default="panda", help="a robot shipped in jaxbody/models, or chainN")
    p.add_argument("--kernels", default="native,vectorised")
    p.add_argument("--min-time", type=float, default=0.5)
    p.add_argument("--out", default=str(RESULTS))
    p.add_argument("--name", default="gradient_profile")
    p.add_argument("--no-rollout", action="store_true", help="skip the per-step pieces of a 1000-step rollout")
    args = p.parse_args(argv)
    set_default_xla_flags()  # before JAX starts: the CPU fusion flag on jaxlib 0.10
    rec = {"stamp": stamp(), "model": args.model, "rows": []}

    import pathlib
    import warnings

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody import backends

    import tempfile

    from dynamics import model_path

    with warnings.catch_warnings(), tempfile.TemporaryDirectory() as tmp:
        warnings.simplefilter("ignore")
        model = jb.from_mjcf(str(model_path(args.model, pathlib.Path(jb.__file__).parent / "models", pathlib.Path(tmp))))
    rng = np.random.default_rng(0)
    q = jb.normalize_qpos(model, jnp.asarray(np.asarray(model.qpos0) + 0.3 * rng.standard_normal(model.nq)))
    v = jnp.asarray(rng.standard_normal(model.nv))
    tau = jnp.asarray(rng.standard_normal(model.nv))
    w = jnp.asarray(rng.standard_normal(model.nv))

    for kernel in args.kernels.split(","):
        def fd(q, v, kernel=kernel):
            return backends.acceleration(model, q, v, tau, gravity=model.gravity, kernel=kernel)

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

    if not args.no_rollout:
        rec["rollout"] = _rollout_pieces(args, model, q, v, tau, w)

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
    if "rollout" in rec:
        r = rec["rollout"]
        md += [
            f"## Per step of a {r['steps']}-step RK4 rollout (native kernel, µs per step)",
            "",
            "Where the time of a checkpointed rollout gradient goes. `fori_loop` rows: the kernel "
            "alone, called once per iteration of a jitted loop. `diffrax floor` rows: the same solve "
            "(written-out RK4 stages, one checkpoint per step, `SaveAt(t1=True)`) of a free vector "
            f"field `tanh(A y)` with as many states ({r['n_state']}) — what diffrax's loop and its "
            "checkpointed reverse pass cost without any dynamics. `simulate` rows: the loss of "
            "`benchmarks/gradients.py` through `jb.simulate` on the native kernel, default adjoint.",
            "",
            markdown_table(["piece", "µs per step", "ratio"], [(k, f"{x:.2f}", f"{y:.2f}" if y else "") for k, x, y in r["rows"]]),
            "",
        ]
    (out / f"{args.name}.md").write_text("\n".join(md))


def _rollout_pieces(args, model, q, v, tau, w):
    """Per-step costs of a rollout and of its checkpointed gradient (see the record's text)."""
    import diffrax
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody import backends
    from jaxbody.backends import native
    from jaxbody.simulation import RK4Stages

    steps, dt = 1000, 1e-3
    per_step = lambda fn: 1e6 * time_per_call(lambda: jax.block_until_ready(fn()), min_time=args.min_time)["median_s"] / steps  # noqa: E731

    def fd(q, v):
        return backends.acceleration(model, q, v, tau, gravity=model.gravity, kernel="native")

    def vjp_step(i, c):
        _, pullback = jax.vjp(fd, c[0], c[1])
        dq, dv = pullback(w)
        return c[0] + 1e-9 * dq, c[1] + 1e-9 * dv

    loop_fd = jax.jit(lambda q, v: jax.lax.fori_loop(0, steps, lambda i, c: (c[0], c[1] + 1e-9 * fd(*c)), (q, v)))
    loop_vjp = jax.jit(lambda q, v: jax.lax.fori_loop(0, steps, vjp_step, (q, v)))

    def rk4(q, v):
        return native.rk4_step(model, q, v, dt, tau, gravity=model.gravity)[:2]

    def rk4_vjp_step(i, c):
        _, pullback = jax.vjp(rk4, c[0], c[1])
        dq, dv = pullback((c[0], c[1]))
        return c[0] + 1e-9 * dq, c[1] + 1e-9 * dv

    loop_rk4 = jax.jit(lambda q, v: jax.lax.fori_loop(0, steps, lambda i, c: rk4(*c), (q, v)))
    loop_rk4_vjp = jax.jit(lambda q, v: jax.lax.fori_loop(0, steps, rk4_vjp_step, (q, v)))
    rows = []
    t_fd = per_step(lambda: loop_fd(q, v))
    rows.append(("fori_loop: forward dynamics", t_fd, None))
    rows.append(("fori_loop: vjp (reverse-mode program, value unused)", per_step(lambda: loop_vjp(q, v)), None))
    a = per_step(lambda: loop_rk4(q, v))
    b = per_step(lambda: loop_rk4_vjp(q, v))
    rows += [("fori_loop: generated RK4 step", a, None), ("fori_loop: its reverse-mode program (value unused)", b, b / a)]

    n_state = model.nq + model.nv
    A = jnp.asarray(np.random.default_rng(0).standard_normal((n_state, n_state)) / np.sqrt(n_state))
    adjoint = diffrax.RecursiveCheckpointAdjoint(checkpoints=steps + 16)

    def free(y0):
        sol = diffrax.diffeqsolve(diffrax.ODETerm(lambda t, y, a: jnp.tanh(A @ y)), RK4Stages(), 0.0, steps * dt, dt, y0,
                                  saveat=diffrax.SaveAt(t1=True), max_steps=steps + 16, adjoint=adjoint)
        return jnp.sum(sol.ys[-1] ** 2)

    y0 = jnp.concatenate([q, v])
    f_fwd, f_grad = jax.jit(free), jax.jit(jax.grad(free))
    a, b = per_step(lambda: f_fwd(y0)), per_step(lambda: f_grad(y0))
    rows += [("diffrax floor: forward", a, None), ("diffrax floor: checkpointed gradient", b, b / a)]

    scene = jb.scene(model, kernel="native")

    def loss(q0, v0):
        sol = jb.simulate(scene, q0, v0, steps * dt, solver="rk4", dt0=dt, saveat=diffrax.SaveAt(t1=True), max_steps=steps + 16)
        return jnp.sum(sol.q[-1] ** 2) + jnp.sum(sol.v[-1] ** 2)

    s_fwd, s_grad = jax.jit(loss), jax.jit(jax.grad(loss, argnums=(0, 1)))
    a, b = per_step(lambda: s_fwd(q, v)), per_step(lambda: s_grad(q, v))
    rows += [("simulate: forward", a, None), ("simulate: gradient", b, b / a)]
    for name, x, y in rows:
        print(f"{name:45s} {x:8.2f} us/step" + (f"  {y:.2f}x" if y else ""), flush=True)
    return {"steps": steps, "n_state": n_state, "rows": rows}


if __name__ == "__main__":
    main()
