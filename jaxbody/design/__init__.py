"""Balancing synthesis of dynamically decoupled mechanisms, and decoupling measures.

Why static moments decide coupling
----------------------------------
In absolute angles (the angle of each body measured from a fixed direction, not from its
parent), the mass matrix of a planar tree has the augmented moments of inertia ``J_k`` on
its diagonal and, for every body ``k`` and every carrier ``i`` of ``k`` (a body on its path to
the ground), the off-diagonal entry ``R · m̄_k``: the link vector from the joint of ``i``
towards ``k`` dotted with the static moment ``m̄_k`` of the augmented body ``k`` (body ``k``
plus the whole mass of every subtree it carries, lumped at the joints of its children).
Velocity products carry the same coefficients. Hence:

* on a **fixed** base the bodies are dynamically decoupled for all configurations iff
  ``m̄_k = 0`` for every body that has a carrier; a body hinged to the ground may keep its
  static moment (it only feels its own weight);
* on a **translating** base the base row couples with every body through ``m̄_k``, so all
  static moments must vanish;
* in space, with ball joints, the off-diagonal blocks ``−[m̄_k]×[R]×`` vanish iff
  ``m̄_k = 0`` likewise.

With the static moments zero, the equations separate into ``J_k α̈_k = M_k − Σ_{children j} M_j``:
a torque in one joint turns only the two bodies it connects, and a torque at the root joint
turns the root body alone, the others keeping their absolute orientation.

:func:`balance` adds a point counterweight to chosen bodies (mass and position within
bounds, through a bounded ``(1 + sin z)/2`` parameterisation) and drives the required ``m̄_k``
to zero with optax (an augmented Lagrangian with L-BFGS inner solves for exact decoupling,
or a quadratic penalty for a trade-off), while penalising added mass and added inertia.
Optionally (``extensions=``) each link is extended beyond its joint by a rod of bounded
length with the counterweight at its end: the extension length replaces the free position
as design variable, and the rod's own mass and inertia count as added.
:func:`static_balance` is the closed-form answer: leaves first, a counterweight opposite
each static moment at a given distance. Both return the balanced system with the
counterweights folded into the bodies' mass, centre of mass and inertia, so every function
of jaxbody works on it.

One module per job, their public names re-exported here: :mod:`~jaxbody.design.decoupling`
(the decoupling check), :mod:`~jaxbody.design.bodies` (static moments and the bodies that must
be balanced), :mod:`~jaxbody.design.counterweights` (folding counterweights into bodies),
:mod:`~jaxbody.design.coupling_measure`, :mod:`~jaxbody.design.closed_form`
(:func:`static_balance`) and :mod:`~jaxbody.design.synthesis` (:func:`balance`).
"""

from .bodies import required_bodies as required_bodies, resolve_bodies as resolve_bodies, static_moments as static_moments
from .closed_form import BalanceReport as BalanceReport, static_balance as static_balance
from .counterweights import fold_counterweights as fold_counterweights
from .coupling_measure import coupling as coupling
from .decoupling import DecouplingReport as DecouplingReport, decoupling_report as decoupling_report
from .synthesis import balance as balance, tradeoff_curve as tradeoff_curve

__all__ = [
    "decoupling_report",
    "DecouplingReport",
    "static_moments",
    "required_bodies",
    "fold_counterweights",
    "coupling",
    "BalanceReport",
    "balance",
    "static_balance",
    "tradeoff_curve",
    "resolve_bodies",
]
