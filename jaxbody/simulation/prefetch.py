"""The native programs a solve is about to trace, built ahead of the trace.

With an empty cache most of a first :func:`jaxbody.simulate` on the native kernel is the C++
compiler: the handler, the energy program and the solve's own program (or the forward dynamics
the solver's loop calls), each built when the trace first reaches its call, one after another.
:func:`prefetch_solve` names them before the trace starts, from the same rules that choose them
during it (:func:`jaxbody.simulation.native_solve.native_solve_applies`,
:func:`jaxbody.simulation.field.native_field`), so that they build beside each other and
beside the tracing (:func:`jaxbody.backends.native.prefetch`). A wrong guess costs a build in
the background and changes no result: the traced calls build whatever they need themselves.
"""

import diffrax
import jax

from ..backends import native
from .field import native_field
from .native_solve import native_method, native_solve_applies, native_solve_enabled
from .solvers import RK4Stages

__all__ = ["prefetch_first", "prefetch_solve"]


def _native_model(scene):
    """The model of a scene whose forward dynamics is the native kernel, else ``None``."""
    if not scene.is_direct() or scene.direct_kernel() != "native":
        return None
    return scene.system


def _differentiated(tree) -> bool:
    """Whether a derivative is being taken of anything in ``tree`` (a guess from the tracers'
    kinds: reverse and forward mode both trace with these)."""
    return any(type(leaf).__name__ in ("JVPTracer", "LinearizeTracer") for leaf in jax.tree.leaves(tree))


def _batched(x) -> bool:
    # a vmap batch's size is not known before its trace: the build to prefetch is not either
    return type(x).__name__ == "BatchTracer"


def prefetch_first(scene, q0) -> list:
    """Start the builds of the handler and the energy program of ``scene``'s native kernel (the
    first things a solve calls). Returns the builds' futures."""
    model = _native_model(scene)
    if model is None or _batched(q0):
        return []
    return native.prefetch(model, ("energy",) if scene.has_energy else ())


def prefetch_solve(scene, y0, solver, controller, saveat, adjoint, meter, event, dense, slots) -> list:
    """Start the builds of the programs the solve of ``scene`` from ``y0`` with these settings
    will call: the one-call solve's program, or the RK4 step or forward dynamics that diffrax's
    loop calls, with their reverse-mode programs where a derivative is being taken. Returns the
    builds' futures."""
    model = _native_model(scene)
    if model is None or _batched(y0[0]) or not native.available():
        return []
    derivative = _differentiated((scene, y0))
    # a derivative with respect to the initial state alone stays native; any other goes
    # through diffrax's loop (see native_or_stepped)
    stepped_derivative = derivative and _differentiated(scene)
    futures = []
    if native_solve_enabled() and native_solve_applies(scene, y0, solver, controller, saveat, adjoint, meter, event,
                                                       dense, slots):
        method = native_method(solver, controller)
        torque = native_field(scene, y0, slots, timed=True)[2].get("torque")
        harmonics = None if torque is None else int(torque[1].shape[-1])
        program = "rk4_run" if method == "rk4" else f"adaptive:{method}"
        reverse = "rk4_run_vjp" if method == "rk4" else f"adaptive_vjp:{method}"
        futures = native.prefetch(model, (program,) + ((reverse,) if derivative and not stepped_derivative else ()),
                                  harmonics)
        if not stepped_derivative:
            return futures
    step = "rk4" if type(getattr(solver, "solver", None)) is RK4Stages else "fd"
    modes = [step] + ([f"{step}_jvp" if step == "rk4" else "jvp", f"{step}_vjp" if step == "rk4" else "vjp"]
                      if derivative else [])
    futures += native.prefetch(model, tuple(modes))
    if isinstance(solver, diffrax.AbstractImplicitSolver) and not derivative:
        # an implicit solver's Jacobian: the forward-mode program over a batch of tangents, one
        # per component of the state (q, v and the works)
        futures += native.prefetch(model, ("jvp",), batch=sum(int(x.size) for x in jax.tree.leaves(y0)))
    return futures
