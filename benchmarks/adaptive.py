"""Native adaptive solves against diffrax's loop and MuJoCo's RK4 at equal accuracy.

The chaotic double pendulum of the papers' Example 1 (released from the horizontal) over 10 s, and
the Panda arm under gravity, its joints' damping and the accuracy study's torque profile
``τ_i = A_i sin(2π f_i t)`` (``benchmarks/_study_torque.py``: a :class:`jaxbody.FourierTorque` for
jaxbody, ``qfrc_applied`` at each step's midpoint for MuJoCo, as ``benchmarks/work_precision.py``
gives it) over 5 s, in float64: the final state's error against a reference (scipy's DOP853 at
rtol = atol = 1e-13 on MuJoCo's ``mj_forward`` with the torque's exact values; its distance to
jaxbody's native Dopri8 at 1e-15 or 1e-13 reported), and
the wall time of one solve (compiled once beforehand, fastest of several calls) for

* jaxbody's ``simulate(..., solver="dopri8"|"tsit5", saveat=SaveAt(t1=True))`` on the native
  kernel (one native call) and the same solve through diffrax's loop (``JAXBODY_NATIVE_SOLVE=0``),
  over a sweep of tolerances;
* MuJoCo's RK4 through ``mujoco.rollout`` over a sweep of timesteps.

Each method's cheapest sweep point reaching the scene's target error (1e-8, Panda 1e-6) is
compared with MuJoCo's, and the ratios are written to
``benchmarks/results/adaptive.json`` and ``.md``.

    .venv/bin/python benchmarks/adaptive.py
"""

import json
import os
import argparse
import pathlib
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import _common  # noqa: E402
from _study_torque import panda_torque, panda_torque_values  # noqa: E402

# the papers' Example 1 (masses 1, 0.6 kg; centres 0.4, 0.3 m; L1 = 0.8 m; central inertias 0.05,
# 0.02 kg·m²) as hinges about y
PENDULUM = _common.DOUBLE_PENDULUM_MJCF
#: scene -> (end time, target error, tolerances of each method, MuJoCo timesteps)
SCENES = {
    "pendulum": (10.0, 1e-8, {"dopri8": (1e-11, 3e-12, 1e-12, 1e-13), "tsit5": (1e-12, 1e-13)},
                 (2e-4, 1.25e-4, 1e-4)),
    "panda": (5.0, 1e-6, {"dopri8": (1e-6, 1e-7, 1e-8, 1e-9), "tsit5": (1e-7, 1e-8, 1e-9)},
              (1e-2, 5e-3, 2e-3, 1e-3, 5e-4, 2e-4)),
}
BATCH = 1024
#: trajectories of the MuJoCo batch actually timed (its cost per trajectory does not depend on
#: the batch: scaled to BATCH)
MUJOCO_BATCH = 32


def best_time(fn, repeats=7):
    """The fastest of ``repeats`` timed calls after a warm-up (on a machine shared with other
    work the fastest call is the least disturbed one; every method is timed the same way)."""
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.min(times))


def cheapest(points, target):
    """The cheapest sweep point whose error is at most ``target`` (``None`` when none is)."""
    ok = [p for p in points if p["error"] <= target]
    return min(ok, key=lambda p: p["time_s"]) if ok else None


def mujoco_reference(mujoco, mj, q0, t1, torque):
    """The final state by scipy's DOP853 at rtol = atol = 1e-13 with MuJoCo's ``mj_forward`` as the
    vector field (``torque``: the study's profile as ``qfrc_applied`` at each evaluation's time):
    an independent formulation and integrator."""
    from scipy.integrate import solve_ivp

    data = mujoco.MjData(mj)
    nq = mj.nq

    def field(t, y):
        data.qpos[:], data.qvel[:] = y[:nq], y[nq:]
        if torque:
            data.qfrc_applied[:] = panda_torque_values(t)
        mujoco.mj_forward(mj, data)
        return np.concatenate([data.qvel, data.qacc])

    sol = solve_ivp(field, (0.0, t1), np.concatenate([q0, np.zeros(mj.nv)]), method="DOP853", rtol=1e-13, atol=1e-13)
    return sol.y[:, -1]


