"""Constrained systems built and checked, and states put on their constraint manifold.

:func:`constrain` adds constraints to a base system (checked at a reference state by
:func:`check_constraints`, which names redundant or inconsistent rows); :func:`initial_state`
checks or projects an initial state; :func:`project_velocities` (kinetic metric) and
:func:`project_positions` (Newton, minimum-norm steps) put a state back on the manifold.
"""

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jax import lax

from .. import linalg
from .._types import ArrayLike
from .._util import compiled_when_eager
from ..kinematics import integrate_qpos
from ..model import Model
from .constrained import ConstrainedSystem
from .constraint import Constraint
from .systems import SINGULAR_PIVOT, ModelBase

__all__ = ["check_constraints", "constrain", "project_velocities", "project_positions", "initial_state"]


def check_constraints(system: ConstrainedSystem, q, x=None, t=0.0, *, rtol: float = 1e-9) -> None:
    """Build-time check at a reference state: raise ``ValueError`` naming redundant or
    inconsistent constraint rows (rows of ``G`` that depend on earlier rows; inconsistent
    when the affine part of a dependent linear row contradicts the earlier ones)."""
    s, n = system.n_constraint, system.nv
    if s == 0:
        return
    if s > n:
        raise ValueError(f"{s} constraints on {n} quasi-velocities: at least {s - n} are redundant")
    x = jnp.zeros((n,), jnp.asarray(q).dtype) if x is None else jnp.asarray(x)
    G, f = _jacobian_and_residual(system, t, q, x)
    _check_rows(G, f, x, system.constraint_names, rtol)


# G and f* at the reference state from one compiled program: evaluated op by op, every
# differentiated call of the kinematics would compile a program of its own; compiled quickly,
# since it runs about once per system
@compiled_when_eager(quick=True)
def _jacobian_and_residual(system, t, q, x):
    return system.constraint_jacobian(t, q, x), system.constraint_residual(t, q, x)


def _check_rows(G, f, x, names, rtol):
    """The rank test of :func:`check_constraints` on ``G`` and ``f*`` at the reference state."""
    s, n = G.shape
    # a build-time check on the host, once and outside any trace: LAPACK's SVD in float64 is
    # safe here and gives the sharpest rank test
    G = np.asarray(G, dtype=np.float64)
    # affine part at x = 0 for linear constraints: f* = G x + c
    c = np.asarray(f, dtype=np.float64) - G @ np.asarray(x, dtype=np.float64)
    # rank tolerance relative to G's largest entry, so the rows' units do not matter; the
    # floor keeps an all-zero G comparable
    scale = max(np.abs(G).max(), 1e-300)
    kept: list[int] = []
    # rows are added one at a time, so the first row that depends on earlier ones is the one named
    for i in range(s):
        trial = G[kept + [i]]
        sv = np.linalg.svd(trial, compute_uv=False)
        if sv[-1] <= rtol * scale * max(1.0, np.sqrt(n)):
            # row i is a combination of the kept rows: consistent only if c follows the same combination
            coef, *_ = np.linalg.lstsq(G[kept].T, G[i], rcond=None) if kept else (np.zeros(0),)
            mismatch = abs(c[i] - (coef @ c[kept] if kept else 0.0))
            deps = [names[j] for j, a in zip(kept, coef) if abs(a) > 1e-9] if kept else []
            # a dependent row whose affine part follows the same combination repeats a constraint
            # (redundant); otherwise no velocity satisfies both (inconsistent)
            what = "inconsistent" if mismatch > 1e-9 * max(1.0, np.abs(c).max()) else "redundant"
            raise ValueError(
                f"constraints are {what}: row {names[i]!r} depends on "
                f"{deps if deps else 'nothing (it is zero)'} at the reference state; remove it "
                f"(or choose fewer components)"
            )
        kept.append(i)


