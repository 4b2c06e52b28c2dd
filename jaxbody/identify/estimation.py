"""Weighted least squares of the base parameters from measured joint forces."""

from typing import NamedTuple

import numpy as np

from .._types import ArrayLike, Float
from ..model import Model
from .base import BaseParameters
from .regression import stacked_regressor

__all__ = ["LeastSquaresFit", "least_squares"]


class LeastSquaresFit(NamedTuple):
    """Result of :func:`least_squares`.

    Attributes:
        estimate: base parameters ``β̂``, ``(r,)``.
        standard_error: their standard errors, ``(r,)``.
        covariance: ``(r, r)`` covariance of ``β̂``.
        noise_std: per-DoF noise standard deviation used as weights (given or estimated).
        residual: weighted residual sum of squares.
        dof: degrees of freedom of the residual (equations − r).
    """

    estimate: np.ndarray
    standard_error: np.ndarray
    covariance: np.ndarray
    noise_std: np.ndarray
    residual: float
    dof: int


def least_squares(
    model: Model,
    q: Float[ArrayLike, "n nq"],
    v: Float[ArrayLike, "n nv"],
    a: Float[ArrayLike, "n nv"],
    tau: Float[ArrayLike, "n nv"],
    base: BaseParameters,
    noise_std: Float[ArrayLike, " nv"] | None = None,
) -> LeastSquaresFit:
    """Weighted least squares of the base parameters from measured joint forces.

    Solves ``min_β Σ_t Σ_j (τ_tj − (Y₁(q_t, v_t, a_t) β)_j)² / σ_j²``. When ``noise_std``
    (``σ_j``) is not given it is estimated per DoF by iterative reweighting,
    ``σ_j² = |ρ_j|² / (n − h_j)`` with ``ρ_j`` the residuals and ``h_j`` the leverage of the
    rows of DoF ``j`` in the weighted fit (an unbiased estimate). The covariance is
    ``(W̃ᵀW̃)⁻¹`` with ``W̃`` the weighted base regressor (exact for known ``σ``; with
    estimated ``σ`` the usual large-sample approximation).
    """
    q, v, a, tau = (np.asarray(x, dtype=np.float64) for x in (q, v, a, tau))
    n = q.shape[0]
    if tau.shape != (n, model.nv):
        raise ValueError(f"tau has shape {tau.shape}, expected ({n}, {model.nv})")
    Y = base.reduce(stacked_regressor(model, q, v, a, base.extra))  # (n, nv, r)
    r = base.rank
    nv = model.nv

    def weighted(sigma):
        Wt = (Y / sigma[None, :, None]).reshape(-1, r)
        yt = (tau / sigma[None, :]).reshape(-1)
        Qm, Rm = np.linalg.qr(Wt)
        beta = np.linalg.solve(Rm, Qm.T @ yt)
        return beta, Qm, Rm, Wt, yt

    if noise_std is None:
        # iteratively reweighted: σ_j² = (residual sum of squares of DoF j) / (n − leverage of
        # its rows), which is unbiased for the weighted fit; three rounds settle it
        sigma = np.ones(nv)
        for _ in range(4):
            beta, Qm, _, _, _ = weighted(sigma)
            res = (tau - Y @ beta).reshape(n, nv)
            lev = np.sum(Qm**2, axis=1).reshape(n, nv).sum(axis=0)
            sigma = np.sqrt(np.sum(res**2, axis=0) / np.maximum(n - lev, 1.0))
    else:
        sigma = np.asarray(noise_std, dtype=np.float64)
    sigma = np.where(sigma > 0, sigma, np.finfo(np.float64).tiny ** 0.25)
    beta, Qm, Rm, Wt, yt = weighted(sigma)
    Rinv = np.linalg.inv(Rm)
    cov = Rinv @ Rinv.T
    rss = float(np.sum((yt - Wt @ beta) ** 2))
    return LeastSquaresFit(
        estimate=beta,
        standard_error=np.sqrt(np.diag(cov)),
        covariance=cov,
        noise_std=sigma,
        residual=rss,
        dof=int(Wt.shape[0] - r),
    )
