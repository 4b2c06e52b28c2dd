"""What a solve returns: the result codes, the :class:`Solution` pytree and its files.

A :class:`Solution` is a pytree, so a ``vmap`` of :func:`jaxbody.simulate` gives one with a
leading batch axis on every array and ``grad`` reaches its fields. Its energy bookkeeping
(:func:`energy_balance`) is shared by single solves and by phased runs, which join several
solutions into one.
"""

import json
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._types import Array, ArrayLike, Float
from .._util import is_concrete
from ..joints import JOINT_KIND_NAMES
from ..model import Model
from ..scene import Scene

__all__ = [
    "RESULTS",
    "SimulationError",
    "Solution",
    "ResultCodes",
    "load_solution",
    "result_code",
    "result_from_code",
    "SUCCESSES",
    "SUCCESS_CODES",
    "succeeded",
    "energy_balance",
    "balance_scale",
    "solution_layout",
    "ran_by",
]


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """diffrax's result codes plus the boundary check of :func:`simulate`."""

    # results of checks that jaxbody adds around diffrax's loop, so that a batch member reports
    # them through the same result field as the solver's own failures
    invalid_input = (
        "The initial state or a parameter is NaN/inf or invalid (checked before the solve: finite values, "
        "non-negative masses, initial velocities admissible for the scene's constraints)."
    )
    partition_degraded = (
        "The coordinate partition of the constraints degraded (quality below partition_tolerance times the "
        "best partition's) and re-partitioning is off (jaxbody.maggi.constrain(..., repartition=False))."
    )
    singular_coordinates = (
        "A step left the scene's coordinate chart (jaxbody.CoordinateChart): its coordinates degenerate there "
        "(e.g. Euler angles at their singular set), so the solve stopped at the last state they describe; "
        "continue in another chart (an Event that switches coordinates) or with another formulation."
    )
    singular_parametrisation = (
        "The constraints cannot be solved for the velocities at this state (jaxbody.maggi.MaggiResult."
        "singular_parametrisation): redundant constraints (a dead point of a linkage), or user characteristics "
        "epsilon that are singular here."
    )


class SimulationError(RuntimeError):
    """A solve that did not finish (raised with ``throw=True``): says when, where and why."""


def result_code(result) -> ArrayLike:
    """The integer code of a :class:`RESULTS` item (batched like the item).

    An equinox enumeration item is a pytree whose one leaf is its code; reading it through the
    pytree keeps to equinox's public interface (files and host callbacks need plain integers).
    """
    (code,) = jax.tree.leaves(result)
    return code


class ResultCodes(type(RESULTS.successful)):
    """The :class:`RESULTS` item of a solve, as :attr:`Solution.result` holds it: compared like
    any item (``sol.result == RESULTS.successful``, an array per member of a batch) and, for a
    batch, indexed per member: ``sol.result[i]`` is member ``i``'s item (``sol.result[1] ==
    RESULTS.invalid_input``), ``len`` counts the members and iterating gives them in order."""

    def _members(self):
        code = jnp.asarray(result_code(self))
        if code.ndim == 0:
            raise TypeError("a single solve's result has no members: compare it (sol.result == RESULTS.successful) "
                            "or index a batch's (sol.result[i] of a solution from jax.vmap or jaxbody.simulate_batch)")
        return code

    def __getitem__(self, i) -> "ResultCodes":
        code = self._members()
        if isinstance(i, (int, np.integer)) and not -len(code) <= i < len(code):
            raise IndexError(f"Solution.result: no batch member {i}; the batch has {len(code)} members")
        return jax.tree.unflatten(jax.tree.structure(self), [code[i]])

    def __len__(self) -> int:
        return int(self._members().shape[0])

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def __bool__(self) -> bool:
        # an object's truth, as the item had before it had a length (a single solve has none)
        return True


def _result_codes(item):
    """``item`` (a :class:`RESULTS` item) as :class:`ResultCodes` (the field converter of
    :attr:`Solution.result`); anything else (a transformation's placeholder) as it is."""
    if isinstance(item, ResultCodes) or not isinstance(item, type(RESULTS.successful)):
        return item
    return jax.tree.unflatten(jax.tree.structure(_RESULT_CODES), jax.tree.leaves(item))


#: The outcomes of a solve that succeeded: it reached ``t1``, or a terminating event stopped it
#: where it was asked to.
SUCCESSES = (RESULTS.successful, RESULTS.event_occurred)
#: Their integer codes (:func:`result_code`), for checks made in NumPy on the host.
SUCCESS_CODES = tuple(int(np.asarray(result_code(item))) for item in SUCCESSES)


