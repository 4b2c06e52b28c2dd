"""Test configuration: every test runs in float64 with strict dtype promotion, so a silent
narrowing to float32 or an implicit promotion between dtypes fails the test; the vectorised
kernel is the default kernel unless the caller chose one; the processes of
one run (pytest-xdist workers, and the ``jaxbody`` commands, notebooks and benchmark scripts
the tests start) share one JAX compilation cache, so a program several tests compile the same
way is compiled once per run; and XLA compiles without its machine-code optimiser (below)."""

import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

from jaxbody._xla import set_default_xla_flags  # importing jaxbody does not start JAX's backend

set_default_xla_flags()  # before the backend starts

# Compiling is most of the suite's time, and about half of a compile is LLVM optimising the
# machine code (measured on tests/test_dynamics_identities.py: 108 s of CPU at the default
# level, 60 s at level 0). The tests check numbers against references to tolerances, which do
# not depend on how fast the code runs, so they compile at level 0: the HLO programs and their
# arithmetic are XLA's, only instruction selection differs. The exceptions, tests of a property
# only optimised code has (a rounding error that needs the fused multiply-adds the optimiser
# makes, two programs that round alike only with them), carry the marker
# ``default_optimisation`` and run in a subprocess at the default levels (below). The native
# kernel's C++ is built at -O0 likewise. Both levels set here also turn jaxbody's tiered
# compilation off (a quick first compile, its optimised one in the background): the suite's
# programs are all quick ones; test_program_store.py and test_backends_native.py test tiering.
# JAXBODY_TEST_XLA_OPTIMISATION=default runs the whole suite at the default level.
OPTIMISATION_FLAG = "--xla_backend_optimization_level"
# XLA also splits each program's machine code into parts compiled on parallel threads; the
# suite already keeps every core busy with its own workers, so the split only adds work (one
# part per program: 17% less compile time on tests/test_dynamics_identities.py, 23.0 s to
# 19.1 s, with the same results: the split changes how code is compiled, not what it computes).
CODEGEN_SPLIT_FLAG = "--xla_cpu_parallel_codegen_split_count=1"
# (pytest-xdist workers inherit the controller's flags: JAXBODY_TEST_REDUCED_OPTIMISATION tells
# them the level was lowered here and not by the caller)
REDUCED_OPTIMISATION = os.environ.get("JAXBODY_TEST_XLA_OPTIMISATION") != "default" and (
    os.environ.get("JAXBODY_TEST_REDUCED_OPTIMISATION") == "1"
    or OPTIMISATION_FLAG not in os.environ.get("XLA_FLAGS", ""))
if REDUCED_OPTIMISATION and os.environ.get("JAXBODY_TEST_REDUCED_OPTIMISATION") != "1":
    os.environ["JAXBODY_TEST_REDUCED_OPTIMISATION"] = "1"
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {OPTIMISATION_FLAG}=0 {CODEGEN_SPLIT_FLAG}".strip()
    # the same for the native kernel's C++ (about 10x faster builds; see compiler_flags)
    os.environ.setdefault("JAXBODY_NATIVE_OPTIMISATION", "-O0")

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
# Likewise the suite traces its solves rather than storing each as a program
# (jaxbody.program_store): exporting and writing hundreds of one-off programs added about a
# tenth to the simulation tests' time (tests/test_simulation.py and test_simulation_features.py:
# 65 s to 78 s on 2 workers). test_program_store.py turns the store on for its own tests;
# ``JAXBODY_PROGRAM_STORE=1 ./run tests`` runs the whole suite on the default.
os.environ.setdefault("JAXBODY_PROGRAM_STORE", "0")

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1.0")))


def pytest_pyfunc_call(pyfuncitem):
    """A test marked ``default_optimisation`` runs in a pytest subprocess at XLA's and the native
    kernel's default optimisation levels when this process compiles at reduced ones (see the top
    of this file)."""
    if not (REDUCED_OPTIMISATION and pyfuncitem.get_closest_marker("default_optimisation")):
        return None
    env = dict(os.environ, JAXBODY_TEST_XLA_OPTIMISATION="default", JAXBODY_NATIVE_OPTIMISATION="-O2")
    env.pop("JAXBODY_TEST_REDUCED_OPTIMISATION", None)
    env["XLA_FLAGS"] = " ".join(f for f in env["XLA_FLAGS"].split() if not f.startswith(OPTIMISATION_FLAG))
    done = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-n", "0", "-q",
                           "-m", "", pyfuncitem.nodeid], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, f"at the default optimisation levels:\n{done.stdout[-6000:]}{done.stderr[-2000:]}"
    return True


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
