"""The ``jaxbody`` command.

Sub-commands:

* ``jaxbody simulate SOURCE``: integrate an MJCF/URDF file or a built-in example and write
  the trajectory (npz, CSV), a plot of the coordinates and the energy, and an animation of
  the mechanism's skeleton. Long runs are integrated in chunks and the files are rewritten
  after each chunk, so an interrupted or failed run keeps what it finished;
* ``jaxbody info SOURCE``: the tree, joints, masses, augmented bodies, declared effects and
  the model content that jaxbody ignores;
* ``jaxbody examples``: the built-in systems (the papers' examples and the shipped robot
  models);
* ``jaxbody balance``: balancing design (``jaxbody.design``);
* ``jaxbody demo``: the double pendulum of Example 1 (eq. 15), a plot and its trajectory.

Bad arguments or files give one line on stderr naming what is wrong and exit status 2; a
solver failure exits with status 1 after writing what was integrated, an interrupt with 130.
Set ``JAXBODY_DEBUG=1`` to see the traceback of an unexpected error. Unlike the library,
the command turns on float64 (``jax_enable_x64``) globally.
"""

import argparse
import csv
import dataclasses
import functools
import json
import math
import os
import pathlib
import sys
import time
import warnings

__all__ = ["main", "EXAMPLES", "ROBOT_MODELS"]

#: Initial state of the demo: absolute angles from the downward vertical (rad), at rest.
DEMO_ALPHA0 = (1.0, -0.5)
DEMO_ALPHA_DOT0 = (0.0, 0.0)

MODELS_DIR = pathlib.Path(__file__).resolve().parent / "models"


@dataclasses.dataclass(frozen=True)
class _Example:
    summary: str
    q_names: tuple[str, ...]
    q0: tuple[float, ...]
    v0: tuple[float, ...]


#: The papers' systems of ``jaxbody.examples``: name -> summary, coordinate names and the
#: initial state ``jaxbody simulate`` starts from (override with ``--q0``/``--v0``).
EXAMPLES: dict[str, _Example] = {
    "double_pendulum": _Example(
        "Example 1: double pendulum in a vertical plane; absolute angles from the downward vertical",
        ("alpha1", "alpha2"), (1.0, -0.5), (0.0, 0.0)),
    "three_link_manipulator": _Example(
        "Example 2: shoulder, forearm and hand in a horizontal plane (no gravity); absolute angles",
        ("alpha1", "alpha2", "alpha3"), (0.0, 0.5, 1.0), (1.0, -0.5, 0.5)),
    "cart_pendulum": _Example(
        "Example 3: cart on a smooth horizontal rail carrying a pendulum; (x, phi)",
        ("x", "phi"), (0.0, 1.0), (0.0, 0.0)),
    "oscillating_support_pendulum": _Example(
        "Example 4: pendulum whose pivot oscillates along an inclined line; phi",
        ("phi",), (0.5,), (0.0,)),
    "vertical_line_double_pendulum": _Example(
        "Example 5: double pendulum with its end point kept on the vertical through the pivot; phi",
        ("phi",), (0.5,), (0.0,)),
    "wheelset_pendulum": _Example(
        "Example 6: wheelset rolling on rails with a pendulum on its axle; (x, phi)",
        ("x", "phi"), (0.0, 0.8), (0.0, 0.0)),
}

#: Robot models shipped in ``jaxbody/models`` (MJCF, meshes removed; licences alongside).
ROBOT_MODELS: dict[str, str] = {
    "panda": "Franka Emika Panda arm without hand (7 hinges), keyframe 'home'",
    "ur5e": "Universal Robots UR5e arm (6 hinges), keyframe 'home'",
    "anymal_c": "ANYbotics ANYmal C quadruped (free base and 12 hinges)",
}


