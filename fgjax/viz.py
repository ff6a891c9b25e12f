"""Pictures of arrays: images to uint8, depth and per-pixel object ids to colour (numpy only)."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["to_u8", "upscale", "pad16", "ids_to_color", "depth_to_color", "caption", "overlay_ids", "grid"]


def to_u8(img: np.ndarray) -> np.ndarray:
    """Image in [0, 1] (float, any shape) -> uint8, rounded to nearest, clipped."""
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def upscale(img: np.ndarray, s: int) -> np.ndarray:
    """[H, W, ...] -> [s H, s W, ...] by pixel repetition (s <= 1: unchanged)."""
    return np.repeat(np.repeat(img, s, axis=0), s, axis=1) if s > 1 else img


def pad16(img: np.ndarray) -> np.ndarray:
    """Pad [H, W, C] to multiples of 16 pixels (ffmpeg's macro-block size) with black."""
    h, w = img.shape[:2]
    return np.pad(img, ((0, -h % 16), (0, -w % 16), (0, 0)))


_ID_COLORS = np.array(
    [[70, 70, 70], [230, 60, 50], [50, 140, 230], [240, 200, 40], [160, 80, 220], [60, 200, 110], [240, 130, 190]],
    dtype=np.uint8,
)


def depth_to_color(depth: np.ndarray, valid: np.ndarray | None = None, *, near: float | None = None,
                   far: float | None = None) -> np.ndarray:
    """[H, W] depth -> [H, W, 3] uint8 RGB (turbo colour map of inverse depth; invalid black)."""
    depth = np.asarray(depth, dtype=np.float64)
    ok = depth > 0 if valid is None else (np.asarray(valid, bool) & (depth > 0))
    if not np.any(ok):
        return np.zeros((*depth.shape, 3), np.uint8)
    near = float(depth[ok].min()) if near is None else near
    far = float(depth[ok].max()) if far is None else far
    inv = np.where(ok, 1.0 / np.where(ok, depth, 1.0), 0.0)
    lo, hi = 1.0 / far, 1.0 / near
    x = np.clip((inv - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    bgr = cv2.applyColorMap(np.round(x * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    rgb = bgr[..., ::-1]
    return np.where(ok[..., None], rgb, 0).astype(np.uint8)


def ids_to_color(ids: np.ndarray) -> np.ndarray:
    """[H, W] object ids (-1 invalid, 0 static, k object) -> [H, W, 3] uint8 RGB."""
    ids = np.asarray(ids)
    out = _ID_COLORS[np.clip(ids, 0, None) % len(_ID_COLORS)]
    return np.where((ids < 0)[..., None], 0, out).astype(np.uint8)


def caption(img: np.ndarray, text: str) -> np.ndarray:
    """[16 + H, W, 3] uint8: a white strip with ``text`` above ``img`` [H, W, 3] uint8 (same width)."""
    strip = np.full((16, img.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([strip, img], axis=0)


def overlay_ids(img: np.ndarray, ids: np.ndarray, weight: float = 0.55) -> np.ndarray:
    """[H, W, 3] uint8: ``img`` (uint8) with the pixels of objects (``ids`` [H, W] >= 1) tinted by their colour
    (`ids_to_color`, blended with ``weight``) and outlined; static pixels unchanged."""
    img = np.asarray(img, np.uint8)
    on = np.asarray(ids) >= 1
    col = ids_to_color(ids).astype(np.float64)
    out = np.where(on[..., None], (1 - weight) * img + weight * col, img).astype(np.uint8)
    edge = on & (cv2.dilate(on.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
                 & ~cv2.erode(on.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool))
    return np.where(edge[..., None], ids_to_color(ids), out).astype(np.uint8)


def grid(rows: list[list[np.ndarray]], pad: int = 2) -> np.ndarray:
    """Tiles (uint8 [h, w, 3], any sizes) laid out in rows, each padded white by ``pad`` and the rows' ends
    padded to one width."""
    made = []
    for row in rows:
        h = max(t.shape[0] for t in row)
        tiles = [np.pad(t, ((pad, pad + h - t.shape[0]), (pad, pad), (0, 0)), constant_values=255) for t in row]
        made.append(np.concatenate(tiles, axis=1))
    w = max(r.shape[1] for r in made)
    return np.concatenate([np.pad(r, ((0, 0), (0, w - r.shape[1]), (0, 0)), constant_values=255) for r in made])
