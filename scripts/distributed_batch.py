"""One batch of simulations split over several processes (hosts) with ``jax.distributed``.

Usage, one process per host, the same first two arguments everywhere and ids ``0 … N−1``::

    python scripts/distributed_batch.py COORDINATOR_HOST:PORT NUM_PROCESSES PROCESS_ID [options]

Process 0 runs the coordinator, so its host must be reachable from the others on the port.
Each process simulates its own slice of the global batch on its local devices (member ``i``
goes to process ``i % N``, row ``i // N`` of its part): simulations of a batch are
independent, so no communication happens during the solves. Every process builds the same
global batch (same seed) and writes ``OUT/partNNN.npz``; :func:`gather` joins the parts into
the global batch, in the order a single process would have computed it.

The process count and id are given explicitly: jax 0.10 reads only the coordinator address
from the environment (``JAX_COORDINATOR_ADDRESS``), so a bare ``jax.distributed.initialize()``
outside SLURM, Open MPI or a TPU pod fails. Under SLURM pass ``--cluster`` instead of the three
positional arguments and JAX detects the rest.
"""

import argparse
import pathlib
import sys

import numpy as np

#: Panda, shipped with jaxbody (found relative to this file: the script runs without installing).
DEFAULT_MODEL = pathlib.Path(__file__).resolve().parents[1] / "jaxbody" / "models" / "panda.xml"


def global_initial_states(qpos0, n: int, seed: int = 0, spread: float = 0.1):
    """The global batch's initial positions ``(n, nq)``: ``qpos0`` plus seeded normal noise, the
    same on every process."""
    rng = np.random.default_rng(seed)
    qpos0 = np.asarray(qpos0)
    return np.tile(qpos0, (n, 1)) + spread * rng.standard_normal((n, qpos0.shape[0]))


def my_members(n: int, process_index: int, process_count: int) -> slice:
    """The members of a global batch of ``n`` that process ``process_index`` simulates."""
    return slice(process_index, n, process_count)


def gather(out: pathlib.Path, process_count: int) -> dict[str, np.ndarray]:
    """The parts written by ``process_count`` processes joined into the global batch (member
    ``i`` from part ``i % process_count``, row ``i // process_count``)."""
    parts = [np.load(pathlib.Path(out) / f"part{i:03d}.npz") for i in range(process_count)]
    n = sum(len(p["q"]) for p in parts)
    joined = {}
    for key in parts[0].files:
        first = parts[0][key]
        joined[key] = np.empty((n,) + first.shape[1:], first.dtype)
        for i, part in enumerate(parts):
            joined[key][my_members(n, i, process_count)] = part[key]
    return joined


def arguments(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("coordinator", nargs="?", help="HOST:PORT of process 0's coordinator")
    parser.add_argument("num_processes", nargs="?", type=int)
    parser.add_argument("process_id", nargs="?", type=int)
    parser.add_argument("--cluster", action="store_true",
                        help="let JAX detect the cluster (SLURM, Open MPI) instead of the three arguments")
    parser.add_argument("--model", type=pathlib.Path, default=DEFAULT_MODEL, help="MJCF file (default: Panda)")
    parser.add_argument("--n", type=int, default=100_000, help="members of the global batch")
    parser.add_argument("--t1", type=float, default=1.0, help="end time (s)")
    parser.add_argument("--n-save", type=int, default=11, help="saved times per member")
    parser.add_argument("--solver", default="tsit5", help="a preset of jaxbody.simulate")
    parser.add_argument("--dt0", type=float, default=None, help="step of a fixed-step solver")
    parser.add_argument("--chunk-size", type=int, default=2048, help="members per device per chunk")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("."), help="folder of the part files")
    args = parser.parse_args(argv)
    explicit = (args.coordinator, args.num_processes, args.process_id)
    if args.cluster == any(a is not None for a in explicit) or (not args.cluster and None in explicit):
        parser.error("give either COORDINATOR NUM_PROCESSES PROCESS_ID or --cluster")
    return args


def main(argv=None) -> None:
    args = arguments(argv)
    import jax

    # before any other JAX call: the processes find each other through the coordinator
    if args.cluster:
        jax.distributed.initialize()
    else:
        jax.distributed.initialize(coordinator_address=args.coordinator, num_processes=args.num_processes,
                                   process_id=args.process_id)
    jax.config.update("jax_enable_x64", True)
    import jaxbody as jb

    scene = jb.scene(jb.from_mjcf(args.model))
    q0s = global_initial_states(scene.system.qpos0, args.n)
    mine = my_members(args.n, jax.process_index(), jax.process_count())
    q0 = q0s[mine]
    sol = jb.simulate_batch(scene, q0, np.zeros((len(q0), scene.nv)), args.t1, solver=args.solver, dt0=args.dt0,
                            devices=jax.local_devices(), chunk_size=args.chunk_size, n_save=args.n_save)
    args.out.mkdir(parents=True, exist_ok=True)
    np.savez(args.out / f"part{jax.process_index():03d}.npz", t=np.asarray(sol.t), q=np.asarray(sol.q),
             v=np.asarray(sol.v), success=np.asarray(sol.success))
    jax.distributed.shutdown()


if __name__ == "__main__":
    sys.exit(main())
