"""Balancing synthesis of dynamically decoupled mechanisms, and decoupling measures.

Why static moments decide coupling
----------------------------------
In absolute angles (the angle of each body measured from a fixed direction, not from its
parent), the mass matrix of a planar tree has the augmented moments of inertia ``J_k`` on
its diagonal and, for every body ``k`` and every carrier ``i`` of ``k`` (a body on its path to
the ground), the off-diagonal entry ``R · m̄_k``: the link vector from the joint of ``i``
towards ``k`` dotted with the static moment ``m̄_k`` of the augmented body ``k`` (body ``k``
plus the whole mass of every subtree it carries, lumped at the joints of its children).
Velocity products carry the same coefficients. Hence:

* on a **fixed** base the bodies are dynamically decoupled for all configurations iff
  ``m̄_k = 0`` for every body that has a carrier; a body hinged to the ground may keep its
  static moment (it only feels its own weight);
* on a **translating** base the base row couples with every body through ``m̄_k``, so all
  static moments must vanish;
* in space, with ball joints, the off-diagonal blocks ``−[m̄_k]×[R]×`` vanish iff
  ``m̄_k = 0`` likewise.

With the static moments zero, the equations separate into ``J_k α̈_k = M_k − Σ_{children j} M_j``:
a torque in one joint turns only the two bodies it connects, and a torque at the root joint
turns the root body alone, the others keeping their absolute orientation.

:func:`balance` adds a point counterweight to chosen bodies (mass and position within
bounds, through a bounded ``(1 + sin z)/2`` parameterisation) and drives the required ``m̄_k``
to zero with optax (an augmented Lagrangian with L-BFGS inner solves for exact decoupling,
or a quadratic penalty for a trade-off), while penalising added mass and added inertia.
Optionally (``extensions=``) each link is extended beyond its joint by a rod of bounded
length with the counterweight at its end: the extension length replaces the free position
as design variable, and the rod's own mass and inertia count as added.
:func:`static_balance` is the closed-form answer: leaves first, a counterweight opposite
each static moment at a given distance. Both return the balanced system with the
counterweights folded into the bodies' mass, centre of mass and inertia, so every function
of jaxbody works on it.
"""

import time
from collections.abc import Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from . import identify as _identify
from . import planar as _planar
from .augmented import static_moment
from .model import Model
from .planar import PlanarSystem, mass_matrix
from .planar.system import ParamLike

__all__ = [
    "decoupling_report",
    "DecouplingReport",
    "static_moments",
    "required_bodies",
    "fold_counterweights",
    "coupling",
    "BalanceReport",
    "balance",
    "static_balance",
    "tradeoff_curve",
    "resolve_bodies",
]

class DecouplingReport(NamedTuple):
    """Result of :func:`decoupling_report` (spec §10, corrected Cor. 8).

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
    """Dynamic decoupling check of Cor. 8 as corrected in spec §10 (concrete values, not traced).

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


# ------------------------------------------------------------------------- adapters
def _is_planar(system) -> bool:
    return isinstance(system, _planar.PlanarSystem)


def _check_system(system):
    if not (_is_planar(system) or isinstance(system, Model)):
        raise TypeError(
            f"balancing needs a planar system (jaxbody.planar) or a jaxbody.Model, got {type(system).__name__}"
        )


def _dim(system) -> int:
    return 2 if _is_planar(system) else 3


def _moving(model: Model) -> np.ndarray:
    joints = np.asarray(model.joints.body_joint_count) > 0
    carriers = model.tree.carrier_mask  # [i, k]: i carries k
    return joints | (carriers & joints[:, None]).any(axis=0)


def _anchor(model: Model) -> np.ndarray:
    """Base point of each body in its own frame: the anchor of its first joint (else origin)."""
    first = np.asarray(model.joints.body_first_joint)
    jp = np.asarray(model.joint_pos)
    return np.where((first >= 0)[:, None], jp[np.maximum(first, 0)], 0.0)


def static_moments(system, q=None):
    """Static moments ``m̄_k`` of the augmented bodies in body axes, about each base point.

    Planar systems: configuration independent (:func:`jaxbody.planar.augmented_bodies`),
    ``(n, 2)``. Models: from :func:`jaxbody.augmented_bodies` at ``q`` (default ``qpos0``)
    rotated into body axes, ``(n, 3)`` (configuration independent for hinge and ball trees).
    """
    _check_system(system)
    return _static_moments(system, q)


