"""``jaxbody simulate SOURCE``: integrate a model or example chunk by chunk and write the
trajectory (npz, CSV), a plot and an animation; the files are rewritten after each chunk, so an
interrupted or failed run keeps what it finished."""

import csv
import json
import math
import os
import pathlib
import sys
import time

import jax.numpy as jnp
import numpy as np

from .. import maggi
from ..simulation import RESULTS, explain_failure, simulate
from .arguments import (
    SOURCE_HELP,
    UsageError,
    add_scene_options,
    count,
    error_line,
    floats,
    one_line,
    positive,
    setup_jax,
)
from .plots import animate, plot_trajectory
from .scene_options import scene_from_options
from .sources import Source, initial_state, load

__all__ = ["add_parser", "run", "chunk_times", "TrajectoryFiles"]

def add_parser(sub):
    """The ``simulate`` sub-command and its options."""
    sim = sub.add_parser(
        "simulate",
        help="integrate a model or example; write npz/CSV, a plot and an animation",
        description=(
            "Integrate the equations of motion of SOURCE from t = 0 to --t1 with diffrax "
            "and write the trajectory. The scene is the model's own gravity, joint springs "
            "and dampers unless the scene options change them, plus the constant joint "
            "torques and body loads they add. Robot models start from --keyframe or qpos0 at rest, examples "
            "from the state `jaxbody examples` lists. The run is split into --chunks pieces; "
            "the files are rewritten after each, so an interrupted or failed run keeps what "
            "it finished."
        ),
    )
    sim.add_argument("source", metavar="SOURCE", help=SOURCE_HELP)
    sim.add_argument("--t1", type=positive(), default=1.0, help="final time in s (default 1)")
    sim.add_argument("--solver", default="tsit5",
                     help="diffrax solver preset, e.g. tsit5, dopri5, dopri8 (adaptive) or "
                          "rk4, euler (fixed step, need --dt); default tsit5")
    sim.add_argument("--rtol", type=positive(), default=1e-8, help="relative tolerance (default 1e-8)")
    sim.add_argument("--atol", type=positive(), default=1e-8, help="absolute tolerance (default 1e-8)")
    sim.add_argument("--dt", type=positive(), default=None,
                     help="step of a fixed-step solver; first trial step of an adaptive one")
    sim.add_argument("--saves", type=count(2), default=201,
                     help="number of evenly spaced saved times from 0 to t1 inclusive (default 201)")
    sim.add_argument("--keyframe", default=None, help="start from this keyframe of an MJCF model")
    sim.add_argument("--q0", type=floats, default=None, help="initial coordinates, comma separated")
    sim.add_argument("--v0", type=floats, default=None, help="initial velocities, comma separated")
    sim.add_argument("--project-initial", action="store_true",
                     help="put the initial state on the model's loop closures (positions by Newton's method, "
                          "velocities in the kinetic metric) instead of stopping when it violates them")
    sim.add_argument("--chunks", type=count(1), default=10,
                     help="integrate and write in this many pieces (default 10)")
    sim.add_argument("--max-steps", type=count(1), default=100_000,
                     help="solver step budget per chunk (default 100000)")
    sim.add_argument("--out", type=pathlib.Path, default=None,
                     help="trajectory as .npz (default outputs/simulate/<name>.npz when no other "
                          "output is asked for)")
    sim.add_argument("--csv", type=pathlib.Path, default=None, help="trajectory as CSV")
    sim.add_argument("--plot", type=pathlib.Path, default=None,
                     help="PNG of the coordinates, the energy and its drift against time")
    sim.add_argument("--animate", type=pathlib.Path, default=None,
                     help="GIF of the skeleton (body origins and joint points) moving")
    sim.add_argument("--frames", type=count(2), default=100,
                     help="at most this many animation frames (default 100)")
    sim.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_scene_options(sim, "integrate with")


def _simulate_chunk(system, q, v, ts, args, continued=False):
    """The one place the command calls the library's integrator.

    ``ts`` are the saved times of this chunk (``ts[0]`` its start). ``throw=False``: a failed
    solve comes back as a result code with ``inf`` after the failure, and the caller keeps
    the finite part. A ``continued`` chunk starts from the end of the previous one, whose
    velocities satisfy a scene's constraints only up to the integration error: they are
    projected back onto them (a correction of that order) instead of being rejected.
    """
    return simulate(system, q, v, ts[-1], t0=ts[0], solver=args.solver, rtol=args.rtol,
                    atol=args.atol, dt0=args.dt, saveat=ts, max_steps=args.max_steps,
                    throw=False, project_initial=continued)