def constrain(
    base,
    constraints: Sequence = (),
    *,
    q_ref: ArrayLike,
    x_ref: ArrayLike | None = None,
    t_ref: float = 0.0,
    epsilon: Callable | None = None,
    baumgarte: float = 10.0,
    repartition: bool = True,
    partition_tolerance: float = 0.1,
    position_atol: float | None = 1e-6,
) -> ConstrainedSystem:
    """Add constraints to a base system (docs/maggi.md §3–4).

    Args:
        base: base system (a :class:`QuasiVelocitySystem`, :class:`ModelBase`, or a
            :class:`ConstrainedSystem`, whose constraints are kept and extended).
        constraints: constraints to add.
        q_ref, x_ref, t_ref: reference state for the build-time checks and the automatic
            partition (``x_ref`` defaults to zero).
        epsilon: user characteristics ``ε(base, t, q, x)`` returning ``n − s`` values, such
            that ``(ε, f*)`` is solvable for ``x``; ``None``: coordinate partitioning.
        baumgarte: stabilisation rate ``ω`` (1/s) of the constraint residuals.
        repartition: with coordinate partitioning, re-choose the partition during a solve
            when it degrades (``False``: stop the solve with ``partition_degraded`` instead).
        partition_tolerance: in ``(0, 1)``; the partition degrades when its quality falls
            below this fraction of the quality of the best (pivoted-QR) partition at the
            current state (docs/maggi.md §4).
        position_atol: largest admissible position residual ``|φ(t_ref, q_ref)|`` of the holonomic
            rows at the reference state (``None``: not checked, for a reference that is only a
            default configuration, such as a model's ``qpos0``).

    Raises:
        ValueError: ``q_ref`` off the holonomic constraints (naming the rows), redundant or
            inconsistent constraints at the reference state, an
            ``epsilon`` of the wrong size / not completing ``f*`` to an invertible set, or a
            ``partition_tolerance`` outside ``(0, 1)``.
    """
    if isinstance(base, Model):
        base = ModelBase(base)
    # a constrained system has no bracket of its own to serve as a base: its rows join the new
    # ones on the original base, since Maggi's equations need all rows in one G
    if isinstance(base, ConstrainedSystem):
        constraints = tuple(base.constraints) + tuple(constraints)
        base = base.base
    constraints = tuple(constraints)
    for c in constraints:
        if not isinstance(c, Constraint):
            raise ValueError(f"constraints must be jaxbody.maggi.Constraint instances, got {type(c).__name__}")
    q_ref = jnp.asarray(q_ref)
    dtype = q_ref.dtype if jnp.issubdtype(q_ref.dtype, jnp.inexact) else jnp.result_type(float)
    q_ref = q_ref.astype(dtype)
    x_ref = jnp.zeros((base.nv,), dtype) if x_ref is None else jnp.asarray(x_ref, dtype)
    tol = float(partition_tolerance)
    if not 0.0 < tol < 1.0:
        raise ValueError(f"constrain: partition_tolerance must lie in (0, 1), got {partition_tolerance!r}")
    # ``free`` is a placeholder until the partition is chosen below; G and f* do not read it
    system = ConstrainedSystem(
        base=base, constraints=constraints, epsilon=epsilon, free=tuple(range(base.nv)),
        baumgarte=jnp.asarray(baumgarte, dtype), repartitioning=bool(repartition), partition_tolerance=tol,
    )
    if system.n_constraint > base.nv:
        check_constraints(system, q_ref, x_ref, t_ref)  # raises: more rows than velocities
    G, f = _jacobian_and_residual(system, t_ref, q_ref, x_ref) if system.n_constraint else (None, None)
    if G is not None:
        _check_rows(G, f, x_ref, system.constraint_names, 1e-9)
    if position_atol is not None:
        # a reference off the constraints would choose the partition and check the rows at a
        # configuration the mechanism cannot reach
        phi = np.asarray(system.position_residual(t_ref, q_ref))
        off = np.flatnonzero(np.abs(phi) > position_atol)
        if off.size:
            raise ValueError(
                f"constrain: q_ref violates the constraints {[system.constraint_names[i] for i in off]} "
                f"(position residuals {[float(phi[i]) for i in off]}, admissible {position_atol:g}); give a "
                "configuration on them (jaxbody.maggi.project_positions projects one)"
            )
    if epsilon is None and G is not None and system.partitioned:
        # the partition from the same G (column-pivoted QR): no second program to compile
        system = system.with_partition(_free_columns(np.asarray(G, np.float64)))
    elif epsilon is None:
        system = system.repartition(q_ref, x_ref, t_ref)
    else:
        n_eps = int(np.prod(jax.eval_shape(lambda: epsilon(base, t_ref, q_ref, x_ref)).shape))
        if n_eps != base.nv - system.n_constraint:
            raise ValueError(
                f"epsilon must give n - s = {base.nv} - {system.n_constraint} = "
                f"{base.nv - system.n_constraint} characteristics, got {n_eps}"
            )
        _, _, ratio = system.parametrisation(t_ref, q_ref, x_ref)
        if not float(ratio) > SINGULAR_PIVOT:
            raise ValueError(
                "epsilon does not complete the constraints to solvable extended characteristics "
                f"(ε, f*) at the reference state (pivot ratio {float(ratio):.3g})"
            )
    return system


