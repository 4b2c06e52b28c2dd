"""Constraints on a base system: rows ``f*(t, q, x) = 0`` of first order in the
quasi-velocities (docs/maggi.md M.6), and for holonomic ones their position residual ``φ(t, q)``.

:class:`Constraint` is the protocol (subclass it, parameters as array fields);
:class:`VelocityConstraint` builds one from functions. Ready constraints on a
:class:`jaxbody.Model` are in :mod:`jaxbody.constraints`.
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax.numpy as jnp

from .._types import Array

__all__ = ["Constraint", "VelocityConstraint"]


class Constraint(eqx.Module):
    """Protocol of a constraint on a base system (subclass it; parameters as array fields).

    ``size`` rows ``f*(t, q, x) = 0`` (:meth:`velocity`); ``linear`` says ``f*`` is affine in
    ``x`` (then ``G`` does not depend on ``x``); holonomic constraints also give their
    position residual ``φ(t, q)`` (:meth:`position`, same rows, ``dφ/dt = f*``), used by the
    Baumgarte stabilisation and :func:`project_positions`; non-holonomic ones return ``None``.
    """

    # the base system is passed in, not stored: a scene rebinds the constraints to its own model,
    # whose parameters are then the ones evaluated and differentiated
    def velocity(self, base, t, q, x) -> Array:
        raise NotImplementedError

    # None marks a non-holonomic constraint: no φ for the ω²φ term or for position projection
    def position(self, base, t, q) -> Array | None:
        return None

    # None: the reduced dynamics differentiates velocity() in forward mode. A constraint whose
    # rows come from the kinematics can say it in closed form: the forward-mode derivative of
    # the kinematics is most of a solve's compiled program and of its run time
    def velocity_bias(self, base, t, q, x) -> Array | None:
        """``γ = ∂f*/∂q·q̇ + ∂f*/∂t`` at fixed ``x`` (M.6), the part of ``df*/dt`` that ``ẋ`` does
        not carry, in closed form; ``None`` (the default) to have it differentiated."""
        return None

    # None: the reduced dynamics differentiates velocity() with respect to x. A closed form
    # saves a forward-mode pass with one tangent per quasi-velocity at every evaluation
    def velocity_jacobian(self, base, t, q, x) -> Array | None:
        """``G = ∂f*/∂x`` (``size``, n) in closed form; ``None`` (the default) to have it
        differentiated."""
        return None

    @property
    def size(self) -> int:
        raise NotImplementedError

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f"{type(self).__name__}[{i}]" for i in range(self.size))

    @property
    # affine rows make one kinetic-metric projection exact (initial states, switches);
    # nonlinear rows are projected by a few Newton iterations
    def linear(self) -> bool:
        return True


class VelocityConstraint(Constraint):
    """A constraint from functions: ``f*(base, t, q, x)`` and optionally ``φ(base, t, q)``.

    Example (no lateral slip of a disk): ``VelocityConstraint(lambda b, t, q, x:
    b.contact_velocity(q, x)[1:2], size=1, label="skate")``. The functions are static (part of
    the compiled program); keep parameters on the base system or in ``params``, passed as
    ``fn(base, t, q, x, params)`` when ``params`` is not ``None``.
    """

    # functions are static (hashed into the compiled program); anything to differentiate must be
    # an array leaf, hence ``params``
    fn: Callable = eqx.field(static=True)
    n_rows: int = eqx.field(static=True)
    label: str = eqx.field(static=True, default="constraint")
    is_linear: bool = eqx.field(static=True, default=True)
    position_fn: Callable | None = eqx.field(static=True, default=None)
    params: Any = None

    def __init__(self, fn, size, label="constraint", linear=True, position=None, params=None):
        self.fn, self.n_rows, self.label = fn, int(size), label
        self.is_linear, self.position_fn, self.params = bool(linear), position, params

    def _call(self, f, *args):
        return f(*args) if self.params is None else f(*args, self.params)

    def velocity(self, base, t, q, x):
        # to the declared row count: a scalar fits, a wrong size fails at trace time
        return jnp.reshape(self._call(self.fn, base, t, q, x), (self.n_rows,))

    def position(self, base, t, q):
        if self.position_fn is None:
            return None
        return jnp.reshape(self._call(self.position_fn, base, t, q), (self.n_rows,))

    @property
    def size(self):
        return self.n_rows

    @property
    def names(self):
        return tuple(f"{self.label}[{i}]" for i in range(self.n_rows))

    @property
    def linear(self):
        return self.is_linear
