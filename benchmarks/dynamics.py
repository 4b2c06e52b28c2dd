"""How fast are jaxbody's joint-space dynamics on CPU, next to MuJoCo (and Pinocchio)?

For each model (menagerie panda / ur5e / anymal_c and generated hinge chains ``chainN``)
this measures, in isolated worker processes:

* compile time of the jitted ``mass_matrix``, ``inverse_dynamics`` and
  ``forward_dynamics`` (trace, lower and XLA compile, separately from run time);
* warm per-call time for one state (median of repeats, ``block_until_ready``);
* ``vmap`` throughput (states/s) at each batch size, one worker process per
  (model, batch) with a timeout, so that a deadlock or an out-of-memory is recorded as
  such instead of hanging the benchmark;
* the same work in MuJoCo on the same MJCF (rigid-body dynamics only: contacts,
  constraints, actuation, springs and dampers disabled): ``mj_makeM + mj_fullM``,
  ``mj_inverse`` and ``mj_forward`` one state at a time on one thread, and
  ``mujoco.batch.Batch.forward`` (``mj_forward`` over the batch in C, on 1 thread and on
  all cores) and one-step ``mujoco.rollout`` (``mj_step``, all cores);
* Pinocchio ``crba``/``rnea``/``aba`` when ``import pinocchio`` works (optional).

Ratios and the targets are computed from numbers of the same run. Results go to
``benchmarks/results/dynamics.{md,json,png}`` stamped with commit, machine, versions,
date and command line. See ``benchmarks/README.md``.

Usage::

    .venv/bin/python benchmarks/dynamics.py            # full run (about 11 min on 2 busy cores)
    .venv/bin/python benchmarks/dynamics.py --quick    # harness check (3-6 min), dynamics_quick.*
    .venv/bin/python benchmarks/dynamics.py --models panda,chain20 --batches 1024,8192 --huge
"""

import argparse
import json
import math
import os
import pathlib
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _common  # noqa: E402

FUNCTIONS = ("mass_matrix", "inverse_dynamics", "forward_dynamics")
MENAGERIE = ("panda", "ur5e", "anymal_c")
DEFAULT_MODELS = ("panda", "anymal_c", "chain2", "chain7", "chain20", "chain50", "chain100")
QUICK_MODELS = ("panda", "chain2", "chain20", "chain100")
DEFAULT_BATCHES = (1, 64, 1024, 8192)
QUICK_BATCHES = (1, 64, 1024)
HUGE_BATCH = 65536
XLA_DEFAULT_FLAG = _common.DEFAULT_XLA_FLAGS  # "" on jaxlib >= 0.11 (jaxbody/_xla.py)
# a batch whose compiled executable needs more than this fraction of the available memory
# is not run (it would swap or be killed, and other people share the machine)
MEMORY_FRACTION = 0.6


# ============================================================================ models
def chain_mjcf(n: int) -> str:
    """An ``n``-link hinge chain hanging from the world, axes alternating y / x.

    Links are 0.3 m apart with an off-axis centre of mass and a full 3-D inertia, so the
    mass matrix is dense and every term of the dynamics is exercised. No geoms: MuJoCo
    and jaxbody both see the explicit inertials only.
    """
    body = []
    for i in range(n):
        axis = "0 1 0" if i % 2 == 0 else "1 0 0"
        pos = "0 0 0" if i == 0 else "0 0 -0.3"
        body.append(
            f'<body name="link{i}" pos="{pos}">'
            f'<joint name="joint{i}" type="hinge" axis="{axis}" armature="0.01"/>'
            f'<inertial pos="0.01 0.005 -0.15" mass="{1.0 + 0.1 * (i % 3):.1f}" '
            f'fullinertia="0.008 0.0075 0.001 0.0001 0.0002 0.0003"/>'
        )
    return (
        f'<mujoco model="chain{n}">\n  <option timestep="0.002"/>\n  <worldbody>\n    '
        + "\n    ".join(body)
        + "\n    "
        + "</body>" * n
        + "\n  </worldbody>\n</mujoco>\n"
    )


def model_path(name: str, models_dir: pathlib.Path, chain_dir: pathlib.Path) -> pathlib.Path:
    """Path of the MJCF of ``name``; chains are generated into ``chain_dir``."""
    if name in MENAGERIE:
        p = models_dir / f"{name}.xml"
        if not p.exists():
            raise SystemExit(f"model {name!r}: {p} does not exist (see --models-dir)")
        return p
    if name.startswith("chain") and name[5:].isdigit() and int(name[5:]) >= 1:
        p = chain_dir / f"{name}.xml"
        if not p.exists():
            p.write_text(chain_mjcf(int(name[5:])))
        return p
    raise SystemExit(f"unknown model {name!r}: use one of {MENAGERIE} or chainN (N >= 1)")


# ============================================================================ worker side
class _Record:
    """The worker's result, rewritten atomically after every measurement."""

    def __init__(self, path):
        self.path = pathlib.Path(path)
        self.data = {}

    def save(self):
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.data, indent=1, default=str))
        os.replace(tmp, self.path)


def _mujoco_rigid(path):
    """MuJoCo model of ``path`` doing rigid-body work only (as jaxbody's dynamics)."""
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(path))
    D = mujoco.mjtDisableBit
    m.opt.disableflags = int(m.opt.disableflags) | int(
        D.mjDSBL_CONSTRAINT | D.mjDSBL_CONTACT | D.mjDSBL_EQUALITY | D.mjDSBL_LIMIT
        | D.mjDSBL_FRICTIONLOSS | D.mjDSBL_ACTUATION | D.mjDSBL_SPRING | D.mjDSBL_DAMPER
        | D.mjDSBL_SENSOR
    )
    m.opt.enableflags = 0
    return m