@eqx.filter_jit
def _static_moments(system, q=None):
    """Static moments ``m̄_k`` of the augmented bodies in body axes, about each base point.

    Planar systems: configuration independent (:func:`jaxbody.planar.augmented_bodies`),
    ``(n, 2)``. Models: from :func:`jaxbody.augmented_bodies` at ``q`` (default ``qpos0``)
    rotated into body axes, ``(n, 3)`` (configuration independent for hinge and ball trees).
    """
    _check_system(system)
    if _is_planar(system):
        return _planar.augmented_bodies_in_body_axes(system).static_moment
    from .dynamics import augmented_bodies
    from .kinematics import forward_kinematics

    q = system.qpos0 if q is None else jnp.asarray(q)
    rot = forward_kinematics(system, q).body_rotation
    return jnp.einsum("nji,nj->ni", rot, augmented_bodies(system, q).static_moment)


def _inertia_measure(system):
    """Per body: planar ``J_k``; spatial trace of the augmented inertia (rotation invariant)."""
    if _is_planar(system):
        return _planar.augmented_bodies_in_body_axes(system).augmented_inertia
    from .dynamics import augmented_bodies

    I = augmented_bodies(system, system.qpos0).augmented_inertia
    return jnp.trace(I, axis1=-2, axis2=-1)


def required_bodies(system) -> tuple[int, ...]:
    """Bodies whose ``m̄_k`` must vanish for decoupling (the corrected Cor. 8).

    Planar: every body with a carrier on a fixed base; every body on a translating base.
    Models: every moving body with a moving carrier; every moving body when a root body is
    free-floating.
    """
    _check_system(system)
    if _is_planar(system):
        if system.translating_base:
            return tuple(range(system.n_body))
        return tuple(int(k) for k in np.nonzero(~system.tree.is_root)[0])
    moving = _moving(system)
    carriers = system.tree.carrier_mask
    free_root = any(system.joints.body_is_free[k] for k in range(system.n_body) if system.tree.parent[k] < 0)
    out = []
    for k in range(system.n_body):
        if not moving[k] or system.joints.body_joint_count[k] == 0:
            continue
        if free_root or (carriers[:, k] & moving).any():
            out.append(k)
    return tuple(out)


def fold_counterweights(system, bodies: Sequence[int], mass, position, gyration: float = 0.0):
    """The system with point counterweights folded into the bodies.

    Args:
        system: planar system or :class:`Model`.
        bodies: the bodies that carry a counterweight (static).
        mass: ``(n_cw,)`` counterweight masses.
        position: ``(n_cw, dim)`` positions in the body's frame (planar: body axes from the
            hinge, like ``body_com``; models: body frame, like ``body_com``).
        gyration: radius of gyration of each counterweight about its own centre (``0``: point).

    Returns:
        The system with ``m' = m + μ``, ``c' = (m c + μ p) / m'`` and the inertia about the new
        centre of mass by the parallel-axis theorem (traceable: ``grad`` reaches ``mass`` and
        ``position``).
    """
    _check_system(system)
    idx = tuple(int(b) for b in np.asarray(bodies, dtype=np.int64).reshape(-1))
    mu = jnp.asarray(mass)
    p = jnp.asarray(position)
    if p.shape != (len(idx), _dim(system)) or mu.shape != (len(idx),):
        raise ValueError(
            f"counterweights: mass has shape {mu.shape} and position {p.shape}, expected "
            f"({len(idx)},) and ({len(idx)}, {_dim(system)}) for bodies {idx}"
        )
    g2 = float(gyration) ** 2
    if _is_planar(system):
        extra = mu * g2
    else:  # a homogeneous ball of radius of gyration g: (2/3) g² μ about each axis
        extra = mu[:, None, None] * (2.0 / 3.0 * g2) * jnp.eye(3, dtype=p.dtype)
    return _fold(system, idx, mu, p, extra)


