"""Balancing-design benchmark: added mass, residual coupling, iterations and wall time.

    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python benchmarks/design.py [--quick] [--smoke]

Writes benchmarks/results/design{_quick}.json, .md and .png (trade-off curve of added mass
against residual coupling for the three-link arm), stamped with commit, machine and command.
Cases: closed form and optax synthesis (two penalties) for the 3-link arm, the cart-pendulum
and a spatial ball-joint tree, and the 3-link arm with link extensions (massless, up to twice
the link's reach) as design variables. ``--smoke``: the 3-link arm only, for the test suite.
"""

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import RESULTS, load_average, markdown_table, stamp, stamp_markdown  # noqa: E402
from _common import set_default_xla_flags  # noqa: E402

set_default_xla_flags()  # before JAX starts: the CPU fusion flag on jaxlib 0.10


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="fewer trade-off points")
    p.add_argument("--smoke", action="store_true", help="the 3-link arm only, two trade-off points (tests)")
    p.add_argument("--out", default=None, help="output folder (default benchmarks/results)")
    p.add_argument("--name", default=None, help="record name (default design or design_quick)")
    args = p.parse_args(argv)
    st = stamp()
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import jaxbody as jb
    from jaxbody import design

    def ball_tree():
        b = jb.ModelBuilder(gravity=(0.0, 0.0, -9.81), name="ball tree")
        b.add_body("torso", mass=3.0, com=(0.0, 0.05, 0.2), inertia=(0.05, 0.06, 0.03), joints=[jb.Ball()])
        b.add_body("left", parent="torso", pos=(0.15, 0.0, 0.4), mass=1.0, com=(0.1, 0.02, -0.15),
                   inertia=(0.01, 0.012, 0.004), joints=[jb.Ball()])
        b.add_body("right", parent="torso", pos=(-0.15, 0.0, 0.4), mass=1.2, com=(-0.05, 0.0, -0.2),
                   inertia=(0.012, 0.012, 0.004), joints=[jb.Ball()])
        b.add_body("hand", parent="left", pos=(0.05, 0.0, -0.3), mass=0.4, com=(0.0, 0.03, -0.08),
                   inertia=(0.002, 0.002, 0.001), joints=[jb.Ball()])
        return b.build()

    cases = [
        ("3-link arm (vertical plane)", jb.examples.three_link_manipulator(gravity=9.81)),
        ("cart-pendulum (translating base)", jb.examples.cart_pendulum().system),
        ("spatial ball-joint tree, 4 bodies", ball_tree()),
    ]
    penalties = [{"mass": 1.0, "inertia": 0.0}, {"mass": 1.0, "inertia": 1.0}]
    if args.smoke:
        cases, penalties = cases[:1], penalties[:1]
    rows, record = [], {"stamp": st, "cases": [], "tradeoff": {}}
    for name, system in cases:
        design.static_balance(system)  # compiles
        _, cf = design.static_balance(system)
        entries = [("closed form (mirror the links)", cf)]
        for pen in penalties:
            # first call compiles; the second is timed as a warm run
            design.balance(system, penalty=pen)
            _, rep = design.balance(system, penalty=pen)
            entries.append((f"optax AL + L-BFGS, penalty {pen}", rep))
        if name.startswith("3-link arm"):  # link extensions as design variables
            ext = {"length": (0.0, 2.0 * design.bodies.link_length(system)[list(design.required_bodies(system))])}
            pen = {"mass": 1.0, "inertia": 0.0}
            design.balance(system, penalty=pen, extensions=ext)
            _, rep = design.balance(system, penalty=pen, extensions=ext)
            entries.append((f"optax AL + L-BFGS, link extensions up to 2x reach (lengths "
                            f"{np.array2string(rep.extension_length, precision=3)}), penalty {pen}", rep))
        for how, rep in entries:
            rows.append([name, how, list(rep.bodies), f"{rep.added_mass:.4f}", f"{rep.added_inertia:.4f}",
                         f"{rep.coupling_before:.3e}", f"{rep.residual_coupling:.3e}",
                         f"{rep.residual_static_moment:.2e}", rep.iterations, f"{rep.wall_time:.2f}",
                         "yes" if rep.polished else "no"])
            record["cases"].append(dict(system=name, method=how, bodies=list(rep.bodies),
                                        added_mass=rep.added_mass, added_inertia=rep.added_inertia,
                                        coupling_before=rep.coupling_before, residual_coupling=rep.residual_coupling,
                                        residual_static_moment=rep.residual_static_moment,
                                        iterations=rep.iterations, wall_s=rep.wall_time, polished=rep.polished,
                                        counterweight_mass=rep.counterweight_mass.tolist(),
                                        counterweight_position=rep.counterweight_position.tolist(),
                                        extension_length=None if rep.extension_length is None
                                        else rep.extension_length.tolist()))
    weights = np.logspace(-2, 4, 2 if args.smoke else 4 if args.quick else 9)
    w, mass, coup, res = design.tradeoff_curve(cases[0][1], weights, steps=100, outer=2)
    record["tradeoff"] = dict(coupling_weight=w.tolist(), added_mass=mass.tolist(), residual_coupling=coup.tolist(),
                              residual_static_moment=res.tolist())
    st["load_average_end"] = load_average()
    import pathlib

    name = args.name or ("design_quick" if args.quick else "design")
    out = pathlib.Path(args.out) if args.out else RESULTS
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(record, indent=2) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4), constrained_layout=True)
    ax.loglog(mass, np.maximum(coup, 1e-17), "o-")
    ax.set_xlabel("added counterweight mass [kg]")
    ax.set_ylabel("residual coupling max|M_ij|/sqrt(M_ii M_jj)")
    ax.set_title(f"3-link arm trade-off ({st['commit']}, jax {st['versions']['jax']})", fontsize=9)
    fig.savefig(out / f"{name}.png", dpi=110)
    md = ["# Balancing-design benchmark", "", stamp_markdown(st), "",
          "Wall times are warm runs (the first call, which compiles, is not timed). Coupling: largest "
          "max|M_ij|/sqrt(M_ii M_jj) over 32 random configurations (3x3 block norms of D for the spatial tree).", "",
          markdown_table(["system", "method", "decoupled bodies", "added mass", "added inertia", "coupling before",
                          "coupling after", "residual |m̄| (rel.)", "iterations", "wall [s]", "closed-form polish"],
                         rows), "", "## Trade-off (3-link arm, penalty weight on |m̄|²)", "",
          markdown_table(["coupling weight", "added mass", "residual coupling", "residual |m̄| (rel.)"],
                         [[f"{a:.3g}", f"{b:.4f}", f"{c:.3e}", f"{d:.2e}"] for a, b, c, d in zip(w, mass, coup, res)]),
          "", f"![trade-off]({name}.png)", ""]
    (out / f"{name}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
