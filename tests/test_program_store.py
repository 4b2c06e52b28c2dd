"""Traced programs stored on disk (jaxbody.program_store): the same results as tracing, a later
process that runs them without tracing, and a fingerprint that changes with everything the
program is a function of."""

import json
import os
import pathlib
import pickle
import subprocess
import sys
import textwrap
import types
import uuid

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxbody as jb
from jaxbody import program_store, tiered_compilation


@pytest.fixture
def store(tmp_path, monkeypatch):
    """An empty store of this test's own, and nothing of it held in memory."""
    monkeypatch.setattr(program_store, "store_dir", lambda: tmp_path / "programs")
    monkeypatch.delenv(program_store.ENV_SWITCH, raising=False)
    program_store.forget()
    yield tmp_path / "programs"
    program_store.forget()


def _primal_files(store):
    return [p for p in store.glob("simulate-*.pickle")
            if not p.name.startswith(("simulate-reverse-", "simulate-forward-"))]


def _arm(gain_offset=0.0, target=(0.3, -0.2)):
    """A two-link arm under a PD law that closes over an array (the target)."""
    b = jb.ModelBuilder()
    b.add_body("upper", mass=1.0, com=(0.0, 0.0, -0.25), inertia=(0.01, 0.01, 0.001), joints=[jb.Hinge(axis=(0, 1, 0))])
    b.add_body("lower", "upper", pos=(0, 0, -0.5), mass=0.7, com=(0.0, 0.0, -0.2), inertia=(0.008, 0.008, 0.001),
               joints=[jb.Hinge(axis=(0, 1, 0))])
    model = b.build()
    target = jnp.asarray(target)

    def pd(t, q, v, gains):
        return (gains[0] + gain_offset) * (target - q) - gains[1] * v

    return model, pd


def _loss(model, pd, q0, adjoint=None):
    """The loss of the arm's final state (``adjoint``: ``simulate``'s; the default lets the
    store differentiate in forward mode, an explicit one keeps reverse mode)."""
    def loss(gains):
        sc = jb.scene(model, actuation=(pd, gains))
        return jnp.sum(jb.simulate(sc, q0, jnp.zeros(2), 0.5, n_save=11, adjoint=adjoint).q[-1] ** 2)
    return loss