class UsageError(Exception):
    """A bad argument or input file: reported on one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``prog: error: message``) and exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _positive():
    def parse(text):
        try:
            x = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(x) and x > 0):
            raise argparse.ArgumentTypeError(f"must be positive and finite, got {text}")
        return x

    return parse


def _count(minimum):
    def parse(text):
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if n < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {n}")
        return n

    return parse


def _floats(text):
    try:
        values = tuple(float(s) for s in text.replace(",", " ").split())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}") from None
    if not values or not all(math.isfinite(x) for x in values):
        raise argparse.ArgumentTypeError(f"expected finite numbers separated by commas, got {text!r}")
    return values


def _nonnegative(text):
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(x) and x >= 0):
        raise argparse.ArgumentTypeError(f"must be non-negative and finite, got {text}")
    return x


def _assignment(text):
    """``NAME=V1[,V2...]`` -> ``(NAME, (V1, V2, ...))``."""
    name, sep, values = text.partition("=")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE[,VALUE...], got {text!r}")
    return name.strip(), _floats(values)


def _add_scene_options(p, verb):
    """The scene options shared by ``simulate`` and ``info`` (they map to ``jaxbody.scene``)."""
    grav = p.add_mutually_exclusive_group()
    grav.add_argument("--gravity", type=_floats, default=None, metavar="GX,GY,GZ",
                      help=f"{verb} this gravity vector in m/s² (world frame) instead of the model's")
    grav.add_argument("--no-gravity", action="store_true", help=f"{verb} no gravity")
    p.add_argument("--no-springs", action="store_true", help=f"{verb} no joint springs")
    damp = p.add_mutually_exclusive_group()
    damp.add_argument("--no-dampers", action="store_true", help=f"{verb} no joint dampers")
    damp.add_argument("--damping", type=_nonnegative, default=None, metavar="VALUE",
                      help=f"{verb} this viscous damping on every DoF (N·m·s/rad or N·s/m) instead of the model's")
    p.add_argument("--torque", type=_assignment, action="append", default=[], metavar="JOINT=VALUE",
                   help="a constant generalized force on a joint, by name (hinge: N·m, slide: N; ball: 3 "
                        "values, free: 6; built-in examples: the example's drive in the layout of its "
                        "velocities, by coordinate name, e.g. the hinge moments of the double pendulum); repeatable")
    p.add_argument("--load", type=_assignment, action="append", default=[], metavar="BODY=FX,FY,FZ[,MX,MY,MZ]",
                   help="a constant world force (N) and moment (N·m) at a body's centre of mass, by name "
                        "(MuJoCo xfrc_applied); repeatable")


def _parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = _Parser(prog="jaxbody", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"jaxbody {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    source_help = (
        "an MJCF (.xml) or URDF (.urdf) file, or a built-in example "
        "(`jaxbody examples` lists them)"
    )
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
    sim.add_argument("source", metavar="SOURCE", help=source_help)
    sim.add_argument("--t1", type=_positive(), default=1.0, help="final time in s (default 1)")
    sim.add_argument("--solver", default="tsit5",
                     help="diffrax solver preset, e.g. tsit5, dopri5, dopri8 (adaptive) or "
                          "rk4, euler (fixed step, need --dt); default tsit5")
    sim.add_argument("--rtol", type=_positive(), default=1e-8, help="relative tolerance (default 1e-8)")
    sim.add_argument("--atol", type=_positive(), default=1e-8, help="absolute tolerance (default 1e-8)")
    sim.add_argument("--dt", type=_positive(), default=None,
                     help="step of a fixed-step solver; first trial step of an adaptive one")
    sim.add_argument("--saves", type=_count(2), default=201,
                     help="number of evenly spaced saved times from 0 to t1 inclusive (default 201)")
    sim.add_argument("--keyframe", default=None, help="start from this keyframe of an MJCF model")
    sim.add_argument("--q0", type=_floats, default=None, help="initial coordinates, comma separated")
    sim.add_argument("--v0", type=_floats, default=None, help="initial velocities, comma separated")
    sim.add_argument("--chunks", type=_count(1), default=10,
                     help="integrate and write in this many pieces (default 10)")
    sim.add_argument("--max-steps", type=_count(1), default=100_000,
                     help="solver step budget per chunk (default 100000)")
    sim.add_argument("--out", type=pathlib.Path, default=None,
                     help="trajectory as .npz (default outputs/simulate/<name>.npz when no other "
                          "output is asked for)")
    sim.add_argument("--csv", type=pathlib.Path, default=None, help="trajectory as CSV")
    sim.add_argument("--plot", type=pathlib.Path, default=None,
                     help="PNG of the coordinates, the energy and its drift against time")
    sim.add_argument("--animate", type=pathlib.Path, default=None,
                     help="GIF of the skeleton (body origins and joint points) moving")
    sim.add_argument("--frames", type=_count(2), default=100,
                     help="at most this many animation frames (default 100)")
    sim.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_scene_options(sim, "integrate with")

    info = sub.add_parser(
        "info",
        help="print the tree, joints, masses, augmented bodies and ignored model content",
        description=(
            "Print the body tree and joints of SOURCE, total and subtree masses, the static "
            "moments and augmented inertias (at --keyframe or the reference configuration), "
            "the effects the scene declares (the model's, changed by the same scene options as "
            "`jaxbody simulate`) and what of an MJCF/URDF file jaxbody ignores."
        ),
    )
    info.add_argument("source", metavar="SOURCE", help=source_help)
    info.add_argument("--keyframe", default=None, help="evaluate at this keyframe")
    _add_scene_options(info, "declare")

    sub.add_parser("examples", help="list the built-in examples and robot models",
                   description="List the papers' systems and the robot models shipped with jaxbody.")

    sub.add_parser("balance", help="balancing design (jaxbody.design); `jaxbody balance --help`",
                   add_help=False)

    demo = sub.add_parser(
        "demo",
        help="simulate the double pendulum (Example 1) and write a plot and its trajectory",
        description=(
            "Integrate the double pendulum of Example 1 (eq. 15) from "
            f"alpha = {DEMO_ALPHA0} rad (absolute angles from the downward vertical), at rest, "
            "print a summary and write a PNG, a CSV trajectory and a JSON summary."
        ),
    )
    demo.add_argument("--t1", type=_positive(), default=10.0, help="final time in s (default 10)")
    demo.add_argument("--out", type=pathlib.Path, default=pathlib.Path("outputs/demo"),
                      help="output folder (default outputs/demo)")
    demo.add_argument("--rtol", type=_positive(), default=1e-10, help="relative tolerance (default 1e-10)")
    demo.add_argument("--atol", type=_positive(), default=1e-10, help="absolute tolerance (default 1e-10)")
    demo.add_argument("--solver", choices=("dopri5", "tsit5", "dopri8"), default="dopri5",
                      help="adaptive Runge-Kutta solver (default dopri5)")
    demo.add_argument("--n-save", type=_count(2), default=1001,
                      help="number of evenly spaced saved times (default 1001)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxbody`` command; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = {"simulate": _simulate, "info": _info, "examples": _examples, "demo": _demo,
                "balance": _balance}
    if argv and argv[0] == "balance":
        # Everything after `balance` belongs to the design module's own parser.
        args = argparse.Namespace(command="balance", argv=argv[1:])
    else:
        parser = _parser()
        args = parser.parse_args(argv)
        if args.command not in commands:
            parser.print_help()
            return 2
    try:
        return commands[args.command](args)
    except UsageError as e:
        _error_line(args.command, str(e))
        return 2
    except KeyboardInterrupt:
        _error_line(args.command, "interrupted")
        return 130
    except Exception as e:  # never a traceback on the command line, unless asked for
        if os.environ.get("JAXBODY_DEBUG"):
            raise
        _error_line(args.command, f"{type(e).__name__}: {e}")
        return 1


def _one_line(text: str) -> str:
    return "; ".join(s.strip() for s in str(text).splitlines() if s.strip())


def _error_line(command, message):
    sys.stdout.flush()
    print(f"jaxbody {command}: error: {_one_line(message)}", file=sys.stderr)


# ------------------------------------------------------------------------------ sources
def _jax():
    """JAX with float64, set up before its backend starts."""
    # Must precede JAX's backend initialisation (known XLA CPU issue with jax 0.10).
    from ._xla import set_default_xla_flags

    set_default_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    return jax


@dataclasses.dataclass
class _Source:
    """A loaded model or example and what the command needs to know about it."""

    name: str
    origin: str  # file path or "jaxbody.examples.<name>" / shipped model path
    system: object  # jaxbody.Model, planar.PlanarSystem or an embedded planar example
    kind: str  # "model" | "planar" | "embedded"
    q_labels: list[str]
    v_labels: list[str]
    q0: object
    v0: object
    ignored: list[str]  # lines of the importer's warning: content jaxbody does not model
    start: str  # where q0/v0 come from, in words


def _load(spec: str, keyframe: str | None = None) -> _Source:
    """Resolve SOURCE (a file or a built-in name) into a :class:`_Source`.

    Raises:
        UsageError: missing or unreadable file, a file MuJoCo's compiler rejects, an unknown
            example or keyframe.
    """
    path = pathlib.Path(spec)
    looks_like_file = path.suffix.lower() in (".xml", ".urdf", ".mjcf") or os.sep in spec or "/" in spec
    if spec in EXAMPLES and not path.exists():
        return _load_example(spec, keyframe)
    if spec in ROBOT_MODELS and not path.exists():
        return _load_file(MODELS_DIR / f"{spec}.xml", keyframe, name=spec)
    if path.exists() or looks_like_file:
        if not path.exists():
            raise UsageError(f"model file not found: {spec!r}")
        if not path.is_file():
            raise UsageError(f"not a file: {spec!r}")
        return _load_file(path, keyframe)
    names = ", ".join([*EXAMPLES, *ROBOT_MODELS])
    raise UsageError(
        f"unknown example {spec!r}: built-in ones are {names}; or give an .xml (MJCF) or "
        ".urdf file"
    )


def _load_file(path: pathlib.Path, keyframe, name=None) -> _Source:
    _jax()
    import jax.numpy as jnp

    import jaxbody as jb

    load = jb.from_urdf if path.suffix.lower() == ".urdf" else jb.from_mjcf
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            model = load(str(path))
        except (ValueError, FileNotFoundError, TypeError, OSError) as e:
            raise UsageError(_one_line(e)) from None
    ignored = []
    for w in caught:
        if issubclass(w.category, UserWarning) and "does not model" in str(w.message):
            ignored += [s.strip()[2:] for s in str(w.message).splitlines() if s.strip().startswith("- ")]
    if keyframe is not None:
        try:
            q0, v0 = model.keyframe(keyframe)
        except KeyError as e:
            raise UsageError(f"--keyframe: {e.args[0]}") from None
        start = f"keyframe {keyframe!r}"
    else:
        q0, v0 = model.qpos0, jnp.zeros(model.nv, model.qpos0.dtype)
        start = "qpos0 at rest"
    q_labels, v_labels = _model_labels(jb, model)
    return _Source(name or path.stem, str(path), model, "model", q_labels, v_labels, q0, v0,
                   ignored, start)


def _load_example(name, keyframe) -> _Source:
    _jax()
    import jax.numpy as jnp

    from . import examples

    if keyframe is not None:
        raise UsageError(f"--keyframe: the built-in example {name!r} has no keyframes")
    ex = EXAMPLES[name]
    system = getattr(examples, name)()
    kind = "planar" if hasattr(system, "tree") else "embedded"
    labels = list(ex.q_names)
    return _Source(name, f"jaxbody.examples.{name}()", system, kind, labels, labels,
                   jnp.asarray(ex.q0), jnp.asarray(ex.v0), [], "the example's default state")


def _model_labels(jb, model):
    """Names of the q and v entries of a spatial model (MuJoCo qpos/qvel layout)."""
    q_parts = {jb.HINGE: [""], jb.SLIDE: [""], jb.BALL: ["qw", "qx", "qy", "qz"],
               jb.FREE: ["x", "y", "z", "qw", "qx", "qy", "qz"]}
    v_parts = {jb.HINGE: [""], jb.SLIDE: [""], jb.BALL: ["wx", "wy", "wz"],
               jb.FREE: ["vx", "vy", "vz", "wx", "wy", "wz"]}
    q_labels, v_labels = [], []
    for kind, name in zip(model.joints.type, model.joints.names):
        q_labels += [f"{name}.{p}" if p else name for p in q_parts[kind]]
        v_labels += [f"{name}.{p}" if p else name for p in v_parts[kind]]
    return q_labels, v_labels


def _initial_state(src: _Source, args):
    import jax.numpy as jnp

    q0, v0 = jnp.asarray(src.q0), jnp.asarray(src.v0)
    nq, nv = src.system.nq, src.system.nv
    if args.q0 is not None:
        if len(args.q0) != nq:
            raise UsageError(f"--q0 has {len(args.q0)} values but {src.name} has nq = {nq} "
                             f"({', '.join(src.q_labels)})")
        q0 = jnp.asarray(args.q0, dtype=q0.dtype)
    if args.v0 is not None:
        if len(args.v0) != nv:
            raise UsageError(f"--v0 has {len(args.v0)} values but {src.name} has nv = {nv} "
                             f"({', '.join(src.v_labels)})")
        v0 = jnp.asarray(args.v0, dtype=q0.dtype)
    given = [name for name, x in (("--q0", args.q0), ("--v0", args.v0)) if x is not None]
    if given:
        src.start = f"{' and '.join(given)} (otherwise {src.start})"
    return q0, v0


# ------------------------------------------------------------------------------ scene
@functools.lru_cache(maxsize=None)
def _constant():
    import equinox as eqx

    class Constant(eqx.Module):
        """A constant ``f(t, q, v) = value`` (an array leaf: one compiled program for any value)."""

        value: object

        def __call__(self, t, q, v):
            return self.value

    return Constant


def _named_vectors(option, given, names, sizes, what):
    """``--torque``/``--load`` assignments -> ``{index: values}``, naming what is wrong."""
    out = {}
    for name, values in given:
        if name not in names:
            plural = {"body": "bodies"}.get(what, what + "s")
            raise UsageError(f"{option}: unknown {what} {name!r}; {plural}: {', '.join(names)}")
        i = names.index(name)
        if i in out:
            raise UsageError(f"{option}: {what} {name!r} given twice")
        if len(values) not in sizes[i]:
            want = " or ".join(str(n) for n in sizes[i])
            raise UsageError(f"{option} {name}: expected {want} values, got {len(values)}")
        out[i] = values
    return out


def _scene(src: _Source, args):
    """The scene the options declare (``jaxbody.scene``), or a UsageError naming the option."""
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb

    system = src.system
    dtype = src.q0.dtype
    spatial = src.kind == "model"
    if not spatial:
        for option, used in (("--no-springs", args.no_springs), ("--no-dampers", args.no_dampers),
                             ("--damping", args.damping is not None), ("--load", bool(args.load)),
                             ("--gravity", args.gravity is not None)):
            if used:
                raise UsageError(f"{option} needs a spatial model (an MJCF or URDF file or a shipped "
                                 f"robot); the built-in example {src.name!r} takes --no-gravity and --torque only")
    kw = {}
    if args.no_gravity:
        kw["gravity"] = False
    elif args.gravity is not None:
        if len(args.gravity) != 3:
            raise UsageError(f"--gravity: expected 3 values GX,GY,GZ, got {len(args.gravity)}")
        kw["gravity"] = jnp.asarray(args.gravity, dtype)
    if args.no_springs:
        kw["springs"] = False
    if args.no_dampers:
        kw["dampers"] = False
    elif args.damping is not None:
        kw["dampers"] = jnp.full((system.nv,), args.damping, dtype)
    if args.torque:
        if spatial:
            names = list(system.joint_names)
            dofs = {jb.HINGE: 1, jb.SLIDE: 1, jb.BALL: 3, jb.FREE: 6}
            sizes = [(dofs[int(k)],) for k in system.joints.type]
            where = [int(a) for a in system.joints.dofadr]
        else:
            names, sizes, where = list(src.q_labels), [(1,)] * system.nv, list(range(system.nv))
        tau = np.zeros(system.nv)
        for i, values in _named_vectors("--torque", args.torque, names, sizes, "joint" if spatial else "coordinate").items():
            tau[where[i]:where[i] + len(values)] = values
        kw["actuation"] = _constant()(jnp.asarray(tau, dtype))
    if args.load:
        names = list(system.body_names)
        wrench = np.zeros((system.n_body, 6))
        for i, values in _named_vectors("--load", args.load, names, [(3, 6)] * len(names), "body").items():
            wrench[i, :len(values)] = values
        kw["loads"] = _constant()(jnp.asarray(wrench, dtype))
    try:
        return jb.scene(system, **kw)
    except ValueError as e:
        raise UsageError(_one_line(str(e))) from None


# ------------------------------------------------------------------------------ simulate
def _simulate_chunk(system, q, v, ts, args, continued=False):
    """The one place the command calls the library's integrator.

    ``ts`` are the saved times of this chunk (``ts[0]`` its start). ``throw=False``: a failed
    solve comes back as a result code with ``inf`` after the failure, and the caller keeps
    the finite part. A ``continued`` chunk starts from the end of the previous one, whose
    velocities satisfy a scene's constraints only up to the integration error: they are
    projected back onto them (a correction of that order) instead of being rejected.
    """
    import jaxbody as jb

    return jb.simulate(system, q, v, ts[-1], t0=ts[0], solver=args.solver, rtol=args.rtol,
                       atol=args.atol, dt0=args.dt, saveat=ts, max_steps=args.max_steps,
                       throw=False, project_initial=continued)


def _result_message(result) -> str:
    import jaxbody as jb

    try:
        return jb.RESULTS[result]
    except Exception:  # pragma: no cover - message lookup is best effort
        return str(result)


class _TrajectoryFiles:
    """npz and CSV files that grow chunk by chunk; each write leaves complete files.

    The npz is rewritten atomically (temporary file, then rename) after every chunk with
    everything so far, ``complete`` false until the last chunk; CSV rows are appended and
    flushed.
    """

    def __init__(self, npz, csv_path, src: _Source, meta: dict):
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
        import numpy as np

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
        import numpy as np

        if not self.t:
            src = self.src
            return (np.zeros(0), np.zeros((0, src.system.nq)), np.zeros((0, src.system.nv)),
                    np.zeros(0))
        return tuple(np.concatenate(a) for a in (self.t, self.q, self.v, self.energy))

    def write_npz(self, status):
        import numpy as np

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


def _chunk_times(t1, n_save, n_chunks):
    """Saved times split into chunks that share their end points.

    Returns ``(ts, n)`` per chunk: every ``ts`` has the same length, so the solve compiles
    once; a shorter last chunk repeats its final time, and only its first ``n`` entries are
    kept.
    """
    import numpy as np

    ts = np.linspace(0.0, t1, n_save)
    intervals = n_save - 1
    step = max(1, math.ceil(intervals / min(n_chunks, intervals)))
    chunks = []
    for i in range(0, intervals, step):
        part = ts[i:min(i + step, intervals) + 1]
        chunks.append((np.pad(part, (0, step + 1 - len(part)), mode="edge"), len(part)))
    return chunks


def _simulate(args) -> int:
    src = _load(args.source, args.keyframe)
    jax = _jax()
    import jax.numpy as jnp
    import numpy as np

    q0, v0 = _initial_state(src, args)
    scene = _scene(src, args)
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
    files = _TrajectoryFiles(out, args.csv, src, meta)
    chunks = _chunk_times(args.t1, args.saves, args.chunks)
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
                    raise UsageError(_one_line(e) + hint) from None
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
                failure = _result_message(sol.result)
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
        _plot_trajectory(args.plot, src, t, qs, energy, args)
    if args.animate is not None and len(t):
        _animate(args.animate, src, t, qs, args.frames)

    print(f"jaxbody simulate: {src.name} ({src.origin}), nq = {src.system.nq}, nv = {src.system.nv}, "
          f"from {src.start}")
    own = ["gravity"] if scene.path == "system" and np.any(np.asarray(getattr(scene.system, "gravity", 0.0)) != 0) else []
    print(f"  effects         {', '.join(own + list(scene.effect_names)) or 'none'}")
    loops = [spec.label for spec in getattr(src.system, "loops", ())]
    if loops and scene.constraints is not None:
        print(f"  constraints     loop closures {', '.join(loops)} (Maggi equations)")
    print(f"  integrated      t = 0 .. {t[-1] if len(t) else 0:g} s of {args.t1:g} s with {args.solver}, "
          f"rtol={args.rtol:g}, atol={args.atol:g}" + (f", dt={args.dt:g}" if args.dt else "")
          + f", in {len(chunks)} chunks")
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
        _error_line("simulate", f"the solver failed after t = {t[-1] if len(t) else 0:g} s: {failure}; "
                                f"the {len(t)} saved states before it were written")
        return 1
    return 0


def _successful():
    import jaxbody as jb

    return jb.RESULTS.successful


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _progress_bar(total, disabled):
    if disabled:
        return _NoBar()
    from tqdm import tqdm

    # delay: arguments the integrator rejects at once leave no bar behind their error line
    return tqdm(total=total, unit="s", unit_scale=False, file=sys.stderr, desc="simulated time", delay=0.5,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.3g}/{total:.3g} s [{elapsed}<{remaining}]")


# ------------------------------------------------------------------------------ plots
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plot_trajectory(path, src, t, q, energy, args):
    """Coordinates, energy and relative energy drift against time."""
    import numpy as np

    plt = _plt()
    path.parent.mkdir(parents=True, exist_ok=True)
    scalar = [i for i, s in enumerate(src.q_labels) if "." not in s]
    cols = scalar or list(range(q.shape[1]))
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(8, 8), constrained_layout=True)
    for i in cols:
        axes[0].plot(t, q[:, i], label=src.q_labels[i])
    axes[0].set_ylabel("joint coordinates [rad or m]" if scalar else "q")
    if len(cols) <= 12:
        axes[0].legend(loc="upper right", fontsize="small", ncol=2)
    axes[0].set_title(f"{src.name}: {args.solver}, rtol={args.rtol:g}, atol={args.atol:g}")
    if np.all(np.isfinite(energy)):
        e0 = energy[0]
        axes[1].plot(t, energy)
        axes[2].plot(t, (energy - e0) / max(abs(e0), np.finfo(float).tiny))
    axes[1].set_ylabel("energy E [J]")
    axes[1].ticklabel_format(axis="y", useOffset=False)
    axes[2].set_ylabel(r"$(E - E_0)/|E_0|$")
    axes[2].set_xlabel("t [s]")
    axes[2].ticklabel_format(axis="y", style="sci", scilimits=(0, 0))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _skeleton(src: _Source, t, q):
    """Per frame, one polyline per body: parent point → joint point → body point.

    Spatial models: parent's origin → joint anchor ``O_0k`` → body origin, in 3-D.
    Planar systems: parent's hinge (or the base point) → hinge ``O_k`` → centre of mass, 2-D.
    Returns ``(lines (frames, n_body, 3, dim), dim)``.
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb

    if src.kind == "model":
        model = src.system
        parent = np.asarray(model.tree.parent)

        def frame(qk):
            kin = jb.forward_kinematics(model, qk)
            return kin.body_position, kin.base_point

        origin, anchor = jax.jit(jax.vmap(frame))(jnp.asarray(q))
        origin, anchor = np.asarray(origin), np.asarray(anchor)
        # A root hangs from the world origin unless it floats (free joint): then no link.
        free = np.zeros(model.n_body, dtype=bool)
        free[[b for kind, b in zip(model.joints.type, model.joints.body) if kind == jb.FREE]] = True
        root_start = np.where(free[None, :, None], anchor, 0.0)
        start = np.where(parent[None, :, None] >= 0, origin[:, np.maximum(parent, 0)], root_start)
        return np.stack([start, anchor, origin], axis=2), 3

    from . import planar

    embedded = src.kind == "embedded"
    psys = src.system.system if embedded else src.system

    def frame(tk, qk):
        Q = src.system.embed(tk, qk) if embedded else qk
        hinge, com = planar.body_positions(psys, Q)
        base = Q[:2] if psys.translating_base else jnp.zeros(2, Q.dtype)
        return hinge, com, base

    hinge, com, base = jax.jit(jax.vmap(frame))(jnp.asarray(t), jnp.asarray(q))
    hinge, com, base = np.asarray(hinge), np.asarray(com), np.asarray(base)
    parent = np.asarray(psys.tree.parent)
    start = np.where(parent[None, :, None] >= 0, hinge[:, np.maximum(parent, 0)], base[:, None, :])
    return np.stack([start, hinge, com], axis=2), 2


