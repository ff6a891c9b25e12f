"""fgjax command line: a thin dispatcher.

Each sub-command is a module of `fgjax.apps` (or `fgjax.bench`) exposing ``main(argv) -> int``;
this file only maps names to those modules, so that ``fgjax --help`` stays fast
(nothing heavy is imported until a command runs). ``FGJAX_COMPILE_SECONDS=1`` prints, after the command, where
its time in JAX's compile path went (`CompileSeconds`).
"""

from __future__ import annotations

import collections
import importlib
import os
import sys
import time
import zipfile

from fgjax.version import __version__

# command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("fgjax.apps.demo", "run the whole pipeline on the built-in synthetic scene"),
    "synth": ("fgjax.apps.synth", "generate a synthetic articulated scene with ground truth"),
    "prepare": ("fgjax.apps.prepare", "a phone clip (poses by SfM) or a Record3D export to a scene folder"),
    "flow": ("fgjax.apps.flow", "estimate optical flow over a sequence (cached)"),
    "train": ("fgjax.apps.train", "stage 1: deformable Gaussian training"),
    "run": ("fgjax.apps.run", "flow, stage 1, stage 2, pictures and metrics on a scene folder in one command"),
    "stage2": ("fgjax.apps.stage2", "discovery, clustering and control network on a trained run"),
    "render": ("fgjax.apps.render", "render cameras (or --clusters object ids) from a trained run"),
    "control": ("fgjax.apps.control", "move a discovered object and render"),
    "eval": ("fgjax.apps.evaluate", "evaluate a run against ground truth"),
    "export": ("fgjax.apps.export", "write a run's scene (at a time, or with objects moved) as a standard 3DGS .ply"),
    "view": ("fgjax.apps.view", "interactive web viewer: the splat, a time slider, a control per object"),
}

BENCHES: dict[str, tuple[str, str]] = {
    "raster": ("fgjax.bench.raster", "tile rasterizer: time, memory, error vs dense reference"),
    "flow": ("fgjax.bench.flow", "flow derivatives: time and end-point error vs reprojection"),
    "opticalflow": ("fgjax.bench.opticalflow", "OpenCV optical flow: EPE and time on Middlebury/Sintel"),
    "train": ("fgjax.bench.train", "stage-1 PSNR against wall time"),
    "motion": ("fgjax.bench.motion", "stage-1 run: object vs static PSNR, learned vs true object motion"),
    "field": ("fgjax.bench.field", "the deformation field alone fitted to a local motion: L1 against L2"),
    "track": ("fgjax.bench.track", "photometric tracker: time a frame drawing all Gaussians vs those near the parts"),
    "placement": ("fgjax.bench.placement", "which parts the flow placement of the motion bases finds, by frame span"),
    "family": ("fgjax.bench.family", "the whole pipeline on seeds of the scene family: ARI, parts found, PSNR, time"),
    "step": ("fgjax.bench.step", "stage-1 step (cameras looped vs vmapped), render with active tiles vs all"),
    "viewer": ("fgjax.bench.viewer", "viewer: time from a control change to the Gaussians ready to send"),
}


def _usage() -> str:
    lines = ["usage: fgjax COMMAND [options]   (fgjax COMMAND --help for options)", "", "commands:"]
    lines += [f"  {name:<12} {help_}" for name, (_, help_) in COMMANDS.items()]
    lines += [f"  {'bench':<12} benchmarks: " + ", ".join(BENCHES)]
    return "\n".join(lines)