def test_stored_program_gives_the_traced_results_and_gradients(store, monkeypatch):
    model, pd = _arm()
    q0 = jnp.asarray([0.4, 0.1])
    gains = jnp.asarray([8.0, 1.0])
    scene = jb.scene(model, actuation=(pd, gains))
    before = program_store.counts()
    sol = jb.simulate(scene, q0, jnp.zeros(2), 0.5, n_save=11)
    # the solve, and the quantities at its saved states (energies) made and compiled beside it,
    # then found in memory by the call that runs them (nothing read back from the store)
    first = program_store.counts()
    assert first["stored"] - before["stored"] == 2 and first["ahead"] - before["ahead"] == 1
    assert first["loaded"] == before["loaded"]
    # reverse mode, as the adjoint asked for (the same primal program as the default adjoint's)
    grad = jax.grad(_loss(model, pd, q0, "checkpoint"))(gains)
    after = program_store.counts()
    assert after["stored"] - before["stored"] == 3  # and the solve's derivative
    assert after["forward"] == before["forward"]
    assert len(_primal_files(store)) == 1 and len(list(store.glob("saved-*.pickle"))) == 1
    assert len(list(store.glob("simulate-reverse-*.pickle"))) == 1
    # the reverse program's output mask is remembered for the next forward pass
    assert len(list(store.glob("simulate-masks-*.json"))) == 1
    # read back from the store (not from memory): the same numbers again; the saved quantities'
    # program and the reverse program read and compiled in background threads
    program_store.forget()
    again = jb.simulate(scene, q0, jnp.zeros(2), 0.5, n_save=11)
    grad_again = jax.grad(_loss(model, pd, q0, "checkpoint"))(gains)
    assert program_store.counts()["loaded"] - after["loaded"] == 3
    assert program_store.counts()["ahead"] - after["ahead"] == 2
    np.testing.assert_array_equal(again.q, sol.q)
    np.testing.assert_array_equal(grad_again, grad)
    assert again.kernel == sol.kernel and again.layout == sol.layout and again.success
    # and what tracing gives, the store switched off
    monkeypatch.setenv(program_store.ENV_SWITCH, "0")
    traced = jb.simulate(scene, q0, jnp.zeros(2), 0.5, n_save=11)
    grad_traced = jax.grad(_loss(model, pd, q0, "checkpoint"))(gains)
    np.testing.assert_allclose(traced.q, sol.q, rtol=0, atol=1e-14)
    np.testing.assert_allclose(grad_traced, grad, rtol=1e-12, atol=1e-14)
    for name in ("t", "v", "energy", "t_final", "q_final", "v_final", "energy_drift"):
        np.testing.assert_allclose(getattr(traced, name), getattr(sol, name), rtol=0, atol=1e-14)
    assert {k: int(v) for k, v in traced.stats.items()} == {k: int(v) for k, v in sol.stats.items()}
    assert int(traced.result._value) == int(sol.result._value)
    # the stored derivative against central differences of the stored solve
    monkeypatch.delenv(program_store.ENV_SWITCH)
    loss, h = _loss(model, pd, q0), 1e-6
    fd = [(loss(gains.at[i].add(h)) - loss(gains.at[i].add(-h))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_a_derivative_with_respect_to_a_few_scalars_is_taken_in_forward_mode(store, monkeypatch):
    model, pd = _arm()
    q0 = jnp.asarray([0.4, 0.1])
    gains = jnp.asarray([8.0, 1.0])
    loss = _loss(model, pd, q0)
    before = program_store.counts()
    grad = jax.grad(loss)(gains)
    after = program_store.counts()
    # one program, the outputs and their Jacobians with respect to the two gains; no primal
    # program traced for it, no reverse one
    assert after["forward"] - before["forward"] == 1 and after["stored"] - before["stored"] == 2  # and "saved"
    assert len(list(store.glob("simulate-forward-*.pickle"))) == 1 and not _primal_files(store)
    # past FORWARD_MAX_INPUTS scalars, reverse mode: the same derivative
    with monkeypatch.context() as patch:
        patch.setattr(program_store, "FORWARD_MAX_INPUTS", 1)
        np.testing.assert_allclose(jax.grad(loss)(gains), grad, rtol=1e-12, atol=1e-14)
    assert program_store.counts()["forward"] == after["forward"]
    assert len(list(store.glob("simulate-reverse-*.pickle"))) == 1
    # read back from the store: the same numbers
    program_store.forget()
    np.testing.assert_array_equal(jax.grad(loss)(gains), grad)
    assert program_store.counts()["loaded"] - after["loaded"] >= 1
    # against central differences of the solve, for a loss of more outputs than the final state
    # (the velocities and energies of the saved states, and the end time): each output's
    # Jacobian is contracted with its cotangent

    def wide_loss(gains):
        sol = jb.simulate(jb.scene(model, actuation=(pd, gains)), q0, jnp.zeros(2), 0.5, n_save=11)
        return jnp.sum(sol.q[-1] ** 2) + jnp.sum(sol.v ** 2) + 0.1 * jnp.sum(sol.energy) + sol.t_final

    h = 1e-6
    for f in (loss, wide_loss):
        fd = [(f(gains.at[i].add(h)) - f(gains.at[i].add(-h))) / (2 * h) for i in range(2)]
        np.testing.assert_allclose(jax.grad(f)(gains), fd, rtol=1e-6)


@pytest.fixture
def tiered(monkeypatch):
    """Tiered compilation on, as users have it: the suite's own optimisation level in
    ``$XLA_FLAGS`` (tests/conftest.py) turns it off."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith("--xla_backend_optimization_level")]
    monkeypatch.setenv("XLA_FLAGS", " ".join(flags))
    monkeypatch.delenv(tiered_compilation.ENV_SWITCH, raising=False)
    assert tiered_compilation.enabled()


def test_a_first_call_runs_a_quick_compile_then_the_optimised_one(store, tiered):
    # (a derivative's program is compiled by the same function as the solve's: not repeated here)
    model, pd = _arm(gain_offset=float(np.random.default_rng().uniform(0.0, 1e-3)))  # a program no earlier test compiled
    q0 = jnp.asarray([0.4, 0.1])
    scene = jb.scene(model, actuation=(pd, jnp.asarray([8.0, 1.0])))
    before = program_store.counts()
    quick = jb.simulate(scene, q0, jnp.zeros(2), 0.5, n_save=11)
    program_store.wait()
    # the solve and its saved quantities, each compiled again optimised in the background,
    # marked as such beside the stored program
    first = program_store.counts()
    assert first["optimised"] - before["optimised"] == 2
    assert len(list(store.glob("*.pickle.optimised"))) == 2
    # the calls after it run the optimised programs: the same numbers to rounding
    optimised = jb.simulate(scene, q0, jnp.zeros(2), 0.5, n_save=11)
    np.testing.assert_allclose(optimised.q, quick.q, rtol=0, atol=1e-13)
    # a later process (this one's memory forgotten) finds the marks and compiles, that is loads
    # from JAX's cache, the optimised programs at once: nothing is compiled twice
    program_store.forget()
    again = jb.simulate(scene, q0, jnp.zeros(2), 0.5, n_save=11)
    program_store.wait()
    assert program_store.counts()["optimised"] == first["optimised"]
    np.testing.assert_array_equal(again.q, optimised.q)


def test_tiered_compilation_is_off_where_switched_off_or_the_level_is_the_callers(tiered, monkeypatch):
    monkeypatch.setenv(tiered_compilation.ENV_SWITCH, "off")
    assert not tiered_compilation.enabled()
    monkeypatch.delenv(tiered_compilation.ENV_SWITCH)
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=2")
    assert not tiered_compilation.enabled()


def test_a_check_run_once_compiles_quickly_where_tiering_is_on(tiered, monkeypatch):
    # compiled_when_eager(quick=True): the program of a construction-time check is compiled at
    # XLA's level 0 where tiering is on, with the defaults where it is off; the same values
    from jaxbody import _util

    requested = []
    real = _util.eqx.filter_jit

    def recording(fn, **kwargs):
        program = real(fn, **kwargs)

        def run(*args):
            requested.append(kwargs.get("compiler_options"))
            return program(*args)

        return run

    monkeypatch.setattr(_util.eqx, "filter_jit", recording)
    check = _util.compiled_when_eager(quick=True)(lambda q: jnp.sin(q) @ q)
    plain = _util.compiled_when_eager(lambda q: jnp.sin(q) @ q)
    q = jnp.linspace(0.0, 1.0, 5)
    quick_value = check(q)
    plain(q)
    monkeypatch.setenv(tiered_compilation.ENV_SWITCH, "off")
    np.testing.assert_allclose(check(q), quick_value, rtol=1e-15)
    assert requested == [tiered_compilation.QUICK_OPTIONS, None, None]


def test_traced_calls_are_left_to_the_callers_program(store):
    model, pd = _arm()
    q0 = jnp.asarray([0.4, 0.1])
    gains = jnp.asarray([8.0, 1.0])
    loss = _loss(model, pd, q0)
    eager = loss(gains)
    before = program_store.counts()
    # jit and vmap hold the solve in their own programs
    np.testing.assert_allclose(jax.jit(loss)(gains), eager, rtol=1e-13)
    np.testing.assert_allclose(jax.vmap(loss)(jnp.stack([gains, gains])), [eager, eager], rtol=1e-13)
    after = program_store.counts()
    assert after["traced"] - before["traced"] == 4  # two programs a solve (see call_then), twice
    assert len(list(store.glob("*.pickle"))) == 2  # the eager solve's only: the solve, its saved quantities


def test_switched_off_stores_nothing(store, monkeypatch):
    monkeypatch.setenv(program_store.ENV_SWITCH, "off")
    model, pd = _arm()
    jb.simulate(jb.scene(model, actuation=(pd, jnp.asarray([8.0, 1.0]))), jnp.asarray([0.4, 0.1]), jnp.zeros(2), 0.5)
    assert not store.exists()


def test_damaged_entry_is_traced_and_stored_again(store):
    model, pd = _arm()
    scene = jb.scene(model, actuation=(pd, jnp.asarray([8.0, 1.0])))
    q0 = jnp.asarray([0.4, 0.1])
    first = jb.simulate(scene, q0, jnp.zeros(2), 0.5)
    (path,) = _primal_files(store)
    path.write_bytes(b"not a stored program")
    program_store.forget()
    before = program_store.counts()
    second = jb.simulate(scene, q0, jnp.zeros(2), 0.5)
    assert program_store.counts()["stored"] - before["stored"] == 1
    np.testing.assert_array_equal(second.q, first.q)
    assert pickle.loads(path.read_bytes())["exported"] is not None


def test_the_store_is_bounded_least_recently_used_first(store, monkeypatch):
    # programs only: whether an executable is kept beside them depends on what JAX's cache
    # already holds (test_an_optimised_executable_is_kept_and_loaded bounds those)
    monkeypatch.setattr(program_store, "store_executable", lambda path, compiled: False)
    model, pd = _arm()
    q0 = jnp.asarray([0.4, 0.1])
    scene = jb.scene(model, actuation=(pd, jnp.asarray([8.0, 1.0])))
    jb.simulate(scene, q0, jnp.zeros(2), 0.5)
    (first,) = _primal_files(store)
    os.utime(first, (1.0, 1.0))  # long unused
    # room for the programs there are and one byte: storing another solve removes the least
    # recently used first
    monkeypatch.setattr(program_store, "MAX_BYTES", _stored_bytes(store) + 1)
    jb.simulate(scene, q0, jnp.zeros(2), 0.25, n_save=5)
    assert not first.exists() and _primal_files(store)
    assert _stored_bytes(store) <= program_store.MAX_BYTES


def test_an_optimised_executable_is_kept_and_loaded(store, monkeypatch):
    # a PD target no earlier program had (it is a constant of the program): JAX's persistent
    # cache cannot serve the optimised compile, whose executable is then kept
    model, pd = _arm(target=(0.3, -0.2 + 1e-9 * (uuid.uuid4().int % 1000)))
    scene = jb.scene(model, actuation=(pd, jnp.asarray([8.0, 1.0])))
    q0, v0 = jnp.asarray([0.4, 0.1]), jnp.zeros(2)
    sol = jb.simulate(scene, q0, v0, 0.5)
    program_store.wait()  # the optimised compile may run in the background
    # the solve's (the saved states' program has no PD law: an earlier test may have compiled it)
    kept = sorted(p.name.split("-")[0] for p in store.glob("*.xla"))
    assert "simulate" in kept and set(kept) <= {"saved", "simulate"}
    # a later process (here: this one, its memory forgotten) loads them without lowering
    program_store.forget()
    before = program_store.counts()
    again = jb.simulate(scene, q0, v0, 0.5)
    assert program_store.counts()["executable"] - before["executable"] == len(kept)
    # the first call may have run the quickly compiled program: the last bits may differ
    np.testing.assert_allclose(again.q, sol.q, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(again.energy, sol.energy, rtol=1e-10, atol=1e-12)
    # a damaged executable is ignored: compiled (or loaded from JAX's cache) as before
    for path in store.glob("*.xla"):
        path.write_bytes(b"not an executable")
    program_store.forget()
    before = program_store.counts()
    np.testing.assert_allclose(jb.simulate(scene, q0, v0, 0.5).q, sol.q, rtol=1e-10, atol=1e-12)
    assert program_store.counts()["executable"] == before["executable"]
    # executables count against the store's bound, the least recently used removed first
    program_store.wait()
    monkeypatch.setattr(program_store, "MAX_BYTES", 1)
    jb.simulate(scene, q0, v0, 0.25, n_save=5)
    assert _stored_bytes(store) <= 1


def test_the_initial_constraint_check_is_a_stored_program_compiled_once(store):
    # a loop closed by an MJCF <connect>: a solve first checks its initial state against the
    # loop's rows, a program of its own that runs once per solve, stored and kept compiled
    # quickly, so that a later process neither traces nor lowers nor compiles it
    import warnings

    from test_constraints import four_bar_angles, four_bar_mjcf

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = jb.from_mjcf(four_bar_mjcf(four_bar_angles(0.6)))
    scene = jb.scene(model)
    q0, v0 = model.qpos0, jnp.zeros(model.nv)
    sol = jb.simulate(scene, q0, v0, 0.2)
    (checked,) = store.glob("constraint_residual-*.pickle")
    program_store.forget()
    before = program_store.counts()
    again = jb.simulate(scene, q0, v0, 0.2)
    np.testing.assert_allclose(again.q, sol.q, rtol=1e-10, atol=1e-12)
    # each run of the suite has a JAX cache of its own (conftest), where no other test compiles
    # this program: it was compiled here and kept (a cache kept across runs may serve it instead)
    if os.path.basename(os.environ.get("JAX_COMPILATION_CACHE_DIR", "")).startswith("jaxbody-test-jax-cache-"):
        assert len(list(store.glob("constraint_residual-*.quick.xla"))) == 1
        assert program_store.counts()["executable"] - before["executable"] >= 1
    # the stored check still names the rows an initial state violates
    with pytest.raises(ValueError, match=r"q0: initial positions violate the constraints \['loop"):
        jb.simulate(scene, q0.at[0].add(0.3), v0, 0.2)


def test_an_executable_loaded_from_jax_cache_is_not_kept():
    # a copy JAX's serialiser writes of a cache-loaded executable lacks its machine code:
    # compile_fresh tells a compile from a load, by JAX's cache-hit events
    from jaxbody.stored_executables import compile_fresh

    threshold = jax.config.jax_persistent_cache_min_compile_time_secs
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    try:
        offset = float(uuid.uuid4().int % 1000)  # a program no earlier run compiled

        def f(x):
            return jnp.sin(x) * 2.0 + offset

        x = jax.ShapeDtypeStruct((3,), jnp.float64)
        first, fresh = compile_fresh(lambda: jax.jit(f).lower(x).compile())
        jax.clear_caches()  # as a later process: nothing compiled in memory
        second, again = compile_fresh(lambda: jax.jit(f).lower(x).compile())
    finally:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", threshold)
    assert fresh and not again
    np.testing.assert_array_equal(second(jnp.ones(3)), first(jnp.ones(3)))


def _stored_bytes(store):
    """Bytes of the programs and executables in ``store`` (what its bound counts)."""
    return sum(p.stat().st_size for p in store.iterdir() if p.name.endswith((".pickle", ".xla")))


def test_a_program_with_a_host_callback_is_traced(store):
    # a progress meter calls back to the host: such a program cannot be stored
    model, pd = _arm()
    scene = jb.scene(model, actuation=(pd, jnp.asarray([8.0, 1.0])))
    before = program_store.counts()
    sol = jb.simulate(scene, jnp.asarray([0.4, 0.1]), jnp.zeros(2), 0.5, progress=True)
    assert sol.success
    assert program_store.counts()["declined"] - before["declined"] == 1
    (path,) = _primal_files(store)
    data = pickle.loads(path.read_bytes())
    assert data["exported"] is None and "callback" in data["reason"]
    # the marker is read, not retried
    program_store.forget()
    jb.simulate(scene, jnp.asarray([0.4, 0.1]), jnp.zeros(2), 0.5, progress=True)
    assert program_store.counts()["declined"] - before["declined"] == 2
    # only the saved states' quantities (no callback there) were stored, once
    assert program_store.counts()["stored"] - before["stored"] == 1


def test_bad_input_under_grad_is_a_python_error_naming_it(store):
    model, pd = _arm()
    loss = _loss(model, pd, jnp.asarray([jnp.nan, 0.1]))
    with pytest.raises(ValueError, match="q0 contains NaN or inf"):
        jax.grad(loss)(jnp.asarray([8.0, 1.0]))


# ---------------------------------------------------------------------------------------------
# the fingerprint


def _fp(*args):
    return program_store.fingerprint("test", args)


def _function(source: str, **globals_):
    """A function defined by ``source`` in a module of its own (globals ``globals_``)."""
    module = types.ModuleType(f"user_{uuid.uuid4().hex}")
    module.__dict__.update(globals_, jnp=jnp)
    exec(textwrap.dedent(source), module.__dict__)
    return module.f


def test_fingerprint_follows_code_closures_and_globals():
    def law(k):
        return lambda t, q, v, p: k * q
    # the same code over equal values: one program; other values or other code: another
    assert _fp(law(2.0)) == _fp(law(2.0))
    assert _fp(law(2.0)) != _fp(law(3.0))
    assert _fp(law(np.ones(2))) == _fp(law(np.ones(2)))
    assert _fp(law(np.ones(2))) != _fp(law(np.full(2, 1.5)))
    assert _fp(lambda q: q + 1) != _fp(lambda q: q - 1)
    # a global array the code reads, a global function it calls, a module it names
    a = _function("def f(q):\n    return q * W\n", W=np.ones(2))
    b = _function("def f(q):\n    return q * W\n", W=np.full(2, 2.0))
    assert _fp(a) != _fp(b)
    helper = _function("def f(q):\n    return q + 1\n")
    other = _function("def f(q):\n    return q + 2\n")
    assert _fp(_function("def f(q):\n    return g(q)\n", g=helper)) != _fp(_function("def f(q):\n    return g(q)\n", g=other))
    lib = types.ModuleType("user_lib")
    lib.scale, lib.unused = 2.0, object()
    c = _function("def f(q):\n    return lib.scale * q\n", lib=lib)
    first = _fp(c)
    lib.scale = 3.0
    assert _fp(c) != first
    # a name the code does not read does not matter
    lib.other = 1.0
    assert _fp(c) == _fp(c)
    # two functions reading different names of one module: each name counts
    d = _function("def f(q):\n    return lib.offset + q\n", lib=lib)
    lib.offset = 0.0
    first = _fp(c, d)
    lib.offset = 1.0
    assert _fp(c, d) != first


def test_fingerprint_follows_a_users_class():
    class Law(eqx.Module):
        k: float

        def __call__(self, q):
            return self.k * q

    class Other(eqx.Module):
        k: float

        def __call__(self, q):
            return self.k * q * q

    assert _fp(Law(1.0)) == _fp(Law(1.0))
    assert _fp(Law(1.0)) != _fp(Law(2.0))
    assert _fp(Law(1.0)) != _fp(Other(1.0))


@pytest.mark.filterwarnings("ignore:A JAX array is being set as static")
def test_fingerprint_takes_input_arrays_by_shape_and_constants_by_value():
    class Holder(eqx.Module):
        x: jax.Array
        table: np.ndarray = eqx.field(static=True)

    # an input array's values do not change the program; its shape and dtype do
    assert _fp(Holder(jnp.ones(3), np.zeros(2))) == _fp(Holder(jnp.zeros(3), np.zeros(2)))
    assert _fp(Holder(jnp.ones(3), np.zeros(2))) != _fp(Holder(jnp.ones(4), np.zeros(2)))
    assert _fp(Holder(jnp.ones(3), np.zeros(2))) != _fp(Holder(jnp.ones(3, jnp.float32), np.zeros(2)))
    # a static array is a constant of the program
    assert _fp(Holder(jnp.ones(3), np.zeros(2))) != _fp(Holder(jnp.ones(3), np.ones(2)))
    # Python numbers are constants too
    assert _fp(1.0) != _fp(2.0) and _fp(1) != _fp(1.0)

    # one object both an input and a constant (held in a static field): its values count
    class Inner(eqx.Module):
        x: jax.Array

    class Outer(eqx.Module):
        inner: Inner = eqx.field(static=True)

    a, b = Inner(jnp.zeros(2)), Inner(jnp.ones(2))
    assert _fp(a, Outer(a)) != _fp(b, Outer(b))


def test_fingerprint_follows_settings_and_refuses_the_unknown(monkeypatch):
    solver = diffrax.Tsit5()
    first = _fp(solver)
    monkeypatch.setenv("JAXBODY_NATIVE_THREADS", "1")
    assert _fp(solver) != first

    class Opaque:  # neither a dataclass nor anything else the fingerprint knows
        gain = 1.0

    with pytest.raises(program_store.Undescribable):
        _fp(Opaque())
    opaque = Opaque()
    with pytest.raises(program_store.Undescribable):
        _fp(lambda q: q * opaque.gain)
    # its class is described by its body
    first = _fp(lambda q: q * Opaque.gain)
    Opaque.gain = 2.0
    assert _fp(lambda q: q * Opaque.gain) != first


# ---------------------------------------------------------------------------------------------
# a later process


_SCRIPT = """
import json, os, sys
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import jaxbody as jb
from jaxbody import program_store

sys.path.insert(0, sys.argv[2])
from test_program_store import _arm  # the arm and PD law of the in-process tests

model, pd = _arm(float(sys.argv[1]))
q0 = jnp.asarray([0.4, 0.1])

def loss(gains):
    sc = jb.scene(model, actuation=(pd, gains), kernel="native")
    return jnp.sum(jb.simulate(sc, q0, jnp.zeros(2), 0.5).q[-1] ** 2)

gains = jnp.asarray([8.0, 1.0])
sol = jb.simulate(jb.scene(model, actuation=(pd, gains), kernel="native"), q0, jnp.zeros(2), 0.5)
grad = jax.grad(loss)(gains)
print(json.dumps({"counts": program_store.counts(), "q": [float(x) for x in sol.q[-1]], "kernel": sol.kernel,
                  "grad": [float(x) for x in grad]}))
"""


def test_a_later_process_runs_the_stored_programs_without_tracing(tmp_path):
    # the native kernel: the later process must also register the kernel's programs it calls
    script = tmp_path / "script.py"
    script.write_text(_SCRIPT)
    offset = str(np.random.default_rng().uniform(0.0, 1e-3))  # a program no earlier run stored
    env = {k: v for k, v in os.environ.items() if k != program_store.ENV_SWITCH}
    env.pop("JAXBODY_KERNEL", None)
    env["JAXBODY_CACHE_DIR"] = str(tmp_path / "cache")  # its native libraries are removed below

    def run():
        done = subprocess.run([sys.executable, str(script), offset, str(pathlib.Path(__file__).parent)],
                              capture_output=True, text=True, env=env, timeout=600)
        assert done.returncode == 0, done.stderr[-3000:]
        return json.loads(done.stdout.strip().splitlines()[-1])

    first, second = run(), run()
    assert first["kernel"] == "native"
    # the solve, the quantities at its saved states and the solve's derivative
    assert first["counts"]["stored"] == 3 and first["counts"]["loaded"] == 0
    assert second["counts"]["loaded"] == 3 and second["counts"]["stored"] == 0 and second["counts"]["traced"] == 0
    assert second["q"] == first["q"] and second["grad"] == first["grad"]
    # no executable is kept for programs that call the native kernel (deserialised, such an
    # executable crashed the process that ran it): JAX's cache serves them
    assert not list((tmp_path / "cache" / "programs").glob("*.xla"))
    # a later process that finds the stored programs but not the native libraries they call
    # (removed, or an optimised build that did not finish) traces the solves again, which builds them
    programs = [p for p in (tmp_path / "cache" / "native").glob("*.so") if not p.name.startswith("handler")]
    for p in programs:
        p.unlink()
    third = run()
    assert third["counts"]["loaded"] == 3 and third["counts"]["traced"] >= 1  # the solve; then all is built
    assert programs and all(p.is_file() for p in programs)
    np.testing.assert_allclose(third["q"], first["q"], rtol=0, atol=1e-14)
