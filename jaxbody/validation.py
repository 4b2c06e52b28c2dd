"""Validation of parameters and inputs, for spatial models and planar systems alike.

Errors come in three layers (one rule each):

1. **Before tracing** (``ValueError``): shapes and static misuse, raised by the public
   functions while they are traced (:func:`check_inputs` and the builders).
2. **At the API boundary, once** (:func:`raise_if`): values — a NaN/inf state, drive or
   parameter, a negative mass or damping set after building (e.g. through ``eqx.tree_at``).
   :func:`check_inputs` does these; the convenience functions (``jb.mass_matrix(model, q)``
   ...) call it, ``jb.simulate`` calls it once on the initial state. Every message names the
   input (``q``, ``v``, ``tau``, ``a``, ``external``) or the parameter and its body or joint.
3. **Never inside a vector field or a solver loop.** The ``(model, data, ...)`` kernels of
   :mod:`jaxbody.kernels` and the ``DynamicalSystem`` methods (``acceleration`` ...) check
   nothing, so one bad member of a ``vmap`` batch cannot kill the others; a NaN there becomes
   a NaN result (a rejected step in a solver).

Build-time checks on concrete values (:func:`validate_parameters`, :func:`validate_planar`)
use the same messages as the traced checks of layer 2, plus the offending value.
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from . import runtime_check
from ._types import Array, ArrayLike, Bool
from ._util import check_shape, is_concrete
from .joints import HINGE, JOINT_KINDS, SLIDE

__all__ = [
    "check_inputs",
    "validate_parameters",
    "validate_planar",
    "validate_at_boundary",
    "check_batch_members",
    "raise_if_any",
    "raise_if",
    "negative_parameters",
    "callback_check",
    "zero_quaternions",
    "check_quaternions",
]

# moving bodies need more than this (MuJoCo's compiler uses mjMINVAL = 1e-15)
_MINVAL = 1e-15


# ----------------------------------------------------------------------------- the tables
def _is_planar(system) -> bool:
    return hasattr(system, "hinge_pos")


def _fields(system):
    """``(field, owner kind)`` of every parameter; owner kinds: body, joint, dof, None."""
    if _is_planar(system):
        return [
            ("body_mass", "body"), ("body_com", "body"), ("hinge_pos", "body"),
            ("body_inertia", "body"), ("gravity", None), ("base_mass", None),
        ]
    return [
        ("body_pos", "body"), ("body_quat", "body"), ("body_mass", "body"), ("body_com", "body"),
        ("body_inertia", "body"), ("joint_pos", "joint"), ("joint_axis", "joint"),
        ("joint_stiffness", "joint"), ("dof_armature", "dof"), ("dof_damping", "dof"),
        ("qpos0", None), ("qpos_spring", None), ("gravity", None),
    ]


def _nonnegative(system):
    """Parameters that must not be negative."""
    if _is_planar(system):
        return ["body_mass", "body_inertia", "base_mass"]
    return ["body_mass", "joint_stiffness", "dof_armature", "dof_damping"]


def _owner(system, kind, i) -> str:
    """Who a parameter entry belongs to, as the messages name it."""
    names = system.tree.names
    if _is_planar(system):
        return f"planar body {i} ({names[i]!r})" if kind == "body" else "planar system"
    if kind == "body":
        return f"body {i} ({names[i]!r})"
    jn = system.joints.names
    if kind == "dof":
        i = system.joints.dof_joint[i]
        kind = "joint"
    if kind == "joint":
        return f"joint {i} ({jn[i]!r})"
    return "model"


def _not_finite(system, field, kind, i) -> str:
    return f"{_owner(system, kind, i)}: {field} is not finite (NaN or inf)"


def _negative(system, field, kind, i) -> str:
    return f"{_owner(system, kind, i)}: {field} is negative"


def _entries(a, kind):
    """Per-owner view of a parameter: one row per body/joint/dof, or one row in all."""
    return a.reshape(a.shape[0], -1) if kind is not None else a.reshape(1, -1)


# ----------------------------------------------------------------------------- build time
def _check_values(system, owner_kinds):
    """Finite everywhere and non-negative where required (concrete values, NumPy)."""
    for field, kind in owner_kinds:
        a = _entries(np.asarray(getattr(system, field), dtype=np.float64), kind)
        bad = ~np.all(np.isfinite(a), axis=1)
        if bad.any():
            raise ValueError(_not_finite(system, field, kind, int(np.argmax(bad))))
    kinds = dict(owner_kinds)
    for field in _nonnegative(system):
        a = _entries(np.asarray(getattr(system, field), dtype=np.float64), kinds[field])
        bad = np.any(a < 0, axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            value = a[i, 0] if a.shape[1] == 1 else a[i].tolist()
            raise ValueError(f"{_negative(system, field, kinds[field], i)} ({value})")


def _moving_subsystems_have_mass(tree, mass, moving, owner):
    """Every moving body carries positive mass in its subsystem (else ``M`` is singular)."""
    sub = tree.subtree_mask.astype(np.float64) @ mass
    for k in np.nonzero(moving & ~(sub > 0))[0]:
        yield k, sub[k]


def validate_parameters(model, rtol: float = 1e-9) -> None:
    """Check the physical parameters of a :class:`~jaxbody.Model` on concrete values.

    Checks: shapes; finite values everywhere; non-negative masses, armature, damping and
    stiffness; a positive subtree mass for every body that moves (carries a joint); symmetric
    inertia tensors with non-negative principal moments satisfying the triangle inequality;
    positive mass and principal moments for a moving body with nothing welded to it (MuJoCo's
    compiler rejects the same models); non-zero hinge and slide axes; non-zero quaternions.

    The inertia checks allow a relative ``rtol``, at least a few roundings of the model's dtype:
    a float32 thin plate (principal moments 0.1, 0.2, 0.3) sits on the triangle inequality,
    which rounding to float32 crosses (0.1 + 0.2 < 0.3 there).

    Raises:
        ValueError: naming the field and its body or joint; or a field that is a traced value
            (called inside ``jax.jit``, ``vmap`` or ``grad``).
    """
    tree, joints = model.tree, model.joints
    bn = tree.names
    for f, _ in _fields(model):
        if isinstance(getattr(model, f), jax.core.Tracer):
            raise ValueError(
                f"validate_parameters: model field {f} is a traced value (inside jax.jit, vmap or grad): these "
                "checks read concrete values; validate the model outside the traced function (inside it, "
                "jaxbody.check_inputs checks parameters as the program runs)"
            )
    dtype = np.asarray(model.body_inertia).dtype
    if np.issubdtype(dtype, np.floating):
        rtol = max(rtol, 8 * float(np.finfo(dtype).eps))
    expected = {
        "body_pos": (tree.n_body, 3), "body_quat": (tree.n_body, 4), "body_mass": (tree.n_body,),
        "body_com": (tree.n_body, 3), "body_inertia": (tree.n_body, 3, 3),
        "joint_pos": (joints.n_joint, 3), "joint_axis": (joints.n_joint, 3),
        "joint_stiffness": (joints.n_joint,), "dof_armature": (joints.nv,),
        "dof_damping": (joints.nv,), "qpos0": (joints.nq,), "qpos_spring": (joints.nq,),
        "gravity": (3,),
    }
    for f, shape in expected.items():
        a = np.asarray(getattr(model, f))
        if a.shape != shape:
            raise ValueError(f"model field {f} has shape {a.shape}, expected {shape}")
    _check_values(model, _fields(model))
    mass = np.asarray(model.body_mass, dtype=np.float64)
    moving = np.asarray(joints.body_joint_count) > 0
    for k, m in _moving_subsystems_have_mass(tree, mass, moving, "body"):
        raise ValueError(
            f"body {k} ({bn[k]!r}) moves (has joints) but its subtree mass is "
            f"{m}: a moving body needs positive mass"
        )
    inertia = np.asarray(model.body_inertia, dtype=np.float64)
    # a moving body with no welded child must have its own mass and inertia, as in MuJoCo
    has_welded_child = np.zeros(tree.n_body, dtype=bool)
    for k, p in enumerate(tree.parent):
        if p >= 0 and not moving[k]:
            has_welded_child[p] = True
    for k in range(tree.n_body):
        I = inertia[k]
        scale = max(np.abs(I).max(), 1e-300)
        if np.abs(I - I.T).max() > rtol * scale + 1e-15:
            raise ValueError(f"body {k} ({bn[k]!r}): body_inertia is not symmetric: {I.tolist()}")
        lam = np.linalg.eigvalsh(0.5 * (I + I.T))
        if lam[0] < -rtol * scale:
            raise ValueError(
                f"body {k} ({bn[k]!r}): body_inertia has a negative principal moment "
                f"({lam.tolist()})"
            )
        if lam[0] + lam[1] < lam[2] * (1 - rtol) - 1e-15:
            raise ValueError(
                f"body {k} ({bn[k]!r}): body_inertia violates the triangle inequality "
                f"(principal moments {lam.tolist()}: the two smaller must sum to at least the largest)"
            )
        if moving[k] and not has_welded_child[k] and mass[k] < _MINVAL:
            raise ValueError(
                f"body {k} ({bn[k]!r}) moves (has joints) but its body_mass is {mass[k]}: "
                "MuJoCo requires positive mass on every moving body"
            )
        if moving[k] and not has_welded_child[k] and lam[0] < _MINVAL:
            raise ValueError(
                f"body {k} ({bn[k]!r}) moves (has joints) but a principal moment of inertia is "
                f"not positive (principal moments {lam.tolist()}); MuJoCo's compiler rejects such "
                "a body too: give it a small inertia"
            )
    axes = np.asarray(model.joint_axis)
    jn = joints.names
    for j in range(joints.n_joint):
        if joints.type[j] in (SLIDE, HINGE) and np.linalg.norm(axes[j]) < 1e-12:
            raise ValueError(f"joint {j} ({jn[j]!r}): joint_axis is zero")
    quats = np.asarray(model.body_quat)
    for k in range(tree.n_body):
        if np.linalg.norm(quats[k]) < 1e-12:
            raise ValueError(f"body {k} ({bn[k]!r}): body_quat is zero")


def validate_at_boundary(model) -> None:
    """:func:`validate_parameters` of a model that arrives at a scene or a solve, when its values
    are concrete: parameters set after building (``eqx.tree_at``) get the builder's checks.

    Skipped for traced parameters (inside ``jit``/``vmap``/``grad``, where the traced checks of
    :func:`check_inputs` and of the solve apply) and for a model whose arrays carry a batch axis
    (one model per member of a batch)."""
    if not is_concrete(model) or np.ndim(model.body_mass) != 1:
        return
    validate_parameters(model)


def batch_members(x):
    """The members ``(batch, ...)`` of ``x`` when it is an input batched by an eager ``jax.vmap``
    (its values concrete, only the batch axis traced), else ``None``. Lets a boundary check name
    the batch member at fault in a plain Python error, before anything runs."""
    val, axis = getattr(x, "val", None), getattr(x, "batch_dim", None)
    if type(x).__name__ != "BatchTracer" or not isinstance(axis, int) or not is_concrete(val):
        return None
    return np.moveaxis(np.asarray(val), axis, 0)


def check_batch_members(inputs: dict, prefix: str = "") -> None:
    """``ValueError`` naming the input and the first batch member that holds NaN or inf, for the
    inputs of an eager ``jax.vmap`` (see :func:`batch_members`; others are skipped)."""
    for name, x in inputs.items():
        members = batch_members(x)
        if members is None or members.ndim < 1:
            continue
        bad = ~np.all(np.isfinite(members.reshape(members.shape[0], -1)), axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"{prefix}{name} contains NaN or inf (batch member {i} of {members.shape[0]})")


def raise_if_any(x: Array, checks: Sequence[tuple[ArrayLike, str]]) -> Array:
    """``x``, unchanged, after the traced ``checks`` ``[(bad, message)]`` (each ``bad`` a boolean
    scalar): :func:`raise_if` of their flags and messages."""
    if not checks:
        return x
    return raise_if(x, jnp.stack([jnp.asarray(b) for b, _ in checks], axis=-1), [m for _, m in checks])


def raise_if(x: Array, flags: Bool[ArrayLike, " n"], messages: Sequence[str]) -> Array:
    """``x``, unchanged, after the traced ``flags`` ``(n,)`` (``True``: check ``i`` failed, whose
    message is ``messages[i]``): when one fails the program stops with that check's message and,
    under ``vmap``, the first batch member that failed it (``q0 contains NaN or inf (batch
    member 1 of 3)``), on the error's first line.

    On the CPU the check is :func:`jaxbody.runtime_check.check`, an XLA foreign-function call
    that fails the program with ``INVALID_ARGUMENT: <message>`` (JAX's runtime error, or a
    ``ValueError`` from a compiled program's fast path). Elsewhere, or where its library cannot be
    built (no C++ compiler), the check is a host callback (:func:`callback_check`). Tangents pass
    through unchanged. The check guards the values computed from ``x``: use the returned array."""
    messages = tuple(" ".join(m.splitlines()) for m in messages)
    if jnp.shape(flags) != (len(messages),):
        raise ValueError(f"raise_if: flags have shape {jnp.shape(flags)}, expected ({len(messages)},)")
    if not messages:
        return x

    @jax.custom_jvp
    def checked(x, flags):
        if runtime_check.target() is None:
            return callback_check(x, flags, messages)
        # the platform the program is compiled for picks the check (the FFI target is the CPU's)
        return lax.platform_dependent(x, flags, cpu=lambda x, f: runtime_check.check(x, f, messages),
                                      default=lambda x, f: callback_check(x, f, messages))

    @checked.defjvp
    def _(primals, tangents):
        return checked(*primals), tangents[0]

    return checked(x, jnp.asarray(flags, bool))


def callback_check(x: Array, flags: Bool[Array, "*batch n"], messages: tuple[str, ...]) -> Array:
    """The check of :func:`raise_if_any` through a host callback: a ``lax.cond`` on "any member
    failed" whose failing branch calls back to the host and raises a ``ValueError`` there (inside
    ``jit`` JAX re-raises it as its runtime error, ``INTERNAL: CpuCallback error``, with this
    text further down). Serves where the foreign-function check cannot."""

    def report(flags, x):
        f = np.asarray(flags)
        flat = f.reshape(-1, f.shape[-1])
        i = int(np.flatnonzero(flat.any(axis=1))[0])
        j = int(np.flatnonzero(flat[i])[0])
        member = f" (batch member {i} of {flat.shape[0]})" if f.ndim > 1 else ""
        raise ValueError(messages[j] + member)

    def fail():
        return jax.pure_callback(report, jax.ShapeDtypeStruct(x.shape, x.dtype), flags, x, vmap_method="broadcast_all")

    # one predicate for a whole vmapped batch: the failing branch runs only when some member failed
    return lax.cond(eqx.internal.unvmap_any(jnp.any(flags)), fail, lambda: x)


def zero_axes(model) -> list[int]:
    """The hinge and slide joints of ``model`` whose axis is zero (concrete values)."""
    axes = np.asarray(model.joint_axis)
    types = np.asarray(model.joints.type)
    norms = np.linalg.norm(axes.reshape(-1, 3), axis=-1)
    return [int(j) for j in np.flatnonzero(((types == SLIDE) | (types == HINGE)) & (norms < 1e-12))]


def quaternion_slices(model) -> list[tuple[int, int]]:
    """``[(joint, offset in q)]`` of every ball and free joint's unit quaternion."""
    joints = model.joints
    out = []
    for j, code in enumerate(joints.type):
        off = JOINT_KINDS[code].quaternion
        if off is not None:
            out.append((j, int(joints.qposadr[j]) + off))
    return out