def _free_columns(G) -> tuple[int, ...]:
    """The free quasi-velocities of the coordinate partition at ``G`` (s, n): the columns a
    column-pivoted QR (Businger–Golub, LAPACK ``geqp3``) does not take as pivots, ascending
    (the choice :func:`jaxbody.maggi.constrained.pivoted_free` makes inside a solve)."""
    s, n = G.shape
    pivots = scipy.linalg.qr(G, pivoting=True, mode="r")[1]
    return tuple(sorted(int(i) for i in pivots[s:]))


def project_velocities(system: ConstrainedSystem, q, x, t=0.0, *, iterations: int = 3):
    """Kinetic-metric projection of ``x`` onto ``f*(t, q, ·) = 0``.

    ``x⁺ = x − D⁻¹Gᵀ(GD⁻¹Gᵀ)⁻¹ f*`` (the closest admissible velocity in kinetic energy;
    exact in one step for linear constraints, Newton iterations for nonlinear ones).

    Returns:
        ``x⁺``.
    """
    if system.n_constraint == 0:
        return jnp.asarray(x)
    # D depends on q only, so it is formed once; each step is the smallest correction in
    # kinetic energy, x − D⁻¹Gᵀ(GD⁻¹Gᵀ)⁻¹f*
    D = system.kinetic_metric(t, q, x)

    def step(_, xx):
        G = system.constraint_jacobian(t, q, xx)
        f = system.constraint_residual(t, q, xx)
        DiGt = linalg.solve_spd(D, G.T)
        lam = linalg.solve_spd(G @ DiGt, f)
        return xx - DiGt @ lam

    # a fixed iteration count, not a convergence test: it traces once, batches and
    # differentiates; for affine rows one step is exact
    return lax.fori_loop(0, 1 if all(c.linear for c in system.constraints) else iterations, step, jnp.asarray(x))


def project_positions(system: ConstrainedSystem, q, t=0.0, *, iterations: int = 8):
    """Newton's method with minimum-norm steps on the holonomic residuals ``φ(t, q) = 0``.

    On a :class:`ModelBase` the steps are taken in the joint velocities and integrated on the
    rotation group, so ball and free joints keep unit quaternions:
    ``Δv = −Gᵀ(GGᵀ)⁻¹φ``, ``q ← integrate_qpos(q, Δv, 1)`` (``G = ∂f*/∂v = ∂φ/∂q · ∂q̇/∂v``
    over the holonomic rows, since ``f* = dφ/dt``). On other bases the coordinates must be plain
    (no quaternions): ``q ← q − Jᵀ(JJᵀ)⁻¹φ``, ``J = ∂φ/∂q``. Returns the projected ``q``."""
    rows = [i for i, ok in enumerate(_holonomic_mask(system)) if ok]
    q = jnp.asarray(q)
    if not rows:
        return q
    # only holonomic rows have a φ; with independent rows J has full row rank and JJᵀ is
    # positive definite, as the Cholesky solve needs
    idx = jnp.asarray(rows, dtype=jnp.int32)
    phi = lambda qq: system.position_residual(t, qq)[idx]

    if isinstance(system.base, ModelBase):
        model = system.base.model
        zero = jnp.zeros((system.nv,), q.dtype)

        def step(_, qq):
            G = system.constraint_jacobian(t, qq, zero)[idx]
            return integrate_qpos(model, qq, -G.T @ linalg.solve_spd(G @ G.T, phi(qq)), 1.0)

        return lax.fori_loop(0, iterations, step, q)

    # Newton iterations with minimum-norm steps (optimistix's Newton needs a square
    # system; its least-squares solvers call LAPACK, which is unsafe in CPU batches).
    def plain_step(_, qq):
        J = jax.jacfwd(phi)(qq)
        return qq - J.T @ linalg.solve_spd(J @ J.T, phi(qq))

    return lax.fori_loop(0, iterations, plain_step, q)


