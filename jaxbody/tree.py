"""Body-tree topology as static index arrays (docs/mathematics.md, "Structure of the tree").

Computed once in NumPy and stored hashably (static fields); bodies are numbered parent-first;
traced code sums over subtrees and paths with these arrays, never with a Python loop over bodies.

A tree is given by a parent array: ``parent[k]`` is the base body (spec: "base body",
the parent) of body ``k`` or ``-1`` for a body jointed to the ground (or to a translating
base). Bodies are numbered topologically, ``parent[k] < k``.

Everything here is computed once in NumPy at build time and stored as tuples of Python
ints, so a :class:`BodyTree` is hashable and can live in an ``eqx.field(static=True)``.
Traced code uses the small helpers at the bottom (:meth:`BodyTree.subtree_sum`,
:meth:`BodyTree.path_sum`, :meth:`BodyTree.accumulate_from_root` ...). How they sum is the
tree's ``traversal``, chosen once when the tree is built and stored with it:

* ``"dense"`` (default up to :data:`DENSE_LIMIT` bodies): products with 0/1 matrices built
  from two length-``n`` index vectors (the preorder number of each body and the end of its
  subtree's preorder interval: ``i`` is an ancestor-or-self of ``k`` iff
  ``pre[i] <= pre[k] < end[i]``). One matrix product is fast in a batch. A mask of up to
  :data:`CONSTANT_MASK_ENTRIES` entries is computed here in NumPy and is a constant of the
  compiled program (a few kilobytes; built in the program, each of a constrained solve's
  dozens of masks was several operations to trace, lower and fold into a constant); a larger
  one is built *inside* the program, so that no ``n × n`` constant grows the program
  quadratically;
* ``"segment"`` (default above the limit): ``jax.ops.segment_sum`` over precomputed index
  pairs, whose memory grows with the pairs rather than with ``n²``.

Either way the number of traced operations does not depend on the number of bodies; the
recursions (:meth:`BodyTree.accumulate_from_root`) are a ``fori_loop`` over a static number of
pointer-jumping steps.

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

from ._util import index, int_tuple

__all__ = ["BodyTree", "CONSTANT_MASK_ENTRIES", "DENSE_LIMIT", "TRAVERSALS", "mask_module"]

#: default traversal: trees up to this many bodies use ``"dense"``, larger ones ``"segment"``
DENSE_LIMIT = 256
TRAVERSALS = ("dense", "segment")


class BodyTree:
    """Static topology of a tree of bodies (immutable; every index array built at construction).

    Args:
        parent: length-``n`` sequence of parent indices (``-1`` = ground / base).
        names: optional body names used in error messages (default ``body0``, ``body1``...).
        traversal: ``"dense"`` or ``"segment"`` (see the module docstring); ``None`` chooses
            ``"dense"`` up to :data:`DENSE_LIMIT` bodies.

    Raises:
        ValueError: lengths differ, a parent index is unknown, the parents form a cycle, the
            numbering is not topological (``parent[k] >= k``), or an unknown traversal. The
            message names the body.

    Equality and hash depend on ``parent``, ``names`` and ``traversal``.
    """

    def __init__(
        self, parent: Sequence, names: Sequence[str] | None = None, traversal: str | None = None
    ):
        parent_list = list(parent)
        n = len(parent_list)
        if names is None:
            names = [f"body{k}" for k in range(n)]
        names = [str(s) for s in names]
        if len(names) != n:
            raise ValueError(
                f"body tree: parent array has {n} entries but {len(names)} body names were given"
            )
        if traversal is None:
            traversal = "dense" if n <= DENSE_LIMIT else "segment"
        if traversal not in TRAVERSALS:
            raise ValueError(f"body tree: unknown traversal {traversal!r}; choose from {TRAVERSALS}")
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
        fields = dict(parent=int_tuple(parent_list), names=tuple(names), traversal=traversal)
        fields.update(_index_arrays(fields["parent"]))
        # jit hashes static fields on every call that takes a model: hash once here
        fields["_hash"] = hash((fields["parent"], fields["names"], traversal))
        for k, v in fields.items():
            object.__setattr__(self, k, v)

    def __setattr__(self, name, value):
        raise AttributeError("BodyTree is immutable")

    def __delattr__(self, name):
        raise AttributeError("BodyTree is immutable")

    def __eq__(self, other):
        if self is other:
            return True
        return (
            isinstance(other, BodyTree)
            and self._hash == other._hash
            and self.parent == other.parent
            and self.names == other.names
            and self.traversal == other.traversal
        )

    def __hash__(self):
        return self._hash

    def __repr__(self):
        return f"BodyTree(n_body={self.n_body}, parent={list(self.parent)}, traversal={self.traversal!r})"

    def with_traversal(self, traversal: str) -> "BodyTree":
        """The same tree with another traversal (a new object; trees are immutable)."""
        return BodyTree(self.parent, self.names, traversal)

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
        """``mask[i, k]`` is True iff ``i`` is a carrier (strict ancestor) of ``k`` (NumPy, build time)."""
        m = np.zeros((self.n_body, self.n_body), dtype=bool)
        m[np.asarray(self.carrier_pair_ancestor, int), np.asarray(self.carrier_pair_body, int)] = True
        return m

    @cached_property
    def subtree_mask(self) -> np.ndarray:
        """``mask[k, i]`` is True iff ``i`` belongs to subsystem ``k`` (self included; NumPy)."""
        return self.carrier_mask | np.eye(self.n_body, dtype=bool)

    @cached_property
    def path_matrix(self) -> np.ndarray:
        """``T[k, i] = 1`` iff ``i`` is ``k`` or a carrier of ``k`` (docs/mathematics.md, "Corollary 7": alpha = T q; NumPy)."""
        return self.subtree_mask.T.astype(np.float64)

    # ------------------------------------------------------------------ traced helpers
    def ancestor_or_self(self, anc, body):
        """Traced boolean array: ``anc`` is ``body`` or one of its carriers (broadcasting).

        ``anc`` and ``body`` are static or traced body indices; the test is the preorder
        interval ``pre[anc] <= pre[body] < end[anc]`` (two length-``n`` constants).
        """
        # static indices (NumPy) give a NumPy mask, which small masks bake in as a constant
        xp = np if isinstance(anc, np.ndarray) and isinstance(body, np.ndarray) else jnp
        pre = xp.asarray(index(self.preorder))
        end = xp.asarray(index(self.preorder_end))
        p_body = pre[body]
        return (pre[anc] <= p_body) & (p_body < end[anc])

    def _path_mask(self, dtype):
        """``P[k, i] = 1`` iff ``i`` is ``k`` or a carrier of ``k`` (:func:`mask_module`)."""
        xp = mask_module(self.n_body**2)
        ids = xp.arange(self.n_body, dtype=np.int32)
        return self.ancestor_or_self(ids[None, :], ids[:, None]).astype(dtype)

    def _children_mask(self, dtype):
        xp = mask_module(self.n_body**2)
        ids = xp.arange(self.n_body, dtype=np.int32)
        return (ids[:, None] == xp.asarray(index(self.parent))[None, :]).astype(dtype)

    def _pairs(self, name):
        return jnp.asarray(index(getattr(self, name)))

    def children_sum(self, x):
        """``out[k] = sum_{j in A(k)} x[j]`` (sum over adjacent bodies). ``x``: (n, ...)."""
        x = jnp.asarray(x)
        if self.traversal == "dense":
            return jnp.tensordot(self._children_mask(x.dtype), x, axes=1)
        par = index(self.parent)
        nonroot = np.nonzero(par >= 0)[0].astype(np.int32)
        if nonroot.size == 0:
            return jnp.zeros_like(x)
        return jax.ops.segment_sum(
            x[jnp.asarray(nonroot)], jnp.asarray(par[nonroot]), num_segments=self.n_body
        )

    def subtree_sum(self, x):
        """``out[k] = sum_{i in S(k)} x[i]`` (sum over subsystem ``k``, ``k`` included)."""
        x = jnp.asarray(x)
        if self.traversal == "dense":
            return jnp.tensordot(self._path_mask(x.dtype).T, x, axes=1)
        return jax.ops.segment_sum(
            x[self._pairs("subtree_pair_body")],
            self._pairs("subtree_pair_root"),
            num_segments=self.n_body,
            indices_are_sorted=True,
        )

    def path_sum(self, x):
        """``out[k] = sum_{i in C(k) or i = k} x[i]`` (sum from the root down to ``k``)."""
        x = jnp.asarray(x)
        if self.traversal == "dense":
            return jnp.tensordot(self._path_mask(x.dtype), x, axes=1)
        return jax.ops.segment_sum(
            x[self._pairs("subtree_pair_root")],
            self._pairs("subtree_pair_body"),
            num_segments=self.n_body,
        )

    def accumulate_from_root(self, local, combine):
        """Compose per-body values from the root down: ``out[k] = l[root] ∘ ... ∘ l[p(k)] ∘ l[k]``.

        ``combine(outer, inner)`` must be associative; ``local`` is a pytree of arrays with a
        leading body axis. Uses pointer jumping: ``ceil(log2(depth+1))`` steps inside a
        ``fori_loop``, so the trace does not grow with the number of bodies. The jump table
        is built in the program from the parent array (no ``steps × n`` constant).
        """
        if self.jump_steps == 0:
            return local

        def step(s, carry):
            acc, jump = carry
            valid = jump >= 0
            safe = jnp.maximum(jump, 0)
            outer = jax.tree.map(lambda a: a[safe], acc)
            new = combine(outer, acc)
            acc = jax.tree.map(
                lambda nw, old: jnp.where(valid.reshape((-1,) + (1,) * (old.ndim - 1)), nw, old),
                new,
                acc,
            )
            # 2^(s+1)-th ancestor = the 2^s-th ancestor of the 2^s-th ancestor
            jump = jnp.where(valid, jump[safe], -1)
            return acc, jump

        parent = jnp.asarray(index(self.parent))
        return jax.lax.fori_loop(0, self.jump_steps, step, (local, parent))[0]


#: A 0/1 mask of at most this many entries is a constant of the compiled program; a larger
#: one is built in the program from its index vectors (see the module docstring)
CONSTANT_MASK_ENTRIES = 4096


def mask_module(entries: int):
    """The array module a 0/1 mask of ``entries`` entries is built with: NumPy (a constant of
    the compiled program: nothing to trace, lower or fold) up to :data:`CONSTANT_MASK_ENTRIES`,
    ``jax.numpy`` above (built in the program from its length-``n`` index vectors, so that the
    program does not grow with ``n²``)."""
    return np if entries <= CONSTANT_MASK_ENTRIES else jnp


def _index_arrays(parent: tuple[int, ...]) -> dict:
    """Every static index array of a tree (computed once, NumPy, at construction)."""
    n = len(parent)
    par = np.asarray(parent, dtype=np.int64)
    depth = np.zeros(n, dtype=np.int64)
    root = np.arange(n)
    for k in range(n):
        if par[k] >= 0:
            depth[k] = depth[par[k]] + 1
            root[k] = root[par[k]]
    children = tuple(tuple(int(j) for j in np.nonzero(par == k)[0].tolist()) for k in range(n))
    # preorder numbering: a subtree is the contiguous interval [pre[k], end[k])
    pre = np.zeros(n, dtype=np.int64)
    end = np.zeros(n, dtype=np.int64)
    counter = 0
    stack = [(r, False) for r in reversed(range(n)) if par[r] < 0]
    while stack:
        k, done = stack.pop()
        if done:
            end[k] = counter
            continue
        pre[k] = counter
        counter += 1
        stack.append((k, True))
        stack.extend((c, False) for c in reversed(children[k]))
    # carrier pairs: (i, k, c(i,k)) for every strict ancestor i of k, sorted by k then depth
    anc, desc, child = [], [], []
    for k in range(n):
        c, i, path = k, par[k], []
        while i >= 0:
            path.append((i, c))
            c, i = i, par[i]
        for i, c in reversed(path):
            anc.append(i)
            desc.append(k)
            child.append(c)
    # subtree pairs (k, i) with i in S(k), self included; sorted by k (segment ids)
    sub_root = list(range(n)) + anc
    sub_body = list(range(n)) + desc
    order = np.lexsort((np.asarray(sub_body), np.asarray(sub_root))) if n else np.zeros(0, int)
    max_depth = int(depth.max()) if n else 0
    return dict(
        depth=int_tuple(depth),
        root=int_tuple(root),
        children=children,
        preorder=int_tuple(pre),
        preorder_end=int_tuple(end),
        carrier_pair_ancestor=int_tuple(anc),
        carrier_pair_body=int_tuple(desc),
        carrier_pair_child=int_tuple(child),
        subtree_pair_root=int_tuple(np.asarray(sub_root, dtype=np.int64)[order]),
        subtree_pair_body=int_tuple(np.asarray(sub_body, dtype=np.int64)[order]),
        # pointer-jumping steps: ceil(log2(max_depth + 1))
        jump_steps=max(1, int(np.ceil(np.log2(max_depth + 1)))) if max_depth > 0 else 0,
    )