def _project(points, azimuth=math.radians(45.0), elevation=math.radians(25.0)):
    """Orthographic view of world points (z up) from azimuth/elevation: (..., 3) -> (..., 2)."""
    import numpy as np

    ca, sa, ce, se = math.cos(azimuth), math.sin(azimuth), math.cos(elevation), math.sin(elevation)
    right = np.array([-sa, ca, 0.0])
    up = np.array([-se * ca, -se * sa, ce])
    return np.stack([points @ right, points @ up], axis=-1)


def _animate(path, src, t, q, max_frames):
    """GIF of the skeleton moving (matplotlib frames, assembled by Pillow)."""
    import numpy as np
    from PIL import Image

    plt = _plt()
    path.parent.mkdir(parents=True, exist_ok=True)
    idx = np.unique(np.linspace(0, len(t) - 1, min(max_frames, len(t))).round().astype(int))
    lines, dim = _skeleton(src, t[idx], q[idx])
    if dim == 3:
        lines = _project(lines)
    lo, hi = lines.reshape(-1, 2).min(axis=0), lines.reshape(-1, 2).max(axis=0)
    pad = 0.1 * max(float(np.max(hi - lo)), 1e-3)
    fig, ax = plt.subplots(figsize=(5, 5), dpi=90, constrained_layout=True)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_title(src.name + (" (oblique view, z up)" if dim == 3 else " (plane of motion)"))
    if dim == 2:  # the horizontal through the world origin
        ax.plot([lo[0] - pad, hi[0] + pad], [0, 0], color="0.85", lw=0.8, zorder=0)
    n_body = lines.shape[1]
    links = [ax.plot([], [], "-", color="C0", lw=2)[0] for _ in range(n_body)]
    joints = ax.plot([], [], "o", color="C3", ms=4)[0]
    points = ax.plot([], [], "o", color="C0", ms=3)[0]
    label = ax.text(0.02, 0.96, "", transform=ax.transAxes, va="top")
    fig.canvas.draw()
    # The layout is fixed after the first draw: re-solving it for every frame is most of
    # the cost of a frame.
    fig.set_layout_engine("none")
    frames = []
    for f in range(len(idx)):
        for k in range(n_body):
            links[k].set_data(lines[f, k, :, 0], lines[f, k, :, 1])
        joints.set_data(lines[f, :, 1, 0], lines[f, :, 1, 1])
        points.set_data(lines[f, :, 2, 0], lines[f, :, 2, 1])
        label.set_text(f"t = {t[idx][f]:.3f} s")
        fig.canvas.draw()
        rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]
        frames.append(Image.fromarray(rgb).quantize(colors=64, method=Image.Quantize.MEDIANCUT))
    plt.close(fig)
    span = float(t[idx][-1] - t[idx][0])
    fps = max(1, min(30, round(len(idx) / span))) if span > 0 else 10
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=round(1000 / fps), loop=0)


