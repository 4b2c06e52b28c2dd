"""Body-tree topology as static index arrays (spec §1; STYLE rules 4–6).

A tree is given by a parent array: ``parent[k]`` is the base body (spec: "base body",
the parent) of body ``k`` or ``-1`` for a body jointed to the ground (or to a translating
base). Bodies are numbered topologically, ``parent[k] < k``.

Everything here is computed once in NumPy at build time and stored as tuples of Python
ints, so a :class:`BodyTree` is hashable and can live in an ``eqx.field(static=True)``.
Traced code uses the small helpers at the bottom (:meth:`BodyTree.subtree_sum`,
:meth:`BodyTree.path_sum`, :meth:`BodyTree.accumulate_from_root` ...): products with
dense static 0/1 matrices (``jax.ops.segment_sum`` over precomputed index pairs for very
large trees), gathers, or a ``fori_loop`` over a static number of pointer-jumping steps, so
the size of the trace does not depend on the number of bodies.

Vocabulary of the spec and the names used here:

========================  ==========================  =====================================
spec                      here                        meaning
========================  ==========================  =====================================
base body ``p(k)``        ``parent[k]``               next body towards the ground
adjacent bodies A(k)      ``children[k]``             bodies whose base is ``k``
carrier chain C(k)        ``carrier_pairs``           strict ancestors of ``k``
subsystem S(k)            ``subtree_pairs``           ``k`` and every body it carries
``c(i, k)``               ``carrier_pair_child``      child of ``i`` on the path to ``k``
========================  ==========================  =====================================
"""

from collections.abc import Sequence
from functools import cached_property

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["BodyTree"]


def _as_int_tuple(a) -> tuple[int, ...]:
    return tuple(int(v) for v in np.asarray(a, dtype=np.int64).reshape(-1).tolist())


