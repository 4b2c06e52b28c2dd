"""Work-precision study: what each digit of accuracy costs in time, jaxbody's solvers against MuJoCo's.

    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python benchmarks/work_precision.py [--quick] [--scenes a,b]

Five scenes, each from one initial state over a fixed span:

* ``pendulum``: the chaotic double pendulum of the papers' Example 1 from the horizontal, 10 s;
  reference: the papers' closed-form equations of motion (eq. 15, absolute angles) integrated by
  scipy's DOP853 at rtol = atol = 1e-13;
* ``panda``: the Panda arm under gravity with a smooth torque profile ``τ_i = A_i sin(2π f_i t)``
  (jaxbody: a :class:`jaxbody.FourierTorque`, ``benchmarks/_study_torque.py``), 5 s; reference: DOP853 at 1e-13 with MuJoCo's ``mj_forward`` as the vector field;
* ``disk``: the rolling disk (Maggi equations, non-holonomic), 10 s; reference: jaxbody's Dopri8
  at 1e-13, its convergence shown by its distance to the run at 1e-12;
* ``fourbar``: the four-bar linkage (a loop closure, holonomic), 10 s; reference as the disk's;
* ``chain``: five links with joint stiffnesses 1, 10, 1e3, 1e5, 1e6 N·m/rad and damping 0.01
  N·m·s/rad under gravity from 0.1 rad, 5 s; reference: DOP853 at 1e-13 on ``mj_forward``.

The pendulum, the arm, the four-bar and the chain are MJCF models: jaxbody imports the same file
MuJoCo runs (contacts, joint limits and actuators off, MuJoCo's timer callback off). The error of
a run is ``max |x − x_ref|`` over the components of the state ``x = (q, v)`` (radians, metres and
their rates), at the final time ("final") and over 101 evenly spaced times ("path"). Wall time is
the median of repeated calls of a compiled solve that saves those 101 states (compile time
apart: the first call minus one call); MuJoCo's is ``mujoco.rollout`` of one trajectory on one
thread. Vector-field evaluations: steps × stages of the method (one per step for MuJoCo's Euler
and implicitfast, four for RK4; for Kvaerno5 its explicit first stage plus one per Newton
iteration are not counted: steps × stages is a lower bound there).

jaxbody runs fixed-step Euler, semi-implicit Euler, Heun and RK4 over a sweep of ``dt``; Tsit5,
Dopri5 and Dopri8 (and Kvaerno5 on the stiff chain) over a sweep of ``rtol = atol``; and
``solver="auto"`` over a sweep of ``target_error``; in float64 and float32. MuJoCo runs Euler,
implicitfast and RK4 over a sweep of timesteps. MuJoCo receives the arm's torque as
``qfrc_applied`` held over each step (its value at the step's midpoint: MuJoCo has no way to vary
an applied force within a step), so its RK4 is second order on that scene.

Writes ``benchmarks/results/work_precision.{json,md,png}`` (``work_precision_quick.*`` with
``--quick``, which runs the pendulum over 2 s with two points per sweep, in float64: the size the
test suite's notebook runs).
"""

import argparse
import json
import math
import os
import pathlib
import sys
import time
import warnings

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _study_torque import panda_torque, panda_torque_values  # noqa: E402
from _common import (  # noqa: E402
    DOUBLE_PENDULUM_MJCF,
    RESULTS,
    load_average,
    markdown_table,
    set_default_xla_flags,
    shared_legend,
    stamp,
    stamp_markdown,
    time_per_call,
)

set_default_xla_flags()

import diffrax  # noqa: E402
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import mujoco.rollout  # noqa: E402
import numpy as np  # noqa: E402
import scipy.integrate  # noqa: E402
import scipy.optimize  # noqa: E402

import jaxbody as jb  # noqa: E402
from jaxbody.examples import disk as disk_example  # noqa: E402
from jaxbody.simulation.auto import choose_auto  # noqa: E402

N_SAVE = 101
REFERENCE_TOL = 1e-13
FIXED = ("euler", "semi_implicit_euler", "heun", "rk4")
ADAPTIVE = ("tsit5", "dopri5", "dopri8")
#: vector-field evaluations per step (FSAL methods: the stages after the first step)
STAGES = {"euler": 1, "semi_implicit_euler": 2, "heun": 2, "rk4": 4, "tsit5": 6, "dopri5": 6, "dopri8": 12,
          "kvaerno5": 7, "mj_euler": 1, "mj_implicitfast": 1, "mj_rk4": 4}
MJ_INTEGRATORS = {"mj_euler": "EULER", "mj_implicitfast": "IMPLICITFAST", "mj_rk4": "RK4"}


# ----------------------------------------------------------------------------- scenes
def pendulum_mjcf():
    """Example 1's double pendulum (masses 1, 0.6 kg; centres 0.4, 0.3 m; L1 = 0.8 m; central
    inertias 0.05, 0.02 kg·m²) as hinges about y: MuJoCo's joint angles are the relative ones."""
    return DOUBLE_PENDULUM_MJCF


