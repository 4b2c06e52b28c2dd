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
import warnings

import jax

from .._types import Array, ArrayLike, Float
from .._util import check_shape
from ..model import Model
from . import native, unrolled, vectorised

__all__ = ["DEFAULT_KERNEL", "KERNELS", "KernelFallbackWarning", "acceleration", "default_kernel", "resolve_kernel"]

# ----------------------------------------------------------------------------- kernel choice
#: The forward-dynamics kernels :func:`acceleration` can run (see docs/performance.md).
KERNELS = ("auto", "native", "unrolled", "vectorised")
#: What ``kernel=None`` means when ``$JAXBODY_KERNEL`` is unset: ``"auto"``, the native kernel
#: wherever it can be built (5-20x faster per state than the vectorised kernel; the first use of
#: each tree costs a C++ compilation of a few seconds, cached on disk), else the fastest kernel
#: that can run (:func:`resolve_kernel`). ``JAXBODY_KERNEL=vectorised`` suits programs that
#: build hundreds of different trees, each of which would pay that compilation.
DEFAULT_KERNEL = "auto"


def default_kernel() -> str:
    """What ``kernel=None`` means now: ``$JAXBODY_KERNEL`` if set, else :data:`DEFAULT_KERNEL`
    (read at each call, so a program or a test can change it)."""
    kernel = os.environ.get("JAXBODY_KERNEL") or DEFAULT_KERNEL
    if kernel not in KERNELS:
        raise ValueError(f"$JAXBODY_KERNEL must be one of {KERNELS}, got {kernel!r}")
    return kernel


class KernelFallbackWarning(UserWarning):
    """``kernel="auto"`` runs a slower kernel than the native one; the message says why."""


_warned: set[str] = set()  # the reasons already told in this process: one line each


def _fall_back(reason: str, kernel: str) -> str:
    if reason not in _warned:
        _warned.add(reason)
        warnings.warn(f"jaxbody: kernel='auto' runs the {kernel} kernel, not the native one: {reason}",
                      KernelFallbackWarning, stacklevel=4)
    return kernel


def resolve_kernel(model: Model, kernel: str | None) -> str:
    """The kernel :func:`acceleration` runs for ``model``: ``"native"``, ``"unrolled"`` or ``"vectorised"``.

    ``None``: :func:`default_kernel` (``"auto"`` unless ``$JAXBODY_KERNEL`` says otherwise).
    ``"auto"``: the native kernel where :func:`jaxbody.backends.native.applies` (a C++ compiler, the
    CPU backend, a tree within :data:`jaxbody.backends.native.MAX_MASS_ENTRIES`); on another
    backend the unrolled kernel for trees within :data:`jaxbody.backends.unrolled.MAX_BODIES`;
    else vectorised. Falling back says why, once per reason and process, in a
    :class:`KernelFallbackWarning` (``warnings.simplefilter("ignore", KernelFallbackWarning)``
    silences it).
    """
    kernel = default_kernel() if kernel is None else kernel
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    if kernel == "native" and not native.available():
        reason = native.unavailable_reason()
        raise RuntimeError(
            "kernel='native' needs a C++17 compiler (g++ or $CXX) and the CPU backend"
            + (f" ({reason})" if reason else "")
            + "; use kernel='auto' (falls back to the vectorised kernel) or 'vectorised'"
        )
    if kernel != "auto":
        return kernel
    if native.applies(model):
        return "native"
    reason = native.unavailable_reason() or native.too_large_reason(model)
    if jax.default_backend() != "cpu" and unrolled.applies(model):
        return _fall_back(reason, "unrolled") if reason else "unrolled"
    return _fall_back(reason, "vectorised") if reason else "vectorised"


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
            :func:`default_kernel` (``"auto"`` unless ``$JAXBODY_KERNEL`` says otherwise).
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
