"""Maggi constraints: drift over 20 s per disk regime, energy lost at switches, cost of one
reduced-dynamics evaluation (disk, four-bar linkage).

    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python benchmarks/maggi.py [--quick]

Writes ``benchmarks/results/maggi.json`` and ``maggi.md`` (``maggi_quick.*`` with --quick,
which integrates 2 s instead of 20 s).
"""

import argparse
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import RESULTS, load_average, markdown_table, stamp, stamp_markdown, time_per_call  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxbody as jb  # noqa: E402
from jaxbody import constraints as jc  # noqa: E402
from jaxbody import maggi  # noqa: E402
from jaxbody.examples import disk as dk  # noqa: E402

RHO, TH = 0.3, 1.2


DISKS = {"sliding": dk.sliding_disk, "skating": dk.skating_disk, "rolling": dk.rolling_disk}


def disk_state(regime):
    """``(regime, system, q0, x0)`` of the disk in one regime, its velocities admissible there."""
    q0 = jnp.array([0.0, 0.0, 0.0, TH, 0.0])
    xx = [0.3, -0.5, 6.0, 0.7, 0.2]
    if regime != "sliding":
        xx[4] = -RHO * np.sin(TH) * xx[0]
    if regime == "rolling":
        xx[3] = -RHO * xx[2]
    return regime, DISKS[regime](), q0, jnp.asarray(xx)


def disk_states():
    return [disk_state(regime) for regime in DISKS]


