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
import os
import re
import sys

from .. import __version__
from ..catalog import EXAMPLES, MODELS_DIR, ROBOT_MODELS
from . import balance, demo, examples, info, simulate
from .arguments import Parser, UsageError, error_line

__all__ = ["main", "EXAMPLES", "MODELS_DIR", "ROBOT_MODELS"]

#: The sub-commands in the order ``jaxbody --help`` lists them: each module adds its parser
#: and runs it.
COMMANDS = {"simulate": simulate, "info": info, "examples": examples, "balance": balance, "demo": demo}


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxbody`` argument parser with every sub-command."""
    parser = Parser(prog="jaxbody", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"jaxbody {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS.values():
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxbody`` command; returns the exit status."""
    from_command_line = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "balance":
        # Everything after `balance` belongs to the balance command's own parser.
        args = argparse.Namespace(command="balance", argv=argv[1:])
    else:
        parser = build_parser()
        args = parser.parse_args(argv)
        if args.command not in COMMANDS:
            parser.print_help()
            return 2
    try:
        return COMMANDS[args.command].run(args)
    except UsageError as e:
        error_line(args.command, str(e))
        return 2
    except KeyboardInterrupt:
        error_line(args.command, "interrupted")
        if from_command_line:
            # the interrupt can abandon a computation XLA is still running on its own threads,
            # and tearing the interpreter down under it crashed the process now and then
            # (SIGSEGV instead of status 130); the files are written and closed: leave at once
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(130)
        return 130
    except Exception as e:  # never a traceback on the command line, unless asked for
        if os.environ.get("JAXBODY_DEBUG"):
            raise
        error_line(args.command, _message(e))
        return 1


def _message(err: Exception) -> str:
    """What an unexpected error says, without a traceback: JAX's runtime errors (from a check or
    a failure inside a compiled program) carry the text of the exception raised inside it after
    a traceback and a banner; that exception's own line is the message."""
    text = str(err)
    if "Traceback (most recent call last)" in text:
        raised = re.findall(r"^(?:[\w.]+\.)?(\w*(?:Error|Exception)): (.+)$", text, flags=re.M)
        if raised:
            name, message = raised[-1]
            return f"{name.lstrip('_')}: {message}"
    return f"{type(err).__name__}: {text}"