def _states(m, n, seed):
    """``n`` random states (q with unit quaternions, v, a, tau) as float64 NumPy arrays."""
    import mujoco
    import numpy as np

    rng = np.random.default_rng(seed)
    q = np.tile(m.qpos0, (n, 1)) + rng.uniform(-0.6, 0.6, (n, m.nq))
    free, ball = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)
    for j in range(m.njnt):
        kind, adr = int(m.jnt_type[j]), int(m.jnt_qposadr[j])  # (NumPy ints do not compare to the enum)
        if kind == free:
            adr += 3
        if kind in (free, ball):
            quat = rng.normal(size=(n, 4))
            q[:, adr : adr + 4] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    v = rng.uniform(-1.0, 1.0, (n, m.nv))
    a = rng.uniform(-1.0, 1.0, (n, m.nv))
    tau = rng.uniform(-1.0, 1.0, (n, m.nv))
    return q, v, a, tau


def _jax_setup(cfg):
    import jax

    jax.config.update("jax_enable_x64", not cfg["float32"])
    # one-time XLA/LLVM start-up cost must not land in the first measured compile
    jax.jit(lambda x: x * 2.0 + 1.0)(jax.numpy.ones(3)).block_until_ready()
    return jax


def _load_jaxbody(path):
    import warnings

    import jaxbody as jb

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # actuators/contacts are reported and ignored
        return jb.from_mjcf(str(path))


def _jaxbody_fn(name):
    import jaxbody as jb

    if name == "mass_matrix":
        return lambda model, q, v, a, tau: jb.mass_matrix(model, q)
    if name == "inverse_dynamics":
        return lambda model, q, v, a, tau: jb.inverse_dynamics(model, q, v, a)
    return lambda model, q, v, a, tau: jb.forward_dynamics(model, q, v, tau)


def _compile(jax, fn, args):
    """Trace, lower and compile ``jax.jit(fn)`` ahead of time, then its first run.

    The AOT compile fills the jitted function's own cache, so the returned ``jitted`` is
    called through JAX's fast C++ dispatch afterwards (a ``Compiled`` object's Python call
    path is several times slower per call and would blur single-state timings).
    """
    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    traced = jitted.trace(*args)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    compiled = lowered.compile()
    t3 = time.perf_counter()
    out = jitted(*args)
    jax.block_until_ready(out)
    t4 = time.perf_counter()
    times = {
        "trace_s": t1 - t0,
        "lower_s": t2 - t1,
        "compile_s": t3 - t2,
        "compile_total_s": t3 - t0,  # the first call incl. tracing, without its run
        "first_call_s": t4 - t0,
    }
    return jitted, compiled, out, times


def _rel(x, ref):
    import numpy as np

    x, ref = np.asarray(x, np.float64), np.asarray(ref, np.float64)
    return float(np.max(np.abs(x - ref)) / max(np.max(np.abs(ref)), 1e-300))


def _mujoco_timer_check(mujoco, m, d, cfg):
    """Is a timer callback installed, and what does one cost? Leaves none installed."""
    before = mujoco.get_mjcb_time()
    out = {"mjcb_time_at_start": None if before is None else repr(before)}
    mujoco.set_mjcb_time(None)
    out["mjcb_time_after_reset"] = mujoco.get_mjcb_time()
    short = dict(min_time=min(cfg["min_time"], 0.1), repeats=3)
    mujoco.set_mjcb_time(time.perf_counter)  # what an installed Python timer costs
    try:
        with_cb = _common.time_per_call(lambda: mujoco.mj_forward(m, d), **short)["median_s"]
    finally:
        mujoco.set_mjcb_time(None)
    without = _common.time_per_call(lambda: mujoco.mj_forward(m, d), **short)["median_s"]
    out.update(
        mj_forward_with_python_timer_s=with_cb,
        mj_forward_without_timer_s=without,
        slowdown_with_timer=with_cb / without,
    )
    return out


def _pinocchio_single(path, m, state, cfg, M_ref, bias_ref):
    """Pinocchio crba/rnea/aba per call, or why it was skipped."""
    try:
        import pinocchio as pin
    except Exception as e:  # noqa: BLE001 - any import failure means "absent"
        return {"available": False, "reason": f"import pinocchio failed: {e.__class__.__name__}: {e}"}
    import mujoco
    import numpy as np

    try:
        pm = pin.buildModelFromMJCF(str(path))
    except Exception as e:  # noqa: BLE001
        return {"available": True, "error": f"buildModelFromMJCF: {e}"}
    q, v, a, tau = (np.asarray(x, np.float64) for x in state)
    if pm.nq != m.nq or pm.nv != m.nv:
        return {"available": True, "error": f"nq/nv {pm.nq}/{pm.nv} != MuJoCo {m.nq}/{m.nv}"}
    # Pinocchio quaternions are (x, y, z, w); MuJoCo's (w, x, y, z)
    qp = q.copy()
    free = False
    kinds = (int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL))
    for j in range(m.njnt):
        t = int(m.jnt_type[j])
        adr = int(m.jnt_qposadr[j]) + (3 if t == kinds[0] else 0)
        if t in kinds:
            qp[adr : adr + 4] = q[[adr + 1, adr + 2, adr + 3, adr]]
            free = True
    pd = pm.createData()
    out = {"available": True, "version": pin.__version__}
    rep = dict(min_time=cfg["min_time"], repeats=cfg["repeats"])
    out["crba"] = _common.time_per_call(lambda: pin.crba(pm, pd, qp), **rep)
    out["rnea"] = _common.time_per_call(lambda: pin.rnea(pm, pd, qp, v, a), **rep)
    out["aba"] = _common.time_per_call(lambda: pin.aba(pm, pd, qp, v, tau), **rep)
    M = np.array(pin.crba(pm, pd, qp))
    M = np.triu(M) + np.triu(M, 1).T
    if free:
        # free-flyer velocities are body-frame in Pinocchio, linear part world-frame in
        # MuJoCo: the matrices differ by an orthogonal change of velocity coordinates
        out["M_eigenvalues_rel_err_vs_mujoco"] = _rel(np.linalg.eigvalsh(M), np.linalg.eigvalsh(M_ref))
    else:
        out["M_rel_err_vs_mujoco"] = _rel(M, M_ref)
        out["bias_rel_err_vs_mujoco"] = _rel(pin.rnea(pm, pd, qp, v, 0 * v), bias_ref)
    return out


