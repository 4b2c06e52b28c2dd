"""Unconstrained variables for fitting: any fields of a system, or the physically consistent
inertial parameters of a model."""

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..model import Model
from .consistency import from_log_cholesky, log_cholesky
from .inertial import parameters, with_parameters

__all__ = ["Parameterisation", "InertialParameterisation"]


class Parameterisation(eqx.Module):
    """Unconstrained variables → fields of a system (any equinox pytree, e.g. a Model or a
    planar system).

    ``fields`` maps attribute paths (``"body_mass"``, ``"system.body_com"``) to ``"log"``
    (positive quantities: the variable is the logarithm) or ``"identity"``.
    ``initial(system)`` gives the variables of a system; calling the parameterisation on
    variables gives the system with those fields replaced.
    """

    template: Any
    fields: tuple = eqx.field(static=True)

    def __init__(self, template, fields: dict[str, str]):
        for path, kind in fields.items():
            if kind not in ("log", "identity"):
                raise ValueError(f"field {path!r}: transform must be 'log' or 'identity', got {kind!r}")
            _get(template, path)
        self.template = template
        self.fields = tuple(fields.items())

    def initial(self, system=None) -> dict:
        system = self.template if system is None else system
        out = {}
        for path, kind in self.fields:
            x = jnp.asarray(_get(system, path))
            if kind == "log":
                if np.any(np.asarray(x) <= 0):
                    raise ValueError(f"field {path!r} must be positive for a log parameterisation")
                x = jnp.log(x)
            out[path] = x
        return out

    def __call__(self, variables: dict):
        system = self.template
        for path, kind in self.fields:
            x = variables[path]
            x = jnp.exp(x) if kind == "log" else x
            system = eqx.tree_at(lambda s, p=path: _get(s, p), system, x)
        return system


def _get(obj, path: str):
    for name in path.split("."):
        try:
            obj = getattr(obj, name)
        except AttributeError:
            raise ValueError(f"{type(obj).__name__} has no field {name!r} (path {path!r})") from None
    return obj


class InertialParameterisation(eqx.Module):
    """Physically consistent inertial (and damping) parameters of a :class:`Model`.

    Variables: ``{"inertial": (n_sel, 10)}`` log-Cholesky factors of the pseudo-inertias of the
    selected ``bodies`` (default: every body of positive mass), and ``{"log_damping": (nv,)}``
    when ``damping=True``. Calling it gives the model.
    """

    template: Model
    bodies: tuple = eqx.field(static=True)
    damping: bool = eqx.field(static=True)

    def __init__(self, model: Model, bodies: Sequence[int] | None = None, damping: bool = False):
        mass = np.asarray(model.body_mass)
        if bodies is None:
            bodies = [k for k in range(model.n_body) if mass[k] > 0]
        self.template = model
        self.bodies = tuple(int(b) for b in bodies)
        self.damping = bool(damping)

    def initial(self, model: Model | None = None) -> dict:
        model = self.template if model is None else model
        pi = np.asarray(parameters(model)).reshape(model.n_body, 10)
        out = {"inertial": jnp.asarray(log_cholesky(pi[list(self.bodies)]))}
        if self.damping:
            d = np.asarray(model.dof_damping)
            if np.any(d <= 0):
                raise ValueError("damping must be positive for a log parameterisation")
            out["log_damping"] = jnp.log(jnp.asarray(d))
        return out

    def __call__(self, variables: dict) -> Model:
        model = self.template
        pi = parameters(model).reshape(model.n_body, 10)
        pi = pi.at[np.asarray(self.bodies)].set(from_log_cholesky(variables["inertial"]))
        model = with_parameters(model, pi.reshape(-1))
        if self.damping:
            model = eqx.tree_at(lambda m: m.dof_damping, model, jnp.exp(variables["log_damping"]))
        return model