def pendulum_closed_form(t, y):
    """Eq. (15) of the papers in absolute angles ``α`` from the downward vertical."""
    m1, m2, a1, a2, L1, I1, I2, g = 1.0, 0.6, 0.4, 0.3, 0.8, 0.05, 0.02, 9.81
    al1, al2, w1, w2 = y
    md1, md2 = m1 * a1 + m2 * L1, m2 * a2
    J1, J2 = I1 + m1 * a1**2 + m2 * L1**2, I2 + m2 * a2**2
    c, s = math.cos(al2 - al1), math.sin(al2 - al1)
    M = np.array([[J1, L1 * md2 * c], [L1 * md2 * c, J2]])
    rhs = np.array([L1 * md2 * s * w2**2 - md1 * g * math.sin(al1), -md2 * L1 * s * w1**2 - md2 * g * math.sin(al2)])
    acc = np.linalg.solve(M, rhs)
    return [w1, w2, acc[0], acc[1]]


def chain_mjcf(stiffness=(1.0, 10.0, 1e3, 1e5, 1e6), damping=0.01):
    """Five 0.5 m links of 1 kg (slender rods) hanging in a vertical plane, joint springs spanning six
    decades; the stiffest mode is near 1e4 rad/s."""
    body = ""
    for i, k in reversed(list(enumerate(stiffness))):
        pos = "0 0 0" if i == 0 else "0 0 -0.5"
        body = (f'<body name="link{i + 1}" pos="{pos}"><joint name="j{i + 1}" type="hinge" axis="0 1 0" '
                f'stiffness="{k:g}" damping="{damping:g}"/><inertial pos="0 0 -0.25" mass="1" '
                f'diaginertia="0.0208 0.0208 0.001"/>{body}</body>')
    return f"""<mujoco model="stiff_chain">
  <option gravity="0 0 -9.81" timestep="0.001"><flag contact="disable" limit="disable" actuation="disable"/></option>
  <worldbody>{body}</worldbody>
</mujoco>"""


# four-bar: ground link D, crank L1, coupler L2, rocker L3 (hinges about -y, in the x-z plane)
FB_D, FB_L, FB_M = 1.0, (0.4, 1.0, 0.7), (0.5, 1.2, 0.9)


def fourbar_angles(crank=0.6):
    e = lambda a: np.array([np.cos(a), np.sin(a)])  # noqa: E731
    L1, L2, L3 = FB_L
    z = scipy.optimize.fsolve(lambda z: L1 * e(crank) + L2 * e(z[0]) - np.array([FB_D, 0]) - L3 * e(z[1]),
                              [0.3, 1.6], xtol=1e-14)
    return np.array([crank, z[0], z[1]])


def fourbar_mjcf():
    """The four-bar with its body frames turned so that ``qpos = 0`` is closed (MuJoCo places the
    connect's second anchor at ``qpos = 0``); the loop closure is an equality ``connect``, made as
    stiff as MuJoCo allows (its time constant is raised to two timesteps where that is more)."""
    th = fourbar_angles()
    q = [th[0], th[1] - th[0], th[2]]
    (L1, L2, L3), (m1, m2, m3) = FB_L, FB_M
    inert = lambda m, l: f'<inertial pos="{l / 2} 0 0" mass="{m}" diaginertia="{m * l * l / 120} {m * l * l / 12} {m * l * l / 12}"/>'  # noqa: E731
    return f"""<mujoco model="four_bar">
  <compiler angle="radian"/>
  <option gravity="0 0 -9.81" timestep="0.001"><flag contact="disable" limit="disable" actuation="disable"/></option>
  <worldbody>
    <body name="crank" euler="0 {-q[0]} 0">
      <joint name="j1" type="hinge" axis="0 -1 0"/>{inert(m1, L1)}
      <body name="coupler" pos="{L1} 0 0" euler="0 {-q[1]} 0">
        <joint name="j2" type="hinge" axis="0 -1 0"/>{inert(m2, L2)}
      </body>
    </body>
    <body name="rocker" pos="{FB_D} 0 0" euler="0 {-q[2]} 0">
      <joint name="j3" type="hinge" axis="0 -1 0"/>{inert(m3, L3)}
    </body>
  </worldbody>
  <equality><connect name="loop" body1="coupler" body2="rocker" anchor="{L2} 0 0" solref="0.0002 1"
    solimp="0.99999 0.99999 0.001"/></equality>
</mujoco>"""


def fourbar_state():
    """Closed at ``qpos = 0`` (the frames are turned); crank rate 2 rad/s and the rates the loop allows."""
    th = fourbar_angles()
    L1, L2, L3 = FB_L
    n = lambda a: np.array([-np.sin(a), np.cos(a)])  # noqa: E731
    w23 = np.linalg.solve(np.stack([L2 * n(th[1]), -L3 * n(th[2])], 1), -L1 * 2.0 * n(th[0]))
    return np.zeros(3), np.array([2.0, w23[0] - 2.0, w23[1]])


