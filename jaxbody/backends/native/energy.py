"""The energies of a state by the native kernel."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import scalar
from ..._types import Array, ArrayLike, Float
from ...model import Model
from .symbolic import parameter_vector
from .rk4 import spring_potential
from .build import compiled_kernel
from .primitives import split_jvp

# ----------------------------------------------------------------------------- energies
def _energy_rows(model, q, v, gravity, stiffness, reference):
    row = lambda x: jnp.reshape(x, (1, -1))  # noqa: E731
    return (row(q), row(v), row(parameter_vector(model)), row(gravity), row(stiffness), row(reference))


def _energies_composed(model, q, v, gravity, stiffness, reference):
    """The energies written in JAX on the unrolled kernel's scalars (their derivatives)."""
    sc = scalar.scalars
    kinetic, potential = scalar.energies(model, sc(q), sc(v), tuple(sc(gravity)))
    spring = spring_potential(model.joints, sc(q), sc(stiffness), sc(reference))
    dtype = q.dtype
    return tuple(jnp.asarray(e, dtype) for e in (kinetic, potential, spring))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _energies(kernel, model, q, v, gravity, stiffness, reference):
    out = kernel.batched(*_energy_rows(model, q, v, gravity, stiffness, reference))[0][0]
    return out[0], out[1], out[2]


def _energies_jvp(kernel, primals, tangents):
    # value: the native call; tangent: the same energies written in JAX (only the inputs that
    # carry a tangent are differentiated)
    out = _energies(kernel, *primals)
    return out, split_jvp(kernel, None, None, out, primals, tangents, _energies_composed)


_energies.defjvp(_energies_jvp, symbolic_zeros=True)


def energies(
    model: Model,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    *,
    gravity: Float[ArrayLike, "3"] | None = None,
    stiffness: Float[ArrayLike, " n_joint"] | None = None,
    reference: Float[ArrayLike, " nq"] | None = None,
) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]]:
    """``(kinetic energy, gravity potential, spring potential)`` of one state in one native call.

    Kinetic energy ``½ Σ_k V_k·(𝕀_k V_k) + ½ Σ_d a_d v_d²`` (armature ``a``); gravity potential
    ``−Σ_k m_k g·C_k`` (``gravity=None``: zero); spring potential ``½ Σ_j k_j |q_j ⊖ q_ref,j|²``
    (``stiffness`` per joint, ``reference`` ``(nq,)``, as :class:`jaxbody.JointSprings`; default
    none). A ``vmap`` batch (over states, saved times, or both) is one call; derivatives come
    from the same sums written in JAX (:func:`jaxbody.backends.unrolled.energies`). No checks.
    """
    dtype = model.body_pos.dtype
    q = jnp.asarray(q, dtype)
    v = jnp.asarray(v, dtype)
    gravity = jnp.zeros(3, dtype) if gravity is None else jnp.asarray(gravity, dtype)
    stiffness = jnp.zeros(model.joints.n_joint, dtype) if stiffness is None else jnp.asarray(stiffness, dtype)
    reference = jnp.zeros(model.nq, dtype) if reference is None else jnp.asarray(reference, dtype)
    kernel = compiled_kernel(model.tree, model.joints, False, np.dtype(dtype), "energy")
    return _energies(kernel, model, q, v, gravity, stiffness, reference)
