"""Synthetic captures for the `fgjax prepare` tests: a textured box room with a textured cube in it, ray-cast in numpy
(short clips with exactly known cameras: structure from motion needs texture and parallax; no JAX, so no compile
time), and a Record3D export writer (`write_record3d`).

World: z up, metres-like units. Room [-2, 2] x [-2, 2] x [0, 2.4] seen from inside; cube [-0.3, 0.3]^2 x [0, 0.6]
(shifted by ``cube_offset``). Every face carries its own random multi-scale texture (bilinear look-up), so SIFT
finds plenty of features. Cameras are OpenCV c2w [4, 4]; images are rendered at 2x and area-averaged.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

from fgjax.geometry import opencv_to_opengl_c2w

ROOM = (np.array([-2.0, -2.0, 0.0]), np.array([2.0, 2.0, 2.4]))
CUBE = (np.array([-0.3, -0.3, 0.0]), np.array([0.3, 0.3, 0.6]))


def _texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """[size, size, 3] float in [0, 1]: random noise at several scales, plus a few sharp-edged blobs."""
    tex = np.zeros((size, size, 3), np.float32)
    for cells, weight in ((4, 0.35), (12, 0.35), (40, 0.3)):
        small = rng.uniform(0, 1, (cells, cells, 3)).astype(np.float32)
        tex += weight * cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)
    for _ in range(25):
        c = tuple(int(x) for x in rng.integers(0, size, 2))
        cv2.circle(tex, c, int(rng.integers(3, 14)), tuple(float(x) for x in rng.uniform(0, 1, 3)), -1)
    return np.clip(tex, 0, 1)


def look_at_c2w(centre, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera-to-world [4, 4] of a camera at ``centre`` looking at ``target`` (image y down = world -up)."""
    c = np.asarray(centre, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z], axis=1)
    m[:3, 3] = c
    return m


class TexturedRoom:
    def __init__(self, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.textures = {(box, axis, side): _texture(rng) for box in ("room", "cube") for axis in range(3)
                         for side in range(2)}

    def render(self, c2w: np.ndarray, K: np.ndarray, width: int, height: int, cube_offset=(0.0, 0.0, 0.0),
               supersample: int = 2, depth: bool = False):
        """[H, W, 3] uint8 RGB of the room from camera ``c2w`` (OpenCV) with intrinsics ``K`` at (width, height);
        with ``depth``, also the [H, W] float32 z-depth (the ray parameter: rays are K^-1 (u, v, 1), z = 1)."""
        s = supersample
        u, v = np.meshgrid((np.arange(width * s) + 0.5) / s, (np.arange(height * s) + 0.5) / s)
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ c2w[:3, :3].T
        o = c2w[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            # room, seen from inside: the nearest exit face
            t_lo, t_hi = (ROOM[0] - o) * inv, (ROOM[1] - o) * inv
            t_exit = np.maximum(t_lo, t_hi)
            t_room = t_exit.min(-1)
            ax_room = t_exit.argmin(-1)
            side_room = np.take_along_axis((t_hi >= t_lo).astype(int), ax_room[..., None], -1)[..., 0]
            # cube, seen from outside: slab entry
            lo, hi = CUBE[0] + cube_offset, CUBE[1] + cube_offset
            c_lo, c_hi = (lo - o) * inv, (hi - o) * inv
            t_near_ax = np.minimum(c_lo, c_hi)
            t_near = t_near_ax.max(-1)
            t_far = np.maximum(c_lo, c_hi).min(-1)
            ax_cube = t_near_ax.argmax(-1)
            side_cube = np.take_along_axis((c_lo > c_hi).astype(int), ax_cube[..., None], -1)[..., 0]
        hit_cube = (t_near <= t_far) & (t_near > 0) & (t_near < t_room)
        t = np.where(hit_cube, t_near, t_room)
        p = o + t[..., None] * d
        img = np.zeros((*t.shape, 3), np.float32)
        for box, hit, ax, side, (blo, bhi) in (("room", ~hit_cube, ax_room, side_room, ROOM),
                                               ("cube", hit_cube, ax_cube, side_cube, (lo, hi))):
            for axis in range(3):
                for sd in range(2):
                    m = hit & (ax == axis) & (side == sd)
                    if not m.any():
                        continue
                    a, b = [k for k in range(3) if k != axis]
                    tex = self.textures[(box, axis, sd)]
                    n = tex.shape[0] - 1
                    ca = (p[m, a] - blo[a]) / (bhi[a] - blo[a]) * n
                    cb = (p[m, b] - blo[b]) / (bhi[b] - blo[b]) * n
                    for ch in range(3):
                        img[m, ch] = map_coordinates(tex[..., ch], [cb, ca], order=1, mode="nearest")
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
        rgb = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
        if not depth:
            return rgb
        return rgb, cv2.resize(t.astype(np.float32), (width, height), interpolation=cv2.INTER_NEAREST)


def orbit_c2w(n: int, *, sweep_deg: float = 40.0, radius: float = 1.6, height: float = 1.0,
              target=(0.0, 0.0, 0.4)) -> np.ndarray:
    """[n, 4, 4] cameras on an arc about ``target`` (OpenCV c2w)."""
    out = []
    for i in range(n):
        phi = math.radians(-sweep_deg / 2 + sweep_deg * i / max(n - 1, 1))
        c = np.array([radius * math.sin(phi), -radius * math.cos(phi), height])
        out.append(look_at_c2w(c, target))
    return np.stack(out)


def pinhole(width: int, height: int, focal: float) -> np.ndarray:
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising sum |dst - (s R src + t)|^2 (Umeyama 1991), src/dst [N, 3]."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    r = u @ d @ vt
    s = float(np.trace(np.diag(sig) @ d) / (a**2).sum(1).mean())
    return s, r, md - s * r @ ms


def write_record3d(folder: Path, c2w_cv: np.ndarray, K: np.ndarray, images: list[np.ndarray],
                   depths: list[np.ndarray] | None = None, conf: list[np.ndarray] | None = None,
                   drop: str | None = None) -> Path:
    """A Record3D export as the app writes it: metadata with column-major K and [qx, qy, qz, qw, tx, ty, tz] poses in
    ARKit (OpenGL) axes, rgbd/<i>.jpg, lzfse-compressed float32 depth and uint8 confidence."""
    folder.mkdir(parents=True)
    (folder / "rgbd").mkdir()
    poses = []
    for m in c2w_cv:
        gl = opencv_to_opengl_c2w(m)
        poses.append([*Rotation.from_matrix(gl[:3, :3]).as_quat().tolist(), *gl[:3, 3].tolist()])
    h, w = images[0].shape[:2]
    meta = {"fps": 30, "w": w, "h": h, "K": K.T.reshape(-1).tolist(), "poses": poses, "initPose": poses[0]}
    if drop:
        meta.pop(drop)
    (folder / "metadata").write_text(json.dumps(meta))
    for i, img in enumerate(images):
        iio.imwrite(folder / "rgbd" / f"{i}.jpg", img, quality=95)
    if depths is not None:
        import lzfse

        for i, d in enumerate(depths):
            (folder / "rgbd" / f"{i}.depth").write_bytes(lzfse.compress(d.astype(np.float32).tobytes()))
            if conf is not None:
                (folder / "rgbd" / f"{i}.conf").write_bytes(lzfse.compress(conf[i].astype(np.uint8).tobytes()))
    return folder
