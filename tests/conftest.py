"""Test-wide JAX settings: float64 available, full-precision matmuls, and shared helpers."""

from __future__ import annotations

import os
import pathlib

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_default_matmul_precision", "highest")

REPO = pathlib.Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def shared_data(name: str) -> pathlib.Path:
    """Path of ../shared/data/NAME; skips the test with a clear message when absent."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"shared dataset {path} is absent (expected at ../shared/data relative to the repo root)")
    return path


@pytest.fixture
def key():
    return jax.random.key(0)


os.environ.setdefault("FGJAX_TEST", "1")
