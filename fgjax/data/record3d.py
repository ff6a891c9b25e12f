"""A Record3D export (iPhone/iPad with LiDAR), read as it is, for `fgjax prepare --record3d`.

Layout of the export folder:

- ``metadata`` (JSON; also read as ``metadata.json``): ``w``, ``h`` (RGB size), ``K`` (9 numbers, the 3x3
  intrinsics stored column-major: K = reshape(K, 3, 3).T, at the RGB size), ``poses`` (one
  [qx, qy, qz, qw, tx, ty, tz] per frame: camera-to-world rotation as an xyzw quaternion and the camera centre in
  metres, in ARKit's camera axes x right, y up, z back, the OpenGL convention), ``fps``; optionally ``dw``, ``dh``
  (depth map size).
- ``rgbd/<i>.jpg``: frame i's RGB.
- ``rgbd/<i>.depth`` (optional): LiDAR z-depth in metres, lzfse-compressed float32, ``dh`` x ``dw`` (when the
  metadata does not give the size, the one with the RGB's aspect ratio and that many values); ``rgbd/<i>.conf``
  (optional): ARKit's confidence, lzfse-compressed uint8 at the same size (0 low, 1 medium, 2 high).
  Decompressing needs the optional ``lzfse`` package (``pip install 'fgjax[video]'``; binary wheels of the LZFSE
  reference decoder); ``pyliblzfse`` (the same decoder, built from source) is used where it is installed instead.

OpenCV camera-to-world = [R(q) | t] @ diag(1, -1, -1, 1) (`fgjax.geometry.opengl_to_opencv_c2w`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from fgjax.geometry import opengl_to_opencv_c2w

try:  # optional: fgjax[video]
    import lzfse as _lzfse
except ImportError:  # pragma: no cover - depends on the environment
    try:
        import liblzfse as _lzfse  # pyliblzfse: the same reference decoder, an sdist only
    except ImportError:
        _lzfse = None

__all__ = ["Record3DCapture", "LZFSE_MISSING", "read_record3d", "record3d_K", "record3d_c2w", "decode_depth"]

LZFSE_MISSING = "lzfse is not installed, so the LiDAR depth is skipped (pip install 'fgjax[video]')"
REQUIRED = ("w", "h", "K", "poses")


@dataclasses.dataclass(frozen=True)
class Record3DCapture:
    """Frames of a Record3D export, resized.

    Attributes:
        images: [T, H, W, 3] uint8 RGB.
        K: [3, 3] intrinsics at (W, H).
        c2w: [T, 4, 4] OpenCV camera-to-world, metres.
        indices: [T] frame numbers of the export.
        fps: frames per second (0 when the metadata does not say).
        depths: [T, H, W] float32 z-depth in metres (0 = unknown or low confidence), or None.
        depth_note: how the depth was read, or why it was not.
    """

    images: np.ndarray
    K: np.ndarray
    c2w: np.ndarray
    indices: np.ndarray
    fps: float
    depths: np.ndarray | None
    depth_note: str


def record3d_K(values: Any, src: Path) -> np.ndarray:
    """The 3x3 K of the metadata's column-major ``K`` (9 numbers); ValueError naming ``src`` otherwise."""
    try:
        k = np.asarray(values, np.float64).reshape(3, 3).T
    except (TypeError, ValueError):
        raise ValueError(f"{src}: field `K` must be 9 numbers (a column-major 3x3), got {values!r}") from None
    if not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0 or np.any(k[2] != [0, 0, 1]):
        raise ValueError(f"{src}: field `K` is not a pinhole intrinsic matrix (column-major): {k.tolist()}")
    return k


def record3d_c2w(pose: Any, src: Path, i: int) -> np.ndarray:
    """OpenCV camera-to-world [4, 4] of one ``poses`` entry [qx, qy, qz, qw, tx, ty, tz] (ARKit axes)."""
    p = np.asarray(pose, np.float64)
    if p.shape != (7,) or not np.all(np.isfinite(p)) or np.linalg.norm(p[:4]) < 1e-6:
        raise ValueError(f"{src}: field `poses`[{i}] must be 7 finite numbers [qx, qy, qz, qw, tx, ty, tz] with a "
                         f"non-zero quaternion, got {pose!r}")
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(p[:4] / np.linalg.norm(p[:4])).as_matrix()  # scipy: xyzw
    m[:3, 3] = p[4:]
    return opengl_to_opencv_c2w(m)


