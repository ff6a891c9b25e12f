"""Test-wide JAX settings: the entry points' XLA settings and compilation cache, float64 available, full-precision
matmuls, XLA's backend optimisation per test (below); and shared helpers.

Most tests compile far more than they run: compiling is about half of the suite's time, and XLA:CPU's LLVM
optimisation is most of each compile. So a test compiles with ``jax_disable_most_optimizations`` (a third of the
compile time; the programs run several times slower) unless it is marked ``@pytest.mark.optimized``: the tests
whose time goes into running long fits (the quality floors, the field and placement benchmarks, the photometric
trackers, the hinge search) or whose assertion sits on a trained run's number near a threshold, which run compiled
as the command line compiles. ``FGJAX_TEST_OPTIMIZE=1`` compiles every test as the command line does. The marked
tests go first, so that each pytest-xdist worker changes the level about once; where it changes, ``jax.clear_caches``
drops every compiled program, so that no test runs a program compiled at the other level (the persistent cache keys
the two apart by their compile options)."""

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

OPTIMIZE_ALL = os.environ.get("FGJAX_TEST_OPTIMIZE", "") == "1"


def pytest_configure(config):
    config.addinivalue_line("markers", "optimized: compiled with XLA's full backend optimisation, as the command "
                            "line compiles (module docstring)")


def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda item: item.get_closest_marker("optimized") is None)  # stable: marked tests first


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    """Before the test's fixtures: XLA's optimisation level for everything it compiles (module docstring)."""
    disable = not (OPTIMIZE_ALL or item.get_closest_marker("optimized") is not None)
    if jax.config.values["jax_disable_most_optimizations"] is not disable:
        jax.clear_caches()
        jax.config.update("jax_disable_most_optimizations", disable)


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

