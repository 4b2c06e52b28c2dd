"""Balancing synthesis with optax: counterweights (optionally on link extensions) that make the
chosen static moments vanish while penalising added mass and inertia."""

import time
import warnings
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .bodies import (
    body_names,
    check_system,
    dimension,
    inertia_measure,
    is_planar,
    joint_anchors,
    link_length,
    link_reach,
    resolve_bodies,
    static_moments,
)
from .closed_form import BalanceReport, static_balance
from .counterweights import fold_counterweights, fold_point_masses, fold_with_extensions
from .coupling_measure import coupling

__all__ = ["balance", "tradeoff_curve"]


def _extensions(system, cw, extensions, mbar0):
    """Resolve the ``extensions`` option: length bounds ``(n_cw,)`` ×2, density ``(n_cw,)``
    and unit directions ``(n_cw, dim)`` in body frames (``None`` when off)."""
    if extensions is None or extensions is False:
        return None
    opts = {} if extensions is True else dict(extensions)
    unknown = set(opts) - {"length", "density", "direction"}
    if unknown:
        raise ValueError(f"extensions: unknown keys {sorted(unknown)}; use 'length', 'density' and 'direction'")
    c = np.asarray(cw, dtype=np.int64)
    dim = dimension(system)
    _, vec = link_reach(system)
    L = link_length(system)[c]
    lo, hi = opts.get("length", (0.0, L))
    lo = np.broadcast_to(np.asarray(lo, dtype=np.float64), (len(cw),)).copy()
    hi = np.broadcast_to(np.asarray(hi, dtype=np.float64), (len(cw),)).copy()
    if np.any(lo < 0) or np.any(hi <= lo):
        raise ValueError(f"extensions: need 0 <= length lower < length upper, got ({lo.tolist()}, {hi.tolist()})")
    rho = np.broadcast_to(np.asarray(opts.get("density", 0.0), dtype=np.float64), (len(cw),)).copy()
    if np.any(rho < 0):
        raise ValueError(f"extensions: density must be non-negative, got {rho.tolist()}")
    if "direction" in opts:
        d = np.broadcast_to(np.asarray(opts["direction"], dtype=np.float64), (len(cw), dim)).copy()
    else:
        # backwards along the link: opposite the reach; a body without reach: opposite m̄
        d = -vec[c]
        flat = np.linalg.norm(d, axis=1) == 0
        d[flat] = -mbar0[c][flat]
        d[np.linalg.norm(d, axis=1) == 0] = np.eye(dim)[0]
    nrm = np.linalg.norm(d, axis=1)
    if np.any(nrm == 0) or not np.all(np.isfinite(d)):
        raise ValueError("extensions: every direction must be a finite non-zero vector")
    return lo, hi, rho, d / nrm[:, None]


def _bounds(system, cw, bounds):
    dim = dimension(system)
    bounds = dict(bounds or {})
    unknown = set(bounds) - {"mass", "position"}
    if unknown:
        raise ValueError(f"bounds: unknown keys {sorted(unknown)}; use 'mass' and 'position'")
    total = float(np.sum(np.asarray(system.body_mass)))
    mlo, mhi = bounds.get("mass", (0.0, 5.0 * total))
    mlo = np.broadcast_to(np.asarray(mlo, dtype=np.float64), (len(cw),)).copy()
    mhi = np.broadcast_to(np.asarray(mhi, dtype=np.float64), (len(cw),)).copy()
    if np.any(mlo < 0) or np.any(mhi <= mlo):
        raise ValueError(f"bounds: need 0 <= mass lower < mass upper, got ({mlo.tolist()}, {mhi.tolist()})")
    anchor = np.zeros((system.n_body, dim)) if is_planar(system) else joint_anchors(system)
    L = link_length(system)
    if "position" in bounds:
        plo, phi = bounds["position"]
        plo = np.broadcast_to(np.asarray(plo, dtype=np.float64), (len(cw), dim)).copy()
        phi = np.broadcast_to(np.asarray(phi, dtype=np.float64), (len(cw), dim)).copy()
    else:
        c = np.asarray(cw, dtype=np.int64)
        plo = anchor[c] - L[c][:, None]
        phi = anchor[c] + L[c][:, None]
    if np.any(phi <= plo):
        raise ValueError("bounds: every position upper bound must exceed its lower bound")
    return (mlo, mhi), (plo, phi)


def _bounded_inv(y):
    """Inverse of ``y = (1 + sin u) / 2`` on ``[-π/2, π/2]``."""
    return np.arcsin(np.clip(2.0 * np.asarray(y) - 1.0, -1.0, 1.0))


