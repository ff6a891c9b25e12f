"""The entry points' XLA settings (`fgjax.xla_env`): the compile flag added once, only for measured jaxlib releases;
the persistent compilation cache written, read back and pruned; the command line's report of its compile seconds
(``FGJAX_COMPILE_SECONDS``, `fgjax.cli.CompileSeconds`)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest

from fgjax import cli, xla_env


def test_fast_cpu_compile_flag_is_added_once_and_only_where_measured():
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert xla_env.use_fast_cpu_compile(env, release=(0, 10))
    assert env["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2 " + xla_env.FAST_CPU_COMPILE
    assert not xla_env.use_fast_cpu_compile(env, release=(0, 10))  # already there: not repeated
    assert env["XLA_FLAGS"].count("fusion_emitters") == 1
    env = {}
    assert not xla_env.use_fast_cpu_compile(env, release=(0, 9))  # XLA aborts on unknown flags: not guessed
    assert env == {}
    env = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}  # the user's choice wins
    assert not xla_env.use_fast_cpu_compile(env, release=(0, 10))
    assert env["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"
    env = {"FGJAX_XLA_DEFAULTS": "0"}
    assert not xla_env.use_fast_cpu_compile(env, release=(0, 10)) and "XLA_FLAGS" not in env
    env = {}
    assert xla_env.use_fast_cpu_compile(env, release=(0, 10)) and env["XLA_FLAGS"] == xla_env.FAST_CPU_COMPILE


def test_the_test_process_runs_with_the_entry_points_settings():
    """conftest.py applies the same settings as `fgjax.cli.main`, so the tests run what users run."""
    if xla_env._jaxlib_release() in xla_env.MEASURED_JAXLIB and os.environ.get("FGJAX_XLA_DEFAULTS", "1") != "0":
        assert "--xla_cpu_use_fusion_emitters=" in os.environ.get("XLA_FLAGS", "")
    if os.environ.get("FGJAX_XLA_DEFAULTS", "1") != "0":  # and the compilation cache, shared by the workers
        assert jax.config.jax_compilation_cache_dir == os.environ["JAX_COMPILATION_CACHE_DIR"] != ""
        assert jax.config.jax_persistent_cache_min_compile_time_secs == float(
            os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])


def test_compilation_cache_defaults_keep_the_users_settings_and_turn_off(tmp_path):
    env = {"XDG_CACHE_HOME": str(tmp_path)}
    assert xla_env.use_compilation_cache(None, env) == tmp_path / "fgjax" / "jax"
    assert env["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path / "fgjax" / "jax")
    assert env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "0" and (tmp_path / "fgjax" / "jax").is_dir()
    (tmp_path / "file").write_text("")
    env = {}  # a folder that cannot be made (under a file): no cache, nothing set
    assert xla_env.use_compilation_cache(tmp_path / "file" / "jax", env) is None and env == {}
    env = {"JAX_COMPILATION_CACHE_DIR": "/mine", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "1.5"}
    assert xla_env.use_compilation_cache("/other", env) == Path("/mine")  # the user's choice wins
    assert env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "1.5"
    env = {"JAX_COMPILATION_CACHE_DIR": ""}  # empty: off
    assert xla_env.use_compilation_cache("/other", env) is None
    env = {"FGJAX_XLA_DEFAULTS": "0"}
    assert xla_env.use_compilation_cache("/other", env) is None and env == {"FGJAX_XLA_DEFAULTS": "0"}
    assert xla_env.default_cache_dir({}) == Path(os.path.expanduser("~")) / ".cache" / "fgjax" / "jax"


def test_prune_cache_deletes_the_oldest_files_down_to_half(tmp_path):
    for i in range(10):  # file i: 100 bytes, modified at time 1000 + i
        (tmp_path / f"e{i}").write_bytes(bytes(100))
        os.utime(tmp_path / f"e{i}", (1000 + i, 1000 + i))
    assert xla_env.prune_cache(tmp_path, 1000) == 0  # not past the limit: kept
    assert xla_env.prune_cache(tmp_path, 999) == 6  # 1000 > 999: the six oldest go, 400 <= 499 stays
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e6", "e7", "e8", "e9"]
    assert xla_env.prune_cache(tmp_path / "absent", 0) == 0
    assert xla_env.prune_cache(tmp_path / "e6", 0) == 0  # not a folder: nothing to prune, no error
    # the folder `use_compilation_cache` sets is pruned; one already named in the environment is left as it is
    env = {"JAX_COMPILATION_CACHE_DIR": str(tmp_path)}
    assert xla_env.use_compilation_cache(tmp_path / "x", env, max_bytes=1) == tmp_path
    assert len(list(tmp_path.iterdir())) == 4
    assert xla_env.use_compilation_cache(tmp_path, {}, max_bytes=1) == tmp_path
    assert list(tmp_path.iterdir()) == []


def test_compiled_programs_are_written_to_the_cache_and_read_back_by_another_process(tmp_path):
    """Through `use_compilation_cache` before JAX's import, as the command line does: a first process writes a jitted
    program's executable into the folder; a second compiles nothing and reads it back."""
    code = textwrap.dedent(f"""
        from fgjax.xla_env import use_compilation_cache
        use_compilation_cache({str(tmp_path / "cache")!r})
        import jax, jax.numpy as jnp
        hits = []
        jax.monitoring.register_event_listener(
            lambda event, **_: hits.append(event) if event == "/jax/compilation_cache/cache_hits" else None)
        print(float(jax.jit(lambda x: jnp.sin(x) * 3.0 + x ** 2)(jnp.float32(0.5))), len(hits))
    """)
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
            for _ in range(2)]
    assert len(list((tmp_path / "cache").iterdir())) >= 1, runs
    first, second = (r.split() for r in runs)
    assert first[0] == second[0] and int(first[1]) == 0 and int(second[1]) >= 1, runs