# ------------------------------------------------------------------------------ info
def _vec(x, fmt="{:+.6g}"):
    return "(" + ", ".join(fmt.format(float(c)) for c in x) + ")"


def _info(args) -> int:
    src = _load(args.source, args.keyframe)
    _jax()
    import jaxbody as jb

    system = src.system
    scene = _scene(src, args)
    print(f"{src.name}: {src.origin}")
    if src.kind == "model":
        _info_model(jb, src, system)
    else:
        _info_planar(src, system)
    _effects(jb, src, scene)
    print("content of the file that jaxbody does not model (ignored):")
    if src.ignored:
        for line in src.ignored:
            print(f"  - {line}")
    elif src.kind == "model":
        print("  none")
    else:
        print("  none (a built-in example)")
    return 0


def _info_model(jb, src, model):
    import numpy as np

    names = model.body_names
    parent = list(model.tree.parent)
    kinds = {jb.HINGE: "hinge", jb.SLIDE: "slide", jb.BALL: "ball", jb.FREE: "free"}
    joints_of = {k: [] for k in range(model.n_body)}
    for j, (kind, body) in enumerate(zip(model.joints.type, model.joints.body)):
        joints_of[body].append(j)
    mass = np.asarray(model.body_mass)
    print(f"  {model.n_body} bodies, {model.n_joint} joints, nq = {model.nq}, nv = {model.nv} "
          "(q, v laid out as MuJoCo's qpos, qvel; body k = MuJoCo body k+1)")
    print(f"  total mass {mass.sum():.6g} kg")
    print("tree (body k, name, mass; joints with their q/v addresses and axes in the body frame):")

    def show(k, depth):
        print(f"  {'  ' * depth}{k:>3} {names[k]}  mass {mass[k]:.6g} kg")
        for j in joints_of[k]:
            kind = model.joints.type[j]
            axis = "" if kind in (jb.BALL, jb.FREE) else f", axis {_vec(np.asarray(model.joint_axis[j]), '{:.4g}')}"
            print(f"  {'  ' * depth}      {kinds[kind]} joint {model.joint_names[j]!r}: "
                  f"q[{model.joints.qposadr[j]}], v[{model.joints.dofadr[j]}]{axis}")
        for c in range(model.n_body):
            if parent[c] == k:
                show(c, depth + 1)

    for k in range(model.n_body):
        if parent[k] < 0:
            show(k, 0)
    aug = jb.augmented_bodies(model, src.q0)
    m_sub = np.asarray(aug.subtree_mass)
    mbar = np.asarray(aug.static_moment)
    inertia = np.asarray(aug.augmented_inertia)
    print(f"augmented bodies at {src.start} (world frame, about each body's joint point O_0k):")
    print("    k  name                    subtree mass m_k [kg]   static moment m̄_k [kg m]")
    for k in range(model.n_body):
        print(f"  {k:>3}  {names[k]:<22}  {m_sub[k]:<22.6g}  {_vec(mbar[k])}")
    print("  augmented inertia I_k [kg m²] (xx, yy, zz, xy, xz, yz):")
    for k in range(model.n_body):
        I = inertia[k]
        print(f"  {k:>3}  {names[k]:<22}  {_vec([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])}")


