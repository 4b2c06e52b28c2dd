"""The scene the options of ``jaxbody simulate`` and ``jaxbody info`` declare (``jaxbody.scene``)."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..constraints import loop_system
from ..joints import BALL, FREE, HINGE, SLIDE
from ..scene import scene
from .arguments import UsageError, one_line
from .sources import Source

__all__ = ["Constant", "scene_from_options"]


class Constant(eqx.Module):
    """A constant ``f(t, q, v) = value`` (an array leaf: one compiled program for any value)."""

    value: object

    def __call__(self, t, q, v):
        return self.value


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


def scene_from_options(src: Source, args):
    """The scene the options declare (``jaxbody.scene``), or a UsageError naming the option."""
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
            dofs = {HINGE: 1, SLIDE: 1, BALL: 3, FREE: 6}
            sizes = [(dofs[int(k)],) for k in system.joints.type]
            where = [int(a) for a in system.joints.dofadr]
        else:
            names, sizes, where = list(src.q_labels), [(1,)] * system.nv, list(range(system.nv))
        tau = np.zeros(system.nv)
        for i, values in _named_vectors("--torque", args.torque, names, sizes, "joint" if spatial else "coordinate").items():
            tau[where[i]:where[i] + len(values)] = values
        kw["actuation"] = Constant(jnp.asarray(tau, dtype))
    if args.load:
        names = list(system.body_names)
        wrench = np.zeros((system.n_body, 6))
        for i, values in _named_vectors("--load", args.load, names, [(3, 6)] * len(names), "body").items():
            wrench[i, :len(values)] = values
        kw["loads"] = Constant(jnp.asarray(wrench, dtype))
    if spatial and system.loops and src.start.startswith("keyframe"):
        # the loops checked and partitioned at the keyframe (projected onto them when it does
        # not close them), where the simulation starts, rather than at qpos0
        kw["constraints"] = "keyframe"
    try:
        if kw.get("constraints") == "keyframe":
            kw["constraints"] = loop_system(system, q_ref=src.q0)
        return scene(system, **kw)
    except ValueError as e:
        raise UsageError(one_line(str(e))) from None