class _Problem(eqx.Module):
    system: Any
    cw: tuple = eqx.field(static=True)
    req: tuple = eqx.field(static=True)
    mlo: Any
    mhi: Any
    plo: Any
    phi: Any
    scale: Any
    m_total: Any
    J_total: Any
    J0: Any
    w_mass: Any
    w_inertia: Any
    gyration: float = eqx.field(static=True)
    # link extensions (None when off): the second design variable is then the extension
    # length in [plo, phi] (n_cw,), and the counterweight sits at anchor + length · direction
    anchor: Any = None
    direction: Any = None
    density: Any = None

    def decode(self, x):
        """Counterweight masses, positions and extension lengths (``None`` without)."""
        u, w = x
        # x = lo + (hi - lo)(1 + sin u)/2: bounded, and the bounds are reached at finite u
        # with a non-vanishing curvature (a sigmoid would flatten out towards them)
        mu = self.mlo + (self.mhi - self.mlo) * 0.5 * (1.0 + jnp.sin(u))
        y = self.plo + (self.phi - self.plo) * 0.5 * (1.0 + jnp.sin(w))
        if self.direction is None:
            return mu, y, None
        return mu, self.anchor + y[:, None] * self.direction, y

    def folded(self, x):
        mu, p, e = self.decode(x)
        if e is None:
            return fold_counterweights(self.system, self.cw, mu, p, self.gyration)
        return fold_with_extensions(self.system, self.cw, mu, p, e, self.anchor, self.direction,
                                     self.density, self.gyration)

    def added_mass(self, x):
        mu, _, e = self.decode(x)
        return jnp.sum(mu) if e is None else jnp.sum(mu) + jnp.sum(self.density * e)

    def parts(self, x):
        s = self.folded(x)
        c = (static_moments(s)[np.asarray(self.req, dtype=np.int64)] / self.scale[:, None]).reshape(-1)
        dJ = jnp.sum(inertia_measure(s)) - self.J0
        f = self.w_mass * self.added_mass(x) / self.m_total + self.w_inertia * dJ / self.J_total
        return f, c


def _minimise(fun, x0, steps, optimizer, learning_rate):
    if optimizer == "lbfgs":
        opt = optax.lbfgs()
        vg = optax.value_and_grad_from_state(fun)

        def body(i, carry):
            x, st = carry
            val, g = vg(x, state=st)
            upd, st = opt.update(g, st, x, value=val, grad=g, value_fn=fun)
            return optax.apply_updates(x, upd), st
    else:
        opt = optax.adam(learning_rate)

        def body(i, carry):
            x, st = carry
            g = jax.grad(fun)(x)
            upd, st = opt.update(g, st, x)
            return optax.apply_updates(x, upd), st

    x, _ = jax.lax.fori_loop(0, steps, body, (x0, opt.init(x0)))
    return x


@eqx.filter_jit
def _solve_al(problem, x0, lam, rho, steps, optimizer, learning_rate):
    def L(x):
        f, c = problem.parts(x)
        return f + jnp.dot(lam, c) + 0.5 * rho * jnp.dot(c, c)

    x = _minimise(L, x0, steps, optimizer, learning_rate)
    f, c = problem.parts(x)
    return x, f, c


@eqx.filter_jit
def _solve_penalty(problem, x0, w_coupling, steps, optimizer, learning_rate):
    def P(x):
        f, c = problem.parts(x)
        return f + w_coupling * jnp.dot(c, c)

    x = _minimise(P, x0, steps, optimizer, learning_rate)
    f, c = problem.parts(x)
    return x, f, c


