"""Which forward-dynamics kernel is faster, for one state and for a batch?

Times, in one process, an RK4 step of ``M(q) a = passive − bias`` (gravity, springs and
dampers of the model, dt = 1e-3) inside a jitted ``lax.fori_loop``, for the unrolled kernel,
the vectorised kernel and ``kernel="auto"`` (what ``jb.simulate`` runs), on one state and on
a ``vmap`` batch, next to MuJoCo's ``mj_step`` with its RK4 integrator (a C loop: ``rollout``
of one trajectory on one thread; timer callback off; contacts, constraints, actuation off).
Also the compile time of each kernel and the HLO instruction count of the batched programs
(the fusion duplication docs/performance.md describes).

Records ``benchmarks/results/<name>.{md,json}`` stamped with commit, machine and command.

Usage::

    .venv/bin/python benchmarks/kernels.py compare               # panda, ur5e, chain7, chain20
    .venv/bin/python benchmarks/kernels.py compare --models panda --batch 1024
"""

import argparse
import json
import pathlib
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # benchmarks/: _common, dynamics
import _common  # noqa: E402

_common.set_default_xla_flags()  # before JAX starts: the CPU fusion flag on jaxlib 0.10
from dynamics import _mujoco_rigid, model_path  # noqa: E402

KERNELS = ("unrolled", "vectorised", "auto")


def measure(name, args, tmp):
    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np
    from mujoco import rollout

    import jaxbody as jb
    from jaxbody import backends, kernels

    path = model_path(name, args.models_dir, tmp)
    model = jb.from_mjcf(str(path))
    h, n = 1e-3, args.steps
    rng = np.random.default_rng(0)
    q0 = np.asarray(model.qpos0) + 0.1 * rng.standard_normal((args.batch, model.nq))
    q0 = jax.vmap(lambda x: jb.kinematics.normalize_qpos(model, x))(jnp.asarray(q0))
    v0 = jnp.asarray(0.1 * rng.standard_normal((args.batch, model.nv)))

    def rk4(kernel):
        def acc(q, v):
            force = kernels.passive_forces_at(model, q, v)
            return backends.acceleration(model, q, v, force, gravity=model.gravity, kernel=kernel)

        def f(q, v):
            return jb.kinematics.qpos_rate(model, q, v), acc(q, v)

        def step(_, y):
            q, v = y
            k1 = f(q, v)
            k2 = f(q + h / 2 * k1[0], v + h / 2 * k1[1])
            k3 = f(q + h / 2 * k2[0], v + h / 2 * k2[1])
            k4 = f(q + h * k3[0], v + h * k3[1])
            return q + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]), v + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])

        return lambda q, v: jax.lax.fori_loop(0, n, step, (q, v))

    out = {"model": name, "n_body": model.n_body, "nv": model.nv, "batch": args.batch, "steps": n}
    for k in KERNELS:
        t0 = time.perf_counter()
        single = jax.jit(rk4(k)).lower(q0[0], v0[0]).compile()
        compile_s = time.perf_counter() - t0
        batched = jax.jit(jax.vmap(rk4(k))).lower(q0, v0).compile()
        ts = _common.time_per_call(lambda: jax.block_until_ready(single(q0[0], v0[0])), min_time=args.min_time)
        tb = _common.time_per_call(lambda: jax.block_until_ready(batched(q0, v0)), min_time=args.min_time)
        out[k] = {
            "compile_single_s": compile_s,
            "single_step_us": ts["median_s"] / n * 1e6,
            "batch_steps_per_s": args.batch * n / tb["median_s"],
            "batched_hlo_instructions": len(batched.as_text().splitlines()),
        }
    if name in args.simulate_models.split(","):
        # through the public API: jb.simulate of a scene, vmapped; the "rk4" preset (stages
        # written out for the unrolled kernel) against diffrax's tableau loop over the stages
        import diffrax

        from jaxbody.simulation import RK4

        for k in ("unrolled", "vectorised"):
            sc = jb.scene(model, kernel=k)
            for label, solver in (("rk4 preset", "rk4"), ("tableau RK4", RK4())):
                def roll(q, v, sc=sc, solver=solver):
                    sol = jb.simulate(sc, q, v, n * h, solver=solver, dt0=h, saveat=diffrax.SaveAt(t1=True),
                                      max_steps=n + 1)
                    return sol.q[-1]

                t0 = time.perf_counter()
                fn = jax.jit(jax.vmap(roll)).lower(q0, v0).compile()
                compile_s = time.perf_counter() - t0
                tb = _common.time_per_call(lambda: jax.block_until_ready(fn(q0, v0)), min_time=args.min_time)
                out[k][f"simulate {label}"] = {"batch_steps_per_s": args.batch * n / tb["median_s"],
                                               "compile_s": compile_s}
    m = _mujoco_rigid(str(path))
    m.opt.integrator = int(mujoco.mjtIntegrator.mjINT_RK4)
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = np.asarray(q0[0]), np.asarray(v0[0])
    state = np.zeros((1, mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS)))
    mujoco.mj_getState(m, d, state[0], mujoco.mjtState.mjSTATE_FULLPHYSICS)
    nstep = 1000
    tm = _common.time_per_call(lambda: rollout.rollout(m, d, state, nstep=nstep), min_time=args.min_time)
    out["mj_step_us"] = tm["median_s"] / nstep * 1e6
    return out