def succeeded(result) -> Array:
    """Boolean (per member of a batch): ``result``, a :class:`RESULTS` item, is one of :data:`SUCCESSES`."""
    ok = result == SUCCESSES[0]
    for item in SUCCESSES[1:]:
        ok = ok | (result == item)
    return ok


def result_from_code(code) -> RESULTS:
    """The :class:`RESULTS` item of an integer code (the inverse of :func:`result_code`). No JAX
    operation runs: a host callback that reports a failure calls it too."""
    return jax.tree.unflatten(jax.tree.structure(RESULTS.successful), [code])


# the pytree structure of a ResultCodes item (its code, its enumeration), built once
_RESULT_CODES = ResultCodes(np.array(0, np.int32), RESULTS)


class Solution(eqx.Module):
    """Result of :func:`simulate` (a pytree: batches and gradients pass through).

    Attributes:
        t: saved times ``(n_save,)``.
        q: coordinates at the saved times ``(n_save, nq)`` (MuJoCo ``qpos`` layout for models).
        v: velocities ``(n_save, nv)``.
        energy: total mechanical energy (kinetic + potentials of the declared conservative
            effects) ``(n_save,)``; ``None`` when the system has none.
        work: work done since ``t0`` by each non-conservative effect, ``{name: (n_save,)}``
            (``"actuation"``, ``"dampers"`` (negative: minus the dissipation), ``"loads"``,
            ``"support"``; for a :class:`jaxbody.Phases` run also ``"switches"``, the energy
            change at the switches up to each time); empty when there are none.
        energy_drift: ``max_t |E(t) − E(t0) − Σ work(t)| / max(|E(t0)|, tiny)`` over the saved
            times: how far the energy balance is from closing (a check of the integration,
            meaningful with damping and actuation too); ``None`` without energy. ``E(t0)`` is
            ``energy0``, so the drift is measured from the start whatever the saved times are
            (with ``SaveAt(t1=True)`` alone, it is the balance at ``t1``).
        constraint_drift: constraint residuals at the saved times, ``{"position": (n_save, s),
            "velocity": (n_save, s)}`` (position residuals ``φ(t, q)`` of the holonomic rows, zero
            on non-holonomic rows; velocity residuals ``f*(t, q, v)`` of every row), or ``None``
            without constraints.
        reactions: constraint reactions ``Λ`` at the saved times ``(n_save, s)``, one column per
            constraint row (``layout`` lists their names under ``"constraint_names"``; forces in
            newtons for the point constraints of :mod:`jaxbody.constraints`), or ``None``. For a
            :class:`jaxbody.Phases` run, ``s`` is the largest row count over the phases and a
            phase with fewer rows is padded with NaN (``layout["phase_constraint_names"]`` names
            each phase's columns); ``constraint_drift`` likewise.
        stats: ``num_steps``, ``num_accepted_steps``, ``num_rejected_steps``; ``v0_correction``
            ``(nv,)`` when ``project_initial=True`` projected ``v0`` onto the constraints; for a
            :class:`jaxbody.Phases` run also ``phase`` ``(n_save,)`` and the switch reports
            ``switch_time``, ``switch_occurred``, ``switch_energy_jump``, ``switch_energy_lost``
            ``(n_switch,)`` (module docstring, "Phases"); ``num_repartitions``
            (changes of the constraints' coordinate partition, see
            :class:`jaxbody.simulation.PartitionSolver`; ``0`` without constraints).
        result: a :class:`RESULTS` code (``successful``; ``event_occurred`` when an event ended
            the solve; a failure code otherwise), one per member of a batch: ``sol.result[i]``
            (or ``sol[i].result``) is member ``i``'s (:class:`ResultCodes`: indexed, counted by
            ``len`` and iterated per member), :attr:`failed` the mask of failed members.
        t_final, q_final, v_final: where the solve stopped (``t1``, the event time, or the
            last step of a failed solve: with ``throw=False`` these are the failure's time and
            state, the ones a ``throw=True`` error message quotes). A member that failed the
            boundary check (``invalid_input``) never started: ``t_final = t0`` and its states,
            saved and final, are NaN.

    After a terminating event, the saved times past the event are not reached: diffrax fills
    their entries of ``t`` (and of ``q``, ``v``) with ``inf``, and energies and residuals there
    are NaN; the state at the event is ``(t_final, q_final, v_final)``. Keep the saved entries
    with ``np.isfinite(sol.t)``.

    ``kernel`` and ``solver`` say what ran (the forward-dynamics kernel, or the scene's path when
    no kernel runs directly, and the solver's name); ``solver_reason`` why that solver was chosen
    when it was chosen automatically (empty otherwise).
        layout: static description of ``q``/``v`` (names, joint kinds, addresses) for replay.
        repartition_times: times at which the coordinate partition was re-chosen (the first
            ``jaxbody.simulation.partitioning.MAX_RECORDED_REPARTITIONS``, NaN in unused
            slots), or ``None`` without an automatically partitioned constraint set. For a
            :class:`jaxbody.Phases` run, those of all phases in time order in the same slots
            (``stats["num_repartitions"]`` their total; the choice made at a switch is not
            counted).
        solver, solver_reason: the solver preset that ran (a diffrax solver's class name when one
            was given) and why (what ``solver="auto"`` read from the scene, or ``"asked for"``).
        energy0: total energy ``E(t0)`` of the initial state (after ``project_initial``), the
            reference of ``energy_balance``, ``energy_error`` and ``energy_drift``; ``None``
            without energy.
    """

    t: Float[Array, " n_save"]
    q: Float[Array, "n_save nq"]
    v: Float[Array, "n_save nv"]
    energy: Float[Array, " n_save"] | None
    work: dict
    energy_drift: Float[Array, ""] | None
    constraint_drift: Any
    reactions: Any
    stats: dict[str, Array]
    result: RESULTS = eqx.field(converter=_result_codes)
    t_final: Float[Array, ""]
    q_final: Float[Array, " nq"]
    v_final: Float[Array, " nv"]
    # static: names and addresses are Python strings and ints shared by every member of a
    # batch; as leaves they would be traced or batched
    layout: tuple = eqx.field(static=True, default=())
    # diffrax's dense output (dense=True only): a pytree, so it batches like the arrays
    interpolation: Any = None
    repartition_times: Any = None
    energy0: Float[Array, ""] | None = None
    # static: the kernel that ran, the solver preset that ran and why ``solver="auto"`` chose it (or "asked for")
    kernel: str = eqx.field(static=True, default="")
    solver: str = eqx.field(static=True, default="")
    solver_reason: str = eqx.field(static=True, default="")

    def evaluate(self, t: ArrayLike) -> tuple[Float[Array, " nq"], Float[Array, " nv"]]:
        """``(q, v)`` at any time ``t`` in ``[t0, t_final]`` from the solver's dense output
        (needs ``simulate(..., dense=True)``)."""
        if self.interpolation is None:
            raise ValueError("Solution.evaluate needs simulate(..., dense=True)")
        t0, tf = self.interpolation.t0, self.t_final
        if is_concrete(t, t0, tf) and np.ndim(tf) == 0:
            # outside the solved interval the interpolation has nothing to give but NaN
            ta, lo, hi = np.asarray(t), float(np.asarray(t0)), float(np.asarray(tf))
            out = ta[(ta < lo) | (ta > hi) | ~np.isfinite(ta)] if ta.ndim else (
                ta if not lo <= float(ta) <= hi else np.zeros(0))
            if np.size(out):
                raise ValueError(
                    f"Solution.evaluate: t = {float(np.ravel(out)[0]):g} lies outside [t0, t_final] = [{lo:g}, {hi:g}], "
                    "the interval the solve covered"
                )
        y = self.interpolation.evaluate(t)
        return y[0], y[1]

    @property
    def batch_size(self) -> int | None:
        """The number of members of a batched solution (``None`` for a single solve)."""
        return None if jnp.ndim(self.t) == 1 else int(jnp.shape(self.t)[0])

    def __len__(self) -> int:
        n = self.batch_size
        if n is None:
            raise TypeError("a single solve's Solution has no length; len() counts the members of a batch")
        return n

    def __getitem__(self, i) -> "Solution":
        """Member ``i`` of a batched solution (from ``jax.vmap`` or :func:`jaxbody.simulate_batch`)
        as a :class:`Solution` of its own: its trajectory, result and final state."""
        n = self.batch_size
        if n is None:
            raise TypeError("Solution is not batched: index a solution from jax.vmap or jaxbody.simulate_batch")
        if isinstance(i, (int, np.integer)):
            if not -n <= i < n:
                raise IndexError(f"Solution: no batch member {i}; the batch has {n} members")
            i = int(i) % n
        return jax.tree.map(lambda x: x[i], self)

    @property
    def failed(self) -> jax.Array:
        """Boolean mask of the members that failed (the negation of :attr:`success`)."""
        return ~self.success

    @property
    def success(self) -> jax.Array:
        """Boolean array: the solve reached ``t1`` or a terminating event (per member when batched)."""
        return succeeded(self.result)

    @property
    def event_occurred(self) -> jax.Array:
        return self.result == RESULTS.event_occurred

    @property
    def dissipation(self) -> Float[Array, "*batch n_save"] | None:
        """Energy dissipated by the dampers since ``t0`` (``−work["dampers"]``)."""
        return None if "dampers" not in self.work else -self.work["dampers"]

    @property
    def energy_balance(self) -> Float[Array, "*batch n_save"] | None:
        """``E(t) − E(t0) − Σ work(t)`` (zero up to integration error)."""
        if self.energy is None:
            return None
        return energy_balance(self.energy, self.work, self.energy0)

    @property
    def energy_error(self) -> Float[Array, "*batch n_save"] | None:
        """Signed relative balance error ``(E − E0 − Σ work) / max(|E0|, tiny)`` per saved time."""
        if self.energy is None:
            return None
        return energy_balance(self.energy, self.work, self.energy0) / balance_scale(self.energy, self.energy0)

    # ------------------------------------------------------------------ files
    def _layout_dict(self):
        return dict(self.layout)

    def save(self, path) -> None:
        """Write the solution to an ``.npz`` file (arrays plus the q/v layout as JSON)."""
        arrays = {
            "t": np.asarray(self.t),
            "q": np.asarray(self.q),
            "v": np.asarray(self.v),
            # the integer code: an enumeration item does not survive np.savez, its code does
            "result": np.asarray(result_code(self.result)),
            "t_final": np.asarray(self.t_final),
            "q_final": np.asarray(self.q_final),
            "v_final": np.asarray(self.v_final),
            # JSON, so that a file needs no pickle (np.load refuses pickles by default)
            "layout": np.asarray(json.dumps(self._layout_dict())),
        }
        if self.energy is not None:
            arrays["energy"] = np.asarray(self.energy)
            arrays["energy_drift"] = np.asarray(self.energy_drift)
            if self.energy0 is not None:
                arrays["energy0"] = np.asarray(self.energy0)
        # dictionaries flatten to "group/key" names: the keys (effect names) vary by scene
        for k, w in self.work.items():
            arrays[f"work/{k}"] = np.asarray(w)
        for k, s in self.stats.items():
            arrays[f"stats/{k}"] = np.asarray(s)
        if self.constraint_drift is not None:
            for k, r in self.constraint_drift.items():
                arrays[f"constraint_drift/{k}"] = np.asarray(r)
        if self.reactions is not None:
            arrays["reactions"] = np.asarray(self.reactions)
        if self.repartition_times is not None:
            arrays["repartition_times"] = np.asarray(self.repartition_times)
        # through a file handle, so that np.savez does not append .npz to the path given
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)

    def to_csv(self, path) -> None:
        """Write ``t``, the coordinates, velocities, energy and work as CSV columns (one row per time).

        The header names the columns as ``jaxbody simulate --csv`` does: ``t``, then ``q:<joint>``
        for each coordinate and ``v:<joint>`` for each velocity in the MuJoCo ``qpos``/``qvel``
        layout (a ball or free joint's entries as ``q:<joint>.qw`` ... and ``v:<joint>.wx`` ...;
        ``q:q0``, ``v:v0`` ... for systems without joint names), then ``energy`` and ``work_<effect>``.
        """
        if self.batch_size is not None:
            raise ValueError(
                f"Solution.to_csv writes one trajectory; this solution holds a batch of {self.batch_size} members: "
                "write each with sol[i].to_csv(path)"
            )
        lay = self._layout_dict()
        nq, nv = self.q.shape[-1], self.v.shape[-1]
        if "joint_names" in lay and "joint_kinds" in lay:
            q_parts = {"ball": ("qw", "qx", "qy", "qz"), "free": ("x", "y", "z", "qw", "qx", "qy", "qz")}
            v_parts = {"ball": ("wx", "wy", "wz"), "free": ("vx", "vy", "vz", "wx", "wy", "wz")}
            qn, vn = [], []
            for name, kind in zip(lay["joint_names"], lay["joint_kinds"]):
                qn += [f"{name}.{c}" for c in q_parts[kind]] if kind in q_parts else [name]
                vn += [f"{name}.{c}" for c in v_parts[kind]] if kind in v_parts else [name]
        else:
            qn, vn = [], []
        # a layout that does not match the arrays (another model's) falls back to plain indices
        if len(qn) != nq or len(vn) != nv:
            qn, vn = [f"q{i}" for i in range(nq)], [f"v{i}" for i in range(nv)]
        cols = [np.asarray(self.t)[:, None], np.asarray(self.q), np.asarray(self.v)]
        names = ["t", *(f"q:{n}" for n in qn), *(f"v:{n}" for n in vn)]
        if self.energy is not None:
            cols.append(np.asarray(self.energy)[:, None])
            names.append("energy")
        for k, w in self.work.items():
            cols.append(np.asarray(w)[:, None])
            names.append(f"work_{k}")
        # comments="": the header is a plain first line of column names, as CSV readers expect
        np.savetxt(path, np.concatenate(cols, axis=1), delimiter=",", header=",".join(names), comments="")


