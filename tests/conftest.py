"""Test-wide JAX settings, as the command line sets them: 64-bit types available (GP fitting runs in
float64; the step is float32 by explicit dtypes), and strict dtype and rank promotion so that an
accidental float64 in the float32 core, or a silent broadcast, fails loudly."""

import os
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")

SHARED = Path(os.environ.get("GTSJAX_SHARED", Path(__file__).resolve().parents[1].parent / "shared"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED}")
    return SHARED
