"""What sets the size limit of ``kernel="auto"``: generated code per tree, and the humanoid's speed.

    python benchmarks/native_limit.py [--name NAME]

For the shipped robots, a 25-DoF humanoid (``benchmarks/models/humanoid25.xml``) and hinge
chains of 12-30 links: DoFs, mass-matrix entries (:func:`jaxbody.backends.native.mass_matrix_entries`,
what ``jaxbody.backends.native.MAX_MASS_ENTRIES`` bounds) and the generated C++ lines of forward
dynamics, its reverse-mode derivative and the RK4 step (float64). Then one jitted forward-dynamics
evaluation of the humanoid (one state, dispatch included) on the native and the vectorised kernel,
and their largest difference. Build times: ``benchmarks/kernels.py build --models ...``. Writes
``NAME.json`` and ``NAME.md`` (default ``native_limit``) to ``benchmarks/results``.
"""

import argparse
import json
import pathlib
import sys
import warnings

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _common import REPO, RESULTS, load_average, markdown_table, set_default_xla_flags, stamp, stamp_markdown, time_per_call  # noqa: E402

sys.path.insert(0, str(REPO / "tests"))
from _support.random_models import hinge_chain  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", default="native_limit")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    args = p.parse_args(argv)
    set_default_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody.backends.native import codegen, mass_matrix_entries

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        models = {"panda": jb.from_mjcf(str(REPO / "jaxbody" / "models" / "panda.xml")),
                  "anymal_c": jb.from_mjcf(str(REPO / "jaxbody" / "models" / "anymal_c.xml")),
                  "humanoid25": jb.from_mjcf(str(REPO / "benchmarks" / "models" / "humanoid25.xml"))}
    for n in (12, 20, 24, 30):
        models[f"chain{n}"] = hinge_chain(n)
    rec = {"stamp": stamp(), "rows": []}
    for name, m in models.items():
        row = {"model": name, "nv": int(m.nv), "entries": mass_matrix_entries(m)}
        for mode in ("fd", "vjp", "rk4"):
            row[f"lines_{mode}"] = codegen.generate(m.tree, m.joints, False, np.float64, mode).count("\n")
        rec["rows"].append(row)
        print(row, flush=True)
    h = models["humanoid25"]
    rng = np.random.default_rng(0)
    q = jb.normalize_qpos(h, h.qpos0 + jnp.asarray(rng.uniform(-0.5, 0.5, h.nq)))
    v = jnp.asarray(rng.uniform(-1, 1, h.nv))
    acc = {}
    for k in ("native", "vectorised"):
        f = jax.jit(lambda q, v, k=k: jb.backends.acceleration(h, q, v, gravity=h.gravity, kernel=k))
        acc[k] = jax.block_until_ready(f(q, v))
        rec[f"humanoid_fd_{k}_s"] = time_per_call(lambda f=f: jax.block_until_ready(f(q, v)), min_time=0.5, repeats=5)["median_s"]
    rec["humanoid_max_difference"] = float(jnp.max(jnp.abs(acc["native"] - acc["vectorised"])))
    rec["stamp"]["load_average_end"] = load_average()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(rec, indent=1))
    rows = [(r["model"], r["nv"], r["entries"], r["lines_fd"], r["lines_vjp"], r["lines_rk4"]) for r in rec["rows"]]
    md = ["# The native kernel's size limit: generated code per tree", "", stamp_markdown(rec["stamp"]), "",
          markdown_table(["tree", "DoFs", "mass-matrix entries", "lines: forward dynamics", "reverse mode", "RK4 step"], rows), "",
          f"The humanoid's forward dynamics, one state, jitted: native {1e6 * rec['humanoid_fd_native_s']:.1f} µs, "
          f"vectorised {1e6 * rec['humanoid_fd_vectorised_s']:.1f} µs; largest difference {rec['humanoid_max_difference']:.1e}.", ""]
    (args.out / f"{args.name}.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
