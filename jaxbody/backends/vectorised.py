"""The vectorised kernel: forward dynamics through :class:`~jaxbody.Data` and the kernels of
:mod:`jaxbody.kernels` (any tree size; its program does not grow with the number of bodies)."""

import jax.numpy as jnp

from .._types import Array, ArrayLike, Float
from ..data import compute_data
from ..kernels import force_factors, mass_matrix, project_force_factors
from ..linalg import solve_spd
from ..model import Model

__all__ = ["forward_dynamics"]


def forward_dynamics(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    external: Float[ArrayLike, "n_body 6"] | None = None,
) -> Float[Array, " nv"]:
    """``a = M⁻¹ (force − bias + Jᵀ external)`` by the vectorised kernels (no checks).

    The same arguments as :func:`jaxbody.backends.unrolled.forward_dynamics`: ``gravity``
    ``None`` means no gravity (pass ``model.gravity`` for the model's own).
    """
    data = compute_data(model, q, v)
    zero = jnp.zeros_like(data.v)
    factors = force_factors(model, data, zero, external=external, gravity=gravity)
    rhs = -project_force_factors(model, data, factors)
    if force is not None:
        rhs = rhs + force
    return solve_spd(mass_matrix(model, data), rhs)