def mujoco_rollout(mujoco, mj, q0s, dt, t1, nthread, torque=False):
    """Final states and wall time of MuJoCo's RK4 through ``mujoco.rollout`` from ``q0s`` at rest;
    ``torque``: the study's profile as ``qfrc_applied``, held over each step at its midpoint's
    value (MuJoCo cannot vary an applied force within a step)."""
    import mujoco.rollout

    mj.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    mj.opt.timestep = dt
    nstep = int(round(t1 / dt))
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    data = [mujoco.MjData(mj) for _ in range(max(nthread, 1))]
    init = np.zeros((len(q0s), mujoco.mj_stateSize(mj, spec)))
    for i, q in enumerate(q0s):
        data[0].qpos[:] = q
        data[0].qvel[:] = 0.0
        mujoco.mj_getState(mj, data[0], init[i], spec)
    state = np.zeros((len(q0s), nstep, init.shape[1]))
    control, control_spec = None, mujoco.mjtState.mjSTATE_CTRL
    if torque:
        mid = (np.arange(nstep) + 0.5) * dt
        control = np.broadcast_to(np.stack([panda_torque_values(t) for t in mid]), (len(q0s), nstep, mj.nv)).copy()
        control_spec = mujoco.mjtState.mjSTATE_QFRC_APPLIED
    with mujoco.rollout.Rollout(nthread=nthread) as r:
        t = best_time(lambda: r.rollout(mj, data, init, control, control_spec=control_spec, nstep=nstep, state=state),
                      repeats=3 if nstep * len(q0s) < 3e5 else 1)
    last = state[:, -1]
    return np.concatenate([last[:, 1 : 1 + mj.nq], last[:, 1 + mj.nq : 1 + mj.nq + mj.nv]], axis=1), t


def run_scene(name, xml, q0, jax, jnp, diffrax, mujoco, jb, torque=False):
    t1, target, tolerances, timesteps = SCENES[name]
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "scene.xml"
        path.write_text(xml)
        model = jb.from_mjcf(str(path))
        mj = mujoco.MjModel.from_xml_path(str(path))
    mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_LIMIT
                               | mujoco.mjtDisableBit.mjDSBL_ACTUATION | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    # planar=False: the native spatial kernel (the planar specialisation has no native program)
    # the torque as a FourierTorque: the native one-call solves evaluate it at each stage's time
    scene = jb.scene(model, kernel="native", planar=False, effects=[panda_torque(jb)] if torque else [])
    q0, v0 = jnp.asarray(q0), jnp.zeros(model.nv)

    def solver_fn(method, tol, batched=False):
        def one(q, v):
            sol = jb.simulate(scene, q, v, t1, solver=method, rtol=tol, atol=tol, saveat=diffrax.SaveAt(t1=True),
                              max_steps=1_000_000)
            return sol.q_final, sol.v_final, sol.stats["num_steps"]
        return jax.jit(jax.vmap(one) if batched else one)

    def final(out):
        return np.concatenate([np.asarray(out[0]), np.asarray(out[1])], axis=-1)

    ref = mujoco_reference(mujoco, mj, np.asarray(q0), t1, torque)
    own = final(solver_fn("dopri8", 1e-15 if name == "pendulum" else 1e-13)(q0, v0))
    rec = {"t1": t1, "target": target, "reference_convergence": float(np.max(np.abs(ref - own))), "sweeps": {}}
    for native in ("1", "0"):
        os.environ["JAXBODY_NATIVE_SOLVE"] = native
        for method, tols in tolerances.items():
            label = f"jaxbody {method} ({'native' if native == '1' else 'diffrax loop'})"
            pts = []
            for tol in tols:
                fn = solver_fn(method, tol)
                out = fn(q0, v0)
                err = float(np.max(np.abs(final(out) - ref)))
                t = best_time(lambda: jax.block_until_ready(fn(q0, v0)), repeats=15 if native == "1" else 3)
                pts.append({"tol": tol, "error": err, "time_s": t, "steps": int(out[2])})
                print(name, label, pts[-1], flush=True)
            rec["sweeps"][label] = pts
    os.environ["JAXBODY_NATIVE_SOLVE"] = "1"
    pts = []
    for dt in timesteps:
        out, t = mujoco_rollout(mujoco, mj, [np.asarray(q0)], dt, t1, 0, torque)
        pts.append({"dt": dt, "error": float(np.max(np.abs(out[0] - ref))), "time_s": t})
        print(name, "mujoco rk4", pts[-1], flush=True)
    rec["sweeps"]["MuJoCo RK4 (mujoco.rollout)"] = pts
    best = {k: cheapest(v, target) for k, v in rec["sweeps"].items()}
    rec["cheapest_at_target"] = best
    mjb = best["MuJoCo RK4 (mujoco.rollout)"]
    rec["ratio_to_mujoco"] = {k: (v["time_s"] / mjb["time_s"] if v and mjb else None) for k, v in best.items()}
    # a batch on both cores: the single trajectory's settings, states spread around q0
    nat = best["jaxbody dopri8 (native)"]
    if nat and mjb:
        rng = np.random.default_rng(0)
        q0s = np.asarray(q0) + 1e-3 * rng.standard_normal((BATCH, model.nq))
        fn = solver_fn("dopri8", nat["tol"], batched=True)
        qs, vs = jnp.asarray(q0s), jnp.zeros((BATCH, model.nv))
        jax.block_until_ready(fn(qs, vs))
        tj = best_time(lambda: jax.block_until_ready(fn(qs, vs)), repeats=3)
        _, tm = mujoco_rollout(mujoco, mj, q0s[:MUJOCO_BATCH], mjb["dt"], t1, 2, torque)
        rec["batch"] = {"batch": BATCH, "jaxbody_native_dopri8_s": tj, "mujoco_timed_batch": MUJOCO_BATCH,
                        "mujoco_timed_s": tm, "mujoco_scaled_s": tm * BATCH / MUJOCO_BATCH,
                        "ratio": tj / (tm * BATCH / MUJOCO_BATCH)}
        print(name, "batch", rec["batch"], flush=True)
    return rec


