"""Phased runs: scenes one after the other, switched by events, joined into one solution.

Each phase is one scene's solve (:func:`jaxbody.simulation.solve.simulate_scene`) from where
the previous one stopped; at a switch the optional transition maps the state and a scene with
Maggi constraints receives velocities projected onto them (an impulsive constraint in the
kinetic metric). The phases' solutions are joined on the common saved times.
"""

import diffrax
import equinox as eqx
import jax.numpy as jnp

from .. import maggi
from ..scene import Phases
from .._util import is_concrete
from .checks import save_times, scene_constraints
from .partitioning import MAX_RECORDED_REPARTITIONS
from .solution import RESULTS, Solution, balance_scale, energy_balance, succeeded
from .solve import simulate_scene

__all__ = ["simulate_phases"]


def simulate_phases(phases: Phases, q0, v0, t1, *, t0, saveat, n_save, track_work, project_initial, throw, **kw):
    """Run phase after phase and join them into one :class:`Solution`.

    Phase ``i`` runs from the end of phase ``i − 1`` until the first root of ``events[i]``
    (the last one to ``t1``). At a switch, ``transitions[i]`` maps the state when given; then,
    when the next scene has Maggi constraints, its velocities are projected onto them as an
    impulsive constraint (:func:`jaxbody.maggi.switch_constraints`: ``x⁺ = A(AᵀDA)⁻¹AᵀD·x⁻``,
    a looser set keeps the velocity). The joined solution carries:

    * ``q``, ``v``, ``energy`` (each saved time from its own phase's scene; the saved time at a
      switch belongs to the phase that ends there);
    * ``work``: the work of every non-conservative effect of any phase, integrated as one state
      vector carried across the switches (an effect absent from a phase adds nothing there),
      plus ``work["switches"]``: the energy change at the switches up to each time, so that
      ``energy_balance = E(t) − E(t0) − Σ work(t)`` closes across the whole run and
      ``energy_drift`` measures only integration error;
    * ``stats``: step counts summed over phases, ``"phase"`` (the phase index of each saved
      time) and per switch ``"switch_time"`` (NaN when its event never triggered),
      ``"switch_occurred"``, ``"switch_energy_jump"`` ``E⁺ − E⁻`` (an impulsive constraint
      loses energy; a phase with other conservative effects measures energy differently) and
      ``"switch_energy_lost"`` ``½(x⁻ − x⁺)ᵀD(x⁻ − x⁺) ≥ 0`` of the velocity projection (zero
      when there is none); ``"num_repartitions"``, the coordinate re-partitions made inside
      the phases (the choice made at a switch is not counted);
    * ``repartition_times``: the times of those re-partitions, all phases' in time order, in
      the first ``MAX_RECORDED_REPARTITIONS`` slots with NaN in the unused ones (as one solve
      records them), or ``None`` when no phase has automatically partitioned constraints. A
      phase that never starts (it follows an event that did not trigger or a failed phase)
      adds none;
    * ``reactions`` and ``constraint_drift`` of every phase with constraints, padded with NaN
      to the largest row count over the phases (``(n_save, s_max)``; a phase with ``s`` rows
      fills columns ``0..s − 1``); ``dict(layout)["phase_constraint_names"]`` names each
      phase's rows, and ``"constraint_names"`` is kept when every phase has the same rows.
    """
    dtype = jnp.result_type(float)
    t0 = jnp.asarray(t0, dtype)
    t1 = jnp.asarray(t1, dtype)
    if saveat is None:
        ts = save_times(t0, t1, n_save, dtype)
    elif isinstance(saveat, diffrax.SaveAt):
        raise ValueError("simulate: phases save at times; pass saveat as an array or n_save")
    else:
        ts = jnp.asarray(saveat, dtype)
    scenes = list(phases.scenes)
    # one energy balance over the whole run needs an energy function in every phase
    energetic = track_work and all(sc.has_energy for sc in scenes)
    work_names: tuple[str, ...] = ()
    if energetic:
        # one work vector for the whole run: the union of the phases' effects, in order of
        # first appearance, so each effect's work continues across the switches
        for sc in scenes:
            work_names += tuple(n for n in sc.work_names if n not in work_names)
    q, v, start = jnp.asarray(q0, dtype), jnp.asarray(v0, dtype), t0
    w = jnp.zeros((len(work_names),), dtype) if work_names else None
    parts, ends, switches = [], [], []
    for i, sc in enumerate(scenes):
        last = i == len(scenes) - 1
        # every phase saves at all the run's times (clipped into its own span) so that the
        # phases' arrays have one shape and are joined by a select; only phase 0 checks v0
        # against the constraints: later phases receive projected velocities
        sol, w = simulate_scene(
            sc, q, v, t1, t0=start, saveat=jnp.clip(ts, start, t1), n_save=None,
            event=None if last else phases.events[i], dense=False, throw=throw, track_work=energetic,
            project_initial=project_initial, work_names=work_names, work0=w, check_constraints=i == 0,
            phase_start=i > 0, **kw,
        )
        parts.append(sol)
        if last:
            ends.append(t1)
            break
        hit = sol.event_occurred
        # an event that never triggered ends its phase at t1: later phases start and end there
        ends.append(jnp.where(hit, sol.t_final, t1))
        t_sw, q_minus, v_minus = sol.t_final, sol.q_final, sol.v_final
        q, v = q_minus, v_minus
        if phases.transitions:
            q, v = phases.transitions[i](t_sw, q, v)
        # the next scene may be re-partitioned at the switch state: later phases use that one
        scenes[i + 1], v, lost = _switch_into(scenes[i + 1], t_sw, q, v)
        jump = _energy_jump(sc, scenes[i + 1], hit, q_minus, v_minus, q, v) if energetic else None
        switches.append((hit, jnp.where(hit, t_sw, jnp.nan), jump, jnp.where(hit, lost, 0.0)))
        start = t_sw
    return _join_phases(ts, parts, ends, switches, work_names, energetic)


