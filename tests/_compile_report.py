"""A pytest plugin that measures where the test suite's time goes: per test, its wall time (setup, call and
teardown) and the seconds JAX spends tracing, lowering and compiling (XLA's backend compile), by jitted function.

    FGJAX_COMPILE_REPORT=DIR PYTHONPATH=tests pytest -q -n 2 -p _compile_report
    python tests/_compile_report.py DIR          # the totals, then the modules by wall time

Each test process writes DIR/<pid>.jsonl (one line per test) when it ends. The durations come from
`jax.monitoring`'s duration events ("/jax/core/compile/..."), which JAX records with the function's name. Not loaded
by `make test`; docs/benchmarks.md, "The tests' compile level", is measured with it.
"""

from __future__ import annotations

import collections
import json
import os
import sys
import time
from pathlib import Path

import pytest

from fgjax.cli import CompileSeconds

_current: list[str] = []  # the node id of the test running in this process
_tests: dict[str, CompileSeconds] = collections.defaultdict(CompileSeconds)  # node id -> its events, its wall


def _listener(event: str, duration: float, **kwargs) -> None:
    _tests[_current[0] if _current else "<outside tests>"].record(event, duration, **kwargs)


def pytest_configure(config):
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_listener)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _current[:] = [item.nodeid]
    start = time.perf_counter()
    yield
    _tests[item.nodeid].wall += time.perf_counter() - start
    _current.clear()


def pytest_unconfigure(config):
    folder = os.environ.get("FGJAX_COMPILE_REPORT")
    if not folder:
        return
    Path(folder).mkdir(parents=True, exist_ok=True)
    with open(Path(folder) / f"{os.getpid()}.jsonl", "w") as f:
        for node, e in _tests.items():
            f.write(json.dumps({"test": node, "wall": e.wall, "seconds": e.seconds, "compiles": e.programs,
                                "by_function": dict(e.by_function.most_common(15))}) + "\n")


def summary(folder: str) -> str:
    """The totals over every test process's file in `folder`, then each test module's, by wall time."""
    modules: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for path in sorted(Path(folder).glob("*.jsonl")):
        for line in path.read_text().splitlines():
            r = json.loads(line)
            m = modules[r["test"].split("::")[0]]
            m["wall"] += r["wall"]
            m["compile"] += r["seconds"].get("XLA compile", 0.0)
            m["trace"] += r["seconds"].get("tracing", 0.0) + r["seconds"].get("lowering", 0.0)
            m["compiles"] += r["compiles"]
    total = sum(modules.values(), collections.Counter())
    rows = [f"{'wall s':>8} {'compile s':>9} {'trace s':>8} {'compiles':>8}  module"]
    for name, m in [("all", total), *sorted(modules.items(), key=lambda kv: -kv[1]["wall"])]:
        rows.append(f"{m['wall']:8.1f} {m['compile']:9.1f} {m['trace']:8.1f} {m['compiles']:8d}  {name}")
    return "\n".join(rows)


if __name__ == "__main__":
    print(summary(sys.argv[1]))
