"""Joint-space dynamics from coordinates: the convenience layer over :mod:`jaxbody.kernels`.

Each function validates its inputs once (:func:`jaxbody.check_inputs`: shapes before
tracing, NaN/inf inputs and invalid parameters at run time, each naming the input or the
parameter), computes the state pytree once (:func:`jaxbody.compute_data`) and calls the kernel
of the same name. Inside vector fields and solver loops call the kernels on a
:class:`~jaxbody.Data` instead: they check nothing, so a vmapped batch survives a bad member.

The same functions serve planar systems (:mod:`jaxbody.planar`) in the planar system's own
coordinates — absolute angles (and base position), drives in the layout of ``v`` — by calling
the planar function of the same name; where a planar system has no counterpart (passive
forces, MuJoCo-style ``external`` loads) the message says what to call instead.

Conventions (docs/conventions.md): ``M(q) a + bias(q, v) = tau [+ passive] + Jᵀ external``;
mass matrices in the coordinates of ``v``; ``external`` = ``(n_body, 6)`` world force and
torque at each centre of mass (MuJoCo ``xfrc_applied``); reactions = ``(force, moment)`` the
parent exerts at the base point ``O_0k``; model first, then the state, options keyword-only.

Each function runs its computation as one compiled program (:func:`_compiled`), built
on the first call for a model structure and input shapes and reused by every later call with
new values (new parameters included); called eagerly, as in a notebook, one call then costs a
dispatch instead of hundreds of operations run one by one. Inside ``jit`` it is inlined.
"""

import equinox as eqx
import jax.numpy as jnp

from . import backends, kernels, planar
from ._types import Array, ArrayLike, Float
from .augmented import AugmentedBodies
from .data import compute_data
from .model import Model
from .validation import check_inputs

#: what the convenience functions accept
System = Model | planar.PlanarSystem

# Inputs other than q and v are annotated with "_" dims (not checked by jaxtyping) so that a
# wrong shape reaches check_inputs, whose message names the input.

__all__ = [
    "augmented_bodies",
    "mass_matrix",
    "bias_forces",
    "inverse_dynamics",
    "forward_dynamics",
    "joint_reactions",
    "kinetic_energy",
    "potential_energy",
    "passive_forces",
]


def _planar(system) -> bool:
    if isinstance(system, planar.PlanarSystem):
        return True
    if not isinstance(system, Model):
        raise TypeError(
            f"expected a jaxbody.Model or a jaxbody.planar.PlanarSystem, got {type(system).__name__}"
            + (
                "; for a constrained example call its own methods (acceleration, total_energy, ...)"
                if hasattr(system, "acceleration")
                else ""
            )
        )
    return False


def _no_planar_external(name, external):
    if external is not None:
        raise ValueError(
            f"{name}: a planar system takes external_force (n_body, 2) and external_moment "
            f"(n_body,), not external: call jaxbody.planar.{name}(system, ..., external_force=..., "
            "external_moment=...)"
        )


def _compiled(fn, model, *args):
    """``fn(model, *args)`` as one compiled program, cached per function (a module-level one,
    static), model structure and the shapes and dtypes of the arrays. Flags and kernel names
    among ``args`` are static; anything else becomes an array (a list of numbers too, which
    would otherwise be compiled into the program). Spatial inputs are checked before (eagerly
    when they are concrete, so that an error names the input and points at the caller's line)."""
    args = tuple(a if a is None or isinstance(a, (bool, str)) else jnp.asarray(a) for a in args)
    return _compiled_program(fn, model, *args)


@eqx.filter_jit
def _compiled_program(fn, model, *args):
    return fn(model, *args)


def _augmented_bodies(model, q):
    return compute_data(model, q).augmented


def _mass_matrix(model, q):
    return kernels.mass_matrix(model, compute_data(model, q))


def _bias_forces(model, q, v):
    return kernels.bias_forces(model, compute_data(model, q, v))


