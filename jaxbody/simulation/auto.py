"""``solver="auto"``: the solver and tolerances :func:`jaxbody.simulate` picks from the scene and
the accuracy asked, and the dtype-dependent default tolerances.

The rules follow the work-precision study of ``benchmarks/work_precision.py`` (its tables are in
``docs/accuracy.md``), where each solver's wall time to reach a given error of the final state
was measured on a chaotic double pendulum, a robot arm under a torque profile, the rolling
disk, a four-bar linkage and a chain with joint stiffnesses spanning six decades:

* non-stiff scenes, tolerances down to about 1e-9: Tsit5 reaches a given error in the least
  time; tighter than that, Dopri8 (its eighth order takes several times fewer steps), which auto
  takes when the accuracy is asked as ``target_error`` (given tolerances keep Tsit5);
* stiffness: the joint springs ``K`` and dampers ``C`` against the mass matrix ``M`` at the
  initial state give the fastest mode ``ω² = max eig(M⁻¹K)`` and its damping ratio
  ``ζ = φᵀCφ / 2ω`` (``φ`` the ``M``-normalised mode). An explicit solver's steps are bounded by
  ``ω`` over the whole run; an implicit one (Kvaerno5) may take long steps only once the fast
  mode has decayed, so it is chosen when the fast mode is well damped (``ζ ≥ 0.5``) and the run
  spans many of its periods. A lightly damped fast mode must be resolved by any solver and
  Newton's iterations on it make the implicit solver slower (or fail): an explicit one is kept;
* float32: tolerances not below :data:`FLOAT32_TOLERANCE` (below it the error estimate is
  rounding noise and the step size collapses);
* a ``target_error`` (largest error of the final state the user accepts) becomes tolerances
  through :data:`ERROR_PER_TOLERANCE`, the ratio of the measured final-state error to the
  tolerance on the study's non-chaotic scenes (a chaotic scene amplifies errors beyond any such
  ratio: ``docs/accuracy.md`` shows by how much).
"""

import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._util import is_concrete
from ..backends import scalar
from ..effects import JointDampers, JointSprings
from ..kernels import spring_dofs
from ..model import Model

__all__ = [
    "AutoChoice",
    "FLOAT32_TOLERANCE",
    "FLOAT64_TOLERANCE",
    "ERROR_PER_TOLERANCE",
    "default_tolerance",
    "warn_below_resolution",
    "stiffness_estimate",
    "choose_auto",
]

#: Default ``rtol = atol`` of float64 solves.
FLOAT64_TOLERANCE = 1e-8
#: Default ``rtol = atol`` of float32 solves: about a hundred times float32's resolution
#: (``eps ≈ 1.2e-7``); the study's float32 table shows the step count exploding below 1e-6.
FLOAT32_TOLERANCE = 1e-5
#: Below ``RESOLUTION_FACTOR × eps`` of the dtype a tolerance asks for more than rounding allows.
RESOLUTION_FACTOR = 10.0
#: Tolerance at or below which Dopri8 beats Tsit5 in wall time on the study's scenes.
HIGH_ORDER_BELOW = 1e-9
#: Final-state error per unit tolerance (``rtol = atol``) measured by the study, per solver, on its
#: non-chaotic scenes (the four-bar and the rolling disk: 20 to 140 for Tsit5). A chaotic scene
#: amplifies local errors far more (about 1e4 on the double pendulum over 10 s): no tolerance
#: mapping can foresee that, the reason says so.
ERROR_PER_TOLERANCE = {"tsit5": 100.0, "dopri8": 10.0}
#: Implicit solver when the fastest mode is damped at least this much (damping ratio) ...
IMPLICIT_MIN_DAMPING_RATIO = 0.5
#: ... and the run spans at least this many of its time constants ``1/ω``.
IMPLICIT_MIN_SPAN = 1e3


class AutoChoice(eqx.Module):
    """What ``solver="auto"`` chose: the preset, its tolerances and the reason in words."""

    solver: str = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    reason: str = eqx.field(static=True)


