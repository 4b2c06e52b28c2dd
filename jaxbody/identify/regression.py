"""The inverse-dynamics regressor ``Y(q, v, a)`` with ``τ = Y π``, and random states to stack it at."""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._types import Array, ArrayLike, Float
from .._util import compiled_when_eager
from ..dynamics import inverse_dynamics
from ..model import Model
from .inertial import check_extra, reference_parameters, with_parameters

__all__ = ["regressor", "stacked_regressor"]


@compiled_when_eager  # one program when called on concrete states (it differentiates inverse dynamics)
def regressor(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    a: Float[ArrayLike, " nv"],
    extra: Sequence[str] = (),
) -> Float[Array, "nv n_param"]:
    """Inverse-dynamics regressor ``Y(q, v, a)`` with ``τ = Y π`` (π of :func:`parameters`).

    The rigid-body columns (ten per body) reproduce ``inverse_dynamics`` of the model
    **without armature** (gravity, Coriolis and centrifugal terms included). The ``extra``
    columns add, per DoF, ``a`` (armature), ``v`` (viscous damping: the drive must overcome
    ``−d v``) and ``sign v`` (Coulomb friction), so with ``extra=("armature", "damping")``
    ``Y π = inverse_dynamics(q, v, a) + dof_damping · v``.

    Computed by automatic differentiation of :func:`jaxbody.inverse_dynamics` with respect to
    ``π`` (the map is linear in ``π``); jit/vmap/grad pass through.
    """
    extra = check_extra(extra)
    dtype = model.body_mass.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    a = jnp.asarray(a, dtype)
    rigid = eqx.tree_at(lambda mo: mo.dof_armature, model, jnp.zeros_like(model.dof_armature))

    def tau(pi):
        return inverse_dynamics(with_parameters(rigid, pi), q, v, a)

    Y = jax.jacfwd(tau)(reference_parameters(model, dtype))
    cols = [Y]
    for e in extra:
        x = {"armature": a, "damping": v, "friction": jnp.sign(v)}[e]
        cols.append(jnp.diag(x))
    return jnp.concatenate(cols, axis=1)


_batched = eqx.filter_jit(jax.vmap(regressor, in_axes=(None, 0, 0, 0, None)))


def stacked_regressor(model, q, v, a, extra):
    """The regressor at each of the states ``(q, v, a)`` (rows of the arrays), NumPy float64."""
    Y = _batched(model, jnp.asarray(q), jnp.asarray(v), jnp.asarray(a), tuple(extra))
    return np.asarray(Y, dtype=np.float64)
