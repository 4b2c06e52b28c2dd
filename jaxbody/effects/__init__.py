"""Scene effects: small modules whose sum is a scene's vector field (see :mod:`jaxbody.scene`)."""

from ._base import Effect as Effect, EffectContext as EffectContext
from .constraints import Constraint as Constraint
from .forces import (
    Actuation as Actuation,
    BodyLoads as BodyLoads,
    ControlSignal as ControlSignal,
    FourierTorque as FourierTorque,
    Gravity as Gravity,
    JointDampers as JointDampers,
    JointSprings as JointSprings,
    SupportMotion as SupportMotion,
)
