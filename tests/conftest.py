"""Test configuration: float64 and strict dtype promotion for every test (STYLE rule 13)."""

import os
import pathlib

os.environ.setdefault("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

REPO = pathlib.Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
MODELS = SHARED / "models"


@pytest.fixture(scope="session")
def models_dir():
    if not MODELS.exists():
        pytest.skip(f"shared models not found at {MODELS}")
    return MODELS