def main(argv=None):
    p = argparse.ArgumentParser(prog="kernels.py compare", description=__doc__.splitlines()[0])
    p.add_argument("--models", default="panda,ur5e,chain7,chain20")
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--min-time", type=float, default=0.5)
    p.add_argument("--simulate-models", default="panda",
                   help="models also timed through a vmapped jb.simulate, rk4 preset vs tableau RK4")
    p.add_argument("--models-dir", type=pathlib.Path, default=_common.REPO / "jaxbody" / "models")
    p.add_argument("--out", type=pathlib.Path, default=_common.RESULTS)
    p.add_argument("--name", default="kernels")
    args = p.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    import mujoco

    mujoco.set_mjcb_time(None)  # MuJoCo 4 installs a Python timer that doubles small models' cost
    stamp = _common.stamp(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.models.split(","):
            r = measure(name, args, pathlib.Path(tmp))
            rows.append(r)
            print(json.dumps(r))
    stamp["load_average_end"] = _common.load_average()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps({"stamp": stamp, "results": rows}, indent=1, default=str))
    headers = ["model", "bodies", "nv"]
    for k in KERNELS:
        headers += [f"{k}: single RK4 step µs", f"{k}: batch steps/s", f"{k}: compile s", f"{k}: batched HLO lines"]
    headers += ["mj_step (RK4) µs", "unrolled / mj_step", "auto batch / vectorised batch"]
    table = []
    for r in rows:
        row = [r["model"], r["n_body"], r["nv"]]
        for k in KERNELS:
            row += [f"{r[k]['single_step_us']:.1f}", f"{r[k]['batch_steps_per_s']:.3g}", f"{r[k]['compile_single_s']:.1f}", r[k]["batched_hlo_instructions"]]
        row += [f"{r['mj_step_us']:.2f}", f"{r['unrolled']['single_step_us'] / r['mj_step_us']:.2f}",
                f"{r['auto']['batch_steps_per_s'] / r['vectorised']['batch_steps_per_s']:.2f}"]
        table.append(row)
    sim_rows = [[r["model"], k, label, f"{r[k][f'simulate {label}']['batch_steps_per_s']:.3g}",
                 f"{r[k][f'simulate {label}']['compile_s']:.1f}"]
                for r in rows for k in ("unrolled", "vectorised") for label in ("rk4 preset", "tableau RK4")
                if f"simulate {label}" in r[k]]
    md_sim = ["## Through `jb.simulate` (vmapped batch)", "",
              "`jax.jit(jax.vmap(...))` of `jb.simulate(jb.scene(model, kernel=K), ..., solver=S, dt0=1e-3)`: "
              "the `\"rk4\"` preset (stages written out when the kernel is unrolled) against "
              "`jaxbody.simulation.RK4()` (diffrax's loop over a Butcher tableau).", "",
              _common.markdown_table(["model", "kernel", "solver", "batch steps/s", "compile s"], sim_rows), ""]
    md = [f"# Forward-dynamics kernels (batch {args.batch}, {args.steps} RK4 steps, float64)", "",
          _common.stamp_markdown(stamp), "", _common.markdown_table(headers, table), ""] + (md_sim if sim_rows else [])
    (args.out / f"{args.name}.md").write_text("\n".join(md))


if __name__ == "__main__":
    main()