def _dispatch(table: dict[str, tuple[str, str]], name: str, argv: list[str], prog: str) -> int:
    module_name, _ = table[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name == module_name:
            print(f"fgjax: '{prog}' is not implemented yet in this version.", file=sys.stderr)
            return 2
        raise
    try:
        return int(module.main(argv) or 0)
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        # Bad input or a file system that refuses (a missing or corrupt file, a malformed field, a read-only or full
        # folder, a path that is a file): one clear line, no traceback. FGJAX_DEBUG=1 shows the traceback.
        if os.environ.get("FGJAX_DEBUG"):
            raise
        print(f"fgjax {prog}: error: {_one_line(e)}", file=sys.stderr)
        return 2


def _one_line(e: BaseException) -> str:
    """The error as one line: an OSError names its file and the system's reason."""
    if isinstance(e, OSError) and e.filename is not None:
        what = e.strerror or type(e).__name__
        return f"{e.filename}: {what}" + (f" (and {e.filename2})" if e.filename2 else "")
    return " ".join(str(e).split()) or type(e).__name__


# `jax.monitoring`'s duration events (names end in these) that `CompileSeconds` adds up
COMPILE_EVENTS = {"jaxpr_trace_duration": "tracing", "jaxpr_to_mlir_module_duration": "lowering",
                  "backend_compile_duration": "XLA compile"}


class CompileSeconds:
    """The seconds a command spends in JAX's tracing, lowering to MLIR and XLA's backend compile (for a program read
    back from the persistent compilation cache, the read), from `jax.monitoring`'s duration events, in total and by
    jitted function, and how many programs were built and how many of them read back; ``FGJAX_COMPILE_SECONDS=1``
    prints them after the command (`report`). A context manager: the listeners are registered on entry and removed
    on exit."""

    def __init__(self):
        self.seconds: collections.Counter = collections.Counter()  # stage ("tracing", ...) -> seconds
        self.by_function: collections.Counter = collections.Counter()  # function name -> seconds, all stages
        self.programs = 0  # programs built by the backend (compiled, or read back from the cache)
        self.cache_hits = 0  # of them read back
        self.wall = 0.0

    def record(self, event: str, duration: float, **kwargs) -> None:
        """Adds one `jax.monitoring` duration event (others than `COMPILE_EVENTS` are ignored); the listener the
        context registers, also usable on its own (tests/_compile_report.py routes each test's events to its own)."""
        stage = COMPILE_EVENTS.get(event.rsplit("/", 1)[-1])
        if stage is None:
            return
        self.seconds[stage] += duration
        self.by_function[str(kwargs.get("fun_name", "?"))] += duration
        self.programs += stage == "XLA compile"

    def _event(self, event: str, **kwargs) -> None:
        self.cache_hits += event == "/jax/compilation_cache/cache_hits"

    def __enter__(self):
        import jax.monitoring

        jax.monitoring.register_event_duration_secs_listener(self.record)
        jax.monitoring.register_event_listener(self._event)
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        import jax.monitoring

        self.wall = time.perf_counter() - self._t0
        jax.monitoring.unregister_event_duration_listener(self.record)
        jax.monitoring.unregister_event_listener(self._event)

    def report(self, top: int = 8) -> str:
        """Two lines: the totals against the command's wall time, then the `top` functions by their seconds."""
        total = sum(self.seconds.values())
        parts = ", ".join(f"{self.seconds[s]:.1f} s {s}" for s in COMPILE_EVENTS.values())
        head = (f"fgjax: {total:.1f} s of {self.wall:.1f} s in JAX's compile path ({parts}); {self.programs} "
                f"program(s), {self.cache_hits} of them read back from the compilation cache")
        funs = ", ".join(f"{name} {sec:.1f} s" for name, sec in self.by_function.most_common(top))
        return head + (f"\nfgjax: by function: {funs}" if funs else "")


def main(argv: list[str] | None = None) -> int:
    from fgjax.xla_env import use_compilation_cache, use_fast_cpu_compile

    use_fast_cpu_compile()  # before any computation starts XLA's backend
    use_compilation_cache()  # before anything imports JAX
    if os.environ.get("FGJAX_COMPILE_SECONDS", "0") not in ("", "0"):
        with CompileSeconds() as seconds:
            code = _main(argv)
        print(seconds.report(), file=sys.stderr)
        return code
    return _main(argv)


def _main(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    if argv[0] in ("--version", "-V"):
        print(f"fgjax {__version__}")
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd == "bench":
        if not rest or rest[0] in ("-h", "--help"):
            print("usage: fgjax bench NAME [options]\n\nbenchmarks:")
            for name, (_, help_) in BENCHES.items():
                print(f"  {name:<12} {help_}")
            return 0
        if rest[0] not in BENCHES:
            print(f"fgjax bench: unknown benchmark '{rest[0]}' (choose from {', '.join(BENCHES)})", file=sys.stderr)
            return 2
        return _dispatch(BENCHES, rest[0], rest[1:], f"bench {rest[0]}")
    if cmd not in COMMANDS:
        print(f"fgjax: unknown command '{cmd}'\n\n{_usage()}", file=sys.stderr)
        return 2
    return _dispatch(COMMANDS, cmd, rest, cmd)


if __name__ == "__main__":
    sys.exit(main())
