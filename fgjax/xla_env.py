"""Process-wide XLA settings for fgjax's entry points (the command line, the tests).

Nothing here imports JAX: XLA reads ``XLA_FLAGS`` once, when the first computation starts its backend, so
an entry point calls `use_fast_cpu_compile` before it runs anything. The library modules never touch the
environment.

``--xla_cpu_use_fusion_emitters=false`` shortens XLA:CPU compile times, which dominate fgjax's small runs
(the quick demo, the tests; about a third shorter on a 2-core CPU with jaxlib 0.10); the results change only by
rounding, and the steps of large scenes (20k Gaussians) may run about 10 % slower. XLA aborts on a flag it does not
know, so the flag is only added for the jaxlib releases listed in `MEASURED_JAXLIB`; it only affects the CPU
backend.

`use_compilation_cache` turns on JAX's persistent compilation cache (a folder of compiled executables keyed by the
program, the compile options and the jax/jaxlib versions): a program compiled again, in the same run (a function
jitted anew for each call or object) or in a later one, is read back instead of compiled. Every executable is kept
(``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0``): most of fgjax's compiles take under a second, and a rerun reads
them all back (docs/benchmarks.md, "The compilation cache"). The
folder is pruned, oldest first, when it grows past `CACHE_BYTES`. JAX reads these settings from the environment
when it is imported, so an entry point calls this before anything imports JAX; settings already in the environment
are kept. ``FGJAX_XLA_DEFAULTS=0`` leaves the environment alone (neither flag nor cache).
"""

from __future__ import annotations

import importlib.metadata
import os
from collections.abc import MutableMapping
from pathlib import Path

FAST_CPU_COMPILE = "--xla_cpu_use_fusion_emitters=false"
MEASURED_JAXLIB = ((0, 10),)  # (major, minor) releases the flag was measured with
CACHE_BYTES = 2 << 30  # the compilation cache's folder is pruned to half this when it grows past it


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


def default_cache_dir(environ: MutableMapping[str, str] | None = None) -> Path:
    """The command line's compilation cache: ``$XDG_CACHE_HOME/fgjax/jax`` (default ``~/.cache/fgjax/jax``)."""
    env = os.environ if environ is None else environ
    base = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "fgjax" / "jax"


def use_compilation_cache(path: str | os.PathLike | None = None, environ: MutableMapping[str, str] | None = None,
                          max_bytes: int = CACHE_BYTES) -> Path | None:
    """Points JAX's persistent compilation cache at `path` (default: `default_cache_dir`) through
    ``JAX_COMPILATION_CACHE_DIR`` and ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0`` in ``environ`` (default:
    ``os.environ``), each unless already set. The folder it sets is made and pruned (`prune_cache`); a folder
    already named in ``environ`` (the user's, or an earlier call's) is used as it is. Returns the folder in use, or
    None when ``FGJAX_XLA_DEFAULTS=0`` or an empty ``JAX_COMPILATION_CACHE_DIR`` turns the cache off or `path`
    cannot be made or written (then nothing is set). Takes effect only when called before JAX is imported."""
    env = os.environ if environ is None else environ
    if env.get("FGJAX_XLA_DEFAULTS", "1") == "0":
        return None
    named = env.get("JAX_COMPILATION_CACHE_DIR")
    if named is not None:  # the user's folder (or an earlier call's), used as it is
        if not named:
            return None
        folder = Path(named)
    else:
        folder = Path(default_cache_dir(env) if path is None else path)
        try:  # a folder that cannot be made or written (a read-only home): no cache rather than a failed compile
            folder.mkdir(parents=True, exist_ok=True)
            if not os.access(folder, os.W_OK):
                return None
        except OSError:
            return None
        env["JAX_COMPILATION_CACHE_DIR"] = str(folder)
        prune_cache(folder, max_bytes)
    env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    return folder


def prune_cache(folder: Path, max_bytes: int) -> int:
    """When the files directly in `folder` hold more than `max_bytes`, deletes them oldest first (by modification
    time) until they hold at most half of it; returns how many were deleted. A folder or file that cannot be read
    or deleted (another process pruned it first) is skipped: pruning never stops a run, and JAX compiles again
    what it cannot read."""
    entries = []
    try:
        with os.scandir(folder) as it:
            for e in it:
                try:
                    if e.is_file(follow_symlinks=False):
                        st = e.stat(follow_symlinks=False)
                        entries.append((st.st_mtime, st.st_size, e.path))
                except OSError:
                    continue
    except OSError:
        return 0
    total = sum(size for _, size, _ in entries)
    if total <= max_bytes:
        return 0
    deleted = 0
    for _, size, name in sorted(entries):
        if total <= max_bytes // 2:
            break
        try:
            os.remove(name)
            deleted += 1
        except OSError:
            pass
        total -= size
    return deleted
