"""Batching helpers for large batches on CPU.

``jax.vmap`` over a very large batch makes every intermediate array of the dynamics as
large as the batch; on CPU each stage then streams through main memory instead of cache,
and throughput *falls* as the batch grows (measured at batch 8192, forward dynamics: panda
81k states/s with plain ``vmap`` and 195k in chunks of 64; chain20 29k and 61k —
``benchmarks/results/dynamics_plain_vmap.md`` and ``dynamics.md``). :func:`vmap_chunked` maps over cache-sized chunks instead:
``vmap`` inside a chunk, a sequential loop over chunks (``jax.lax.map`` with
``batch_size``). It is ``jit``-, ``grad``- and nested-``vmap``-compatible, and compiled: the
returned function is an ``equinox.filter_jit`` of the chunked map, so calling it again with
arrays of the same shapes reuses the compilation (keep the returned function; a new
``vmap_chunked(fn)`` is a new function and compiles again).

XLA runs these batched loops on one CPU thread. With ``devices=N`` the batch is split over
``N`` local devices (``jax.shard_map``) and each device runs its chunks; on a CPU machine
make the cores visible as devices first, before JAX starts:
``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (or
``jax.config.update("jax_num_cpu_devices", 2)``). On a GPU the devices are the GPUs.
"""

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, PartitionSpec

__all__ = ["vmap_chunked"]


def vmap_chunked(
    fn: Callable,
    chunk_size: int = 64,
    in_axes: int | None | Sequence[int | None] = 0,
    devices: int | Sequence | None = None,
) -> Callable:
    """Like ``jax.vmap(fn, in_axes)`` but evaluated in chunks of ``chunk_size`` states.

    Args:
        fn: function of positional arguments.
        chunk_size: states per chunk (vectorised); chunks run one after another.
        in_axes: ``0`` (map the leading axis) or ``None`` (broadcast) per argument, or one
            value for all. Only the leading axis can be mapped.
        devices: split the batch over this many local devices (or these devices); the batch
            size must be a multiple of their number. ``None``: one device.

    Returns:
        A compiled function (``equinox.filter_jit``) with the signature of ``fn`` whose outputs
        have a leading batch axis; repeated calls with the same shapes do not re-trace.

    Raises:
        ValueError: bad ``chunk_size``/``in_axes``, more devices asked for than exist, or a
            batch that does not split evenly over the devices.
    """
    if chunk_size < 1:
        raise ValueError(f"vmap_chunked: chunk_size must be positive, got {chunk_size}")
    if devices is not None:
        local = jax.local_devices()
        if isinstance(devices, int):
            if not 1 <= devices <= len(local):
                raise ValueError(
                    f"vmap_chunked: {devices} devices requested, {len(local)} available "
                    "(on CPU set XLA_FLAGS=--xla_force_host_platform_device_count=N before JAX starts)"
                )
            devices = local[:devices]
        mesh = Mesh(np.asarray(list(devices)), ("batch",))
        inner = vmap_chunked(fn, chunk_size, in_axes)

        def sharded(*args):
            axes = in_axes if isinstance(in_axes, (list, tuple)) else (in_axes,) * len(args)
            n_dev = mesh.devices.size
            for a, ax in zip(args, axes):
                if ax == 0:
                    size = jax.tree.leaves(a)[0].shape[0]
                    if size % n_dev:
                        raise ValueError(
                            f"vmap_chunked: batch of {size} does not split over {n_dev} devices"
                        )
            specs = tuple(PartitionSpec("batch") if ax == 0 else PartitionSpec() for ax in axes)
            # check_vma=False: an eqx.error_if inside fn (a public boundary check) uses a cond
            # whose branches differ in "varying" type; every output here is batch-sharded anyway
            return jax.shard_map(
                inner, mesh=mesh, in_specs=specs, out_specs=PartitionSpec("batch"), check_vma=False
            )(*args)

        return eqx.filter_jit(sharded)

    def wrapped(*args):
        axes = in_axes if isinstance(in_axes, (list, tuple)) else (in_axes,) * len(args)
        if len(axes) != len(args):
            raise ValueError(f"vmap_chunked: in_axes has {len(axes)} entries for {len(args)} arguments")
        for ax in axes:
            if ax not in (0, None):
                raise ValueError(f"vmap_chunked: in_axes entries must be 0 or None, got {ax!r}")
        mapped = tuple(a for a, ax in zip(args, axes) if ax == 0)
        if not mapped:
            raise ValueError("vmap_chunked: at least one argument must be mapped (in_axes 0)")

        def one(xs):
            it = iter(xs)
            full = [next(it) if ax == 0 else a for a, ax in zip(args, axes)]
            return fn(*full)

        return jax.lax.map(one, mapped, batch_size=chunk_size)

    return eqx.filter_jit(wrapped)
