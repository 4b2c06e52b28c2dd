"""jaxbody: differentiable multibody dynamics in JAX.

Augmented-body equations of rigid-body trees (Telegin) and Maggi's equations in
quasi-coordinates (Byachkov). One engine with one state: a :class:`Model` (or a planar
system), the state pytree :class:`Data` computed once by :func:`compute_data`, and kernels
``jb.kernels.*(model, data, ...)``; the functions ``jb.mass_matrix(model, q)`` ... are those
kernels behind one input check (:func:`check_inputs`). Conventions: ``docs/conventions.md``.
The library changes two global settings on import: it turns JAX's persistent compilation
cache on in its own cache directory, unless ``JAXBODY_JAX_CACHE=0`` or the user configured one
(:mod:`jaxbody.compilation_cache`), and, with jaxlib 0.10, it adds
``--xla_cpu_use_fusion_emitters=false`` to ``XLA_FLAGS`` unless they set that flag (XLA CPU's
fusion emitters compile jaxbody's programs slowly; effective only if JAX has not computed
anything yet). Enable float64 with
``jax.config.update("jax_enable_x64", True)`` for accuracy work.
"""

# first: XLA reads its flags when JAX's backend starts, and JAX decides at the first
# compilation whether its persistent cache is used
from ._xla import set_default_xla_flags as _set_default_xla_flags

_set_default_xla_flags()

from . import compilation_cache as compilation_cache  # noqa: E402

compilation_cache.enable()

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
from .model import Model as Model, ModelBuilder as ModelBuilder
from .validation import check_inputs as check_inputs, validate_parameters as validate_parameters
from .augmented import (
    AugmentedBodies as AugmentedBodies,
    subtree_mass as subtree_mass,
    static_moment as static_moment,
    augmented_inertia as augmented_inertia,
    augmented_moment_of_inertia as augmented_moment_of_inertia,
)

# --- spatial engine (kinematics.py, spatial.py, data.py, kernels.py, dynamics.py) ---
from . import kinematics as kinematics
from . import spatial as spatial
from . import kernels as kernels
from .data import Data as Data, compute_data as compute_data
from .kinematics import (
    forward_kinematics as forward_kinematics,
    qpos_rate as qpos_rate,
    integrate_qpos as integrate_qpos,
    normalize_qpos as normalize_qpos,
)
from .dynamics import (
    augmented_bodies as augmented_bodies,
    mass_matrix as mass_matrix,
    bias_forces as bias_forces,
    inverse_dynamics as inverse_dynamics,
    forward_dynamics as forward_dynamics,
    joint_reactions as joint_reactions,
    kinetic_energy as kinetic_energy,
    potential_energy as potential_energy,
    passive_forces as passive_forces,
)
from . import linalg as linalg
from .batching import vmap_chunked as vmap_chunked
# --- planar systems (planar/, examples/) and design (design/) ---
from . import planar as planar
from . import examples as examples
# --- scenes and simulation (scene/, effects/, simulation/) ---
from . import effects as effects
from .effects import FourierTorque as FourierTorque  # a joint torque the one-call native solves evaluate
from .scene import Scene as Scene, scene as scene, Phases as Phases, Event as Event
from .scene import CoordinateChart as CoordinateChart
from .simulation import (
    DynamicalSystem as DynamicalSystem,
    RESULTS as RESULTS,
    SimulationError as SimulationError,
    Solution as Solution,
    load_solution as load_solution,
    simulate as simulate,
    simulate_batch as simulate_batch,
)
# --- identification and balancing design (identify/, design/) ---
from . import identify as identify
from . import design as design
# --- constraints: Maggi's equations (maggi/, constraints.py) ---
from . import maggi as maggi
from . import constraints as constraints
# --- import (io/mujoco.py) ---
from .io.mujoco import (
    from_mjcf as from_mjcf,
    from_urdf as from_urdf,
    from_mujoco as from_mujoco,
)

__version__ = "0.1.0"

# --- names that moved in the restructuring into one package per concept: still found at their
# old places, with a DeprecationWarning that names the new one. They are resolved here, where
# both old and new modules are loaded, so no module imports upwards to serve them.
import warnings as _warnings

from . import backends as _backends
from . import simulation as _simulation

_MOVED_ATTRIBUTES = {
    kernels: {name: (_backends, name) for name in ("acceleration", "resolve_kernel", "KERNELS", "DEFAULT_KERNEL")},
    maggi: {
        name: (_simulation, name)
        for name in ("PartitionSolver", "partition_solver", "partition_report", "with_best_partition")
    },
}
_MOVED_MODULES = {"native": _backends.native, "unrolled": _backends.unrolled}


def _moved(old: str, new: str, value):
    _warnings.warn(f"{old} moved to {new}; the old name will be removed", DeprecationWarning, stacklevel=3)
    return value


def _module_getattr(module):
    def __getattr__(name):
        if name in _MOVED_ATTRIBUTES[module]:
            target, new = _MOVED_ATTRIBUTES[module][name]
            return _moved(f"{module.__name__}.{name}", f"{target.__name__}.{new}", getattr(target, new))
        raise AttributeError(f"module {module.__name__!r} has no attribute {name!r}")

    return __getattr__


for _module in _MOVED_ATTRIBUTES:
    _module.__getattr__ = _module_getattr(_module)


def __getattr__(name):
    if name in _MOVED_MODULES:
        return _moved(f"jaxbody.{name}", _MOVED_MODULES[name].__name__, _MOVED_MODULES[name])
    raise AttributeError(f"module 'jaxbody' has no attribute {name!r}")

