"""Which training frames a stage-1 step draws: uniformly, by their last error, or from a time window that opens
over the steps (a curriculum). Functions of (seed, step, errors) only, so a resumed run draws the same frames."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["batch_indices", "time_window"]


def batch_indices(seed: int, step: int, num_frames: int, batch: int, window: np.ndarray | None = None,
                   frame_err: np.ndarray | None = None, mix: float = 0.0) -> np.ndarray:
    """Frame indices of one step, a function of (seed, step, frame_err) only, so a resumed run draws the
    same ones. With `window` (frame indices) they are drawn from it. With `mix` > 0, that fraction of the
    steps draws frames with probability proportional to their squared last MSE `frame_err` [T] (frames
    not measured yet, NaN, count as the worst measured one); the other steps draw uniformly."""
    rng = np.random.default_rng([seed, step])
    pool = np.arange(num_frames) if window is None else np.asarray(window)
    replace = batch > len(pool)
    if mix > 0 and frame_err is not None and rng.uniform() < mix:
        e = np.asarray(frame_err, np.float64)[pool]
        if np.any(np.isfinite(e)):
            e = np.where(np.isfinite(e), e, np.nanmax(e))
            p = e * e
            if p.sum() > 0 and np.count_nonzero(p) >= (batch if not replace else 1):
                return pool[rng.choice(len(pool), size=batch, replace=replace, p=p / p.sum())]
    return pool[rng.choice(len(pool), size=batch, replace=replace)]


def time_window(step: int, times: np.ndarray, warmup: int, curriculum: int, start_fraction: float) -> np.ndarray:
    """Frames (indices, earliest first) that step `step` may draw under the time curriculum: the earliest
    `start_fraction` of them up to the end of the warm-up, then a window opening linearly to all frames
    over `curriculum` steps."""
    order = np.argsort(np.asarray(times), kind="stable")
    n = len(order)
    if curriculum <= 0:
        return order
    open_ = min(1.0, max(0.0, (step - warmup) / curriculum))
    frac = start_fraction + (1.0 - start_fraction) * open_
    return order[:max(1, min(n, int(math.ceil(frac * n - 1e-9))))]