@eqx.filter_jit
def _fold(system, bodies, mass, position, extra):
    """Fold point masses ``mass`` at ``position`` plus their own central inertia ``extra``
    (planar ``(n_cw,)``, spatial ``(n_cw, 3, 3)``) into ``bodies`` (repeats allowed)."""
    idx = np.asarray(bodies, dtype=np.int64)
    mu, p = mass, position
    if _is_planar(system):
        m = system.body_mass
        c = system.body_com
        J = system.body_inertia + m * jnp.sum(c * c, axis=-1)  # about the hinge
        m2 = m.at[idx].add(mu)
        h2 = (m[:, None] * c).at[idx].add(mu[:, None] * p)
        J2 = J.at[idx].add(mu * jnp.sum(p * p, axis=-1) + extra)
        c2 = h2 / m2[:, None]
        I2 = J2 - m2 * jnp.sum(c2 * c2, axis=-1)
        return eqx.tree_at(lambda s: (s.body_mass, s.body_com, s.body_inertia), system, (m2, c2, I2))
    pi = _identify.parameters(system).reshape(system.n_body, 10)
    eye = jnp.eye(3, dtype=p.dtype)
    Ip = mu[:, None, None] * (jnp.sum(p * p, axis=-1)[:, None, None] * eye - p[:, :, None] * p[:, None, :]) + extra
    add = jnp.concatenate(
        [mu[:, None], mu[:, None] * p, jnp.stack([Ip[:, i, j] for i, j in _identify.SYMMETRIC_INDEX], axis=-1)], axis=-1
    )
    pi = pi.at[idx].add(add)
    return _identify.with_parameters(system, pi.reshape(-1))


def _rod(system, direction, length, density):
    """A straight uniform rod from the base point along ``direction`` (unit, ``(n, dim)``):
    mass ``density · length``, centre at ``length/2 · direction``, central inertia
    ``m ℓ²/12`` about the hinge axis (planar) or ``m ℓ²/12 (1 − d dᵀ)`` (spatial)."""
    mass = density * length
    centre = 0.5 * length[:, None] * direction
    i_perp = mass * length**2 / 12.0
    if _is_planar(system):
        return mass, centre, i_perp
    eye = jnp.eye(3, dtype=direction.dtype)
    return mass, centre, i_perp[:, None, None] * (eye - direction[:, :, None] * direction[:, None, :])


# ------------------------------------------------------------------------- coupling measure
def _random_configs(system, n, seed):
    rng = np.random.default_rng(seed)
    if _is_planar(system):
        cfg = np.zeros((n, system.nq))
        cfg[:, system.n_base :] = rng.uniform(-np.pi, np.pi, size=(n, system.n_body))
        return cfg
    q, _, _ = _identify.random_states(system, n, seed)
    return q


def _normalised_offdiag(M, blocks):
    """max over i≠j of |M_ij| / sqrt(M_ii M_jj) (blocks: Frobenius norms of blocks)."""
    if blocks == 1:
        d = jnp.sqrt(jnp.abs(jnp.diagonal(M, axis1=-2, axis2=-1)))
        dd = d[..., :, None] * d[..., None, :]
        R = jnp.where(dd > 0, jnp.abs(M) / jnp.where(dd > 0, dd, 1.0), 0.0)
        n = M.shape[-1]
    else:
        n = M.shape[-1] // blocks
        B = M.reshape(M.shape[:-2] + (n, blocks, n, blocks))
        F = jnp.sqrt(jnp.sum(B * B, axis=(-3, -1)))
        d = jnp.sqrt(jnp.diagonal(F, axis1=-2, axis2=-1))
        dd = d[..., :, None] * d[..., None, :]
        R = jnp.where(dd > 0, F / jnp.where(dd > 0, dd, 1.0), 0.0)
    # massless bodies (zero diagonal) neither couple nor count (handled by the where above)
    return jnp.max(jnp.where(jnp.eye(n, dtype=bool), 0.0, R))


def _spatial_D(model: Model, q):
    from . import spatial
    from .dynamics import augmented_bodies
    from .kinematics import forward_kinematics

    kin = forward_kinematics(model, q)
    aug = augmented_bodies(model, q)
    par = np.asarray(model.tree.parent)
    link = kin.base_point - kin.base_point[np.maximum(par, 0)]
    link = jnp.where(jnp.asarray(par >= 0)[:, None], link, 0.0)
    return spatial.absolute_mass_matrix(model.tree, aug.static_moment, aug.augmented_inertia, link)


@jax.jit
def _planar_coupling(system, cfg):
    return _normalised_offdiag(jax.vmap(_planar.mass_matrix, in_axes=(None, 0))(system, cfg), 1)


@eqx.filter_jit
def _spatial_coupling(system, cfg, rows):
    Ds = jax.vmap(_spatial_D, in_axes=(None, 0))(system, cfg)[:, rows][:, :, rows]
    return _normalised_offdiag(Ds, 3)