def panda_tau(t, q, v):
    """The study's torque profile in NumPy (:func:`_study_torque.panda_torque_values`), a ``tau(t, q, v)``
    for MuJoCo's ``qfrc_applied``; jaxbody's scene has it as a :class:`jaxbody.FourierTorque`."""
    return panda_torque_values(t)


def panda_mjcf():
    path = pathlib.Path(__file__).resolve().parents[1] / "jaxbody" / "models" / "panda.xml"
    return path.read_text(), path


def scene_specs(quick: bool) -> dict:
    """Each scene: span, MJCF (or ``None``), initial state, torque, how its reference is made."""
    specs = {}
    specs["pendulum"] = dict(title="double pendulum (chaotic), Example 1", t1=2.0 if quick else 10.0,
                             xml=pendulum_mjcf(), q0=np.array([np.pi / 2, 0.0]), v0=np.zeros(2), reference="closed form",
                             kind="chaotic, smooth")
    xml, _ = panda_mjcf()
    m = mujoco.MjModel.from_xml_string(xml)
    home = m.key("home").qpos.copy() if m.nkey else np.zeros(m.nq)
    specs["panda"] = dict(title="Panda arm, gravity and a torque profile", t1=5.0, xml=xml, q0=home, v0=np.zeros(m.nv),
                          tau=panda_tau, reference="mj_forward", kind="robot arm, smooth forcing")
    specs["disk"] = dict(title="rolling disk (non-holonomic, Maggi)", t1=10.0, xml=None, reference="dopri8",
                         kind="non-holonomic constraints")
    specs["fourbar"] = dict(title="four-bar linkage (loop closure)", t1=10.0, xml=fourbar_mjcf(), reference="dopri8",
                            kind="holonomic loop")
    q0, v0 = fourbar_state()
    specs["fourbar"].update(q0=q0, v0=v0)
    specs["chain"] = dict(title="5-link chain, stiffnesses 1 … 1e6, damping 0.01", t1=5.0, xml=chain_mjcf(),
                          q0=np.full(5, 0.1), v0=np.zeros(5), reference="mj_forward", kind="stiff, lightly damped")
    return specs


def jb_scene(spec, name, dtype):
    """The jaxbody scene of a spec in ``dtype`` and its initial state."""
    if name == "disk":
        system = disk_example.rolling_disk()
        th, rho = 1.2, 0.3
        x = [0.3, -0.5, 6.0, -rho * 6.0, -rho * np.sin(th) * 0.3]
        q0, v0 = np.array([0.0, 0.0, 0.0, th, 0.0]), np.array(x)
        return jb.scene(system), q0.astype(dtype), v0.astype(dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # what MuJoCo models that jaxbody does not is switched off here
        model = jb.from_mjcf(spec["xml"], dtype=dtype)
    # the torque profile as an effect of the scene: the native one-call solves evaluate it
    effects = [panda_torque(jb, dtype)] if spec.get("tau") is not None else []
    return jb.scene(model, effects=effects), spec["q0"].astype(dtype), spec["v0"].astype(dtype)


# ----------------------------------------------------------------------------- references
def mj_model(spec):
    m = mujoco.MjModel.from_xml_string(spec["xml"])
    m.opt.disableflags |= (mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_LIMIT
                           | mujoco.mjtDisableBit.mjDSBL_ACTUATION)
    return m


def reference(spec, name, ts):
    """``(states (N_SAVE, nq + nv), seconds, convergence)``: the reference at the saved times and
    (for the dopri8 references) its distance to the same run at 1e-12. ``$WP_REFERENCE_CACHE``
    (a folder): keep references there between runs while developing."""
    cache = os.environ.get("WP_REFERENCE_CACHE")
    path = pathlib.Path(cache, f"{name}_{spec['t1']:g}.json") if cache else None
    if path is not None and path.exists():
        d = json.loads(path.read_text())
        return np.asarray(d["states"]), d["seconds"], d["convergence"]
    out = _reference(spec, name, ts)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(dict(states=out[0].tolist(), seconds=out[1], convergence=out[2])))
    return out


