"""Events that end a solve, and phases: scenes switched by events."""

from collections.abc import Callable

import equinox as eqx

__all__ = ["Event", "Phases"]


class Event(eqx.Module):
    """A condition ``g(t, q, v)`` whose zero crossing stops a solve (located by root finding).

    Attributes:
        condition: ``g(t, q, v) -> scalar`` (or a boolean, which triggers without root finding).
        direction: ``None`` (either way), ``True`` (upward crossing ``−→+``) or ``False`` (downward).
    """

    condition: Callable
    # static: diffrax builds a different root-finding program for each direction
    direction: bool | None = eqx.field(static=True, default=None)

    def __call__(self, t, q, v):
        return self.condition(t, q, v)


class Phases(eqx.Module):
    """An ordered list of scenes switched by events: phase ``i`` runs until ``events[i]``
    triggers, then phase ``i + 1`` starts from that state (mapped by ``transitions[i]``
    ``(t, q, v) -> (q, v)`` when given). The last phase runs to ``t1``.

    When the scene of phase ``i + 1`` has Maggi constraints (``jb.scene(model, constraints=...)``
    or a :class:`jaxbody.maggi.ConstrainedSystem`), the velocities entering it are projected onto
    them as an impulsive constraint in the kinetic metric, ``x⁺ = A(AᵀDA)⁻¹AᵀD·x⁻``
    (:func:`jaxbody.maggi.switch_constraints`); a looser constraint set keeps the velocity.
    ``jb.simulate(phases, q0, v0, t1)`` checks ``v0`` against the first phase's constraints
    and returns one :class:`jaxbody.Solution` for the whole run: the work of the
    non-conservative effects carried across the switches, the energy change at each switch in
    ``stats["switch_energy_jump"]`` and ``work["switches"]`` (so the energy balance closes),
    the energy lost by each projection in ``stats["switch_energy_lost"]``, the phase of each
    saved time in ``stats["phase"]``, and reactions and constraint residuals padded with NaN to
    the largest number of constraint rows over the phases.

    Attributes:
        scenes: the phases' scenes (same ``nq`` and ``nv``).
        events: ``len(scenes) − 1`` :class:`Event` (or callables ``g(t, q, v)``); ``events[i]``
            ends phase ``i``.
        transitions: optional maps ``(t, q, v) -> (q, v)`` applied at each switch, before the
            projection onto the next constraints.
    """

    scenes: tuple
    events: tuple
    transitions: tuple = ()

    # checked when built, so a mismatch is reported before any phase is traced
    def __check_init__(self):
        if len(self.scenes) < 1 or len(self.events) != len(self.scenes) - 1:
            raise ValueError(
                f"phases: need n scenes and n - 1 events, got {len(self.scenes)} scenes and {len(self.events)} events"
            )
        if self.transitions and len(self.transitions) != len(self.events):
            raise ValueError("phases: give one transition per event (or none)")
        # one state flows through every phase (the joined solution has one q and one v array)
        shapes = {(s.nq, s.nv) for s in self.scenes}
        if len(shapes) != 1:
            raise ValueError(f"phases: every scene needs the same (nq, nv), got {sorted(shapes)}")

    @property
    def nq(self) -> int:
        return self.scenes[0].nq

    @property
    def nv(self) -> int:
        return self.scenes[0].nv