def _effects(jb, src, scene):
    """The effects the scene declares, as ``jaxbody simulate`` with the same options integrates them."""
    import numpy as np

    from .effects import Actuation, BodyLoads, Gravity, JointDampers, JointSprings

    by_kind = {type(e): e for e in scene.effects}
    spatial = src.kind == "model"
    print(f"effects the scene declares (what `jaxbody simulate` integrates; path {scene.path!r}):")
    if spatial:
        g = by_kind.get(Gravity)
        g = None if g is None else np.asarray(g.vector)
    else:
        g = getattr(scene.system, "gravity", None)
        g = np.asarray(scene.system.system.gravity if g is None else g)
        g = g if np.any(g != 0) else None
    print(f"  gravity          {'on, ' + _vec(g, '{:.4g}') + ' m/s²' if g is not None and np.any(g != 0) else 'off'}")
    if spatial:
        model = src.system
        names = model.joint_names
        springs = by_kind.get(JointSprings)
        on = [] if springs is None else [names[j] for j in np.nonzero(np.asarray(springs.stiffness) != 0)[0]]
        print(f"  joint springs    {len(on)} joints" + (f" ({', '.join(on)})" if on else ""))
        dampers = by_kind.get(JointDampers)
        dofs = [] if dampers is None else np.nonzero(np.asarray(dampers.damping) != 0)[0]
        print(f"  joint dampers    {len(dofs)} DoFs" + (f" (v[{', '.join(map(str, dofs))}])" if len(dofs) else ""))
        print(f"  armature         {int(np.count_nonzero(np.asarray(model.dof_armature)))} DoFs")
        if scene.constraints is not None:
            rows = getattr(scene.constraints, "constraint_names", None) or ()
            loops = [spec.label for spec in model.loops]
            print(f"  constraints      {len(rows)} rows (Maggi): loop closures {', '.join(loops)}")
    elif src.kind == "embedded":
        print(f"  constraints      solved explicitly by {type(src.system).__name__} (coordinates "
              f"{', '.join(src.q_labels)})")
    act = by_kind.get(Actuation)
    if act is None:
        print("  actuation        none (no joint forces are applied)")
    else:
        tau = np.asarray(act.law.value)
        parts = [f"{src.v_labels[i]} = {tau[i]:.6g}" for i in np.nonzero(tau)[0]]
        what = "generalized forces" if spatial else "drives"
        print(f"  actuation        constant {what}: {', '.join(parts) or 'all zero'}")
    loads = by_kind.get(BodyLoads)
    if loads is None:
        print("  external loads   none")
    else:
        w = np.asarray(loads.wrench.value)
        for k in np.nonzero(np.any(w != 0, axis=1))[0]:
            print(f"  external load    {src.system.body_names[k]}: force {_vec(w[k, :3], '{:.4g}')} N, "
                  f"moment {_vec(w[k, 3:], '{:.4g}')} N·m at the centre of mass")