def default_tolerance(dtype) -> float:
    """Default ``rtol = atol`` for solves in ``dtype``: :data:`FLOAT64_TOLERANCE` in float64,
    :data:`FLOAT32_TOLERANCE` in float32 (and lower precisions)."""
    return FLOAT64_TOLERANCE if jnp.finfo(dtype).bits >= 64 else FLOAT32_TOLERANCE


def warn_below_resolution(dtype, rtol, atol) -> None:
    """Warn when a concrete ``rtol`` or ``atol`` is below ``RESOLUTION_FACTOR`` times the
    resolution of ``dtype``: the error estimate is then dominated by rounding and the step
    size control takes very many steps for no accuracy."""
    eps = float(jnp.finfo(dtype).eps)
    for name, tol in (("rtol", rtol), ("atol", atol)):
        if tol is None or not is_concrete(tol):
            continue
        tol = float(np.min(np.asarray(tol)))
        if tol == 0.0:
            continue  # a purely relative (atol = 0) or absolute (rtol = 0) control, asked for on purpose
        if tol < RESOLUTION_FACTOR * eps:
            warnings.warn(
                f"simulate: {name}={tol:g} is below {RESOLUTION_FACTOR:g} x the resolution of {jnp.dtype(dtype).name} "
                f"(eps = {eps:.2g}): the error estimate is rounding noise there and the solve takes many steps for "
                f"no accuracy; use {name} >= {default_tolerance(dtype):g} in {jnp.dtype(dtype).name} or float64 states",
                stacklevel=4,
            )


@eqx.filter_jit
def _kinetic_energies(scene, q, velocities):
    # forward evaluations only: no derivative of the dynamics is traced or compiled, which keeps
    # the first call of a solve short (a Hessian through the kernels costs seconds to trace)
    return jax.vmap(lambda v: scene.kinetic_energy(q, v))(velocities)


def _tree_mass_matrix(model, q) -> np.ndarray:
    """``M(q)`` of a tree in its joint coordinates by the composite-rigid-body algorithm of the
    generated kernels (:func:`jaxbody.backends.scalar.bias_and_mass`) run on host numbers in
    float64: about a millisecond for a 7-DoF arm, with no program traced, compiled or built, so
    that the solve's own programs can start building as soon as the choice is made."""
    host = jax.tree.map(lambda x: np.asarray(x, np.float64) if np.issubdtype(np.asarray(x).dtype, np.floating)
                        else np.asarray(x), model)
    M, _, _ = scalar.bias_and_mass(host, [float(x) for x in np.asarray(q, np.float64)], [0.0] * model.nv,
                                   (0.0, 0.0, 0.0), None, want_bias=False)
    out = np.zeros((model.nv, model.nv))
    for (i, j), value in M.items():
        out[i, j] = out[j, i] = float(value)
    return out


def _mass_matrix(scene, q) -> np.ndarray:
    """The mass matrix in the scene's own coordinates (spatial, planar or embedded), whatever path
    computes the dynamics, by polarisation of the kinetic energy ``T(v) = ½ vᵀMv``:
    ``M_ii = 2 T(e_i)`` and ``M_ij = T(e_i + e_j) − T(e_i) − T(e_j)`` (exact for a quadratic form
    up to rounding, ample for an estimate of the fastest mode). A tree in its joint coordinates
    has its own on the host (:func:`_tree_mass_matrix`), and so has a spatial scene of a tree
    whatever its effects and constraints (its kinetic energy is the tree's; loops and other
    constraints restrict the velocities, not the metric)."""
    nv = scene.nv
    model = scene.system if scene.path == "spatial" else None
    # concrete parameters of one model (not traced, not a batch of models)
    if isinstance(model, Model) and model.nv == nv and is_concrete(model) and np.ndim(model.body_mass) == 1:
        return _tree_mass_matrix(model, q)
    i, j = np.triu_indices(nv, k=1)
    eye = np.eye(nv)
    velocities = np.concatenate([eye, eye[i] + eye[j]]).astype(np.asarray(q).dtype)
    energies = np.asarray(_kinetic_energies(scene, q, jnp.asarray(velocities)), float)
    single, pairs = energies[:nv], energies[nv:]
    M = np.diag(2.0 * single)
    M[i, j] = M[j, i] = pairs - single[i] - single[j]
    return M


