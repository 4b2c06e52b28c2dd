"""Loop closures a model carries: :class:`LoopSpec`.

A spec is plain static data (bodies, body-frame points, the reference frame and the directions
constrained in it, the directions dropped and why), so it sits below the model, which holds a
tuple of them (``Model.loops``). The directions a loop constrains are found from the model's
kinematics (:mod:`jaxbody.loop_directions`); the constraints built from the specs are
:class:`jaxbody.constraints.LoopClosure` (:func:`jaxbody.constraints.loop_closures`).
"""

from typing import NamedTuple

__all__ = ["LoopSpec"]


class LoopSpec(NamedTuple):
    """A loop closure a model carries (MJCF ``<equality><connect>``): the point ``point_a`` of
    body ``body_a`` stays on the point ``point_b`` of body ``body_b`` (body frames; ``-1`` is
    the world), along the directions ``axes`` of the frame of body ``frame`` (``-1``: world
    axes; ``None``: the lowest common ancestor of the two bodies). ``axes=None``: found when a
    scene is built (:func:`jaxbody.constraints.loop_closures`). ``dropped`` says, one sentence
    each, which directions were left out and why (the loop cannot open along them, or they
    repeat another loop's rows). Static and hashable; :func:`jaxbody.scene` turns each into a
    :class:`jaxbody.constraints.LoopClosure`."""

    label: str
    body_a: int
    point_a: tuple[float, float, float]
    body_b: int
    point_b: tuple[float, float, float]
    axes: tuple[tuple[float, float, float], ...] | None = None
    frame: int | None = None
    dropped: tuple[str, ...] = ()
