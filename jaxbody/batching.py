"""Batching helpers for large batches on CPU.

``jax.vmap`` over a very large batch makes every intermediate array of the dynamics as
large as the batch; on CPU each stage then streams through main memory instead of cache,
and throughput *falls* as the batch grows (measured: panda forward dynamics at batch 8192,
0.063 M states/s with plain ``vmap``, 0.186 M states/s in chunks of 64 —
``benchmarks/dynamics.py``). :func:`vmap_chunked` maps over cache-sized chunks instead:
``vmap`` inside a chunk, a sequential loop over chunks (``jax.lax.map`` with
``batch_size``). It is ``jit``-, ``grad``- and nested-``vmap``-compatible.
"""

from collections.abc import Callable, Sequence

import jax

__all__ = ["vmap_chunked"]


def vmap_chunked(fn: Callable, chunk_size: int = 64, in_axes: int | None | Sequence[int | None] = 0) -> Callable:
    """Like ``jax.vmap(fn, in_axes)`` but evaluated in chunks of ``chunk_size`` states.

    Args:
        fn: function of positional arguments.
        chunk_size: states per chunk (vectorised); chunks run one after another.
        in_axes: ``0`` (map the leading axis) or ``None`` (broadcast) per argument, or one
            value for all. Only the leading axis can be mapped.

    Returns:
        A function with the signature of ``fn`` whose outputs have a leading batch axis.
    """
    if chunk_size < 1:
        raise ValueError(f"vmap_chunked: chunk_size must be positive, got {chunk_size}")

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

    return wrapped
