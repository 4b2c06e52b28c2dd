"""Time a jitted loop of the generated RK4 step over a batch, alone, for a profiler.

``jaxbody.backends.native.rk4_step`` of the Panda arm (or another shipped robot, or a chain of N hinge
links, ``--model chainN``) over ``--batch``
states, 50 steps per call in a ``lax.fori_loop``, called for ``--seconds``; prints nanoseconds
per state and step. Nothing else runs in the loop, so a sampling profiler sees the generated
program, its sine and cosine, the thread pool and XLA's call around it::

    perf record -o perf.data .venv/bin/python benchmarks/kernels.py loop --dtype float32 --batch 1024 --seconds 6
    perf report -i perf.data --no-children --sort symbol
    perf annotate -i perf.data fd_block --stdio     # instruction by instruction

(``kernels.py step`` times the same loop next to ``jb.simulate`` and writes a record.)
"""

import argparse
import os
import pathlib
import sys
import tempfile
import time
import warnings

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common, dynamics
from _common import set_default_xla_flags  # noqa: E402
from dynamics import model_path  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(prog="kernels.py loop", description=__doc__.splitlines()[0])
    p.add_argument("--model", default="panda", help="a robot shipped in jaxbody/models, or chainN (N hinge links)")
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--seconds", type=float, default=3.0)
    args = p.parse_args(argv)
    set_default_xla_flags()

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody.backends import native

    dtype = jnp.dtype(args.dtype)
    with warnings.catch_warnings(), tempfile.TemporaryDirectory() as tmp:
        warnings.simplefilter("ignore")
        shipped = pathlib.Path(jb.__file__).parent / "models"
        path = shipped / f"{args.model}.xml"
        if not path.exists():
            path = model_path(args.model, shipped, pathlib.Path(tmp))
        model = jb.from_mjcf(str(path), dtype=dtype)
    rng = np.random.default_rng(0)
    q = jax.vmap(lambda x: jb.normalize_qpos(model, x))(
        jnp.asarray(np.asarray(model.qpos0) + 0.1 * rng.standard_normal((args.batch, model.nq)), dtype))
    v = jnp.zeros((args.batch, model.nv), dtype)
    h = jnp.asarray(1e-3, dtype)

    @jax.jit
    def loop(q, v):
        def body(_, s):
            out = jax.vmap(lambda q, v: native.rk4_step(model, q, v, h, gravity=model.gravity))(*s)
            return out[0], out[1]

        return jax.lax.fori_loop(0, 50, body, (q, v))

    jax.block_until_ready(loop(q, v))
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < args.seconds:
        jax.block_until_ready(loop(q, v))
        calls += 1
    elapsed = time.perf_counter() - start
    print(f"{args.model} {args.dtype} B={args.batch}: {1e9 * elapsed / (calls * 50 * args.batch):.1f} ns/state-step")
    return 0


if __name__ == "__main__":
    sys.exit(main())