def coupling(system, configurations=None, n_samples: int = 32, seed: int = 0) -> float:
    """Largest normalised off-diagonal coupling over configurations.

    Planar: ``max |ℳ_ij| / sqrt(ℳ_ii ℳ_jj)`` of the absolute-angle mass matrix
    (:func:`jaxbody.planar.mass_matrix`). Models (fixed base): the same with the Frobenius
    norms of the 3×3 blocks of the absolute block matrix ``D`` in the absolute angular
    velocities (:func:`jaxbody.spatial.absolute_mass_matrix`), over the moving bodies.
    ``0`` means decoupled; ``1`` is the largest possible value.
    """
    _check_system(system)
    cfg = _random_configs(system, n_samples, seed) if configurations is None else np.asarray(configurations)
    cfg = jnp.asarray(cfg, system.body_mass.dtype)
    if _is_planar(system):
        return float(_planar_coupling(system, cfg))
    if any(system.joints.body_is_free):
        raise ValueError("coupling: models with a free-floating body are not supported; use a fixed base")
    keep = np.nonzero(_moving(system))[0]
    rows = (3 * keep[:, None] + np.arange(3)).reshape(-1)
    return float(_spatial_coupling(system, cfg, rows))


# ------------------------------------------------------------------------- synthesis
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


def _body_names(system):
    return system.tree.names


def resolve_bodies(system, bodies, what):
    """Bodies given by index or name, ``"all"`` or ``None`` -> sorted body indices.

    ``None``: :func:`required_bodies`; ``"all"``: every body (planar) or every moving body
    with a joint (models). ``what`` names the argument in the error message.

    Raises:
        ValueError: an unknown name, an index out of range or another string than ``"all"``.
    """
    n = system.n_body
    if bodies is None:
        return required_bodies(system)
    if isinstance(bodies, str):
        if bodies == "all":
            if _is_planar(system):
                return tuple(range(n))
            return tuple(int(k) for k in np.nonzero(_moving(system))[0] if system.joints.body_joint_count[k] > 0)
        raise ValueError(f"{what} must be a list of bodies, 'all' or None, got {bodies!r}")
    out = []
    for b in bodies:
        if isinstance(b, str):
            if b not in _body_names(system):
                raise ValueError(f"{what}: no body named {b!r}; bodies: {list(_body_names(system))}")
            b = _body_names(system).index(b)
        b = int(b)
        if not 0 <= b < n:
            raise ValueError(f"{what}: body index {b} out of range (0..{n - 1})")
        out.append(b)
    return tuple(sorted(set(out)))


def _reach(system) -> tuple[np.ndarray, np.ndarray]:
    """Per body: its base point and the vector from it to the farthest of its CM and its
    children's joints (the link's own reach), ``(n, dim)`` each."""
    n = system.n_body
    if _is_planar(system):
        com = np.asarray(system.body_com)
        hinge = np.asarray(system.hinge_pos)
        anchor = np.zeros((n, 2))
        child_pts = [(k, hinge[j]) for j in range(n) for k in [system.tree.parent[j]] if k >= 0]
    else:
        com = np.asarray(system.body_com)
        anchor = _anchor(system)
        # a child's joint anchor in the parent's frame at the reference configuration
        from ._util import quat_to_matrix

        pos, quat = np.asarray(system.body_pos), np.asarray(system.body_quat)
        child_pts = [(system.tree.parent[j], pos[j] + np.asarray(quat_to_matrix(quat[j])) @ anchor[j])
                     for j in range(n) if system.tree.parent[j] >= 0]
    vec = com - anchor
    for k, pt in child_pts:
        if np.linalg.norm(pt - anchor[k]) > np.linalg.norm(vec[k]):
            vec[k] = pt - anchor[k]
    return anchor, vec


def _scale_length(system) -> np.ndarray:
    """Per body: the farthest of its CM and its children's joints from its own base point."""
    L = np.linalg.norm(_reach(system)[1], axis=1)
    return np.where(L > 0, L, 1.0)


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
    dim = _dim(system)
    _, vec = _reach(system)
    L = _scale_length(system)[c]
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
    dim = _dim(system)
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
    anchor = np.zeros((system.n_body, dim)) if _is_planar(system) else _anchor(system)
    L = _scale_length(system)
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
        return _fold_with_extensions(self.system, self.cw, mu, p, e, self.anchor, self.direction,
                                     self.density, self.gyration)

    def added_mass(self, x):
        mu, _, e = self.decode(x)
        return jnp.sum(mu) if e is None else jnp.sum(mu) + jnp.sum(self.density * e)

    def parts(self, x):
        s = self.folded(x)
        c = (static_moments(s)[np.asarray(self.req, dtype=np.int64)] / self.scale[:, None]).reshape(-1)
        dJ = jnp.sum(_inertia_measure(s)) - self.J0
        f = self.w_mass * self.added_mass(x) / self.m_total + self.w_inertia * dJ / self.J_total
        return f, c


