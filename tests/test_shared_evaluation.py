"""Evaluations shared within one traced function (jaxbody.shared_evaluation): the frames of a
configuration computed once per vector-field evaluation, never a tracer handed across traces."""

import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody import maggi
from jaxbody.constraints import LoopClosure
from jaxbody.shared_evaluation import shared, shared_evaluations

from _support.jaxpr_tools import count_eqns

CALLS = []


@shared
def _counted(a, b):
    CALLS.append(1)
    a = a[0] if isinstance(a, tuple) else a
    return a * b + 1.0


def _count(fn, *args):
    CALLS.clear()
    out = fn(*args)
    return len(CALLS), out


def test_same_arguments_share_one_evaluation_only_inside_a_scope():
    x, y = jnp.ones(3), jnp.arange(3.0)

    def twice(a, b):
        return _counted(a, b) + _counted(a, b)

    assert _count(twice, x, y)[0] == 2  # no scope: every call runs

    def scoped(a, b):
        with shared_evaluations():
            return twice(a, b)

    n, out = _count(scoped, x, y)
    assert n == 1
    np.testing.assert_array_equal(out, 2.0 * (x * y + 1.0))
    # traced: the jaxpr holds one evaluation
    CALLS.clear()
    jaxpr = jax.make_jaxpr(scoped)(x, y)
    assert len(CALLS) == 1
    assert sum(e.primitive.name == "mul" for e in jaxpr.eqns) == 1  # a*b once, its result added to itself


def test_other_leaves_or_structure_are_not_shared():
    x, y = jnp.ones(3), jnp.arange(3.0)

    def calls(a, b):
        with shared_evaluations():
            _counted(a, b)
            _counted(b, a)  # same leaves, other order
            _counted(a, b + 0.0)  # an equal value in a new array
            _counted((a,), b)  # another structure around the same leaf
            _counted(a, b)  # the first again: shared

    assert _count(calls, x, y)[0] == 4


def test_a_nested_trace_keeps_its_tracers():
    """A result computed inside a cond branch or a jvp holds that trace's tracers: the caller
    must get its own evaluation, not an escaped tracer."""

    def f(a, b):
        with shared_evaluations():
            inner = jax.lax.cond(a[0] > 0, lambda: _counted(a, b), lambda: jnp.zeros(3))
            outer = _counted(a, b)
            t = jax.jvp(lambda bb: _counted(a, bb), (b,), (jnp.ones(3),))[1]
            return inner + outer + t + _counted(a, b)

    x, y = jnp.ones(3), jnp.arange(3.0)
    out = jax.jit(f)(x, y)
    np.testing.assert_allclose(out, 3.0 * (x * y + 1.0) + x)
    # and differentiable through the shared results
    g = jax.grad(lambda b: jnp.sum(f(x, b)))(y)
    np.testing.assert_allclose(g, 3.0 * x)


def test_scopes_are_per_thread():
    """A solve traced on a helper thread does not see the caller's entries."""
    seen = {}

    def worker():
        seen["scopes"] = len(__import__("jaxbody.shared_evaluation", fromlist=["_scopes"])._scopes())

    with shared_evaluations():
        t = threading.Thread(target=worker)
        t.start()
        t.join()
    assert seen["scopes"] == 0


def _forward_kinematics_calls(jaxpr) -> int:
    """Copies of forward kinematics (its nested jit) in a jaxpr and its sub-jaxprs."""
    return count_eqns(jaxpr, lambda e: e.primitive.name in ("pjit", "jit")
                      and e.params.get("name") == "_forward_kinematics")


def _looped_model():
    """A planar four-bar linkage: crank and coupler in one branch, the rocker in another,
    closed by a loop between the coupler's tip and the rocker's."""
    b = jb.ModelBuilder(gravity=(0, 0, -9.81))
    for name, parent, pos in (("crank", None, (0, 0, 0)), ("coupler", "crank", (0.4, 0, 0)), ("rocker", None, (1.0, 0, 0))):
        b.add_body(name, parent=parent, pos=pos, mass=1.0, com=(0.2, 0, 0), inertia=(0.01, 0.02, 0.02),
                   joints=[jb.Hinge(axis=(0, -1, 0))])
    return b.build()


def test_one_constrained_evaluation_computes_the_frames_once():
    """The mass matrix, the velocity terms, the constraint Jacobian, its velocity bias and the
    Baumgarte residuals of a constrained scene read one computation of the frames."""
    model = _looped_model()
    loop = LoopClosure(model, "coupler", (1.0, 0, 0), "rocker", (0.7, 0, 0), axes=[(1, 0, 0), (0, 0, 1)])
    q = jnp.array([0.6, 0.5, 1.4])
    cs = maggi.constrain(model, [loop], q_ref=q, position_atol=None)
    scene = jb.scene(model, constraints=cs)
    jaxpr = jax.make_jaxpr(lambda q, v: scene.evaluate(0.0, q, v)[0])(q, jnp.array([2.0, -1.0, 0.5]))
    assert _forward_kinematics_calls(jaxpr.jaxpr) == 1
    # the system's own solve too (its base's bracket terms and the constraint rows)
    jaxpr = jax.make_jaxpr(lambda q, v: cs.solve(0.0, q, v, stabilise=True).xdot)(q, jnp.array([2.0, -1.0, 0.5]))
    assert _forward_kinematics_calls(jaxpr.jaxpr) == 1


@pytest.mark.parametrize("frame", [-1, "rocker"])
def test_loop_closure_jacobian_closed_form_matches_forward_mode(frame):
    model = _looped_model()
    loop = LoopClosure(model, "coupler", (1.0, 0, 0), "rocker", (0.7, 0, 0), frame=frame)
    q, x = jnp.array([0.6, 0.5, 1.4]), jnp.array([2.0, -1.0, 0.5])
    base = maggi.ModelBase(model)
    closed = loop.velocity_jacobian(base, 0.0, q, x)
    forward = jax.jacfwd(lambda xx: loop.velocity(base, 0.0, q, xx))(x)
    np.testing.assert_allclose(closed, forward, rtol=0, atol=1e-14)