def load_solution(path) -> Solution:
    """Read a solution written by :meth:`Solution.save` (``.npz``) or :meth:`Solution.to_csv`.

    A CSV file holds the trajectory only: ``t``, ``q``, ``v``, the energy and the work; the
    solution read from it has ``t_final``, ``q_final``, ``v_final`` from its last row, no
    statistics, and ``result`` ``successful`` (``nonfinite`` when the last row is not finite).

    Raises:
        FileNotFoundError: no such file.
        ValueError: a file that is neither a solution's ``.npz`` nor its CSV, naming the file.
    """
    with open(path, "rb") as fh:
        head = fh.read(4)
    # .npz files are zip archives; anything else is read as the CSV of Solution.to_csv
    if head[:2] != b"PK":
        return _load_csv(path)
    with np.load(path) as data:
        d = {k: data[k] for k in data.files}
    missing = [k for k in ("t", "q", "v", "result", "t_final", "q_final", "v_final", "layout") if k not in d]
    if missing:
        raise ValueError(f"load_solution: {str(path)!r} is not a jaxbody solution file (Solution.save): it lacks {missing}")
    work = {k[5:]: jnp.asarray(v) for k, v in d.items() if k.startswith("work/")}
    stats = {k[6:]: jnp.asarray(v) for k, v in d.items() if k.startswith("stats/")}
    layout = json.loads(str(d["layout"]))
    # older files have no energy0 (energy_balance then starts from the first saved time)
    result = result_from_code(jnp.asarray(d["result"]))
    return Solution(
        t=jnp.asarray(d["t"]),
        q=jnp.asarray(d["q"]),
        v=jnp.asarray(d["v"]),
        energy=jnp.asarray(d["energy"]) if "energy" in d else None,
        work=work,
        energy_drift=jnp.asarray(d["energy_drift"]) if "energy_drift" in d else None,
        energy0=jnp.asarray(d["energy0"]) if "energy0" in d else None,
        constraint_drift={k[17:]: jnp.asarray(v) for k, v in d.items() if k.startswith("constraint_drift/")} or None,
        reactions=jnp.asarray(d["reactions"]) if "reactions" in d else None,
        stats=stats,
        result=result,
        t_final=jnp.asarray(d["t_final"]),
        q_final=jnp.asarray(d["q_final"]),
        v_final=jnp.asarray(d["v_final"]),
        # the layout is a static field: hashable tuples, in the sorted order solutions are built with
        layout=tuple(sorted((k, _tuples(v)) for k, v in layout.items())),
        repartition_times=jnp.asarray(d["repartition_times"]) if "repartition_times" in d else None,
    )


