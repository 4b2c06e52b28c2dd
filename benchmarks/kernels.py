"""What does each forward-dynamics kernel cost, and where does a step's time go?

One script, one subcommand per probe; each subcommand takes ``--help`` and writes its own
record (``--out``, ``--name``) except ``loop``, which only prints (it is meant for a profiler):

    .venv/bin/python benchmarks/kernels.py compare       # unrolled / vectorised / auto kernels, one state and a batch, next to MuJoCo
    .venv/bin/python benchmarks/kernels.py build         # native kernel: generated lines and compile time per program
    .venv/bin/python benchmarks/kernels.py step          # the generated RK4 step alone and inside jb.simulate, float64 and float32
    .venv/bin/python benchmarks/kernels.py loop          # a loop of the generated RK4 step alone, for perf
    .venv/bin/python benchmarks/kernels.py single-state  # the scalar one-state build against 256-bit lanes
    .venv/bin/python benchmarks/kernels.py gradient      # one evaluation and its jvp/vjp per kernel; one step of a rollout gradient
    python benchmarks/kernels.py gpu-profile             # on an accelerator: XLA's cost analysis and a profiled call

The probes live in ``benchmarks/_kernel_probes/`` (one module each, its docstring says what it
measures); shared helpers in ``benchmarks/_common.py``.
"""

import importlib
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # benchmarks/: _common, dynamics, _kernel_probes

#: subcommand -> module of ``_kernel_probes`` that runs it
SUBCOMMANDS = {
    "compare": "compare",
    "build": "build",
    "step": "step",
    "loop": "loop",
    "single-state": "single_state",
    "gradient": "gradient",
    "gpu-profile": "gpu_profile",
}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] not in SUBCOMMANDS:
        print(__doc__)
        for sub, mod in SUBCOMMANDS.items():
            doc = importlib.import_module(f"_kernel_probes.{mod}").__doc__.strip().splitlines()[0]
            print(f"  {sub:13s} {doc}")
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    module = importlib.import_module(f"_kernel_probes.{SUBCOMMANDS[argv[0]]}")
    return module.main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
