"""How many RK4 system-steps per second does ``jb.simulate`` reach, next to MuJoCo and MJX?

For each model (double pendulum ``chain2``, hinge chains ``chainN``, menagerie ``panda`` and
``anymal_c``) and each batch size this measures, in isolated worker processes, RK4 rollouts
at dt = 1e-3 from random states (rigid-body dynamics only, no actuation/contacts/limits):

* jaxbody through the public API, ``jax.jit`` of ``jax.vmap`` (small batches) or
  ``jb.vmap_chunked`` (large ones, optionally split over CPU devices) of
  ``jb.simulate(model, q0, v0, t1, solver="rk4", dt0=1e-3, saveat=SaveAt(t1=True))``, in
  float64 and in float32 (a worker without ``jax_enable_x64``), compile time (trace, lower,
  XLA compile) separate from run time;
* MuJoCo ``mujoco.rollout`` with ``m.opt.integrator = RK4`` on 1 thread and on all cores
  (timer callback off);
* MJX: ``jax.jit(jax.vmap(rollout))`` with ``rollout`` a ``lax.fori_loop`` of
  ``mjx.step`` (RK4 integrator, float32 as MJX runs by default), with its compile time; a
  worker that does not finish within ``--mjx-timeout`` (default 300 s) is recorded as such;
* single trajectory: per-step time of a jitted, unbatched ``jb.simulate`` of
  ``--single-steps`` steps against MuJoCo's ``mj_step`` (a C loop: ``rollout`` of one
  trajectory on one thread; and a Python loop of ``mujoco.mj_step``);
* compile time of ``jb.forward_dynamics`` and of the single-trajectory ``jb.simulate`` (does it stay flat as the tree grows?);
* float32 against float64 (speed and accuracy, and the README's "float32: when it is enough"): the final
  state after 1 s from a few random states, RK4 at dt = 1e-3 in both precisions, and
  float32 ``tsit5`` at rtol = atol from 1e-4 to 1e-8 against a float64 ``tsit5`` solution
  at 1e-10 (did it succeed, how many steps, what error).

Records ``benchmarks/results/<name>.{md,json,png}`` (default name ``throughput``) stamped with
commit, machine, versions, date, load average and command. See ``benchmarks/README.md``.

Usage::

    .venv/bin/python benchmarks/throughput.py                     # every model, batches 1..8192
    .venv/bin/python benchmarks/throughput.py --batches 1,64,1024,8192,65536
    .venv/bin/python benchmarks/throughput.py --models panda,chain20 --impls jb64,mujoco
"""

import argparse
import json
import math
import os
import pathlib
import statistics
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _common  # noqa: E402
from dynamics import MENAGERIE, XLA_DEFAULT_FLAG, _compile, _mujoco_rigid, _Record, _states  # noqa: E402
from dynamics import model_path as _model_path  # noqa: E402

DEFAULT_MODELS = ("panda", "chain20", "anymal_c", "chain2", "chain100", "chain7", "chain50")  # targets first
DEFAULT_BATCHES = (1, 64, 1024, 8192, 65536)
IMPLS = ("jb64", "jb32", "mujoco", "mjx")
LABEL = {
    "jb64": "jaxbody float64",
    "jb32": "jaxbody float32",
    "mj1": "MuJoCo rollout 1 thread",
    "mjN": "MuJoCo rollout all cores",
    "mjx": "MJX (float32)",
}
DT = 1e-3
ACCURACY_TIME = 1.0
TSIT5_TOLS = (1e-4, 1e-5, 1e-6, 1e-7, 1e-8)


def model_path(name, models_dir, tmp):
    # "double_pendulum" is an alias of chain2 (two hinge links, the smallest tree)
    return _model_path("chain2" if name == "double_pendulum" else name, models_dir, tmp)


