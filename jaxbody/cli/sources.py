"""SOURCE of ``jaxbody simulate`` and ``jaxbody info``: a model file, a shipped robot model or a
built-in example, loaded with what the commands need to know about it."""

import dataclasses
import os
import pathlib
import warnings

import jax.numpy as jnp

from .. import catalog
from ..io.mujoco import from_mjcf, from_urdf
from ..joints import BALL, FREE, HINGE, SLIDE
from .arguments import UsageError, one_line, setup_jax

__all__ = ["Source", "load", "load_file", "load_example", "model_labels", "initial_state"]


@dataclasses.dataclass
class Source:
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


def load(spec: str, keyframe: str | None = None) -> Source:
    """Resolve SOURCE (a file or a built-in name) into a :class:`Source`.

    Raises:
        UsageError: missing or unreadable file, a file MuJoCo's compiler rejects, an unknown
            example or keyframe.
    """
    path = pathlib.Path(spec)
    looks_like_file = path.suffix.lower() in (".xml", ".urdf", ".mjcf") or os.sep in spec or "/" in spec
    if spec in catalog.EXAMPLES and not path.exists():
        return load_example(spec, keyframe)
    if spec in catalog.ROBOT_MODELS and not path.exists():
        return load_file(catalog.robot_model_path(spec), keyframe, name=spec)
    if path.exists() or looks_like_file:
        if not path.exists():
            raise UsageError(f"model file not found: {spec!r}")
        if not path.is_file():
            raise UsageError(f"not a file: {spec!r}")
        return load_file(path, keyframe)
    names = ", ".join([*catalog.EXAMPLES, *catalog.ROBOT_MODELS])
    raise UsageError(
        f"unknown example {spec!r}: built-in ones are {names}; or give an .xml (MJCF) or "
        ".urdf file"
    )


def load_file(path: pathlib.Path, keyframe, name=None) -> Source:
    """An MJCF or URDF file as a :class:`Source`, with the content jaxbody ignores."""
    setup_jax()
    read = from_urdf if path.suffix.lower() == ".urdf" else from_mjcf
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            model = read(str(path))
        except (ValueError, FileNotFoundError, TypeError, OSError) as e:
            raise UsageError(one_line(e)) from None
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
    q_labels, v_labels = model_labels(model)
    return Source(name or path.stem, str(path), model, "model", q_labels, v_labels, q0, v0,
                  ignored, start)


def load_example(name, keyframe) -> Source:
    """The built-in example ``name`` as a :class:`Source`, at its default state."""
    setup_jax()
    if keyframe is not None:
        raise UsageError(f"--keyframe: the built-in example {name!r} has no keyframes")
    ex = catalog.EXAMPLES[name]
    system = catalog.example_system(name)
    kind = "planar" if hasattr(system, "tree") else "embedded"
    labels = list(ex.q_names)
    return Source(name, f"jaxbody.examples.{name}()", system, kind, labels, labels,
                  jnp.asarray(ex.q0), jnp.asarray(ex.v0), [], "the example's default state")


def model_labels(model):
    """Names of the q and v entries of a spatial model (MuJoCo qpos/qvel layout)."""
    q_parts = {HINGE: [""], SLIDE: [""], BALL: ["qw", "qx", "qy", "qz"],
               FREE: ["x", "y", "z", "qw", "qx", "qy", "qz"]}
    v_parts = {HINGE: [""], SLIDE: [""], BALL: ["wx", "wy", "wz"],
               FREE: ["vx", "vy", "vz", "wx", "wy", "wz"]}
    q_labels, v_labels = [], []
    for kind, name in zip(model.joints.type, model.joints.names):
        q_labels += [f"{name}.{p}" if p else name for p in q_parts[kind]]
        v_labels += [f"{name}.{p}" if p else name for p in v_parts[kind]]
    return q_labels, v_labels


def initial_state(src: Source, args):
    """``(q0, v0)``: the source's start unless ``--q0``/``--v0`` give it."""
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
