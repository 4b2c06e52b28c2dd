"""The systems shipped with jaxbody: the papers' worked examples and the robot models.

One table of each, read by the command line (``jaxbody simulate NAME``, ``jaxbody info NAME``,
``jaxbody balance NAME``) and by anyone who wants a system by name.
"""

import dataclasses
import pathlib

from . import examples

__all__ = ["Example", "EXAMPLES", "MODELS_DIR", "ROBOT_MODELS", "example_system", "robot_model_path"]

#: Folder of the shipped robot models (MJCF, meshes removed; licences alongside).
MODELS_DIR = pathlib.Path(__file__).resolve().parent / "models"


@dataclasses.dataclass(frozen=True)
class Example:
    """A worked example of :mod:`jaxbody.examples`: what it is, and where a run starts.

    Attributes:
        summary: one line naming the example and its coordinates.
        q_names: the names of its coordinates.
        q0, v0: the initial state ``jaxbody simulate`` starts from.
    """

    summary: str
    q_names: tuple[str, ...]
    q0: tuple[float, ...]
    v0: tuple[float, ...]


#: The papers' systems of ``jaxbody.examples``: name -> summary, coordinate names and the
#: initial state ``jaxbody simulate`` starts from (override with ``--q0``/``--v0``).
EXAMPLES: dict[str, Example] = {
    "double_pendulum": Example(
        "Example 1: double pendulum in a vertical plane; absolute angles from the downward vertical",
        ("alpha1", "alpha2"), (1.0, -0.5), (0.0, 0.0)),
    "three_link_manipulator": Example(
        "Example 2: shoulder, forearm and hand in a horizontal plane (no gravity); absolute angles",
        ("alpha1", "alpha2", "alpha3"), (0.0, 0.5, 1.0), (1.0, -0.5, 0.5)),
    "cart_pendulum": Example(
        "Example 3: cart on a smooth horizontal rail carrying a pendulum; (x, phi)",
        ("x", "phi"), (0.0, 1.0), (0.0, 0.0)),
    "oscillating_support_pendulum": Example(
        "Example 4: pendulum whose pivot oscillates along an inclined line; phi",
        ("phi",), (0.5,), (0.0,)),
    "vertical_line_double_pendulum": Example(
        "Example 5: double pendulum with its end point kept on the vertical through the pivot; phi",
        ("phi",), (0.5,), (0.0,)),
    "wheelset_pendulum": Example(
        "Example 6: wheelset rolling on rails with a pendulum on its axle; (x, phi)",
        ("x", "phi"), (0.0, 0.8), (0.0, 0.0)),
}

#: Robot models shipped in ``jaxbody/models`` (MJCF, meshes removed; licences alongside).
ROBOT_MODELS: dict[str, str] = {
    "panda": "Franka Emika Panda arm without hand (7 hinges), keyframe 'home'",
    "ur5e": "Universal Robots UR5e arm (6 hinges), keyframe 'home'",
    "anymal_c": "ANYbotics ANYmal C quadruped (free base and 12 hinges)",
}


def example_system(name: str):
    """The system of the example ``name`` of :data:`EXAMPLES`, with the papers' parameters."""
    return getattr(examples, name)()


def robot_model_path(name: str) -> pathlib.Path:
    """The MJCF file of the shipped robot model ``name`` of :data:`ROBOT_MODELS`."""
    return MODELS_DIR / f"{name}.xml"
