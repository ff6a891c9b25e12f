"""The entry points' XLA settings (`fgjax.xla_env`): added once, only for measured jaxlib releases."""

from __future__ import annotations

import os

from fgjax import xla_env


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
