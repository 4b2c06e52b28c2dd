"""Physical consistency of inertial parameters: the pseudo-inertia, positive definite exactly
for consistent bodies, and its log-Cholesky parameterisation (every value consistent)."""

import jax
import jax.numpy as jnp
import numpy as np

from .._types import Array, ArrayLike, Float
from .inertial import SYMMETRIC_INDEX, unpack

__all__ = ["pseudo_inertia", "from_log_cholesky", "log_cholesky"]


def pseudo_inertia(pi_body: Float[ArrayLike, "*b 10"]) -> Float[Array, "*b 4 4"]:
    """4×4 pseudo-inertia ``J = [[Σ, h], [hᵀ, m]]`` with ``Σ = ½ tr(I_O) E − I_O``.

    ``J`` is positive definite iff the body is physically consistent (positive mass; inertia
    about the centre of mass positive definite with the triangle inequality, strictly).
    """
    m, h, Io = unpack(jnp.asarray(pi_body))
    eye = jnp.eye(3, dtype=h.dtype)
    Sigma = 0.5 * jnp.trace(Io, axis1=-2, axis2=-1)[..., None, None] * eye - Io
    top = jnp.concatenate([Sigma, h[..., :, None]], axis=-1)
    bottom = jnp.concatenate([h, m[..., None]], axis=-1)[..., None, :]
    return jnp.concatenate([top, bottom], axis=-2)


_TRIU = np.triu_indices(4)


def from_log_cholesky(theta: Float[ArrayLike, "*b 10"]) -> Float[Array, "*b 10"]:
    """Inertial parameters from the log-Cholesky factor of the pseudo-inertia.

    ``θ`` holds the upper triangle of ``U`` row by row (``J = U Uᵀ``), with the logarithm of
    the four diagonal entries in place of the entries. Every ``θ ∈ R¹⁰`` gives a physically
    consistent body, and the map is smooth (Rucker & Wensing's log-Cholesky parameterisation).
    """
    theta = jnp.asarray(theta)
    diag = np.array([i == j for i, j in zip(*_TRIU)])
    vals = jnp.where(jnp.asarray(diag), jnp.exp(theta), theta)
    U = jnp.zeros(theta.shape[:-1] + (4, 4), theta.dtype).at[..., _TRIU[0], _TRIU[1]].set(vals)
    J = U @ jnp.swapaxes(U, -1, -2)
    Sigma, h, m = J[..., :3, :3], J[..., :3, 3], J[..., 3, 3]
    Io = jnp.trace(Sigma, axis1=-2, axis2=-1)[..., None, None] * jnp.eye(3, dtype=J.dtype) - Sigma
    sym = jnp.stack([Io[..., i, j] for i, j in SYMMETRIC_INDEX], axis=-1)
    return jnp.concatenate([m[..., None], h, sym], axis=-1)


def log_cholesky(pi_body: ArrayLike) -> np.ndarray:
    """Inverse of :func:`from_log_cholesky` (NumPy; raises for inconsistent bodies)."""
    J = np.asarray(pseudo_inertia(jnp.asarray(pi_body, jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)),
                   dtype=np.float64)
    flat = J.reshape(-1, 4, 4)
    out = []
    for k, Jk in enumerate(flat):
        # upper Cholesky J = U Uᵀ from the lower one of the reversed matrix
        try:
            L = np.linalg.cholesky(Jk[::-1, ::-1])
        except np.linalg.LinAlgError:
            raise ValueError(
                f"body {k}: inertial parameters are not physically consistent (pseudo-inertia not "
                "positive definite: non-positive mass or inertia breaking the triangle inequality)"
            ) from None
        U = L[::-1, ::-1]
        vals = U[_TRIU]
        diag = np.array([i == j for i, j in zip(*_TRIU)])
        out.append(np.where(diag, np.log(np.where(diag, vals, 1.0)), vals))
    return np.asarray(out).reshape(np.shape(pi_body))