def stiffness_estimate(scene, q) -> dict | None:
    """The fastest mode of the linearised joint springs and dampers at ``q``.

    ``K`` (joint stiffness on each DoF) and ``C`` (joint damping) against the mass matrix ``M``:
    ``ω_i² = eig(K, M)``, damping ratios ``ζ_i = φ_iᵀCφ_i / 2ω_i`` (``φ_i`` ``M``-normalised);
    for dampers without springs the fastest decay rate ``max eig(C, M)``. Returns ``{"omega":
    largest ω (rad/s), "zeta": its damping ratio, "decay": fastest decay rate of the dampers
    alone (1/s), "omega_min": smallest nonzero ω}`` or ``None`` when the scene has neither
    springs nor dampers (or its values are traced). A traced ``q`` (under ``jit``/``vmap``) is
    replaced by the model's reference configuration ``qpos0``.
    """
    springs = [e for e in scene.effects if isinstance(e, JointSprings)]
    dampers = [e for e in scene.effects if isinstance(e, JointDampers)]
    if not springs and not dampers:
        return None
    if not is_concrete(*springs, *dampers) or not is_concrete(scene):
        return None
    if is_concrete(q) and (np.shape(q) != (scene.nq,) or not np.all(np.isfinite(np.asarray(q)))):
        # a malformed initial state: the boundary checks that follow name it; the estimate
        # reads the reference configuration instead
        q = jnp.zeros((0,))
    if not is_concrete(q) or np.shape(q) != (scene.nq,):
        # a traced initial state (under jit or vmap): the model's reference configuration instead,
        # the springs' stiffness and the mass matrix change little with the configuration
        q = getattr(scene.model, "qpos0", None)
        if q is None or not is_concrete(q):
            return None
    # concrete values: computed now even inside a jit/vmap trace (which would stage them out)
    with jax.ensure_compile_time_eval():
        return _estimate(scene, q, springs, dampers)


def _estimate(scene, q, springs, dampers):
    nv = scene.nv
    K = np.zeros((nv, nv))
    for e in springs:
        model = eqx.tree_at(lambda m: m.joint_stiffness, scene.model, np.asarray(e.stiffness, float))
        # the layout alone (no displacement computed: its operations would run one by one)
        for dofs, k in spring_dofs(model):
            dofs = np.asarray(dofs)
            K[dofs, dofs] += np.broadcast_to(np.asarray(k, float)[:, None], dofs.shape)
    C = np.zeros((nv, nv))
    for e in dampers:
        C += np.diag(np.asarray(e.damping, float))
    if not np.any(K) and not np.any(C):
        return None
    M = _mass_matrix(scene, jnp.asarray(q))
    try:
        w2, phi = scipy.linalg.eigh(K, M)
        decay = float(np.max(scipy.linalg.eigh(C, M, eigvals_only=True)))
    except (np.linalg.LinAlgError, ValueError):
        # a singular mass matrix (a massless leaf): no estimate rather than a wrong one
        return None
    w = np.sqrt(np.clip(w2, 0.0, None))
    i = int(np.argmax(w))
    zeta = float(phi[:, i] @ C @ phi[:, i] / (2 * w[i])) if w[i] > 0 else math.inf
    nonzero = w[w > 0]
    return {"omega": float(w[i]), "zeta": zeta, "decay": decay,
            "omega_min": float(nonzero.min()) if nonzero.size else 0.0}


def _explicit_method(target_error=None) -> str:
    """The explicit method ``solver="auto"`` takes for a scene that is not stiff: Dopri8 where a
    ``target_error`` asks for tolerances at or below ``HIGH_ORDER_BELOW`` (in Tsit5's error per
    unit tolerance), else Tsit5."""
    if target_error is None or not math.isfinite(float(target_error)):
        return "tsit5"
    return "dopri8" if float(target_error) / ERROR_PER_TOLERANCE["tsit5"] <= HIGH_ORDER_BELOW else "tsit5"


