"""The unrolled kernel: forward dynamics of a small tree as straight-line scalar arithmetic in JAX.

The tree's static structure (parents, joints, DoF parents) is known when the model is built,
so for a small tree the whole of forward dynamics is written out at trace time as one
straight-line program over **scalars** (:mod:`jaxbody.backends.scalar`, the algorithm: the
composite-rigid-body method with a tree-sparse ``LᵀDL`` factorisation). Nothing has a "3" or
an "n_body" axis. Traced on one state the program is pure scalar code that XLA fuses into a
few loops; under ``jax.vmap`` every scalar becomes a contiguous ``(batch,)`` array, so every
operation is one long SIMD loop over the batch (the batch is the innermost axis by
construction) — no gathers, no ``(…, 3)`` arrays, no per-body kernel launches. No LAPACK call
(safe under large ``vmap`` batches on CPU).

The program grows with the tree (it is unrolled), so it serves trees up to
:data:`MAX_BODIES` bodies; larger trees use the vectorised kernel of
:mod:`jaxbody.kernels`, whose trace size does not depend on the number of bodies. Both give the
same numbers (tests compare them with each other and with MuJoCo).
"""

import jax.numpy as jnp

from .._types import Array, ArrayLike, Float
from ..model import Model
from .scalar import add, bias_and_mass, energies as scalar_energies, ltdl_solve, scalars, stack

__all__ = ["MAX_BODIES", "MAX_DOFS", "applies", "bias_forces", "energies", "forward_dynamics", "mass_matrix"]

MAX_BODIES = 12
#: Largest number of DoFs ``kernel="auto"`` gives the unrolled kernel.
MAX_DOFS = 12


def applies(model: Model) -> bool:
    """Whether the unrolled kernel serves ``model`` by default (size thresholds above)."""
    return 0 < model.nv <= MAX_DOFS and model.n_body <= MAX_BODIES


def energies(
    model: Model, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"], *, gravity: Float[ArrayLike, "3"] | None = None
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """``(kinetic energy, gravity potential)`` by the unrolled kernel (no checks; ``gravity=None``:
    no potential)."""
    dtype = model.body_pos.dtype
    q_s, v_s, g, _ = _scalar_inputs(model, q, v, gravity, None)
    return tuple(jnp.asarray(e, dtype) for e in scalar_energies(model, q_s, v_s, g))


def _scalar_inputs(model: Model, q, v, gravity, external):
    """The state, gravity and body loads as the scalar lists and tuples the passes take."""
    dtype = model.body_pos.dtype
    q = scalars(jnp.asarray(q, dtype))
    v = scalars(jnp.asarray(v, dtype))
    g = None if gravity is None else tuple(scalars(jnp.asarray(gravity, dtype)))
    if external is None:
        return q, v, g, None
    external = jnp.asarray(external, dtype)
    return q, v, g, [tuple(external[b, i] for i in range(6)) for b in range(external.shape[0])]


def forward_dynamics(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    force: Float[ArrayLike, " nv"] | None = None,
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    external: Float[ArrayLike, "n_body 6"] | None = None,
) -> Float[Array, " nv"]:
    """``a = M⁻¹ (force − bias)`` by the unrolled kernel (no checks; module docstring).

    Args:
        model: the model (any size; the program grows with it, see :data:`MAX_BODIES`).
        q, v: the state.
        force: generalized force in the layout of ``v`` (drives, springs, dampers, …);
            ``None`` = zero.
        gravity: uniform field acting on every body (world, m/s²); ``None`` = none (pass
            ``model.gravity`` for the model's own).
        external: ``(n_body, 6)`` world force and torque at each centre of mass
            (MuJoCo ``xfrc_applied``); ``None`` = none.
    """
    dtype = model.body_pos.dtype
    M, bias, lam = bias_and_mass(model, *_scalar_inputs(model, q, v, gravity, external))
    rhs = [-bi for bi in bias]
    if force is not None:
        f = scalars(jnp.asarray(force, dtype))
        rhs = [add(fi, ri) for fi, ri in zip(f, rhs)]
    return stack(ltdl_solve(M, lam, rhs), dtype)


def mass_matrix(model: Model, q: Float[ArrayLike, " nq"]) -> Float[Array, "nv nv"]:
    """Joint-space mass matrix by the unrolled kernel (armature included; no checks)."""
    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    M, _, _ = bias_and_mass(model, scalars(q), [0.0] * model.nv, None, None, want_bias=False)
    nv = model.nv
    zero = jnp.zeros((), dtype)
    rows = [[M.get((max(a, b), min(a, b)), zero) for b in range(nv)] for a in range(nv)]
    return jnp.stack([stack(r, dtype) for r in rows])


def bias_forces(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    external: Float[ArrayLike, "n_body 6"] | None = None,
) -> Float[Array, " nv"]:
    """``bias − Jᵀ external`` by the unrolled kernel (``gravity=None``: no gravity; no checks)."""
    _, bias, _ = bias_and_mass(model, *_scalar_inputs(model, q, v, gravity, external))
    return stack(bias, model.body_pos.dtype)