def _reference(spec, name, ts):
    t0 = time.perf_counter()
    T = spec["t1"]
    convergence = None
    if spec["reference"] == "closed form":
        a0 = np.array([spec["q0"][0], spec["q0"][0] + spec["q0"][1], spec["v0"][0], spec["v0"][0] + spec["v0"][1]])
        sol = scipy.integrate.solve_ivp(pendulum_closed_form, (0, T), a0, method="DOP853", rtol=REFERENCE_TOL,
                                        atol=REFERENCE_TOL, t_eval=ts)
        al = sol.y.T
        # absolute angles -> MuJoCo's relative joint angles
        states = np.stack([al[:, 0], al[:, 1] - al[:, 0], al[:, 2], al[:, 3] - al[:, 2]], 1)
    elif spec["reference"] == "mj_forward":
        m = mj_model(spec)
        d = mujoco.MjData(m)
        tau = spec.get("tau")

        def f(t, y):
            d.qpos[:], d.qvel[:] = y[: m.nq], y[m.nq:]
            d.time = t
            d.qfrc_applied[:] = 0.0 if tau is None else tau(t, None, None)
            mujoco.mj_forward(m, d)
            return np.concatenate([d.qvel, d.qacc])

        sol = scipy.integrate.solve_ivp(f, (0, T), np.concatenate([spec["q0"], spec["v0"]]), method="DOP853",
                                        rtol=REFERENCE_TOL, atol=REFERENCE_TOL, t_eval=ts)
        states = sol.y.T
    else:
        scene, q0, v0 = jb_scene(spec, name, np.float64)
        runs = {}
        for tol in (1e-12, REFERENCE_TOL):
            s = jb.simulate(scene, q0, v0, T, solver="dopri8", rtol=tol, atol=tol, saveat=ts, max_steps=2_000_000)
            runs[tol] = np.concatenate([np.asarray(s.q), np.asarray(s.v)], 1)
        states = runs[REFERENCE_TOL]
        convergence = float(np.max(np.abs(runs[1e-12] - states)))
    return states, time.perf_counter() - t0, convergence


# ----------------------------------------------------------------------------- jaxbody runs
def jb_solve_fn(scene, spec, solver, dtype, ts, max_steps, **fixed):
    """A compiled ``(q0, v0, knob) -> Solution`` where the knob is ``dt0`` (fixed step) or
    ``rtol = atol`` (adaptive); the knob is traced, so one compilation serves the sweep."""
    adaptive = solver not in FIXED

    @jax.jit
    def solve(q0, v0, knob):
        kw = dict(rtol=knob, atol=knob) if adaptive else dict(dt0=knob)
        return jb.simulate(scene, q0, v0, jnp.asarray(spec["t1"], dtype), solver=solver, saveat=ts,
                           max_steps=max_steps, throw=False, **kw, **fixed)

    return solve


def measure(run, ref, min_time):
    """Compile (first call minus one call), median wall time, the run's errors and counts."""
    t0 = time.perf_counter()
    sol = jax.block_until_ready(run())
    first = time.perf_counter() - t0
    timing = time_per_call(lambda: jax.block_until_ready(run()), min_time=min_time, repeats=3, budget=3 * min_time,
                           warmup=False)
    x = np.concatenate([np.asarray(sol.q, np.float64), np.asarray(sol.v, np.float64)], 1)
    ok = bool(np.asarray(sol.success)) and bool(np.all(np.isfinite(x)))
    err = np.max(np.abs(x - ref), axis=1) if ok else np.full(len(ref), np.inf)
    out = dict(wall_s=timing["median_s"], compile_s=max(first - timing["median_s"], 0.0), success=ok,
               final_error=float(err[-1]), path_error=float(np.max(err)), steps=int(np.asarray(sol.stats["num_steps"])),
               rejected=int(np.asarray(sol.stats["num_rejected_steps"])), solver_ran=sol.solver,
               solver_reason=sol.solver_reason)
    if sol.energy is not None and ok:
        bal = np.asarray(sol.energy_balance, np.float64) / max(abs(float(sol.energy0)), 1e-300)
        out["energy_drift"] = float(np.max(np.abs(bal)))
        out["energy_trace"] = [float(b) for b in bal]
    if sol.constraint_drift is not None and ok:
        pos = np.max(np.abs(np.asarray(sol.constraint_drift["position"], np.float64)), axis=1)
        out["constraint_drift"] = float(np.max(pos))
        out["constraint_trace"] = [float(p) for p in pos]
    return out


