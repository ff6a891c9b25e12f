"""Optical flow over a frame sequence: `estimate_sequence` (OpenCV, cached) and `import_sequence`
(precomputed .flo/.npy), written atomically with a ``flows.json`` manifest and forward-backward masks."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import cv2
import numpy as np

from fgjax.data.flowio import load_flow, read_image, save_flow
from fgjax.data.flowmethods import DEFAULT_METHOD, resolve_params
from fgjax.data.opticalflow import estimate_flow_cached, forward_backward_mask
from fgjax.io import atomic_write

__all__ = [
    "estimate_sequence",
    "import_sequence",
]



def _fmt_seconds(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


_OUTPUT_NAME = re.compile(r"^(flow_\d{5}\.(npy|flo)|flow_bw_\d{5}\.(npy|flo)|fbmask_\d{5}\.png)$")


class _Staging:
    """Output folder whose files appear only on success: files are written to a hidden staging
    folder inside it and moved into place at the end; on failure the staging folder (and any
    folder this created) is removed, so nothing is left behind. On success, outputs of an earlier
    run that this run did not produce (same naming scheme) are removed, so that the folder matches
    its manifest."""

    def __init__(self, out_dir: Path):
        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise ValueError(f"--out {self.out_dir}: exists and is not a folder")
        self.created: list[Path] = []
        for d in reversed([self.out_dir, *self.out_dir.parents]):
            if not d.exists():
                d.mkdir()
                self.created.append(d)
        self.tmp = Path(tempfile.mkdtemp(dir=self.out_dir, prefix=".fgjax-flow-staging-"))
        self.names: list[str] = []

    def path(self, name: str) -> Path:
        self.names.append(name)
        return self.tmp / name

    def commit(self) -> None:
        for name in self.names:
            os.replace(self.tmp / name, self.out_dir / name)
        self.tmp.rmdir()
        keep = set(self.names)
        for q in self.out_dir.iterdir():
            if q.name not in keep and _OUTPUT_NAME.match(q.name) and q.is_file():
                q.unlink()

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)
        for d in reversed(self.created):
            try:
                d.rmdir()
            except OSError:
                break


def _save_mask(path: Path, mask: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255)
    if not ok:
        raise RuntimeError(f"{path}: PNG encoding failed")
    atomic_write(path, lambda f: f.write(buf.tobytes()))


def _check_frames(frames: Sequence[Path], background: int) -> tuple[int, int]:
    if len(frames) < 2:
        raise ValueError(f"need at least 2 frames for optical flow, got {len(frames)}")
    shape = first = None
    for p in frames:
        im = read_image(p, background=background)
        if shape is None:
            shape, first = im.shape, p
        elif im.shape != shape:
            raise ValueError(f"{p}: image is {im.shape[1]}x{im.shape[0]} but {first} is {shape[1]}x{shape[0]}; "
                             "all frames must have the same size")
    if min(shape[:2]) < 16:
        raise ValueError(f"{frames[0]}: images are {shape[1]}x{shape[0]}; optical flow needs at least 16x16 pixels")
    return shape[:2]


def _check_common(fmt: str, fb_alpha: float, fb_beta: float) -> None:
    if fmt not in ("npy", "flo"):
        raise ValueError(f"--format {fmt!r}: choose 'npy' or 'flo'")
    if not (math.isfinite(fb_alpha) and math.isfinite(fb_beta) and fb_alpha >= 0 and fb_beta >= 0):
        raise ValueError(f"forward-backward thresholds must be finite and >= 0, got alpha={fb_alpha}, beta={fb_beta}")


def _write_sequence(out_dir, n, produce, *, fmt, method, params, shape, backward, fb_alpha, fb_beta, progress) -> dict:
    """Shared writer of `estimate_sequence` / `import_sequence`. produce(k) -> (entry, fw, bw|None,
    note) for pair k; entry already names the frames/sources."""
    if progress is True:
        progress = sys.stderr  # looked up now, not at import (tests and callers may swap it)
    elif progress is False:
        progress = None
    stage = _Staging(Path(out_dir))
    try:
        pairs = []
        t_start = time.perf_counter()
        for k in range(n):
            t0 = time.perf_counter()
            entry, fw, bw, note = produce(k)
            entry = {"index": k, **entry, "forward": f"flow_{k:05d}.{fmt}"}
            save_flow(stage.path(entry["forward"]), fw)
            if bw is not None:
                mask = forward_backward_mask(fw, bw, alpha=fb_alpha, beta=fb_beta)
                entry.update(backward=f"flow_bw_{k:05d}.{fmt}", mask=f"fbmask_{k:05d}.png",
                             consistent_fraction=round(float(mask.mean()), 6))
                save_flow(stage.path(entry["backward"]), bw)
                _save_mask(stage.path(entry["mask"]), mask)
            pairs.append(entry)
            if progress is not None:
                now = time.perf_counter()
                avg = (now - t_start) / (k + 1)
                print(f"[flow] pair {k + 1}/{n} {note}: {now - t0:.2f} s, {avg:.2f} s/pair, "
                      f"ETA {_fmt_seconds(avg * (n - k - 1))}", file=progress, flush=True)
        manifest = {
            "format": 1,
            "convention": "forward flow frame0 -> frame1 on frame0's pixel grid, float32 [H, W, 2] (dx, dy) pixels",
            "method": method,
            "params": params,
            "height": int(shape[0]),
            "width": int(shape[1]),
            "backward": backward,
            "fb_alpha": fb_alpha if backward else None,
            "fb_beta": fb_beta if backward else None,
            "pairs": pairs,
        }
        text = json.dumps(manifest, indent=1).encode()
        atomic_write(stage.path("flows.json"), lambda f: f.write(text))
        stage.commit()
    except BaseException:
        stage.abort()
        raise
    return manifest


def estimate_sequence(
    frames: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    method: str = DEFAULT_METHOD,
    params: Any = None,
    backward: bool = False,
    cache_dir: str | os.PathLike | None = None,
    fmt: str = "npy",
    times: Sequence[float] | None = None,
    fb_alpha: float = 0.01,
    fb_beta: float = 0.5,
    background: int = 255,
    progress: TextIO | bool | None = True,
) -> dict:
    """Flow between consecutive frames, written to `out_dir`.

    Pair k (frames[k] -> frames[k+1]) gives ``flow_{k:05d}.{fmt}``; with `backward` also
    ``flow_bw_{k:05d}.{fmt}`` (frames[k+1] -> frames[k]) and ``fbmask_{k:05d}.png`` (255 where
    `forward_backward_mask` holds), plus ``flows.json``, a manifest of frames, pairs and parameters.
    All inputs are checked before any flow is computed; outputs appear only when every pair
    succeeded (the cache, if any, keeps finished pairs, so a rerun resumes).

    Args:
        frames: image files, in order.
        out_dir: output folder (created if needed).
        method, params: as in `estimate_flow`.
        backward: also compute backward flow and forward-backward masks.
        cache_dir: flow cache folder (see `estimate_flow`).
        fmt: "npy" or "flo".
        times: optional time stamp per frame, recorded in the manifest.
        fb_alpha, fb_beta: `forward_backward_mask` thresholds.
        background: grey level RGBA frames are composited over.
        progress: True (stderr, the default), a stream, or False/None (silent): per-pair lines
            with seconds per pair and ETA.

    Returns:
        The manifest written to ``flows.json``.
    """
    frames = [Path(f) for f in frames]
    _check_common(fmt, fb_alpha, fb_beta)
    if times is not None and len(times) != len(frames):
        raise ValueError(f"got {len(times)} times for {len(frames)} frames")
    p = resolve_params(method, params)
    shape = _check_frames(frames, background)
    images = {}

    def produce(k):
        im0 = images.pop(k, None)
        im0 = read_image(frames[k], background=background) if im0 is None else im0
        im1 = images[k + 1] = read_image(frames[k + 1], background=background)
        fw, hit = estimate_flow_cached(im0, im1, method, p, cache_dir)
        bw = None
        if backward:
            bw, hit_bw = estimate_flow_cached(im1, im0, method, p, cache_dir)
            hit = hit and hit_bw
        entry = {"frame0": str(frames[k]), "frame1": str(frames[k + 1])}
        if times is not None:
            entry.update(time0=float(times[k]), time1=float(times[k + 1]))
        return entry, fw, bw, f"{frames[k].name} -> {frames[k + 1].name}{' (cached)' if hit else ''}"

    return _write_sequence(out_dir, len(frames) - 1, produce, fmt=fmt, method=method, params=dataclasses.asdict(p),
                           shape=shape, backward=backward, fb_alpha=fb_alpha, fb_beta=fb_beta, progress=progress)


def import_sequence(
    flow_files: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    frames: Sequence[str | os.PathLike] | None = None,
    backward_files: Sequence[str | os.PathLike] | None = None,
    fmt: str = "npy",
    times: Sequence[float] | None = None,
    fb_alpha: float = 0.01,
    fb_beta: float = 0.5,
    background: int = 255,
    progress: TextIO | bool | None = True,
) -> dict:
    """Bring precomputed flows (RAFT or any estimator; .flo or .npy, see `load_flow`) into the
    layout of `estimate_sequence`: same file names, manifest and (with `backward_files`)
    forward-backward masks. With `frames`, the counts (pairs = frames - 1) and sizes are checked.
    Every file is validated before anything is written."""
    fws = [Path(f) for f in flow_files]
    bws = None if backward_files is None else [Path(f) for f in backward_files]
    _check_common(fmt, fb_alpha, fb_beta)
    if not fws:
        raise ValueError("no flow files to import")
    if bws is not None and len(bws) != len(fws):
        raise ValueError(f"got {len(bws)} backward flow files for {len(fws)} forward ones")
    shape = None
    if frames is not None:
        frames = [Path(f) for f in frames]
        if len(frames) != len(fws) + 1:
            raise ValueError(f"{len(fws)} flow files need {len(fws) + 1} frames, got {len(frames)}")
        if times is not None and len(times) != len(frames):
            raise ValueError(f"got {len(times)} times for {len(frames)} frames")
        shape = _check_frames(frames, background)
    for f in fws + (bws or []):  # validate every file before writing anything
        shape = load_flow(f, shape=shape).shape[:2]

    def produce(k):
        entry = {"source": str(fws[k])}
        if frames is not None:
            entry.update(frame0=str(frames[k]), frame1=str(frames[k + 1]))
            if times is not None:
                entry.update(time0=float(times[k]), time1=float(times[k + 1]))
        bw = None
        if bws is not None:
            entry["source_backward"] = str(bws[k])
            bw = load_flow(bws[k], shape=shape)
        return entry, load_flow(fws[k], shape=shape), bw, f"imported {fws[k].name}"

    return _write_sequence(out_dir, len(fws), produce, fmt=fmt, method="imported", params={}, shape=shape,
                           backward=bws is not None, fb_alpha=fb_alpha, fb_beta=fb_beta, progress=progress)
