"""The boundary checks of a solve: values checked once, before the solve, never inside it.

With concrete inputs a check raises a ``ValueError`` naming the input (or the constraint rows)
at fault. Under ``jit``/``vmap`` the same check is traced: :func:`jaxbody.simulate` turns it
into the run-time check of :func:`jaxbody.validation.raise_if_any` (``throw=True``) or the
result code ``RESULTS.invalid_input`` of that member alone (``throw=False``). Nothing is checked
inside the vector field, where one bad member would stop a whole batch.

:func:`jaxbody.check_inputs` checks a model's own fields; a scene is more than its model (its
effects carry parameters of their own, a protocol system has any fields), so the finiteness
check here runs over every inexact leaf of the scene, and its messages name the leaf's path.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import maggi, program_store
from .._types import Array, Float
from .._util import compiled_when_eager, is_concrete
from ..effects import JointDampers, JointSprings
from ..model import Model
from ..scene import Scene
from ..validation import (
    check_batch_members,
    check_quaternions,
    negative_parameters,
    quaternion_slices,
    raise_if_any,
    validate_at_boundary,
)

__all__ = [
    "value_checks",
    "concrete_value_checks",
    "checked_save_times",
    "checked_step_sign",
    "batch_member_checks",
    "Q0_ATOL",
    "check_positive",
    "scene_constraints",
    "V0_ATOL",
    "concrete_constraint_check",
    "traced_constraint_check",
    "traced_position_check",
]


def _param_leaves(system):
    """``[(path, leaf)]`` of every inexact array of ``system``: the parameters a solve reads
    (integer arrays are indices, fixed when the model was built)."""
    leaves = jax.tree_util.tree_flatten_with_path(eqx.filter(system, eqx.is_inexact_array))[0]
    return [(jax.tree_util.keystr(path), leaf) for path, leaf in leaves if leaf is not None]


def value_checks(system, q0, v0):
    """``[(bad, message)]``: boundary value checks (each ``bad`` a boolean scalar)."""
    # flags, not errors: the caller decides between a run-time check and a per-member result code
    checks = [
        (~jnp.all(jnp.isfinite(q0)), "simulate: q0 contains NaN or inf"),
        (~jnp.all(jnp.isfinite(v0)), "simulate: v0 contains NaN or inf"),
    ]
    for name, leaf in _param_leaves(system):
        checks.append((~jnp.all(jnp.isfinite(leaf)), f"simulate: parameter {name} contains NaN or inf"))
    model = system.system if isinstance(system, Scene) else system
    # a negative mass gives an indefinite mass matrix: the solve would run and be meaningless;
    # negative stiffness, damping or armature feed energy in without bound
    if isinstance(model, Model):
        flags, messages = negative_parameters(model)
        checks += [(flags[i], f"simulate: {m}") for i, m in enumerate(messages)]
        for j, a in quaternion_slices(model):
            checks.append((
                jnp.sum(q0[a:a + 4] ** 2) == 0,
                f"simulate: q0: joint {j} ({model.joints.names[j]!r}): its quaternion q0[{a}:{a + 4}] is zero",
            ))
    if isinstance(system, Scene):
        for eff in system.effects:
            if isinstance(eff, JointDampers):
                checks.append((jnp.any(eff.damping < 0), "simulate: dampers: a damping coefficient is negative"))
            if isinstance(eff, JointSprings):
                checks.append((jnp.any(eff.stiffness < 0), "simulate: springs: a stiffness is negative"))
    return checks


def concrete_value_checks(system, q0, v0):
    """Python errors naming the culprit when every input is concrete (the same checks as
    :func:`value_checks`, with the index, the body name or the value, which a traced check
    cannot put in its message)."""
    if not np.all(np.isfinite(np.asarray(q0))):
        raise ValueError(f"simulate: q0 contains NaN or inf at indices {np.nonzero(~np.isfinite(np.asarray(q0)))[0].tolist()}")
    if not np.all(np.isfinite(np.asarray(v0))):
        raise ValueError(f"simulate: v0 contains NaN or inf at indices {np.nonzero(~np.isfinite(np.asarray(v0)))[0].tolist()}")
    for name, leaf in _param_leaves(system):
        if not np.all(np.isfinite(np.asarray(leaf))):
            raise ValueError(f"simulate: parameter {name} contains NaN or inf")
    model = system.system if isinstance(system, Scene) else system
    if isinstance(model, Model):
        # parameters set after building (eqx.tree_at) get the builder's checks
        try:
            validate_at_boundary(model)
            check_quaternions(model, q0, "q0")
        except ValueError as err:
            raise ValueError(f"simulate: {err}") from None
    if isinstance(system, Scene):
        # a damping or stiffness changed on the scene itself (not through its model)
        for eff in system.effects:
            if isinstance(eff, (JointDampers, JointSprings)):
                try:
                    eff.check(system)
                except ValueError as err:
                    raise ValueError(f"simulate: {err}") from None


def batch_member_checks(system, q0, v0) -> None:
    """Under an eager ``jax.vmap`` over concrete initial states (``throw=True``): a plain
    ``ValueError`` naming the input and the first batch member holding NaN or inf, raised before
    anything is traced further (inside ``jit`` the traced checks apply instead)."""
    if is_concrete(system):
        check_batch_members({"q0": q0, "v0": v0}, prefix="simulate: ")


def save_times(t0, t1, n_save: int | None, dtype) -> Float[Array, " n_save"]:
    """The default save times: ``n_save`` (default 101) equally spaced from ``t0`` to ``t1``,
    both included. Concrete bounds are spaced in NumPy: each eager JAX operation is an XLA
    program compiled once per process (and too small for JAX's persistent cache), which a first
    simulation would otherwise wait for."""
    n = 101 if n_save is None else n_save
    if is_concrete(t0, t1):
        return jnp.asarray(np.linspace(np.asarray(t0, dtype), np.asarray(t1, dtype), n, dtype=dtype), dtype)
    return jnp.linspace(t0, t1, n, dtype=dtype)


def checked_save_times(saveat, t0, t1):
    """``saveat`` with its times checked against ``[t0, t1]`` and for increasing order: with
    concrete times a ``ValueError`` naming the first time at fault; traced ones carry the run-time
    check of :func:`jaxbody.validation.raise_if_any` with the same rule (a usage error, raised
    whatever ``throw`` says; under ``vmap`` naming the batch member).
    (diffrax would otherwise stop with an internal check deep in its loop.)"""
    sub = saveat.subs
    if not isinstance(sub, diffrax.SubSaveAt) or sub.ts is None:
        return saveat
    ts = sub.ts
    if is_concrete(ts, t0, t1):
        a, lo, hi = np.asarray(ts), float(np.asarray(t0)), float(np.asarray(t1))
        # a few ulps of slack: linspace(t0, t1) in float32 may round its ends outwards
        slack = 4 * np.finfo(a.dtype).eps * max(abs(lo), abs(hi), 1.0)
        out = np.flatnonzero((a < lo - slack) | (a > hi + slack) | ~np.isfinite(a))
        if out.size:
            raise ValueError(
                f"simulate: saveat time {a[out[0]]:g} (index {out[0]}) lies outside [t0, t1] = [{lo:g}, {hi:g}]; "
                "save times must lie inside the solve's interval"
            )
        down = np.flatnonzero(np.diff(a) < 0)
        if down.size:
            raise ValueError(
                f"simulate: saveat times must be increasing; time {a[down[0] + 1]:g} (index {down[0] + 1}) comes "
                f"after {a[down[0]]:g}"
            )
        return saveat
    outside = jnp.any(ts < t0) | jnp.any(ts > t1) | ~jnp.all(jnp.isfinite(ts))
    ts = raise_if_any(ts, [
        (outside, "simulate: saveat: a time lies outside [t0, t1]; save times must lie inside the solve's interval"),
        (jnp.any(jnp.diff(ts) < 0), "simulate: saveat times must be increasing; a time comes before the one it follows"),
    ])
    return eqx.tree_at(lambda s: s.subs.ts, saveat, ts)


def checked_step_sign(dt0, t0, t1):
    """``dt0`` checked for a step that runs from ``t0`` towards ``t1`` (``(t1 - t0) * dt0 ≥ 0``):
    concrete values were checked already (``t1`` after ``t0``, ``dt0`` positive); traced ones carry
    the run-time check of :func:`jaxbody.validation.raise_if_any` here, outside the compiled solve
    (diffrax's own check of the same rule is left out of it, see
    :func:`jaxbody.simulation.solve.integrate`)."""
    if dt0 is None or is_concrete(dt0, t0, t1):
        return dt0
    msg = "simulate: t1 must not be before t0 (a solve with a step dt0 runs forward: (t1 - t0) * dt0 >= 0)"
    return raise_if_any(dt0, [((t1 - t0) * dt0 < 0, msg)])


def check_positive(name, value, integer=False):
    """``ValueError`` unless ``value`` is a positive finite number (an integer with ``integer``).

    Traced values pass: a tolerance or step inside ``jit`` cannot stop the trace, and diffrax
    reports a bad one through its own result codes."""
    if value is None or not is_concrete(value):
        return
    # size 1, not shape (): a tolerance given as a one-element array is accepted
    a = np.asarray(value)
    if a.size != 1 or not np.isfinite(a) or a <= 0:
        raise ValueError(f"simulate: {name} must be a positive finite number, got {value!r}")
    if integer and (int(a) != a):
        raise ValueError(f"simulate: {name} must be a positive integer, got {value!r}")


def scene_constraints(scene) -> "maggi.ConstrainedSystem | None":
    """The scene's Maggi constraints as a :class:`jaxbody.maggi.ConstrainedSystem` on the
    scene's own model (so its parameters, not the copy the constraints were built with, give
    the kinetic metric), or ``None`` (no constraints, or a constraint object of another kind:
    those are neither checked at ``t0`` nor projected at switches)."""
    cs = scene.constraints
    if not isinstance(cs, maggi.ConstrainedSystem):
        return None
    # the scene's model may have been changed after the constraints were built (tree_at on
    # scene.system, a vmapped parameter): the constraints must see that model
    if isinstance(cs.base, maggi.ModelBase) and isinstance(scene.system, Model) and cs.base.model is not scene.system:
        cs = eqx.tree_at(lambda c: c.base.model, cs, scene.system)
    return cs


# admissible position residual of q0 on the holonomic constraints (a length for loop closures):
# positions off the constraints are not pulled back by the solve (Baumgarte only damps drift),
# so a start off a loop would simulate another mechanism
Q0_ATOL = 1e-6
V0_ATOL = 1e-9  # admissible residual of v0, scaled by max(1, max|v0|) (as jaxbody.maggi.initial_state)


def admissible(atol: float, dtype) -> float:
    """``atol`` or, where the dtype cannot resolve it, 64 units of its rounding: a float32 state
    on its constraints has residuals of a few times 1e-7, far above float64's tolerances."""
    return max(atol, 64 * float(jnp.finfo(dtype).eps))


