"""The run-time check of inputs (runtime_check.py, validation.raise_if_any): inside a compiled
program a failed check stops it with ``INVALID_ARGUMENT`` and jaxbody's message on the error's
first line, naming the batch member under ``vmap`` (nested too); tangents pass through; a program
holding it is stored in and loaded from JAX's persistent cache; without a C++ compiler the check
falls back to a host callback with the same message further down."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxbody import runtime_check
from jaxbody.validation import raise_if_any

MESSAGES = ("x contains NaN or inf", "x is negative")
# JAX raises a failed status as its runtime error, or (a compiled program called again, from
# its C++ fast path) as a ValueError: either way the first line is the status and the message
FAILED = (jax.errors.JaxRuntimeError, ValueError)


def checked(x):
    return raise_if_any(x, [(~jnp.all(jnp.isfinite(x)), MESSAGES[0]), (jnp.any(x < 0), MESSAGES[1])])


def first_line(err):
    return str(err).splitlines()[0]


@pytest.fixture(scope="module")
def jitted():
    return jax.jit(lambda x: 2.0 * checked(x))


def test_a_failed_check_names_the_input_and_the_member_on_the_first_line(jitted):
    assert runtime_check.target() == runtime_check.TARGET  # the suite's machine has g++
    x = jnp.array([0.5, 1.5])
    np.testing.assert_array_equal(np.asarray(jitted(x)), [1.0, 3.0])  # passed unchanged
    with pytest.raises(FAILED) as info:
        jax.block_until_ready(jitted(jnp.array([0.5, jnp.nan])))
    assert first_line(info.value) == "INVALID_ARGUMENT: x contains NaN or inf"
    with pytest.raises(FAILED) as info:
        jax.block_until_ready(jitted(jnp.array([0.5, -1.0])))
    assert first_line(info.value) == "INVALID_ARGUMENT: x is negative"
    # jax.vmap without jit, and nested: members counted row-major over the batch axes
    batch = jnp.ones((3, 2)).at[1, 0].set(-1.0).at[2, 1].set(jnp.nan)
    with pytest.raises(FAILED) as info:
        jax.block_until_ready(jax.vmap(checked)(batch))
    assert first_line(info.value) == "INVALID_ARGUMENT: x is negative (batch member 1 of 3)"
    nested = jnp.ones((2, 3, 2)).at[1, 1, 0].set(jnp.inf)
    with pytest.raises(FAILED) as info:
        jax.block_until_ready(jax.jit(jax.vmap(jax.vmap(checked)))(nested))
    assert first_line(info.value) == "INVALID_ARGUMENT: x contains NaN or inf (batch member 4 of 6)"
    np.testing.assert_array_equal(np.asarray(jax.vmap(jax.vmap(checked))(jnp.ones((2, 3, 2)))), np.ones((2, 3, 2)))


def test_tangents_and_cotangents_pass_through_the_check(jitted):
    x = jnp.array([0.5, 1.5])

    def f(x):
        return jnp.sum(jnp.sin(checked(x)) * x)

    def reference(x):
        return jnp.sum(jnp.sin(x) * x)

    np.testing.assert_array_equal(np.asarray(jax.grad(f)(x)), np.asarray(jax.grad(reference)(x)))
    np.testing.assert_array_equal(np.asarray(jax.jit(jax.grad(f))(x)), np.asarray(jax.grad(reference)(x)))
    out, tangent = jax.jvp(jitted, (x,), (jnp.array([1.0, -2.0]),))
    np.testing.assert_array_equal(np.asarray(tangent), [2.0, -4.0])
    # a gradient of a program whose value needs the checked array still checks it
    with pytest.raises(FAILED, match="^INVALID_ARGUMENT: x contains NaN or inf"):
        jax.block_until_ready(jax.jit(jax.grad(f))(jnp.array([0.5, jnp.nan])))


# the program of the persistent-cache test, compiled by this process and by a fresh one
_PROGRAM = """
import jax, jax.numpy as jnp
from jaxbody.validation import raise_if_any

x = jnp.array([1.0, jnp.nan])

def failure(f):
    try:
        jax.block_until_ready(f(x))
    except Exception as err:
        return str(err)
    return ""

stored = jax.jit(lambda x: 3.0 * raise_if_any(x, [(~jnp.all(jnp.isfinite(x)), "x contains NaN or inf")]))
"""

# the fresh process: first without a C++ compiler (the host-callback fallback), then with one,
# loading the stored program
_PROBE = _PROGRAM + """
import json, os
events = []
jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
from jaxbody import runtime_check
reason = runtime_check.unavailable_reason()
bare = failure(jax.jit(lambda x: 2.0 * raise_if_any(x, [(~jnp.all(jnp.isfinite(x)), "x contains NaN or inf")])))
del os.environ["CXX"]
events.clear()  # the stored program's compilation alone
loaded = failure(stored)
print(json.dumps(dict(reason=reason, bare=bare, loaded=loaded, hit="/jax/compilation_cache/cache_hits" in events)))
"""


@pytest.fixture
def every_compilation_stored():
    before = jax.config.jax_persistent_cache_min_compile_time_secs
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    try:
        yield
    finally:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before)


def test_the_check_is_stored_in_the_persistent_cache_and_falls_back_without_a_compiler(every_compilation_stored):
    # this process stores the program (in the suite's JAX cache)
    program = {}
    exec(_PROGRAM, program)
    assert program["failure"](program["stored"]).splitlines()[0] == "INVALID_ARGUMENT: x contains NaN or inf"
    env = dict(os.environ, CXX="/nonexistent", JAX_ENABLE_X64="1", JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    done = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    # without a compiler: the callback's error, with the message further down
    assert out["reason"].startswith("no C++ compiler found (/nonexistent")
    assert out["bare"].splitlines()[0].startswith("INTERNAL: CpuCallback error")
    assert "ValueError: x contains NaN or inf" in out["bare"]
    # with one: the stored program, loaded, still raises
    assert out["hit"] and out["loaded"].splitlines()[0] == "INVALID_ARGUMENT: x contains NaN or inf"