def decode_depth(path: Path, dtype, shape: tuple[int, int] | None, aspect: float) -> np.ndarray:
    """An lzfse-compressed map (``dtype`` values) as [dh, dw]; without ``shape``, the size with ``aspect`` = W / H
    that holds that many values. ValueError naming the file when it does not decode or does not fit."""
    data = path.read_bytes()
    try:
        raw = np.frombuffer(_lzfse.decompress(data), dtype)
    except Exception as e:  # the decoder raises its own error type
        raise ValueError(f"{path}: not an lzfse-compressed map ({e})") from e
    if shape is None:
        dw = round(math.sqrt(raw.size * aspect))
        shape = (raw.size // max(dw, 1), dw)
    if raw.size != shape[0] * shape[1]:
        raise ValueError(f"{path}: holds {raw.size} values, not {shape[0]} x {shape[1]}")
    return raw.reshape(shape)


def _read_metadata(folder: Path) -> tuple[Path, dict]:
    for name in ("metadata", "metadata.json"):
        src = folder / name
        if src.is_file():
            break
    else:
        raise FileNotFoundError(f"{folder / 'metadata'}: no Record3D metadata file (metadata or metadata.json)")
    try:
        meta = json.loads(src.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{src}: cannot parse as JSON ({e})") from e
    if not isinstance(meta, dict):
        raise ValueError(f"{src}: expected a JSON object")
    for key in REQUIRED:
        if key not in meta:
            raise ValueError(f"{src}: field `{key}` is missing (a Record3D export has {', '.join(REQUIRED)})")
    for key in ("w", "h"):
        if isinstance(meta[key], bool) or not isinstance(meta[key], int) or meta[key] < 1:
            raise ValueError(f"{src}: field `{key}` must be a positive integer, got {meta[key]!r}")
    if not isinstance(meta["poses"], list) or not meta["poses"]:
        raise ValueError(f"{src}: field `poses` must be a non-empty list")
    return src, meta


def read_record3d(folder: str | os.PathLike, *, max_side: int = 320, stride: int = 1, first: int = 0,
                  last: int | None = None, depth: bool = True, min_confidence: int = 2,
                  log: Callable[[str], None] = print) -> Record3DCapture:
    """Frames ``first, first + stride, ... < last`` of the Record3D export in ``folder``, resized so the longer side
    is at most ``max_side`` (area averaging; K scaled by the exact size ratios), with LiDAR depth where the export has
    it and ``depth`` is set (nearest-neighbour resized to the frame size; pixels whose ARKit confidence is below
    ``min_confidence`` are 0 = unknown, when the export has ``.conf`` files).

    Raises:
        FileNotFoundError: no folder, no metadata, a listed frame's jpg missing (naming it).
        ValueError: a missing or malformed metadata field, an unreadable image or depth file (naming it).
    """
    root = Path(folder)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such Record3D export folder")
    src, meta = _read_metadata(root)
    w, h = int(meta["w"]), int(meta["h"])
    k_full = record3d_K(meta["K"], src)
    n = len(meta["poses"])
    stop = n if last is None else min(last, n)
    idx = list(range(first, stop, stride))
    if not idx:
        raise ValueError(f"{src}: no frame in the range {first}:{'' if last is None else last} "
                         f"(the export has {n} poses)")
    shape = None
    if "dw" in meta or "dh" in meta:
        if not all(isinstance(meta.get(k), int) and meta[k] > 0 for k in ("dw", "dh")):
            raise ValueError(f"{src}: fields `dw` and `dh` must both be positive integers")
        shape = (int(meta["dh"]), int(meta["dw"]))
    rgbd = root / "rgbd"
    has_depth = (rgbd / f"{idx[0]}.depth").is_file()
    note = "none in the export"
    if has_depth and not depth:
        has_depth, note = False, "not read (--no-depth)"
    elif has_depth and _lzfse is None:
        log(f"record3d: {LZFSE_MISSING}")
        has_depth, note = False, "skipped: lzfse is not installed"
    s = min(1.0, max_side / max(w, h))
    w2, h2 = max(1, round(w * s)), max(1, round(h * s))
    K = np.diag([w2 / w, h2 / h, 1.0]) @ k_full
    images, c2w, depths = [], [], []
    for i in idx:
        c2w.append(record3d_c2w(meta["poses"][i], src, i))
        p = rgbd / f"{i}.jpg"
        if not p.is_file():
            raise FileNotFoundError(f"{p}: frame {i} of {src} has no image")
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{p}: not a readable image")
        if bgr.shape[:2] != (h, w):
            raise ValueError(f"{p}: image is {bgr.shape[1]}x{bgr.shape[0]} but {src} says w={w}, h={h}")
        if (w2, h2) != (w, h):
            bgr = cv2.resize(bgr, (w2, h2), interpolation=cv2.INTER_AREA)
        images.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        if has_depth:
            dp = rgbd / f"{i}.depth"
            if not dp.is_file():
                raise FileNotFoundError(f"{dp}: frame {i} has no depth while frame {idx[0]} has one")
            d = decode_depth(dp, np.float32, shape, w / h).astype(np.float32)
            raw_size = (d.shape[1], d.shape[0])
            conf = rgbd / f"{i}.conf"
            if conf.is_file():
                c = decode_depth(conf, np.uint8, d.shape, w / h)
                d = np.where(c >= min_confidence, d, 0.0).astype(np.float32)
            d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
            depths.append(cv2.resize(d, (w2, h2), interpolation=cv2.INTER_NEAREST))
    if has_depth:
        note = (f"LiDAR {raw_size[0]}x{raw_size[1]} resized (nearest) to {w2}x{h2}, metres; pixels with ARKit "
                f"confidence < {min_confidence} set to 0 (unknown)")
    fps = float(meta.get("fps") or 0.0) if isinstance(meta.get("fps"), int | float) else 0.0
    return Record3DCapture(np.stack(images), K, np.stack(c2w), np.asarray(idx, np.int64), fps,
                           np.stack(depths) if has_depth else None, note)
