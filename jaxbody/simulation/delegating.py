"""A diffrax solver that wraps another and delegates everything to it (shared base of the
simulator's step wrappers: the quaternion projection and the re-partitioning of constraints)."""

import diffrax
import equinox as eqx

__all__ = ["DelegatingSolver", "for_adjoint"]


class DelegatingSolver(diffrax.AbstractAdaptiveSolver, diffrax.AbstractWrappedSolver):
    """Wraps ``solver``; subclasses override :meth:`init` / :meth:`step`.

    The error estimate (and so the step control), orders, interpolation and term structure are
    the wrapped solver's. diffrax counts a wrapped solver as an instance of the wrapped one's
    class and sets ``scan_kind`` on it for forward-mode and bounded-while-loop adjoints; the
    field is mirrored here and handed to the wrapped solver (:attr:`inner`). diffrax's
    forwarding looks through one wrapper only, so a wrapper of a wrapper gets its
    ``scan_kind`` from :func:`for_adjoint` instead.
    """

    solver: diffrax.AbstractSolver
    # a field because diffrax writes it on the outermost solver with tree_at; it reaches the
    # solver that runs the stages through :attr:`inner`
    scan_kind: str | None = eqx.field(default=None, kw_only=True)

    @property
    def inner(self) -> diffrax.AbstractSolver:
        """The wrapped solver, with the ``scan_kind`` diffrax asked for."""
        if self.scan_kind is not None and hasattr(self.solver, "scan_kind"):
            # is_leaf for None: None is an empty pytree, so tree_at could not otherwise replace an
            # unset field
            return eqx.tree_at(lambda s: s.scan_kind, self.solver, self.scan_kind, is_leaf=lambda x: x is None)
        return self.solver

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms) if hasattr(self.solver, "error_order") else self.order(terms)

    # the identity wrapper: calls go through :attr:`inner`, so the stage loop diffrax chose
    # is the one that runs
    def init(self, terms, t0, t1, y0, args):
        return self.inner.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        return self.inner.step(terms, t0, t1, y0, args, solver_state, made_jump)

    def func(self, terms, t0, y0, args):
        return self.inner.func(terms, t0, y0, args)


def for_adjoint(solver, adjoint, max_steps):
    """``solver`` with the Runge-Kutta stage loop diffrax would choose for ``adjoint``.

    diffrax switches a Runge-Kutta solver's stage loop to a plain ``lax`` loop under
    ``ForwardMode`` (JAX cannot push tangents through the checkpointed loop's ``custom_vjp``)
    and to a bounded loop under ``DirectAdjoint``, but it recognises the solver through one
    wrapper only. For nested :class:`DelegatingSolver` wrappers the choice is made here and
    handed down from the outermost one; a ``scan_kind`` already set is kept.
    """
    inner = solver
    # only the innermost solver has a stage loop to choose
    while issubclass(type(inner), DelegatingSolver):
        inner = inner.solver
    if not issubclass(type(solver), DelegatingSolver) or not issubclass(
        type(inner), (diffrax.AbstractRungeKutta, diffrax.AbstractSRK)
    ) or inner.scan_kind is not None:
        return solver
    if isinstance(adjoint, diffrax.ForwardMode):
        kind = "lax"
    elif isinstance(adjoint, diffrax.DirectAdjoint):
        kind = "lax" if max_steps is None else "bounded"
    else:
        return solver
    return eqx.tree_at(lambda s: s.scan_kind, solver, kind, is_leaf=lambda x: x is None)