# ----------------------------------------------------------------------------- MuJoCo runs
def mj_run(spec, integrator, dt, ts, ref, scene, min_time):
    """``mujoco.rollout`` of one trajectory on one thread at timestep ``dt``."""
    m = mj_model(spec)
    m.opt.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{MJ_INTEGRATORS[integrator]}")
    m.opt.timestep = dt
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = spec["q0"], spec["v0"]
    mujoco.mj_forward(m, d)
    spec_bits = mujoco.mjtState.mjSTATE_FULLPHYSICS
    init = np.zeros(mujoco.mj_stateSize(m, spec_bits))
    mujoco.mj_getState(m, d, init, spec_bits)
    nstep = int(round(spec["t1"] / dt))  # dt from grid_dt: the span is a whole number of steps
    tau = spec.get("tau")
    control, cspec = None, mujoco.mjtState.mjSTATE_CTRL
    if tau is not None:
        mid = (np.arange(nstep) + 0.5) * dt
        control = np.stack([tau(t, None, None) for t in mid])[None]
        cspec = mujoco.mjtState.mjSTATE_QFRC_APPLIED
    state = np.zeros((1, nstep, init.size))
    with mujoco.rollout.Rollout(nthread=1) as r:
        def run():
            r.rollout(m, [d], init[None], control, control_spec=cspec, nstep=nstep, state=state)

        t0 = time.perf_counter()
        run()
        first = time.perf_counter() - t0
        timing = time_per_call(run, min_time=min_time, repeats=3, budget=3 * min_time, warmup=False)
    # the saved times are multiples of the timestep: state[k - 1] is the state at step k
    idx = np.round(ts / dt).astype(int)
    states = np.concatenate([init[None], state[0]])[idx]
    x = states[:, 1:1 + m.nq + m.nv]
    ok = bool(np.all(np.isfinite(x)))
    err = np.max(np.abs(x - ref), axis=1) if ok else np.full(len(ts), np.inf)
    out = dict(wall_s=timing["median_s"], first_call_s=first, success=ok, final_error=float(err[-1]),
               path_error=float(np.max(err)), steps=nstep)
    if ok and scene is not None:
        # energy and loop residual of MuJoCo's states, computed by jaxbody on the same model
        q, v = jnp.asarray(x[:, : m.nq]), jnp.asarray(x[:, m.nq:])
        energy = np.asarray(jax.vmap(scene.total_energy)(q, v))
        if spec.get("tau") is None and "damping" not in spec["title"]:
            out["energy_trace"] = [float(e) for e in (energy - energy[0]) / abs(energy[0])]
            out["energy_drift"] = float(np.max(np.abs(out["energy_trace"])))
        if scene.constraints is not None:
            pos, _ = jax.vmap(scene.constraint_drift)(jnp.asarray(ts), q, v)
            out["constraint_trace"] = [float(p) for p in np.max(np.abs(np.asarray(pos)), axis=1)]
            out["constraint_drift"] = float(max(out["constraint_trace"]))
    return out


# ----------------------------------------------------------------------------- sweeps
def sweeps(name, quick):
    """``{method: [knob, ...]}`` for a scene: dt for fixed steps, tolerance for adaptive ones,
    target error for auto, timestep for MuJoCo."""
    if quick:
        return {"rk4": [1e-2, 1e-3], "tsit5": [1e-6, 1e-9], "dopri8": [1e-8, 1e-11], "auto": [1e-4, 1e-6],
                "mj_rk4": [1e-2, 1e-3]}
    dts = [1e-2, 3e-3, 1e-3, 3e-4, 1e-4]
    low = [1e-3, 3e-4, 1e-4, 3e-5]
    tols = [1e-4, 1e-6, 1e-8, 1e-10, 1e-12]
    out = {"euler": low, "semi_implicit_euler": low, "heun": dts[1:], "rk4": dts,
           "tsit5": tols, "dopri5": tols, "dopri8": tols, "auto": [1e-4, 1e-6, 1e-8, 1e-10, 1e-12],
           "mj_euler": low, "mj_implicitfast": low, "mj_rk4": dts + [3e-5]}
    if name == "chain":
        # the stiffest mode bounds explicit steps: start where they are stable (explicit Euler is
        # unstable on an undamped mode at any step)
        out.update(euler=[1e-4, 3e-5], semi_implicit_euler=[1e-4, 3e-5], heun=[1e-4, 3e-5],
                   rk4=[3e-4, 1e-4, 3e-5], mj_euler=[1e-4, 3e-5], mj_implicitfast=[1e-4, 3e-5],
                   mj_rk4=[3e-4, 1e-4, 3e-5], kvaerno5=[1e-4, 1e-6, 1e-8],
                   tsit5=tols[:3], dopri5=tols[:3], dopri8=tols[:4], auto=[1e-4, 1e-6, 1e-8])
    if name in ("disk", "fourbar"):
        # the constrained field costs tens of µs per evaluation: the smallest steps of the
        # fixed-step sweeps (minutes each) add no point the others do not show
        out.update(euler=low[:3], semi_implicit_euler=low[:3], heun=dts[1:4], rk4=dts[:4], tsit5=tols[:4],
                   dopri8=tols[1:])
    return out


FLOAT32 = {"rk4": None, "tsit5": [1e-3, 1e-4, 1e-5, 1e-6, 1e-7], "auto": [1e-2, 1e-3, 1e-4]}
#: float32 on the scenes whose float64 solves are long or whose constrained field takes minutes to compile
FLOAT32_SHORT = {"rk4": None, "tsit5": [1e-3, 1e-4, 1e-5], "auto": [1e-2, 1e-3]}


def grid_dt(T, dt):
    """The step nearest ``dt`` that puts every one of the ``N_SAVE`` saved times on the step grid
    (no interpolation between steps, for jaxbody and MuJoCo alike)."""
    per_interval = max(1, round(T / (N_SAVE - 1) / dt))
    return T / ((N_SAVE - 1) * per_interval)


