"""Counting the equations a program really contains (shared by the trace-size tests)."""

import jax


def count_eqns(jaxpr, match=None) -> int:
    """Equations in a jaxpr, including those of every sub-jaxpr (loop bodies, custom rules);
    ``match(eqn)``: count only the equations it accepts."""
    total = 0
    for eqn in jaxpr.eqns:
        total += 1 if match is None or match(eqn) else 0
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else (param,):
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    total += count_eqns(sub.jaxpr, match)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    total += count_eqns(sub, match)
    return total