def worker_single(cfg, rec):
    """Compile times and one-state per-call times of one model (jaxbody, MuJoCo, Pinocchio)."""
    import mujoco
    import numpy as np

    jax = _jax_setup(cfg)
    path = pathlib.Path(cfg["path"])
    dtype = np.float32 if cfg["float32"] else np.float64
    m = _mujoco_rigid(path)
    model = _load_jaxbody(path)
    q, v, a, tau = (x[0] for x in _states(m, 1, cfg["seed"]))
    rec.data.update(model=cfg["model"], n_body=model.n_body, nq=model.nq, nv=model.nv,
                    dtype=np.dtype(dtype).name, jax_devices=[str(d) for d in jax.devices()])
    rep = dict(min_time=cfg["min_time"], repeats=cfg["repeats"])

    # --- MuJoCo, single thread, one state at a time
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.qfrc_applied[:] = q, v, tau
    mj = rec.data["mujoco"] = {"timer_callback": _mujoco_timer_check(mujoco, m, d, cfg)}
    M_ref = np.zeros((m.nv, m.nv))

    def full_m():
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_makeM(m, d)
        mujoco.mj_fullM(m, d, M_ref)

    mj["fullM"] = _common.time_per_call(full_m, **rep)
    mj["fullM"]["what"] = "mj_kinematics + mj_comPos + mj_makeM + mj_fullM"
    mj["forward"] = _common.time_per_call(lambda: mujoco.mj_forward(m, d), **rep)
    mj["forward"]["what"] = "mj_forward (qfrc_applied = tau)"
    qacc_ref, bias_ref = d.qacc.copy(), d.qfrc_bias.copy()
    d.qacc[:] = a
    mj["inverse"] = _common.time_per_call(lambda: mujoco.mj_inverse(m, d), **rep)
    mj["inverse"]["what"] = "mj_inverse (qacc = a)"
    inv_ref = d.qfrc_inverse.copy()
    refs = {"mass_matrix": M_ref, "inverse_dynamics": inv_ref, "forward_dynamics": qacc_ref}
    rec.save()

    # --- jaxbody
    args = (model, *(jax.device_put(np.asarray(x, dtype)) for x in (q, v, a, tau)))
    jb_out = rec.data["jaxbody"] = {}
    agree = rec.data["agreement_vs_mujoco"] = {}
    for name in cfg["functions"]:
        rec.data["running"] = name
        rec.save()
        try:
            jitted, _, out, times = _compile(jax, _jaxbody_fn(name), args)
        except Exception as e:  # noqa: BLE001 - recorded, the other functions go on
            jb_out[name] = {"error": f"{e.__class__.__name__}: {e}"[:1000]}
            continue
        times["per_call"] = _common.time_per_call(lambda: jax.block_until_ready(jitted(*args)), **rep)
        jb_out[name] = times
        agree[name] = _rel(out, refs[name])
    rec.data.pop("running", None)
    # JAX's per-call floor with these arguments: a jitted function of (model, q, v, a, tau)
    # that does no work; single-state times above are this plus the computation
    noop, _, _, _ = _compile(jax, lambda model, q, v, a, tau: q, args)
    rec.data["jax_dispatch_floor"] = _common.time_per_call(lambda: jax.block_until_ready(noop(*args)), **rep)
    rec.save()

    # --- Pinocchio (optional)
    if cfg["pinocchio"]:
        rec.data["pinocchio"] = _pinocchio_single(path, m, (q, v, a, tau), cfg, M_ref, bias_ref)
    else:
        rec.data["pinocchio"] = {"available": None, "reason": "--no-pinocchio"}
    rec.save()


