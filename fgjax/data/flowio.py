"""Flow and frame files: Middlebury ``.flo`` and ``.npy`` flow I/O, RGB(A) frame reading, frame listing
(a folder, a glob, or a transforms json ordered by time). Flow is float32 [H, W, 2] (dx, dy) in pixels."""

from __future__ import annotations

import glob as globlib
import json
import math
import os
import re
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from fgjax.io import atomic_write

__all__ = [
    "FLO_MAGIC",
    "FLO_UNKNOWN",
    "IMAGE_SUFFIXES",
    "flow_valid_mask",
    "frames_from_transforms",
    "list_frames",
    "load_flow",
    "natural_key",
    "read_flo",
    "read_image",
    "save_flow",
    "write_flo",
]

if TYPE_CHECKING:  # annotations only: jaxtyping costs ~0.5 s to import and the CLI should start fast
    from jaxtyping import Bool, Float, Float32, UInt8

FLO_MAGIC = b"PIEH"  # float32 202021.25 in little-endian, the Middlebury tag
FLO_UNKNOWN = 1e9  # |value| above this marks unknown flow in .flo ground truth
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")


# --------------------------------------------------------------------------------------------------
# Files: .flo, .npy, images
# --------------------------------------------------------------------------------------------------


def read_flo(path: str | os.PathLike) -> Float32[np.ndarray, "H W 2"]:
    """Read a Middlebury .flo file ('PIEH', int32 width, int32 height, float32 (u, v) row-major).

    Values are returned exactly as stored; unknown flow (|value| > 1e9) is kept as is (see
    `flow_valid_mask`).

    Raises:
        FileNotFoundError: no such file.
        ValueError: bad magic, implausible size, or a body of the wrong length (names the file).
    """
    path = Path(path)
    data = path.read_bytes()
    if len(data) < 12:
        raise ValueError(f"{path}: too short for a .flo header ({len(data)} bytes; need 12)")
    if data[:4] != FLO_MAGIC:
        raise ValueError(f"{path}: bad .flo magic {data[:4]!r} (expected {FLO_MAGIC!r})")
    w, h = (int(v) for v in np.frombuffer(data, "<i4", 2, 4))
    if not (0 < w < 1 << 16 and 0 < h < 1 << 16):
        raise ValueError(f"{path}: implausible .flo size width={w} height={h}")
    need = 12 + 8 * w * h
    if len(data) != need:
        raise ValueError(f"{path}: .flo header says {w}x{h} ({need} bytes) but the file has {len(data)} bytes")
    return np.frombuffer(data, "<f4", 2 * w * h, 12).reshape(h, w, 2).astype(np.float32)


def _check_flow_array(flow, where: str) -> np.ndarray:
    if not isinstance(flow, np.ndarray):
        raise ValueError(f"{where}: flow must be a numpy array, got {type(flow).__name__}")
    if flow.ndim != 3 or flow.shape[2] != 2 or flow.shape[0] < 1 or flow.shape[1] < 1:
        raise ValueError(f"{where}: flow has shape {flow.shape}; expected [H, W, 2]")
    if not np.issubdtype(flow.dtype, np.floating):
        raise ValueError(f"{where}: flow has dtype {flow.dtype}; expected a float type")
    return flow


def write_flo(path: str | os.PathLike, flow: Float[np.ndarray, "H W 2"]) -> None:
    """Write `flow` as a Middlebury .flo file, atomically. Nothing is written when `flow` is invalid."""
    path = Path(path)
    flow = _check_flow_array(flow, str(path))
    h, w = flow.shape[:2]
    body = np.ascontiguousarray(flow, dtype="<f4").tobytes()
    header = FLO_MAGIC + np.array([w, h], "<i4").tobytes()
    atomic_write(path, lambda f: f.write(header + body))


def save_flow(path: str | os.PathLike, flow: Float[np.ndarray, "H W 2"]) -> None:
    """Write `flow` to `path` (.npy float32 or .flo by suffix), atomically."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".flo":
        return write_flo(path, flow)
    if suffix != ".npy":
        raise ValueError(f"{path}: flow files must end in .npy or .flo")
    arr = np.ascontiguousarray(_check_flow_array(flow, str(path)), dtype=np.float32)
    atomic_write(path, lambda f: np.save(f, arr))


def flow_valid_mask(flow: Float[np.ndarray, "H W 2"]) -> Bool[np.ndarray, "H W"]:
    """Pixels with known flow: finite and |u|, |v| <= 1e9 (the .flo 'unknown' convention)."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(flow).all(-1) & (np.abs(flow) <= FLO_UNKNOWN).all(-1)