def _load_csv(path) -> Solution:
    """The :class:`Solution` of a CSV written by :meth:`Solution.to_csv`."""
    with open(path) as fh:
        names = fh.readline().strip().split(",")
    qi = [i for i, n in enumerate(names) if n.startswith("q:")]
    vi = [i for i, n in enumerate(names) if n.startswith("v:")]
    if not names or names[0] != "t" or not qi or not vi:
        raise ValueError(
            f"load_solution: {str(path)!r} is not a Solution.to_csv file: its first line must name the column "
            f"'t' and then 'q:...' and 'v:...' columns, got {names[:6]}"
        )
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if data.shape[1] != len(names):
        raise ValueError(f"load_solution: {str(path)!r}: {data.shape[1]} values per row for {len(names)} columns")
    col = lambda i: jnp.asarray(data[:, i])  # noqa: E731
    q, v = jnp.asarray(data[:, qi]), jnp.asarray(data[:, vi])
    energy = col(names.index("energy")) if "energy" in names else None
    work = {n[5:]: col(i) for i, n in enumerate(names) if n.startswith("work_")}
    finite = bool(np.all(np.isfinite(data[-1])))
    return Solution(
        t=col(0), q=q, v=v, energy=energy, work=work, energy_drift=None, constraint_drift=None, reactions=None,
        stats={}, result=RESULTS.successful if finite else RESULTS.nonfinite, t_final=col(0)[-1],
        q_final=q[-1], v_final=v[-1],
        layout=(("csv_columns", tuple(names)),),
    )