def four_bar():
    import scipy.optimize

    d, l1, l2, l3 = 1.0, 0.4, 1.0, 0.7
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    for name, parent, pos, m, l in (("crank", None, (0, 0, 0), 0.5, l1), ("coupler", "crank", (l1, 0, 0), 1.2, l2),
                                    ("rocker", None, (d, 0, 0), 0.9, l3)):
        I = m * l**2 / 12
        b.add_body(name, parent=parent, pos=pos, mass=m, com=(l / 2, 0, 0), inertia=(I / 10, I, I),
                   joints=[jb.Hinge(axis=(0, -1, 0))])
    model = b.build()
    loop = jc.LoopClosure(model, "coupler", (l2, 0, 0), "rocker", (l3, 0, 0), axes=[(1, 0, 0), (0, 0, 1)])
    e = lambda t: np.array([np.cos(t), np.sin(t)])
    t1 = 0.6
    z = scipy.optimize.fsolve(lambda z: l1 * e(t1) + l2 * e(z[0]) - np.array([d, 0]) - l3 * e(z[1]), [0.3, 1.6], xtol=1e-14)
    q = jnp.array([t1, z[0] - t1, z[1]])
    s = maggi.constrain(model, [loop], q_ref=q)
    n = lambda t: np.array([-np.sin(t), np.cos(t)])
    w23 = np.linalg.solve(np.stack([l2 * n(z[0]), -l3 * n(z[1])], 1), -l1 * 2.0 * n(t1))
    v = jnp.array([2.0, w23[0] - 2.0, w23[1]])
    return s, q, v


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args(argv)
    record = {"stamp": stamp(), "drift": [], "switches": [], "cost": []}
    horizon = 2.0 if args.quick else 20.0
    for regime, system, q0, x0 in disk_states():
        for rtol in (1e-8, 1e-12):
            t0 = time.perf_counter()
            sol = jb.simulate(system, q0, x0, horizon, rtol=rtol, atol=rtol, n_save=2001, max_steps=1_000_000)
            wall = time.perf_counter() - t0
            _, vel = maggi.constraint_residuals(system, sol.t, sol.q, sol.v)
            record["drift"].append(dict(
                regime=regime, rtol=rtol, horizon_s=horizon, energy_drift=float(sol.energy_drift),
                max_velocity_residual=float(jnp.max(jnp.abs(vel), initial=0.0)),
                steps=int(sol.stats["num_steps"]), wall_s_incl_compile=wall,
            ))
            print(record["drift"][-1], flush=True)
    # four-bar drift (holonomic loop: position residual too)
    s, q, v = four_bar()
    for rtol in (1e-8, 1e-12):
        sol = jb.simulate(s, q, v, horizon, rtol=rtol, atol=rtol, n_save=2001, max_steps=1_000_000)
        pos, vel = maggi.constraint_residuals(s, sol.t, sol.q, sol.v)
        record["drift"].append(dict(
            regime="four-bar", rtol=rtol, horizon_s=horizon, energy_drift=float(sol.energy_drift),
            max_velocity_residual=float(jnp.max(jnp.abs(vel))), max_position_residual=float(jnp.max(jnp.abs(pos))),
            steps=int(sol.stats["num_steps"]),
        ))
        print(record["drift"][-1], flush=True)
    # smooth -> ice -> rough
    slide, skate, roll = dk.sliding_disk(), dk.skating_disk(), dk.rolling_disk()
    at_switch = []  # (t, q, x-) at each switch, as the phases hand it to the next constraint set

    def record_switch(t, q, x):
        at_switch.append((t, q, x))
        return q, x

    phases = jb.Phases(
        scenes=(jb.scene(slide), jb.scene(skate), jb.scene(roll)),
        events=(jb.Event(lambda t, q, x: slide.base.contact_point(q)[0] - 0.5),
                jb.Event(lambda t, q, x: skate.base.contact_point(q)[0] - 1.2)),
        transitions=(record_switch, record_switch),
    )
    jb.simulate(phases, jnp.array([0.0, 0.0, 0.3, 1.3, 0.0]), jnp.array([0.0, 0.5, 12.0, 1.0, 0.4]), 3.0,
                rtol=1e-10, atol=1e-10)
    reports = [maggi.switch_constraints(new.repartition(q_sw, x_sw, t_sw), t_sw, q_sw, x_sw)
               for (t_sw, q_sw, x_sw), new in zip(at_switch, (skate, roll))]
    for name, rep in zip(("smooth->ice", "ice->rough"), reports):
        record["switches"].append(dict(
            switch=name, t=float(rep.t), energy_before=float(rep.energy_before), energy_lost=float(rep.energy_lost),
            relative=float(rep.energy_lost / rep.energy_before), impulse=[float(v) for v in rep.impulse],
        ))
        print(record["switches"][-1], flush=True)
    # cost of one reduced-dynamics evaluation
    cases = [("disk (rolling)", dk.rolling_disk(), *disk_states()[2][2:]), ("disk (skating)", dk.skating_disk(), *disk_states()[1][2:]),
             ("four-bar", s, q, v)]
    for name, system, qq, xx in cases:
        f = jax.jit(lambda q_, x_, system=system: system.solve(0.0, q_, x_).xdot)
        t0 = time.perf_counter()
        f(qq, xx).block_until_ready()
        compile_s = time.perf_counter() - t0
        one = time_per_call(lambda: f(qq, xx).block_until_ready())
        fb = jax.jit(jax.vmap(lambda q_, x_, system=system: system.solve(0.0, q_, x_).xdot))
        qb, xb = jnp.tile(qq, (1024, 1)), jnp.tile(xx, (1024, 1))
        batch = time_per_call(lambda: fb(qb, xb).block_until_ready())
        record["cost"].append(dict(system=name, compile_s=compile_s, single_us=one["median_s"] * 1e6,
                                   batch1024_per_state_us=batch["median_s"] / 1024 * 1e6))
        print(record["cost"][-1], flush=True)
    record["stamp"]["load_average_end"] = load_average()
    suffix = "_quick" if args.quick else ""
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"maggi{suffix}.json").write_text(json.dumps(record, indent=1))
    md = ["# Maggi constraints: drift, switches, cost", "", stamp_markdown(record["stamp"]), "",
          f"## Drift over {horizon:g} s (Tsit5, atol = rtol)", "",
          markdown_table(["system", "rtol", "energy drift", "max |f*|", "max |φ|", "steps"],
                         [(d["regime"], f"{d['rtol']:.0e}", f"{d['energy_drift']:.2e}", f"{d['max_velocity_residual']:.2e}",
                           f"{d.get('max_position_residual', float('nan')):.2e}", d["steps"]) for d in record["drift"]]),
          "", "## Energy lost at the switches (smooth → ice at contact x = 0.5 m, ice → rough at 1.2 m)", "",
          markdown_table(["switch", "t (s)", "E before (J)", "lost (J)", "lost / E", "impulse (N·s)"],
                         [(w["switch"], f"{w['t']:.6f}", f"{w['energy_before']:.6f}", f"{w['energy_lost']:.6e}",
                           f"{w['relative']:.3e}", ", ".join(f"{v:.4g}" for v in w["impulse"])) for w in record["switches"]]),
          "", "## Cost of one reduced-dynamics evaluation (ẋ, with A, K, Λ)", "",
          markdown_table(["system", "compile (s)", "one state (µs)", "per state in a batch of 1024 (µs)"],
                         [(c["system"], f"{c['compile_s']:.2f}", f"{c['single_us']:.1f}", f"{c['batch1024_per_state_us']:.2f}")
                          for c in record["cost"]]), ""]
    (RESULTS / f"maggi{suffix}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
