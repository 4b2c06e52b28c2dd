"""The inertial parameters of a model: ten per body (Pinocchio's order), optional per-DoF
columns, and the model rebuilt from them."""

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._types import Array, ArrayLike, Float
from ..model import Model

__all__ = [
    "PARAMETER_NAMES", "EXTRA_COLUMNS", "SYMMETRIC_INDEX", "check_extra", "body_parameters", "unpack",
    "n_extra", "parameters", "parameter_names", "with_parameters", "reference_parameters",
]

#: Order of the ten inertial parameters of one body (Pinocchio's order).
PARAMETER_NAMES = ("m", "mc_x", "mc_y", "mc_z", "I_xx", "I_xy", "I_yy", "I_xz", "I_yz", "I_zz")
#: Optional per-DoF columns of the regressor: ``armature`` (× a), ``damping`` (× v),
#: ``friction`` (Coulomb, × sign v).
EXTRA_COLUMNS = ("armature", "damping", "friction")

#: The entries ``(i, j)`` of a symmetric 3×3 tensor in the order of the six inertia parameters
#: (``xx, xy, yy, xz, yz, zz``).
SYMMETRIC_INDEX = ((0, 0), (0, 1), (1, 1), (0, 2), (1, 2), (2, 2))


def check_extra(extra) -> tuple[str, ...]:
    """The extra column groups as a tuple, each of ``EXTRA_COLUMNS`` and none repeated."""
    extra = tuple(extra)
    for e in extra:
        if e not in EXTRA_COLUMNS:
            raise ValueError(f"unknown extra regressor column {e!r}; choose from {EXTRA_COLUMNS}")
    if len(set(extra)) != len(extra):
        raise ValueError(f"extra regressor columns repeated: {extra}")
    return extra


def body_parameters(
    mass: Float[ArrayLike, "*b"], com: Float[ArrayLike, "*b 3"], central_inertia: Float[ArrayLike, "*b 3 3"]
) -> Float[Array, "*b 10"]:
    """Ten inertial parameters from mass, centre of mass and inertia about the centre of mass.

    ``(m, m c, I_O)`` with ``I_O = I_C + m (|c|² E − c cᵀ)`` (parallel-axis theorem), the
    tensor entries in the order ``xx, xy, yy, xz, yz, zz``.
    """
    m = jnp.asarray(mass)
    c = jnp.asarray(com)
    Ic = jnp.asarray(central_inertia)
    eye = jnp.eye(3, dtype=c.dtype)
    c2 = jnp.sum(c * c, axis=-1)[..., None, None]
    Io = Ic + m[..., None, None] * (c2 * eye - c[..., :, None] * c[..., None, :])
    sym = jnp.stack([Io[..., i, j] for i, j in SYMMETRIC_INDEX], axis=-1)
    return jnp.concatenate([m[..., None], m[..., None] * c, sym], axis=-1)


def unpack(pi):
    """``(m, h = m c, I_O)`` from stacked ten-parameter vectors ``(..., 10)``."""
    m, h, s = pi[..., 0], pi[..., 1:4], pi[..., 4:10]
    xx, xy, yy, xz, yz, zz = (s[..., i] for i in range(6))
    Io = jnp.stack(
        [jnp.stack([xx, xy, xz], -1), jnp.stack([xy, yy, yz], -1), jnp.stack([xz, yz, zz], -1)], -2
    )
    return m, h, Io


def n_extra(model, extra) -> int:
    """Number of extra columns: one per DoF and group."""
    return model.nv * len(extra)


def parameters(
    model: Model, extra: Sequence[str] = (), friction: Float[ArrayLike, " nv"] | None = None
) -> Float[Array, " n_param"]:
    """The parameter vector ``π`` of a model: ten per body (body order), then ``extra``.

    Args:
        model: the model.
        extra: optional per-DoF groups appended in the given order, from ``EXTRA_COLUMNS``:
            ``"armature"`` (``dof_armature``), ``"damping"`` (``dof_damping``), ``"friction"``
            (Coulomb friction, not a model field: ``friction`` or zeros).

    Returns:
        ``(10 n_body + nv len(extra),)``.
    """
    extra = check_extra(extra)
    pi = body_parameters(model.body_mass, model.body_com, model.body_inertia).reshape(-1)
    parts = [pi]
    for e in extra:
        if e == "armature":
            parts.append(model.dof_armature)
        elif e == "damping":
            parts.append(model.dof_damping)
        else:
            f = jnp.zeros((model.nv,), pi.dtype) if friction is None else jnp.asarray(friction, pi.dtype)
            if f.shape != (model.nv,):
                raise ValueError(f"friction has shape {f.shape}, expected ({model.nv},)")
            parts.append(f)
    return jnp.concatenate(parts)


def parameter_names(model: Model, extra: Sequence[str] = ()) -> list[str]:
    """Names of the entries of :func:`parameters`, e.g. ``"mc_x[link3]"``, ``"damping[joint2]"``."""
    extra = check_extra(extra)
    names = [f"{p}[{b}]" for b in model.body_names for p in PARAMETER_NAMES]
    dof_names = [model.joint_names[j] + ("" if model.joints.nv == len(model.joint_names) else f".{i}")
                 for i, j in enumerate(model.joints.dof_joint)]
    for e in extra:
        names += [f"{e}[{d}]" for d in dof_names]
    return names


def with_parameters(
    model: Model, pi: Float[ArrayLike, " n_param"], extra: Sequence[str] = ()
) -> Model:
    """The model with the inertial (and ``extra``) parameters ``π`` of :func:`parameters`.

    Inverse of :func:`parameters` for bodies of positive mass: ``c = h / m``,
    ``I_C = I_O − (|h|² E − h hᵀ) / m``. A zero mass gives ``c = 0`` (gradient-safe).
    The ``friction`` group is not a model field and is ignored. Values are not validated
    (the result may be traced); see :func:`jaxbody.validate_parameters`.
    """
    extra = check_extra(extra)
    pi = jnp.asarray(pi, model.body_mass.dtype)
    nb = 10 * model.n_body
    if pi.shape != (nb + n_extra(model, extra),):
        raise ValueError(
            f"parameter vector has shape {pi.shape}, expected ({nb + n_extra(model, extra)},) "
            f"for {model.n_body} bodies and extra={extra}"
        )
    m, h, Io = unpack(pi[:nb].reshape(model.n_body, 10))
    pos = m > 0
    safe = jnp.where(pos, m, 1.0)
    c = jnp.where(pos[:, None], h / safe[:, None], 0.0)
    eye = jnp.eye(3, dtype=pi.dtype)
    hh = jnp.sum(h * h, axis=-1)[:, None, None] * eye - h[:, :, None] * h[:, None, :]
    Ic = Io - jnp.where(pos[:, None, None], hh / safe[:, None, None], 0.0)
    out = eqx.tree_at(lambda mo: (mo.body_mass, mo.body_com, mo.body_inertia), model, (m, c, Ic))
    for i, e in enumerate(extra):
        seg = pi[nb + i * model.nv : nb + (i + 1) * model.nv]
        if e == "armature":
            out = eqx.tree_at(lambda mo: mo.dof_armature, out, seg)
        elif e == "damping":
            out = eqx.tree_at(lambda mo: mo.dof_damping, out, seg)
    return out


def reference_parameters(model: Model, dtype):
    """The fixed reference ``π`` the linear maps are differentiated at: unit masses, zero first
    moments, identity inertias."""
    one = np.zeros((model.n_body, 10))
    one[:, 0] = 1.0
    one[:, [4, 6, 9]] = 1.0
    return jnp.asarray(one.reshape(-1), dtype)
