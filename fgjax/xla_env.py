"""Process-wide XLA settings for fgjax's entry points (the command line, the tests).

Nothing here imports JAX: XLA reads ``XLA_FLAGS`` once, when the first computation starts its backend, so
an entry point calls `use_fast_cpu_compile` before it runs anything. The library modules never touch the
environment.

``--xla_cpu_use_fusion_emitters=false`` shortens XLA:CPU compile times, which dominate fgjax's small runs
(the quick demo, the tests; about a third shorter on a 2-core CPU with jaxlib 0.10); the results change only by
rounding, and the steps of large scenes (20k Gaussians) may run about 10 % slower. XLA aborts on a flag it does not know, so the flag is only added for the
jaxlib releases listed in `MEASURED_JAXLIB`; it only affects the CPU backend. ``FGJAX_XLA_DEFAULTS=0`` leaves
``XLA_FLAGS`` alone.
"""

from __future__ import annotations

import importlib.metadata
import os
from collections.abc import MutableMapping

FAST_CPU_COMPILE = "--xla_cpu_use_fusion_emitters=false"
MEASURED_JAXLIB = ((0, 10),)  # (major, minor) releases the flag was measured with


def _jaxlib_release() -> tuple[int, int] | None:
    try:
        parts = importlib.metadata.version("jaxlib").split(".")
        return int(parts[0]), int(parts[1])
    except (importlib.metadata.PackageNotFoundError, ValueError, IndexError):
        return None


def use_fast_cpu_compile(environ: MutableMapping[str, str] | None = None,
                         release: tuple[int, int] | None = None) -> bool:
    """Adds `FAST_CPU_COMPILE` to ``environ["XLA_FLAGS"]`` (default: ``os.environ``) unless the flag is
    already set there (either value), ``FGJAX_XLA_DEFAULTS=0`` opts out, or the jaxlib release (default:
    the installed one) is not one it was measured with. Returns whether it was added."""
    env = os.environ if environ is None else environ
    release = _jaxlib_release() if release is None else release
    flags = env.get("XLA_FLAGS", "")
    if env.get("FGJAX_XLA_DEFAULTS", "1") == "0" or release not in MEASURED_JAXLIB:
        return False
    if FAST_CPU_COMPILE.split("=")[0] in flags:
        return False
    env["XLA_FLAGS"] = f"{flags} {FAST_CPU_COMPILE}".strip()
    return True