def zero_quaternions(model, q) -> list[tuple[int, float]]:
    """``[(joint, norm)]`` of the ball/free joints whose quaternion in ``q`` (concrete, ``(nq,)``)
    has zero norm: no rotation is defined by it (normalising it gives NaN)."""
    q = np.asarray(q, dtype=np.float64)
    out = []
    for j, a in quaternion_slices(model):
        n = float(np.linalg.norm(q[a:a + 4]))
        if not n > 1e-12 and np.isfinite(n):
            out.append((j, n))
    return out


def check_quaternions(model, q, name: str = "q") -> None:
    """``ValueError`` naming the first ball/free joint whose quaternion in ``q`` is zero."""
    bad = zero_quaternions(model, q)
    if bad:
        j, _ = bad[0]
        a = dict(quaternion_slices(model))[j]
        raise ValueError(
            f"{name}: joint {j} ({model.joints.names[j]!r}): its quaternion {name}[{a}:{a + 4}] is zero "
            f"({np.asarray(q)[a:a + 4].tolist()}); a rotation needs a non-zero quaternion (w, x, y, z), "
            "e.g. (1, 0, 0, 0)"
        )


def validate_planar(system) -> None:
    """Check the parameters of a planar system on concrete values (see :func:`validate_parameters`).

    Checks: finite values; non-negative masses, moments of inertia and base mass; positive
    mass in every subsystem; a positive augmented moment of inertia ``J_k`` (eq. 6, planar)
    for every body. Skipped (silently) when parameters are traced (a system built inside
    ``jit``/``grad``).

    Raises:
        ValueError: naming the body and field.
    """
    values = [getattr(system, f) for f, _ in _fields(system)]
    if any(isinstance(x, jax.core.Tracer) for x in values):
        return
    _check_values(system, _fields(system))
    tr, names = system.tree, system.tree.names
    mass = np.asarray(system.body_mass, dtype=np.float64)
    for k, _ in _moving_subsystems_have_mass(tr, mass, np.ones(tr.n_body, bool), "planar body"):
        raise ValueError(
            f"planar body {k} ({names[k]!r}): body_mass of its subsystem is zero; "
            "a moving body needs positive total mass"
        )
    # eq. (6), planar: J_k = I_Ck + m_0k |r_k|² + Σ_{j∈A(k)} m_j |R_j|²
    sub = tr.subtree_mask.astype(np.float64) @ mass
    com = np.asarray(system.body_com, dtype=np.float64)
    hinge = np.asarray(system.hinge_pos, dtype=np.float64)
    J = np.asarray(system.body_inertia, dtype=np.float64) + mass * np.sum(com**2, axis=-1)
    for j in range(tr.n_body):
        p = tr.parent[j]
        if p >= 0:
            J[p] += sub[j] * np.sum(hinge[j] ** 2)
    for k in np.nonzero(~(J > 0))[0]:
        raise ValueError(
            f"planar body {k} ({names[k]!r}): body_inertia gives a zero augmented moment of "
            "inertia J_k (all of its mass on its hinge axis); the mass matrix would be singular"
        )


