"""Identification benchmark: recovered-parameter errors, iterations and wall time.

    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python benchmarks/identify.py [--quick] [--spatial] [--smoke]

Writes benchmarks/results/identify{_quick}.json and .md, stamped with commit, machine and
command. Regressor identification of the Panda (noise-free and noisy torques, weighted least
squares with standard errors) and trajectory fitting through the integrator (double pendulum
with Levenberg-Marquardt, L-BFGS and Adam; three-link arm by single and multiple shooting; an 8 s
chaotic double-pendulum record by single and multiple shooting; link lengths; the rolling disk's
radius and mass; with --spatial also a spatial three-link arm with log-Cholesky inertias and
damping under PD-tracking excitation). "LM" = Levenberg-Marquardt. ``--smoke`` (for the test
suite): 100 Panda states and one short double-pendulum fit.
"""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import REPO, RESULTS, load_average, markdown_table, stamp, stamp_markdown  # noqa: E402
from _common import set_default_xla_flags  # noqa: E402

set_default_xla_flags()  # before JAX starts: the CPU fusion flag on jaxlib 0.10


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes")
    p.add_argument("--spatial", action="store_true", help="also fit the spatial arm (slow)")
    p.add_argument("--smoke", action="store_true", help="100 Panda states, one 1 s double-pendulum fit (tests)")
    p.add_argument("--out", default=None, help="output folder (default benchmarks/results)")
    p.add_argument("--name", default=None, help="record name (default identify or identify_quick)")
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
        panda = jb.from_mjcf(REPO / "jaxbody" / "models" / "panda.xml")
    t0 = time.perf_counter()
    base = idf.base_parameters(panda, n_samples=64, seed=1)
    t_base = time.perf_counter() - t0
    pi = np.asarray(idf.parameters(panda))
    true = base.base(pi)
    n = 100 if args.smoke else 200 if args.quick else 1000
    t = np.linspace(0.0, 10.0, n)
    q, v, a = idf.excitation_trajectory(panda, t, seed=1)
    t0 = time.perf_counter()
    Y = idf.regression.stacked_regressor(panda, q, v, a, ())
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

    def fit_case(name, system, build, x0, err_fn, tau_fn, t1, n_t, q0, optimizer, *, v0=None, segments=1,
                 use_v=True, steps=120, **kw):
        ts = np.linspace(0.0, t1, n_t)
        v0 = jnp.zeros(system.nv) if v0 is None else v0
        sol = jb.simulate(system, q0, v0, t1, tau=tau_fn, saveat=ts, rtol=1e-12, atol=1e-12)
        res = idf.fit_trajectory(build, x0, ts, sol.q, sol.v if use_v else None, tau=tau_fn,
                                 v0=None if use_v else v0, optimizer=optimizer, learning_rate=0.02, steps=steps,
                                 tol=1e-22, segments=segments, progress=False, **kw)
        err = err_fn(res)
        record["fits"].append(dict(case=name, optimizer=optimizer, segments=segments, iterations=res.n_iter,
                                   wall_s=res.wall_time, first_step_s=float(res.history["time"][0]),
                                   loss0=float(res.history["loss"][0]), loss=float(res.history["loss"][-1]),
                                   max_rel_param_error=err))
        print(record["fits"][-1], flush=True)

    def tau2(t, q, v):
        return jnp.stack([2.0 * jnp.sin(2.0 * t), jnp.cos(3.0 * t)])

    def tau3(t, q, v):
        return jnp.stack([jnp.sin(1.7 * t), 0.8 * jnp.cos(2.3 * t), 0.4 * jnp.sin(3.1 * t)])

    mc = lambda s: idf.Parameterisation(s, {"body_mass": "log", "body_com": "identity"})

    def planar_err(s_true):
        def err(res):
            s_fit = res.system
            e_m = np.abs(np.asarray(s_fit.body_mass) / np.asarray(s_true.body_mass) - 1).max()
            c_t, c_f = np.asarray(s_true.body_com), np.asarray(s_fit.body_com)
            e_c = (np.abs(c_f - c_t).max(axis=1) / np.linalg.norm(c_t, axis=1)).max()
            return float(max(e_m, e_c))
        return err

    def x0_of(P, fm, fc):
        x = P.initial()
        return {"body_mass": x["body_mass"] + jnp.log(jnp.asarray(fm)),
                "body_com": x["body_com"] * jnp.asarray(fc)[:, None]}

    quick = args.quick
    dp = jb.examples.double_pendulum()
    P = mc(dp)
    if args.smoke:
        fit_case("double pendulum 1 s, masses + CM, +-30 %", dp, P, x0_of(P, [1.3, 0.7], [0.7, 1.3]),
                 planar_err(dp), tau2, 1.0, 11, jnp.array([0.3, -0.2]), "levenberg_marquardt", steps=30)
    for opt, steps in (("levenberg_marquardt", 40), ("lbfgs", 80), ("adam", 200 if quick else 500)):
        if args.smoke or (quick and opt == "adam"):
            continue
        fit_case("double pendulum 1.5 s, masses + CM, +-30 %", dp, P, x0_of(P, [1.3, 0.7], [0.7, 1.3]),
                 planar_err(dp), tau2, 1.5, 31, jnp.array([0.3, -0.2]), opt, use_v=False, steps=steps)
    arm = jb.examples.three_link_manipulator(gravity=9.81)
    P = mc(arm)
    cases = [(1, "levenberg_marquardt", 40), (2, "levenberg_marquardt", 40), (2, "lbfgs", 120)]
    if not quick:
        cases.insert(1, (1, "lbfgs", 250))
    for segments, opt, steps in [] if args.smoke else cases:
        fit_case(f"3-link arm (vertical) 2 s, masses + CM, +-30 %, {segments} segment(s)", arm, P,
                 x0_of(P, [1.3, 0.7, 1.3], [0.7, 1.3, 0.7]), planar_err(arm), tau3, 2.0, 41,
                 jnp.array([0.4, 0.2, -0.3]), opt, segments=segments, steps=steps)
    P = mc(dp)
    for segments, steps in () if args.smoke else ((1, 30), (8, 60)):
        fit_case(f"double pendulum 8 s, large swings (chaotic), +-30 %, {segments} segment(s)", dp, P,
                 x0_of(P, [1.3, 0.7], [0.7, 1.3]), planar_err(dp), tau2, 8.0, 161, jnp.array([2.0, -1.0]),
                 "levenberg_marquardt", segments=segments, steps=steps)

    # link lengths (centres of mass at mid-link) and masses
    L_true, m_true = np.array([0.8, 0.6]), np.array([1.0, 0.6])
    dpl = jb.examples.double_pendulum(mass=m_true, com_distance=L_true / 2, length=L_true)

    def build_len(x):
        L = jnp.exp(x["log_length"])
        return eqx.tree_at(lambda s: (s.body_mass, s.hinge_pos, s.body_com), dpl,
                           (jnp.exp(x["log_mass"]), dpl.hinge_pos.at[1, 0].set(L[0]), dpl.body_com.at[:, 0].set(L / 2)))

    def len_err(res):
        return float(max(np.abs(np.exp(np.asarray(res.variables["log_length"])) / L_true - 1).max(),
                         np.abs(np.exp(np.asarray(res.variables["log_mass"])) / m_true - 1).max()))

    if not args.smoke:
        fit_case("double pendulum 1.5 s, link lengths (CM at mid-link) + masses, +-30 %", dpl, build_len,
                 {"log_length": jnp.log(L_true * np.array([1.3, 0.7])),
                  "log_mass": jnp.log(m_true * np.array([0.7, 1.3]))},
                 len_err, tau2, 1.5, 31, jnp.array([0.3, -0.2]), "levenberg_marquardt", steps=30)

    # rolling disk: radius and mass, with a known spin torque and push
    from jaxbody.examples import disk as dk

    disk = dk.rolling_disk(mass=2.0, radius=0.3)
    Pd = idf.Parameterisation(disk, {"base.mass": "log", "base.radius": "log"})
    xd = Pd.initial()

    def tau_d(t, q, x):
        z = jnp.zeros_like(t)
        return jnp.stack([z, z, 0.3 * jnp.sin(2.0 * t), 0.5 * jnp.cos(1.3 * t), z])

    def disk_err(res):
        return float(max(abs(float(res.system.base.mass) / 2.0 - 1), abs(float(res.system.base.radius) / 0.3 - 1)))

    if not args.smoke:
        fit_case("rolling disk 2 s, radius + mass, +-30 %", disk, Pd,
                 {"base.mass": xd["base.mass"] + np.log(1.3), "base.radius": xd["base.radius"] + np.log(0.7)},
                 disk_err, tau_d, 2.0, 21, jnp.array([0.0, 0.0, 0.0, 1.2, 0.0]), "levenberg_marquardt",
                 v0=jnp.array([0.4, -0.7, 5.0, -1.5, -0.3 * np.sin(1.2) * 0.4]), steps=30,
                 initial_state=lambda s, q, x: (q, jb.maggi.project_velocities(s, q, x)))

    if args.spatial and not args.smoke:
        b = jb.ModelBuilder(gravity=(0, 0, -9.81), name="arm3")
        b.add_body("base", mass=2.0, com=(0.02, 0.01, 0.1), inertia=(0.02, 0.025, 0.01),
                   joints=[jb.Hinge(axis=(0, 0, 1), damping=0.3)])
        b.add_body("upper", parent="base", pos=(0, 0, 0.2), mass=1.5, com=(0.25, 0.02, 0.0),
                   inertia=(0.004, 0.03, 0.03), joints=[jb.Hinge(axis=(0, 1, 0), damping=0.2)])
        b.add_body("fore", parent="upper", pos=(0.5, 0, 0), mass=0.8, com=(0.2, 0.0, 0.01),
                   inertia=(0.002, 0.012, 0.012), joints=[jb.Hinge(axis=(0, 1, 0), damping=0.1)])
        model = b.build()
        sbase = idf.base_parameters(model, extra=("damping",))

        def ref(t):
            return jnp.stack([0.8 * jnp.sin(1.3 * t) + 0.3 * jnp.sin(3.7 * t),
                              -0.3 + 0.6 * jnp.sin(2.1 * t) + 0.2 * jnp.cos(4.3 * t),
                              0.5 + 0.8 * jnp.sin(2.9 * t) + 0.3 * jnp.sin(5.1 * t)])

        def tau_pd(t, q, v):  # closed-loop excitation: PD tracking of a multi-sine reference
            qr, vr = jax.jvp(ref, (t,), (jnp.ones_like(t),))
            return 40.0 * (qr - q) + 6.0 * (vr - v)

        def base_err(res):
            bt = sbase.base(idf.parameters(model, ("damping",)))
            bf = sbase.base(idf.parameters(res.system, ("damping",)))
            return float(np.abs(bf - bt).max() / np.abs(bt).max())

        f = np.array([1.3, 0.7, 1.3])
        pert = eqx.tree_at(lambda m: (m.body_mass, m.body_com, m.body_inertia, m.dof_damping), model,
                           (model.body_mass * f, model.body_com * f[::-1, None],
                            model.body_inertia * f[:, None, None], model.dof_damping * f[::-1]))
        Ps = idf.InertialParameterisation(model, damping=True)
        fit_case("spatial 3-link arm 2 s (PD tracking), log-Cholesky inertias + damping, +-30 % "
                 "(error: base parameters)", model, Ps, Ps.initial(pert), base_err, tau_pd, 2.0, 41,
                 jnp.array([0.0, -0.3, 0.5]), "levenberg_marquardt", steps=80)

    st["load_average_end"] = load_average()
    import pathlib

    name = args.name or ("identify_quick" if args.quick else "identify")
    out = pathlib.Path(args.out) if args.out else RESULTS
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(record, indent=2) + "\n")
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
                         [[f["case"], f["optimizer"].replace("levenberg_marquardt", "LM"), f["iterations"],
                           f"{f['wall_s']:.1f}",
                           f"{f['first_step_s']:.1f}", f"{f['loss0']:.2e}", f"{f['loss']:.2e}",
                           f"{f['max_rel_param_error']:.2e}"] for f in record["fits"]]), ""]
    (out / f"{name}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