def run_scene(name, spec, quick, dtypes, min_time, log, methods=None):
    T = spec["t1"]
    ts64 = np.linspace(0.0, T, N_SAVE)
    ref, ref_s, convergence = reference(spec, name, ts64)
    log(f"{name}: reference ({spec['reference']}) in {ref_s:.1f} s" + (f", converged to {convergence:.1e}" if convergence is not None else ""))
    rec = dict(title=spec["title"], kind=spec["kind"], t1=T, reference=spec["reference"], reference_s=ref_s,
               reference_convergence=convergence, runs=[])
    plan = {k: [grid_dt(T, x) for x in v] if k in FIXED or k.startswith("mj_") else v
            for k, v in sweeps(name, quick).items()}
    if methods is not None:
        plan = {k: v for k, v in plan.items() if k in methods}
    for dtype in dtypes:
        scene, q0, v0 = jb_scene(spec, name, dtype)
        ts = jnp.asarray(ts64, dtype)
        f32 = FLOAT32_SHORT if name in ("chain", "disk", "fourbar") else FLOAT32
        todo = plan if dtype == np.float64 else {k: (v if v is not None else plan["rk4"]) for k, v in f32.items()
                                                 if methods is None or k in methods}
        # auto last: it reuses the compiled solve of the preset it picks
        todo = {k: todo[k] for k in sorted(todo, key=lambda k: k == "auto")}
        compiled = {}
        for method, knobs in todo.items():
            if method.startswith("mj_"):
                continue
            for knob in knobs:
                solver, choice = method, None
                if method == "auto":
                    # what simulate(..., target_error=knob) runs: the preset and tolerances chosen,
                    # through the sweep's compiled solve of that preset (one compilation per preset)
                    choice = choose_auto(scene, q0, 0.0, T, dtype, None, None, knob)
                    solver, knob_run = choice.solver, choice.rtol
                else:
                    knob_run = knob
                if solver not in compiled:
                    fixed = solver in FIXED
                    # Kvaerno5: each step is Newton iterations with a Jacobian; a tenth of the budget
                    steps = int(math.ceil(T / min(knobs))) + 10 if fixed else (100_000 if solver == "kvaerno5" else 1_000_000)
                    compiled[solver] = jb_solve_fn(scene, spec, solver, dtype, ts, steps)
                call = lambda f=compiled[solver], k=jnp.asarray(knob_run, dtype): f(q0, v0, k)  # noqa: E731
                try:
                    row = measure(call, ref, min_time)
                except Exception as err:  # a failed solve is a result of the study, not its end
                    row = dict(success=False, error=f"{type(err).__name__}: {str(err)[:200]}")
                row.update(engine="jaxbody", method=method, knob=knob, dtype=np.dtype(dtype).name,
                           evaluations=row.get("steps", 0) * STAGES[solver])
                if choice is not None:
                    row.update(solver_ran=choice.solver, solver_reason=choice.reason, tolerance=choice.rtol)
                rec["runs"].append(row)
                log(f"  {name} {np.dtype(dtype).name} {method} {knob:g}: " + _brief(row))
    if spec["xml"] is not None:
        scene64, _, _ = jb_scene(spec, name, np.float64)
        for method in [k for k in plan if k.startswith("mj_")]:
            for dt in plan[method]:
                try:
                    row = mj_run(spec, method, dt, ts64, ref, scene64, min_time)
                except Exception as err:
                    row = dict(success=False, error=f"{type(err).__name__}: {str(err)[:200]}")
                row.update(engine="mujoco", method=method, knob=dt, dtype="float64",
                           evaluations=row.get("steps", 0) * STAGES[method])
                rec["runs"].append(row)
                log(f"  {name} mujoco {method} {dt:g}: " + _brief(row))
    return rec


def _brief(row):
    if not row.get("success"):
        return "FAILED " + row.get("error", f"(steps {row.get('steps')})")
    return (f"final {row['final_error']:.2e} path {row['path_error']:.2e} wall {row['wall_s'] * 1e3:.2f} ms "
            f"steps {row['steps']}" + (f" compile {row['compile_s']:.1f} s" if "compile_s" in row else "")
            + (f" [{row['solver_ran']}]" if row.get("method") == "auto" else ""))


# ----------------------------------------------------------------------------- summaries
def fastest_to(runs, target, key="final_error"):
    """The fastest successful run reaching ``error <= target``, or None."""
    ok = [r for r in runs if r.get("success") and r[key] <= target]
    return min(ok, key=lambda r: r["wall_s"]) if ok else None


def label(r):
    if r is None:
        return "—"
    knob = "dt" if r["method"] in FIXED or r["engine"] == "mujoco" else ("target" if r["method"] == "auto" else "tol")
    name = ("MuJoCo " + MJ_INTEGRATORS[r["method"]].lower()) if r["engine"] == "mujoco" else r["method"]
    if r["method"] == "auto":
        name = f"auto→{r['solver_ran']}"
    return f"{name} {knob} {r['knob']:g} ({r['wall_s'] * 1e3:.3g} ms)"


TARGETS = (1e-4, 1e-6, 1e-8)