# ----------------------------------------------------------------------------- API boundary
def _parameter_check(system):
    """``(flags, messages)``: one flag per (parameter, owner) that is NaN/inf or negative."""
    flags, msgs = [], []
    for field, kind in _fields(system):
        a = _entries(jnp.asarray(getattr(system, field)), kind)
        flags.append(~jnp.all(jnp.isfinite(a), axis=1))
        msgs += [_not_finite(system, field, kind, i) for i in range(a.shape[0])]
    negative, negative_msgs = negative_parameters(system)
    return jnp.concatenate([*flags, negative]), msgs + negative_msgs


def negative_parameters(system) -> tuple[Bool[Array, " n"], list[str]]:
    """``(flags, messages)`` of the parameters that must not be negative (masses, and damping,
    armature and stiffness of a model): one flag per (parameter, owner), ``True`` where negative,
    its message naming the body or joint (``"body 1 ('b'): body_mass is negative"``)."""
    flags, msgs = [], []
    kinds = dict(_fields(system))
    for field in _nonnegative(system):
        a = _entries(jnp.asarray(getattr(system, field)), kinds[field])
        flags.append(jnp.any(a < 0, axis=1))
        msgs += [_negative(system, field, kinds[field], i) for i in range(a.shape[0])]
    return jnp.concatenate(flags), msgs