def _fold_with_extensions(system, cw, mu, p, e, anchor, direction, density, gyration):
    """Counterweights at the ends of the extensions, and the extension rods, folded in."""
    rm, rc, ri = _rod(system, direction, e, density)
    g2 = float(gyration) ** 2
    if _is_planar(system):
        extra = jnp.concatenate([mu * g2, ri])
    else:
        extra = jnp.concatenate([mu[:, None, None] * (2.0 / 3.0 * g2) * jnp.eye(3, dtype=p.dtype), ri])
    return _fold(system, tuple(cw) + tuple(cw), jnp.concatenate([mu, rm]),
                 jnp.concatenate([p, anchor + rc]), extra)


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
    _check_system(system)
    start = time.perf_counter()
    req = resolve_bodies(system, bodies, "bodies")
    cw = req if counterweights is None else resolve_bodies(system, counterweights, "counterweights")
    if not req:
        raise ValueError("balance: no body to decouple (nothing has a carrier); pass bodies='all' to balance statically")
    sub = system.tree.subtree_mask  # [k, i]: i in subsystem k
    for k in req:
        if not any(sub[k, c] for c in cw):
            raise ValueError(
                f"balance: body {k} ({_body_names(system)[k]!r}) must be balanced but carries no counterweight "
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
    req_scale = msub[list(req)] * _scale_length(system)[list(req)]
    req_scale = np.where(req_scale > 0, req_scale, scale)
    J = np.asarray(_inertia_measure(system), dtype=np.float64)
    f = lambda a: jnp.asarray(a, dtype)
    anchor = np.zeros((system.n_body, _dim(system))) if _is_planar(system) else _anchor(system)
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
    half = 0.5 * _scale_length(system)[cwi]
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
        lam = jnp.zeros((len(req) * _dim(system),), dtype)
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
        import warnings

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
        added_inertia=float(np.sum(np.asarray(_inertia_measure(out))) - np.sum(J)),
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
    cur = _fold_with_extensions(problem.system, cw, zeros, problem.anchor, jnp.asarray(e, dtype), problem.anchor,
                                problem.direction, problem.density, 0.0)  # the rods alone
    mu = np.zeros(len(cw))
    for i in sorted(range(len(cw)), key=lambda i: cw[i], reverse=True):
        mb = np.asarray(static_moments(cur), dtype=np.float64)[cw[i]]
        mu[i] = -float(mb @ d[i]) / e[i]
        if not (mlo[i] - 1e-12 * (1.0 + mhi[i]) <= mu[i] <= mhi[i]):
            return None
        mu[i] = max(mu[i], 0.0)
        cur = _fold(cur, (cw[i],), jnp.asarray([mu[i]], dtype), jnp.asarray((anchor[i] + e[i] * d[i])[None], dtype),
                    jnp.zeros((1,) if _is_planar(cur) else (1, 3, 3), dtype))
    if problem.gyration:
        cur = _fold_with_extensions(problem.system, cw, jnp.asarray(mu, dtype), problem.anchor
                                    + jnp.asarray(e, dtype)[:, None] * problem.direction, jnp.asarray(e, dtype),
                                    problem.anchor, problem.direction, problem.density, problem.gyration)
    return mu, cur


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
    _check_system(system)
    start = time.perf_counter()
    req = resolve_bodies(system, bodies, "bodies")
    L = _scale_length(system)
    if radius is None:
        rad = {k: float(L[k]) for k in req}
    elif isinstance(radius, dict):
        rad = {int(k): float(v) for k, v in radius.items()}
    else:
        r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (system.n_body,))
        rad = {k: float(r[k]) for k in req}
    anchor = np.zeros((system.n_body, _dim(system))) if _is_planar(system) else _anchor(system)
    mbar0 = np.asarray(static_moments(system), dtype=np.float64)
    J0 = float(np.sum(np.asarray(_inertia_measure(system))))
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
        counterweight_position=positions.reshape(len(req), _dim(system)),
        added_mass=float(np.sum(masses)),
        added_inertia=float(np.sum(np.asarray(_inertia_measure(cur)))) - J0,
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