class TrajectoryFiles:
    """npz and CSV files that grow chunk by chunk; each write leaves complete files.

    The npz is rewritten atomically (temporary file, then rename) after every chunk with
    everything so far, ``complete`` false until the last chunk; CSV rows are appended and
    flushed.
    """

    def __init__(self, npz, csv_path, src: Source, meta: dict):
        self.npz, self.csv_path, self.src, self.meta = npz, csv_path, src, dict(meta)
        self.t, self.q, self.v, self.energy = [], [], [], []
        self._csv = None

    def _open_csv(self):
        # Opened with the first rows, so arguments rejected before integrating leave no file.
        self.csv_path.parent.mkdir(parents=True, exist_ok=True)
        self._csv = open(self.csv_path, "w", newline="")
        self._writer = csv.writer(self._csv)
        src = self.src
        header = ["t", *(f"q:{s}" for s in src.q_labels), *(f"v:{s}" for s in src.v_labels)]
        self._writer.writerow(header + ["energy"])

    def append(self, t, q, v, energy, status):
        if self.csv_path is not None and self._csv is None:
            self._open_csv()
        self.t.append(t)
        self.q.append(q)
        self.v.append(v)
        self.energy.append(np.full(t.shape, np.nan) if energy is None else energy)
        if self._csv is not None:
            for row in zip(t, q, v, self.energy[-1]):
                self._writer.writerow([repr(float(row[0])), *map(_fmt, row[1]), *map(_fmt, row[2]),
                                       _fmt(row[3])])
            self._csv.flush()
        self.write_npz(status)

    def arrays(self):
        if not self.t:
            src = self.src
            return (np.zeros(0), np.zeros((0, src.system.nq)), np.zeros((0, src.system.nv)),
                    np.zeros(0))
        return tuple(np.concatenate(a) for a in (self.t, self.q, self.v, self.energy))

    def write_npz(self, status):
        if self.npz is None:
            return
        t, q, v, energy = self.arrays()
        self.npz.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.npz.with_name(self.npz.name + ".tmp.npz")
        np.savez(
            tmp, t=t, q=q, v=v, energy=energy,
            q_labels=np.array(self.src.q_labels, dtype=str),
            v_labels=np.array(self.src.v_labels, dtype=str),
            complete=np.array(status == "complete"), status=np.array(status),
            meta=np.array(json.dumps(self.meta)),
        )
        os.replace(tmp, self.npz)

    def close(self):
        if self._csv is not None:
            self._csv.close()
            self._csv = None


def _fmt(x):
    return repr(float(x))


def chunk_times(t1, n_save, n_chunks):
    """Saved times split into chunks that share their end points.

    Returns ``(ts, n)`` per chunk: every ``ts`` has the same length, so the solve compiles
    once; a shorter last chunk repeats its final time, and only its first ``n`` entries are
    kept.
    """
    ts = np.linspace(0.0, t1, n_save)
    intervals = n_save - 1
    step = max(1, math.ceil(intervals / min(n_chunks, intervals)))
    chunks = []
    for i in range(0, intervals, step):
        part = ts[i:min(i + step, intervals) + 1]
        chunks.append((np.pad(part, (0, step + 1 - len(part)), mode="edge"), len(part)))
    return chunks