def balance(
    system,
    bodies: Sequence[int | str] | str | None = None,
    counterweights: Sequence[int | str] | None = None,
    bounds: dict | None = None,
    penalty: dict | None = None,
    *,
    extensions: dict | bool | None = None,
    exact: bool = True,
    coupling_weight: float = 1e3,
    optimizer: str = "lbfgs",
    learning_rate: float = 0.05,
    steps: int = 200,
    outer: int = 12,
    tol: float = 1e-13,
    gyration: float = 0.0,
    polish: bool = True,
    n_samples: int = 32,
    seed: int = 0,
):
    """Balancing synthesis: counterweights that make the chosen static moments vanish.

    Args:
        system: planar system (:mod:`jaxbody.planar`) or :class:`Model` (spatial tree).
        bodies: bodies whose ``m̄_k`` must vanish (indices or names). Default
            (:func:`required_bodies`): those the corrected Cor. 8 requires for full decoupling;
            ``"all"`` also balances the root against gravity; a subset decouples partially.
        counterweights: bodies that carry a counterweight (default: ``bodies``).
        bounds: ``{"mass": (lo, hi), "position": (lo, hi)}``; masses ``(n_cw,)`` or scalars,
            positions ``(n_cw, dim)`` or ``(dim,)`` in body frames. Default: masses up to five
            times the total mass, positions within the link's own reach around its joint.
        penalty: ``{"mass": w_m, "inertia": w_I}`` weights of the added mass (relative to the
            total mass) and the added augmented inertia (relative to the total); default 1, 1.
        extensions: link extensions as design variables (``None``: off). ``True`` or
            ``{"length": (lo, hi), "density": λ, "direction": d}``: each counterweight body's
            link is extended beyond its joint by a straight uniform rod of length ``e`` in
            ``[lo, hi]`` (default ``[0, L_k]``, ``L_k`` the link's own reach: the farthest of
            its CM and its children's joints), of mass ``λ e`` per body (``density`` in mass per
            length, default ``0``: a massless arm), along the unit direction ``d`` in the body
            frame (default: backwards along the link, opposite the reach), and the
            counterweight is clamped at the rod's end, ``p = anchor + e d``. The design
            variables per body are then the counterweight mass and ``e``; the rod's mass,
            static moment and inertia (``λ e³/3`` about the joint) are folded into the body
            with the counterweight and count as added mass and inertia. A counterweight on
            the link's line cancels only the static moment along it: for a link whose CM lies
            off that line, give ``direction`` or use free positions. Excludes
            ``bounds["position"]``. The link geometry that defines the mechanism (joint
            positions ``hinge_pos``, the children's joints) is not changed.
        exact: enforce ``m̄_k = 0`` (augmented Lagrangian, ``outer`` multiplier updates of
            ``steps`` optimiser iterations each) or, with ``False``, penalise
            ``coupling_weight · |m̄ / scale|²`` (one solve; use it for trade-off curves).
        optimizer: ``"lbfgs"`` (optax.lbfgs) or ``"adam"`` (with ``learning_rate``).
        tol: stop the outer iterations when ``max |m̄_k| / scale`` falls below it.
        gyration: radius of gyration of the counterweights (``0``: point masses).
        polish: with ``exact``, finish with the closed-form step at the optimiser's distances
            (see :func:`static_balance`) so the static moments vanish to round-off.
        n_samples, seed: random configurations for the coupling measure.

    Returns:
        ``(balanced_system, BalanceReport)``.

    Raises:
        TypeError: not a planar system or Model.
        ValueError: unknown bodies, bad bounds or penalty keys, a required body without a
            counterweight on it or below it.
    """
    check_system(system)
    start = time.perf_counter()
    req = resolve_bodies(system, bodies, "bodies")
    cw = req if counterweights is None else resolve_bodies(system, counterweights, "counterweights")
    if not req:
        raise ValueError("balance: no body to decouple (nothing has a carrier); pass bodies='all' to balance statically")
    sub = system.tree.subtree_mask  # [k, i]: i in subsystem k
    for k in req:
        if not any(sub[k, c] for c in cw):
            raise ValueError(
                f"balance: body {k} ({body_names(system)[k]!r}) must be balanced but carries no counterweight "
                "on itself or below it"
            )
    if optimizer not in ("lbfgs", "adam"):
        raise ValueError(f"optimizer must be 'lbfgs' or 'adam', got {optimizer!r}")
    penalty = dict(penalty or {})
    unknown = set(penalty) - {"mass", "inertia"}
    if unknown:
        raise ValueError(f"penalty: unknown keys {sorted(unknown)}; use 'mass' and 'inertia'")
    if extensions not in (None, False) and "position" in dict(bounds or {}):
        raise ValueError("bounds: 'position' cannot be combined with extensions (the counterweight sits at the "
                         "end of its extension; bound the extension length instead)")
    (mlo, mhi), (plo, phi) = _bounds(system, cw, bounds)
    dtype = system.body_mass.dtype
    mbar0 = np.asarray(static_moments(system), dtype=np.float64)
    ext = _extensions(system, cw, extensions, mbar0)
    scale = float(np.max(np.linalg.norm(mbar0, axis=1)))
    scale = scale if scale > 0 else 1.0
    # each constraint m̄_k = 0 in units of its own size: subsystem mass times the body's reach
    msub = np.asarray(system.tree.subtree_mask, dtype=np.float64) @ np.asarray(system.body_mass)
    req_scale = msub[list(req)] * link_length(system)[list(req)]
    req_scale = np.where(req_scale > 0, req_scale, scale)
    J = np.asarray(inertia_measure(system), dtype=np.float64)
    f = lambda a: jnp.asarray(a, dtype)
    anchor = np.zeros((system.n_body, dimension(system))) if is_planar(system) else joint_anchors(system)
    cwi = np.asarray(cw, dtype=np.int64)
    extra = {}
    if ext is not None:
        plo, phi = ext[0], ext[1]
        extra = dict(anchor=f(anchor[cwi]), direction=f(ext[3]), density=f(ext[2]))
    problem = _Problem(
        system=system, cw=cw, req=req, mlo=f(mlo), mhi=f(mhi), plo=f(plo), phi=f(phi), scale=f(req_scale),
        m_total=f(np.sum(np.asarray(system.body_mass))), J_total=f(np.sum(J)), J0=f(np.sum(J)),
        w_mass=f(penalty.get("mass", 1.0)), w_inertia=f(penalty.get("inertia", 1.0)), gyration=float(gyration),
        **extra,
    )
    # start: each counterweight opposite its body's static moment at half the link's reach,
    # with the mass that would cancel that moment alone (children's counterweights ignored)
    nrm = np.linalg.norm(mbar0[cwi], axis=1)
    half = 0.5 * link_length(system)[cwi]
    if ext is None:
        d = -mbar0[cwi] / np.maximum(nrm, 1e-300)[:, None]
        y0 = np.clip(anchor[cwi] + d * half[:, None], plo, phi)
    else:  # half-way along the extension's range
        y0 = 0.5 * (plo + phi)
        half = np.where(y0 > 0, y0, half)
    mu0 = np.clip(nrm / half, mlo, mhi)
    x = (f(_bounded_inv((mu0 - mlo) / (mhi - mlo))), f(_bounded_inv((y0 - plo) / (phi - plo))))
    history = []
    it = 0
    if exact:
        lam = jnp.zeros((len(req) * dimension(system),), dtype)
        # a large first penalty keeps the iterates near the constraint surface, where a bound
        # (zero counterweight) cannot become a spurious stationary point
        rho = f(1e3 * (1.0 + float(penalty.get("mass", 1.0)) + float(penalty.get("inertia", 1.0))))
        for _ in range(outer):
            with jax.numpy_dtype_promotion("standard"):  # optax's L-BFGS mixes int32/int64
                x, fv, c = _solve_al(problem, x, lam, rho, steps, optimizer, learning_rate)
            it += steps
            history.append(float(fv))
            res = float(jnp.max(jnp.abs(c)))
            if res < tol:
                break
            lam = lam + rho * c
            rho = jnp.minimum(rho * 4.0, f(1e8))
    else:
        with jax.numpy_dtype_promotion("standard"):
            x, fv, c = _solve_penalty(problem, x, f(coupling_weight), steps * outer, optimizer, learning_rate)
        it = steps * outer
        history.append(float(fv))
    mu, p, e = problem.decode(x)
    added = float(problem.added_mass(x))
    out = problem.folded(x)
    mbar1 = np.asarray(static_moments(out), dtype=np.float64)
    polished = False
    if exact and polish and set(cw) == set(req) and ext is not None:
        # the same final step with the extension lengths kept: leaves first, the mass at the
        # end of each extension that zeroes the static moment along it
        res = float(np.max(np.linalg.norm(mbar1[list(req)], axis=1) / req_scale))
        if res > 0:
            cand = _polish_extensions(problem, np.asarray(e), np.asarray(mlo), np.asarray(mhi))
            if cand is not None:
                mu_c, s_c = cand
                mb_c = np.asarray(static_moments(s_c), dtype=np.float64)
                if float(np.max(np.linalg.norm(mb_c[list(req)], axis=1) / req_scale)) < res:
                    mu, out, mbar1, polished = jnp.asarray(mu_c), s_c, mb_c, True
                    added = float(np.sum(mu_c) + np.sum(ext[2] * np.asarray(e)))
    elif exact and polish and set(cw) == set(req):
        # Final exact step: keep the distance of every counterweight from its joint that the
        # optimiser chose and solve, leaves first, for the direction and mass that zero m̄_k
        # (the closed form of static_balance); it moves the design by the order of the
        # remaining constraint violation and leaves m̄_k at round-off.
        res = float(np.max(np.linalg.norm(mbar1[list(req)], axis=1) / req_scale))
        if res > 0:
            anchor_cw = anchor[cwi]
            radius = {k: float(np.linalg.norm(np.asarray(p)[i] - anchor_cw[i])) for i, k in enumerate(cw)}
            if all(r > 0 for r in radius.values()):
                out, rep_cf = static_balance(system, bodies=req, radius=radius, n_samples=0)
                mu, p = jnp.asarray(rep_cf.counterweight_mass), jnp.asarray(rep_cf.counterweight_position)
                mbar1 = rep_cf.static_moment_after
                polished = True
    req_idx = np.asarray(req, dtype=np.int64)
    # the closed form (counterweights mirroring each link) on the same bodies, for comparison
    cf_mass = float("nan")
    if set(cw) == set(req):
        try:
            cf_mass = static_balance(system, bodies=req)[1].added_mass
        except ValueError:
            pass
    if ext is None:
        added = float(jnp.sum(mu))
    res_final = float(np.max(np.linalg.norm(mbar1[req_idx], axis=1)) / scale)
    if exact and res_final > 1e-8:
        warnings.warn(
            f"balance: the required static moments did not vanish (residual |m̄| {res_final:.2e} relative)"
            + ("; a counterweight on a link extension cancels only the static moment along its direction: "
               "give extensions={'direction': ...} or use free positions" if ext is not None else
               "; widen the bounds or raise steps/outer"),
            RuntimeWarning, stacklevel=2,
        )
    report = BalanceReport(
        bodies=req,
        counterweight_bodies=cw,
        counterweight_mass=np.asarray(mu, dtype=np.float64),
        counterweight_position=np.asarray(p, dtype=np.float64),
        added_mass=added,
        added_inertia=float(np.sum(np.asarray(inertia_measure(out))) - np.sum(J)),
        static_moment_before=mbar0,
        static_moment_after=mbar1,
        residual_static_moment=res_final,
        coupling_before=coupling(system, n_samples=n_samples, seed=seed),
        residual_coupling=coupling(out, n_samples=n_samples, seed=seed),
        iterations=it,
        wall_time=time.perf_counter() - start,
        history=np.asarray(history),
        closed_form_added_mass=cf_mass,
        polished=polished,
        extension_length=None if e is None else np.asarray(e, dtype=np.float64),
    )
    return out, report


