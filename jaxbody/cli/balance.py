"""``jaxbody balance MODEL_OR_EXAMPLE``: the augmented static moments, the bodies the corrected
Cor. 8 requires to balance, and a proposed design (``jaxbody.design``)."""

import argparse
import pathlib
import sys
from collections.abc import Sequence

import numpy as np

from .. import catalog
from ..design import balance, required_bodies, resolve_bodies, static_balance, static_moments
from ..dynamics import augmented_bodies
from ..io.mujoco import from_mjcf
from ..planar import PlanarSystem, augmented_bodies_in_body_axes
from .arguments import setup_jax

__all__ = ["add_parser", "run", "cli_balance", "EXAMPLES"]

#: The planar examples ``jaxbody balance`` takes by name: name -> the planar system.
EXAMPLES = {
    "double_pendulum": lambda: catalog.example_system("double_pendulum"),
    "three_link_manipulator": lambda: catalog.example_system("three_link_manipulator"),
    "cart_pendulum": lambda: catalog.example_system("cart_pendulum").system,
}


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _UsageError(message)


def add_parser(sub):
    """The ``balance`` sub-command: its arguments are parsed by :func:`cli_balance`."""
    sub.add_parser("balance", help="balancing design (jaxbody.design); `jaxbody balance --help`",
                   add_help=False)


def run(args) -> int:
    """``jaxbody balance``: everything after ``balance`` goes to :func:`cli_balance`."""
    return cli_balance(args.argv)


def _load(target):
    """The system named by MODEL_OR_EXAMPLE: an example, an MJCF file or a shipped robot model."""
    path = pathlib.Path(target)
    if target in EXAMPLES and not path.exists():
        return EXAMPLES[target]()
    if path.is_file() or (target in catalog.ROBOT_MODELS and not path.exists()):
        if not path.is_file():  # a robot model shipped with jaxbody
            path = catalog.robot_model_path(target)
        try:
            return from_mjcf(str(path))
        except Exception as err:  # the importer's message, on one line
            raise _UsageError(f"cannot load {target}: {str(err).splitlines()[0]}") from None
    raise _UsageError(
        f"{target!r} is neither a file, an example ({', '.join(sorted(EXAMPLES))}) nor a "
        f"shipped robot model ({', '.join(catalog.ROBOT_MODELS)})"
    )


def cli_balance(argv: Sequence[str] | None = None) -> int:
    """``jaxbody balance MODEL_OR_EXAMPLE``: print the augmented static moments, the bodies
    the corrected Cor. 8 requires to balance, and a proposed design (closed form and, with
    ``--optimise``, the optimised one). Bad input: one line on stderr, exit status 2."""
    parser = _Parser(prog="jaxbody balance", description=cli_balance.__doc__.splitlines()[0])
    parser.add_argument("target", metavar="MODEL_OR_EXAMPLE",
                        help=f"an MJCF file, one of {', '.join(sorted(EXAMPLES))} or a shipped robot "
                             "model (panda, ur5e, anymal_c)")
    parser.add_argument("--bodies", default=None, help="comma-separated bodies to decouple, or 'all'")
    parser.add_argument("--radius", type=float, default=None, help="counterweight distance from the joint")
    parser.add_argument("--optimise", action="store_true", help="also run the optax synthesis")
    parser.add_argument("--penalty-mass", type=float, default=1.0)
    parser.add_argument("--penalty-inertia", type=float, default=1.0)
    try:
        args = parser.parse_args(argv)
        if args.radius is not None and not args.radius > 0:
            raise _UsageError(f"--radius must be positive, got {args.radius}")
        setup_jax()
        system = _load(args.target)
        bodies = None
        if args.bodies is not None:
            bodies = "all" if args.bodies == "all" else [
                int(b) if b.strip().lstrip("-").isdigit() else b.strip() for b in args.bodies.split(",")
            ]
        try:
            req = resolve_bodies(system, bodies, "bodies")
        except ValueError as err:
            raise _UsageError(str(err)) from None
    except _UsageError as err:
        print(f"jaxbody balance: error: {err}", file=sys.stderr)
        return 2

    names = system.tree.names
    mbar = np.asarray(static_moments(system), dtype=np.float64)
    msub = (np.asarray(augmented_bodies_in_body_axes(system).subtree_mass) if isinstance(system, PlanarSystem)
            else np.asarray(augmented_bodies(system, system.qpos0).subtree_mass))
    must = set(required_bodies(system))
    print(f"augmented static moments of {getattr(system, 'name', type(system).__name__)} "
          f"(body axes, about each joint)")
    print(f"{'body':>16} {'m_k':>10} {'|m̄_k|':>10}  m̄_k{'':<24} must vanish")
    for k, name in enumerate(names):
        print(f"{name:>16} {msub[k]:10.5g} {np.linalg.norm(mbar[k]):10.5g}  "
              f"{np.array2string(mbar[k], precision=5, suppress_small=True):<28} {'yes' if k in must else 'no'}")
    if not req:
        print("nothing to balance: no body has a moving carrier (use --bodies all for static balance)")
        return 0
    try:
        _, rep = static_balance(system, bodies=req, radius=args.radius)
    except ValueError as err:
        print(f"jaxbody balance: error: {err}", file=sys.stderr)
        return 2
    print("proposed design (closed form, counterweight opposite each static moment):")
    print(rep.summary())
    if args.optimise:
        _, rep2 = balance(system, bodies=req, penalty={"mass": args.penalty_mass, "inertia": args.penalty_inertia})
        print("optimised design (optax, penalties on added mass and inertia):")
        print(rep2.summary())
    return 0