def _info_planar(src, system):
    import numpy as np

    from . import planar

    embedded = src.kind == "embedded"
    psys = system.system if embedded else system
    names = psys.tree.names
    parent = list(psys.tree.parent)
    mass = np.asarray(psys.body_mass)
    Q = system.embed(0.0, src.q0) if embedded else src.q0
    print(f"  planar system in absolute angles: {psys.n_body} hinged bodies, nq = nv = {system.nq} "
          f"({', '.join(src.q_labels)})" + (f"; a constrained example of a {psys.nq}-coordinate tree"
                                           if embedded else ""))
    base = float(np.asarray(psys.base_mass)) if psys.translating_base else 0.0
    print(f"  total mass {mass.sum() + base:.6g} kg"
          + (f" (translating base {base:.6g} kg)" if psys.translating_base else ""))
    print("tree (body k, name, mass, hinge position in the parent's axes):")

    def show(k, depth):
        print(f"  {'  ' * depth}{k:>3} {names[k]}  mass {mass[k]:.6g} kg, hinge at "
              f"{_vec(np.asarray(psys.hinge_pos[k]), '{:.4g}')}")
        for c in range(psys.n_body):
            if parent[c] == k:
                show(c, depth + 1)

    for k in range(psys.n_body):
        if parent[k] < 0:
            show(k, 0)
    aug = planar.augmented_bodies(psys, Q)
    print(f"augmented bodies at {src.start} (world axes in the plane, about each hinge O_k):")
    print("    k  name                    m_k [kg]     m̄_k [kg m]                J_k [kg m²]")
    for k in range(psys.n_body):
        print(f"  {k:>3}  {names[k]:<22}  {float(aug.subtree_mass[k]):<11.6g}  "
              f"{_vec(np.asarray(aug.static_moment[k])):<24}  {float(aug.augmented_inertia[k]):.6g}")


