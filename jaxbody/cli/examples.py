"""``jaxbody examples``: the papers' systems and the robot models shipped with jaxbody."""

from ..catalog import EXAMPLES, MODELS_DIR, ROBOT_MODELS

__all__ = ["add_parser", "run"]


def add_parser(sub):
    """The ``examples`` sub-command."""
    sub.add_parser("examples", help="list the built-in examples and robot models",
                   description="List the papers' systems and the robot models shipped with jaxbody.")


def run(args) -> int:
    """``jaxbody examples``: returns the exit status."""
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
