"""Every malformed input a clear error: the table of ``_support/bad_inputs.py`` with each
case's pinned message, and what a :class:`jaxbody.Solution` keeps of failed and batched solves.

A case passes when its call raises and its pattern (naming the input, body, joint or field at
fault) is on the first line of the error — the line a user reads. ``scripts/bad_input_survey.py``
runs the same table and counts clear, misleading, silent and crashing answers.
"""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from _support.bad_inputs import all_cases, batch_solution, dense_solution, first_line, pendulum, solved, tmpfile

CASES = all_cases()


def test_the_table_is_large():
    assert len(CASES) >= 110


@pytest.fixture
def as_users_run():
    """The runtime shape checker of the test run (jaxtyping) off: it would answer a wrong shape
    before jaxbody's own check does, and users run without it."""
    import jaxtyping

    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", False)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_gives_a_clear_error(case, as_users_run):
    with pytest.raises(Exception) as info:
        jax.block_until_ready(case.call())  # an error of a running program is raised when its result is read
    text = first_line(info.value) if case.first_line else str(info.value)
    assert re.search(case.pattern, text), f"{case.id}: {text!r} does not match {case.pattern!r}"


# ------------------------------------------------------------------------------ Solution
def test_a_batch_is_indexable_with_results_per_member_and_a_failed_mask():
    sol = batch_solution()  # members 0 and 2 valid, member 1 given a NaN q0
    assert len(sol) == 3
    np.testing.assert_array_equal(np.asarray(sol.failed), [False, True, False])
    member = sol[1]
    assert member.result == jb.RESULTS.invalid_input
    assert sol[0].result == jb.RESULTS.successful
    assert sol[-1].t.shape == sol.t.shape[1:]
    # the result alone, per member: indexed, counted and iterated
    assert sol.result[1] == jb.RESULTS.invalid_input and sol.result[-1] == jb.RESULTS.successful
    assert len(sol.result) == 3
    assert [bool(r == jb.RESULTS.successful) for r in sol.result] == [True, False, True]
    # the member that never started is marked: no time reached, no state
    assert float(member.t_final) == 0.0
    assert np.all(np.isnan(np.asarray(member.q_final))) and np.all(np.isnan(np.asarray(member.q)))
    # the valid members are untouched by their neighbour (a solve without the zero control law:
    # the same motion, to the tolerances)
    np.testing.assert_allclose(np.asarray(sol[0].q_final), np.asarray(solved().q_final), rtol=1e-6)


def test_the_csv_written_is_the_csv_read():
    sol = solved()
    path = tmpfile("run.csv")
    sol.to_csv(path)
    back = jb.load_solution(path)
    for name in ("t", "q", "v", "energy"):
        np.testing.assert_allclose(np.asarray(getattr(back, name)), np.asarray(getattr(sol, name)), rtol=1e-15, atol=0)
    assert set(back.work) == set(sol.work)
    np.testing.assert_allclose(np.asarray(back.q_final), np.asarray(sol.q_final), rtol=1e-15)
    assert back.result == jb.RESULTS.successful


def test_a_solution_says_which_kernel_and_solver_ran():
    sol = solved()
    assert sol.solver == "tsit5"
    assert sol.kernel in ("native", "unrolled", "vectorised", "planar")
    # the default solver="auto" says why it chose tsit5; a solver asked for says so
    assert "tsit5" in sol.solver_reason
    asked = jb.simulate(pendulum(), jnp.array([0.3]), jnp.zeros(1), 0.05, solver="dopri5")
    assert (asked.solver, asked.solver_reason) == ("dopri5", "asked for")


def test_evaluate_inside_the_solved_interval_still_works():
    sol = dense_solution()
    q, _ = sol.evaluate(0.1)
    np.testing.assert_allclose(np.asarray(q), np.asarray(sol.q_final), rtol=1e-10)


# ------------------------------------------------------------------------------ why a solve failed
class _Chart(eqx.Module):
    """A system whose coordinates degenerate at q = 0 (acceleration 1/q): a singular chart."""

    nq = 1
    nv = 1

    def qdot(self, q, v):
        return v

    def acceleration(self, t, q, v, tau=None):
        return 1.0 / q


def _code(item):
    from jaxbody.simulation.solution import result_code

    return int(np.asarray(result_code(item)))


def test_a_failure_is_diagnosed_at_the_state_where_the_solve_stopped():
    from jaxbody.simulation.failures import diagnose

    one, zero = jnp.ones(1), jnp.zeros(1)
    steps = _code(jb.RESULTS.max_steps_reached)
    # finite forces, infinite accelerations: the equations are singular there
    chart = jb.scene(_Chart())
    why = diagnose(chart, 0.0, zero, zero, steps, 64, 0.0, 1.0)
    assert "singular" in why and "coordinate chart" in why
    # 64 steps that advanced the solve by a nanosecond: the step size collapsed
    why = diagnose(chart, 1e-9, one, zero, steps, 64, 0.0, 1.0)
    assert why.startswith("the step size collapsed") and "kvaerno5" in why and "max_steps will not help" in why
    # a long motion that simply needs more steps
    why = diagnose(chart, 0.5, one, zero, steps, 64, 0.0, 1.0)
    assert why.startswith("The maximum number of solver steps was reached") and "64 steps reached t = 0.5" in why
    # a mass matrix that is not positive definite (a massless moving body set inside the solve)
    model = eqx.tree_at(lambda m: m.body_mass, pendulum(), jnp.zeros(1))
    model = eqx.tree_at(lambda m: m.body_inertia, model, jnp.zeros((1, 3, 3)))
    scene = jb.scene(pendulum())
    scene = eqx.tree_at(lambda s: s.system, scene, model)
    why = diagnose(scene, 0.0, jnp.array([0.3]), zero, steps, 64, 0.0, 1.0)
    assert "mass matrix is not positive definite" in why
