"""What every command shares: the argument parser, the option types, the scene options, the
one-line error report and the float64 set-up of JAX."""

import argparse
import math
import sys

import jax

from .._xla import set_default_xla_flags

__all__ = [
    "SOURCE_HELP", "UsageError", "Parser", "positive", "count", "floats", "nonnegative", "assignment",
    "add_scene_options", "one_line", "error_line", "setup_jax",
]


#: Help of the SOURCE argument of ``simulate`` and ``info``.
SOURCE_HELP = (
    "an MJCF (.xml) or URDF (.urdf) file, or a built-in example "
    "(`jaxbody examples` lists them)"
)


class UsageError(Exception):
    """A bad argument or input file: reported on one line, exit status 2."""


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``prog: error: message``) and exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def positive():
    """Argument type: a positive finite number."""
    def parse(text):
        try:
            x = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(x) and x > 0):
            raise argparse.ArgumentTypeError(f"must be positive and finite, got {text}")
        return x

    return parse


def count(minimum):
    """Argument type: an integer of at least ``minimum``."""
    def parse(text):
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if n < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {n}")
        return n

    return parse


def floats(text):
    """Argument type: finite numbers separated by commas (or spaces)."""
    try:
        values = tuple(float(s) for s in text.replace(",", " ").split())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}") from None
    if not values or not all(math.isfinite(x) for x in values):
        raise argparse.ArgumentTypeError(f"expected finite numbers separated by commas, got {text!r}")
    return values


def nonnegative(text):
    """Argument type: a non-negative finite number."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(x) and x >= 0):
        raise argparse.ArgumentTypeError(f"must be non-negative and finite, got {text}")
    return x


def assignment(text):
    """``NAME=V1[,V2...]`` -> ``(NAME, (V1, V2, ...))``."""
    name, sep, values = text.partition("=")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE[,VALUE...], got {text!r}")
    return name.strip(), floats(values)


def add_scene_options(p, verb):
    """The scene options shared by ``simulate`` and ``info`` (they map to ``jaxbody.scene``)."""
    grav = p.add_mutually_exclusive_group()
    grav.add_argument("--gravity", type=floats, default=None, metavar="GX,GY,GZ",
                      help=f"{verb} this gravity vector in m/s² (world frame) instead of the model's")
    grav.add_argument("--no-gravity", action="store_true", help=f"{verb} no gravity")
    p.add_argument("--no-springs", action="store_true", help=f"{verb} no joint springs")
    damp = p.add_mutually_exclusive_group()
    damp.add_argument("--no-dampers", action="store_true", help=f"{verb} no joint dampers")
    damp.add_argument("--damping", type=nonnegative, default=None, metavar="VALUE",
                      help=f"{verb} this viscous damping on every DoF (N·m·s/rad or N·s/m) instead of the model's")
    p.add_argument("--torque", type=assignment, action="append", default=[], metavar="JOINT=VALUE",
                   help="a constant generalized force on a joint, by name (hinge: N·m, slide: N; ball: 3 "
                        "values, free: 6; built-in examples: the example's drive in the layout of its "
                        "velocities, by coordinate name, e.g. the hinge moments of the double pendulum); repeatable")
    p.add_argument("--load", type=assignment, action="append", default=[], metavar="BODY=FX,FY,FZ[,MX,MY,MZ]",
                   help="a constant world force (N) and moment (N·m) at a body's centre of mass, by name "
                        "(MuJoCo xfrc_applied); repeatable")


def one_line(text: object) -> str:
    """A (multi-line) message (a string or an exception) on one line, its lines joined by ``; ``."""
    return "; ".join(s.strip() for s in str(text).splitlines() if s.strip())


def error_line(command, message):
    """``jaxbody COMMAND: error: MESSAGE`` on stderr, after what was printed so far."""
    sys.stdout.flush()
    print(f"jaxbody {command}: error: {one_line(message)}", file=sys.stderr)


def setup_jax():
    """JAX with float64, set up before its backend starts."""
    # Must precede JAX's backend initialisation (known XLA CPU issue with jax 0.10).
    set_default_xla_flags()
    jax.config.update("jax_enable_x64", True)
    return jax
