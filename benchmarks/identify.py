"""Identification benchmark: recovered-parameter errors, iterations and wall time.

    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python benchmarks/identify.py [--quick] [--spatial]

Writes benchmarks/results/identify{_quick}.json and .md, stamped with commit, machine and
command. Regressor identification of the Panda (noise-free and noisy torques, weighted least
squares with standard errors) and trajectory fitting through the integrator (double pendulum
with L-BFGS and Adam, three-link arm by multiple shooting; with --spatial also a spatial
three-link arm with log-Cholesky inertias and damping).
"""

import argparse
import json
import os
import sys
import time

os.environ.setdefault("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import REPO, RESULTS, load_average, markdown_table, stamp, stamp_markdown  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes")
    p.add_argument("--spatial", action="store_true", help="also fit the spatial arm (slow)")
    args = p.parse_args(argv)
    st = stamp()
    import warnings

    import jax

    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody import identify as idf

    rows, record = [], {"stamp": st, "panda": {}, "fits": []}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        panda = jb.from_mjcf(REPO.parent / "shared" / "models" / "panda.xml")
    t0 = time.perf_counter()
    base = idf.base_parameters(panda, n_samples=64, seed=1)
    t_base = time.perf_counter() - t0
    pi = np.asarray(idf.parameters(panda))
    true = base.base(pi)
    n = 200 if args.quick else 1000
    t = np.linspace(0.0, 10.0, n)
    q, v, a = idf.excitation_trajectory(panda, t, seed=1)
    t0 = time.perf_counter()
    Y = idf._stack(panda, q, v, a, ())
    t_reg = time.perf_counter() - t0
    tau0 = Y @ pi
    denom = np.maximum(np.abs(true), 1e-3 * np.abs(true).max())
    fit0 = idf.least_squares(panda, q, v, a, tau0, base, noise_std=np.ones(panda.nv))
    err0 = float(np.max(np.abs(fit0.estimate - true) / denom))
    sigma = np.full(panda.nv, 0.05)
    tau = tau0 + sigma * np.random.default_rng(0).normal(size=tau0.shape)
    t0 = time.perf_counter()
    fit = idf.least_squares(panda, q, v, a, tau, base)
    t_ls = time.perf_counter() - t0
    z = (fit.estimate - true) / fit.standard_error
    rel_se = fit.standard_error / denom
    record["panda"] = dict(
        rank=base.rank, n_param=len(base.names), base_parameters_s=t_base, n_states=n,
        regressor_stack_s=t_reg, noise_free_max_rel_error=err0, noise_std=sigma.tolist(),
        noisy_mean_z2=float(np.mean(z**2)), noisy_max_abs_z=float(np.abs(z).max()),
        noisy_median_rel_se=float(np.median(rel_se)), least_squares_s=t_ls,
        estimated_noise_std=fit.noise_std.tolist(),
    )

    def fit_case(name, system, fields, true_fn, x0_fn, tau_fn, t1, n_t, q0, optimizer, segments=1, use_v=False,
                 steps=120):
        ts = np.linspace(0.0, t1, n_t)
        sol = jb.simulate(system, q0, jnp.zeros(system.nv), t1, tau=tau_fn, saveat=ts, rtol=1e-11, atol=1e-11)
        P = fields(system)
        x0 = x0_fn(P, P.initial())
        res = idf.fit_trajectory(P, x0, ts, sol.q, sol.v if use_v else None, tau=tau_fn,
                                 v0=None if use_v else jnp.zeros(system.nv), optimizer=optimizer,
                                 learning_rate=0.02, steps=steps, tol=1e-20, segments=segments, progress=False)
        err = true_fn(system, res.system)
        record["fits"].append(dict(case=name, optimizer=optimizer, segments=segments, iterations=res.n_iter,
                                   wall_s=res.wall_time, first_step_s=float(res.history["time"][0]),
                                   loss0=float(res.history["loss"][0]), loss=float(res.history["loss"][-1]),
                                   max_rel_param_error=err))

    def tau2(t, q, v):
        return jnp.stack([2.0 * jnp.sin(2.0 * t), jnp.cos(3.0 * t)])

    def tau3(t, q, v):
        return jnp.stack([jnp.sin(1.7 * t), 0.8 * jnp.cos(2.3 * t), 0.4 * jnp.sin(3.1 * t)])

    mc = lambda s: idf.Parameterisation(s, {"body_mass": "log", "body_com": "identity"})

    def planar_err(s_true, s_fit):
        e_m = np.abs(np.asarray(s_fit.body_mass) / np.asarray(s_true.body_mass) - 1).max()
        c_t, c_f = np.asarray(s_true.body_com), np.asarray(s_fit.body_com)
        e_c = (np.abs(c_f - c_t).max(axis=1) / np.linalg.norm(c_t, axis=1)).max()
        return float(max(e_m, e_c))

    def x0_of(fm, fc):
        return lambda P, x: {"body_mass": x["body_mass"] + jnp.log(jnp.asarray(fm)),
                             "body_com": x["body_com"] * jnp.asarray(fc)[:, None]}

    dp = jb.examples.double_pendulum()
    for opt in ("lbfgs", "adam"):
        fit_case("double pendulum, masses + CM, +-30 %", dp, mc, planar_err, x0_of([1.3, 0.7], [0.7, 1.3]), tau2,
                 1.5, 31, jnp.array([0.3, -0.2]), opt, steps=80 if opt == "lbfgs" else (200 if args.quick else 500))
    arm = jb.examples.three_link_manipulator(gravity=9.81)
    for segments, steps in ((1, 250), (2, 120)):
        fit_case(f"3-link arm (vertical), masses + CM, +-30 %, {segments} shooting segment(s)", arm, mc,
                 planar_err, x0_of([1.3, 0.7, 1.3], [0.7, 1.3, 0.7]), tau3, 2.0, 41, jnp.array([0.4, 0.2, -0.3]),
                 "lbfgs", segments=segments, use_v=True, steps=steps)
    if args.spatial:
        b = jb.ModelBuilder(gravity=(0, 0, -9.81), name="arm3")
        b.add_body("base", mass=2.0, com=(0.02, 0.01, 0.1), inertia=(0.02, 0.025, 0.01),
                   joints=[jb.Hinge(axis=(0, 0, 1), damping=0.3)])
        b.add_body("upper", parent="base", pos=(0, 0, 0.2), mass=1.5, com=(0.25, 0.02, 0.0),
                   inertia=(0.004, 0.03, 0.03), joints=[jb.Hinge(axis=(0, 1, 0), damping=0.2)])
        b.add_body("fore", parent="upper", pos=(0.5, 0, 0), mass=0.8, com=(0.2, 0.0, 0.01),
                   inertia=(0.002, 0.012, 0.012), joints=[jb.Hinge(axis=(0, 1, 0), damping=0.1)])
        model = b.build()
        sbase = idf.base_parameters(model, extra=("damping",))

        def tau_s(t, q, v):
            return jnp.stack([0.5 * jnp.sin(1.7 * t), 2.0 * jnp.cos(2.3 * t) + 10.0, jnp.sin(3.1 * t)])

        def base_err(m_true, m_fit):
            bt = sbase.base(idf.parameters(m_true, ("damping",)))
            bf = sbase.base(idf.parameters(m_fit, ("damping",)))
            return float(np.abs(bf - bt).max() / np.abs(bt).max())

        f = np.array([1.3, 0.7, 1.3])

        def x0_s(P, x):
            pert = eqx.tree_at(lambda m: (m.body_mass, m.body_com, m.body_inertia, m.dof_damping), model,
                               (model.body_mass * f, model.body_com * f[::-1, None],
                                model.body_inertia * f[:, None, None], model.dof_damping * f[::-1]))
            return P.initial(pert)

        fit_case("spatial 3-link arm, log-Cholesky inertias + damping, +-30 % (error: base parameters)", model,
                 lambda m: idf.InertialParameterisation(m, damping=True), base_err, x0_s, tau_s, 1.5, 31,
                 jnp.array([0.0, -0.3, 0.5]), "lbfgs", use_v=True, steps=200)

    st["load_average_end"] = load_average()
    suffix = "_quick" if args.quick else ""
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"identify{suffix}.json").write_text(json.dumps(record, indent=2) + "\n")
    pd = record["panda"]
    md = ["# Identification benchmark", "", stamp_markdown(st), "", "## Panda, regressor and least squares", "",
          markdown_table(["quantity", "value"], [
              ["parameters / base parameters", f"{pd['n_param']} / {pd['rank']}"],
              ["base_parameters (64 random states) [s]", f"{pd['base_parameters_s']:.2f}"],
              [f"regressor stack, {pd['n_states']} states [s] (incl. compile)", f"{pd['regressor_stack_s']:.2f}"],
              ["noise-free: max relative error of base parameters", f"{pd['noise_free_max_rel_error']:.2e}"],
              ["noisy (sigma 0.05 N m): mean z^2 / max |z|", f"{pd['noisy_mean_z2']:.3f} / {pd['noisy_max_abs_z']:.2f}"],
              ["noisy: median standard error relative to the parameter", f"{pd['noisy_median_rel_se']:.2e}"],
              ["weighted least squares [s]", f"{pd['least_squares_s']:.3f}"],
          ]), "", "## Trajectory fitting through the integrator", "",
          markdown_table(["case", "optimizer", "iterations", "wall [s]", "first step (compile) [s]", "loss start",
                          "loss end", "max rel. parameter error"],
                         [[f["case"], f["optimizer"], f["iterations"], f"{f['wall_s']:.1f}",
                           f"{f['first_step_s']:.1f}", f"{f['loss0']:.2e}", f"{f['loss']:.2e}",
                           f"{f['max_rel_param_error']:.2e}"] for f in record["fits"]]), ""]
    (RESULTS / f"identify{suffix}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
