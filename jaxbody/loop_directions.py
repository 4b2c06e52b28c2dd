"""Which world directions a loop closure constrains.

A loop closure keeps a point of one body on a point of another (:class:`jaxbody.loops.LoopSpec`).
Its rows are the gap ``p_a(q) − p_b(q)`` along some world directions; only the directions in
which the loop can open at all may be constrained (a planar loop: the two in-plane ones),
otherwise the constraint set is redundant. :func:`independent_loop_axes` finds them from the
gap's velocity Jacobian at sampled configurations; the MJCF importer stores them in
``LoopSpec.axes`` and :func:`jaxbody.constraints.loop_closures` uses them. The gap and its rate
(:func:`point_gap`, :func:`point_gap_velocity`) are also the rows of
:class:`jaxbody.constraints.LoopClosure`.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, Float
from .kinematics import forward_kinematics, qpos_rate
from .sampling import random_states

__all__ = ["point_gap", "point_gap_velocity", "independent_loop_axes"]


def point_gap(model, q, body_a: int, point_a, body_b: int, point_b) -> Float[Array, " 3"]:
    """``p_a(q) − p_b(q)`` of two body points (``-1``: the world), the frames computed once."""
    if body_a < 0 and body_b < 0:
        return jnp.asarray(point_a, q.dtype) - jnp.asarray(point_b, q.dtype)
    kin = forward_kinematics(model, q)

    def at(body, point):
        if body < 0:
            return jnp.asarray(point, q.dtype)
        return kin.body_position[body] + kin.body_rotation[body] @ point

    return at(body_a, point_a) - at(body_b, point_b)


def point_gap_velocity(model, q, v, body_a: int, point_a, body_b: int, point_b) -> Float[Array, " 3"]:
    """``d/dt`` of :func:`point_gap` along ``q̇ = qpos_rate(q, v)``."""
    gap = lambda qq: point_gap(model, qq, body_a, point_a, body_b, point_b)  # noqa: E731
    return jax.jvp(gap, (q,), (qpos_rate(model, q, v),))[1]


def independent_loop_axes(model, spec, n_random: int = 4, rtol: float = 1e-9):
    """World directions a loop constrains (see :func:`jaxbody.constraints.loop_closures`).

    The span of the left singular vectors of the loop's 3 × nv velocity Jacobian, sampled at
    ``qpos0`` and at ``n_random`` random configurations, with singular values above ``rtol``
    times the largest; given by world axes when they span it, else by those singular vectors.

    Raises:
        ValueError: the model's parameters are traced (the directions need a concrete model),
            or the loop's two points move together at every sampled configuration.
    """
    if isinstance(model.body_pos, jax.core.Tracer):
        raise ValueError(
            f"loop {spec.label!r}: its constrained directions are found from a concrete model; give them "
            "(LoopSpec.axes, or loop_closures(model, axes=...)) when the model's parameters are traced"
        )
    dtype = model.body_pos.dtype
    qs = [jnp.asarray(model.qpos0)]
    if n_random:
        qs += list(jnp.asarray(random_states(model, n_random, seed=0)[0], dtype))

    def jac(q):
        def rate(x):
            return point_gap_velocity(model, q, x, spec.body_a, jnp.asarray(spec.point_a, dtype),
                                      spec.body_b, jnp.asarray(spec.point_b, dtype))

        return jax.jacfwd(rate)(jnp.zeros(model.nv, dtype))

    J = np.concatenate([np.asarray(jax.jit(jac)(q), np.float64) for q in qs], axis=1)  # (3, K·nv)
    U, S, _ = np.linalg.svd(J)
    keep = S > rtol * max(float(S[0]), np.finfo(np.float64).tiny)
    if not np.any(keep):
        raise ValueError(f"loop {spec.label!r}: its two points move together at every sampled configuration; "
                         "it constrains nothing")
    # world axes when they span those directions (a loop in the x-z plane keeps x and z), so the
    # reactions are world force components; otherwise the singular vectors
    basis = U[:, keep]
    inside = [i for i in range(3) if np.linalg.norm(basis[i]) > 1.0 - 1e-9]
    return np.eye(3)[inside] if len(inside) == basis.shape[1] else basis.T