def ran_by(scene, solver) -> dict:
    """The ``kernel`` and ``solver`` fields of a solution of ``scene``: the forward-dynamics
    kernel that ran (the scene's path when none runs directly) and the solver's name."""
    try:
        kernel = scene.direct_kernel() or scene.path
    except Exception:  # noqa: BLE001 (a description must not stop a solve)
        kernel = ""
    name = solver if isinstance(solver, str) else type(solver).__name__
    return {"kernel": str(kernel or ""), "solver": name}


def _tuples(x):
    """JSON lists back to (hashable) tuples, nested ones too."""
    return tuple(_tuples(y) for y in x) if isinstance(x, list) else x


def balance_scale(energy, energy0=None):
    """``max(|E(t0)|, tiny)``: what the balance is divided by to make it relative (the first
    saved energy stands for ``E(t0)`` when ``energy0`` is unknown, as in older files)."""
    # tiny, not zero: a system at rest at its zero of potential has E(t0) = 0
    e0 = energy[..., :1] if energy0 is None else energy0[..., None]
    return jnp.maximum(jnp.abs(e0), jnp.finfo(energy.dtype).tiny)


def energy_balance(energy, work, energy0=None, work0=None):
    """``E(t) − E(t0) − Σ (w(t) − w(t0))``. ``energy0``: ``E(t0)``, with ``work0`` the work
    vector at ``t0`` (default zero, in ``work``'s order); without ``energy0`` (a solution read
    from an older file) the first saved time stands for ``t0``."""
    e0 = energy[..., :1] if energy0 is None else energy0[..., None]
    out = energy - e0
    # work entries are cumulative; their value at t0 (zero by default, work0 when given, the first
    # saved value when E(t0) is unknown) is subtracted so that only the work done since t0 enters
    for i, w in enumerate(work.values()):
        if energy0 is None:
            out = out - (w - w[..., :1])
        else:
            out = out - (w if work0 is None else w - work0[..., i : i + 1])
    return out