# ------------------------------------------------------------------------------ examples
def _examples(args) -> int:
    del args
    print("The papers' systems (jaxbody.examples; `jaxbody simulate NAME` starts from q0, v0):")
    for name, ex in EXAMPLES.items():
        print(f"  {name:<30} {ex.summary}")
        print(f"  {'':<30} q0 = {ex.q0}, v0 = {ex.v0}")
    print(f"Robot models shipped with jaxbody (MJCF in {MODELS_DIR}):")
    for name, summary in ROBOT_MODELS.items():
        print(f"  {name:<30} {summary}")
    print("Any MJCF (.xml) or URDF (.urdf) file works as well: `jaxbody info FILE`.")
    return 0


# ------------------------------------------------------------------------------ balance
def _balance(args) -> int:
    from .design import cli_balance

    return cli_balance(args.argv)


# ------------------------------------------------------------------------------ demo
def _demo(args) -> int:
    jax = _jax()
    import jax.numpy as jnp
    import numpy as np

    import jaxbody as jb
    from jaxbody import examples

    system = examples.double_pendulum()
    q0 = jnp.asarray(DEMO_ALPHA0)
    v0 = jnp.asarray(DEMO_ALPHA_DOT0)

    def run():
        sol = jb.simulate(system, q0, v0, args.t1, solver=args.solver, rtol=args.rtol,
                          atol=args.atol, n_save=args.n_save)
        return jax.block_until_ready(sol)

    start = time.perf_counter()
    sol = run()
    wall = time.perf_counter() - start
    start = time.perf_counter()
    run()
    rerun = time.perf_counter() - start

    t, q, v = np.asarray(sol.t), np.asarray(sol.q), np.asarray(sol.v)
    energy, rel_err = np.asarray(sol.energy), np.asarray(sol.energy_error)
    drift = float(sol.energy_drift)
    stats = {k: int(x) for k, x in sol.stats.items()}

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    csv_path, json_path, png_path = out / "trajectory.csv", out / "summary.json", out / "double_pendulum.png"
    with open(csv_path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["t", "alpha1", "alpha2", "alpha1_dot", "alpha2_dot", "energy", "relative_energy_error"])
        for row in zip(t, q[:, 0], q[:, 1], v[:, 0], v[:, 1], energy, rel_err):
            writer.writerow([repr(float(x)) for x in row])
    summary = {
        "system": "double pendulum, Example 1 (eq. 15), jaxbody.examples.double_pendulum()",
        "coordinates": "absolute angles from the downward vertical (rad)",
        "alpha0": list(DEMO_ALPHA0),
        "alpha_dot0": list(DEMO_ALPHA_DOT0),
        "t1": args.t1,
        "solver": args.solver,
        "rtol": args.rtol,
        "atol": args.atol,
        "alpha_final": q[-1].tolist(),
        "alpha_dot_final": v[-1].tolist(),
        "energy0": float(energy[0]),
        "relative_energy_drift": drift,
        "stats": stats,
        "wall_time_s_incl_compile": wall,
        "wall_time_s_rerun": rerun,
        "jax_version": jax.__version__,
        "jaxbody_version": jb.__version__,
        "device": str(jax.devices()[0]),
    }
    json_path.write_text(json.dumps(summary, indent=2) + "\n")
    _plot_demo(png_path, t, q, rel_err, args)

    print("jaxbody demo: double pendulum, Example 1 (eq. 15); angles from the downward vertical")
    print(f"  initial state   alpha = {DEMO_ALPHA0} rad, alpha_dot = {DEMO_ALPHA_DOT0} rad/s")
    print(f"  integrated      t = 0 .. {args.t1:g} s with {args.solver}, rtol={args.rtol:g}, atol={args.atol:g}")
    print(f"  final state     alpha = ({q[-1, 0]:.10f}, {q[-1, 1]:.10f}) rad, "
          f"alpha_dot = ({v[-1, 0]:.10f}, {v[-1, 1]:.10f}) rad/s")
    print(f"  energy          E0 = {energy[0]:.12g}; relative drift max|E-E0|/|E0| = {drift:.3e}")
    print(f"  steps           accepted {stats['num_accepted_steps']}, rejected {stats['num_rejected_steps']}")
    print(f"  wall time       {wall:.2f} s incl. compile ({rerun:.3f} s re-run) on {jax.devices()[0].platform}")
    for path in (png_path, csv_path, json_path):
        print(f"wrote {path}")
    sys.stdout.flush()
    return 0


def _plot_demo(path, t, q, rel_err, args):
    plt = _plt()
    fig, (ax_angle, ax_drift) = plt.subplots(2, 1, sharex=True, figsize=(8, 6), constrained_layout=True)
    ax_angle.plot(t, q[:, 0], label=r"$\alpha_1$")
    ax_angle.plot(t, q[:, 1], label=r"$\alpha_2$")
    ax_angle.set_ylabel("angle from downward vertical [rad]")
    ax_angle.legend(loc="upper right")
    ax_angle.set_title(f"Double pendulum (Example 1), {args.solver}, rtol={args.rtol:g}, atol={args.atol:g}")
    ax_drift.plot(t, rel_err)
    ax_drift.set_ylabel(r"$(E - E_0)/|E_0|$")
    ax_drift.set_xlabel("t [s]")
    ax_drift.ticklabel_format(axis="y", style="sci", scilimits=(0, 0))
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