def load_flow(path: str | os.PathLike, *, shape: tuple[int, int] | None = None) -> Float32[np.ndarray, "H W 2"]:
    """Import a precomputed flow (from RAFT or any estimator) from .flo or .npy.

    Accepts ``[H, W, 2]``, or ``[2, H, W]`` (PyTorch layout; transposed here), in any float dtype.
    Unknown values (|value| > 1e9, the .flo convention) and non-finite ones become NaN.

    Args:
        path: a .flo or .npy file.
        shape: expected (H, W), e.g. of the images the flow belongs to.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unsupported suffix, pickled or non-float data, wrong shape (names the file).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".flo":
        flow = read_flo(path)
    elif suffix == ".npy":
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file")
        with open(path, "rb") as fh:  # our handle, closed even when numpy gives up half-way
            try:
                flow = np.load(fh, allow_pickle=False)
            except (ValueError, EOFError, OSError, zipfile.BadZipFile) as e:
                raise ValueError(f"{path}: not a plain .npy array ({e})") from None
            if not isinstance(flow, np.ndarray):
                flow.close()
                raise ValueError(f"{path}: holds an .npz archive, not a .npy array")
        if flow.ndim == 3 and flow.shape[0] == 2 and flow.shape[2] != 2:
            flow = flow.transpose(1, 2, 0)  # [2, H, W] -> [H, W, 2]
    else:
        raise ValueError(f"{path}: cannot import flow from {suffix or 'a file without suffix'!r}; use .flo or .npy")
    _check_flow_array(flow, str(path))
    if shape is not None and flow.shape[:2] != tuple(shape):
        raise ValueError(f"{path}: flow has shape {flow.shape[:2]} (H, W) but the images are {tuple(shape)}")
    flow = flow.astype(np.float32)
    flow[~flow_valid_mask(flow)] = np.nan
    return flow


def read_image(path: str | os.PathLike, *, background: int = 255) -> UInt8[np.ndarray, "H W 3"]:
    """Read an image file as uint8 RGB ``[H, W, 3]``.

    Grey images are replicated to RGB; 16-bit images are scaled to 8 bits; RGBA images are
    composited over a grey level `background` (255 = white, as D-NeRF's white background).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such image file")
    im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if im is None:
        raise ValueError(f"{path}: cannot decode image (not an image, or truncated)")
    if im.dtype == np.uint16:
        im = (im // 257).astype(np.uint8)
    elif im.dtype != np.uint8:
        raise ValueError(f"{path}: unsupported pixel type {im.dtype}; expected 8- or 16-bit")
    if im.ndim == 2:
        return cv2.cvtColor(im, cv2.COLOR_GRAY2RGB)
    if im.shape[2] == 4:
        rgb = cv2.cvtColor(im, cv2.COLOR_BGRA2RGBA).astype(np.float32)
        a = rgb[..., 3:] / 255.0
        return np.round(rgb[..., :3] * a + background * (1.0 - a)).astype(np.uint8)
    if im.shape[2] == 3:
        return cv2.cvtColor(im, cv2.COLOR_BGR2RGB)
    raise ValueError(f"{path}: unsupported channel count {im.shape[2]}")


# --------------------------------------------------------------------------------------------------
# Sequences
# --------------------------------------------------------------------------------------------------


def natural_key(p: Path):
    """Sort key of a file name with its digit runs compared as numbers (frame_2 before frame_10)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def list_frames(images: str | os.PathLike) -> list[Path]:
    """Image files of a folder or a glob pattern, sorted by file name (digit runs compared as
    numbers, so frame_2 < frame_10)."""
    s = str(images)
    p = Path(s)
    if p.is_dir():
        files = [q for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_SUFFIXES]
        where = f"folder {p}"
    elif globlib.has_magic(s):
        files = [Path(q) for q in globlib.glob(s) if Path(q).is_file()]
        where = f"pattern {s!r}"
    elif p.exists():
        raise ValueError(f"--images {p}: expected a folder or a glob pattern, not a single file")
    else:
        raise FileNotFoundError(f"--images {p}: no such folder")
    if not files:
        raise ValueError(f"{where} holds no image files ({', '.join(IMAGE_SUFFIXES)})")
    return sorted(files, key=natural_key)


def frames_from_transforms(scene_dir: str | os.PathLike, split: str = "train") -> tuple[list[Path], list[float]]:
    """Frames of a nerfstudio / D-NeRF scene ordered by time: reads ``transforms_{split}.json``.

    ``frames[*].file_path`` is relative to `scene_dir` and may lack the extension (D-NeRF writes
    './train/r_000'); ``frames[*].time`` orders them (ties keep file order).

    Returns:
        (paths, times), both in time order.

    Raises:
        FileNotFoundError: no transforms file, or a frame's image is missing (names the frame index).
        ValueError: malformed JSON or a missing/wrong field (names the file and the field).
    """
    scene = Path(scene_dir)
    tf = scene / f"transforms_{split}.json"
    if not tf.is_file():
        raise FileNotFoundError(f"{tf}: no such file (expected a nerfstudio/D-NeRF scene folder)")
    try:
        meta = json.loads(tf.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{tf}: not valid JSON ({e})") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{tf}: field 'frames' is missing or empty")
    items = []
    for k, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise ValueError(f"{tf}: frames[{k}] is not an object")
        fp = fr.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise ValueError(f"{tf}: frames[{k}].file_path is missing or not a string")
        t = fr.get("time")
        if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
            raise ValueError(f"{tf}: frames[{k}].time is missing or not a number (got {t!r})")
        path = scene / fp
        if not path.is_file():
            cands = [path.with_name(path.name + s) for s in (".png", ".jpg", ".jpeg", ".PNG", ".JPG")]
            found = [c for c in cands if c.is_file()]
            if not found:
                raise FileNotFoundError(f"{tf}: frames[{k}].file_path {fp!r}: no such image (tried {path} and "
                                        f"{', '.join(c.suffix for c in cands)})")
            path = found[0]
        items.append((float(t), k, path))
    items.sort(key=lambda it: (it[0], it[1]))
    return [it[2] for it in items], [it[0] for it in items]