# compiled (once per pair of scene structures): eagerly each switch would be op by op
@eqx.filter_jit
def _energy_jump(before, after, hit, q_minus, v_minus, q_plus, v_plus):
    """``E⁺ − E⁻`` at a switch (zero when its event did not trigger)."""
    return jnp.where(hit, after.total_energy(q_plus, v_plus) - before.total_energy(q_minus, v_minus), 0.0)


@eqx.filter_jit
def _join_phases(ts, parts, ends, switches, work_names, energetic):
    """One :class:`Solution` from the phases' solutions (see :func:`simulate_phases`)."""
    dtype = ts.dtype
    # the saved time t belongs to the first phase whose end is at or after t
    phase = sum(((ts > end).astype(jnp.int32) for end in ends[:-1]), jnp.zeros(ts.shape, jnp.int32))

    def join(arrays):
        # a select per phase, not a gather: the phases' saved arrays all have the full length
        out = arrays[-1]
        for k in range(len(arrays) - 2, -1, -1):
            mine = (phase == k).reshape(phase.shape + (1,) * (out.ndim - 1))
            out = jnp.where(mine, arrays[k], out)
        return out

    q_out = join([p.q for p in parts])
    v_out = join([p.v for p in parts])
    energy = work = drift = energy0 = None
    if energetic:
        energy = join([p.energy for p in parts])
        work = {name: join([p.work[name] for p in parts]) for name in work_names}
        if switches:
            # the energy a switch changes is booked as work from the switch on, so the balance
            # closes while each jump stays visible in stats
            work["switches"] = sum((jnp.where(ts > end, jump, 0.0) for end, (_, _, jump, _) in zip(ends, switches)),
                                   jnp.zeros(ts.shape, dtype))
        finite = jnp.isfinite(energy)
        energy0 = parts[0].energy0
        drift = jnp.max(jnp.where(finite, jnp.abs(energy_balance(energy, work, energy0) / balance_scale(energy, energy0)), 0.0))
    reactions = cdrift = None
    rows = [None if p.reactions is None else p.reactions.shape[-1] for p in parts]
    if any(r is not None for r in rows):
        s_max = max(r for r in rows if r is not None)

        def padded(x):
            if x is None:
                return jnp.full(ts.shape + (s_max,), jnp.nan, dtype)
            return jnp.concatenate([x, jnp.full(x.shape[:-1] + (s_max - x.shape[-1],), jnp.nan, x.dtype)], axis=-1)

        reactions = join([padded(p.reactions) for p in parts])
        cdrift = {
            key: join([padded(None if p.constraint_drift is None else p.constraint_drift[key]) for p in parts])
            for key in ("position", "velocity")
        }
    # the first phase that failed decides the run's result (later phases started from its end)
    result = parts[0].result
    for p in parts[1:]:
        result = RESULTS.where(succeeded(result), p.result, result)
    stats = {k: sum(p.stats[k] for p in parts) for k in ("num_steps", "num_accepted_steps", "num_rejected_steps")}
    stats["phase"] = phase
    stats["num_repartitions"], repartition_times = _joined_repartitions(parts, ends)
    if "v0_correction" in parts[0].stats:
        stats["v0_correction"] = parts[0].stats["v0_correction"]
    if switches:
        stats["switch_occurred"] = jnp.stack([s[0] for s in switches])
        stats["switch_time"] = jnp.stack([s[1] for s in switches])
        if energetic:
            stats["switch_energy_jump"] = jnp.stack([s[2] for s in switches])
        stats["switch_energy_lost"] = jnp.stack([s[3] for s in switches]).astype(dtype)
    final = parts[-1]
    return Solution(
        t=ts, q=q_out, v=v_out, energy=energy, work=work or {}, energy_drift=drift, constraint_drift=cdrift,
        reactions=reactions, stats=stats, result=result, t_final=final.t_final, q_final=final.q_final,
        v_final=final.v_final, layout=_phases_layout(parts), energy0=energy0, repartition_times=repartition_times,
    )