def solution_layout(system) -> tuple:
    """The static description of ``q``/``v`` a :class:`Solution` carries (joint names and kinds,
    addresses, the constraint rows' names): enough to replay or label a saved trajectory
    without the model."""
    # constraint objects other than jaxbody.maggi's need not name their rows
    names = getattr(getattr(system, "constraints", None), "constraint_names", None)
    extra = (("constraint_names", tuple(names)),) if names is not None else ()
    return tuple(sorted(_layout_of(system) + extra))


def _layout_of(system) -> tuple:
    if isinstance(system, Scene):
        system = system.system
    if not isinstance(system, Model):
        return (("nq", system.nq), ("nv", system.nv))
    j = system.joints
    q_names, v_names = [], []
    for name, kind in zip(j.names, j.type):
        kind = int(kind)
        # ball and free joints have more coordinates than velocities: name each one
        if JOINT_KIND_NAMES[kind] == "free":
            q_names += [f"{name}_{c}" for c in ("x", "y", "z", "qw", "qx", "qy", "qz")]
            v_names += [f"{name}_{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz")]
        elif JOINT_KIND_NAMES[kind] == "ball":
            q_names += [f"{name}_{c}" for c in ("qw", "qx", "qy", "qz")]
            v_names += [f"{name}_{c}" for c in ("wx", "wy", "wz")]
        else:
            q_names.append(name)
            v_names.append(name)
    return (
        ("joint_kinds", tuple(JOINT_KIND_NAMES[int(k)] for k in j.type)),
        ("joint_names", tuple(j.names)),
        ("model", system.name),
        ("nq", system.nq),
        ("nv", system.nv),
        ("q_names", tuple(q_names)),
        ("qposadr", tuple(int(a) for a in j.qposadr)),
        ("v_names", tuple(v_names)),
    )
