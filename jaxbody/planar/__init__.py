"""Planar systems with parallel hinge axes in absolute angles (docs/mathematics.md, "Planar systems in absolute angles" to "Corollary 8"; the paper's Corollaries 5–7).

Modules, re-exported here: :mod:`~jaxbody.planar.parameters` (the data of a planar system:
tree, parameters, frames and angles), :mod:`~jaxbody.planar.system` (the :class:`PlanarSystem`
users hold and the builders :func:`from_parents` and :func:`chain`),
:mod:`~jaxbody.planar.convert` (:func:`from_model` for a spatial model with parallel hinges,
and the one planarity test), :mod:`~jaxbody.planar.dynamics` (mass matrix, bias, forward and
inverse dynamics, reactions through the same Statement-1 kernel as the spatial path,
energies) and :mod:`~jaxbody.planar.joint_space` (relative angles);
:mod:`~jaxbody.planar.arrays` holds the builders' array helpers. The decoupling report of
Cor. 8 is :func:`jaxbody.design.decoupling_report`.
"""

from .parameters import ParamLike as ParamLike, PlanarParameters as PlanarParameters
from .system import (
    DOWNWARD_VERTICAL as DOWNWARD_VERTICAL,
    PlanarSystem as PlanarSystem,
    chain as chain,
    from_parents as from_parents,
    horizontal_to_vertical as horizontal_to_vertical,
    validate as validate,
    vertical_to_horizontal as vertical_to_horizontal,
)
from .convert import (
    NotPlanar as NotPlanar,
    aligned_system as aligned_system,
    from_model as from_model,
    plane_basis as plane_basis,
    planarity as planarity,
)
from .dynamics import (
    absolute_angles as absolute_angles,
    augmented_bodies as augmented_bodies,
    augmented_bodies_in_body_axes as augmented_bodies_in_body_axes,
    bias_forces as bias_forces,
    body_positions as body_positions,
    forward_dynamics as forward_dynamics,
    generalized_forces as generalized_forces,
    inverse_dynamics as inverse_dynamics,
    joint_reactions as joint_reactions,
    kinetic_energy as kinetic_energy,
    mass_matrix as mass_matrix,
    point_load as point_load,
    point_position as point_position,
    potential_energy as potential_energy,
    power as power,
    root_force as root_force,
    total_energy as total_energy,
)
from .joint_space import (
    absolute_to_relative as absolute_to_relative,
    joint_bias_forces as joint_bias_forces,
    joint_mass_matrix as joint_mass_matrix,
    relative_to_absolute as relative_to_absolute,
)
