"""The ``jaxbody`` command.

``jaxbody demo`` integrates the double pendulum of the spec's Example 1 (eq. 15) and writes a
plot and the trajectory; ``jaxbody --version`` prints the version. Unlike the library, the
command turns on float64 (``jax_enable_x64``) globally.
"""

import argparse
import csv
import json
import os
import pathlib
import sys
import time

__all__ = ["main"]

#: Initial state of the demo: absolute angles from the downward vertical (rad), at rest.
DEMO_ALPHA0 = (1.0, -0.5)
DEMO_ALPHA_DOT0 = (0.0, 0.0)


def _parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(prog="jaxbody", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"jaxbody {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo = sub.add_parser(
        "demo",
        help="simulate the double pendulum (spec Example 1) and write a plot and its trajectory",
        description=(
            "Integrate the double pendulum of Example 1 (eq. 15) from "
            f"alpha = {DEMO_ALPHA0} rad (absolute angles from the downward vertical), at rest, "
            "print a summary and write a PNG, a CSV trajectory and a JSON summary."
        ),
    )
    demo.add_argument("--t1", type=float, default=10.0, help="final time in s (default 10)")
    demo.add_argument("--out", type=pathlib.Path, default=pathlib.Path("outputs/demo"),
                      help="output folder (default outputs/demo)")
    demo.add_argument("--rtol", type=float, default=1e-10, help="relative tolerance (default 1e-10)")
    demo.add_argument("--atol", type=float, default=1e-10, help="absolute tolerance (default 1e-10)")
    demo.add_argument("--solver", choices=("dopri5", "tsit5", "dopri8"), default="dopri5",
                      help="adaptive Runge-Kutta solver (default dopri5)")
    demo.add_argument("--n-save", type=int, default=1001,
                      help="number of evenly spaced saved times (default 1001)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxbody`` command; returns the exit status."""
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command == "demo":
        return _demo(args)
    parser.print_help()
    return 2


def _demo(args) -> int:
    # Must precede JAX's backend initialisation (known XLA CPU issue with jax 0.10).
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody import examples

    system = examples.double_pendulum()
    q0 = jnp.asarray(DEMO_ALPHA0)
    v0 = jnp.asarray(DEMO_ALPHA_DOT0)

    def run():
        sol = jb.simulate(system, q0, v0, args.t1, solver=args.solver, rtol=args.rtol,
                          atol=args.atol, n_save=args.n_save)
        return jax.block_until_ready(sol)

    start = time.perf_counter()
    sol = run()
    wall = time.perf_counter() - start
    start = time.perf_counter()
    run()
    rerun = time.perf_counter() - start

    t, q, v = np.asarray(sol.t), np.asarray(sol.q), np.asarray(sol.v)
    energy, rel_err = np.asarray(sol.energy), np.asarray(sol.energy_error)
    drift = float(sol.energy_drift)
    stats = {k: int(x) for k, x in sol.stats.items()}

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    csv_path, json_path, png_path = out / "trajectory.csv", out / "summary.json", out / "double_pendulum.png"
    with open(csv_path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["t", "alpha1", "alpha2", "alpha1_dot", "alpha2_dot", "energy", "relative_energy_error"])
        for row in zip(t, q[:, 0], q[:, 1], v[:, 0], v[:, 1], energy, rel_err):
            writer.writerow([repr(float(x)) for x in row])
    summary = {
        "system": "double pendulum, spec Example 1 (eq. 15), jaxbody.examples.double_pendulum()",
        "coordinates": "absolute angles from the downward vertical (rad)",
        "alpha0": list(DEMO_ALPHA0),
        "alpha_dot0": list(DEMO_ALPHA_DOT0),
        "t1": args.t1,
        "solver": args.solver,
        "rtol": args.rtol,
        "atol": args.atol,
        "alpha_final": q[-1].tolist(),
        "alpha_dot_final": v[-1].tolist(),
        "energy0": float(energy[0]),
        "relative_energy_drift": drift,
        "stats": stats,
        "wall_time_s_incl_compile": wall,
        "wall_time_s_rerun": rerun,
        "jax_version": jax.__version__,
        "jaxbody_version": jb.__version__,
        "device": str(jax.devices()[0]),
    }
    json_path.write_text(json.dumps(summary, indent=2) + "\n")
    _plot(png_path, t, q, rel_err, args)

    print("jaxbody demo: double pendulum, spec Example 1 (eq. 15); angles from the downward vertical")
    print(f"  initial state   alpha = {DEMO_ALPHA0} rad, alpha_dot = {DEMO_ALPHA_DOT0} rad/s")
    print(f"  integrated      t = 0 .. {args.t1:g} s with {args.solver}, rtol={args.rtol:g}, atol={args.atol:g}")
    print(f"  final state     alpha = ({q[-1, 0]:.10f}, {q[-1, 1]:.10f}) rad, "
          f"alpha_dot = ({v[-1, 0]:.10f}, {v[-1, 1]:.10f}) rad/s")
    print(f"  energy          E0 = {energy[0]:.12g}; relative drift max|E-E0|/|E0| = {drift:.3e}")
    print(f"  steps           accepted {stats['num_accepted_steps']}, rejected {stats['num_rejected_steps']}")
    print(f"  wall time       {wall:.2f} s incl. compile ({rerun:.3f} s re-run) on {jax.devices()[0].platform}")
    for path in (png_path, csv_path, json_path):
        print(f"wrote {path}")
    sys.stdout.flush()
    return 0


def _plot(path, t, q, rel_err, args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_angle, ax_drift) = plt.subplots(2, 1, sharex=True, figsize=(8, 6), constrained_layout=True)
    ax_angle.plot(t, q[:, 0], label=r"$\alpha_1$")
    ax_angle.plot(t, q[:, 1], label=r"$\alpha_2$")
    ax_angle.set_ylabel("angle from downward vertical [rad]")
    ax_angle.legend(loc="upper right")
    ax_angle.set_title(f"Double pendulum (spec Example 1), {args.solver}, rtol={args.rtol:g}, atol={args.atol:g}")
    ax_drift.plot(t, rel_err)
    ax_drift.set_ylabel(r"$(E - E_0)/|E_0|$")
    ax_drift.set_xlabel("t [s]")
    ax_drift.ticklabel_format(axis="y", style="sci", scilimits=(0, 0))
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