def _inverse_dynamics(model, q, v, a, external, include_passive):
    return kernels.inverse_dynamics(model, compute_data(model, q, v), a, external=external,
                                    include_passive=include_passive)


def _forward_dynamics(model, q, v, tau, external, include_passive, kernel):
    force = tau
    if include_passive:
        passive = kernels.passive_forces_at(model, q, v)
        force = passive if force is None else force + passive
    return backends.acceleration(model, q, v, force, gravity=model.gravity, external=external, kernel=kernel)


def _joint_reactions(model, q, v, a, external):
    return kernels.joint_reactions(model, compute_data(model, q, v), a, external=external)


def _kinetic_energy(model, q, v):
    return kernels.kinetic_energy(model, compute_data(model, q, v))


def _potential_energy(model, q):
    return kernels.potential_energy(model, compute_data(model, q))


def _passive_forces(model, q, v):
    return kernels.passive_forces(model, compute_data(model, q, v))


def augmented_bodies(model: System, q: Float[ArrayLike, " nq"]) -> AugmentedBodies:
    """Subtree masses, augmented static moments and inertias about ``O_0k`` (spec eqs 5–6).

    Vectors and tensors are in world axes; the base point of body ``k`` is the anchor of its
    first joint (see :mod:`jaxbody.kinematics`). Planar system: :func:`jaxbody.planar.augmented_bodies`.
    """
    if _planar(model):
        return _compiled(planar.augmented_bodies, model, q)
    model, q = check_inputs(model, q=q)
    return _compiled(_augmented_bodies, model, q)


def mass_matrix(model: System, q: Float[ArrayLike, " nq"]) -> Float[Array, "nv nv"]:
    """Mass matrix ``M(q)`` in the coordinates of ``v``, armature included.

    Spatial model: joint coordinates (:func:`jaxbody.kernels.mass_matrix`). Planar system: the
    absolute-angle matrix ``ℳ`` of :func:`jaxbody.planar.mass_matrix` (for joint angles:
    :func:`jaxbody.planar.joint_mass_matrix`).
    """
    if _planar(model):
        return _compiled(planar.mass_matrix, model, q)
    model, q = check_inputs(model, q=q)
    return _compiled(_mass_matrix, model, q)


def bias_forces(model: System, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]) -> Float[Array, " nv"]:
    """Coriolis, centrifugal and gravity forces (MuJoCo ``qfrc_bias``): ``tau`` at ``a = 0``.

    Planar system: ``h`` of :func:`jaxbody.planar.bias_forces` (absolute angles).
    """
    if _planar(model):
        return _compiled(planar.bias_forces, model, q, v)
    model, q, v = check_inputs(model, q=q, v=v)
    return _compiled(_bias_forces, model, q, v)


def inverse_dynamics(
    model: System,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    a: Float[ArrayLike, " _nv"],
    *,
    external: Float[ArrayLike, "_n_body _six"] | None = None,
    include_passive: bool = False,
) -> Float[Array, " nv"]:
    """Joint forces ``tau = M(q) a + bias(q, v) - Jᵀ external`` via Statement 1.

    Args:
        external: optional loads per body, MuJoCo ``xfrc_applied`` layout: world force and
            torque applied at the body's centre of mass.
        include_passive: subtract the joint springs and dampers (``tau`` is then what the
            actuators add to them). MuJoCo's ``mj_inverse`` corresponds to ``True``; the default
            ``False`` leaves them out.

    Planar system: the drive torques of :func:`jaxbody.planar.inverse_dynamics`.
    """
    if _planar(model):
        _no_planar_external("inverse_dynamics", external)
        return _compiled(planar.inverse_dynamics, model, q, v, a)
    model, q, v, a, *ext = check_inputs(model, q=q, v=v, a=a, external=external)
    return _compiled(_inverse_dynamics, model, q, v, a, ext[0] if ext else None, bool(include_passive))