def test_compile_seconds_count_the_programs_built_inside_the_context_only():
    import jax.numpy as jnp

    f = jax.jit(lambda x: jnp.cos(x) * 1.2345678 + x ** 3)  # a program no other test builds
    x = jnp.full((3,), 0.25, jnp.float32)
    with cli.CompileSeconds() as seconds:
        f(x)
    assert seconds.programs == 1 and seconds.seconds["XLA compile"] > 0 and seconds.seconds["tracing"] > 0
    assert any("lambda" in name for name in seconds.by_function), seconds.by_function
    assert 0 < sum(seconds.seconds.values()) <= seconds.wall
    jax.jit(lambda x: jnp.sin(x) * 7.654321)(x)  # after the context: not counted
    assert seconds.programs == 1
    report = seconds.report()
    assert report.startswith(f"fgjax: {sum(seconds.seconds.values()):.1f} s of {seconds.wall:.1f} s") and "\n" in report


def test_the_command_line_reports_its_compile_seconds_when_asked(tmp_path):
    """``FGJAX_COMPILE_SECONDS=1 fgjax synth``: one report after the command; a second run with the same compilation
    cache reads every program back; without the variable, no report."""
    argv = [sys.executable, "-m", "fgjax.cli", "synth", "--out", str(tmp_path / "scene"), "--width", "32", "--height",
            "24", "--frames", "3", "--quiet", "--overwrite"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env.update(JAX_COMPILATION_CACHE_DIR=str(tmp_path / "cache"), FGJAX_COMPILE_SECONDS="1")
    reports = []
    for _ in range(2):
        err = subprocess.run(argv, env=env, capture_output=True, text=True, check=True).stderr
        found = re.search(r"in JAX's compile path \(.*\); (\d+) program\(s\), (\d+) of them read back", err)
        assert found, err
        reports.append((int(found[1]), int(found[2])))
        assert "by function:" in err and "_render_frame" in err, err
    assert reports[0][0] >= 1 and reports[0][1] == 0, reports
    assert reports[1][1] == reports[1][0] >= 1, reports
    env["FGJAX_COMPILE_SECONDS"] = "0"
    err = subprocess.run(argv, env=env, capture_output=True, text=True, check=True).stderr
    assert "compile path" not in err, err


def test_a_test_compiles_without_most_optimisations_unless_marked():
    """tests/conftest.py: an unmarked test compiles with ``jax_disable_most_optimizations`` (unless
    FGJAX_TEST_OPTIMIZE=1), and its programs still compute what the optimised ones do."""
    import jax.numpy as jnp
    from conftest import OPTIMIZE_ALL

    assert jax.config.values["jax_disable_most_optimizations"] is (not OPTIMIZE_ALL)
    x = jnp.linspace(-3.0, 3.0, 101, dtype=jnp.float32)
    np.testing.assert_allclose(np.asarray(jax.jit(jax.grad(lambda v: jnp.sum(jnp.tanh(v) ** 2)))(x)),
                               2 * np.tanh(np.asarray(x)) / np.cosh(np.asarray(x)) ** 2, rtol=1e-5, atol=1e-6)


@pytest.mark.optimized
def test_a_marked_test_compiles_as_the_command_line_does():
    assert jax.config.values["jax_disable_most_optimizations"] is False
