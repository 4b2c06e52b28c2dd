"""Scenes: a mechanism plus the effects it declares, and nothing else.

A :class:`Scene` is what :func:`jaxbody.simulate` integrates. It holds a system (a spatial
:class:`jaxbody.Model`, a planar system, or any object with the simulation protocol) and a
tuple of effect modules (:mod:`jaxbody.effects`); its vector field is

    q̇ = qdot(q, v),     M(q) a = Σ_effects f_e(t, q, v) − c(q, v)     (+ constraints)

where ``c`` holds only the velocity-product terms of the tree (Statement 1 with no gravity and
no loads): gravity, springs, dampers, actuation, loads and a moving support are effects, so an
undeclared one is absent from the traced program.

:class:`Scene` is abstract: :func:`scene` builds one of its final classes, one per path —
:class:`SpatialScene` (the spatial tree), :class:`PlanarScene` (absolute angles of parallel
hinges) and :class:`SystemScene` (planar systems and other objects with the simulation
protocol); ``scene.path`` names it. Coordinates are always the system's own (for a
:class:`Model`, MuJoCo's ``qpos``/``qvel``); on the planar path the absolute angles are an
internal change of variables.

Modules: :mod:`~jaxbody.scene.base` (the protocol), :mod:`~jaxbody.scene.spatial`,
:mod:`~jaxbody.scene.planar`, :mod:`~jaxbody.scene.system` (one per path),
:mod:`~jaxbody.scene.builder`
(:func:`scene`), :mod:`~jaxbody.scene.events` (:class:`Event`, :class:`Phases`) and
:mod:`~jaxbody.scene.chart` (:class:`CoordinateChart`: where a system's coordinates are regular).
"""

from .base import ModelScene as ModelScene, Scene as Scene
from .builder import scene as scene
from .chart import CoordinateChart as CoordinateChart
from .events import Event as Event, Phases as Phases
from .planar import PlanarScene as PlanarScene
from .spatial import SpatialScene as SpatialScene
from .system import SystemScene as SystemScene, own_constraints as own_constraints

__all__ = ["Scene", "scene", "CoordinateChart", "Phases", "Event", "SpatialScene", "PlanarScene", "SystemScene", "own_constraints"]