def concrete_constraint_check(cs, t0, q0, v0, project_initial):
    """``(q0, v0, correction)``: the initial state when it satisfies the constraints ``cs`` at
    ``t0``, else its projection (``project_initial``: the positions onto the holonomic rows, then
    the velocities onto all rows) or a ``ValueError`` naming the rows at fault. Without
    ``project_initial`` the positions must lie on the holonomic rows within :data:`Q0_ATOL`;
    ``correction`` is the velocity projection's change (``None`` without ``project_initial``)."""
    # the admissible case (the usual one) is decided by one compiled residual; otherwise
    # jaxbody.maggi.initial_state names the rows at fault or projects
    # a stored program (a later process loads its executable instead of tracing and lowering it)
    phi, f = (np.asarray(x) for x in program_store.call(_residual, (cs, t0, q0, v0), "constraint_residual", once=True))
    q_atol, v_atol = admissible(Q0_ATOL, q0.dtype), admissible(V0_ATOL, v0.dtype)
    off = np.flatnonzero(np.abs(phi) > q_atol)
    if off.size and not project_initial:
        names = [cs.constraint_names[i] for i in off]
        raise ValueError(
            f"simulate: q0: initial positions violate the constraints {names} (position residuals "
            f"{[float(phi[i]) for i in off]}, admissible {q_atol:g}); start on the constraints, e.g. from "
            "jaxbody.maggi.project_positions(constrained_system, q0), or pass project_initial=True"
        )
    scale = max(1.0, float(np.max(np.abs(np.asarray(v0)))))
    if not off.size and np.all(np.abs(f) <= v_atol * scale):
        return q0, v0, (jnp.zeros_like(v0) if project_initial else None)
    try:
        q0p, v0p, correction = maggi.initial_state(cs, q0, v0, t0, project_initial=project_initial, atol=v_atol)
    except ValueError as err:
        raise ValueError(f"simulate: v0: {err}") from None
    # positions within the check's tolerance stay as given (a continued run's drift is kept)
    q0 = q0p.astype(q0.dtype) if off.size else q0
    return q0, v0p.astype(v0.dtype), (correction.astype(v0.dtype) if project_initial else None)