def summary_rows(record):
    rows = []
    for name, rec in record["scenes"].items():
        runs64 = [r for r in rec["runs"] if r["dtype"] == "float64"]
        for target in TARGETS:
            jb_best = fastest_to([r for r in runs64 if r["engine"] == "jaxbody"], target)
            auto = fastest_to([r for r in runs64 if r["method"] == "auto"], target)
            mj_best = fastest_to([r for r in runs64 if r["engine"] == "mujoco"], target)
            mj_rk4 = fastest_to([r for r in runs64 if r["method"] == "mj_rk4"], target)
            ratio = (f"{auto['wall_s'] / mj_rk4['wall_s']:.3g}" if auto and mj_rk4 else "—")
            rows.append((name, f"{target:g}", label(jb_best), label(auto), label(mj_best), ratio))
    return rows


def float32_rows(record):
    rows = []
    for name, rec in record["scenes"].items():
        for r in rec["runs"]:
            if r["dtype"] != "float32":
                continue
            rows.append((name, r["method"] + (f"→{r.get('solver_ran')}" if r["method"] == "auto" else ""), f"{r['knob']:g}",
                         f"{r['final_error']:.2e}" if r.get("success") else "failed",
                         r.get("steps", "—"), f"{r['wall_s'] * 1e3:.3g}" if r.get("success") else "—"))
    return rows


def all_rows(record):
    rows = []
    for name, rec in record["scenes"].items():
        for r in rec["runs"]:
            ok = r.get("success")
            rows.append((name, r["engine"], r["method"] + (f"→{r.get('solver_ran')}" if r["method"] == "auto" else ""),
                         r["dtype"], f"{r['knob']:g}",
                         f"{r['final_error']:.2e}" if ok else "failed", f"{r['path_error']:.2e}" if ok else "—",
                         f"{r['wall_s'] * 1e3:.3g}" if "wall_s" in r else "—",
                         f"{r['compile_s']:.2f}" if "compile_s" in r else "—", r.get("steps", "—"), r.get("evaluations", "—"),
                         f"{r['energy_drift']:.1e}" if "energy_drift" in r else "—",
                         f"{r['constraint_drift']:.1e}" if "constraint_drift" in r else "—"))
    return rows


def markdown(record) -> str:
    md = ["# Work precision: error against wall time, jaxbody's solvers and MuJoCo's integrators", "",
          stamp_markdown(record["stamp"]), "",
          "Error: max |x − x_ref| over the state's components (q and v) at the final time (final) and over "
          f"{N_SAVE} evenly spaced times (path). Wall time: median of repeated calls of a compiled solve saving those "
          f"{N_SAVE} states (jaxbody) or `mujoco.rollout` of one trajectory on one thread (MuJoCo, timer callback off). "
          "Compile time apart. Evaluations: steps × stages (Kvaerno5: a lower bound). See the docstring of "
          "`benchmarks/work_precision.py` for the scenes and their references.", "",
          "## References", "",
          markdown_table(["scene", "span (s)", "reference", "computed in (s)", "convergence (dopri8 1e-12 vs 1e-13)"],
                         [(n, r["t1"], r["reference"], f"{r['reference_s']:.1f}",
                           f"{r['reference_convergence']:.1e}" if r["reference_convergence"] is not None else "—")
                          for n, r in record["scenes"].items()]), "",
          "## Fastest run to a final-state error (float64)", "",
          markdown_table(["scene", "error ≤", "fastest jaxbody", "jaxbody auto", "fastest MuJoCo", "auto / MuJoCo RK4"],
                         summary_rows(record)), ""]
    f32 = float32_rows(record)
    if f32:
        md += ["## float32", "", "Final-state error in float32 (against the float64 reference), steps and wall time.", "",
               markdown_table(["scene", "method", "dt / tol / target", "final error", "steps", "wall (ms)"], f32), ""]
    md += ["## Every run", "",
           markdown_table(["scene", "engine", "method", "dtype", "dt / tol / target", "final error", "path error",
                           "wall (ms)", "compile (s)", "steps", "evaluations", "energy drift", "constraint drift"],
                          all_rows(record)), ""]
    return "\n".join(md)


STYLE = {"euler": ("C0", "o"), "semi_implicit_euler": ("C1", "o"), "heun": ("C2", "o"), "rk4": ("C3", "o"),
         "tsit5": ("C4", "s"), "dopri5": ("C5", "s"), "dopri8": ("C6", "s"), "kvaerno5": ("C7", "s"),
         "auto": ("k", "*"), "mj_euler": ("C0", "x"), "mj_implicitfast": ("C8", "x"), "mj_rk4": ("C3", "x")}


