"""Counting the equations a program really contains (shared by the trace-size tests)."""

import jax


def count_eqns(jaxpr) -> int:
    """Equations in a jaxpr, including those of every sub-jaxpr (loop bodies, custom rules)."""
    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else (param,):
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    total += count_eqns(sub.jaxpr)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    total += count_eqns(sub)
    return total
