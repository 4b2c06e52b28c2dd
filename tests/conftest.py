"""Test configuration: every test runs in float64 with strict dtype promotion, so a silent
narrowing to float32 or an implicit promotion between dtypes fails the test."""

import pathlib

from jaxbody._xla import set_default_xla_flags  # importing jaxbody does not start JAX's backend

set_default_xla_flags()  # before the backend starts

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

REPO = pathlib.Path(__file__).resolve().parents[1]
# the robot models (panda, ur5e, anymal_c) shipped with the package: the MuJoCo comparison tests
# always have them, so they never skip for want of a file outside the repository
MODELS = REPO / "jaxbody" / "models"


@pytest.fixture(scope="session")
def models_dir():
    missing = [n for n in ("panda.xml", "ur5e.xml", "anymal_c.xml") if not (MODELS / n).is_file()]
    assert not missing, f"robot models missing from {MODELS}: {missing}"
    return MODELS