def forward_dynamics(
    model: System,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    tau: Float[ArrayLike, " _nv"] | None = None,
    *,
    external: Float[ArrayLike, "_n_body _six"] | None = None,
    include_passive: bool = False,
    kernel: str | None = None,
) -> Float[Array, " nv"]:
    """Accelerations ``a = M⁻¹ (tau - bias + Jᵀ external [+ passive])``.

    Runs :func:`jaxbody.backends.acceleration` with ``kernel`` (``None``: the default,
    ``"auto"`` unless ``$JAXBODY_KERNEL`` says otherwise: the native kernel where it can be
    built, the fastest on CPU; the same numbers either way, docs/performance.md).

    ``include_passive=True`` adds the joint springs and dampers (as ``jb.simulate`` does for a
    model). Planar system: :func:`jaxbody.planar.forward_dynamics` (absolute angular
    accelerations).
    """
    if _planar(model):
        _no_planar_external("forward_dynamics", external)
        return _compiled(planar.forward_dynamics, model, q, v, tau)
    model, q, v, *rest = check_inputs(model, q=q, v=v, tau=tau, external=external)
    tau = rest.pop(0) if tau is not None else None
    ext = rest.pop(0) if external is not None else None
    # the kernel is chosen here ($JAXBODY_KERNEL and the compiler read at each call, not once
    # per compiled program)
    kernel = backends.resolve_kernel(model, kernel)
    return _compiled(_forward_dynamics, model, q, v, tau, ext, bool(include_passive), kernel)


def joint_reactions(
    model: System,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    a: Float[ArrayLike, " _nv"],
    *,
    external: Float[ArrayLike, "_n_body _six"] | None = None,
) -> tuple[Float[Array, "n_body dim"], Float[Array, "n_body *moment"]]:
    """``(force, moment)`` the parent exerts on each body at its base point ``O_0k`` (world).

    The relative force factors ``F_k``, ``M_k`` of Statement 1 (spec eqs 1–2): constraint
    reaction plus drive; the moment is about ``O_0k`` (the anchor of the body's first joint,
    the body origin for welded and free bodies). Planar system:
    :func:`jaxbody.planar.joint_reactions` (force ``(n_body, 2)``, moment ``(n_body,)``).
    """
    if _planar(model):
        _no_planar_external("joint_reactions", external)
        return _compiled(planar.joint_reactions, model, q, v, a)
    model, q, v, a, *ext = check_inputs(model, q=q, v=v, a=a, external=external)
    return _compiled(_joint_reactions, model, q, v, a, ext[0] if ext else None)


def kinetic_energy(model: System, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]) -> Float[Array, ""]:
    """``T = sum_k ½ m_0k |v_Ck|² + ½ ω_k·I_Ck ω_k`` from body velocities (armature adds ½ a v²)."""
    if _planar(model):
        return _compiled(planar.kinetic_energy, model, q, v)
    model, q, v = check_inputs(model, q=q, v=v)
    return _compiled(_kinetic_energy, model, q, v)


def potential_energy(model: System, q: Float[ArrayLike, " nq"]) -> Float[Array, ""]:
    """Gravity plus joint-spring potential energy (as MuJoCo ``mj_energyPos``)."""
    if _planar(model):
        return _compiled(planar.potential_energy, model, q)
    model, q = check_inputs(model, q=q)
    return _compiled(_potential_energy, model, q)


def passive_forces(model: System, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]) -> Float[Array, " nv"]:
    """Joint springs towards ``qpos_spring`` and viscous damping (MuJoCo ``qfrc_passive``)."""
    if _planar(model):
        raise ValueError(
            "passive_forces: a planar system has no joint springs or dampers; add such forces "
            "to tau (jaxbody.planar.forward_dynamics(system, q, v, tau))"
        )
    model, q, v = check_inputs(model, q=q, v=v)
    return _compiled(_passive_forces, model, q, v)
