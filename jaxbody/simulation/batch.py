"""Batches of solves over devices: one compilation, data-parallel chunks."""

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._types import ArrayLike, Float
from .integrate import simulate
from .solution import Solution

__all__ = ["simulate_batch"]


def simulate_batch(
    system,
    q0s: Float[ArrayLike, "batch nq"],
    v0s: Float[ArrayLike, "batch nv"],
    t1: ArrayLike,
    *,
    batched_system: bool = False,
    chunk_size: int | None = None,
    devices: Sequence[jax.Device] | None = None,
    **kwargs,
) -> Solution:
    """Simulate a batch of initial states (and systems) with one compilation, over all devices.

    The batch is split in chunks of at most ``chunk_size`` members per device (all of it when
    ``None``), padded to a multiple of the device count, and each chunk is laid out over a 1-D
    device mesh (``jax.sharding.Mesh`` + ``NamedSharding`` along the batch axis): the vmapped
    solve runs data-parallel, one compiled program for every chunk. ``throw=False`` is implied:
    a failed member keeps its result code and the others their trajectories. Results equal the
    unsharded ``jax.vmap`` of :func:`simulate`.

    Args:
        system: as in :func:`simulate`; with ``batched_system=True`` its array leaves carry a
            leading batch axis (one system per member, e.g. from ``eqx.filter_vmap`` of a builder).
        q0s, v0s: ``(batch, nq)``, ``(batch, nv)``.
        t1: final time (shared).
        chunk_size: members per device per chunk (bounds memory); ``None``: one chunk.
        devices: devices to use (default ``jax.devices()``).
        **kwargs: passed to :func:`simulate` (``throw`` is forced to ``False``).

    Returns:
        :class:`Solution` with a leading batch axis on every array.
    """
    kwargs = dict(kwargs)
    # one failed member must not stop the others: failures stay per-member result codes
    kwargs["throw"] = False
    q0s = jnp.asarray(q0s)
    v0s = jnp.asarray(v0s)
    if q0s.ndim != 2 or v0s.ndim != 2 or q0s.shape[0] != v0s.shape[0]:
        raise ValueError(f"simulate_batch: q0s and v0s must be (batch, nq) and (batch, nv), got {q0s.shape} and {v0s.shape}")
    if chunk_size is not None and (int(chunk_size) != chunk_size or chunk_size < 1):
        raise ValueError(f"simulate_batch: chunk_size must be a positive integer, got {chunk_size!r}")
    n = q0s.shape[0]
    devices = list(jax.devices() if devices is None else devices)
    n_dev = len(devices)
    # every chunk has the same shape (the last one padded), so one compiled program serves all
    per_chunk = n_dev * (math.ceil(n / n_dev) if chunk_size is None else int(chunk_size))
    n_chunks = math.ceil(n / per_chunk)
    pad = n_chunks * per_chunk - n
    params, static = eqx.partition(system, eqx.is_array)

    def padded(x):
        # padding repeats the last member (a valid input, unlike zeros for a quaternion)
        return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x

    q0s, v0s = padded(q0s), padded(v0s)
    if batched_system:
        params = jax.tree.map(padded, params)
    mesh = Mesh(np.asarray(devices), ("batch",))
    shard = NamedSharding(mesh, PartitionSpec("batch"))
    # a shared system is replicated on every device; a batched one is split like the states
    replicated = NamedSharding(mesh, PartitionSpec())
    run = _batch_runner(static, batched_system, t1, tuple(sorted(kwargs.items(), key=lambda kv: kv[0])))
    outs = []
    for c in range(n_chunks):
        sl = slice(c * per_chunk, (c + 1) * per_chunk)
        p = jax.tree.map(lambda x: x[sl], params) if batched_system else params
        p = jax.device_put(p, shard if batched_system else replicated)
        outs.append(run(p, jax.device_put(q0s[sl], shard), jax.device_put(v0s[sl], shard)))
    out = outs[0] if len(outs) == 1 else jax.tree.map(lambda *xs: jnp.concatenate(xs), *outs)
    return jax.tree.map(lambda x: x[:n], out) if pad else out


class _Kw:
    """Hashable wrapper of keyword arguments (arrays compared by identity).

    Arrays (``saveat`` times, a ``tau``) are not hashable by value; by identity, a caller that
    passes the same objects again reuses the compiled runner, and a new array compiles anew
    instead of silently reusing another array's values."""

    def __init__(self, items):
        self.items = items

    def __hash__(self):
        return hash(tuple((k, id(v)) for k, v in self.items))

    def __eq__(self, other):
        return isinstance(other, _Kw) and [(k, id(v)) for k, v in self.items] == [(k, id(v)) for k, v in other.items]


# compiled runners by (static part, batched_system, keyword arguments): repeated calls with the
# same arguments reuse one compilation instead of re-tracing the vmapped solve
_RUNNERS: dict = {}


def _batch_runner(static, batched_system, t1, kw_items):
    key = (static, batched_system, _Kw(kw_items))
    try:
        hit = _RUNNERS.get(key)
    except TypeError:  # unhashable static part: compile per call
        hit, key = None, None
    if hit is not None:
        return hit[0]
    kwargs = dict(kw_items)

    # t1 is an argument, not a constant of the trace: batches over other horizons reuse the program
    @eqx.filter_jit
    def run(params, q0s, v0s, t1):
        def one(p, q0, v0):
            return simulate(eqx.combine(p, static), q0, v0, t1, **kwargs)

        return jax.vmap(one, in_axes=(0 if batched_system else None, 0, 0))(params, q0s, v0s)

    def call(params, q0s, v0s):
        return run(params, q0s, v0s, jnp.asarray(t1, q0s.dtype))

    if key is not None:
        # bounded: each entry holds a compiled program and the arrays of its key
        if len(_RUNNERS) > 32:
            _RUNNERS.clear()
        _RUNNERS[key] = (call, kw_items)  # keep the kwargs alive: their ids are the key
    return call
