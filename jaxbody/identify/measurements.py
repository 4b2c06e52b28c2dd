"""The data of an identification experiment: an exciting trajectory, and joint states
estimated from measured positions."""

from typing import NamedTuple

import numpy as np

from .._types import ArrayLike, Float
from ..joints import HINGE, SLIDE
from ..model import Model

__all__ = ["excitation_trajectory", "MeasuredStates", "states_from_positions"]


def excitation_trajectory(
    model: Model,
    t: Float[ArrayLike, " n"],
    n_harmonics: int = 5,
    base_frequency: float = 0.1,
    amplitude: float = 1.0,
    seed: int = 0,
):
    """A periodic excitation (finite Fourier series per DoF) and its exact rates.

    ``q_j(t) = q0_j + Σ_l (a_jl / (ω_l)) sin(ω_l t) − (b_jl / ω_l) cos(ω_l t)``, ``ω_l = 2π f l``,
    random coefficients scaled so each joint swings about ``amplitude`` rad. Only models whose
    joints are all hinges or slides (``nq == nv``). Returns NumPy ``(q, v, a)``, each ``(n, nv)``.
    """
    if any(k not in (HINGE, SLIDE) for k in model.joints.type):
        raise ValueError("excitation_trajectory needs a model with hinge and slide joints only")
    rng = np.random.default_rng(seed)
    t = np.asarray(t, dtype=np.float64)[:, None, None]
    w = 2 * np.pi * base_frequency * np.arange(1, n_harmonics + 1)  # (L,)
    A = rng.normal(size=(model.nv, n_harmonics))
    Bc = rng.normal(size=(model.nv, n_harmonics))
    s = amplitude / np.sqrt(np.sum((A**2 + Bc**2) / w**2, axis=1, keepdims=True))
    A, Bc = A * s, Bc * s
    q0 = rng.uniform(-0.5, 0.5, size=model.nv)
    sn, cs = np.sin(w * t), np.cos(w * t)
    q = q0 + np.sum(A / w * sn - Bc / w * cs, axis=-1)
    v = np.sum(A * cs + Bc * sn, axis=-1)
    a = np.sum(-A * w * sn + Bc * w * cs, axis=-1)
    return q, v, a


class MeasuredStates(NamedTuple):
    """Joint states estimated from measured positions (from :func:`states_from_positions`).

    Attributes:
        index: indices of the kept samples into the measured series, ``(m,)``.
        t: their times, ``(m,)``.
        q, v, a: smoothed positions and their first and second derivatives, ``(m, nv)``.
    """

    index: np.ndarray
    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    a: np.ndarray


def states_from_positions(
    t: Float[ArrayLike, " n"],
    q: Float[ArrayLike, "n nv"],
    window: float,
    order: int = 4,
    stride: int | None = None,
) -> MeasuredStates:
    """Positions, velocities and accelerations from noisy sampled joint positions.

    Encoders measure positions only; the regressor also needs ``v`` and ``a``. Each sample is
    replaced by the value and derivatives at its centre of a least-squares polynomial of degree
    ``order`` fitted over ``window`` seconds of samples (a Savitzky–Golay filter, zero phase
    lag). The half window at each end, where the filter extrapolates, is dropped, and only every
    ``stride``-th sample is kept (default: one window apart): filtered samples closer than a
    window share their measurements, so their errors are correlated, which the standard errors
    of :func:`least_squares` assume they are not.

    Use it when the acceleration noise the differentiation leaves, of order
    ``σ_q / (window/2)²``, is small against the excitation's accelerations (about 1 %): beyond
    that the regressor itself is noisy and the estimates are biased (errors in variables).

    Args:
        t: sample times, uniformly spaced, ``(n,)``.
        q: measured joint positions (hinge and slide joints, ``nq = nv``), ``(n, nv)``.
        window: length of the local fit in seconds (rounded to an odd number of samples,
            at least ``order + 3``).
        order: polynomial degree (at least 2, for accelerations).
        stride: keep every ``stride``-th filtered sample.
    """
    from scipy.signal import savgol_filter  # SciPy loads only when positions are filtered

    t = np.asarray(t, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] < 3:
        raise ValueError(f"states_from_positions: t must be a 1-D series of at least 3 samples, got shape {t.shape}")
    if q.ndim != 2 or q.shape[0] != t.shape[0]:
        raise ValueError(f"states_from_positions: q has shape {q.shape}, expected ({t.shape[0]}, nv)")
    if not np.all(np.isfinite(q)):
        raise ValueError("states_from_positions: q contains NaN or infinite samples")
    dt = np.diff(t)
    if not np.all(dt > 0) or np.ptp(dt) > 1e-6 * dt.mean():
        raise ValueError("states_from_positions: t must be increasing and uniformly spaced")
    dt = float(dt.mean())
    if int(order) < 2:
        raise ValueError(f"states_from_positions: order must be at least 2 (accelerations), got {order}")
    n_window = int(round(window / dt)) // 2 * 2 + 1
    if n_window < order + 3:
        raise ValueError(
            f"states_from_positions: window {window} s holds {n_window} samples; a degree-{order} fit needs at "
            f"least {order + 3}"
        )
    if n_window > t.shape[0]:
        raise ValueError(f"states_from_positions: window {window} s is longer than the series ({t[-1] - t[0]} s)")
    stride = n_window if stride is None else int(stride)
    if stride < 1:
        raise ValueError(f"states_from_positions: stride must be positive, got {stride}")
    half = n_window // 2
    index = np.arange(half, t.shape[0] - half, stride)
    smooth = [savgol_filter(q, n_window, order, deriv=k, delta=dt, axis=0)[index] for k in range(3)]
    return MeasuredStates(index, t[index], *smooth)