def choose_auto(scene, q0, t0, t1, dtype, rtol, atol, target_error) -> AutoChoice:
    """The preset and tolerances of ``solver="auto"`` (module docstring), with the reason.

    ``rtol``/``atol``: given by the user (``None``: not given). ``target_error``: the final-state
    error asked for instead of tolerances (``None``: not given).
    """
    floor = FLOAT32_TOLERANCE if jnp.finfo(dtype).bits < 64 else 0.0
    why, preset = [], None
    if target_error is not None:
        if rtol is not None or atol is not None:
            raise ValueError("simulate: give target_error or rtol/atol, not both")
        target = float(target_error)
        if not target > 0 or not math.isfinite(target):
            raise ValueError(f"simulate: target_error must be a positive finite number, got {target_error!r}")
        name = _explicit_method(target)
        tol = target / ERROR_PER_TOLERANCE[name]
        why.append(f"target error {target:g} -> rtol = atol = {tol:.2g} ({name}'s final-state error per unit "
                   f"tolerance about {ERROR_PER_TOLERANCE[name]:g} on non-chaotic scenes; a chaotic one amplifies more)")
        if tol < floor:
            why.append(f"raised to {floor:g}: {jnp.dtype(dtype).name} cannot resolve less; use float64 for a "
                       f"target below {floor * ERROR_PER_TOLERANCE[name]:g}")
            tol = floor
        rtol = atol = tol
        preset = name
    else:
        default = default_tolerance(dtype)
        rtol = default if rtol is None else rtol
        atol = default if atol is None else atol
    tightest = min(float(np.min(np.asarray(rtol))), float(np.min(np.asarray(atol)))) if is_concrete(rtol, atol) else None
    span = float(np.asarray(t1) - np.asarray(t0)) if is_concrete(t0, t1) else None
    # the span is the end of the study's rule (modes over the run): traced times give no estimate
    est = stiffness_estimate(scene, q0) if span is not None else None
    if est is not None:
        fast_span = max(est["omega"], est["decay"]) * span
        damped = est["zeta"] >= IMPLICIT_MIN_DAMPING_RATIO or est["omega"] == 0.0
        if damped and fast_span >= IMPLICIT_MIN_SPAN:
            rate = (f"fastest mode {est['omega']:.3g} rad/s, damping ratio {est['zeta']:.2g}" if est["omega"] > 0
                    else f"damper decay rate {est['decay']:.3g} 1/s")
            return AutoChoice("kvaerno5", rtol, atol, "; ".join(why + [
                f"stiff: {rate} over {fast_span:.3g} time constants; implicit kvaerno5 steps over the decayed mode"]))
        if est["omega"] * span >= IMPLICIT_MIN_SPAN:
            why.append(f"fast mode {est['omega']:.3g} rad/s lightly damped (damping ratio {est['zeta']:.2g}): "
                       "explicit, since any solver must resolve its oscillation")
    constrained = scene.constraints is not None
    if preset is not None:
        name = preset
    else:
        # tolerances given (or the defaults): tsit5, whatever their size, so that a solve asked by its
        # tolerances runs the method it always ran (its gradients and step counts stay as they were);
        # the study's faster choice below HIGH_ORDER_BELOW is taken when the accuracy is asked as a
        # target_error
        name = "tsit5"
        if tightest is not None and tightest <= HIGH_ORDER_BELOW:
            why.append(f"tolerance {tightest:g} given: tsit5 (give target_error to let auto take dopri8, "
                       f"the study's fastest at errors below about 1e-6)")
        else:
            why.append(f"tolerance {tightest:g} > {HIGH_ORDER_BELOW:g}: fifth-order tsit5 is fastest there"
                       if tightest is not None else "tolerances traced: tsit5, the fastest at moderate tolerances")
    if constrained:
        why.append("constrained (Maggi equations): the same rule holds on the study's four-bar and rolling disk")
    return AutoChoice(name, rtol, atol, "; ".join(w for w in why if w))
