"""The planar path: a :class:`jaxbody.Model` whose hinges are parallel, run in absolute angles.

When every joint is a hinge (one per body, fixed base, no armature), all hinge axes are
parallel and gravity lies in their plane, the dynamics run on the absolute-angle equations of
planar trees (a mass matrix of augmented-body constants rotated by the link angles) in place of
the spatial tree. Coordinates stay the model's own: the absolute angles are an internal change
of variables, ``θ_k = Σ_{j on the path to k} s_j (q_j − q0_j)`` with ``s_j = ±1`` the sense of
hinge ``j`` about the plane normal.
"""

from typing import Any, final

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._types import Array, Float
from ..effects import EffectContext
from ..linalg import solve_spd
from ..planar import augmented_bodies, bias_forces, body_positions, kinetic_energy, mass_matrix
from .base import ModelScene, compiled_when_eager

__all__ = ["PlanarScene"]


@final
class PlanarScene(ModelScene):
    """A :class:`jaxbody.Model` on the planar path (see :class:`jaxbody.Scene`).

    Attributes:
        planar: the absolute-angle system (its hinges turned along the plane normal, without
            springs, dampers or gravity: those are the scene's effects).
        plane: rows ``(e1, e2)`` of the plane of motion in world axes.
        axis_sign: sense ``±1`` of each hinge about the plane normal.
    """

    planar: Any = None
    plane: Float[Array, "2 3"] | None = None
    axis_sign: tuple[float, ...] = eqx.field(static=True, default=())

    @property
    def path(self) -> str:
        return "planar"

    def is_direct(self) -> bool:
        return False

    def direct_kernel(self) -> str | None:
        return None

    # ------------------------------------------------------------------ kinematics
    def _signs(self, dtype):
        return jnp.asarray(self.axis_sign, dtype)

    def context(self, t, q, v) -> EffectContext:
        tree = self.system.tree
        s = self._signs(q.dtype)
        theta = tree.path_sum(s * (q - self.system.qpos0))
        omega = tree.path_sum(s * v)
        return EffectContext(self, t, q, v, angles=(theta, omega))

    def _to_joint(self, force_abs):
        """Forces conjugate to absolute angles → joint forces (``τ_j = s_j Σ_{S(j)} Q_k``)."""
        return self._signs(force_abs.dtype) * self.system.tree.subtree_sum(force_abs)

    def uniform_field_force(self, ctx: EffectContext, field):
        field = jnp.asarray(field, ctx.v.dtype)
        # only the in-plane part of the field does work on a planar motion
        g2 = self.plane @ field
        mbar = augmented_bodies(self.planar, ctx.angles[0]).static_moment
        q_abs = mbar[:, 0] * g2[1] - mbar[:, 1] * g2[0]
        return self._to_joint(q_abs)

    def uniform_field_potential(self, ctx: EffectContext, field):
        field = jnp.asarray(field, ctx.q.dtype)
        _, com = body_positions(self.planar, ctx.angles[0])
        return -jnp.sum(self.planar.body_mass * (com @ (self.plane @ field)))

    def body_wrench_force(self, ctx: EffectContext, wrenches):
        # out-of-plane loads have no meaning in absolute angles; the builder keeps scenes with
        # loads on the spatial path, so this is reached only by a hand-made effect
        raise ValueError("body loads need the spatial path")

    # ------------------------------------------------------------------ protocol
    @compiled_when_eager
    def evaluate(self, t, q, v, tau=None):
        ctx = self.context(t, q, v)
        total, powers = self.effect_forces(ctx, tau)
        theta, omega = ctx.angles
        # joint forces → forces conjugate to the absolute angles (the transpose of _to_joint)
        rhs_abs = self._signs(v.dtype) * total
        rhs_abs = rhs_abs - self.system.tree.children_sum(rhs_abs)
        rhs_abs = rhs_abs - bias_forces(self.planar, theta, omega)
        acc_abs = solve_spd(mass_matrix(self.planar, theta), rhs_abs)
        # absolute angular accelerations → joint accelerations (each relative to its parent)
        par = np.asarray(self.system.tree.parent_array)
        acc_parent = jnp.where(jnp.asarray(par >= 0), acc_abs[np.maximum(par, 0)], 0.0)
        a = self._signs(v.dtype) * (acc_abs - acc_parent)
        return a, tuple(powers), None

    @compiled_when_eager
    def kinetic_energy(self, q, v) -> Float[Array, ""]:
        theta, omega = self.context(0.0, q, v).angles
        return kinetic_energy(self.planar, theta, omega)

    @compiled_when_eager
    def total_energy(self, q: Float[Array, " nq"], v: Float[Array, " nv"]) -> Float[Array, ""]:
        return self.kinetic_energy(q, v) + self.potential_energy(q)