def worker_batch(cfg, rec):
    """Throughput at one batch size: MuJoCo first (cannot hang), then jaxbody ``vmap``."""
    import mujoco
    import mujoco.batch
    import mujoco.rollout
    import numpy as np

    mujoco.set_mjcb_time(None)
    path, n = pathlib.Path(cfg["path"]), cfg["batch"]
    m = _mujoco_rigid(path)
    q, v, a, tau = _states(m, n, cfg["seed"])
    rec.data.update(model=cfg["model"], batch=n, nv=int(m.nv))
    rep = dict(min_time=cfg["min_time"], repeats=cfg["repeats"])

    # --- MuJoCo: mj_forward over the batch in C, 1 thread and all cores
    mj = rec.data["mujoco"] = {}
    for key, nthread in (("forward_1thread", 1), ("forward_nthread", cfg["threads"])):
        b = mujoco.batch.Batch(m, nsim=n, nthread=nthread)
        b.bind("qpos")[...] = q
        b.bind("qvel")[...] = v
        b.bind("qfrc_applied")[...] = tau
        qacc = b.bind("qacc")  # copied out after every call, as jaxbody returns it
        t = _common.time_per_call(b.forward, **rep)
        t.update(nthread=b.nthread, states_per_s=n / t["median_s"], what="mujoco.batch.Batch.forward")
        mj[key] = t
        if key == "forward_1thread":
            qacc_ref = np.array(qacc)
        del b
        rec.save()
    # one-step rollouts (mj_step = mj_forward + Euler), all cores
    try:
        nstate = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        d = mujoco.MjData(m)
        init = np.empty((n, nstate))
        for i in range(n):
            d.qpos[:], d.qvel[:] = q[i], v[i]
            mujoco.mj_getState(m, d, init[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
        spec = int(mujoco.mjtState.mjSTATE_QFRC_APPLIED)
        ctrl = np.ascontiguousarray(tau[:, None, :])
        datas = [mujoco.MjData(m) for _ in range(cfg["threads"])]
        state_out = np.empty((n, 1, nstate))
        sens_out = np.empty((n, 1, m.nsensordata))
        with mujoco.rollout.Rollout(nthread=cfg["threads"]) as r:
            def step():
                r.rollout(m, datas, init, ctrl, control_spec=spec, nstep=1, state=state_out, sensordata=sens_out)
            t = _common.time_per_call(step, **rep)
        t.update(nthread=cfg["threads"], states_per_s=n / t["median_s"], what="mujoco.rollout, nstep=1 (mj_step)")
        mj["rollout_step_nthread"] = t
    except Exception as e:  # noqa: BLE001
        mj["rollout_step_nthread"] = {"error": f"{e.__class__.__name__}: {e}"[:500]}
    rec.save()

    # --- jaxbody: jit(vmap(f))
    jax = _jax_setup(cfg)
    dtype = np.float32 if cfg["float32"] else np.float64
    model = _load_jaxbody(path)
    args = (model, *(jax.device_put(np.asarray(x, dtype)) for x in (q, v, a, tau)))
    avail = _common.mem_available_bytes()
    jb_out = rec.data["jaxbody"] = {}
    for name in cfg["functions"]:
        rec.data["running"] = name
        rec.save()
        n_dev = cfg.get("devices", 1)
        if cfg.get("chunk") and n > cfg["chunk"] and n % n_dev == 0:
            import jaxbody as jb

            fn = jb.vmap_chunked(_jaxbody_fn(name), cfg["chunk"], in_axes=(None, 0, 0, 0, 0),
                                 devices=n_dev if n_dev > 1 else None)
            res_form = f"vmap_chunked(chunk={cfg['chunk']}, devices={n_dev})"
        else:
            fn = jax.vmap(_jaxbody_fn(name), in_axes=(None, 0, 0, 0, 0))
            res_form = "vmap"
        try:
            jitted = jax.jit(fn)
            t0 = time.perf_counter()
            compiled = jitted.trace(*args).lower().compile()  # fills jitted's cache
            res = jb_out[name] = {"compile_total_s": time.perf_counter() - t0, "form": res_form}
            mem = compiled.memory_analysis()
            need = None
            if mem is not None:
                need = mem.temp_size_in_bytes + mem.output_size_in_bytes + mem.argument_size_in_bytes
                res["memory_bytes"] = need
            if need is not None and avail is not None and need > MEMORY_FRACTION * avail:
                res["skipped"] = (f"needs {need / 2**30:.1f} GiB, more than {MEMORY_FRACTION:.0%} of the "
                                  f"{avail / 2**30:.1f} GiB available")
                continue
            t0 = time.perf_counter()
            out = jitted(*args)
            jax.block_until_ready(out)
            res["first_run_s"] = time.perf_counter() - t0
            rec.save()
            if res["first_run_s"] > 5.0 * cfg["min_time"]:
                # seconds per call: the first run is the measurement (no second run)
                res["per_batch"] = {"median_s": res["first_run_s"], "repeats": 1, "number": 1,
                                    "note": "slow call: timed once, its first run"}
            else:  # the first run was the warm-up
                res["per_batch"] = _common.time_per_call(
                    lambda: jax.block_until_ready(jitted(*args)), warmup=False, **rep)
            res["states_per_s"] = n / res["per_batch"]["median_s"]
            if name == "forward_dynamics":
                res["rel_err_vs_mujoco"] = _rel(out, qacc_ref)
                res["finite"] = bool(np.all(np.isfinite(np.asarray(out))))
        except Exception as e:  # noqa: BLE001
            jb_out[name] = {"error": f"{e.__class__.__name__}: {e}"[:1000]}
        rec.save()
    rec.data.pop("running", None)
    rec.save()


# ============================================================================ parent side
def _si(x, unit=""):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    for f, s in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(x) >= f:
            return f"{x / f:.3g}{s}{unit}"
    return f"{x:.3g}{unit}"


def _us(t):
    return "—" if t is None else f"{t * 1e6:.3g}"


def _get(d, *keys):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _jb_status(batch_rec, fn):
    """'ok', 'timeout', 'skipped: ...', 'error: ...' or 'not run' for one jaxbody batch cell."""
    r = _get(batch_rec, "jaxbody", fn)
    if r is not None:
        if "states_per_s" in r and "error" not in r:
            return "ok"
        if "skipped" in r:
            return "skipped: " + r["skipped"]
        if "error" in r:
            return r["error"] if r["error"] == "timeout" else "error: " + r["error"].splitlines()[0][:120]
    if batch_rec.get("status") == "timeout":
        return "timeout"
    if batch_rec.get("status", "ok") != "ok":
        return batch_rec["status"]
    return "not run"


def compute_targets(results, args):
    """The targets, each MET / NOT MET / NOT MEASURED with its numbers."""
    single, batch = results["single"], results["batch"]
    targets = []

    def fd_ratio_rows(model, key):
        rows = []
        for b, rec in sorted(batch.get(model, {}).items(), key=lambda kv: int(kv[0])):
            if int(b) < 1024:
                continue
            jb_sps = _get(rec, "jaxbody", "forward_dynamics", "states_per_s")
            mj_sps = _get(rec, "mujoco", key, "states_per_s")
            rows.append((int(b), jb_sps, mj_sps, _jb_status(rec, "forward_dynamics")))
        return rows

    def ratio_target(tid, model, key, factor, label):
        rows = fd_ratio_rows(model, key)
        t = {"id": tid, "target": label}
        if not rows:
            t.update(verdict="NOT MEASURED", detail=f"{model} at batch >= 1024 not in this run")
            return t
        parts, ok = [], True
        for b, jb_sps, mj_sps, st in rows:
            if jb_sps is None or mj_sps is None:
                parts.append(f"batch {b}: jaxbody {st}")
                ok = False
                continue
            r = jb_sps / mj_sps
            ok &= r >= factor
            parts.append(f"batch {b}: {_si(jb_sps)}/s vs {_si(mj_sps)}/s = {r:.2f}x (need {factor:g}x)")
        t.update(verdict="MET" if ok else "NOT MET", detail="; ".join(parts))
        return t

    targets.append(ratio_target(
        "panda-vs-mujoco-all-cores", "panda", "forward_nthread", 2.0,
        "panda: batched forward_dynamics (batch >= 1024) >= 2x MuJoCo mj_forward on all cores"))
    targets.append(ratio_target(
        "chain20-vs-mujoco-one-thread", "chain20", "forward_1thread", 1.0,
        "chain20: batched forward_dynamics (batch >= 1024) >= MuJoCo mj_forward on one thread"))

    # large batches complete
    t = {"id": "large-batches", "target": "forward_dynamics batches of 8192 and 65536 complete"}
    parts, ok, missing = [], True, []
    for b in (8192, HUGE_BATCH):
        cells = [(model, recs[str(b)]) for model, recs in batch.items() if str(b) in recs]
        if not cells:
            missing.append(str(b) + (" (use --huge)" if b == HUGE_BATCH else ""))
            continue
        for model, rec in cells:
            st = _jb_status(rec, "forward_dynamics")
            fin = _get(rec, "jaxbody", "forward_dynamics", "finite")
            ok &= st == "ok" and fin is not False
            parts.append(f"{model}@{b}: {st}" + ("" if fin is not False else " (non-finite)"))
    if len(missing) == 2:
        t.update(verdict="NOT MEASURED", detail="no batch of 8192 or 65536 in this run")
    else:
        verdict = "MET" if ok else "NOT MET"
        if missing:
            verdict += f" (not run: {', '.join(missing)})"
        t.update(verdict=verdict, detail="; ".join(parts))
    targets.append(t)

    # compile time scaling
    t = {"id": "compile-scaling", "target": "forward_dynamics compile time, chain100 within 2x of chain2"}
    c100 = _get(single, "chain100", "jaxbody", "forward_dynamics", "compile_total_s")
    c2 = _get(single, "chain2", "jaxbody", "forward_dynamics", "compile_total_s")
    if c100 is None or c2 is None:
        t.update(verdict="NOT MEASURED", detail="needs chain2 and chain100 with a working forward_dynamics")
    else:
        r = c100 / c2
        t.update(verdict="MET" if r <= 2.0 else "NOT MET",
                 detail=f"{c100:.2f} s / {c2:.2f} s = {r:.2f}x (need <= 2x)")
    targets.append(t)
    return targets


def write_markdown(results, path):
    s = results["stamp"]
    single, batch = results["single"], results["batch"]
    out = ["# jaxbody dynamics benchmark", "", _common.stamp_markdown(s), ""]
    if results.get("quick"):
        out += ["**Quick mode** (few models, small batches, short timing): a harness check, not a record.", ""]
    out += [f"dtype: {results['dtype']} (MuJoCo and Pinocchio are always float64); "
            f"MuJoCo multi-thread runs use {results['threads']} threads.", ""]

    out += ["## Targets", ""]
    out.append(_common.markdown_table(
        ["id", "target", "verdict", "numbers"],
        [(t["id"], t["target"], f"**{t['verdict']}**", t["detail"]) for t in results["targets"]]))

    out += ["", "## One state: compile time and warm per-call time", "",
            "Compile = trace + lower + XLA compile of the jitted function (first call without "
            "its run), in a fresh worker process. Per-call times in µs (median), one state, "
            "jitted and warm for jaxbody with the model passed as an argument (as for `grad` "
            "with respect to parameters); 'jax floor' is the same call of a jitted function that "
            "does nothing, i.e. JAX's dispatch cost for these arguments. MuJoCo and Pinocchio called from Python one state at a "
            "time on one thread (Python call overhead included, well under 1 µs per call).", ""]
    rows = []
    for model, r in single.items():
        jb_ = r.get("jaxbody", {})
        mj = r.get("mujoco", {})
        pn = r.get("pinocchio", {})

        def failed(x):
            return x["error"] if x["error"] == "timeout" else "error"

        def comp(fn):
            x = jb_.get(fn, {})
            return failed(x) if "error" in x else (f"{x['compile_total_s']:.2f}" if "compile_total_s" in x else "—")

        def call(fn):
            x = jb_.get(fn, {})
            return failed(x) if "error" in x else _us(_get(x, "per_call", "median_s"))

        status = "" if r.get("status") == "ok" else f" ({r.get('status')})"
        rows.append((
            f"{model}{status}", f"{r.get('nq', '?')}/{r.get('nv', '?')}",
            comp("mass_matrix"), comp("inverse_dynamics"), comp("forward_dynamics"),
            call("mass_matrix"), call("inverse_dynamics"), call("forward_dynamics"),
            _us(_get(mj, "fullM", "median_s")), _us(_get(mj, "inverse", "median_s")),
            _us(_get(mj, "forward", "median_s")),
            _us(_get(pn, "crba", "median_s")), _us(_get(pn, "rnea", "median_s")), _us(_get(pn, "aba", "median_s")),
            _us(_get(r, "jax_dispatch_floor", "median_s")),
        ))
    out.append(_common.markdown_table(
        ["model", "nq/nv", "compile M (s)", "compile ID (s)", "compile FD (s)",
         "jb M µs", "jb ID µs", "jb FD µs", "mj fullM µs", "mj_inverse µs", "mj_forward µs",
         "pin crba µs", "pin rnea µs", "pin aba µs", "jax floor µs"], rows))

    out += ["", "Agreement with MuJoCo at the timed state (max abs difference / max abs reference):", ""]
    rows = []
    for model, r in single.items():
        ag = r.get("agreement_vs_mujoco", {})
        pn = r.get("pinocchio", {})
        pin_err = pn.get("M_rel_err_vs_mujoco", pn.get("M_eigenvalues_rel_err_vs_mujoco"))
        rows.append((model, *(f"{ag[f]:.1e}" if f in ag else "—" for f in FUNCTIONS),
                     "—" if pin_err is None else f"{pin_err:.1e}"))
    out.append(_common.markdown_table(["model", "M", "inverse", "forward (qacc)", "Pinocchio M"], rows))

    out += ["", "## Batched throughput (states/s)", "",
            "jaxbody: `jit(vmap(f))` over the batch, or `jit(jb.vmap_chunked(f, chunk))` for batches "
            f"larger than the chunk (chunk = {results.get('chunk', 0)}; 0 = plain vmap), split over "
            f"{results.get('devices', 1)} CPU device(s) (XLA CPU, its own "
            "threading). MuJoCo: "
            "`mujoco.batch.Batch.forward` (mj_forward over the batch in C) on 1 thread and on all "
            "cores; `mujoco.rollout` one step (mj_step) on all cores. Ratios are jaxbody "
            "forward_dynamics over the MuJoCo column named.", ""]
    rows = []
    for model, recs in batch.items():
        for b, rec in sorted(recs.items(), key=lambda kv: int(kv[0])):
            def sps(fn):
                st = _jb_status(rec, fn)
                return _si(_get(rec, "jaxbody", fn, "states_per_s")) if st == "ok" else st.split(":")[0]
            fd = _get(rec, "jaxbody", "forward_dynamics", "states_per_s")
            m1 = _get(rec, "mujoco", "forward_1thread", "states_per_s")
            mn = _get(rec, "mujoco", "forward_nthread", "states_per_s")
            rows.append((
                model, b, sps("mass_matrix"), sps("inverse_dynamics"), sps("forward_dynamics"),
                _si(m1), _si(mn), _si(_get(rec, "mujoco", "rollout_step_nthread", "states_per_s")),
                f"{fd / m1:.2f}" if fd and m1 else "—", f"{fd / mn:.2f}" if fd and mn else "—",
            ))
    out.append(_common.markdown_table(
        ["model", "batch", "jb M", "jb ID", "jb FD", "mj_forward 1T", "mj_forward NT", "mj_step rollout NT",
         "FD / mj 1T", "FD / mj NT"], rows))

    tc = [(m, _get(r, "mujoco", "timer_callback")) for m, r in single.items()]
    tc = [(m, x) for m, x in tc if x]
    if tc:
        out += ["", "## MuJoCo timer callback", "",
                "`mujoco.get_mjcb_time()` at worker start, and mj_forward with a Python timer "
                "callback (`mujoco.set_mjcb_time(time.perf_counter)`) against none "
                "(`mujoco.set_mjcb_time(None)`, used for every MuJoCo number above):", ""]
        out.append(_common.markdown_table(
            ["model", "mjcb_time at start", "with Python timer µs", "without µs", "slowdown"],
            [(m, x["mjcb_time_at_start"] or "None", _us(x["mj_forward_with_python_timer_s"]),
              _us(x["mj_forward_without_timer_s"]), f"{x['slowdown_with_timer']:.2f}x") for m, x in tc]))
    pn = next((r.get("pinocchio") for r in single.values() if r.get("pinocchio")), None)
    if pn and pn.get("available") in (False, None):
        out += ["", f"Pinocchio: skipped ({pn['reason']})."]
    out += ["", f"Raw numbers: `{path.stem}.json`; plot: `{path.stem}.png`.", ""]
    path.write_text("\n".join(out))


def write_plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    batch = results["batch"]
    models = [m for m in batch if batch[m]]
    if not models:
        return False
    ncol = min(4, len(models))
    nrow = math.ceil(len(models) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.6 * nrow), squeeze=False)
    lines = [
        (("jaxbody", "forward_dynamics"), "jaxbody forward_dynamics", dict(color="C0", marker="o", lw=2)),
        (("jaxbody", "inverse_dynamics"), "jaxbody inverse_dynamics", dict(color="C0", marker=".", ls=":", lw=1)),
        (("jaxbody", "mass_matrix"), "jaxbody mass_matrix", dict(color="C0", marker=".", ls="-.", lw=1)),
        (("mujoco", "forward_1thread"), "MuJoCo mj_forward, 1 thread", dict(color="C3", marker="s", ls="--")),
        (("mujoco", "forward_nthread"), f"MuJoCo mj_forward, {results['threads']} threads",
         dict(color="C1", marker="s", ls="--")),
        (("mujoco", "rollout_step_nthread"), f"MuJoCo rollout mj_step, {results['threads']} threads",
         dict(color="C2", marker="^", ls=":", lw=1)),
    ]
    for ax, model in zip(axes.flat, models):
        recs = sorted(batch[model].items(), key=lambda kv: int(kv[0]))
        for keys, label, style in lines:
            xs, ys = [], []
            for b, rec in recs:
                y = _get(rec, *keys, "states_per_s")
                if y:
                    xs.append(int(b))
                    ys.append(y)
            if xs:
                ax.plot(xs, ys, label=label, **style)
        fails = [int(b) for b, rec in recs if _jb_status(rec, "forward_dynamics") != "ok"]
        for b in fails:
            ax.axvline(b, color="0.6", lw=0.8, ls=":")
            ax.annotate(_jb_status(batch[model][str(b)], "forward_dynamics").split(":")[0],
                        (b, 0.05), xycoords=("data", "axes fraction"), rotation=90, fontsize=7, color="0.4")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"{model} (nv={_get(results['single'], model, 'nv') or '?'})")
        ax.set_xlabel("batch size")
        ax.set_ylabel("states / s")
        ax.grid(True, which="both", alpha=0.3)
    for ax in list(axes.flat)[len(models):]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    s = results["stamp"]
    fig.suptitle(f"jaxbody vs MuJoCo throughput ({results['dtype']}), commit {s['commit']}"
                 f"{' (dirty)' if s.get('dirty') else ''}, {s['cpu']} x{s['cores']}, jax {s['versions']['jax']}, "
                 f"mujoco {s['versions']['mujoco']}, {s['date']}", fontsize=8)
    fig.tight_layout(rect=(0, 0.08, 1, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help=f"harness check: models {','.join(QUICK_MODELS)}, batches "
                        f"{','.join(map(str, QUICK_BATCHES))}, short timing")
    p.add_argument("--models", help=f"comma-separated: {', '.join(MENAGERIE)}, chainN "
                                    f"(default {','.join(DEFAULT_MODELS)})")
    p.add_argument("--batches", help=f"comma-separated batch sizes (default {','.join(map(str, DEFAULT_BATCHES))})")
    p.add_argument("--huge", action="store_true", help=f"also batch {HUGE_BATCH}")
    p.add_argument("--float32", action="store_true", help="jaxbody in float32 (default float64)")
    p.add_argument("--devices", type=int, default=1,
                   help="split chunked batches over this many CPU devices (sets "
                        "--xla_force_host_platform_device_count; 2 = both cores of the CI machine)")
    p.add_argument("--chunk", type=int, default=64,
                   help="batches larger than this run as jb.vmap_chunked(f, CHUNK) (cache-sized chunks); "
                        "0 = plain jax.vmap over the whole batch (default 64)")
    p.add_argument("--functions", default=",".join(FUNCTIONS), help="comma-separated subset of " + ", ".join(FUNCTIONS))
    p.add_argument("--keep-xla-flags", action="store_true",
                   help=f"do not add {XLA_DEFAULT_FLAG} to XLA_FLAGS (added by default)")
    p.add_argument("--threads", type=int, default=_common.core_count(),
                   help="MuJoCo multi-thread count (default: cores available)")
    p.add_argument("--no-pinocchio", action="store_true", help="skip Pinocchio even if installed")
    p.add_argument("--min-time", type=float, help="seconds per timing (default 0.5, quick 0.1); a "
                                                  "timing stops adding repeats after 5x this")
    p.add_argument("--repeats", type=int, help="timing repeats, median reported (default 5, quick 3)")
    p.add_argument("--timeout", type=float, help="seconds per worker process (default 300, quick 180)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--models-dir", type=pathlib.Path, default=_common.REPO / "jaxbody" / "models")
    p.add_argument("--out", type=pathlib.Path, default=_common.RESULTS, help="results folder")
    p.add_argument("--name", help="results file stem (default dynamics; dynamics_quick with --quick, "
                                  "so a harness check never overwrites the record)")
    # internal: worker processes
    p.add_argument("--worker", choices=("single", "batch"), help=argparse.SUPPRESS)
    p.add_argument("--config", help=argparse.SUPPRESS)
    p.add_argument("--result", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        return args
    args.models = [m.strip() for m in (args.models or ",".join(QUICK_MODELS if args.quick else DEFAULT_MODELS)).split(",") if m.strip()]
    args.batches = sorted({int(b) for b in (args.batches or ",".join(map(str, QUICK_BATCHES if args.quick else DEFAULT_BATCHES))).split(",")})
    if args.huge and HUGE_BATCH not in args.batches:
        args.batches.append(HUGE_BATCH)
    args.functions = [f.strip() for f in args.functions.split(",") if f.strip()]
    bad = [f for f in args.functions if f not in FUNCTIONS]
    if bad:
        p.error(f"unknown function(s) {bad}; choose from {FUNCTIONS}")
    args.min_time = args.min_time or (0.1 if args.quick else 0.5)
    args.repeats = args.repeats or (3 if args.quick else 5)
    args.timeout = args.timeout or (180.0 if args.quick else 300.0)
    args.name = args.name or ("dynamics_quick" if args.quick else "dynamics")
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.worker:
        rec = _Record(args.result)
        cfg = json.loads(args.config)
        (worker_single if args.worker == "single" else worker_batch)(cfg, rec)
        return 0

    env = dict(os.environ)
    if not args.keep_xla_flags and XLA_DEFAULT_FLAG and XLA_DEFAULT_FLAG not in env.get("XLA_FLAGS", ""):
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + XLA_DEFAULT_FLAG).strip()
    if args.devices > 1:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={args.devices}").strip()
    os.environ["XLA_FLAGS"] = env.get("XLA_FLAGS", "")  # so the stamp records what workers get
    stamp = _common.stamp(sys.argv if argv is None else [sys.argv[0], *argv])
    args.out.mkdir(parents=True, exist_ok=True)
    results = {
        "stamp": stamp, "quick": args.quick, "dtype": "float32" if args.float32 else "float64",
        "threads": args.threads, "models": args.models, "batches": args.batches,
        "functions": args.functions, "timeout_s": args.timeout, "min_time_s": args.min_time,
        "repeats": args.repeats, "chunk": args.chunk, "devices": args.devices, "single": {}, "batch": {},
    }
    t_start = time.perf_counter()
    print(f"jaxbody dynamics benchmark: models {args.models}, batches {args.batches}, "
          f"{results['dtype']}, XLA_FLAGS={env.get('XLA_FLAGS', '')!r}", flush=True)
    with tempfile.TemporaryDirectory(prefix="jaxbody-bench-") as tmp:
        tmp = pathlib.Path(tmp)
        for model in args.models:
            path = model_path(model, args.models_dir, tmp)
            base = dict(model=model, path=str(path), float32=args.float32, functions=args.functions,
                        min_time=args.min_time, repeats=args.repeats, seed=args.seed,
                        threads=args.threads, pinocchio=not args.no_pinocchio, chunk=args.chunk,
                        devices=args.devices)
            jobs = [("single", None)] + [("batch", b) for b in args.batches]
            for kind, b in jobs:
                cfg = dict(base, batch=b)
                result_file = tmp / f"{model}-{kind}-{b}.json"
                cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--worker", kind,
                       "--config", json.dumps(cfg), "--result", str(result_file)]
                r = _common.run_worker(cmd, timeout=args.timeout, result_file=result_file, env=env)
                if r.get("running") and r["status"] != "ok":
                    # the function in progress when the worker died or timed out
                    r.setdefault("jaxbody", {}).setdefault(r["running"], {})["error"] = r["status"]
                if kind == "single":
                    results["single"][model] = r
                    jbr = r.get("jaxbody", {})
                    msg = ", ".join(
                        f"{f} compile {jbr[f]['compile_total_s']:.2f}s run {jbr[f]['per_call']['median_s'] * 1e6:.3g}us"
                        if "per_call" in jbr.get(f, {}) else f"{f} {jbr.get(f, {}).get('error', 'missing')[:80]}"
                        for f in args.functions)
                    fwd = _get(r, "mujoco", "forward", "median_s")
                    print(f"[{time.perf_counter() - t_start:6.0f}s] {model} single ({r['status']}): {msg}; "
                          f"mj_forward {_us(fwd)}us", flush=True)
                else:
                    results["batch"].setdefault(model, {})[str(b)] = r
                    fd = _jb_status(r, "forward_dynamics")
                    print(f"[{time.perf_counter() - t_start:6.0f}s] {model} batch {b} ({r['status']}): jaxbody FD "
                          f"{_si(_get(r, 'jaxbody', 'forward_dynamics', 'states_per_s')) if fd == 'ok' else fd} /s, "
                          f"mj_forward 1T {_si(_get(r, 'mujoco', 'forward_1thread', 'states_per_s'))} /s, "
                          f"{args.threads}T {_si(_get(r, 'mujoco', 'forward_nthread', 'states_per_s'))} /s", flush=True)

    stamp["load_average_end"] = _common.load_average()
    stamp["wall_s"] = time.perf_counter() - t_start
    results["targets"] = compute_targets(results, args)
    md, js, png = (args.out / f"{args.name}.{ext}" for ext in ("md", "json", "png"))
    js.write_text(json.dumps(results, indent=1, default=str))
    write_markdown(results, md)
    plotted = write_plot(results, png)
    print("\nTargets:")
    for t in results["targets"]:
        print(f"  {t['id']} {t['verdict']}: {t['target']}\n      {t['detail']}")
    print(f"\nwrote {md}, {js}" + (f", {png}" if plotted else "") + f" in {stamp['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
