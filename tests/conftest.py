"""Test configuration: every test runs in float64 with strict dtype promotion, so a silent
narrowing to float32 or an implicit promotion between dtypes fails the test; the vectorised
kernel is the default kernel unless the caller chose one; and the processes of
one run (pytest-xdist workers, and the ``jaxbody`` commands, notebooks and benchmark scripts
the tests start) share one JAX compilation cache, so a program several tests compile the same
way is compiled once per run."""

import os
import pathlib
import shutil
import tempfile

from jaxbody._xla import set_default_xla_flags  # importing jaxbody does not start JAX's backend

set_default_xla_flags()  # before the backend starts

# The first process of a run (the xdist controller, or the only process) makes the cache
# folder and hands it to every process it starts through JAX's environment variables; each
# run starts empty, as CI does, so nothing compiled by another version of the code is reused.
# A caller's own JAX_COMPILATION_CACHE_DIR is kept (and not removed).
_OWN_CACHE = None
if not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
    _OWN_CACHE = tempfile.mkdtemp(prefix="jaxbody-test-jax-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _OWN_CACHE
    # compilations under 0.1 s (single eager operations) are cheaper to repeat than to store
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.1")

# The suite builds hundreds of different trees (random models, chains of every length): on
# jaxbody's default kernel ("auto": the native kernel) each would cost a C++ build of seconds.
# The suite runs the vectorised kernel unless the caller sets JAXBODY_KERNEL (``JAXBODY_KERNEL=auto
# ./run tests`` runs it on the default); the processes it starts inherit the choice. Tests of
# the default itself remove the variable (test_scene.py, test_backends_native.py).
os.environ.setdefault("JAXBODY_KERNEL", "vectorised")

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1.0")))


def pytest_unconfigure(config):
    if _OWN_CACHE is not None:
        shutil.rmtree(_OWN_CACHE, ignore_errors=True)


REPO = pathlib.Path(__file__).resolve().parents[1]
# the robot models (panda, ur5e, anymal_c) shipped with the package: the MuJoCo comparison tests
# always have them, so they never skip for want of a file outside the repository
MODELS = REPO / "jaxbody" / "models"


@pytest.fixture(scope="session")
def models_dir():
    missing = [n for n in ("panda.xml", "ur5e.xml", "anymal_c.xml") if not (MODELS / n).is_file()]
    assert not missing, f"robot models missing from {MODELS}: {missing}"
    return MODELS
