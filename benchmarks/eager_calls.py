"""What the public dynamics functions cost when called eagerly, as in a notebook.

    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python benchmarks/eager_calls.py [--name NAME] [--repeats N]
        [--models panda,anymal_c,planar3] [--calls 20] [--baseline DIR]

For each model (shipped in ``jaxbody/models``, ``chainN``, or ``planar3``: the planar three-link
manipulator of ``jaxbody.examples.telegin``, in absolute angles) and each of ``jb.inverse_dynamics``,
``jb.forward_dynamics``, ``jb.mass_matrix`` and a scene's ``acceleration`` (``jb.scene(model)``): the time of the first call in a fresh process
(tracing and compiling included) and the median of ``--calls`` later calls, each with a new
random state, the result waited for. No ``jax.jit`` around the call: this is what a user's
loop over states pays. Every repeat runs in a fresh process; medians over the repeats.
Writes ``NAME.json`` and ``NAME.md`` (default ``eager_calls``) to ``--out`` (default
``benchmarks/results``). ``--baseline DIR`` also times jaxbody from another checkout (``DIR``,
e.g. a ``git worktree`` of an older commit), its workers alternating with this tree's.
"""

import argparse
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import RESULTS, alternate, checkouts, load_average, markdown_table, stamp, stamp_markdown  # noqa: E402

FUNCTIONS = ("inverse_dynamics", "forward_dynamics", "mass_matrix", "scene_acceleration")
#: the planar three-link manipulator of the augmented-body paper (``jaxbody.examples.telegin``)
PLANAR = "planar3"


def _one(model_name: str, calls: int) -> dict:
    """Time the functions on one model in this process (a fresh one)."""
    import tempfile
    import warnings

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from dynamics import model_path

    rng = np.random.default_rng(0)
    if model_name == PLANAR:
        from jaxbody.examples import telegin

        model = telegin.three_link_manipulator()

        def state():
            return jnp.asarray(rng.standard_normal(model.nq)), jnp.asarray(rng.standard_normal(model.nv))
    else:
        shipped = pathlib.Path(jb.__file__).parent / "models"
        path = model_path(model_name, shipped, pathlib.Path(tempfile.mkdtemp()))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = jb.from_mjcf(str(path))

        def state():
            q = jb.normalize_qpos(model, jnp.asarray(np.asarray(model.qpos0) + 0.3 * rng.standard_normal(model.nq)))
            return q, jnp.asarray(rng.standard_normal(model.nv))

    scene = jb.scene(model)  # the model's default effects; built before the clock starts
    run = {
        "inverse_dynamics": lambda q, v: jb.inverse_dynamics(model, q, v, v),
        "forward_dynamics": lambda q, v: jb.forward_dynamics(model, q, v),
        "mass_matrix": lambda q, v: jb.mass_matrix(model, q),
        "scene_acceleration": lambda q, v: scene.acceleration(0.0, q, v),
    }
    out = {}
    for name in FUNCTIONS:
        q, v = state()
        t0 = time.perf_counter()
        jax.block_until_ready(run[name](q, v))
        first = time.perf_counter() - t0
        later = []
        for _ in range(calls):
            q, v = state()
            t0 = time.perf_counter()
            jax.block_until_ready(run[name](q, v))
            later.append(time.perf_counter() - t0)
        out[name] = dict(first_s=first, later_s=float(np.median(later)))
    return dict(model=model_name, times=out, jaxbody=str(pathlib.Path(jb.__file__).parent))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", default="eager_calls")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--calls", type=int, default=20)
    p.add_argument("--models", default="panda,anymal_c," + PLANAR)
    p.add_argument("--baseline", type=pathlib.Path, help="another checkout whose jaxbody is timed alongside")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(_one(args.worker, args.calls)))
        return
    record = {"stamp": stamp(), "runs": []}
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    trees, baseline = checkouts(args.baseline)
    if baseline:
        record["baseline"] = baseline
    record["runs"] = alternate(__file__, models, trees, args.repeats, ("--calls", str(args.calls)))
    import numpy as np

    rows = []
    for model in models:
        for name in FUNCTIONS:
            for tree in trees:
                runs = [r["times"][name] for r in record["runs"] if r["model"] == model and r["tree"] == tree]
                first = float(np.median([r["first_s"] for r in runs]))
                later = float(np.median([r["later_s"] for r in runs]))
                rows.append((model, "`scene.acceleration`" if name == "scene_acceleration" else f"`jb.{name}`", tree, f"{first:.3f}", f"{1e3 * later:.2f}", len(runs)))
    record["stamp"]["load_average_end"] = load_average()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(record, indent=1))
    md = ["# Eager calls of the public dynamics functions", "", stamp_markdown(record["stamp"]), "",
          f"Each repeat in a fresh process: the first call (trace and compile included) and the median of {args.calls} "
          "later calls with new random states, no `jax.jit` around them; medians over the repeats.", "",
          markdown_table(["model", "function", "jaxbody", "first call s", "later call ms", "repeats"], rows), ""]
    (args.out / f"{args.name}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