def _nonfinite_inputs(given: dict) -> dict:
    """One flag per input: whether it holds a NaN or inf."""
    return {name: ~jnp.all(jnp.isfinite(x)) for name, x in given.items()}


@eqx.filter_jit
def _value_flags(system, given: dict):
    """The flags of :func:`_parameter_check` and of :func:`_nonfinite_inputs`, as one compiled
    program (cached per system structure and input shapes) for eager calls."""
    return _parameter_check(system)[0], _nonfinite_inputs(given)


def check_inputs(system, *, q=None, v=None, tau=None, a=None, external=None) -> tuple:
    """Validate a system's parameters and the given inputs once, at the API boundary.

    Shapes are checked while tracing (``ValueError``); values inside the program (the run-time
    check of :func:`raise_if`): every parameter finite, masses (and damping, armature, stiffness)
    non-negative, every given input finite. Call it once per public call or per simulation —
    never inside a vector field, where one bad member would stop a whole ``vmap`` batch.

    Args:
        system: a :class:`~jaxbody.Model` or a planar system.
        q: coordinates ``(nq,)``.
        v: velocities ``(nv,)``.
        tau: generalized forces ``(nv,)``.
        a: accelerations ``(nv,)``.
        external: body loads ``(n_body, 6)`` (spatial models only; see
            :func:`jaxbody.inverse_dynamics`).

    Returns:
        ``(system, *inputs)``: the system and the given inputs (``None`` ones left out) in the
        order ``q, v, tau, a, external``, as arrays of the parameters' float dtype. Use the
        returned values: under ``jit`` a check whose result is unused is dropped.

    Raises:
        ValueError: an input of the wrong shape (before tracing), naming it; called eagerly
            (concrete values), also a NaN/inf input (``"tau contains NaN or inf"``) or an
            invalid parameter (``"body 1 ('b'): body_mass is negative"``).
        jax.errors.JaxRuntimeError: under ``jit``, the same value errors at run time, the
            message on the first line after the status (``INVALID_ARGUMENT: tau contains NaN
            or inf``, under ``vmap`` with ``(batch member 2 of 3)``); a compiled program called
            again may raise it as a ``ValueError`` with the same text.
    """
    where = "planar system" if _is_planar(system) else ""
    dtype = system.body_mass.dtype
    given = {}
    for name, value, shape in (
        ("q", q, (system.nq,)),
        ("v", v, (system.nv,)),
        ("tau", tau, (system.nv,)),
        ("a", a, (system.nv,)),
        ("external", external, (system.n_body, 6)),
    ):
        if value is None:
            continue
        if name == "external" and _is_planar(system):
            raise ValueError(
                "planar system: external loads are external_force (n_body, 2) and "
                "external_moment (n_body,); pass them to jaxbody.planar functions"
            )
        given[name] = check_shape(value, shape, name, where, dtype=dtype)
    concrete = is_concrete(system, given)
    if concrete:
        # the flags from one compiled program; under a trace (a jit closing over concrete
        # inputs) they are traced after all
        flags, bad_inputs = _value_flags(system, given)
        concrete = is_concrete(flags, bad_inputs)
    if concrete:
        # Concrete values (eager call): a plain Python error whose traceback is this call's.
        # (eqx.error_if outside jit reports the stack of the first call that compiled it.) The
        # messages are written only for an error.
        flags = np.asarray(flags)
        if flags.any():
            raise ValueError(_parameter_check(system)[1][int(np.argmax(flags))])
        for name, bad in bad_inputs.items():
            if bool(bad):
                raise ValueError(f"{name} contains NaN or inf")
        if not _is_planar(system):
            # a zero axis (set after building) gives NaN or a singular mass matrix, silently
            for j in zero_axes(system)[:1]:
                raise ValueError(f"joint {j} ({system.joints.names[j]!r}): joint_axis is zero")
            if "q" in given:
                check_quaternions(system, given["q"])
        return (system, *given.values())
    if is_concrete(system):
        # an eager vmap over the inputs: a plain error naming the member, before anything runs
        check_batch_members(given)
    flags, msgs = _parameter_check(system)
    bad_inputs = _nonfinite_inputs(given)
    if not given:
        system = eqx.tree_at(lambda s: s.body_mass, system, raise_if(system.body_mass, flags, msgs))
        return (system,)
    # the parameters' checks travel with the first input, which every public function reads
    first = next(iter(given))
    out = []
    for name, x in given.items():
        own, message = bad_inputs[name][None], f"{name} contains NaN or inf"
        if name == first:
            out.append(raise_if(x, jnp.concatenate([flags, own]), [*msgs, message]))
        else:
            out.append(raise_if(x, own, [message]))
    return (system, *out)
