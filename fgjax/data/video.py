"""Frames of a video file (OpenCV), downsized and selected for `fgjax prepare --video`.

`read_video` decodes with ``cv2.VideoCapture`` and keeps the frames ``A <= i < B`` (source frame numbers, 0-based)
whose offset from ``A`` is a multiple of ``stride``; each kept frame is resized with area averaging so that its longer
side is at most ``max_side`` pixels (never enlarged). Decoding stops at the first frame the decoder cannot return
(some phone clips announce more frames in their header than they hold); the frames before it are kept.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import cv2
import numpy as np

__all__ = ["VideoFrames", "parse_frame_range", "read_video", "resized_shape"]


@dataclasses.dataclass(frozen=True)
class VideoFrames:
    """Decoded frames of one clip.

    Attributes:
        images: [T, H, W, 3] uint8 RGB.
        indices: [T] source frame numbers (0-based).
        fps: frames per second from the container (0 when it does not say).
        source_size: (W, H) of the decoded frames before resizing.
        decoded: number of frames the decoder returned up to the last one kept or read.
        announced: frame count in the container's header (0 when unknown).
    """

    images: np.ndarray
    indices: np.ndarray
    fps: float
    source_size: tuple[int, int]
    decoded: int
    announced: int


def parse_frame_range(text: str | None) -> tuple[int, int | None]:
    """``"A:B"`` -> (A, B) with B None for ``"A:"``; None or ``""`` -> (0, None). Raises ValueError naming the
    option for anything else (negative numbers, B <= A, not integers)."""
    if text is None or text == "":
        return 0, None
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        a = int(parts[0]) if parts[0].strip() else 0
        b = int(parts[1]) if parts[1].strip() else None
    except ValueError:
        raise ValueError(f"--frames {text!r}: expected A:B (source frame numbers, B excluded), e.g. 0:120") from None
    if a < 0 or (b is not None and b <= a):
        raise ValueError(f"--frames {text!r}: need 0 <= A < B")
    return a, b


def resized_shape(width: int, height: int, max_side: int) -> tuple[int, int]:
    """(W', H') with the longer side at most ``max_side`` and the aspect kept (rounded; never enlarged)."""
    s = min(1.0, max_side / max(width, height))
    return max(1, round(width * s)), max(1, round(height * s))


def read_video(path: str | os.PathLike, *, max_side: int = 320, stride: int = 1, first: int = 0,
               last: int | None = None) -> VideoFrames:
    """Decode the frames ``first, first + stride, ...`` (< ``last``) of the video at ``path``, resized to at most
    ``max_side`` pixels on the longer side, as RGB uint8.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a video OpenCV can decode, holds no frame, or holds no frame in the range;
            the message names the file.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such video file")
    if max_side < 16:
        raise ValueError(f"--max-side must be >= 16, got {max_side}")
    if stride < 1:
        raise ValueError(f"--stride must be >= 1, got {stride}")
    cap = cv2.VideoCapture(str(p))
    try:
        if not cap.isOpened():
            raise ValueError(f"{p}: not a video OpenCV can open (empty, corrupt or an unknown format)")
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        announced = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        frames, idx = [], []
        i, size = 0, None
        while last is None or i < last:
            ok = cap.grab() if i < first or (i - first) % stride else None
            if ok is None:  # a frame to keep: decode it
                ok, bgr = cap.read()
                if ok and bgr is not None:
                    h, w = bgr.shape[:2]
                    size = size or (w, h)
                    w2, h2 = resized_shape(w, h, max_side)
                    if (w2, h2) != (w, h):
                        bgr = cv2.resize(bgr, (w2, h2), interpolation=cv2.INTER_AREA)
                    frames.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
                    idx.append(i)
            if not ok:
                break
            i += 1
    finally:
        cap.release()
    if not frames:
        if i == 0:
            raise ValueError(f"{p}: the video holds no decodable frame")
        raise ValueError(f"{p}: no frame in the range {first}:{'' if last is None else last} "
                         f"(the decoder returned {i} frames)")
    return VideoFrames(np.stack(frames), np.asarray(idx, np.int64), fps, size, i, announced)
