"""Random states of a joint layout.

Sampled configurations and rates of a :class:`jaxbody.Model` for everything that needs
states spread over the configuration space rather than a trajectory: the base parameters of
identification (regressor stacked over states), design samples.
"""

import numpy as np

from .joints import FREE, HINGE, SLIDE
from .model import Model

__all__ = ["random_states"]


def random_states(model: Model, n: int, seed: int = 0, scale: float = 1.0):
    """``n`` random states ``(q, v, a)`` (NumPy): hinge angles uniform in ``[−π, π)``, slide
    displacements and all rates normal with standard deviation ``scale``, unit quaternions
    uniform on the sphere."""
    rng = np.random.default_rng(seed)
    q = np.zeros((n, model.nq))
    for j, kind in enumerate(model.joints.type):
        adr = model.joints.qposadr[j]
        if kind == HINGE:
            q[:, adr] = rng.uniform(-np.pi, np.pi, n)
        elif kind == SLIDE:
            q[:, adr] = scale * rng.normal(size=n)
        else:
            off = 0
            if kind == FREE:
                q[:, adr : adr + 3] = scale * rng.normal(size=(n, 3))
                off = 3
            u = rng.normal(size=(n, 4))
            q[:, adr + off : adr + off + 4] = u / np.linalg.norm(u, axis=1, keepdims=True)
    v = scale * rng.normal(size=(n, model.nv))
    a = scale * rng.normal(size=(n, model.nv))
    return q, v, a