def main():
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"),
                        help="folder of the record adaptive.md/.json (default benchmarks/results)")
    args = parser.parse_args()
    import jax
    jax.config.update("jax_enable_x64", True)
    import diffrax
    import jax.numpy as jnp
    import mujoco

    import jaxbody as jb

    panda = (pathlib.Path(jb.__file__).parent / "models" / "panda.xml").read_text()
    panda_q0 = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    stamp = _common.stamp()
    results = {"pendulum": run_scene("pendulum", PENDULUM, np.array([np.pi / 2, 0.0]), jax, jnp, diffrax, mujoco, jb),
               "panda": run_scene("panda", panda, panda_q0, jax, jnp, diffrax, mujoco, jb, torque=True)}
    stamp["load_average_end"] = _common.load_average()
    out = pathlib.Path(args.out)
    (out / "adaptive.json").write_text(json.dumps({"stamp": stamp, "results": results}, indent=1))
    md = ["# Native adaptive solves against diffrax's loop and MuJoCo's RK4", "", _common.stamp_markdown(stamp), "",
          "Final-state error (max abs over (q, v)) against scipy's DOP853 at rtol = atol = 1e-13 on MuJoCo's "
          "`mj_forward` (its distance to jaxbody's native Dopri8 at the tightest tolerance given as the reference's "
          "convergence); one trajectory, float64, wall time of a compiled call (fastest of several). For each solve, the cheapest "
          "sweep point reaching the target error, and its time over MuJoCo RK4's (`mujoco.rollout`) at the largest "
          "timestep of the sweep reaching it. Targets: at most 1/50 on the pendulum at 1e-8, 1/10 on Panda at 1e-6.", "",
          "Panda: under gravity, its joints' damping and the accuracy study's torque profile "
          "τ_i = A_i sin(2π f_i t) from a bent pose; jaxbody evaluates the torque (a `FourierTorque`) at each stage's "
          "time inside the one-call solve, MuJoCo holds it over each step at the step's midpoint (`qfrc_applied`), "
          "so its RK4 is second order here. On a shared machine a short call timed "
          "as the fastest of several catches quieter moments than a long one: compare the load averages.", ""]
    for name, rec in results.items():
        md += [f"## {name}: {rec['t1']} s, target error {rec['target']:g} (reference convergence "
               f"{rec['reference_convergence']:.1e})", ""]
        rows = [[k, (f"tol {v['tol']:g}" if "tol" in v else f"dt {v['dt']:g}") if v else "not reached",
                 f"{v['error']:.2e}" if v else "-", f"{v['time_s'] * 1e3:.2f}" if v else "-",
                 f"1/{1 / rec['ratio_to_mujoco'][k]:.0f}" if rec["ratio_to_mujoco"][k] else "-"]
                for k, v in rec["cheapest_at_target"].items()]
        md += [_common.markdown_table(["solve", "setting", "error", "ms", "time / MuJoCo RK4"], rows), ""]
        if "batch" in rec:
            b = rec["batch"]
            md += [f"Batch of {b['batch']} (both cores): jaxbody native Dopri8 {b['jaxbody_native_dopri8_s']:.3f} s; "
                   f"MuJoCo RK4 `mujoco.rollout` nthread=2 {b['mujoco_timed_s']:.3f} s for {b['mujoco_timed_batch']} "
                   f"trajectories, {b['mujoco_scaled_s']:.2f} s scaled to {b['batch']}: ratio 1/{1 / b['ratio']:.0f}.", ""]
        sweep = [[k, p.get("tol", p.get("dt")), f"{p['error']:.2e}", f"{p['time_s'] * 1e3:.2f}", p.get("steps", "")]
                 for k, v in rec["sweeps"].items() for p in v]
        md += [_common.markdown_table(["solve", "tol / dt", "error", "ms", "steps"], sweep), ""]
    (out / "adaptive.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
