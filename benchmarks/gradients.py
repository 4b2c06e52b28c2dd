"""What does the gradient of a 1000-step rollout cost, next to the rollout itself?

For each model (default ``panda`` and ``chain20``) this measures, each case in its own worker
process (so peak memory is that case's own):

* ``forward``: ``jax.jit`` of a loss on the final state of
  ``jb.simulate(model, q0, v0, T, solver="rk4", dt0=1e-3, saveat=SaveAt(t1=True))`` over
  ``--steps`` steps (default 1000), loss = |q(T)|² + |v(T)|²;
* ``checkpoint``: ``jax.jit(jax.grad(loss))`` w.r.t. (q0, v0), recursive checkpointing
  (diffrax ``RecursiveCheckpointAdjoint``, jaxbody's default);
* ``backsolve``: the same gradient by the continuous adjoint (``BacksolveAdjoint``);
* ``forward_mode``: ``jax.jacfwd`` of the loss w.r.t. ``--fwd-params`` parameters (offsets of
  the first coordinates of q0), diffrax ``ForwardMode``;

each with compile time, run time (median, warm), XLA's ``memory_analysis()`` of the compiled
executable (temporary, argument and output bytes) and the worker's peak resident memory. The
checkpointed gradient is compiled a second time for a 16× longer horizon to show whether its
memory grows with the number of steps (jaxbody's default adjoint keeps a checkpoint per step
up to a fixed memory budget, ``jaxbody.simulation.CHECKPOINT_BYTES``, then recomputes). The gradients of the three adjoints are compared with
each other (a fast wrong gradient shows). Records ``benchmarks/results/<name>.{md,json,png}``
(default ``gradients``), stamped; verdict for the gradient target (gradient ≤ 3× the forward
rollout, memory bounded). The ratio is the median of ``--pairs`` (default 5) forward and
gradient timings taken one after the other in the checkpoint worker: on a virtual machine the
speed drifts by 10-20% between separate workers, which moves a ratio of two workers as much.

Usage::

    .venv/bin/python benchmarks/gradients.py
    .venv/bin/python benchmarks/gradients.py --models panda --steps 1000 --modes forward,checkpoint
"""

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _common  # noqa: E402
from dynamics import XLA_DEFAULT_FLAG, _compile, _mujoco_rigid, _Record, _states  # noqa: E402
from throughput import model_path  # noqa: E402

MODES = ("forward", "checkpoint", "backsolve", "forward_mode")
DT = 1e-3


def _peak_rss_bytes():
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


def _memory(compiled):
    try:
        ma = compiled.memory_analysis()
    except Exception as e:  # noqa: BLE001 - not every backend has it
        return {"error": str(e)[:200]}
    keys = ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes",
            "alias_size_in_bytes", "generated_code_size_in_bytes")
    return {k: int(getattr(ma, k)) for k in keys if hasattr(ma, k)}


