"""Coordinate charts: where a system's coordinates stop describing its configuration.

Angles such as Euler angles cover the configuration space only away from their singular set
(z–x–z angles where the middle angle's sine vanishes: there the rates divide by it). A system
declares its chart with a method ``coordinate_chart() -> CoordinateChart`` (the simulation
protocol makes it optional); the step guard of :func:`jaxbody.simulate` ends a solve whose
accepted step leaves the chart with the result code ``singular``, member by member in a batch,
and the failure message names the chart, the coordinate and the time.
"""

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._types import Array, Bool, Float

__all__ = ["CoordinateChart", "chart_of"]


class CoordinateChart(eqx.Module):
    """Where a system's coordinates are regular: every margin ``margins(q)[i]`` above ``bound``.

    The chart ends where a margin reaches zero (the coordinates degenerate); a solve stops once
    a margin falls to ``bound``. ``bound`` defaults to ``ε^(1/4)`` of the state's dtype (1.2e-4
    in float64, 1.8e-2 in float32): the kinematics divides by the margin, so the rates grow like
    ``1/margin`` and an adaptive solver's steps shrink as it approaches; without the bound it
    spends its whole step budget just short of the singular set and stops there with
    ``max_steps_reached``, which names no cause.

    Attributes:
        name: the chart in words (e.g. ``"z-x-z Euler angles (ψ, θ, φ)"``).
        coordinates: one label per margin (e.g. ``("sin θ (θ = q[3], the nutation)",)``).
        margins: ``q -> (k,)`` distances from the singular set, positive inside the chart.
        advice: what to do instead (e.g. stop earlier with an event on the margin).
        bound: the margin at which the chart counts as left (``None``: ``ε^(1/4)`` of the dtype).
    """

    name: str = eqx.field(static=True)
    coordinates: tuple[str, ...] = eqx.field(static=True)
    margins: Callable = eqx.field(static=True)
    advice: str = eqx.field(static=True, default="")
    bound: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not isinstance(self.coordinates, tuple) or not self.coordinates:
            raise ValueError(f"CoordinateChart {self.name!r}: coordinates must be a non-empty tuple of labels")
        if self.bound is not None and not float(self.bound) > 0:
            raise ValueError(f"CoordinateChart {self.name!r}: bound must be positive, got {self.bound}")

    def limit(self, dtype) -> float:
        """The margin at which the chart counts as left, for states of ``dtype``."""
        return float(self.bound) if self.bound is not None else float(np.finfo(dtype).eps) ** 0.25

    def margin_values(self, q: Float[Array, " nq"]) -> Float[Array, " k"]:
        """The margins at ``q`` as a vector (one per label of :attr:`coordinates`)."""
        return jnp.reshape(jnp.asarray(self.margins(q), q.dtype), (len(self.coordinates),))

    def inside(self, q: Float[Array, " nq"]) -> Bool[Array, ""]:
        """Whether ``q`` lies inside the chart (every margin above :meth:`limit`)."""
        return jnp.all(self.margin_values(q) > self.limit(q.dtype))

    def explain(self, margins, t: float, dtype) -> str:
        """The failure message of a solve that left the chart at time ``t`` with ``margins``."""
        margins = np.asarray(margins, dtype=np.float64).reshape(-1)
        i = int(np.argmin(margins))
        limit = self.limit(dtype)
        text = (f"the coordinates left their chart, the {self.name}: {self.coordinates[i]} = {margins[i]:.3g} at "
                f"t = {t:.6g}, at or below the chart's bound {limit:.3g}; the coordinates are singular where it "
                "reaches 0 and the motion cannot be followed in them beyond")
        return text + (f". {self.advice}" if self.advice else "")

    def explain_at(self, q, t: float) -> str | None:
        """:meth:`explain` for a concrete state ``q`` outside the chart; ``None`` inside it."""
        q = jnp.asarray(q)
        margins = np.asarray(self.margin_values(q))
        if np.all(margins > self.limit(q.dtype)):
            return None
        return self.explain(margins, t, q.dtype)


def chart_of(system) -> CoordinateChart | None:
    """The chart a system (or a scene's system) declares with ``coordinate_chart()``, or ``None``."""
    declare = getattr(system, "coordinate_chart", None)
    chart = declare() if callable(declare) else None
    if chart is not None and not isinstance(chart, CoordinateChart):
        raise ValueError(f"{type(system).__name__}.coordinate_chart() must return a jaxbody.scene.CoordinateChart "
                         f"or None, got {type(chart).__name__}")
    return chart
