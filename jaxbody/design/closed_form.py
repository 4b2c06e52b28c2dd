"""Closed-form balancing (leaves first, a counterweight opposite each static moment) and the
report every balancing returns."""

import time
from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from .bodies import (
    check_system,
    dimension,
    inertia_measure,
    is_planar,
    joint_anchors,
    link_length,
    resolve_bodies,
    static_moments,
)
from .counterweights import fold_counterweights
from .coupling_measure import coupling

__all__ = ["BalanceReport", "static_balance"]


class BalanceReport(NamedTuple):
    """Result of :func:`balance` / :func:`static_balance`.

    Attributes:
        bodies: bodies whose ``m̄_k`` was driven to zero.
        counterweight_bodies: bodies that carry a counterweight.
        counterweight_mass: ``(n_cw,)``.
        counterweight_position: ``(n_cw, dim)`` in each body's frame (as ``body_com``).
        added_mass: total counterweight mass.
        added_inertia: increase of ``Σ_k J_k`` (planar) or ``Σ_k tr I_k`` (spatial).
        static_moment_before, static_moment_after: ``m̄_k`` in body axes, ``(n, dim)``.
        residual_static_moment: ``max_{k in bodies} |m̄_k|`` after balancing divided by the
            largest ``|m̄_k|`` before.
        coupling_before, residual_coupling: :func:`coupling` before and after.
        iterations: optimiser iterations (0 for the closed form).
        wall_time: seconds.
        history: objective value per outer iteration.
        polished: the final closed-form step of :func:`balance` was applied.
        closed_form_added_mass: added mass of :func:`static_balance` on the same bodies with
            its default distances (for comparison; ``nan`` in the closed form itself).
        extension_length: ``(n_cw,)`` lengths of the link extensions (``None`` without them);
            ``added_mass`` then includes the extensions' own mass.
    """

    bodies: tuple
    counterweight_bodies: tuple
    counterweight_mass: np.ndarray
    counterweight_position: np.ndarray
    added_mass: float
    added_inertia: float
    static_moment_before: np.ndarray
    static_moment_after: np.ndarray
    residual_static_moment: float
    coupling_before: float
    residual_coupling: float
    iterations: int
    wall_time: float
    history: np.ndarray
    closed_form_added_mass: float
    polished: bool = False
    extension_length: np.ndarray | None = None

    def summary(self) -> str:
        lines = [
            f"decoupled bodies {list(self.bodies)}; counterweights on {list(self.counterweight_bodies)}",
            f"added mass {self.added_mass:.6g}, added inertia {self.added_inertia:.6g}"
            + ("" if np.isnan(self.closed_form_added_mass) else
               f" (closed form, counterweights mirroring the links: {self.closed_form_added_mass:.6g})"),
        ]
        ext = self.extension_length
        for i, (k, mu, p) in enumerate(zip(self.counterweight_bodies, self.counterweight_mass,
                                           self.counterweight_position)):
            lines.append(f"  body {k}: counterweight {mu:.6g} at {np.array2string(np.asarray(p), precision=5)}"
                         + ("" if ext is None else f" (end of a {ext[i]:.5g} extension)"))
        lines.append(
            f"residual |m̄| (relative) {self.residual_static_moment:.3e}; coupling "
            f"{self.coupling_before:.3e} -> {self.residual_coupling:.3e}"
        )
        return "\n".join(lines)


def static_balance(system, bodies: Sequence[int | str] | str | None = None, radius=None, n_samples: int = 32,
                   seed: int = 0):
    """Closed-form balancing: leaves first, a point counterweight opposite each static moment.

    For each body ``k`` of ``bodies`` in reverse topological order (its subtree already
    balanced), the counterweight sits at distance ``ρ_k`` from the base point, opposite the
    current ``m̄_k``, with mass ``μ_k = |m̄_k| / ρ_k``: then ``m̄_k = 0`` exactly, and its mass
    is part of the subsystem mass the parent sees. ``radius``: a number, a per-body
    sequence, or a ``{body: ρ}`` dict (default: the farthest of the body's CM and its
    children's joints from its base point, i.e. the counterweight mirrors the link).
    Runs on concrete values (NumPy loop), not traced.

    Returns:
        ``(balanced_system, BalanceReport)``.
    """
    check_system(system)
    start = time.perf_counter()
    req = resolve_bodies(system, bodies, "bodies")
    L = link_length(system)
    if radius is None:
        rad = {k: float(L[k]) for k in req}
    elif isinstance(radius, dict):
        rad = {int(k): float(v) for k, v in radius.items()}
    else:
        r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (system.n_body,))
        rad = {k: float(r[k]) for k in req}
    anchor = np.zeros((system.n_body, dimension(system))) if is_planar(system) else joint_anchors(system)
    mbar0 = np.asarray(static_moments(system), dtype=np.float64)
    J0 = float(np.sum(np.asarray(inertia_measure(system))))
    cur = system
    masses, positions = [], []
    for k in sorted(req, reverse=True):
        if rad.get(k, 0.0) <= 0:
            raise ValueError(f"static_balance: radius of body {k} must be positive")
        mb = np.asarray(static_moments(cur), dtype=np.float64)[k]
        nrm = float(np.linalg.norm(mb))
        if nrm == 0.0:
            mu, p = 0.0, anchor[k].copy()
        else:
            mu, p = nrm / rad[k], anchor[k] - rad[k] * mb / nrm
        cur = fold_counterweights(cur, [k], jnp.asarray([mu], cur.body_mass.dtype),
                                  jnp.asarray(p[None], cur.body_mass.dtype))
        masses.append(mu)
        positions.append(p)
    order = np.argsort(sorted(req, reverse=True))
    masses, positions = np.asarray(masses)[order], np.asarray(positions)[order]
    mbar1 = np.asarray(static_moments(cur), dtype=np.float64)
    scale = float(np.max(np.linalg.norm(mbar0, axis=1))) or 1.0
    report = BalanceReport(
        bodies=req,
        counterweight_bodies=req,
        counterweight_mass=masses,
        counterweight_position=positions.reshape(len(req), dimension(system)),
        added_mass=float(np.sum(masses)),
        added_inertia=float(np.sum(np.asarray(inertia_measure(cur)))) - J0,
        static_moment_before=mbar0,
        static_moment_after=mbar1,
        residual_static_moment=float(np.max(np.linalg.norm(mbar1[list(req)], axis=1)) / scale) if req else 0.0,
        coupling_before=coupling(system, n_samples=n_samples, seed=seed) if n_samples else float("nan"),
        residual_coupling=coupling(cur, n_samples=n_samples, seed=seed) if n_samples else float("nan"),
        iterations=0,
        wall_time=time.perf_counter() - start,
        history=np.zeros(0),
        closed_form_added_mass=float("nan"),
    )
    return cur, report