def n_steps(batch, cfg):
    """Steps per timed rollout: ``--steps``, fewer for big batches (``--max-work`` system-steps)."""
    return int(max(cfg["min_steps"], min(cfg["steps"], cfg["max_work"] // batch)))


# ============================================================================ workers
def _rigid_rk4(path):
    import mujoco

    m = _mujoco_rigid(path)
    m.opt.integrator = int(mujoco.mjtIntegrator.mjINT_RK4)
    m.opt.timestep = DT
    return m


def worker_mujoco(cfg, rec):
    """``mujoco.rollout`` of RK4 rollouts: per batch on 1 thread and all cores; one trajectory; accuracy."""
    import mujoco
    import mujoco.rollout
    import numpy as np

    rec.data["mjcb_time_at_start"] = repr(mujoco.get_mjcb_time())
    mujoco.set_mjcb_time(None)  # a Python timer callback would time every stage through Python
    m = _rigid_rk4(cfg["path"])
    rec.data.update(nq=int(m.nq), nv=int(m.nv), integrator="RK4", timestep=m.opt.timestep)
    full = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(m, full)
    rep = dict(min_time=cfg["min_time"], repeats=cfg["repeats"])

    def initial(q, v):
        d = mujoco.MjData(m)
        init = np.empty((len(q), nstate))
        for i in range(len(q)):
            d.qpos[:], d.qvel[:] = q[i], v[i]
            mujoco.mj_getState(m, d, init[i], full)
        return init

    def make_rollout(batch, nstep, nthread):
        q, v, _, _ = _states(m, batch, cfg["seed"])
        init = initial(q, v)
        datas = [mujoco.MjData(m) for _ in range(nthread)]
        state = np.empty((batch, nstep, nstate))
        sens = np.empty((batch, nstep, m.nsensordata))
        r = mujoco.rollout.Rollout(nthread=nthread)

        def run():
            r.rollout(m, datas, init, nstep=nstep, state=state, sensordata=sens)

        return r, run, state

    rows = rec.data["batches"] = {}
    for batch in cfg["batches"]:
        nstep = n_steps(batch, cfg)
        row = rows[str(batch)] = {"steps": nstep}
        for key, nthread in (("mj1", 1), ("mjN", cfg["threads"])):
            r, run, _ = make_rollout(batch, nstep, nthread)
            with r:
                t = _common.time_per_call(run, **rep)
            t.update(nthread=nthread, steps_per_s=batch * nstep / t["median_s"])
            row[key] = t
            rec.save()

    # one trajectory, mj_step in a C loop (rollout, 1 thread) and from Python
    ns = cfg["single_steps"]
    if not ns:
        return
    r, run, _ = make_rollout(1, ns, 1)
    with r:
        t = _common.time_per_call(run, **rep)
    single = rec.data["single"] = {"steps": ns, "rollout_1thread_per_step_s": t["median_s"] / ns}
    d = mujoco.MjData(m)
    q, v, _, _ = _states(m, 1, cfg["seed"])

    def py_loop():
        d.qpos[:], d.qvel[:] = q[0], v[0]
        for _ in range(ns):
            mujoco.mj_step(m, d)

    single["python_mj_step_per_step_s"] = _common.time_per_call(py_loop, **rep)["median_s"] / ns
    rec.save()

    # accuracy reference: RK4 at the same dt, final state after ACCURACY_TIME
    if cfg["accuracy"]:
        nacc = int(round(ACCURACY_TIME / DT))
        q, v, _, _ = _states(m, cfg["accuracy_states"], cfg["seed"] + 1)
        init = initial(q, v)
        with mujoco.rollout.Rollout(nthread=1) as rr:
            state = np.empty((len(q), nacc, nstate))
            rr.rollout(m, [mujoco.MjData(m)], init, nstep=nacc, state=state)
        d = mujoco.MjData(m)
        qs, vs = [], []
        for i in range(len(q)):
            mujoco.mj_setState(m, d, state[i, -1], full)
            qs.append(np.array(d.qpos))
            vs.append(np.array(d.qvel))
        rec.data["accuracy"] = {"rk4_q": np.array(qs).tolist(), "rk4_v": np.array(vs).tolist()}
        rec.save()


def _jax_setup(x64):
    import jax

    jax.config.update("jax_enable_x64", x64)
    jax.jit(lambda x: x * 2.0 + 1.0)(jax.numpy.ones(3)).block_until_ready()  # XLA start-up
    return jax


def _batched(jax, jb, rollout, batch, cfg):
    """``(function, description)``: ``rollout`` over a batch of states, as the jaxbody workers
    run it (``jax.vmap``, or ``jb.vmap_chunked`` above ``--chunk``, split over ``--devices``)."""
    axes = (None, 0, 0, None)
    ndev = cfg["devices"]
    if cfg["chunk"] and batch > cfg["chunk"]:
        devs = ndev if ndev > 1 and batch % ndev == 0 and batch >= ndev * cfg["chunk"] else None
        return jb.vmap_chunked(rollout, cfg["chunk"], in_axes=axes, devices=devs), \
            f"jb.vmap_chunked(chunk={cfg['chunk']}, devices={devs})"
    return jax.vmap(rollout, in_axes=axes), "jax.vmap"


def _simulate_rollout(jb, diffrax, cfg):
    """The timed rollout: ``jb.simulate`` RK4 to ``t1``, final state and steps taken."""

    def rollout(model, q0, v0, t1):
        system = jb.scene(model, kernel=cfg["kernel"]) if cfg.get("kernel") else model
        sol = jb.simulate(system, q0, v0, t1, solver="rk4", dt0=DT, saveat=diffrax.SaveAt(t1=True),
                          max_steps=cfg["max_steps"])
        return sol.q[-1], sol.v[-1], sol.stats["num_steps"]

    return rollout


def worker_pairs(cfg, rec):
    """float32 against float64 in pairs: float64 and float32 rollouts of the same batch in one process
    (``jax_enable_x64`` on, a float32 model and float32 states for the float32 one), timed
    one after the other ``cfg["pairs"]`` times. A virtual machine's speed drifts between
    worker processes by more than the margin the float32 target asks about; a pair shares the drift."""
    import warnings

    import diffrax
    import numpy as np

    jax = _jax_setup(True)
    import jax.numpy as jnp

    import jaxbody as jb

    m = _rigid_rk4(cfg["path"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        models = {d: jb.from_mujoco(m, dtype=d) for d in (jnp.float64, jnp.float32)}
    rollout = _simulate_rollout(jb, diffrax, cfg)
    rep = dict(min_time=cfg["min_time"], repeats=cfg["repeats"])
    rows = rec.data["batches"] = {}
    for batch in cfg["batches"]:
        nstep = n_steps(batch, cfg)
        q, v, _, _ = _states(m, batch, cfg["seed"])
        calls = {}
        row = rows[str(batch)] = {"steps_requested": nstep, "pairs": []}
        for dtype, model in models.items():
            name = jnp.dtype(dtype).name
            args = (model, jnp.asarray(q, dtype), jnp.asarray(v, dtype), jnp.asarray(nstep * DT, dtype))
            fn, row["path"] = _batched(jax, jb, rollout, batch, cfg)
            jitted, _, out, t = _compile(jax, fn, args)
            row[f"compile_{name}"] = t
            row[f"steps_{name}"] = steps = int(np.max(np.asarray(out[2])))
            row[f"finite_{name}"] = bool(np.isfinite(np.asarray(out[0])).all() and np.isfinite(np.asarray(out[1])).all())
            row[f"kernel_{name}"] = jb.backends.resolve_kernel(model, cfg.get("kernel"))
            calls[name] = (lambda f=jitted, a=args: jax.block_until_ready(f(*a))), steps
        rec.save()
        for _ in range(cfg["pairs"]):
            pair = {}
            for name, (call, steps) in calls.items():
                pair[name] = batch * steps / _common.time_per_call(call, warmup=False, **rep)["median_s"]
            pair["ratio"] = pair["float32"] / pair["float64"]
            row["pairs"].append(pair)
            rec.save()
        row["median_ratio"] = float(np.median([p["ratio"] for p in row["pairs"]]))
        rec.save()


def worker_jaxbody(cfg, rec):
    """``jb.simulate`` RK4 rollouts, jitted and batched, in one precision."""
    import warnings

    import diffrax
    import numpy as np

    x64 = cfg["dtype"] == "float64"
    jax = _jax_setup(x64)
    import jax.numpy as jnp

    import jaxbody as jb

    dtype = jnp.float64 if x64 else jnp.float32
    m = _rigid_rk4(cfg["path"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # actuators/contacts are reported and ignored
        # the MjModel MuJoCo runs (springs, dampers, gravity flags honoured), not the file:
        # from_mjcf(path) would keep the joint damping MuJoCo's rollout has switched off
        model = jb.from_mujoco(m, dtype=dtype)
    rec.data.update(dtype=cfg["dtype"], devices=[str(d) for d in jax.devices()], nq=int(m.nq), nv=int(m.nv),
                    device_kind=jax.devices()[0].device_kind, backend=jax.default_backend(),
                    kernel=jb.backends.resolve_kernel(model, cfg.get("kernel")))
    rep = dict(min_time=cfg["min_time"], repeats=cfg["repeats"])
    rollout = _simulate_rollout(jb, diffrax, cfg)

    def arrays(batch, seed):
        q, v, _, _ = _states(m, batch, seed)
        return jnp.asarray(q, dtype), jnp.asarray(v, dtype)

    # compile time of forward_dynamics and of one whole simulate, single state
    # (--single-steps 0: neither, e.g. on a GPU, where batches are what is measured)
    ns = cfg["single_steps"]
    if ns:
        q1, v1 = arrays(1, cfg["seed"])
        _, _, _, t = _compile(jax, lambda mo, q, v: jb.forward_dynamics(mo, q, v, jnp.zeros_like(v)),
                              (model, q1[0], v1[0]))
        rec.data["compile_forward_dynamics"] = t
        t1 = jnp.asarray(ns * DT, dtype)
        single_fn, _, out, t = _compile(jax, rollout, (model, q1[0], v1[0], t1))
        rec.data["single"] = {"compile": t, "steps": int(out[2])}
        rec.save()
        tm = _common.time_per_call(lambda: jax.block_until_ready(single_fn(model, q1[0], v1[0], t1)), **rep)
        rec.data["single"].update(per_step_s=tm["median_s"] / int(out[2]), timing=tm)
        rec.save()

    rows = rec.data["batches"] = {}
    for batch in cfg["batches"]:
        nstep = n_steps(batch, cfg)
        row = rows[str(batch)] = {"steps_requested": nstep}
        rec.data["running"] = batch
        rec.save()
        q, v = arrays(batch, cfg["seed"])
        tb = jnp.asarray(nstep * DT, dtype)
        fn, row["path"] = _batched(jax, jb, rollout, batch, cfg)
        try:
            jitted, compiled, out, t = _compile(jax, fn, (model, q, v, tb))
        except Exception as e:  # noqa: BLE001 - recorded, the next batch still runs
            row["error"] = f"{e.__class__.__name__}: {e}"[:800]
            rec.save()
            continue
        row["compile"] = t
        row["loop_body_ops"] = _loop_body_ops(compiled)
        steps = int(np.max(np.asarray(out[2])))
        row["steps"] = steps
        row["finite"] = bool(np.isfinite(np.asarray(out[0])).all() and np.isfinite(np.asarray(out[1])).all())
        tm = _common.time_per_call(lambda: jax.block_until_ready(jitted(model, q, v, tb)), warmup=False, **rep)
        tm["steps_per_s"] = batch * steps / tm["median_s"]
        row["run"] = tm
        rec.save()
    rec.data.pop("running", None)

    if cfg["accuracy"]:
        nacc = int(round(ACCURACY_TIME / DT))
        q, v = arrays(cfg["accuracy_states"], cfg["seed"] + 1)
        T = jnp.asarray(ACCURACY_TIME, dtype)
        f = jax.jit(jax.vmap(rollout, in_axes=(None, 0, 0, None)))
        qf, vf, st = f(model, q, v, T)
        acc = rec.data["accuracy"] = {"rk4_q": np.asarray(qf, np.float64).tolist(),
                                      "rk4_v": np.asarray(vf, np.float64).tolist(),
                                      "rk4_steps": int(np.max(np.asarray(st))), "rk4_steps_expected": nacc}

        def tsit5(model, q0, v0, tol):
            sol = jb.simulate(model, q0, v0, T, solver="tsit5", rtol=tol, atol=tol,
                              saveat=diffrax.SaveAt(t1=True), max_steps=cfg["tsit5_max_steps"], throw=False)
            return sol.q[-1], sol.v[-1], sol.stats["num_steps"], sol.result == jb.RESULTS.successful

        g = jax.jit(jax.vmap(tsit5, in_axes=(None, 0, 0, None)))
        tols = (1e-10,) if x64 else TSIT5_TOLS
        acc["tsit5"] = {}
        for tol in tols:
            qf, vf, st, ok = g(model, q, v, jnp.asarray(tol, dtype))
            acc["tsit5"][repr(tol)] = {"q": np.asarray(qf, np.float64).tolist(), "v": np.asarray(vf, np.float64).tolist(),
                                       "max_steps_taken": int(np.max(np.asarray(st))),
                                       "all_successful": bool(np.all(np.asarray(ok)))}
            rec.save()
        rec.save()


def worker_mjx(cfg, rec):
    """``jax.jit(jax.vmap(fori_loop(mjx.step)))`` at one batch size, float32."""
    import numpy as np

    try:
        from mujoco import mjx
    except ImportError as e:
        rec.data["error"] = f"mujoco-mjx not importable: {e}"
        rec.save()
        return
    jax = _jax_setup(False)
    import mujoco

    m = _rigid_rk4(cfg["path"])
    rec.data.update(integrator="RK4", dtype="float32", mjx_version=_common._version("mujoco-mjx"),
                    devices=[str(d) for d in jax.devices()], device_kind=jax.devices()[0].device_kind)
    # contacts are disabled anyway; without collision pairs MJX also accepts models whose
    # geom pairs it has no collision function for (anymal_c: cylinder-box)
    m.geom_contype[:] = 0
    m.geom_conaffinity[:] = 0
    mx = mjx.put_model(m)
    batch = cfg["batch"]
    nstep = n_steps(batch, cfg)
    q, v, _, _ = _states(m, batch, cfg["seed"])
    dx0 = mjx.make_data(mx)

    def init(q, v):
        return dx0.replace(qpos=q, qvel=v)

    dxs = jax.vmap(init)(jax.numpy.asarray(q, np.float32), jax.numpy.asarray(v, np.float32))

    def rollout(d):
        return jax.lax.fori_loop(0, nstep, lambda i, d: mjx.step(mx, d), d)

    rec.data.update(batch=batch, steps=nstep, running="compile")
    rec.save()
    jitted, compiled, out, t = _compile(jax, jax.vmap(rollout), (dxs,))
    rec.data["compile"] = t
    rec.data["loop_body_ops"] = _loop_body_ops(compiled)
    rec.data["finite"] = bool(np.isfinite(np.asarray(out.qpos)).all())
    rec.data["running"] = "run"
    rec.save()
    tm = _common.time_per_call(lambda: jax.block_until_ready(jitted(dxs)), warmup=False,
                               min_time=cfg["min_time"], repeats=cfg["repeats"])
    tm["steps_per_s"] = batch * nstep / tm["median_s"]
    rec.data["run"] = tm
    rec.data.pop("running")
    rec.save()
    del mujoco


def _loop_body_ops(compiled):
    """Operations per iteration of the compiled program's loops (:func:`_common.loop_body_ops`)."""
    try:
        return _common.loop_body_ops(compiled.as_text())
    except Exception as e:  # noqa: BLE001 - a diagnostic, never a reason to lose the timing
        return {"error": f"{e.__class__.__name__}: {e}"[:200]}


# ============================================================================ analysis
def _get(d, *keys):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _si(x):
    if x is None:
        return "—"
    for div, suf in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(x) >= div:
            return f"{x / div:.3g}{suf}"
    return f"{x:.3g}"


def steps_per_s(results, model, batch, impl):
    """System-steps/s of one cell, or None."""
    r = results["runs"].get(model, {})
    if impl in ("mj1", "mjN"):
        return _get(r, "mujoco", "batches", str(batch), impl, "steps_per_s")
    if impl == "mjx":
        return _get(r, "mjx", str(batch), "run", "steps_per_s")
    return _get(r, impl, "batches", str(batch), "run", "steps_per_s")


def cell_status(results, model, batch, impl):
    r = results["runs"].get(model, {})
    if impl == "mjx":
        w = _get(r, "mjx", str(batch))
        if w is None:
            return "not run"
        if "run" in w:
            return "ok"
        return (w.get("error") or f"{w.get('status')} during {w.get('running', '?')}")[:60]
    w = _get(r, "mujoco" if impl in ("mj1", "mjN") else impl)
    if w is None:
        return "not run"
    row = _get(w, "batches", str(batch))
    if row is None or (impl not in ("mj1", "mjN") and "run" not in row):
        err = _get(row, "error") if row else None
        return (err or (f"{w.get('status')}" if w.get("running") == batch or row is None else "missing"))[:60]
    return "ok"


def rel_state_error(a_q, a_v, b_q, b_v):
    import numpy as np

    a = np.concatenate([np.asarray(a_q), np.asarray(a_v)], axis=1)
    b = np.concatenate([np.asarray(b_q), np.asarray(b_v)], axis=1)
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


def accuracy_table(results):
    """float32 vs float64 (and MuJoCo) final-state errors after 1 s, per model."""
    out = {}
    for model, r in results["runs"].items():
        a64, a32, amj = _get(r, "jb64", "accuracy"), _get(r, "jb32", "accuracy"), _get(r, "mujoco", "accuracy")
        if not a64:
            continue
        e = out[model] = {}
        if amj:
            e["rk4_f64_vs_mujoco_rk4"] = rel_state_error(a64["rk4_q"], a64["rk4_v"], amj["rk4_q"], amj["rk4_v"])
        ref = _get(a64, "tsit5", repr(1e-10))
        if ref:
            e["rk4_f64_vs_tsit5_1e-10"] = rel_state_error(a64["rk4_q"], a64["rk4_v"], ref["q"], ref["v"])
        if a32:
            e["rk4_f32_vs_rk4_f64"] = rel_state_error(a32["rk4_q"], a32["rk4_v"], a64["rk4_q"], a64["rk4_v"])
            e["rk4_f32_steps"] = a32.get("rk4_steps")
            e["tsit5_f32"] = {}
            for tol, s in (a32.get("tsit5") or {}).items():
                e["tsit5_f32"][tol] = {
                    "error_vs_f64_tsit5_1e-10": rel_state_error(s["q"], s["v"], ref["q"], ref["v"]) if ref else None,
                    "steps": s["max_steps_taken"], "successful": s["all_successful"]}
    return out


def compute_targets(results):
    T = []
    batches = results["batches"]
    big = [b for b in batches if b >= 1024]

    def ratio_rows(model, num, den):
        return [(b, steps_per_s(results, model, b, num), steps_per_s(results, model, b, den)) for b in big]

    for model, factor in (("panda", 2.0), ("anymal_c", 1.5), ("chain20", 1.0)):
        rows = ratio_rows(model, "jb64", "mjN")
        ok_rows = [(b, x / y) for b, x, y in rows if x and y]
        if model not in results["runs"] or not big:
            verdict, detail = "NOT MEASURED", f"{model} or a batch >= 1024 not in the run"
        elif not {"jb64", "mujoco"} <= set(results["impls"]):
            verdict, detail = "NOT MEASURED", "jb64 or mujoco not in --impls"
        elif len(ok_rows) < len(rows):
            verdict = "NOT MET"
            detail = "failed/missing cells at B=" + ",".join(str(b) for b, x, y in rows if not (x and y))
        else:
            verdict = "MET" if all(r >= factor for _, r in ok_rows) else "NOT MET"
            detail = ", ".join(f"B={b}: {r:.3g}x" for b, r in ok_rows)
        T.append(dict(id="batch-vs-mujoco", target=f"{model}: jaxbody float64 RK4 rollout >= {factor}x MuJoCo rollout on all cores, B >= 1024",
                      verdict=verdict, detail=detail))
    jb = _get(results["runs"], "panda", "jb64", "single", "per_step_s")
    mj = _get(results["runs"], "panda", "mujoco", "single", "rollout_1thread_per_step_s")
    if jb and mj:
        T.append(dict(id="single-trajectory", target="panda single trajectory: jitted jb.simulate RK4 step <= 2x mj_step (RK4)",
                      verdict="MET" if jb / mj <= 2 else "NOT MET",
                      detail=f"{jb * 1e6:.3g} us vs {mj * 1e6:.3g} us per step: {jb / mj:.3g}x"))
    else:
        T.append(dict(id="single-trajectory", target="panda single trajectory <= 2x mj_step", verdict="NOT MEASURED", detail="panda not in the run or failed"))
    for what, keys in (("forward_dynamics", ("compile_forward_dynamics", "compile_total_s")),
                       ("simulate (single trajectory)", ("single", "compile", "compile_total_s"))):
        c100 = _get(results["runs"], "chain100", "jb64", *keys)
        c2 = _get(results["runs"], "chain2", "jb64", *keys)
        if c100 and c2:
            T.append(dict(id="compile-scaling", target=f"compile time of {what}: chain100 within 2x of chain2",
                          verdict="MET" if c100 / c2 <= 2 else "NOT MET",
                          detail=f"{c100:.3g} s vs {c2:.3g} s: {c100 / c2:.3g}x"))
        else:
            T.append(dict(id="compile-scaling", target=f"compile time of {what}: chain100 within 2x of chain2",
                          verdict="NOT MEASURED", detail="chain2 or chain100 missing"))
    if 65536 in batches:
        bad = [m for m in results["runs"] if cell_status(results, m, 65536, "jb64") != "ok"]
        if "jb64" not in results["impls"]:
            T.append(dict(id="batch-65536", target="batches of 65536 complete for every model (float64)",
                          verdict="NOT MEASURED", detail="jb64 not in --impls"))
        else:
            T.append(dict(id="batch-65536", target="batches of 65536 complete for every model (float64)",
                          verdict="MET" if not bad else "NOT MET",
                          detail="failed: " + ", ".join(bad) if bad else "all complete"))
    else:
        T.append(dict(id="batch-65536", target="batches of 65536 complete for every model", verdict="NOT MEASURED",
                      detail="65536 not in --batches"))
    rows = [(m, b, steps_per_s(results, m, b, "jb32"), steps_per_s(results, m, b, "jb64"))
            for m in results["runs"] for b in big]
    ok_rows = [(m, b, x / y) for m, b, x, y in rows if x and y]
    skipped = {(m, b) for m, b in results.get("skip", [])}
    paired = [(m, b, _get(results["runs"], m, "pairs", "batches", str(b), "median_ratio"))
              for m in results["runs"] for b in big if results.get("float32_pairs") and (m, b) not in skipped]
    if paired:
        ok = [(m, b, r) for m, b, r in paired if r]
        sep = {(m, b): r for m, b, r in ok_rows}
        T.append(dict(id="float32-speed", target=f"float32 throughput >= 1.8x float64 (B >= 1024; median of {results['float32_pairs']} "
                                      "interleaved pairs in one process)",
                      verdict="MET" if ok and len(ok) == len(paired) and all(r >= 1.8 for *_, r in ok) else "NOT MET",
                      detail="; ".join(f"{m} B={b}: {r:.3g}x" + (f" (separate workers {sep[m, b]:.3g}x)" if (m, b) in sep else "")
                                       for m, b, r in ok) + ("; failed: " + ", ".join(f"{m} B={b}" for m, b, r in paired if not r)
                                                             if len(ok) < len(paired) else "")))
    elif ok_rows:
        T.append(dict(id="float32-speed", target="float32 throughput >= 1.8x float64 (B >= 1024)",
                      verdict="MET" if all(r >= 1.8 for *_, r in ok_rows) and len(ok_rows) == len(rows) else "NOT MET",
                      detail="; ".join(f"{m} B={b}: {r:.3g}x" for m, b, r in ok_rows)))
    else:
        T.append(dict(id="float32-speed", target="float32 throughput >= 1.8x float64", verdict="NOT MEASURED", detail="no float32/float64 pair"))
    gpu = [d for d in (_get(results["runs"], "panda", impl, "device_kind") for impl in ("jb32", "jb64"))
           if d and _get(results["runs"], "panda", "jb32", "backend") == "gpu"]
    if gpu:
        rows = [(impl, b, steps_per_s(results, "panda", b, impl)) for impl in ("jb32", "jb64") for b in batches]
        best = max(((impl, b, x) for impl, b, x in rows if x), key=lambda r: r[2], default=None)
        mjx = {b: steps_per_s(results, "panda", b, "mjx") for b in batches}
        pairs = [(b, steps_per_s(results, "panda", b, "jb32"), mjx[b]) for b in batches]
        pairs = [(b, x / y) for b, x, y in pairs if x and y]
        T.append(dict(id="GPU", target=f"panda RK4 >= 1e7 steps/s on the GPU ({gpu[0]})",
                      verdict="NOT MEASURED" if best is None else ("MET" if best[2] >= 1e7 else "NOT MET"),
                      detail="—" if best is None else f"best {best[2]:.3g} steps/s ({best[0]}, B={best[1]})"))
        T.append(dict(id="GPU", target="jaxbody float32 >= 10x MJX (float32) on the same GPU, panda",
                      verdict="NOT MEASURED" if not pairs else ("MET" if all(r >= 10 for _, r in pairs) else "NOT MET"),
                      detail=", ".join(f"B={b}: {r:.3g}x" for b, r in pairs) or "no batch with both"))
    acc = results.get("accuracy", {})
    errs = {m: a["rk4_f32_vs_rk4_f64"] for m, a in acc.items() if "rk4_f32_vs_rk4_f64" in a}
    if errs:
        T.append(dict(id="float32-accuracy", target="float32 within 1e-4 of float64 (final state after 1 s, RK4 dt=1e-3, relative to max |state|)",
                      verdict="MET" if all(e <= 1e-4 for e in errs.values()) else "NOT MET",
                      detail=", ".join(f"{m}: {e:.2g}" for m, e in errs.items())))
    return T


# ============================================================================ output
def write_markdown(results, path):
    s = results["stamp"]
    impls = [i for i in ("jb64", "jb32", "mj1", "mjN", "mjx")
             if (i[:2] == "mj" and i != "mjx" and "mujoco" in results["impls"]) or i in results["impls"]]
    L = [f"# RK4 rollout throughput: jaxbody `jb.simulate` vs MuJoCo `rollout` vs MJX", "", _common.stamp_markdown(s),
         f"- wall time: {s.get('wall_s', 0):.0f} s; MuJoCo threads (all cores): {results['threads']}; "
         f"jaxbody chunk {results['chunk']}, devices {results['devices']}, kernel {results.get('kernel') or 'default (vectorised)'}", ""]
    if results.get("note"):
        L += [f"**Note.** {results['note']}", ""]
    L += ["System-steps/s (batch × steps / wall time of one rollout call), RK4, dt = 1e-3, rigid-body "
          "dynamics only (MuJoCo: contacts, constraints, limits, actuation, springs, dampers off; timer "
          "callback off). jaxbody: the public `jb.simulate(..., solver=\"rk4\")`, jitted and vmapped "
          "(`jb.vmap_chunked` above the chunk size). Steps per call shrink for big batches "
          "(`--max-work`); the `steps` column gives them. Compile = trace + lower + XLA compile.", ""]
    hdr = ["model", "batch", "steps"] + [LABEL[i] + " /s" for i in impls] + \
          ["jb64 / mj all", "jb32 / mj all", "jb32 / jb64", "jb64 compile s", "jb32 compile s", "MJX compile s"]
    rows = []
    for model in results["models"]:
        r = results["runs"].get(model, {})
        for b in results["batches"]:
            vals = {i: steps_per_s(results, model, b, i) for i in impls}
            cells = [_si(vals[i]) if vals[i] else cell_status(results, model, b, i) for i in impls]

            def ratio(x, y):
                return f"{x / y:.3g}" if x and y else "—"

            steps = (_get(r, "mujoco", "batches", str(b), "steps") or _get(r, "jb64", "batches", str(b), "steps")
                     or _get(r, "jb32", "batches", str(b), "steps"))
            c64 = _get(r, "jb64", "batches", str(b), "compile", "compile_total_s")
            c32 = _get(r, "jb32", "batches", str(b), "compile", "compile_total_s")
            cx = _get(r, "mjx", str(b), "compile", "compile_total_s")
            rows.append([model, b, steps, *cells,
                         ratio(vals.get("jb64"), vals.get("mjN")), ratio(vals.get("jb32"), vals.get("mjN")),
                         ratio(vals.get("jb32"), vals.get("jb64")),
                         f"{c64:.3g}" if c64 else "—", f"{c32:.3g}" if c32 else "—", f"{cx:.3g}" if cx else "—"])
    L += [_common.markdown_table(hdr, rows), ""]

    ran_on = sorted({f"{impl} on {_get(r, impl, 'device_kind')} ({_get(r, impl, 'backend')}), kernel "
                     f"{_get(r, impl, 'kernel')}" for r in results["runs"].values() for impl in ("jb64", "jb32")
                     if _get(r, impl, "device_kind")})
    mjx_on = sorted({str(_get(w, "device_kind")) for r in results["runs"].values()
                     for w in (r.get("mjx") or {}).values() if _get(w, "device_kind")})
    if ran_on or mjx_on:
        L += ["Where it ran: " + "; ".join(ran_on + [f"MJX on {d}" for d in mjx_on]) + ".", ""]
    if not results["single_steps"]:
        L += ["Single trajectory and compile of one state: not in this run (`--single-steps 0`).", ""]
    else:
        L += _single_section(results)
    return _finish_markdown(results, path, L)


def _single_section(results):
    L = []
    L += ["## Single trajectory and compile times", "",
          f"Unbatched `jax.jit` of `jb.simulate` over {results['single_steps']} RK4 steps, per step; MuJoCo "
          "`mj_step` (RK4) in a C loop (`rollout`, 1 thread, one trajectory) and from a Python loop.", ""]
    rows = []
    for model in results["models"]:
        r = results["runs"].get(model, {})
        jb64, jb32 = _get(r, "jb64", "single", "per_step_s"), _get(r, "jb32", "single", "per_step_s")
        mjc, mjp = _get(r, "mujoco", "single", "rollout_1thread_per_step_s"), _get(r, "mujoco", "single", "python_mj_step_per_step_s")
        us = lambda x: f"{x * 1e6:.3g}" if x else "—"
        rows.append([model, _get(r, "jb64", "nv") or _get(r, "mujoco", "nv"), us(jb64), us(jb32), us(mjc), us(mjp),
                     f"{jb64 / mjc:.3g}" if jb64 and mjc else "—",
                     *(f"{x:.3g}" if x else "—" for x in (
                         _get(r, "jb64", "compile_forward_dynamics", "compile_total_s"),
                         _get(r, "jb64", "single", "compile", "compile_total_s"),
                         _get(r, "jb32", "single", "compile", "compile_total_s")))])
    L += [_common.markdown_table(["model", "nv", "jb64 µs/step", "jb32 µs/step", "mj_step C µs", "mj_step Python µs",
                                  "jb64 / mj_step C", "jb64 compile FD s", "jb64 compile simulate s",
                                  "jb32 compile simulate s"], rows), ""]
    return L


def _finish_markdown(results, path, L):
    acc = results.get("accuracy", {})
    if acc:
        L += ["## float32 against float64 (after 1 s)", "",
              "Relative error max|x − x_ref| / max|x_ref| of the final state x = (q, v) after 1 s from "
              f"{results['accuracy_states']} random states. RK4 at dt = 1e-3 in float32 against the same in "
              "float64; float64 RK4 against MuJoCo's RK4 (same method, a check of the harness) and against "
              "float64 `tsit5` at rtol = atol = 1e-10; float32 `tsit5` at several tolerances against that "
              "reference (steps taken, whether every solve succeeded).", ""]
        rows = []
        for m, a in acc.items():
            ts = a.get("tsit5_f32", {})
            rows.append([m, *(f"{a[k]:.2g}" if a.get(k) is not None else "—" for k in
                              ("rk4_f32_vs_rk4_f64", "rk4_f64_vs_mujoco_rk4", "rk4_f64_vs_tsit5_1e-10")),
                         *(f"{t['error_vs_f64_tsit5_1e-10']:.2g} ({t['steps']} steps{'' if t['successful'] else ', FAILED'})"
                           if t.get("error_vs_f64_tsit5_1e-10") is not None else "—"
                           for t in (ts.get(repr(tol), {}) for tol in TSIT5_TOLS))])
        L += [_common.markdown_table(["model", "RK4 f32 vs f64", "RK4 f64 vs MuJoCo RK4", "RK4 f64 vs tsit5 1e-10",
                                      *(f"tsit5 f32 tol {tol:g}" for tol in TSIT5_TOLS)], rows), ""]

    pair_rows = []
    for m, r in results["runs"].items():
        for b, row in sorted(((int(b), x) for b, x in (_get(r, "pairs", "batches") or {}).items())):
            pairs = row.get("pairs") or []
            if pairs:
                pair_rows.append([m, b, row.get("steps_float64"), _si(statistics.median(p["float64"] for p in pairs)),
                                  _si(statistics.median(p["float32"] for p in pairs)),
                                  " ".join(f"{p['ratio']:.2f}" for p in pairs), f"{row['median_ratio']:.3g}"])
    if pair_rows:
        L += ["## float32 against float64 in pairs", "",
              "One process (`jax_enable_x64` on; a float32 model and float32 states for the float32 rollouts) "
              "compiles both rollouts of a batch, then times float64 and float32 one after the other, "
              f"{results['float32_pairs']} times (`--float32-pairs`): the drift of a virtual machine's speed between "
              "the separate workers above moves their ratio by more than the float32 target's margin. System-steps/s are "
              "medians over the pairs.", "",
              _common.markdown_table(["model", "batch", "steps", "float64 /s", "float32 /s", "pair ratios f32/f64", "median"],
                                     pair_rows), ""]
    L += ["## Targets", "", _common.markdown_table(
        ["id", "target", "verdict", "measured"], [[t["id"], t["target"], t["verdict"], t["detail"]] for t in results["targets"]]), ""]
    fails = []
    for model, r in results["runs"].items():
        for impl, w in r.items():
            ws = w.values() if impl == "mjx" else [w]
            for x in ws:
                if isinstance(x, dict) and x.get("status") not in ("ok", None):
                    fails.append([model, impl, x.get("status"), (x.get("stderr_tail") or "").strip().splitlines()[-1:] or ""])
    if fails:
        L += ["## Workers that did not finish", "", _common.markdown_table(["model", "implementation", "status", "last stderr line"],
                                                                           [[a, b, c, " ".join(d)[:200]] for a, b, c, d in fails]), ""]
    path.write_text("\n".join(L))


def write_plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = [m for m in results["models"] if m in results["runs"]]
    if not models:
        return False
    ncol = min(4, len(models))
    nrow = math.ceil(len(models) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.6 * nrow), squeeze=False)
    styles = {"jb64": dict(color="C0", marker="o", lw=2), "jb32": dict(color="C0", marker="o", ls=":"),
              "mj1": dict(color="C3", marker="s", ls="--"), "mjN": dict(color="C1", marker="s", ls="--"),
              "mjx": dict(color="C2", marker="^", ls="-.")}
    for ax, model in zip(axes.flat, models):
        for impl, st in styles.items():
            pts = [(b, steps_per_s(results, model, b, impl)) for b in results["batches"]]
            pts = [(b, y) for b, y in pts if y]
            if pts:
                ax.plot(*zip(*pts), label=LABEL[impl], **st)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(model)
        ax.set_xlabel("batch size")
        ax.set_ylabel("system-steps / s (RK4)")
        ax.grid(True, which="both", alpha=0.3)
    _common.shared_legend(fig, axes, len(models), ncol=5, fontsize=8, frameon=False)
    s = results["stamp"]
    fig.suptitle(f"RK4 rollout throughput, commit {s['commit']}{' (dirty)' if s.get('dirty') else ''}, "
                 f"{s['cpu']} x{s['cores']}, load {s['load_average_start']}, jax {s['versions']['jax']}, "
                 f"mujoco {s['versions']['mujoco']}, {s['date']}", fontsize=8)
    fig.tight_layout(rect=(0, 0.08, 1, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


# ============================================================================ driver
def write_records(results, args, t_start):
    """Analyse and write md/json/png (after every model, so a killed run leaves a record)."""
    stamp = results["stamp"]
    stamp["load_average_end"] = _common.load_average()
    stamp["wall_s"] = time.perf_counter() - t_start
    results["accuracy"] = accuracy_table(results)
    results["targets"] = compute_targets(results)
    md, js, png = (args.out / f"{args.name}.{ext}" for ext in ("md", "json", "png"))
    js.write_text(json.dumps(results, indent=1, default=str))
    write_markdown(results, md)
    plotted = write_plot(results, png)
    return md, js, png, plotted


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default=",".join(DEFAULT_MODELS),
                   help=f"comma-separated: {', '.join(MENAGERIE)}, chainN, double_pendulum (= chain2)")
    p.add_argument("--batches", default=",".join(map(str, DEFAULT_BATCHES)), help="comma-separated batch sizes")
    p.add_argument("--skip", default="", help="model:batch pairs not to run for jaxbody/MJX, e.g. chain100:65536")
    p.add_argument("--impls", default=",".join(IMPLS), help=f"comma-separated subset of {', '.join(IMPLS)}")
    p.add_argument("--mjx-batches", help="batches for MJX (default: --batches)")
    p.add_argument("--mjx-models", help="models for MJX (default: --models)")
    p.add_argument("--steps", type=int, default=100, help="RK4 steps per timed rollout (default 100)")
    p.add_argument("--min-steps", type=int, default=10, help="fewest steps per timed rollout (default 10)")
    p.add_argument("--max-work", type=int, default=200_000,
                   help="cap batch x steps of a timed call: steps = max(min_steps, min(steps, max_work // batch))")
    p.add_argument("--single-steps", type=int, default=1000,
                   help="steps of the single-trajectory timing ; 0 skips it and the compile timings")
    p.add_argument("--kernel", choices=("auto", "native", "unrolled", "vectorised"),
                   help="forward-dynamics kernel of the jaxbody runs: jb.simulate(jb.scene(model, kernel=KERNEL), ...); "
                        "default: the model itself (jaxbody.backends.DEFAULT_KERNEL)")
    p.add_argument("--chunk", type=int, default=256, help="batches above this run through jb.vmap_chunked(.., CHUNK)")
    p.add_argument("--devices", type=int, default=_common.core_count(),
                   help="CPU devices jb.vmap_chunked splits big batches over (sets "
                        "--xla_force_host_platform_device_count for the jaxbody workers; default: cores)")
    p.add_argument("--threads", type=int, default=_common.core_count(), help="MuJoCo 'all cores' thread count")
    p.add_argument("--float32-pairs", dest="float32_pairs", metavar="N", type=int, default=0,
                   help="also time float64 and float32 one after the other in one process, this many pairs per "
                        "model and batch >= 1024 (the float32 speed target then reads the median pair ratio; default 0: separate workers only)")
    # the flag's earlier spelling, which the commands stamped in older records use
    p.add_argument("--t5-pairs", dest="float32_pairs", type=int, help=argparse.SUPPRESS)
    p.add_argument("--no-accuracy", action="store_true", help="skip the float32/float64 accuracy runs")
    p.add_argument("--accuracy-models", default="panda,chain20", help="models of the accuracy runs")
    p.add_argument("--accuracy-states", type=int, default=4)
    p.add_argument("--min-time", type=float, default=0.3, help="seconds per timing (see _common.time_per_call)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per jaxbody/MuJoCo worker (all batches)")
    p.add_argument("--mjx-timeout", type=float, default=300.0, help="seconds per MJX worker (one batch)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--note", default="", help="free text written into the record (e.g. machine load)")
    p.add_argument("--models-dir", type=pathlib.Path, default=_common.REPO / "jaxbody" / "models")
    p.add_argument("--out", type=pathlib.Path, default=_common.RESULTS)
    p.add_argument("--name", default="throughput", help="results file stem")
    p.add_argument("--rerender", type=pathlib.Path,
                   help="re-analyse a record's JSON (e.g. one made on another machine) and rewrite its md/png "
                        "(and JSON) under --out/--name; nothing is measured, the stamp is kept")
    p.add_argument("--worker", choices=("mujoco", "jaxbody", "mjx", "pairs"), help=argparse.SUPPRESS)
    p.add_argument("--config", help=argparse.SUPPRESS)
    p.add_argument("--result", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker or args.rerender:
        return args
    split = lambda s: [x.strip() for x in s.split(",") if x.strip()]
    args.models = split(args.models)
    args.batches = sorted({int(b) for b in split(args.batches)})
    args.mjx_batches = sorted({int(b) for b in split(args.mjx_batches)}) if args.mjx_batches else args.batches
    args.mjx_models = split(args.mjx_models) if args.mjx_models else args.models
    args.impls = split(args.impls)
    bad = [i for i in args.impls if i not in IMPLS]
    if bad:
        p.error(f"unknown implementation(s) {bad}; choose from {IMPLS}")
    args.skip = {(m, int(b)) for m, b in (x.split(":") for x in split(args.skip))}
    args.accuracy_models = set(split(args.accuracy_models)) if not args.no_accuracy else set()
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.worker:
        rec = _Record(args.result)
        workers = {"mujoco": worker_mujoco, "jaxbody": worker_jaxbody, "mjx": worker_mjx, "pairs": worker_pairs}
        workers[args.worker](json.loads(args.config), rec)
        return 0
    if args.rerender:
        results = json.loads(args.rerender.read_text())
        if "t5_pairs" in results:  # the key's earlier name, in records made before it was renamed
            results["float32_pairs"] = results.pop("t5_pairs")
        results["accuracy"] = accuracy_table(results)
        results["targets"] = compute_targets(results)
        args.out.mkdir(parents=True, exist_ok=True)
        md, js, png = (args.out / f"{args.name}.{ext}" for ext in ("md", "json", "png"))
        js.write_text(json.dumps(results, indent=1, default=str))
        write_markdown(results, md)
        write_plot(results, png)
        print(f"wrote {md}, {js}, {png}")
        return 0

    env = dict(os.environ)
    if XLA_DEFAULT_FLAG and XLA_DEFAULT_FLAG not in env.get("XLA_FLAGS", ""):
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + XLA_DEFAULT_FLAG).strip()
    env_jb = dict(env)
    if args.devices > 1:
        env_jb["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={args.devices}").strip()
    os.environ["XLA_FLAGS"] = env_jb.get("XLA_FLAGS", "")  # what the jaxbody workers get, for the stamp
    stamp = _common.stamp(sys.argv if argv is None else [sys.argv[0], *argv])
    args.out.mkdir(parents=True, exist_ok=True)
    results = {"stamp": stamp, "models": args.models, "batches": args.batches, "impls": args.impls,
               "mjx_batches": args.mjx_batches, "threads": args.threads, "chunk": args.chunk, "devices": args.devices,
               "kernel": args.kernel,
               "steps": args.steps, "max_work": args.max_work, "single_steps": args.single_steps, "dt": DT,
               "accuracy_states": args.accuracy_states, "skip": sorted(map(list, args.skip)), "note": args.note,
               "float32_pairs": args.float32_pairs,
               "runs": {}}
    t_start = time.perf_counter()
    me = str(pathlib.Path(__file__).resolve())

    def log(msg):
        print(f"[{time.perf_counter() - t_start:6.0f}s load {_common.load_average()}] {msg}", flush=True)

    with tempfile.TemporaryDirectory(prefix="jaxbody-throughput-") as tmp:
        tmp = pathlib.Path(tmp)
        for model in args.models:
            path = model_path(model, args.models_dir, tmp)
            runs = results["runs"][model] = {}
            base = dict(model=model, path=str(path), min_time=args.min_time, repeats=args.repeats, seed=args.seed,
                        steps=args.steps, min_steps=args.min_steps, max_work=args.max_work,
                        single_steps=args.single_steps, threads=args.threads, chunk=args.chunk,
                        devices=args.devices, kernel=args.kernel, accuracy=model in args.accuracy_models,
                        accuracy_states=args.accuracy_states, max_steps=max(args.steps, args.single_steps, 1000) + 16,
                        tsit5_max_steps=20_000)
            batches = [b for b in args.batches if (model, b) not in args.skip]

            def go(kind, cfg, timeout, e, tag):
                rf = tmp / f"{model}-{tag}.json"
                cmd = [sys.executable, me, "--worker", kind, "--config", json.dumps(cfg), "--result", str(rf)]
                return _common.run_worker(cmd, timeout=timeout, result_file=rf, env=e)

            for impl in args.impls:  # in the order given: the first ones matter most when time is short
                if impl == "mujoco":
                    r = runs["mujoco"] = go("mujoco", dict(base, batches=args.batches), args.timeout, env, "mujoco")
                    log(f"{model} MuJoCo ({r['status']}): " + ", ".join(
                        f"B={b} 1T {_si(_get(r, 'batches', str(b), 'mj1', 'steps_per_s'))} "
                        f"NT {_si(_get(r, 'batches', str(b), 'mjN', 'steps_per_s'))}" for b in args.batches))
                elif impl in ("jb64", "jb32"):
                    dtype = {"jb64": "float64", "jb32": "float32"}[impl]
                    r = runs[impl] = go("jaxbody", dict(base, batches=batches, dtype=dtype), args.timeout, env_jb, impl)
                    log(f"{model} {impl} ({r['status']}): single {_get(r, 'single', 'per_step_s')} s/step, " + ", ".join(
                        f"B={b} {_si(_get(r, 'batches', str(b), 'run', 'steps_per_s'))}" for b in batches))
                elif impl == "mjx" and model in args.mjx_models:
                    runs["mjx"] = {}
                    for b in args.mjx_batches:
                        if (model, b) in args.skip:
                            continue
                        r = runs["mjx"][str(b)] = go("mjx", dict(base, batch=b), args.mjx_timeout, env, f"mjx-{b}")
                        log(f"mjx {model} B={b} ({r['status']}): compile {_get(r, 'compile', 'compile_total_s')} s, "
                            f"{_si(_get(r, 'run', 'steps_per_s'))} steps/s")
                        if r["status"] == "timeout":
                            break  # a bigger batch will not compile faster
                write_records(results, args, t_start)  # after each worker: a run cut short keeps what it has
            big = [b for b in batches if b >= 1024]
            if args.float32_pairs and big:
                r = runs["pairs"] = go("pairs", dict(base, batches=big, pairs=args.float32_pairs), args.timeout, env_jb, "pairs")
                log(f"{model} float32/float64 pairs ({r['status']}): " + ", ".join(
                    f"B={b} median {_get(r, 'batches', str(b), 'median_ratio') or float('nan'):.3g}x" for b in big))
            write_records(results, args, t_start)

    md, js, png, plotted = write_records(results, args, t_start)
    print("\nTargets:")
    for t in results["targets"]:
        print(f"  {t['id']} {t['verdict']}: {t['target']}\n      {t['detail']}")
    print(f"\nwrote {md}, {js}" + (f", {png}" if plotted else "") + f" in {stamp['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