class BodyTree:
    """Static topology of a tree of bodies.

    Args:
        parent: length-``n`` sequence of parent indices (``-1`` = ground / base).
        names: optional body names used in error messages (default ``body0``, ``body1``...).

    Raises:
        ValueError: lengths differ, a parent index is unknown, the parents form a cycle, or
            the numbering is not topological (``parent[k] >= k``). The message names the body.

    The instance is immutable; equality and hash depend only on ``parent`` and ``names``.
    """

    __slots__ = ("parent", "names", "__dict__")

    def __init__(self, parent: Sequence, names: Sequence[str] | None = None):
        parent_list = list(parent)
        n = len(parent_list)
        if names is None:
            names = [f"body{k}" for k in range(n)]
        names = [str(s) for s in names]
        if len(names) != n:
            raise ValueError(
                f"body tree: parent array has {n} entries but {len(names)} body names were given"
            )
        for k, p in enumerate(parent_list):
            if isinstance(p, (bool, np.bool_)) or not isinstance(p, (int, np.integer)):
                raise ValueError(
                    f"body tree: parent of body {k} ({names[k]!r}) must be an integer, got {p!r}"
                )
            if p < -1 or p >= n:
                raise ValueError(
                    f"body tree: body {k} ({names[k]!r}) has unknown parent {int(p)} "
                    f"(valid: -1 for the ground, or 0..{n - 1})"
                )
        # Cycles before ordering: a cycle is the more fundamental error.
        for k in range(n):
            seen = {k}
            p = int(parent_list[k])
            while p != -1:
                if p in seen:
                    raise ValueError(
                        f"body tree: body {k} ({names[k]!r}) lies on a cycle of parents "
                        f"(parent chain returns to body {p} ({names[p]!r}))"
                    )
                seen.add(p)
                p = int(parent_list[p])
        for k, p in enumerate(parent_list):
            if p >= k:
                raise ValueError(
                    f"body tree: body {k} ({names[k]!r}) has parent {int(p)} ({names[p]!r}); "
                    "bodies must be numbered so that parent[k] < k (renumber topologically)"
                )
        object.__setattr__(self, "parent", _as_int_tuple(parent_list))
        object.__setattr__(self, "names", tuple(names))
        self._build()

    def __setattr__(self, name, value):  # pragma: no cover - immutability guard
        raise AttributeError("BodyTree is immutable")

    def __eq__(self, other):
        if self is other:
            return True
        return (
            isinstance(other, BodyTree)
            and hash(self) == hash(other)
            and self.parent == other.parent
            and self.names == other.names
        )

    def __hash__(self):
        # cached: jit hashes static fields on every call that takes a model as an argument
        h = self.__dict__.get("_hash")
        if h is None:
            h = self.__dict__["_hash"] = hash((self.parent, self.names))
        return h

    def __repr__(self):
        return f"BodyTree(n_body={self.n_body}, parent={list(self.parent)})"

    # ------------------------------------------------------------------ build time
    def _build(self):
        n = len(self.parent)
        par = np.asarray(self.parent, dtype=np.int64)
        depth = np.zeros(n, dtype=np.int64)
        for k in range(n):
            depth[k] = 0 if par[k] < 0 else depth[par[k]] + 1
        root = np.arange(n)
        for k in range(n):
            if par[k] >= 0:
                root[k] = root[par[k]]
        # carrier pairs: (i, k, c(i,k)) for every strict ancestor i of k, sorted by k then depth
        anc, desc, child = [], [], []
        for k in range(n):
            c = k
            i = par[k]
            path = []
            while i >= 0:
                path.append((i, c))
                c = i
                i = par[i]
            for i, c in reversed(path):
                anc.append(i)
                desc.append(k)
                child.append(c)
        # subtree pairs (k, i) with i in S(k), self included; sorted by k (segment ids)
        sub_root = list(range(n)) + anc
        sub_body = list(range(n)) + desc
        order = np.lexsort((np.asarray(sub_body), np.asarray(sub_root))) if n else np.zeros(0, int)
        sub_root = np.asarray(sub_root, dtype=np.int64)[order]
        sub_body = np.asarray(sub_body, dtype=np.int64)[order]
        # pointer-jumping table: jump[s, k] = 2**s-th ancestor of k or -1
        max_depth = int(depth.max()) if n else 0
        steps = max(1, int(np.ceil(np.log2(max_depth + 1)))) if max_depth > 0 else 0
        jump = np.full((max(steps, 1), n), -1, dtype=np.int64)
        if n:
            jump[0] = par
            for s in range(1, steps):
                prev = jump[s - 1]
                jump[s] = np.where(prev >= 0, prev[np.maximum(prev, 0)], -1)
        d = self.__dict__
        d["depth"] = _as_int_tuple(depth)
        d["root"] = _as_int_tuple(root)
        d["carrier_pair_ancestor"] = _as_int_tuple(anc)
        d["carrier_pair_body"] = _as_int_tuple(desc)
        d["carrier_pair_child"] = _as_int_tuple(child)
        d["subtree_pair_root"] = _as_int_tuple(sub_root)
        d["subtree_pair_body"] = _as_int_tuple(sub_body)
        d["jump_steps"] = steps
        d["jump_table"] = tuple(_as_int_tuple(row) for row in jump)
        d["children"] = tuple(
            tuple(int(j) for j in np.nonzero(par == k)[0].tolist()) for k in range(n)
        )

    # ------------------------------------------------------------------ static views
    @property
    def n_body(self) -> int:
        return len(self.parent)

    @property
    def parent_array(self) -> np.ndarray:
        return np.asarray(self.parent, dtype=np.int64)

    @property
    def is_root(self) -> np.ndarray:
        return self.parent_array < 0

    @cached_property
    def carrier_mask(self) -> np.ndarray:
        """``mask[i, k]`` is True iff ``i`` is a carrier (strict ancestor) of ``k``."""
        m = np.zeros((self.n_body, self.n_body), dtype=bool)
        m[np.asarray(self.carrier_pair_ancestor, int), np.asarray(self.carrier_pair_body, int)] = True
        return m

    @cached_property
    def subtree_mask(self) -> np.ndarray:
        """``mask[k, i]`` is True iff ``i`` belongs to subsystem ``k`` (self included)."""
        return self.carrier_mask | np.eye(self.n_body, dtype=bool)

    @cached_property
    def path_matrix(self) -> np.ndarray:
        """``T[k, i] = 1`` iff ``i`` is ``k`` or a carrier of ``k`` (spec §9.4: alpha = T q)."""
        return self.subtree_mask.T.astype(np.float64)

    def leaves(self) -> tuple[int, ...]:
        return tuple(k for k in range(self.n_body) if not self.children[k])

    # ------------------------------------------------------------------ traced helpers
    def _pairs(self, name):
        return jnp.asarray(np.asarray(getattr(self, name), dtype=np.int32))

    #: trees up to this many bodies use dense static 0/1 matrices for subtree, path and
    #: children sums (one matrix product, fast in batch); larger ones use segment sums.
    DENSE_LIMIT = 256

    def _dense(self, name) -> np.ndarray:
        cache = self.__dict__.setdefault("_dense_cache", {})
        if name not in cache:
            n = self.n_body
            if name == "subtree":
                m = self.subtree_mask
            elif name == "path":
                m = self.subtree_mask.T
            else:
                m = np.zeros((n, n), dtype=bool)
                for k, p in enumerate(self.parent):
                    if p >= 0:
                        m[p, k] = True
            cache[name] = m.astype(np.float64)
        return cache[name]

    def _matmul(self, name, x):
        m = jnp.asarray(self._dense(name), x.dtype)
        return jnp.tensordot(m, x, axes=1)

    def children_sum(self, x):
        """``out[k] = sum_{j in A(k)} x[j]`` (sum over adjacent bodies). ``x``: (n, ...)."""
        x = jnp.asarray(x)
        n = self.n_body
        if n <= self.DENSE_LIMIT:
            return self._matmul("children", x)
        par = np.asarray(self.parent, dtype=np.int32)
        nonroot = np.nonzero(par >= 0)[0].astype(np.int32)
        if nonroot.size == 0:
            return jnp.zeros_like(x)
        return jax.ops.segment_sum(
            x[jnp.asarray(nonroot)], jnp.asarray(par[nonroot]), num_segments=n
        )

    def subtree_sum(self, x):
        """``out[k] = sum_{i in S(k)} x[i]`` (sum over subsystem ``k``, ``k`` included)."""
        x = jnp.asarray(x)
        if self.n_body <= self.DENSE_LIMIT:
            return self._matmul("subtree", x)
        return jax.ops.segment_sum(
            x[self._pairs("subtree_pair_body")],
            self._pairs("subtree_pair_root"),
            num_segments=self.n_body,
            indices_are_sorted=True,
        )

    def path_sum(self, x):
        """``out[k] = sum_{i in C(k) or i = k} x[i]`` (sum from the root down to ``k``)."""
        x = jnp.asarray(x)
        if self.n_body <= self.DENSE_LIMIT:
            return self._matmul("path", x)
        return jax.ops.segment_sum(
            x[self._pairs("subtree_pair_root")],
            self._pairs("subtree_pair_body"),
            num_segments=self.n_body,
        )

    def accumulate_from_root(self, local, combine):
        """Compose per-body values from the root down: ``out[k] = l[root] ∘ ... ∘ l[p(k)] ∘ l[k]``.

        ``combine(outer, inner)`` must be associative; ``local`` is a pytree of arrays with a
        leading body axis. Uses pointer jumping: ``ceil(log2(depth+1))`` steps inside a
        ``fori_loop``, so the trace does not grow with the number of bodies.
        """
        if self.jump_steps == 0:
            return local
        table = jnp.asarray(np.asarray(self.jump_table, dtype=np.int32))

        def step(s, acc):
            idx = table[s]
            valid = idx >= 0
            outer = jax.tree.map(lambda a: a[jnp.maximum(idx, 0)], acc)
            new = combine(outer, acc)
            return jax.tree.map(
                lambda nw, old: jnp.where(valid.reshape((-1,) + (1,) * (old.ndim - 1)), nw, old),
                new,
                acc,
            )

        return jax.lax.fori_loop(0, self.jump_steps, step, local)
