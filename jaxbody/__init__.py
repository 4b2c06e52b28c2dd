"""jaxbody: differentiable multibody dynamics in JAX.

Augmented-body equations of rigid-body trees (Telegin) and Maggi's equations in
quasi-coordinates (Byachkov); see ``shared/spec/equations.md`` for the mathematics.
The library never changes global JAX configuration on import; enable float64 with
``jax.config.update("jax_enable_x64", True)`` for accuracy work.
"""

from . import tree as tree
from .tree import BodyTree as BodyTree
from .joints import (
    FREE as FREE,
    BALL as BALL,
    SLIDE as SLIDE,
    HINGE as HINGE,
    Free as Free,
    Ball as Ball,
    Slide as Slide,
    Hinge as Hinge,
    JointLayout as JointLayout,
)
from .model import Model as Model, ModelBuilder as ModelBuilder, validate_parameters as validate_parameters
from .augmented import (
    AugmentedBodies as AugmentedBodies,
    subtree_mass as subtree_mass,
    static_moment as static_moment,
    augmented_inertia as augmented_inertia,
    augmented_moment_of_inertia as augmented_moment_of_inertia,
)

# --- spatial engine (dynamics.py, kinematics.py, spatial.py) ---
# --- planar systems (planar.py, examples) ---
# --- simulation (simulate.py) ---
# --- import (io/mujoco.py) ---

__version__ = "0.1.0"
