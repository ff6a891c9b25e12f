"""Test-wide JAX settings: the entry points' XLA settings and compilation cache, float64 available, full-precision
matmuls; and shared helpers."""

from __future__ import annotations

import os
import pathlib

from fgjax.xla_env import use_compilation_cache, use_fast_cpu_compile

REPO = pathlib.Path(__file__).resolve().parents[1]
use_fast_cpu_compile()  # as the command line does; before jax starts its backend
# as the command line does, but in the repository (.cache/, ignored by git): a clean clone starts with none, and
# the workers of `pytest -n` share it
use_compilation_cache(REPO / ".cache" / "jax")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_default_matmul_precision", "highest")

# re-exported for the tests: `from conftest import synth`
from fgjax import cli, synth  # noqa: E402, F401

SHARED_DATA = REPO.parent / "shared" / "data"


def shared_data(name: str) -> pathlib.Path:
    """Path of ../shared/data/NAME; skips the test with a clear message when absent."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"shared dataset {path} is absent (expected at ../shared/data relative to the repo root)")
    return path


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    """``fgjax ARGV`` in this process (arguments made strings): (exit status, stdout, stderr) of that call alone."""
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def key():
    return jax.random.key(0)


os.environ.setdefault("FGJAX_TEST", "1")


def look_at(centre, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """OpenCV world-to-camera 4x4 of a camera at `centre` looking at `target`, world z up."""
    c = np.asarray(centre, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    vm = np.eye(4)
    vm[:3, :3] = np.stack([x, y, z])
    vm[:3, 3] = -vm[:3, :3] @ c
    return vm