# compiled once per constraint structure, quickly (a check: nothing for the optimiser to
# speed up): the eager check runs it on every concrete solve
@compiled_when_eager(quick=True)
def _residual(cs, t, q, v):
    return cs.position_residual(t, q), cs.constraint_residual(t, q, v)


def traced_position_check(cs, t0, q0):
    """``(bad, message)``: the initial positions' check of :func:`concrete_constraint_check` on
    traced values (the holonomic rows' residuals ``φ(t0, q0)`` within :data:`Q0_ATOL`)."""
    q_atol = admissible(Q0_ATOL, q0.dtype)
    bad = jnp.any(jnp.abs(cs.position_residual(t0, q0)) > q_atol)
    msg = (
        f"simulate: q0: initial positions violate the constraints {list(cs.constraint_names)} (a position residual "
        f"exceeds {q_atol:g}); start on the constraints, e.g. from jaxbody.maggi.project_positions"
    )
    return bad, msg


def traced_constraint_check(cs, t0, q0, v0):
    """``(bad, message)``: the check of :func:`jaxbody.maggi.initial_state` on traced values."""
    f = cs.constraint_residual(t0, q0, v0)
    # relative to the speeds, as the eager check: fast motions carry larger rounding residuals
    scale = jnp.maximum(1.0, jnp.max(jnp.abs(v0)))
    v_atol = admissible(V0_ATOL, v0.dtype)
    bad = jnp.any(jnp.abs(f) > v_atol * scale)
    msg = (
        f"simulate: v0: initial velocities violate the constraints {list(cs.constraint_names)} (a residual "
        f"exceeds {v_atol:g}·max(1, max|v0|)); give admissible rates or pass project_initial=True"
    )
    return bad, msg