def plot(record, path, x="wall_s"):
    """Log–log work-precision diagrams: final-state error against wall time, one panel per scene
    (float64 solid, float32 dotted, MuJoCo dashed with crosses)."""
    import matplotlib

    matplotlib.use(os.environ.get("MPLBACKEND", "Agg"))
    import matplotlib.pyplot as plt

    names = list(record["scenes"])
    cols = min(3, len(names))
    rows = math.ceil(len(names) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.2 * rows), squeeze=False)
    for ax, name in zip(axes.flat, names):
        rec = record["scenes"][name]
        groups = {}
        for r in rec["runs"]:
            if r.get("success") and r["final_error"] > 0:
                groups.setdefault((r["engine"], r["method"], r["dtype"]), []).append(r)
        for (engine, method, dtype), runs in groups.items():
            runs = sorted(runs, key=lambda r: r[x])
            color, marker = STYLE.get(method, ("gray", "."))
            ls = "--" if engine == "mujoco" else (":" if dtype == "float32" else "-")
            lab = ("MuJoCo " + MJ_INTEGRATORS[method].lower()) if engine == "mujoco" else method + (" f32" if dtype == "float32" else "")
            ax.loglog([r[x] * (1e3 if x == "wall_s" else 1) for r in runs], [max(r["final_error"], 1e-16) for r in runs],
                      ls=ls, marker=marker, color=color, label=lab, ms=5)
        ax.set_title(f"{name}: {rec['title']}", fontsize=9)
        ax.set_xlabel("wall time (ms)" if x == "wall_s" else "vector-field evaluations")
        ax.set_ylabel("final-state error")
        ax.grid(True, which="both", alpha=0.3)
    labels = {lab for ax in axes.flat for lab in ax.get_legend_handles_labels()[1]}
    labels = shared_legend(fig, axes, len(names), ncol=min(7, len(labels)), fontsize=8)
    fig.tight_layout(rect=(0, 0.08 if len(labels) > 7 else 0.05, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_drift(record, path):
    """Energy drift (relative energy balance) and loop-closure residual against time, for the runs
    nearest 1e-8 final error of Tsit5, Dopri8 and MuJoCo's RK4 per scene."""
    import matplotlib

    matplotlib.use(os.environ.get("MPLBACKEND", "Agg"))
    import matplotlib.pyplot as plt

    names = list(record["scenes"])
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.6), squeeze=False)
    for ax, name in zip(axes[0], names):
        rec = record["scenes"][name]
        t = np.linspace(0, rec["t1"], N_SAVE)
        for method in ("tsit5", "dopri8", "auto", "mj_rk4"):
            runs = [r for r in rec["runs"] if r["method"] == method and r["dtype"] == "float64" and r.get("success")]
            trace = [r for r in runs if "energy_trace" in r] or [r for r in runs if "constraint_trace" in r]
            if not trace:
                continue
            r = min(trace, key=lambda r: abs(math.log10(max(r["final_error"], 1e-16)) + 8))
            key = "energy_trace" if "energy_trace" in r else "constraint_trace"
            y = np.maximum(np.abs(r[key]), 1e-17)
            ax.semilogy(t, y, label=f"{method} {r['knob']:g} ({'energy' if key == 'energy_trace' else 'loop'})")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("t (s)")
        ax.set_ylabel("|energy balance| / E0  or  |loop residual|")
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(scenes=None, quick=False, dtypes=None, min_time=None, log=print, methods=None) -> dict:
    """Run the study; returns the record (what ``main`` writes as JSON). ``methods``: a subset of
    the method names (``"rk4"``, ``"tsit5"``, ``"auto"``, ``"mj_rk4"``, ...) to run."""
    specs = scene_specs(quick)
    scenes = list(specs) if scenes is None else list(scenes)
    unknown = [s for s in scenes if s not in specs]
    if unknown:
        raise ValueError(f"unknown scenes {unknown}; choose from {list(specs)}")
    dtypes = ([np.float64] if quick else [np.float64, np.float32]) if dtypes is None else dtypes
    min_time = (0.02 if quick else 0.1) if min_time is None else min_time
    mujoco.set_mjcb_time(None)  # a Python timer callback would time every stage through Python
    record = {"stamp": stamp(), "quick": quick, "scenes": {}}
    start = time.perf_counter()
    for name in scenes:
        record["scenes"][name] = run_scene(name, specs[name], quick, dtypes, min_time, log, methods)
    record["stamp"]["load_average_end"] = load_average()
    record["wall_s"] = time.perf_counter() - start
    return record


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="the pendulum over 2 s, two points per sweep, float64")
    p.add_argument("--scenes", default=None, help="comma-separated subset of pendulum,panda,disk,fourbar,chain")
    p.add_argument("--out", default=None, help="results name (default work_precision[_quick])")
    args = p.parse_args(argv)
    scenes = args.scenes.split(",") if args.scenes else (["pendulum"] if args.quick else None)
    record = run(scenes, quick=args.quick)
    name = args.out or ("work_precision_quick" if args.quick else "work_precision")
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(record, indent=1))
    (RESULTS / f"{name}.md").write_text(markdown(record))
    plot(record, RESULTS / f"{name}.png")
    plot(record, RESULTS / f"{name}_evaluations.png", x="evaluations")
    plot_drift(record, RESULTS / f"{name}_drift.png")
    print(markdown(record).split("## Every run")[0])


if __name__ == "__main__":
    main()