def _holonomic_mask(system: ConstrainedSystem) -> list[bool]:
    mask = []
    # whether a row is holonomic is structural (position() gives None or not), so one probe
    # state answers it in Python
    q = jnp.zeros((system.nq,))
    for c in system.constraints:
        try:
            p = c.position(system.base, 0.0, q)
        except Exception:  # noqa: BLE001 - a position function may not accept a probe state
            p = None
        mask += [p is not None] * c.size
    return mask


def initial_state(system: ConstrainedSystem, q, x, t=0.0, *, project_initial: bool = False, atol: float = 1e-9,
                  position_atol: float = 1e-8, check_positions: bool = False):
    """Check (or project) an initial state against the constraints.

    Args:
        system: constrained system.
        q, x: initial coordinates and quasi-velocities.
        project_initial: project ``q`` on the holonomic constraints (:func:`project_positions`)
            and then ``x`` on all of them (kinetic metric, :func:`project_velocities`) instead of
            raising; the velocity correction is returned.
        atol: admissible velocity residual ``max |f*|`` (scaled by ``max(1, |x|)``).
        position_atol: admissible position residual ``max |φ|`` of the holonomic rows (scaled
            by ``max(1, |q|)``).
        check_positions: raise when ``q`` violates the holonomic constraints and
            ``project_initial`` is off (by default only the velocities are checked here;
            :func:`jaxbody.simulate` checks positions itself).

    Returns:
        ``(q, x, correction)`` with ``correction = x_projected − x`` (zeros when not projected).

    Raises:
        ValueError: the initial quasi-velocities (or, with ``check_positions``, coordinates)
            violate the constraints, naming the rows.
    """
    q = jnp.asarray(q)
    x = jnp.asarray(x, q.dtype)
    names = system.constraint_names
    hol = np.asarray(_holonomic_mask(system), bool)
    if hol.any():
        phi = np.where(hol, np.asarray(system.position_residual(t, q)), 0.0)
        pscale = max(1.0, float(np.max(np.abs(np.asarray(q))))) if q.size else 1.0
        off = np.flatnonzero(np.abs(phi) > position_atol * pscale)
        if off.size and check_positions and not project_initial:
            raise ValueError(
                f"initial positions violate the constraints {[names[i] for i in off]} (residuals "
                f"{[float(phi[i]) for i in off]}); give coordinates that satisfy them or pass "
                "project_initial=True"
            )
        if off.size and project_initial:
            q = project_positions(system, q, t)
    f = np.asarray(system.constraint_residual(t, q, x))
    # tolerance relative to the speed (floored at 1), so fast and slow states are judged alike
    scale = max(1.0, float(np.max(np.abs(np.asarray(x)))) if x.size else 1.0)
    bad = [names[i] for i in np.flatnonzero(np.abs(f) > atol * scale)]
    if not bad:
        return q, x, jnp.zeros_like(x)
    if not project_initial:
        raise ValueError(
            f"initial velocities violate the constraints {bad} (residuals "
            f"{[float(v) for v in f[np.abs(f) > atol * scale]]}); give admissible rates or "
            "pass project_initial=True"
        )
    xp = project_velocities(system, q, x, t)
    return q, xp, xp - x
