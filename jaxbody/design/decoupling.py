"""The dynamic decoupling check of Cor. 8 (as corrected in docs/mathematics.md, "Corollary 8") for planar systems."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..augmented import static_moment
from ..planar import ParamLike, PlanarSystem, mass_matrix

__all__ = ["DecouplingReport", "decoupling_report"]


class DecouplingReport(NamedTuple):
    """Result of :func:`decoupling_report` (docs/mathematics.md, "Corollary 8", corrected Cor. 8).

    Attributes:
        static_moment: ``m̄_k`` in body-``k`` axes, ``(n, 2)`` (NumPy).
        static_moment_magnitude: ``(md)_k = |m̄_k|``, ``(n,)``.
        must_vanish: ``(n,)`` bool: bodies whose ``m̄_k`` must vanish for decoupling — those with
            a carrier (non-empty ``C(k)``); all bodies on a translating base.
        offending: indices of bodies in ``must_vanish`` whose ``(md)_k`` exceeds the tolerance.
        decoupled: ``True`` when no body is offending.
        residual: largest ``|off-diagonal|`` of the absolute-angle mass matrix over the
            configurations.
        configurations: the configurations used, ``(n_config, nq)``.
    """

    static_moment: np.ndarray
    static_moment_magnitude: np.ndarray
    must_vanish: np.ndarray
    offending: tuple[int, ...]
    decoupled: bool
    residual: float
    configurations: np.ndarray


def decoupling_report(
    system: PlanarSystem,
    configurations: ParamLike | None = None,
    n_samples: int = 32,
    seed: int = 0,
    atol: float = 1e-12,
) -> DecouplingReport:
    """Dynamic decoupling check of Cor. 8 as corrected in docs/mathematics.md, "Corollary 8" (concrete values, not traced).

    The absolute-angle mass matrix is diagonal for all configurations iff ``m̄_k = 0`` for every
    body with a carrier (given non-zero hinge offsets ``R``); with a translating base, iff
    ``m̄_k = 0`` for every body. ``m̄`` of a body hinged to the fixed ground only gives its own
    gravity torque and does not couple.

    Args:
        system: planar system.
        configurations: ``(n_config, nq)`` configurations; default: ``n_samples`` uniform random
            angles in ``[-π, π)`` (base coordinates zero, they do not enter ``ℳ``) from ``seed``.
        atol: tolerance on ``(md)_k`` (scaled by ``1 + max (md)``) for ``offending``.
    """
    n = system.n_body
    mbar = np.asarray(
        static_moment(system.tree, system.body_mass, system.body_com, system.hinge_pos),
        dtype=np.float64,
    )
    md = np.linalg.norm(mbar, axis=-1)
    if system.translating_base:
        must = np.ones(n, dtype=bool)
    else:
        must = ~system.tree.is_root
    tol = atol * (1.0 + float(md.max()))
    offending = tuple(int(k) for k in np.nonzero(must & (md > tol))[0].tolist())
    if configurations is None:
        rng = np.random.default_rng(seed)
        cfg = np.zeros((n_samples, system.nq))
        cfg[:, system.n_base :] = rng.uniform(-np.pi, np.pi, size=(n_samples, n))
    else:
        cfg = np.asarray(configurations, dtype=np.float64)
        if cfg.ndim != 2 or cfg.shape[1] != system.nq:
            raise ValueError(
                f"decoupling_report: configurations has shape {cfg.shape}, "
                f"expected (n_config, {system.nq})"
            )
    dtype = system.body_mass.dtype
    Ms = jax.vmap(mass_matrix, in_axes=(None, 0))(system, jnp.asarray(cfg, dtype=dtype))
    Ms = np.asarray(Ms, dtype=np.float64)
    off = Ms * (1.0 - np.eye(system.nv))[None]
    residual = float(np.abs(off).max()) if off.size else 0.0
    return DecouplingReport(
        static_moment=mbar,
        static_moment_magnitude=md,
        must_vanish=must,
        offending=offending,
        decoupled=not offending,
        residual=residual,
        configurations=cfg,
    )
