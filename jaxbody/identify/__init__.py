"""Parameter identification: inverse-dynamics regressor, base parameters, least squares,
trajectory fitting through the integrator.

One module per job: :mod:`~jaxbody.identify.inertial` (the parameter vector),
:mod:`~jaxbody.identify.regression` (the regressor), :mod:`~jaxbody.identify.base` (base parameters),
:mod:`~jaxbody.identify.estimation` (least squares), :mod:`~jaxbody.identify.measurements` (excitation and
states from measured positions), :mod:`~jaxbody.identify.consistency` (pseudo-inertia,
log-Cholesky), :mod:`~jaxbody.identify.parameterisation` and
:mod:`~jaxbody.identify.trajectory` (fitting through the integrator); their public names are
re-exported here.

Inertial parameters
-------------------
Each body ``k`` carries ten inertial parameters, in the order and frame of Pinocchio's
``Inertia.toDynamicParameters``::

    π_k = (m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz)

with ``m`` the body mass, ``c`` the centre of mass in the body frame and ``I`` the inertia
tensor **about the body-frame origin**, in body axes (``I = I_C + m (|c|² E − c cᵀ)``).
The joint forces are linear in these parameters: ``inverse_dynamics(q, v, a) = Y(q, v, a) π``.
:func:`regressor` obtains ``Y`` as the Jacobian of inverse dynamics with respect to ``π``
(automatic differentiation of the engine; no per-robot formulas). Because the map is linear,
the Jacobian is taken at a fixed reference ``π`` (unit masses, zero first moments, identity
inertias), which keeps it exact for bodies whose true mass is zero.

Identifiable (base) parameters
------------------------------
Not every ``π`` is identifiable from joint forces: a body fixed to the ground never moves,
a column may be a combination of others (a hinge about ``z`` only sees ``I_zz`` of its
body plus the masses it carries times squared distances, ...). :func:`base_parameters`
stacks the regressor at random states and performs a rank-revealing (column-pivoted) QR
decomposition: the ``r`` independent columns ``W₁`` and the rest ``W₂ = W₁ K`` give the
**base parameters** ``β = π₁ + K π₂`` with ``Y π = Y₁ β``. The groups are exactly the
augmented-body quantities of the engine: the static moment ``m̄_k`` of an augmented body
(body ``k`` plus the subtree masses of its children placed at their joints) and the inertia
of the augmented body about its joint, less their components along the joint axes;
:meth:`BaseParameters.augmented_identifiability` reports which of them are identifiable.

Least squares
-------------
:func:`least_squares` solves ``W₁ β = τ`` from many states with per-joint weights (the
inverse noise standard deviations, estimated from the residuals of an ordinary fit when not
given) and returns the standard errors from ``σ² (W̃ᵀW̃)⁻¹``.

Trajectory fitting
------------------
:func:`fit_trajectory` minimises the mismatch between a simulated (:func:`jaxbody.simulate`,
diffrax underneath) and a measured trajectory over any parameters of any system, with optax
(Adam, or L-BFGS with a zoom line search) or Levenberg–Marquardt (Gauss–Newton on the residuals,
Jacobian by forward-mode differentiation through the integrator), optionally by multiple
shooting, which keeps long or chaotic horizons well posed. Physical
consistency comes from the parameterisation: :class:`Parameterisation` maps unconstrained
variables to fields (``log`` for positive quantities), and :func:`log_cholesky` /
:func:`from_log_cholesky` map the ten inertial parameters of a body to and from the
log-Cholesky factor of its 4×4 pseudo-inertia ``J = [[Σ, h], [hᵀ, m]]`` (``Σ = ½ tr(I) E − I``),
which is positive definite exactly for physically consistent bodies (positive mass, inertia
satisfying the triangle inequality about the centre of mass).
"""

from .inertial import (
    PARAMETER_NAMES as PARAMETER_NAMES,
    EXTRA_COLUMNS as EXTRA_COLUMNS,
    SYMMETRIC_INDEX as SYMMETRIC_INDEX,
    body_parameters as body_parameters,
    parameters as parameters,
    parameter_names as parameter_names,
    with_parameters as with_parameters,
)
from ..sampling import random_states as random_states  # kept here: identification's examples sample with it
from .regression import regressor as regressor
from .base import (
    BaseParameters as BaseParameters,
    base_parameters as base_parameters,
)
from .estimation import (
    LeastSquaresFit as LeastSquaresFit,
    least_squares as least_squares,
)
from .measurements import (
    excitation_trajectory as excitation_trajectory,
    MeasuredStates as MeasuredStates,
    states_from_positions as states_from_positions,
)
from .consistency import (
    pseudo_inertia as pseudo_inertia,
    log_cholesky as log_cholesky,
    from_log_cholesky as from_log_cholesky,
)
from .parameterisation import (
    Parameterisation as Parameterisation,
    InertialParameterisation as InertialParameterisation,
)
from .trajectory import (
    FitResult as FitResult,
    fit_trajectory as fit_trajectory,
)

__all__ = [
    "PARAMETER_NAMES",
    "EXTRA_COLUMNS",
    "body_parameters",
    "parameters",
    "parameter_names",
    "with_parameters",
    "regressor",
    "random_states",
    "BaseParameters",
    "base_parameters",
    "LeastSquaresFit",
    "least_squares",
    "excitation_trajectory",
    "MeasuredStates",
    "states_from_positions",
    "pseudo_inertia",
    "log_cholesky",
    "from_log_cholesky",
    "Parameterisation",
    "InertialParameterisation",
    "FitResult",
    "fit_trajectory",
    "SYMMETRIC_INDEX",
]
