"""How long does the native kernel take to build, per tree and per program?

For each model this generates the C++ of the native kernel's three programs — forward
dynamics (``fd``), its forward-mode derivative (``jvp``) and its reverse-mode derivative
(``vjp``) — and compiles each with the flags the kernel uses, into a fresh cache directory
(nothing reused), recording the generated lines and the compile time:

    .venv/bin/python benchmarks/kernels.py build [--models panda,chain7,chain12,chain20] [--modes fd,jvp,vjp]
        [--level=-O0] [--build one|narrow|wide]

``--level`` compiles at another optimisation level than the kernel's default (``-O0``: the
quick build a first call runs while the optimised one builds in the background) and
``--build`` another of the builds (``jaxbody.backends.native.BUILDS``: one state, 256-bit or
512-bit lanes). Another checkout's generator is timed by running this script with
``PYTHONPATH`` set to it (its ``jaxbody`` is imported first).

This is a one-time cost per tree (the libraries are cached in ``$JAXBODY_CACHE_DIR``); it is
what sets :data:`jaxbody.backends.native.MAX_MASS_ENTRIES` and :data:`jaxbody.backends.native.MAX_DERIVATIVE_DOFS`.
Writes ``benchmarks/results/<name>.{md,json}`` (default ``native_build``).
"""

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common, dynamics
from _common import RESULTS, REPO, load_average, markdown_table, stamp, stamp_markdown  # noqa: E402
from dynamics import model_path  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(prog="kernels.py build", description=__doc__.splitlines()[0])
    p.add_argument("--models", default="panda,chain7,chain12,chain20", help="robots of jaxbody/models or chainN")
    p.add_argument("--modes", default="fd,jvp,vjp", help="comma-separated subset of native.MODES (fd, jvp, vjp, rk4, rk4_jvp, rk4_vjp)")
    p.add_argument("--level", help="optimisation level (-O0 ... -O3; default: the kernel's)")
    p.add_argument("--build", default="narrow", help="one, narrow or wide (jaxbody.backends.native.BUILDS)")
    p.add_argument("--handler", action="store_true",
                   help="also time the tree-independent handler library (float64, the kernel's own flags)")
    p.add_argument("--out", default=str(RESULTS))
    p.add_argument("--name", default="native_build")
    args = p.parse_args(argv)
    rec = {"stamp": stamp(), "rows": []}

    import warnings

    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import jaxbody as jb
    from jaxbody.backends import native

    with tempfile.TemporaryDirectory() as tmp:
        os.environ["JAXBODY_CACHE_DIR"] = tmp  # nothing cached: every build compiles
        for name in args.models.split(","):
            path = model_path(name, REPO / "jaxbody" / "models", pathlib.Path(tmp))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                model = jb.from_mjcf(str(path))
            for mode in args.modes.split(","):
                # by default the 256-bit-lane build (small batches; single states and batches of
                # native.WIDE_BATCH and more get other builds of the same source: native.BUILDS)
                source = native.codegen.generate(model.tree, model.joints, False, np.float64, mode).replace(
                    "@VECTOR_BYTES@", native.BUILDS[args.build])
                t = time.perf_counter()
                native.build.build_library(source, f"probe_{mode}", flags=native.build.compiler_flags(args.level))
                seconds = time.perf_counter() - t
                row = {"model": name, "nv": int(model.nv), "program": mode, "lines": source.count("\n"), "compile_s": seconds,
                       "level": args.level or native.build.compiler_flags()[0], "build": args.build,
                       "jaxbody": str(pathlib.Path(jb.__file__).parent)}
                rec["rows"].append(row)
                print(f"{name:10s} nv={model.nv:3d} {mode:4s} {row['lines']:7d} lines {seconds:7.1f} s", flush=True)

        if args.handler:
            # built once per machine and dtype, on a new user's first native call
            t = time.perf_counter()
            native.build.handler_library(np.float64)
            rec["rows"].append({"model": "(any)", "nv": 0, "program": "handler", "lines": 0,
                                "compile_s": time.perf_counter() - t, "level": native.build.compiler_flags()[0],
                                "build": "-", "jaxbody": str(pathlib.Path(jb.__file__).parent)})
            print(f"handler {rec['rows'][-1]['compile_s']:7.2f} s", flush=True)

    rec["stamp"]["load_average_end"] = load_average()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps(rec, indent=1))
    rows = [(r["model"], r["nv"], r["program"], r["level"], r["build"], r["lines"], f"{r['compile_s']:.2f}")
            for r in rec["rows"]]
    md = [
        "# Building the native kernel: generated lines and compile time per program",
        "",
        stamp_markdown(rec["stamp"]),
        "",
        "Each program generated for float64 without body loads and compiled from scratch with the "
        "kernel's flags (`jaxbody.backends.native.build.compiler_flags()`); `fd` is built on a tree's first use, `jvp`/`vjp` "
        "on its first derivative (trees up to `MAX_DERIVATIVE_DOFS`).",
        "",
        f"jaxbody: `{rec['rows'][0]['jaxbody']}`." if rec["rows"] else "",
        "",
        markdown_table(["model", "nv", "program", "level", "build", "lines", "compile s"], rows),
        "",
    ]
    (out / f"{args.name}.md").write_text("\n".join(md))
    print(f"wrote {out / args.name}.md, .json")


if __name__ == "__main__":
    main()