def _polish_extensions(problem, e, mlo, mhi):
    """Closed-form counterweight masses at fixed extension lengths ``e`` (leaves first):
    ``μ_k = -(m̄_k · d_k) / e_k`` with the rods and the descendants' counterweights already
    folded in. ``None`` when a length is zero or a mass leaves its bounds."""
    if np.any(e <= 0):
        return None
    dtype = problem.system.body_mass.dtype
    cw = problem.cw
    d = np.asarray(problem.direction)
    anchor = np.asarray(problem.anchor)
    zeros = jnp.zeros(len(cw), dtype)
    cur = fold_with_extensions(problem.system, cw, zeros, problem.anchor, jnp.asarray(e, dtype), problem.anchor,
                                problem.direction, problem.density, 0.0)  # the rods alone
    mu = np.zeros(len(cw))
    for i in sorted(range(len(cw)), key=lambda i: cw[i], reverse=True):
        mb = np.asarray(static_moments(cur), dtype=np.float64)[cw[i]]
        mu[i] = -float(mb @ d[i]) / e[i]
        if not (mlo[i] - 1e-12 * (1.0 + mhi[i]) <= mu[i] <= mhi[i]):
            return None
        mu[i] = max(mu[i], 0.0)
        cur = fold_point_masses(cur, (cw[i],), jnp.asarray([mu[i]], dtype), jnp.asarray((anchor[i] + e[i] * d[i])[None], dtype),
                    jnp.zeros((1,) if is_planar(cur) else (1, 3, 3), dtype))
    if problem.gyration:
        cur = fold_with_extensions(problem.system, cw, jnp.asarray(mu, dtype), problem.anchor
                                    + jnp.asarray(e, dtype)[:, None] * problem.direction, jnp.asarray(e, dtype),
                                    problem.anchor, problem.direction, problem.density, problem.gyration)
    return mu, cur


def tradeoff_curve(system, coupling_weights: Sequence[float], **kwargs):
    """Added mass against residual coupling: :func:`balance` with ``exact=False`` for each
    coupling weight. Returns NumPy ``(coupling_weights, added_mass, residual_coupling,
    residual_static_moment)``."""
    w = np.asarray(coupling_weights, dtype=np.float64)
    mass, coup, res = [], [], []
    for wi in w:
        _, rep = balance(system, exact=False, coupling_weight=float(wi), **kwargs)
        mass.append(rep.added_mass)
        coup.append(rep.residual_coupling)
        res.append(rep.residual_static_moment)
    return w, np.asarray(mass), np.asarray(coup), np.asarray(res)
