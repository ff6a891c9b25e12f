"""``fgjax flow``: dense optical flow between consecutive frames (`fgjax.data.flowseq`)."""

from __future__ import annotations

import argparse
import dataclasses
import glob as globlib
import sys
from collections.abc import Sequence
from pathlib import Path

from fgjax.data.flowio import frames_from_transforms, list_frames, natural_key
from fgjax.data.flowmethods import DEFAULT_METHOD, METHODS
from fgjax.data.flowseq import estimate_sequence, import_sequence

# --------------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------------


def _parse_param_args(items: Sequence[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--param {item!r}: expected key=value")
        out[key.strip()] = value.strip()
    return out


def _methods_help() -> str:
    lines = []
    for name, spec in METHODS.items():
        lines.append(f"{name}{' (default)' if name == DEFAULT_METHOD else ''}: {spec.summary}")
        for f in dataclasses.fields(spec.params):
            lines.append(f"    {f.name} = {f.default!r}")
    return "\n".join(lines)


def _build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="fgjax flow",
        description="Dense optical flow between consecutive frames (forward, frame k -> k+1), cached on disk.",
        epilog="Methods and their parameters: fgjax flow --list-methods",
    )
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--images", metavar="DIR_OR_GLOB", help="frames: a folder or a glob, sorted by file name")
    src.add_argument("--data", metavar="SCENE_DIR", help="scene with transforms_SPLIT.json; frames ordered by time")
    ap.add_argument("--split", default="train", help="with --data: read transforms_SPLIT.json (default: train)")
    ap.add_argument("--out", metavar="DIR", help="output folder")
    ap.add_argument("--method", default=DEFAULT_METHOD, help=f"one of {', '.join(METHODS)} (default: {DEFAULT_METHOD})")
    ap.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="method parameter (repeatable)")
    ap.add_argument("--backward", action="store_true", help="also backward flow and forward-backward masks")
    ap.add_argument("--cache", metavar="DIR", help="flow cache folder (keyed by frames, method and parameters)")
    ap.add_argument("--format", default="npy", choices=("npy", "flo"), help="flow file format (default: npy)")
    ap.add_argument("--fb-alpha", type=float, default=0.01, help="forward-backward test: alpha (default 0.01)")
    ap.add_argument("--fb-beta", type=float, default=0.5, help="forward-backward test: beta in px^2 (default 0.5)")
    ap.add_argument("--background", default="white", choices=("white", "black"),
                    help="RGBA frames are composited over this (default: white)")
    ap.add_argument("--import", dest="import_flow", metavar="GLOB",
                    help="import precomputed forward flows (.flo/.npy, sorted by name) instead of estimating")
    ap.add_argument("--import-backward", metavar="GLOB", help="with --import: backward flows, for masks")
    ap.add_argument("--quiet", action="store_true", help="no progress output")
    ap.add_argument("--list-methods", action="store_true", help="print methods and parameter defaults, then exit")
    return ap


def _glob_files(pattern: str, what: str) -> list[Path]:
    p = Path(pattern)
    if p.is_dir():
        files = [q for q in p.iterdir() if q.is_file() and q.suffix.lower() in (".flo", ".npy")]
    else:
        files = [Path(q) for q in globlib.glob(pattern) if Path(q).is_file()]
    if not files:
        raise FileNotFoundError(f"{what} {pattern!r}: no .flo/.npy files match")
    return sorted(files, key=natural_key)


def _run_cli(args) -> int:
    if args.list_methods:
        print(_methods_help())
        return 0
    if args.out is None:
        raise ValueError("--out DIR is required")
    background = 255 if args.background == "white" else 0
    progress = None if args.quiet else sys.stderr
    frames = times = None
    if args.data is not None:
        frames, times = frames_from_transforms(args.data, args.split)
    elif args.images is not None:
        frames = list_frames(args.images)
    if args.import_flow is not None:
        if args.param or args.backward or args.cache:
            raise ValueError("--import takes no --param, --backward or --cache (use --import-backward for masks)")
        fws = _glob_files(args.import_flow, "--import")
        bws = _glob_files(args.import_backward, "--import-backward") if args.import_backward else None
        manifest = import_sequence(fws, args.out, frames=frames, backward_files=bws, fmt=args.format, times=times,
                                   fb_alpha=args.fb_alpha, fb_beta=args.fb_beta, background=background,
                                   progress=progress)
    else:
        if args.import_backward:
            raise ValueError("--import-backward needs --import")
        if frames is None:
            raise ValueError("give the frames with --images DIR_OR_GLOB or --data SCENE_DIR")
        params = _parse_param_args(args.param)
        manifest = estimate_sequence(frames, args.out, method=args.method, params=params, backward=args.backward,
                                     cache_dir=args.cache, fmt=args.format, times=times, fb_alpha=args.fb_alpha,
                                     fb_beta=args.fb_beta, background=background, progress=progress)
    print(f"wrote {len(manifest['pairs'])} flow pair(s) to {args.out} (manifest: flows.json)")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``fgjax flow``: parse `argv`, run, and return the exit status (2 on bad input, no traceback)."""
    args = _build_parser().parse_args(argv)
    try:
        return _run_cli(args)
    except (ValueError, FileNotFoundError, NotADirectoryError, PermissionError) as e:
        print(f"fgjax flow: error: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:  # a backend failed on valid input
        print(f"fgjax flow: failed: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