def _joined_repartitions(parts, ends):
    """``(num_repartitions, repartition_times)`` of the joined run: the phases' counts summed and
    their recorded times concatenated in phase order, the recorded ones moved to the front and
    cut to ``MAX_RECORDED_REPARTITIONS`` (``None`` when no phase records times)."""
    t1 = ends[-1]
    count = jnp.zeros((), jnp.int32)
    recorded = []
    # a phase takes part in the joined run only when every earlier phase ended before t1 (an
    # event that never triggered, or a failed phase, leaves the later phases an empty span)
    live = jnp.asarray(True)
    for k, p in enumerate(parts):
        if k > 0:
            live = live & (ends[k - 1] < t1)
        count = count + jnp.where(live, p.stats["num_repartitions"], 0).astype(jnp.int32)
        if p.repartition_times is not None:
            recorded.append(jnp.where(live, p.repartition_times, jnp.nan))
    if not recorded:
        return count, None
    times = jnp.concatenate(recorded)
    # a stable sort on "unused" keeps the recorded times in their (time) order
    order = jnp.argsort(jnp.isnan(times), stable=True)
    return count, times[order][:MAX_RECORDED_REPARTITIONS]


def _switch_into(scene, t, q, v):
    """Velocities entering ``scene`` at a switch: projected onto its Maggi constraints in the
    kinetic metric (impulsive constraint). Returns ``(scene, v⁺, energy lost)``; ``scene`` is
    re-partitioned at the switch state when it chooses its independent quasi-velocities
    automatically and the state is concrete."""
    cs = scene_constraints(scene)
    if cs is None or cs.n_constraint == 0:
        return scene, v, jnp.zeros((), v.dtype)
    # re-choosing the partition is a host-side decision (a pivoted QR on concrete values); a
    # traced switch keeps the partition the constraints were built with
    if cs.epsilon is None and is_concrete(cs, t, q, v):
        cs = cs.repartition(q, v, t)
        scene = scene.with_constraints(cs)
    report = maggi.switch_constraints(cs, t, q, v)
    return scene, report.x_after.astype(v.dtype), report.energy_lost


def _phases_layout(parts) -> tuple:
    """The joined layout: the last phase's, each phase's constraint rows named, and the common
    ``"constraint_names"`` only when every phase has the same rows (else columns differ by phase)."""
    lay = dict(parts[-1].layout)
    names = [dict(p.layout).get("constraint_names", ()) for p in parts]
    lay.pop("constraint_names", None)
    if any(names):
        lay["phase_constraint_names"] = tuple(tuple(n) for n in names)
        if all(n == names[0] for n in names):
            lay["constraint_names"] = tuple(names[0])
    return tuple(sorted(lay.items()))
