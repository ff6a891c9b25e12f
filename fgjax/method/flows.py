"""The optical flow that stage 1's flow losses train with (DESIGN.md section 1, step 4): consecutive frames' flow in
time order for L_uGS (``flow.loss = "pair"``), and the first frame's tracks chained through it for the track loss
(``flow.loss = "track"``, `fgjax.flow.track`). Flow is estimated with OpenCV and cached on disk
(`fgjax.data.opticalflow`)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fgjax.data.opticalflow import chained_tracks, estimate_flow, forward_backward_mask

__all__ = ["previous_frames", "estimate_training_flows", "training_tracks"]


def previous_frames(times: np.ndarray, span: int = 1) -> np.ndarray:
    """Index of the frame ``span`` frames earlier in time order for each frame (-1 for the first ``span``)."""
    if span < 1:
        raise ValueError(f"previous_frames: span must be >= 1; got {span}")
    order = np.argsort(np.asarray(times), kind="stable")
    prev = np.full(len(order), -1, np.int64)
    prev[order[span:]] = order[:max(len(order) - span, 0)]
    return prev


def estimate_training_flows(scene, method: str = "dis_deepflow", cache_dir: str | Path | None = None,
                            log=print, backward: bool = False, span: int = 1) -> np.ndarray:
    """Observed optical flow into each training frame from its predecessor in time, on the predecessor's
    grid: [T, H, W, 2] float32, NaN for the first frame (``fgjax.data.opticalflow.estimate_flow``, cached
    on disk under `cache_dir`). ``backward``: the reverse, from each frame to its predecessor on the frame's
    own grid (the round trip of ``pose.bundle_fb_px``). ``span``: the predecessor ``span`` frames earlier
    (`previous_frames`; NaN for the first ``span`` frames)."""
    prev = previous_frames(scene.times, span)
    imgs = (np.clip(np.asarray(scene.images), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    out = np.full((scene.num_frames, scene.height, scene.width, 2), np.nan, np.float32)
    t0 = time.time()
    for i, j in enumerate(prev):
        if j >= 0:
            a, b = (i, j) if backward else (j, i)  # the flow from frame a to frame b, on a's grid
            out[i] = estimate_flow(imgs[a], imgs[b], method, cache_dir=cache_dir)
    log(f"optical flow ({method}{', backward' if backward else ''}{f', span {span}' if span > 1 else ''}): "
        f"{int(np.sum(prev >= 0))} pairs in {time.time() - t0:.1f} s")
    return out


def training_tracks(scene, method: str = "dis_deepflow", cache_dir: str | Path | None = None,
                    log=print) -> tuple[np.ndarray, np.ndarray]:
    """(reference [T] int: the first frame in time for every other frame, -1 for itself; tracks [T, H, W, 2]: the
    displacement of each pixel of the first frame into each frame, on the first frame's grid, NaN where lost) for
    ``flow.loss = "track"``: the optical flow between consecutive frames (both directions, cached under
    `cache_dir`) chained from the first frame (`fgjax.data.opticalflow.chained_tracks`), a track stopping where the
    forward flow fails the round trip through the backward flow (`fgjax.data.opticalflow.forward_backward_mask`,
    Sundaram et al. 2010) or leaves the image."""
    fw = estimate_training_flows(scene, method, cache_dir=cache_dir, log=log)
    bw = estimate_training_flows(scene, method, cache_dir=cache_dir, log=log, backward=True)
    order = np.argsort(np.asarray(scene.times), kind="stable")
    seq = [fw[i] for i in order[1:]]  # frame order[k] -> order[k+1] on order[k]'s grid
    ok = [forward_backward_mask(fw[i], bw[i]) for i in order[1:]]
    tracks = np.full_like(fw, np.nan)
    if len(seq):
        tracks[order] = chained_tracks(np.stack(seq), np.stack(ok))
    else:
        tracks[order] = 0.0
    ref = np.full(scene.num_frames, int(order[0]), np.int64)
    ref[order[0]] = -1
    last = tracks[order[-1]]
    log(f"flow tracks from frame {int(order[0])}: {float(np.mean(np.isfinite(last[..., 0]))):.0%} of its pixels "
        f"tracked to the last frame")
    return ref, tracks
