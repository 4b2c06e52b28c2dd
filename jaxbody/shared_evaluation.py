"""Evaluations shared within one traced function: the same kinematics computed once.

A constrained vector field asks for the frames of the same configuration many times: the mass
matrix and the velocity terms, then every loop closure for its gap, its Jacobian, its velocity
bias and its Baumgarte residual. Each request traced separately is another copy of forward
kinematics in the compiled program. XLA merges some of the copies after tracing, but each still
costs its trace and its share of the compile, and a quickly compiled program (the first call's)
runs them all. Sharing them took a Cassie-like biped's solve from 67 copies to 8, its quick
compile from 11.4 to 4.3 s and its optimised run from 2.4 to 0.8 s
(``benchmarks/constrained_program.py``).

Within :func:`shared_evaluations`, a function decorated with :func:`shared` returns its first
result again when it is called with the same arguments (the same pytree structure around the
very same leaf objects: tracers have no value to compare) in the same trace. The trace is part
of the key because a result computed inside a nested trace (a ``lax.cond`` branch, a ``jvp``)
holds that trace's tracers, which must not escape to the caller. Outside a scope the functions
run as usual. Scopes are per thread (solves are traced on helper threads beside the caller's).
"""

import contextlib
import functools
import threading
from collections.abc import Callable, Iterator

import jax
from jax.extend.core import get_opaque_trace_state

__all__ = ["shared", "shared_evaluations"]

_local = threading.local()


def _scopes() -> list:
    scopes = getattr(_local, "scopes", None)
    if scopes is None:
        scopes = _local.scopes = []
    return scopes


@contextlib.contextmanager
def shared_evaluations() -> Iterator[None]:
    """Share the results of :func:`shared` functions until the block ends.

    Open it inside the traced function whose evaluations should be shared (a vector field's
    body); nested scopes share with the outermost one. Results are held until the outermost
    scope closes, so that no argument's identity is reused while its entry lives.
    """
    scopes = _scopes()
    scopes.append({} if not scopes else scopes[-1])
    try:
        yield
    finally:
        scopes.pop()


def shared(fn: Callable) -> Callable:
    """``fn`` evaluated once per set of arguments and trace inside :func:`shared_evaluations`
    (positional arguments only; keyword calls are not shared).

    Arguments match when their pytree structures are equal and their leaves are the same
    objects: a model rebuilt around the same arrays (``eqx.tree_at`` rebuilds the nodes it
    passes through) still matches, a model with one new parameter array does not.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        scopes = _scopes()
        if not scopes or kwargs:
            return fn(*args, **kwargs)
        memo = scopes[-1]
        leaves, structure = jax.tree.flatten(args)
        key = (fn, structure, *map(id, leaves))
        state = get_opaque_trace_state()
        hit = memo.get(key)
        # the stored leaves keep their identities unique while the entry lives; the trace check
        # keeps a nested trace's tracers from reaching its caller
        if hit is not None and hit[1] == state and all(a is b for a, b in zip(hit[0], leaves)):
            return hit[2]
        out = fn(*args)
        memo[key] = (leaves, state, out)
        return out

    return wrapper
