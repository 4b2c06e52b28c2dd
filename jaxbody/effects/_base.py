"""The effect protocol: what a scene asks of each thing that pushes on a mechanism.

A scene's vector field is the sum of its declared effects (DESIGN: "effects are modules").
Each effect is an ``equinox.Module`` (its arrays are parameters that ``grad`` reaches) with

* ``generalized_force(ctx) -> (nv,)``: its contribution to the right-hand side of
  ``M(q) a = f − bias`` in the layout of ``v`` (joint coordinates), evaluated from an
  :class:`EffectContext` that carries the state and the kinematics computed once for it;
* ``conservative``: ``True`` when the force derives from ``potential_energy(ctx)``; otherwise
  the simulator integrates its power ``f·v`` so the energy balance closes
  (``E(t) − E(t0) = Σ work``);
* ``check(scene)``: build-time validation (Python errors naming the culprit), optional.

A later effect (contact, joint limits) is a new module with these three members; nothing
else changes. Constraints are different in kind: they do not add a force but replace the
solve for ``a`` (see :class:`jaxbody.effects.Constraint`).
"""

from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax.numpy as jnp

from .._types import Array, Float

__all__ = ["Effect", "EffectContext"]


class EffectContext(NamedTuple):
    """What one evaluation of the vector field knows, computed once and shared by the effects.

    Attributes:
        scene: the :class:`jaxbody.Scene` being evaluated (model, path, plane basis).
        t: time.
        q: coordinates ``(nq,)`` (the model's layout).
        v: velocities ``(nv,)``.
        kinematics: spatial :class:`jaxbody.kinematics.Kinematics` on the spatial path, else
            ``None``.
        angles: absolute angles of the bodies on the planar path, else ``None``.
    """

    scene: Any
    t: Array
    q: Array
    v: Array
    kinematics: Any = None
    angles: Any = None


class Effect(eqx.Module):
    """Base class of scene effects (see the module docstring for the protocol)."""

    name: ClassVar[str] = "effect"
    conservative: ClassVar[bool] = False

    def generalized_force(self, ctx: EffectContext) -> Float[Array, " nv"]:
        raise NotImplementedError

    def potential_energy(self, ctx: EffectContext) -> Float[Array, ""]:
        """Potential of a conservative effect (zero for others)."""
        return jnp.zeros((), ctx.q.dtype)

    def check(self, scene) -> None:
        """Build-time validation; raise ``ValueError`` naming the argument at fault."""
        return None
