"""The embedded Runge–Kutta pairs of the native adaptive solves, read from diffrax's solvers.

Each method's Butcher tableau (stage coefficients ``a``, weights ``b``, error weights ``e``
and nodes ``c``) is diffrax's own (``diffrax.Dopri5.tableau`` and so on), so the native
program takes the steps diffrax takes. Its dense output is diffrax's too, written in the one
form every polynomial interpolant of an explicit pair has,

    y(t₀ + θh) = y₀ + h Σᵢ Bᵢ(θ) fᵢ,        Bᵢ(θ) = Σₚ Pᵢₚ θᵖ,

with ``fᵢ`` the stage derivatives: the polynomial coefficients ``P`` are recovered from the
solver's ``interpolation_cls`` by evaluating it on each unit stage vector at ``deg + 1``
Chebyshev nodes and solving the Vandermonde system (exact to rounding for a polynomial of
that degree; checked at other points).
"""

import dataclasses
import functools

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Tableau", "METHODS", "tableau"]

#: The native adaptive methods: preset name -> diffrax solver class.
METHODS = {"tsit5": diffrax.Tsit5, "dopri5": diffrax.Dopri5, "dopri8": diffrax.Dopri8}


@dataclasses.dataclass(frozen=True)
class Tableau:
    """An explicit embedded pair with first-same-as-last stage (``S`` stages, the last one the
    solution's: its row of ``a`` is ``b``, its weight zero)."""

    name: str
    a: tuple  # S rows, row i: the i coefficients of the earlier stages
    b: tuple  # S weights of the solution
    e: tuple  # S weights of the error estimate (b minus the embedded method's)
    c: tuple  # S nodes
    order: int  # of the solution; the controller's error order (diffrax: the same)
    dense: tuple  # S rows of polynomial coefficients P[i][p] of θ^p (p = 0 .. degree)

    @property
    def stages(self) -> int:
        return len(self.b)


def _dense_coefficients(cls, stages: int, b: np.ndarray) -> np.ndarray:
    """``P`` (stages × (degree + 1)) of the solver's interpolant (module docstring): the lowest
    degree whose fit reproduces the interpolant at other points."""
    check = np.linspace(0.0, 1.0, 9)
    # concrete even when first asked for while a solve is traced
    with jax.enable_x64(True), jax.ensure_compile_time_eval():
        def interpolant(unit, x):
            # h = 1, y₀ = 0, k the unit vector of one stage: y₁ = b·k (first same as last: the
            # solution is the last stage's)
            interp = cls.interpolation_cls(t0=jnp.float64(0.0), t1=jnp.float64(1.0), y0=jnp.zeros(1, jnp.float64),
                                           y1=(jnp.asarray(b) @ unit)[None], k=unit[:, None])
            return interp.evaluate(x)[0]

        # every stage at every point of every candidate degree in one batched evaluation (one by
        # one, the hundreds of small eager evaluations cost seconds of a first adaptive solve)
        every = jax.vmap(jax.vmap(interpolant, (None, 0)), (0, None))
        degrees = range(1, stages + 2)
        nodes = {d: 0.5 - 0.5 * np.cos(np.pi * (np.arange(d) + 0.5) / d) for d in degrees}
        points = np.concatenate([check, *nodes.values()])
        table = np.asarray(jax.jit(every)(jnp.eye(stages, dtype=jnp.float64), jnp.asarray(points, jnp.float64)))
        exact, start = table[:, : check.size].T, check.size
        for degree in degrees:
            # every interpolant starts at y₀ (no constant term): fit θ¹ .. θ^degree
            vander = np.vander(nodes[degree], degree + 1, increasing=True)[:, 1:]
            at_nodes, start = table[:, start : start + degree], start + degree
            P = np.concatenate([np.zeros((stages, 1)), np.linalg.solve(vander, at_nodes.T).T], axis=1)
            fitted = np.vander(check, degree + 1, increasing=True) @ P.T
            if np.max(np.abs(fitted - exact)) <= 1e-12 * max(1.0, np.max(np.abs(exact))):
                return P
    raise AssertionError(f"{cls.__name__}'s interpolant is not a polynomial in θ")


@functools.cache
def tableau(name: str) -> Tableau:
    """The :class:`Tableau` of the preset ``name`` (one of :data:`METHODS`)."""
    cls = METHODS[name]
    tab = cls.tableau
    b = np.asarray(tab.b_sol, np.float64)
    stages = len(b)
    a = [()] + [tuple(float(x) for x in row) for row in tab.a_lower]
    c = (0.0,) + tuple(float(x) for x in tab.c)
    if not (tab.fsal and tab.ssal) or b[-1] != 0.0 or len(a) != stages:
        raise AssertionError(f"{name}: the native solve needs a first-same-as-last pair")
    order = int(cls().order(diffrax.ODETerm(lambda t, y, args: y)))
    dense = _dense_coefficients(cls, stages, b)
    return Tableau(name, tuple(a), tuple(float(x) for x in b), tuple(float(x) for x in tab.b_error), c, order,
                   tuple(tuple(float(x) for x in row) for row in dense))