def run(args) -> int:
    """``jaxbody simulate``: returns the exit status."""
    src = load(args.source, args.keyframe)
    jax = setup_jax()
    q0, v0 = initial_state(src, args)
    scene = scene_from_options(src, args)
    q0, v0, projected = _on_constraints(scene, q0, v0, args.project_initial)
    for line in src.ignored:
        print(f"jaxbody simulate: note: not modelled, ignored: {line}", file=sys.stderr)
    out = args.out
    if out is None and not (args.csv or args.plot or args.animate):
        out = pathlib.Path("outputs/simulate") / f"{src.name}.npz"
    meta = {
        "source": src.origin, "name": src.name, "start": src.start, "t1": args.t1,
        "solver": args.solver, "rtol": args.rtol, "atol": args.atol, "dt": args.dt,
        "saves": args.saves, "layout": "MuJoCo qpos/qvel" if src.kind == "model" else "example coordinates",
        "jax_version": jax.__version__, "effects": list(scene.effect_names),
    }
    files = TrajectoryFiles(out, args.csv, src, meta)
    chunks = chunk_times(args.t1, args.saves, args.chunks)
    progress = _progress_bar(args.t1, args.no_progress)
    q, v = q0, v0
    stats = {"num_accepted_steps": 0, "num_rejected_steps": 0}
    status, failure = "running", None
    balance, offset = [], 0.0  # E - E0 - work of the non-conservative effects, chunk by chunk
    start = time.perf_counter()
    try:
        for k, (ts, n) in enumerate(chunks):
            ts_j = jnp.asarray(ts, dtype=q0.dtype)
            try:
                sol = _simulate_chunk(scene, q, v, ts_j, args, continued=k > 0)
            except (ValueError, TypeError) as e:
                if k == 0:  # the integrator rejected the arguments before integrating
                    hint = " (give --dt)" if "dt0" in str(e) else ""
                    raise UsageError(one_line(e) + hint) from None
                raise
            t, qs, vs = np.asarray(sol.t)[:n], np.asarray(sol.q)[:n], np.asarray(sol.v)[:n]
            energy = None if sol.energy is None else np.asarray(sol.energy)[:n]
            for key in stats:
                stats[key] += int(sol.stats[key])
            ok = bool(sol.result == _successful())
            keep = np.isfinite(t) & np.all(np.isfinite(qs), axis=1) & np.all(np.isfinite(vs), axis=1)
            if k > 0:  # the first point repeats the end of the previous chunk
                keep[0] = False
            if not ok:
                keep &= np.cumprod(keep | (np.arange(len(t)) == 0)).astype(bool)
                failure = explain_failure(scene, sol, ts[0], ts[-1])
            is_last = k == len(chunks) - 1
            status = "failed" if not ok else ("complete" if is_last else "running")
            files.append(t[keep], qs[keep], vs[keep], None if energy is None else energy[keep], status)
            if sol.work and energy is not None:
                bal = offset + np.asarray(sol.energy_balance)[:n]
                balance.append(bal[keep])
                offset = float(bal[-1])
            progress.update(float(ts[-1] - ts[0]))
            if not ok:
                break
            q, v = sol.q[n - 1], sol.v[n - 1]
    except KeyboardInterrupt:
        status = "interrupted"
        files.write_npz(status)
        raise
    finally:
        progress.close()
        files.close()
    wall = time.perf_counter() - start

    t, qs, vs, energy = files.arrays()
    if args.plot is not None and len(t):
        plot_trajectory(args.plot, src, t, qs, energy, args)
    if args.animate is not None and len(t):
        animate(args.animate, src, t, qs, args.frames)

    print(f"jaxbody simulate: {src.name} ({src.origin}), nq = {src.system.nq}, nv = {src.system.nv}, "
          f"from {src.start}")
    own = ["gravity"] if scene.path == "system" and np.any(np.asarray(getattr(scene.system, "gravity", 0.0)) != 0) else []
    print(f"  effects         {', '.join(own + list(scene.effect_names)) or 'none'}")
    loops = [spec.label for spec in getattr(src.system, "loops", ())]
    if loops and scene.constraints is not None:
        print(f"  constraints     loop closures {', '.join(loops)} (Maggi equations)")
    if projected:
        print(f"  initial state   {projected}")
    print(f"  integrated      t = 0 .. {t[-1] if len(t) else 0:g} s of {args.t1:g} s with {args.solver}, "
          f"rtol={args.rtol:g}, atol={args.atol:g}" + (f", dt={args.dt:g}" if args.dt else "")
          + f", in {len(chunks)} chunks")
    print(f"  solver          {sol.solver} ({sol.solver_reason})")
    print(f"  steps           accepted {stats['num_accepted_steps']}, rejected {stats['num_rejected_steps']}")
    if len(t) and np.all(np.isfinite(energy)):
        e0 = energy[0]
        drift = np.max(np.abs(energy - e0)) / max(abs(e0), np.finfo(float).tiny)
        print(f"  energy          E0 = {e0:.12g}; max|E-E0|/|E0| = {drift:.3e}")
        if balance:
            bal = np.max(np.abs(np.concatenate(balance))) / max(abs(e0), np.finfo(float).tiny)
            print(f"  energy balance  max|E-E0-W|/|E0| = {bal:.3e} (W: work of the non-conservative effects)")
    print(f"  wall time       {wall:.2f} s incl. compile")
    for path in (out, args.csv, args.plot, args.animate):
        if path is not None and path.exists():
            print(f"wrote {path}")
    if failure is not None:
        error_line("simulate", f"the solver failed after t = {t[-1] if len(t) else 0:g} s: {failure}; "
                               f"the {len(t)} saved states before it were written")
        return 1
    return 0


def _on_constraints(scene, q0, v0, project):
    """``(q0, v0, note)``: the initial state checked against the scene's constraints (positions
    and velocities), or put on them with ``--project-initial`` (``note`` says by how much)."""
    cs = scene.constraints
    if not isinstance(cs, maggi.ConstrainedSystem) or cs.n_constraint == 0:
        return q0, v0, ""
    try:
        q, v, dv = maggi.initial_state(cs, q0, v0, 0.0, project_initial=project, check_positions=True)
    except ValueError as e:
        raise UsageError(f"{one_line(e)} (or pass --project-initial)".replace(" or pass project_initial=True", "")) from None
    if not project:
        return q0, v0, ""
    dq = float(np.max(np.abs(np.asarray(q) - np.asarray(q0)), initial=0.0))
    return q, v, (f"projected onto the constraints (--project-initial): max|Δq| = {dq:.3g}, "
                  f"max|Δv| = {float(np.max(np.abs(np.asarray(dv)), initial=0.0)):.3g}")


def _successful():
    return RESULTS.successful


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _progress_bar(total, disabled):
    if disabled:
        return _NoBar()
    from tqdm import tqdm  # optional: only when a progress bar is shown

    # delay: arguments the integrator rejects at once leave no bar behind their error line
    return tqdm(total=total, unit="s", unit_scale=False, file=sys.stderr, desc="simulated time", delay=0.5,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.3g}/{total:.3g} s [{elapsed}<{remaining}]")


