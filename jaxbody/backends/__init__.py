"""The forward-dynamics backends of a tree and the choice between them.

* :mod:`.vectorised`: :class:`~jaxbody.Data` and the kernels of :mod:`jaxbody.kernels` (any
  tree size, nothing but XLA);
* :mod:`.unrolled`: the tree algorithm of :mod:`.scalar` written out as straight-line scalar
  JAX (small trees, fastest on accelerators);
* :mod:`.native`: the same algorithm compiled to machine code and called through XLA's FFI
  (the CPU, with a C++ compiler).

:func:`acceleration` runs the one :func:`resolve_kernel` picks (docs/performance.md: when each
is faster).
"""

import os

import jax

from .._types import Array, ArrayLike, Float
from .._util import check_shape
from ..model import Model
from . import native, unrolled, vectorised

__all__ = ["DEFAULT_KERNEL", "KERNELS", "acceleration", "resolve_kernel"]

# ----------------------------------------------------------------------------- kernel choice
#: The forward-dynamics kernels :func:`acceleration` can run (see docs/performance.md).
KERNELS = ("auto", "native", "unrolled", "vectorised")
#: What ``kernel=None`` means: ``$JAXBODY_KERNEL`` if set, else the vectorised kernel, whose
#: compile time and memory are flat in the tree's size and which needs nothing but XLA.
#: ``"auto"`` (the native kernel where it can be built: 5-20x faster per state, but the first
#: use of each tree costs a C++ compilation of a few seconds, cached on disk) is opt-in.
DEFAULT_KERNEL = os.environ.get("JAXBODY_KERNEL", "vectorised")


def resolve_kernel(model: Model, kernel: str | None) -> str:
    """The kernel :func:`acceleration` runs for ``model``: ``"native"``, ``"unrolled"`` or ``"vectorised"``.

    ``"auto"``: the native kernel where :func:`jaxbody.backends.native.applies` (a C++ compiler, the
    CPU backend, at most :data:`jaxbody.backends.native.MAX_DOFS` DoFs); on another backend the
    unrolled kernel for trees within :data:`jaxbody.backends.unrolled.MAX_BODIES`; else vectorised.
    """
    kernel = DEFAULT_KERNEL if kernel is None else kernel
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    if kernel == "native" and not native.available():
        raise RuntimeError(
            "kernel='native' needs a C++17 compiler (g++ or $CXX) and the CPU backend; "
            "use kernel='auto' (falls back to the vectorised kernel) or 'vectorised'"
        )
    if kernel != "auto":
        return kernel
    if native.applies(model):
        return "native"
    if jax.default_backend() != "cpu" and unrolled.applies(model):
        return "unrolled"
    return "vectorised"


def _vectorised_acceleration(model: Model, q, v, force, gravity, external):
    return vectorised.forward_dynamics(model, q, v, force, gravity=gravity, external=external)


def _unrolled_acceleration(model: Model, q, v, force, gravity, external):
    return unrolled.forward_dynamics(model, q, v, force, gravity=gravity, external=external)


def _native_acceleration(model: Model, q, v, force, gravity, external):
    return native.forward_dynamics(model, q, v, force, gravity=gravity, external=external)


def acceleration(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    external: Float[ArrayLike, "n_body 6"] | None = None,
    kernel: str | None = None,
) -> Float[Array, " nv"]:
    """Forward dynamics from the coordinates: ``a = M⁻¹ (force − bias + Jᵀ external)``.

    The vector-field kernel of scenes (:func:`jaxbody.scene`) and
    :func:`jaxbody.forward_dynamics`; it checks nothing.

    Args:
        model, q, v: the model and its state.
        force: total generalized force in the layout of ``v`` (drives, springs, dampers);
            ``None`` = zero.
        gravity: uniform acceleration field (world) acting on every body; ``None`` = none.
        external: ``(n_body, 6)`` world force and torque at each centre of mass.
        kernel: ``"native"`` (the tree compiled to machine code, :mod:`jaxbody.backends.native`),
            ``"unrolled"`` (straight-line scalar program in JAX, :mod:`jaxbody.backends.unrolled`),
            ``"vectorised"`` (:class:`~jaxbody.Data` and the kernels of :mod:`jaxbody.kernels`) or ``"auto"``
            (:func:`resolve_kernel`; docs/performance.md: when each is faster). ``None``:
            :data:`DEFAULT_KERNEL`.
    """
    kernel = resolve_kernel(model, kernel)
    dtype = model.body_pos.dtype
    q = check_shape(q, (model.nq,), "q", dtype=dtype)
    v = check_shape(v, (model.nv,), "v", dtype=dtype)
    if force is not None:
        force = check_shape(force, (model.nv,), "force", dtype=dtype)
    if gravity is not None:
        gravity = check_shape(gravity, (3,), "gravity", dtype=dtype)
    if external is not None:
        external = check_shape(external, (model.n_body, 6), "external", dtype=dtype)
    args = (model, q, v, force, gravity, external)
    run = {"native": _native_acceleration, "unrolled": _unrolled_acceleration, "vectorised": _vectorised_acceleration}
    return run[kernel](*args)
