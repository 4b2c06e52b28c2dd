"""Maggi's equations in quasi-coordinates: constraints, reduced dynamics and reactions.

Joints are the first layer of Maggi's method: a tree's joint velocities ``v`` already
parametrise the admissible motions of its bodies. This module is the second layer: extra
constraints of first order in the quasi-velocities ``x`` of a *base system*,

    f*(t, q, x) = 0,    f* ∈ R^s                                   (docs/maggi.md, eq. M.6)

linear ones ``C(t, q)·x + c(t, q) = 0`` (holonomic constraints in velocity form,
rolling, skating, loop closures) and nonlinear ones (their Jacobians come from automatic
differentiation). The unconstrained motion obeys ``𝓔 = 0``, where the *bracket*

    𝓔(t, q, x, ẋ) = D(q)·ẋ + h(t, q, x)                            (M.4)

is the left-hand side of the equations of motion in quasi-velocities (``D`` the kinetic
metric ``∂²T*/∂x∂x``, ``h`` the velocity, gravity and applied terms). With extended
characteristics ``ε̃ = (ε, f*)`` solvable for ``x`` (M.8), ``[A | K] = ∂x/∂ε̃`` and

    Aᵀ·𝓔 = 0          (Maggi's equations in quasi-coordinates, M.10)
    Λ = Kᵀ·𝓔          (constraint reactions, M.12)

The constrained accelerations follow from ``Aᵀ𝓔 = 0`` and the differentiated constraints
``G·ẋ = −γ`` (``G = ∂f*/∂x``, ``γ = ∂f*/∂q·q̇ + ∂f*/∂t``): writing ``ẋ = A·α − K·γ`` gives the
symmetric positive-definite reduced system ``(AᵀDA)·α = −Aᵀ(h − D·K·γ)`` (M.11), solved
with :func:`jaxbody.linalg.solve_spd` (no LAPACK, safe under ``vmap``).

``[A | K]`` is the inverse of ``∂ε̃/∂x = [E; G]`` (``E = ∂ε/∂x``), computed by Gauss–Jordan
elimination with partial pivoting written in plain array operations (:func:`solve_general`).
``ε`` is either given by the user (a function of ``(base, t, q, x)``) or chosen by
*coordinate partitioning*: a column-pivoted QR of ``G`` at a reference state picks the
``s`` best-conditioned dependent quasi-velocities; the others are ``ε``. The choice only
fixes what ``ε`` means: ``ẋ`` and ``Λ`` do not depend on it (docs/maggi.md §4). The pivot
ratio of the elimination is returned as a conditioning measure. Along a solve the partition
is kept while well conditioned and re-chosen when it degrades: :class:`PartitionSolver`
compares its quality ``det[E; G]/sqrt(det GGᵀ)`` (M.9a) after every step with that of the
partition pivoted QR would choose there (the choice is written in array operations, so it
runs inside ``jit``/``vmap``), and ``jb.simulate`` uses it (phases included);
``repartition=False`` stops the solve with ``partition_degraded`` instead.
:meth:`ConstrainedSystem.repartition` re-chooses the partition by hand
(``jb.simulate(jb.Phases(...))`` does so at every switch).

Errors follow the project's three layers: shape and static misuse raise ``ValueError``
while building; redundant or inconsistent constraints are detected at the reference state
by :func:`check_constraints` (``ValueError`` naming the rows); inside ``jit``, a singular
parametrisation or reduced mass matrix is a :class:`MaggiResult` code, so a batch survives
a bad member.

Drift: holonomic constraints enter in velocity form, so their positions drift. The vector
field applies Baumgarte stabilisation ``φ̈ + 2ω·φ̇ + ω²·φ = 0`` (holonomic rows) and
``ḟ* + 2ω·f* = 0`` (non-holonomic rows) with one rate ``ω`` (``baumgarte``, default
``10 s⁻¹``: residuals decay critically damped with time constant ``1/ω``; ``0`` switches it
off). It leaves exact solutions unchanged. :func:`project_positions` (Newton, minimum-norm
steps) and :func:`project_velocities` (kinetic-metric projection) put a state back on the
manifold; :func:`constraint_residuals` reports both residuals along a solution.

Switching kinematic structure: :func:`switch_constraints` projects the velocities onto the
manifold of a new constraint set, ``x⁺ = A(AᵀDA)⁻¹AᵀD·x⁻`` (impulsive constraint), and
reports the impulse and the kinetic energy lost; ``jb.simulate(jb.Phases(...))`` integrates a
sequence of constraint sets with switches triggered by events (diffrax events).

Layout: :mod:`.systems` (base systems, result codes), :mod:`.constraint` (the constraint
protocol), :mod:`.constrained` (:class:`ConstrainedSystem`: parametrisation, reduced dynamics,
partition), :mod:`.projections` (building, checks, projections onto the manifold),
:mod:`.reactions` (outputs along a solution), :mod:`.switching` (impulsive switches). The
diffrax solver that re-partitions during a solve belongs to the simulation layer
(:mod:`jaxbody.simulation.partitioning`).
"""

from ..linalg import solve_general
from .constrained import ConstrainedSystem, MaggiSolution
from .constraint import Constraint, VelocityConstraint
from .projections import check_constraints, constrain, initial_state, project_positions, project_velocities
from .reactions import constraint_residuals, reactions
from .switching import SwitchReport, switch_constraints
from .systems import SINGULAR_PIVOT as SINGULAR_PIVOT, MaggiResult, ModelBase, QuasiVelocitySystem

__all__ = [
    "MaggiResult",
    "QuasiVelocitySystem",
    "ModelBase",
    "Constraint",
    "VelocityConstraint",
    "ConstrainedSystem",
    "MaggiSolution",
    "constrain",
    "check_constraints",
    "solve_general",
    "initial_state",
    "project_velocities",
    "project_positions",
    "switch_constraints",
    "SwitchReport",
    "reactions",
    "constraint_residuals",
]
