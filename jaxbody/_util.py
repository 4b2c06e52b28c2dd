"""Private index, shape and small-vector helpers shared by every module (one place each).

Nothing here is physics: converting static index lists, checking array shapes before tracing
(the first of the three error layers: static misuse raises while tracing), the skew matrix and planar/3-D vector helpers,
and :func:`compiled_when_eager`, which runs a function called on concrete values as one program.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .tiered_compilation import QUICK_OPTIONS
from .tiered_compilation import enabled as tiered_enabled

__all__ = ["compiled_when_eager", "int_tuple", "index", "check_shape", "skew", "cross2", "perp2", "rot2", "plane3", "axial3", "quat_to_matrix", "quat_multiply"]


def int_tuple(a) -> tuple[int, ...]:
    """Static index list as a tuple of Python ints (hashable, so it can sit in a static field)."""
    return tuple(int(v) for v in np.asarray(a, dtype=np.int64).reshape(-1).tolist())


def index(a) -> np.ndarray:
    """Static index list as an int32 NumPy array (a small constant when used in traced code)."""
    return np.asarray(a, dtype=np.int32).reshape(-1)


def check_shape(x, shape: tuple, name: str, where: str = "", dtype=None):
    """``jnp.asarray(x)`` of the given ``shape`` or a ``ValueError`` naming ``name`` (before tracing)."""
    x = jnp.asarray(x) if dtype is None else jnp.asarray(x, dtype)
    if tuple(x.shape) != tuple(shape):
        prefix = f"{where}: " if where else ""
        raise ValueError(f"{prefix}{name} has shape {tuple(x.shape)}, expected {tuple(shape)}")
    return x


def skew(a):
    """``[a]×`` with ``[a]× b = a × b`` (stacked over leading axes)."""
    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(a.shape[:-1] + (3, 3))


def cross2(a, b):
    """``k · (a × b)`` of planar vectors (the z component of the 3-D cross product)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def perp2(v):
    """``k × v`` of a planar vector."""
    return jnp.stack([-v[..., 1], v[..., 0]], axis=-1)


def rot2(theta, v):
    """Planar vector ``v`` rotated counter-clockwise by ``theta``."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def plane3(v):
    """Planar vectors ``(..., 2)`` as 3-D vectors in the plane ``z = 0``."""
    return jnp.concatenate([v, jnp.zeros_like(v[..., :1])], axis=-1)


def axial3(s):
    """Scalars ``(...)`` as 3-D vectors along ``k`` (planar angular rates as spatial ones)."""
    zero = jnp.zeros_like(s)
    return jnp.stack([zero, zero, s], axis=-1)


def quat_to_matrix(q):
    """Rotation matrix of a quaternion (w, x, y, z), normalised first (gradient-safe at 0).

    NumPy in, NumPy out (build time, float64); anything else goes through ``jax.numpy``.
    """
    xp = np if isinstance(q, np.ndarray) else jnp
    n2 = xp.sum(q * q, axis=-1, keepdims=True)
    # double where: the norm's derivative is infinite at q = 0
    safe = xp.where(n2 > 0, n2, 1.0)
    q = q / xp.sqrt(safe)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = xp.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return r.reshape(q.shape[:-1] + (3, 3))


def quat_multiply(a, b):
    """Hamilton product ``a ⊗ b`` of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def is_concrete(*xs) -> bool:
    """Whether no leaf of ``xs`` is traced (inside ``jit``, ``vmap`` or ``grad`` they are).

    Structural choices (a scene's path, a check that raises a Python error) can only be made
    from concrete values; traced ones defer to result codes or keep the general path.
    """
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(xs))


# the tracers of differentiation, whose ``primal`` is the value being differentiated at
_DIFFERENTIATION_TRACERS = ("LinearizeTracer", "JVPTracer")


def primal_value(x):
    """The concrete value a leaf stands for: itself when concrete; under ``jax.grad``,
    ``jax.vjp`` or ``jax.jvp`` of concrete values (and nothing else) the value being
    differentiated at; ``None`` for any other traced value (``jit``, ``vmap``)."""
    while isinstance(x, jax.core.Tracer):
        if type(x).__name__ not in _DIFFERENTIATION_TRACERS:
            return None
        x = getattr(x, "primal", None)
    return x


def concrete_primals(tree):
    """``tree`` with each leaf replaced by :func:`primal_value`, or ``None`` where some leaf has
    none. Under eager differentiation the forward values are concrete: a check of them can
    raise a plain Python error (and costs no operation on the tracers, each compiled alone)."""
    leaves, treedef = jax.tree.flatten(tree)
    values = [primal_value(x) for x in leaves]
    if any(v is None for v, x in zip(values, leaves) if x is not None):
        return None
    return jax.tree.unflatten(treedef, values)


def compiled_when_eager(method=None, *, quick: bool = False):
    """A function or method that runs as one compiled program when called on concrete values (in a
    notebook, a test, a failure diagnosis), and as plain code when traced (a vector field inside
    :func:`jaxbody.simulate`, ``jit``, ``vmap``, ``grad``), where the caller's program holds it.

    Called eagerly, JAX would run the method's hundreds of operations one by one, each compiled
    on its first use and dispatched on every call: a planar three-link scene's ``acceleration``
    cost 31 ms a call that way and costs 0.16 ms as one program (``benchmarks/eager_calls.py``).
    As one program it is one compilation, cached per scene structure
    and input shapes (:func:`equinox.filter_jit`: the scene's arrays are inputs, so new
    parameter values reuse it). Python floats among the arguments (a time ``t``) become arrays
    of the state's dtype, so a new value does not compile a new program; other non-array
    arguments (flags, names, integers) are static.

    ``quick=True`` (``@compiled_when_eager(quick=True)``): for a check that runs about once per
    system (at its construction), the program is compiled at XLA's backend optimisation level
    0 where tiered compilation is on (:func:`jaxbody.tiered_compilation.enabled`): a program
    that runs once has no later calls for the optimiser to speed up (with its checks compiled
    so, the four-bar linkage's construction went from 1.05 to 0.60 s with an empty cache,
    ``benchmarks/first_call.py``)."""
    if method is None:
        return functools.partial(compiled_when_eager, quick=quick)
    programs = {False: eqx.filter_jit(method)}
    if quick:
        programs[True] = eqx.filter_jit(method, compiler_options=QUICK_OPTIONS)

    @functools.wraps(method)
    def run(*args, **kwargs):
        leaves = jax.tree.leaves((args, kwargs))
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return method(*args, **kwargs)
        dtype = next((x.dtype for x in leaves if isinstance(x, (np.ndarray, jax.Array))
                      and jnp.issubdtype(x.dtype, jnp.floating)), None)

        def as_array(x):
            # a Python float would be a static argument, compiled into the program
            return jnp.asarray(x, dtype) if type(x) is float else x

        program = programs[quick and tiered_enabled()]
        return program(*(as_array(a) for a in args), **{k: as_array(a) for k, a in kwargs.items()})

    return run