def worker(cfg, rec):
    import warnings

    import jax

    jax.config.update("jax_enable_x64", True)
    import diffrax
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb

    jax.jit(lambda x: x + 1.0)(jnp.ones(2)).block_until_ready()  # XLA start-up
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mjcf(cfg["path"])
    if cfg.get("kernel"):
        model = jb.scene(model, kernel=cfg["kernel"])
    m = _mujoco_rigid(cfg["path"])
    q, v, _, _ = _states(m, 1, cfg["seed"])
    q0, v0 = jnp.asarray(q[0]), jnp.asarray(v[0])
    mode, steps = cfg["mode"], cfg["steps"]
    rec.data.update(model=cfg["model"], mode=mode, steps=steps, nq=int(m.nq), nv=int(m.nv),
                    rss_before_compile_bytes=_peak_rss_bytes())
    rep = dict(min_time=cfg["min_time"], repeats=cfg["repeats"])
    adjoint = _common.simulate_adjoint("forward" if mode == "forward_mode" else
                                       "checkpoint" if mode == "forward" else mode)

    def make_loss(horizon):
        T = jnp.asarray(horizon * DT)

        def loss(q0, v0):
            budget = {} if cfg.get("max_steps") == "default" else {"max_steps": horizon + 16}
            sol = jb.simulate(model, q0, v0, T, solver="rk4", dt0=DT, saveat=diffrax.SaveAt(t1=True),
                              adjoint=adjoint, **budget)
            return jnp.sum(sol.q[-1] ** 2) + jnp.sum(sol.v[-1] ** 2)

        return loss

    k = min(cfg["fwd_params"], int(m.nq))
    E = jnp.eye(int(m.nq))[:, :k]

    def build(horizon):
        loss = make_loss(horizon)
        if mode == "forward":
            return loss, (q0, v0)
        if mode == "forward_mode":
            return (lambda th, q0, v0: jax.jacfwd(lambda t: loss(q0 + E @ t, v0))(th)), (jnp.zeros(k), q0, v0)
        return jax.grad(loss, argnums=(0, 1)), (q0, v0)

    fn, args = build(steps)
    rec.data["running"] = "compile"
    rec.save()
    jitted, compiled, out, t = _compile(jax, fn, args)
    rec.data.update(compile=t, memory=_memory(compiled), rss_after_compile_bytes=_peak_rss_bytes(), running="run")
    rec.save()
    tm = _common.time_per_call(lambda: jax.block_until_ready(jitted(*args)), warmup=False, **rep)
    rec.data.update(run=tm, peak_rss_bytes=_peak_rss_bytes())
    leaves = [np.asarray(x, np.float64).ravel() for x in jax.tree.leaves(out)]
    rec.data["value"] = np.concatenate(leaves).tolist()
    rec.data["finite"] = bool(all(np.isfinite(x).all() for x in leaves))
    rec.data.pop("running")
    rec.save()
    if mode == "checkpoint" and cfg.get("pairs"):
        # the ratio measured in pairs in this process: the forward rollout and the gradient timed
        # one after the other, ``pairs`` times (a VM's speed drifts between separate workers)
        loss = make_loss(steps)
        fwd = jax.jit(loss)
        jax.block_until_ready(fwd(q0, v0))
        pair_rep = dict(min_time=cfg["min_time"] / 2, repeats=max(cfg["repeats"] // 2, 1))
        ratios, fwd_s, grad_s = [], [], []
        for _ in range(cfg["pairs"]):
            tf = _common.time_per_call(lambda: jax.block_until_ready(fwd(q0, v0)), **pair_rep)["median_s"]
            tg = _common.time_per_call(lambda: jax.block_until_ready(jitted(*args)), **pair_rep)["median_s"]
            fwd_s.append(tf), grad_s.append(tg), ratios.append(tg / tf)
        rec.data["paired"] = {"forward_s": fwd_s, "gradient_s": grad_s, "ratios": ratios,
                              "ratio_median": float(np.median(ratios))}
        rec.save()
    if mode in ("checkpoint", "backsolve") and cfg["horizon_factor"] > 1:
        fn4, args4 = build(steps * cfg["horizon_factor"])
        _, c4, _, t4 = _compile(jax, fn4, args4)
        rec.data["longer_horizon"] = {"steps": steps * cfg["horizon_factor"], "memory": _memory(c4),
                                      "compile_total_s": t4["compile_total_s"]}
        rec.save()


def _get(d, *keys):
    for key in keys:
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


def _mib(x):
    return "—" if x is None else f"{x / 2**20:.3g}"


def analyse(results):
    """Ratios to the forward rollout, gradient agreement, the gradient-cost verdict."""
    import numpy as np

    out = {}
    for model, r in results["runs"].items():
        f = _get(r, "forward", "run", "median_s")
        fmem = _get(r, "forward", "memory", "temp_size_in_bytes")
        a = out[model] = {}
        for mode in MODES:
            t = _get(r, mode, "run", "median_s")
            mem = _get(r, mode, "memory", "temp_size_in_bytes")
            a[mode] = {"time_ratio": t / f if t and f else None, "temp_ratio": mem / fmem if mem and fmem else None}
        ck, bs, fm = (_get(r, m, "value") for m in ("checkpoint", "backsolve", "forward_mode"))
        if ck and bs:
            x, y = np.asarray(ck), np.asarray(bs)
            a["backsolve_vs_checkpoint_rel"] = float(np.max(np.abs(x - y)) / max(np.max(np.abs(x)), 1e-300))
        if ck and fm:
            x, y = np.asarray(ck)[: len(fm)], np.asarray(fm)  # grad w.r.t. q0 first, then v0
            a["forward_mode_vs_checkpoint_rel"] = float(np.max(np.abs(x - y)) / max(np.max(np.abs(x)), 1e-300))
    T = []
    for model, a in out.items():
        r = results["runs"][model]
        paired = _get(r, "checkpoint", "paired", "ratio_median")
        # the paired ratio (same process, interleaved) when measured, else the ratio of the workers
        tr = paired if paired is not None else a["checkpoint"]["time_ratio"]
        pair_txt = ""
        if paired is not None:
            rs = _get(r, "checkpoint", "paired", "ratios")
            pair_txt = (f" (median of {len(rs)} interleaved pairs in one process, "
                        f"{min(rs):.3g}-{max(rs):.3g}; separate workers: {a['checkpoint']['time_ratio']:.3g}x)")
        m1 = _get(r, "checkpoint", "memory", "temp_size_in_bytes")
        m4 = _get(r, "checkpoint", "longer_horizon", "memory", "temp_size_in_bytes")
        hf = results["horizon_factor"]
        if tr is None:
            T.append(dict(id="gradient-cost", target=f"{model}: gradient (checkpointed) <= 3x forward rollout, memory bounded",
                          verdict="NOT MEASURED", detail="checkpoint or forward case failed"))
            continue
        bounded = m1 is not None and m4 is not None and m4 < hf * m1 * 0.75
        mem_txt = (f"temp memory {_mib(m1)} MiB at {results['steps']} steps, {_mib(m4)} MiB at {hf}x the horizon"
                   if m4 is not None else "longer horizon not measured")
        T.append(dict(id="gradient-cost", target=f"{model}: gradient of a {results['steps']}-step rollout (checkpointed) <= 3x forward, memory bounded",
                      verdict="MET" if tr <= 3 and bounded else "NOT MET",
                      detail=f"time {tr:.3g}x forward{pair_txt}; {mem_txt} ({'sub-linear' if bounded else 'not sub-linear'})"))
    return out, T


def write_markdown(results, path):
    s = results["stamp"]
    L = [f"# Gradient of a {results['steps']}-step RK4 rollout vs the rollout", "", _common.stamp_markdown(s),
         f"- wall time: {s.get('wall_s', 0):.0f} s", ""]
    if results.get("note"):
        L += [f"**Note.** {results['note']}", ""]
    L += [f"Loss = |q(T)|² + |v(T)|² of `jb.simulate(..., solver=\"rk4\", dt0=1e-3, saveat=SaveAt(t1=True))`, "
          f"T = {results['steps']} steps, float64, kernel {results.get('kernel') or 'default (vectorised)'}. `checkpoint`/`backsolve`: `jax.grad` w.r.t. (q0, v0); "
          f"`forward_mode`: `jax.jacfwd` w.r.t. {results['fwd_params']} offsets of q0. Time: warm median of the "
          "jitted call. Temp: XLA `memory_analysis().temp_size_in_bytes` of the compiled executable; peak RSS: the "
          "worker process's maximum resident memory (includes compilation and the Python/JAX runtime).", ""]
    rows = []
    for model, r in results["runs"].items():
        a = results["analysis"].get(model, {})
        for mode in MODES:
            w = r.get(mode)
            if w is None:
                continue
            t = _get(w, "run", "median_s")
            rows.append([model, mode, w.get("status"), f"{t * 1e3:.4g}" if t else w.get("running", "—"),
                         f"{a[mode]['time_ratio']:.3g}" if a.get(mode, {}).get("time_ratio") else "—",
                         f"{_get(w, 'compile', 'compile_total_s'):.3g}" if _get(w, "compile", "compile_total_s") else "—",
                         _mib(_get(w, "memory", "temp_size_in_bytes")),
                         f"{a[mode]['temp_ratio']:.3g}" if a.get(mode, {}).get("temp_ratio") else "—",
                         _mib(_get(w, "longer_horizon", "memory", "temp_size_in_bytes")),
                         _mib(_get(w, "peak_rss_bytes") or _get(w, "rss_after_compile_bytes"))])
    L += [_common.markdown_table(["model", "mode", "status", "run ms", "time / forward", "compile s", "temp MiB",
                                  "temp / forward", f"temp MiB at {results['horizon_factor']}x horizon", "peak RSS MiB"], rows), ""]
    agree = [[m, f"{a['backsolve_vs_checkpoint_rel']:.2g}" if "backsolve_vs_checkpoint_rel" in a else "—",
              f"{a['forward_mode_vs_checkpoint_rel']:.2g}" if "forward_mode_vs_checkpoint_rel" in a else "—"]
             for m, a in results["analysis"].items()]
    L += ["Agreement of the gradients (max abs difference / max |checkpointed gradient|; backsolve integrates the "
          "adjoint ODE with its own RK4 steps, so it differs at the discretisation-error level):", "",
          _common.markdown_table(["model", "backsolve vs checkpoint", "forward mode vs checkpoint"], agree), "",
          "## Targets", "",
          _common.markdown_table(["id", "target", "verdict", "measured"],
                                 [[t["id"], t["target"], t["verdict"], t["detail"]] for t in results["targets"]]), ""]
    path.write_text("\n".join(L))


def write_plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = list(results["runs"])
    if not models:
        return False
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    width = 0.8 / max(len(models), 1)
    for i, model in enumerate(models):
        a = results["analysis"].get(model, {})
        xs = range(len(MODES))
        axes[0].bar([x + i * width for x in xs], [a.get(mo, {}).get("time_ratio") or 0 for mo in MODES], width, label=model)
        axes[1].bar([x + i * width for x in xs],
                    [(_get(results["runs"][model], mo, "memory", "temp_size_in_bytes") or 0) / 2**20 for mo in MODES],
                    width, label=model)
    for ax, title in zip(axes, ("run time / forward rollout", "XLA temp memory (MiB)")):
        ax.set_xticks([x + width * (len(models) - 1) / 2 for x in range(len(MODES))], MODES)
        ax.set_title(title)
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].axhline(3.0, color="k", lw=0.8, ls="--")
    s = results["stamp"]
    fig.suptitle(f"{results['steps']}-step RK4 rollout gradients, commit {s['commit']}{' (dirty)' if s.get('dirty') else ''}, "
                 f"{s['cpu']} x{s['cores']}, load {s['load_average_start']}, jax {s['versions']['jax']}, {s['date']}", fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default="panda,chain20", help="comma-separated: panda, ur5e, anymal_c, chainN")
    p.add_argument("--modes", default=",".join(MODES), help=f"comma-separated subset of {', '.join(MODES)}")
    p.add_argument("--steps", type=int, default=1000, help="RK4 steps of the rollout (dt = 1e-3)")
    p.add_argument("--horizon-factor", type=int, default=16,
                   help="also compile the reverse-mode gradients for this many times the horizon (memory only); 1 = off")
    p.add_argument("--fwd-params", type=int, default=4, help="parameters of the forward-mode jacfwd")
    p.add_argument("--min-time", type=float, default=0.5)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per worker")
    p.add_argument("--max-steps", choices=("horizon", "default"), default="horizon",
                   help="simulate's step budget: the horizon plus 16 steps, or simulate's default")
    p.add_argument("--pairs", type=int, default=5,
                   help="the checkpoint worker also times the forward rollout and the gradient in this many "
                        "interleaved pairs; the gradient-cost verdict takes the median of their ratios (0: the ratio of the two workers)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--kernel", choices=("auto", "native", "unrolled", "vectorised"),
                   help="forward-dynamics kernel: jb.simulate(jb.scene(model, kernel=KERNEL), ...); default: the model itself")
    p.add_argument("--note", default="")
    p.add_argument("--models-dir", type=pathlib.Path, default=_common.REPO / "jaxbody" / "models")
    p.add_argument("--out", type=pathlib.Path, default=_common.RESULTS)
    p.add_argument("--name", default="gradients")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--config", help=argparse.SUPPRESS)
    p.add_argument("--result", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        return args
    args.models = [x.strip() for x in args.models.split(",") if x.strip()]
    args.modes = [x.strip() for x in args.modes.split(",") if x.strip()]
    bad = [m for m in args.modes if m not in MODES]
    if bad:
        p.error(f"unknown mode(s) {bad}; choose from {MODES}")
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.worker:
        worker(json.loads(args.config), _Record(args.result))
        return 0
    env = dict(os.environ)
    if XLA_DEFAULT_FLAG and XLA_DEFAULT_FLAG not in env.get("XLA_FLAGS", ""):
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + XLA_DEFAULT_FLAG).strip()
    os.environ["XLA_FLAGS"] = env["XLA_FLAGS"]
    stamp = _common.stamp(sys.argv if argv is None else [sys.argv[0], *argv])
    args.out.mkdir(parents=True, exist_ok=True)
    results = {"stamp": stamp, "models": args.models, "modes": args.modes, "steps": args.steps, "dt": DT,
               "max_steps": args.max_steps,
               "horizon_factor": args.horizon_factor, "fwd_params": args.fwd_params, "kernel": args.kernel,
               "note": args.note, "runs": {}}
    t0 = time.perf_counter()
    me = str(pathlib.Path(__file__).resolve())
    md, js, png = (args.out / f"{args.name}.{ext}" for ext in ("md", "json", "png"))
    with tempfile.TemporaryDirectory(prefix="jaxbody-gradients-") as tmp:
        tmp = pathlib.Path(tmp)
        for model in args.models:
            path = model_path(model, args.models_dir, tmp)
            for mode in args.modes:
                cfg = dict(model=model, path=str(path), mode=mode, steps=args.steps, seed=args.seed, kernel=args.kernel,
                           min_time=args.min_time, repeats=args.repeats, fwd_params=args.fwd_params,
                           horizon_factor=args.horizon_factor, pairs=args.pairs, max_steps=args.max_steps)
                rf = tmp / f"{model}-{mode}.json"
                cmd = [sys.executable, me, "--worker", "--config", json.dumps(cfg), "--result", str(rf)]
                r = results["runs"].setdefault(model, {})[mode] = _common.run_worker(
                    cmd, timeout=args.timeout, result_file=rf, env=env)
                t = _get(r, "run", "median_s")
                print(f"[{time.perf_counter() - t0:6.0f}s load {_common.load_average()}] {model} {mode} ({r['status']}): "
                      f"compile {_get(r, 'compile', 'compile_total_s')} s, run {t} s, temp "
                      f"{_mib(_get(r, 'memory', 'temp_size_in_bytes'))} MiB", flush=True)
                stamp["load_average_end"] = _common.load_average()
                stamp["wall_s"] = time.perf_counter() - t0
                results["analysis"], results["targets"] = analyse(results)
                js.write_text(json.dumps(results, indent=1, default=str))
                write_markdown(results, md)
    plotted = write_plot(results, png)
    print("\nTargets:")
    for t in results["targets"]:
        print(f"  {t['id']} {t['verdict']}: {t['target']}\n      {t['detail']}")
    print(f"\nwrote {md}, {js}" + (f", {png}" if plotted else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
