"""Array helpers of the planar builders: concrete parameters are assembled in NumPy, traced
ones (a system built inside ``jit``/``grad``) in ``jax.numpy``."""

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["is_traced", "array_namespace", "float_dtype"]


def is_traced(x) -> bool:
    """Whether ``x`` is a JAX tracer (a value inside ``jit``/``grad``/``vmap``)."""
    return isinstance(x, jax.core.Tracer)


def array_namespace(*values):
    """``jnp`` when any value is traced (building inside ``jit``/``grad``), else ``np``.

    Concrete parameters are assembled and validated in NumPy: eager JAX would compile every
    small operation of the builder.
    """
    return jnp if any(is_traced(v) for v in values) else np


def float_dtype(x):
    """The dtype of the parameters built from ``x``: its own when it is a floating array, else
    the default float dtype (float64 with ``jax_enable_x64``, else float32)."""
    if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating):
        return jax.dtypes.canonicalize_dtype(x.dtype)
    return jax.dtypes.canonicalize_dtype(np.float64)
