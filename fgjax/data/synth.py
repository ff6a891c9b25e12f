"""Synthetic articulated scenes with ground truth (``fgjax synth``, ``fgjax.data.synth``).

A procedural room (floor and three walls, textured so that optical flow has something to track)
with movable objects of four kinds, all built from Gaussians and rendered with
`fgjax.rasterization`:

- ``door``: a cabinet (static, open-front box) whose door rotates about a vertical hinge on its
  left front edge, up to 85 degrees, swinging towards the camera;
- ``drawer``: a chest (static) whose drawer (front panel + tray) slides out along the chest's
  front normal, up to 0.75 of the chest depth;
- ``lid``: a chest (static, open top) whose lid rotates about a horizontal hinge on the back top
  edge, up to 75 degrees;
- ``free``: a ball that rolls along a curved path on the floor towards the camera (translation
  plus rolling rotation; a straight path when it is one of the close pair).

Units and frames. World z is up, the floor is z = 0, the room spans x, y in [-1.6, 1.6] and
z in [0, 1.6] (3.2 units across, `ROOM_SIZE`). Objects are 0.2-0.5 units across. Gaussians on a
movable part are spaced `SynthConfig.object_spacing` (0.025) apart, so DBSCAN with eps 0.05 groups
each part; distinct objects are more than 0.1 apart at every state (`SynthScene.min_separation`),
except with ``close_pair``, which puts the first two objects side by side with the nearest
Gaussian centres of their moving parts `SynthConfig.close_gap` (0.05) apart in the canonical state
(their motions keep them about that far apart). Where the two parts sit at different heights (a
ball next to a lid) the whole objects stop at 0.8 gap instead and the parts' actual gap, recorded
as `SynthScene.close_gap`, is larger. Cameras are OpenCV (x right, y down, z forward),
``viewmat`` world-to-camera, pixel (j, i) centred at (j + 0.5, i + 0.5) (DESIGN.md section 2).

Kinematics. Object k has a rigid transform T_k(s) of its state s in [0, 1] (s = 0: closed, the
canonical pose in which the Gaussians are stored): X' = R(s)(X - p) + p + d(s) with pivot p.
Its state follows a schedule s_k(t): keyframes joined by smoothstep segments (zero velocity at
each keyframe), so there are rests at the start, between movements and at the end; each object
opens, holds and closes in its own time window, so objects move at different times.

The camera sweeps an arc (``orbit_deg``, 60 degrees by default) around the objects at about 2
units, with smooth hand-held jitter (position, look-at point and roll).

Ground truth (written by `generate`; ``gt/meta.json`` lists every file):

- depth: the rasterizer's expected camera z-depth (sum T a z / alpha), 0 where alpha <= 1e-6;
- object id per pixel: argmax of the composited one-hot labels (0 = static, k = object k),
  -1 where alpha < 0.5 (``valid`` False);
- optical flow t-1 -> t on frame t-1's grid, ``[T-1, H, W, 2]`` (dx, dy) in pixels: the centre m
  of each valid pixel is back-projected with its expected depth to a world point X (true camera
  t-1), moved with its object's rigid motion T_k(s_t) T_k(s_{t-1})^-1 (identity for static
  pixels), and projected with the true camera t: flow = pi_t(X') - m. Camera flow =
  pi_t(X) - m (the point held static); object flow = flow - camera flow (exactly 0 on static
  pixels). Approximation: at object boundaries the composited depth and id mix the front and
  back surfaces, so the flow there is that of a point in between (it is exact wherever one
  opaque surface covers the pixel). ``flow_occluded`` marks points that leave the image or land
  behind frame t's surface (depth test, 3 % + 0.01 tolerance);
- per-Gaussian labels, the canonical (state 0) Gaussians (``gt/canonical.npz``), per-frame
  object states and 3D centres (mean of the object's deformed Gaussians), the true poses.

Options: the object kinds and count (up to `MAX_OBJECTS`), resolution, frame count, seed, pose
noise on the *written training* poses (the images are rendered from the true poses, which are
stored in ``gt/``; test poses are written exact), a lighting change (a per-frame global gain
g(t) = 1 - a * smoothstep((t - 0.3) / 0.4) that multiplies the rendered RGB; brightness
constancy breaks, the geometry and the flow do not change), and a close pair.

Test split (``transforms_test.json``): ``view`` frames at training times seen from other camera
positions (azimuth +-10 degrees off the arc, higher and closer), with the schedule's states; and
``state`` frames seen from a training camera with object-state combinations the training
schedule never shows (all objects open at once, to different degrees); their ``time`` is the
training camera's time, so they are meant for control evaluation (``gt/test/kind.npy``,
``gt/meta.json`` say which frame is which).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import hashlib
import json
import math
import os
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
from jaxtyping import Bool, Float, Int

__all__ = [
    "OBJECT_KINDS",
    "SynthConfig",
    "SynthObject",
    "SynthScene",
    "Renders",
    "make_scene",
    "object_state",
    "object_transform",
    "scene_states",
    "deform",
    "object_centres",
    "camera_c2w",
    "render_sequence",
    "ground_truth_flow",
    "sequence_flow",
    "flow_to_color",
    "generate",
    "config_from_args",
    "main",
]

OBJECT_KINDS = ("door", "drawer", "lid", "free")
MAX_OBJECTS = 6
ROOM_HALF = 1.6  # room spans [-1.6, 1.6] in x and y
ROOM_HEIGHT = 1.6
ROOM_SIZE = 2 * ROOM_HALF  # "scene size" for the translational pose noise
GENERATOR = "fgjax.data.synth"
FORMAT_VERSION = 1
VALID_ALPHA = 0.5  # pixels with alpha below this are background (id -1, no flow)
_TEST_VIEW, _TEST_STATE = 0, 1


# ============================================================================ configuration


@dataclasses.dataclass(frozen=True)
class SynthConfig:
    """Options of a synthetic articulated scene (all lengths in scene units).

    Attributes:
        objects: kinds of the movable objects, in label order (label k = objects[k - 1]); each
            one of ``door``, ``drawer``, ``lid``, ``free``; 1 to 6 of them.
        width, height: image size in pixels.
        frames: number of training frames (>= 2); times are i / (frames - 1).
        seed: seed of every random choice (layout jitter, textures, schedules, camera jitter,
            pose noise, test states). Same config and seed -> identical output.
        pose_noise_deg: std of the rotation noise (degrees, random axis) on the written training
            poses.
        pose_noise_trans: std of the translation noise per axis on the written training poses,
            as a fraction of the scene size `ROOM_SIZE` (3.2 units).
        lighting_change: a in the per-frame gain g(t) = 1 - a * smoothstep((t - 0.3) / 0.4)
            applied to the RGB (0 = constant lighting, 0.3 = 30 % darker at the end).
        close_pair: put objects 1 and 2 side by side, ``close_gap`` apart.
        close_gap: gap between the nearest Gaussian centres of the close pair (canonical state).
        room_spacing: Gaussian spacing on the room's walls and floor.
        object_spacing: Gaussian spacing on movable parts (static bodies use 1.6x this).
        focal: fx = fy = focal * width (principal point at the image centre).
        orbit_deg: angle swept by the camera arc over the sequence.
        orbit_radius: distance of the camera from the look-at point.
        jitter: amplitude of the hand-held position jitter (the look-at point jitters 1.5x this,
            the roll 150 degrees per unit, i.e. 1.5 degrees at the default 0.01).
        test_views: number of test frames from other camera positions (at training times).
        test_states: number of test frames with unseen object-state combinations.
    """

    objects: tuple[str, ...] = ("door", "drawer", "lid")
    width: int = 160
    height: int = 120
    frames: int = 60
    seed: int = 0
    pose_noise_deg: float = 0.0
    pose_noise_trans: float = 0.0
    lighting_change: float = 0.0
    close_pair: bool = False
    close_gap: float = 0.05
    room_spacing: float = 0.06
    object_spacing: float = 0.025
    focal: float = 0.8
    orbit_deg: float = 60.0
    orbit_radius: float = 2.0
    jitter: float = 0.01
    test_views: int = 6
    test_states: int = 4

    def __post_init__(self):
        objs = (self.objects,) if isinstance(self.objects, str) else tuple(self.objects)
        object.__setattr__(self, "objects", objs)
        if not 1 <= len(objs) <= MAX_OBJECTS:
            raise ValueError(f"SynthConfig.objects: need 1 to {MAX_OBJECTS} objects, got {len(objs)}")
        for o in objs:
            if o not in OBJECT_KINDS:
                raise ValueError(f"SynthConfig.objects: unknown kind {o!r} (choose from {', '.join(OBJECT_KINDS)})")
        for name, lo in (("width", 16), ("height", 16), ("frames", 2)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"SynthConfig.{name} must be an integer >= {lo}, got {v!r}")
        if self.width > 4096 or self.height > 4096 or self.frames > 10000:
            raise ValueError(f"SynthConfig: {self.width}x{self.height}, {self.frames} frames is too large")
        for name in ("test_views", "test_states"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 1000:
                raise ValueError(f"SynthConfig.{name} must be an integer in [0, 1000], got {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"SynthConfig.seed must be a non-negative integer, got {self.seed!r}")
        ranges = {
            "pose_noise_deg": (0.0, 45.0),
            "pose_noise_trans": (0.0, 0.5),
            "lighting_change": (0.0, 0.9),
            "close_gap": (0.005, 0.5),
            "room_spacing": (0.02, 0.5),
            "object_spacing": (0.008, 0.049),
            "focal": (0.2, 5.0),
            "orbit_deg": (0.0, 120.0),
            "orbit_radius": (1.0, 2.3),
            "jitter": (0.0, 0.1),
        }
        for name, (lo, hi) in ranges.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not (lo <= float(v) <= hi):
                raise ValueError(f"SynthConfig.{name} must be a number in [{lo}, {hi}], got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.close_pair and len(objs) < 2:
            raise ValueError("SynthConfig.close_pair needs at least 2 objects")

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""
        d = dataclasses.asdict(self)
        d["objects"] = list(self.objects)
        return d


# ============================================================================ small maths (numpy)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by `angle` (rad) about the unit `axis`."""
    a = _normalize(np.asarray(axis, dtype=np.float64))
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of wxyz quaternions (broadcasting)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit wxyz quaternion with w >= 0 (Shepperd's method)."""
    m = np.asarray(r, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def _quat_from_z(n: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz rotations taking the local z axis to the unit normals n [N, 3]."""
    n = _normalize(np.asarray(n, dtype=np.float64))
    w = 1.0 + n[:, 2]  # (1 + z.n, z x n) normalised = rotation z -> n
    q = np.stack([w, -n[:, 1], n[:, 0], np.zeros_like(w)], axis=-1)
    flip = w < 1e-8  # n = -z: half turn about x
    q[flip] = np.array([0.0, 1.0, 0.0, 0.0])
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _rigid(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def _rigid_inv(m: np.ndarray) -> np.ndarray:
    r = m[..., :3, :3]
    out = np.zeros_like(m)
    out[..., :3, :3] = np.swapaxes(r, -1, -2)
    out[..., :3, 3] = -np.einsum("...ji,...j->...i", r, m[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ m[:3, :3].T + m[:3, 3]


# ============================================================================ geometry builders


@dataclasses.dataclass
class _Part:
    """Gaussian centres, normals and colours of one surface group (local or world frame)."""

    points: np.ndarray  # [n, 3]
    normals: np.ndarray  # [n, 3]
    colors: np.ndarray  # [n, 3]
    spacing: float

    def transformed(self, m: np.ndarray) -> _Part:
        return _Part(_apply(m, self.points), self.normals @ m[:3, :3].T, self.colors, self.spacing)


def _box_surface(lo, hi, spacing: float, skip: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Points on the faces of the box [lo, hi] (grids including the edges), with face normals.

    Faces are named "-x", "+x", "-y", "+y", "-z", "+z"; those in `skip` are left open. Points
    shared by two faces are kept once. Spacing is at most `spacing` along each face.
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    pts, nrm = [], []
    for axis in range(3):
        u_ax, v_ax = [a for a in range(3) if a != axis]
        nu = max(2, math.ceil((hi[u_ax] - lo[u_ax]) / spacing - 1e-9) + 1)
        nv = max(2, math.ceil((hi[v_ax] - lo[v_ax]) / spacing - 1e-9) + 1)
        uu, vv = np.meshgrid(np.linspace(lo[u_ax], hi[u_ax], nu), np.linspace(lo[v_ax], hi[v_ax], nv), indexing="ij")
        for sign, val in ((-1, lo[axis]), (1, hi[axis])):
            if f"{'-' if sign < 0 else '+'}{'xyz'[axis]}" in skip:
                continue
            p = np.zeros((uu.size, 3))
            p[:, axis] = val
            p[:, u_ax] = uu.ravel()
            p[:, v_ax] = vv.ravel()
            n = np.zeros_like(p)
            n[:, axis] = sign
            pts.append(p)
            nrm.append(n)
    p, n = np.concatenate(pts), np.concatenate(nrm)
    _, idx = np.unique(np.round(p, 7), axis=0, return_index=True)
    idx = np.sort(idx)
    return p[idx], n[idx]


def _sphere_surface(centre, radius: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Fibonacci points on a sphere, about one per spacing^2 of area, with radial normals."""
    n = max(12, math.ceil(4 * math.pi * radius**2 / spacing**2))
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    nrm = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)
    return np.asarray(centre) + radius * nrm, nrm


def _value_noise(p: np.ndarray, rng: np.random.Generator, scale: float, n: int = 4) -> np.ndarray:
    """Smooth pseudo-noise in [-1, 1] at positions p [N, 3]: a few random plane waves."""
    out = np.zeros(p.shape[0])
    for _ in range(n):
        k = _normalize(rng.normal(size=3)) * (2 * math.pi / scale) * rng.uniform(0.6, 1.4)
        out += np.sin(p @ k + rng.uniform(0, 2 * math.pi))
    return out / n


def _texture(p: np.ndarray, base, rng: np.random.Generator, *, checker: float, contrast: float = 0.18,
             noise: float = 0.07, second=None) -> np.ndarray:
    """Per-Gaussian colours: a 3D checker of cell `checker` blending `base` and `second`, smooth
    value noise and iid noise (so that optical flow has texture at every scale)."""
    base = np.asarray(base, dtype=np.float64)
    second = base * (1.0 - contrast) if second is None else np.asarray(second, dtype=np.float64)
    cell = np.floor(p / checker + 1e-6).astype(np.int64).sum(axis=-1) % 2
    col = np.where(cell[:, None] == 0, base, second)
    col = col * (1.0 + 0.15 * _value_noise(p, rng, 4 * checker))[:, None]
    col = col + rng.normal(scale=noise, size=col.shape)
    return np.clip(col, 0.02, 0.98)


def _room(rng: np.random.Generator, spacing: float) -> _Part:
    """Floor and back/left/right walls (the front wall is behind the camera and not built)."""
    h, r = ROOM_HALF, ROOM_HEIGHT
    groups = []
    # floor: wooden checker
    p, n = _box_surface([-h, -h, 0.0], [h, h, 0.0], spacing, skip=("-x", "+x", "-y", "+y", "+z"))
    groups.append((p, n, _texture(p, (0.62, 0.45, 0.30), rng, checker=0.25, second=(0.45, 0.30, 0.18))))
    # walls: each its own colour, stripes via the checker, and a few "posters"
    wall_specs = [
        (([-h, h, 0.0], [h, h, r]), ("-x", "+x", "-z", "+z", "+y"), (0.55, 0.62, 0.70)),  # back, normal -y
        (([-h, -h, 0.0], [-h, h, r]), ("-y", "+y", "-z", "+z", "-x"), (0.70, 0.66, 0.52)),  # left, normal +x
        (([h, -h, 0.0], [h, h, r]), ("-y", "+y", "-z", "+z", "+x"), (0.60, 0.70, 0.58)),  # right, normal -x
    ]
    for (lo, hi), skip, base in wall_specs:
        p, n = _box_surface(lo, hi, spacing, skip=skip)
        col = _texture(p, base, rng, checker=0.3, contrast=0.22)
        for _ in range(4):  # posters: rectangles of random colour
            c = p[rng.integers(len(p))]
            half = rng.uniform(0.12, 0.3, size=3)
            inside = np.all(np.abs(p - c) <= half, axis=-1) & (p[:, 2] > 0.15)
            col[inside] = np.clip(rng.uniform(0.1, 0.9, size=3) + rng.normal(scale=0.06, size=(inside.sum(), 3)), 0, 1)
        groups.append((p, n, col))
    return _Part(*(np.concatenate([g[i] for g in groups]) for i in range(3)), spacing=spacing)


@dataclasses.dataclass
class _LocalObject:
    """An object in its local frame (origin at the footprint centre on the floor, front facing -y)."""

    body: _Part | None
    part: _Part
    width: float  # x extent [-width/2, width/2] of the part (and body) in the canonical state
    depth: float  # y extent of the footprint including swept space in front (for layout)
    kin: dict[str, Any]  # kinematics in the local frame

    @property
    def front(self) -> float:
        """Smallest y of the moving part (its front face) in the canonical state."""
        return float(self.part.points[:, 1].min())


def _build_door(rng, sp: float, palette) -> _LocalObject:
    w, d, h, th = 0.32, 0.28, 0.5, 0.02
    bsp = 1.6 * sp
    bp, bn = _box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("-y",))
    body = _Part(bp, bn, _texture(bp, palette[1], rng, checker=0.08), bsp)
    pp, pn = _box_surface([-w / 2, -d / 2 - th, 0.0], [w / 2, -d / 2, h], sp)
    part = _Part(pp, pn, _texture(pp, palette[0], rng, checker=0.05, contrast=0.3), sp)
    kin = {"pivot": np.array([-w / 2, -d / 2 - th, 0.0]), "axis": np.array([0.0, 0.0, -1.0]),
           "max_angle": math.radians(85.0)}
    return _LocalObject(body, part, w, d + w, kin)


def _build_drawer(rng, sp: float, palette) -> _LocalObject:
    w, d, h, th, inset = 0.36, 0.30, 0.30, 0.02, 0.03
    bsp = 1.6 * sp
    bp, bn = _box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("-y",))
    body = _Part(bp, bn, _texture(bp, palette[1], rng, checker=0.08), bsp)
    fp, fn = _box_surface([-w / 2, -d / 2 - th, 0.0], [w / 2, -d / 2, h], sp)  # front panel
    tp, tn = _box_surface([-w / 2 + inset, -d / 2, inset], [w / 2 - inset, d / 2 - inset, h - 2 * inset], sp,
                          skip=("-y", "+z"))  # open tray behind the panel
    pp, pn = np.concatenate([fp, tp]), np.concatenate([fn, tn])
    col = _texture(pp, palette[0], rng, checker=0.05, contrast=0.3)
    part = _Part(pp, pn, col, sp)
    travel = 0.75 * d
    kin = {"direction": np.array([0.0, -1.0, 0.0]), "distance": travel}
    return _LocalObject(body, part, w, d + travel, kin)


def _build_lid(rng, sp: float, palette) -> _LocalObject:
    w, d, h, th = 0.36, 0.26, 0.24, 0.02
    bsp = 1.6 * sp
    bp, bn = _box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("+z",))
    body = _Part(bp, bn, _texture(bp, palette[1], rng, checker=0.08), bsp)
    pp, pn = _box_surface([-w / 2, -d / 2, h], [w / 2, d / 2, h + th], sp)
    part = _Part(pp, pn, _texture(pp, palette[0], rng, checker=0.05, contrast=0.3), sp)
    kin = {"pivot": np.array([0.0, d / 2, h]), "axis": np.array([-1.0, 0.0, 0.0]),
           "max_angle": math.radians(75.0)}
    return _LocalObject(body, part, w, d, kin)


def _build_free(rng, sp: float, palette, *, straight: bool) -> _LocalObject:
    r = 0.09
    pp, pn = _sphere_surface([0.0, 0.0, r], r, sp)
    part = _Part(pp, pn, _texture(pp, palette[0], rng, checker=0.045, contrast=0.45), sp)
    length = 0.4
    wiggle = 0.0 if straight else 0.12
    kin = {"pivot": np.array([0.0, 0.0, r]), "direction": np.array([0.0, -1.0, 0.0]),
           "lateral": np.array([1.0, 0.0, 0.0]), "distance": length, "wiggle": wiggle, "radius": r,
           "axis": np.array([1.0, 0.0, 0.0])}  # rolling towards -y turns about +x
    return _LocalObject(None, part, 2 * r, 2 * r + length, kin)


_PALETTE = [
    ((0.85, 0.25, 0.20), (0.40, 0.32, 0.28)),
    ((0.20, 0.55, 0.85), (0.35, 0.35, 0.40)),
    ((0.95, 0.75, 0.15), (0.30, 0.38, 0.30)),
    ((0.60, 0.30, 0.80), (0.42, 0.36, 0.30)),
    ((0.20, 0.80, 0.45), (0.38, 0.30, 0.34)),
    ((0.95, 0.50, 0.75), (0.32, 0.34, 0.38)),
]


# ============================================================================ scene


@dataclasses.dataclass(frozen=True, eq=False)
class SynthObject:
    """One movable object: its kinematics (world frame) and its state schedule.

    T(s) X = R(s) (X - pivot) + pivot + d(s), with
      door, lid: R = rotation about `axis` by s * max_angle, d = 0;
      drawer:    R = I, d = s * distance * direction;
      free:      d = path(s) - path(0), path(s) = s * distance * direction
                 + wiggle * sin(pi s) * lateral; R = rotation about `axis` by
                 s * distance / radius (rolling along the main direction).
    State schedule: s(t) interpolates (key_times, key_states) with smoothstep segments.

    Attributes:
        label: 1-based label (per-Gaussian labels and per-pixel ids use it; 0 = static).
        kind: one of `OBJECT_KINDS`.
        name: e.g. "door_1".
        pivot, axis, direction, lateral: [3] world vectors (unused ones are zero).
        max_angle: radians; distance, wiggle, radius: scene units (unused ones 0).
        key_times, key_states: [M] schedule keyframes (times increasing in [0, 1]).
    """

    label: int
    kind: str
    name: str
    pivot: np.ndarray
    axis: np.ndarray
    direction: np.ndarray
    lateral: np.ndarray
    max_angle: float
    distance: float
    wiggle: float
    radius: float
    key_times: np.ndarray
    key_states: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
        return out


def object_transform(obj: SynthObject, s: float) -> Float[np.ndarray, "4 4"]:
    """Rigid world transform T(s) taking the canonical (s = 0) object to state s (see `SynthObject`)."""
    s = float(s)
    if obj.kind in ("door", "lid"):
        r, d = _axis_angle_matrix(obj.axis, s * obj.max_angle), np.zeros(3)
    elif obj.kind == "drawer":
        r, d = np.eye(3), s * obj.distance * obj.direction
    elif obj.kind == "free":
        d = s * obj.distance * obj.direction + obj.wiggle * math.sin(math.pi * s) * obj.lateral
        r = _axis_angle_matrix(obj.axis, s * obj.distance / obj.radius)
    else:  # pragma: no cover - guarded by SynthConfig
        raise ValueError(f"object_transform: unknown kind {obj.kind!r}")
    return _rigid(r, obj.pivot + d - r @ obj.pivot)


def object_state(obj: SynthObject, t: float | np.ndarray) -> np.ndarray:
    """State s(t) of the object's schedule (smoothstep between keyframes, constant outside)."""
    t = np.asarray(t, dtype=np.float64)
    kt, ks = obj.key_times, obj.key_states
    i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, len(kt) - 2)
    u = (t - kt[i]) / np.maximum(kt[i + 1] - kt[i], 1e-12)
    return ks[i] + (ks[i + 1] - ks[i]) * _smoothstep(u)


@dataclasses.dataclass(frozen=True, eq=False)
class SynthScene:
    """Canonical Gaussians (every object at state 0), their labels, objects and the camera path.

    Attributes:
        cfg: the `SynthConfig`.
        means, quats, scales, opacities, colors: [N, 3], [N, 4] (wxyz), [N, 3] (activated),
            [N] (activated), [N, 3] RGB in [0, 1]: the canonical Gaussians.
        labels: [N] int32, 0 = static, k = object k.
        objects: the K `SynthObject`s, objects[k - 1] has label k.
        K: [3, 3] intrinsics (same for every frame).
        camera: camera path parameters (see `camera_c2w`).
        min_separation: smallest distance between Gaussian centres of different objects over
            a sweep of their states (bodies included), excluding the close pair.
        close_gap: canonical distance between the nearest Gaussians of the close pair (moving
            parts), or None.
    """

    cfg: SynthConfig
    means: Float[np.ndarray, "N 3"]
    quats: Float[np.ndarray, "N 4"]
    scales: Float[np.ndarray, "N 3"]
    opacities: Float[np.ndarray, " N"]
    colors: Float[np.ndarray, "N 3"]
    labels: Int[np.ndarray, " N"]
    objects: tuple[SynthObject, ...]
    K: Float[np.ndarray, "3 3"]
    camera: dict[str, Any]
    min_separation: float
    close_gap: float | None

    @property
    def num_objects(self) -> int:
        return len(self.objects)


def _schedules(k: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per object: rest, open (to s_max), hold, close, rest, inside its own window of [0.08, 0.95]."""
    out = []
    t0, t1 = 0.08, 0.95
    w = (t1 - t0) / k
    for i in range(k):
        a = t0 + i * w
        j = rng.uniform(-0.03, 0.03, size=3) * w
        s_max = rng.uniform(0.85, 1.0)
        times = np.array([0.0, a + 0.02 * w, a + 0.42 * w + j[0], a + 0.55 * w + j[1], a + 0.95 * w + j[2], 1.0])
        states = np.array([0.0, 0.0, s_max, s_max, 0.0, 0.0])
        out.append((times, states))
    return out


def _layout(cfg: SynthConfig, locals_: list[_LocalObject], rng: np.random.Generator) -> list[np.ndarray]:
    """World placement [4, 4] of each object (rows of objects on the floor, facing the camera)."""
    groups: list[list[int]] = [[0, 1]] + [[i] for i in range(2, len(locals_))] if cfg.close_pair else [
        [i] for i in range(len(locals_))]
    gap = 0.3

    def group_width(g):
        return sum(locals_[i].width for i in g) + cfg.close_gap * (len(g) - 1)

    rows = [groups] if len(groups) <= 3 else [groups[: (len(groups) + 1) // 2], groups[(len(groups) + 1) // 2:]]
    row_y = [0.0] if len(rows) == 1 else [-0.2, 0.8]
    out: list[np.ndarray | None] = [None] * len(locals_)
    for row, y in zip(rows, row_y, strict=True):
        total = sum(group_width(g) for g in row) + gap * (len(row) - 1)
        x = -total / 2
        for g in row:
            gw = group_width(g)
            yaw = 0.0 if len(g) > 1 else math.radians(rng.uniform(-8, 8))
            gx = x + gw / 2 + rng.uniform(-0.03, 0.03)
            gy = y + rng.uniform(-0.05, 0.05)
            place = _rigid(_axis_angle_matrix([0, 0, 1], yaw), np.array([gx, gy, 0.0]))
            off = -gw / 2
            front = min(locals_[i].front for i in g)  # align the pair's front faces
            for i in g:
                lw = locals_[i].width
                out[i] = place @ _rigid(np.eye(3), np.array([off + lw / 2, front - locals_[i].front, 0.0]))
                off += lw + cfg.close_gap
            x += gw + gap
    return out  # type: ignore[return-value]


def _tighten_pair(a: _LocalObject, place_a: np.ndarray, b: _LocalObject, place_b: np.ndarray,
                  gap: float) -> np.ndarray:
    """Slide object b along the pair's x axis so that the nearest Gaussian centres of the two moving
    parts (canonical state) are `gap` apart, unless that would bring the whole objects (bodies
    included) closer than 0.8 gap; then they stop there (the parts' gap is larger, e.g. a ball
    next to a chest whose lid sits higher than the ball).

    Each distance is solved by the fixed-point iteration delta <- delta - (d(delta) - target): d
    changes by at most |step|, and by exactly |step| once the nearest points line up with the axis.
    """
    from scipy.spatial import cKDTree

    axis = place_b[:3, 0]

    def solve(pa, pb, target):
        tree = cKDTree(pa)
        delta = 0.0
        for _ in range(100):
            d = float(tree.query(pb + delta * axis, k=1)[0].min())
            if abs(d - target) < 1e-12:
                break
            delta -= d - target
        return delta

    def whole(o, place):
        return _apply(place, np.concatenate([o.part.points] + ([o.body.points] if o.body is not None else [])))

    d_parts = solve(_apply(place_a, a.part.points), _apply(place_b, b.part.points), gap)
    d_whole = solve(whole(a, place_a), whole(b, place_b), 0.8 * gap)
    out = place_b.copy()
    out[:3, 3] += max(d_parts, d_whole) * axis
    return out


def _seed_of(key_or_seed) -> int:
    if key_or_seed is None:
        raise ValueError("make_scene: seed is None")
    if isinstance(key_or_seed, int | np.integer) and not isinstance(key_or_seed, bool):
        return int(key_or_seed)
    import jax  # a JAX PRNG key

    return int(jax.random.randint(key_or_seed, (), 0, 2**31 - 1))


def make_scene(cfg: SynthConfig, key_or_seed: int | Any | None = None) -> SynthScene:
    """Build the room, the objects, their schedules and the camera path.

    Args:
        cfg: the options.
        key_or_seed: an int seed or a JAX PRNG key; None uses ``cfg.seed``.

    Returns:
        The `SynthScene` (canonical Gaussians with every object at state 0).
    """
    seed = cfg.seed if key_or_seed is None else _seed_of(key_or_seed)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5EED]))
    room = _room(rng, cfg.room_spacing)
    builders = {"door": _build_door, "drawer": _build_drawer, "lid": _build_lid}
    locals_: list[_LocalObject] = []
    for i, kind in enumerate(cfg.objects):
        pal = _PALETTE[i % len(_PALETTE)]
        if kind == "free":
            locals_.append(_build_free(rng, cfg.object_spacing, pal, straight=cfg.close_pair and i < 2))
        else:
            locals_.append(builders[kind](rng, cfg.object_spacing, pal))
    places = _layout(cfg, locals_, rng)
    if cfg.close_pair:
        places[1] = _tighten_pair(locals_[0], places[0], locals_[1], places[1], cfg.close_gap)
    scheds = _schedules(len(locals_), rng)

    parts: list[tuple[_Part, int, int]] = [(room, 0, 0)]  # (part, label, owner)
    objects = []
    for i, (lo, place) in enumerate(zip(locals_, places, strict=True)):
        label = i + 1
        if lo.body is not None:
            parts.append((lo.body.transformed(place), 0, label))
        parts.append((lo.part.transformed(place), label, label))
        rot = place[:3, :3]
        kin = lo.kin

        def vec(name, *, point=False, kin=kin, rot=rot, place=place):
            if name not in kin:
                return np.zeros(3)
            return _apply(place, kin[name]) if point else rot @ kin[name]

        objects.append(SynthObject(
            label=label, kind=cfg.objects[i], name=f"{cfg.objects[i]}_{label}",
            pivot=vec("pivot", point=True), axis=vec("axis"), direction=vec("direction"), lateral=vec("lateral"),
            max_angle=float(kin.get("max_angle", 0.0)), distance=float(kin.get("distance", 0.0)),
            wiggle=float(kin.get("wiggle", 0.0)), radius=float(kin.get("radius", 0.0)),
            key_times=scheds[i][0], key_states=scheds[i][1],
        ))

    means = np.concatenate([p.points for p, _, _ in parts])
    normals = np.concatenate([p.normals for p, _, _ in parts])
    colors = np.concatenate([p.colors for p, _, _ in parts])
    labels = np.concatenate([np.full(len(p.points), lab, dtype=np.int32) for p, lab, _ in parts])
    owner = np.concatenate([np.full(len(p.points), own, dtype=np.int32) for p, _, own in parts])
    sig = np.concatenate([np.full(len(p.points), p.spacing) for p, _, _ in parts])
    scales = np.stack([0.6 * sig, 0.6 * sig, 0.12 * sig], axis=-1)
    quats = _quat_from_z(normals)
    opacities = np.full(len(means), 0.97)

    fx = cfg.focal * cfg.width
    K = np.array([[fx, 0.0, cfg.width / 2.0], [0.0, fx, cfg.height / 2.0], [0.0, 0.0, 1.0]])
    camera = {
        "target": np.array([0.0, 0.35, 0.25]),
        "radius": cfg.orbit_radius,
        "height": 0.95,
        "sweep": math.radians(cfg.orbit_deg),
        # hand-held jitter: 3 sinusoids per channel (3 position, 3 target, 1 roll)
        "freqs": rng.uniform(2.0, 6.0, size=(7, 3)),
        "phases": rng.uniform(0.0, 2 * math.pi, size=(7, 3)),
        "weights": rng.uniform(0.5, 1.0, size=(7, 3)) / 2.25,
        "wobble_phase": float(rng.uniform(0, 2 * math.pi)),
    }
    scene = SynthScene(
        cfg=cfg, means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, labels=labels,
        objects=tuple(objects), K=K, camera=camera, min_separation=math.inf, close_gap=None,
    )
    sep, close = _separations(scene, owner)
    return dataclasses.replace(scene, min_separation=sep, close_gap=close)


def _separations(scene: SynthScene, owner: np.ndarray) -> tuple[float, float | None]:
    """(min distance between different objects over a sweep of states, canonical close-pair gap).

    `owner` [N]: 0 for the room, k for object k's static body and moving part.
    """
    from scipy.spatial import cKDTree

    sweep = np.linspace(0.0, 1.0, 5)
    clouds = {}
    for k, obj in enumerate(scene.objects, start=1):
        part = scene.means[scene.labels == k]
        body = scene.means[(owner == k) & (scene.labels == 0)]
        clouds[k] = np.concatenate([body] + [_apply(object_transform(obj, s), part) for s in sweep])
    pair = (1, 2) if scene.cfg.close_pair else None
    sep = math.inf
    for a in clouds:
        tree = cKDTree(clouds[a])
        for b in clouds:
            if b <= a or (a, b) == pair:
                continue
            sep = min(sep, float(tree.query(clouds[b], k=1)[0].min()))
    close = None
    if pair is not None:
        pa, pb = (scene.means[scene.labels == k] for k in pair)
        close = float(cKDTree(pa).query(pb, k=1)[0].min())
    return sep, close


def scene_states(scene: SynthScene, times: Float[np.ndarray, " T"]) -> Float[np.ndarray, "T K"]:
    """Scheduled object states at `times`."""
    times = np.asarray(times, dtype=np.float64)
    return np.stack([object_state(o, times) for o in scene.objects], axis=-1).reshape(len(times), -1)


def _object_transforms(scene: SynthScene, states: np.ndarray) -> np.ndarray:
    """[K + 1, 4, 4] transforms by label (identity for label 0) at one state vector [K]."""
    out = np.tile(np.eye(4), (scene.num_objects + 1, 1, 1))
    for k, obj in enumerate(scene.objects, start=1):
        out[k] = object_transform(obj, states[k - 1])
    return out


def deform(scene: SynthScene, states: Float[np.ndarray, " K"]) -> tuple[Float[np.ndarray, "N 3"], Float[np.ndarray, "N 4"]]:
    """Means and quaternions of the Gaussians with the objects at `states` [K]."""
    states = np.asarray(states, dtype=np.float64).reshape(-1)
    if states.shape != (scene.num_objects,):
        raise ValueError(f"deform: states must have shape [K] = [{scene.num_objects}], got {states.shape}")
    tr = _object_transforms(scene, states)  # [K + 1, 4, 4]
    m = tr[scene.labels]  # [N, 4, 4]
    means = np.einsum("nij,nj->ni", m[:, :3, :3], scene.means) + m[:, :3, 3]
    qk = np.stack([_rotmat_to_quat(t[:3, :3]) for t in tr])  # [K + 1, 4]
    quats = _quat_mul(qk[scene.labels], scene.quats)
    return means, quats


def object_centres(scene: SynthScene, states: Float[np.ndarray, "T K"]) -> Float[np.ndarray, "T K 3"]:
    """3D centre (mean of the deformed Gaussians of each object's moving part) per state vector."""
    states = np.atleast_2d(np.asarray(states, dtype=np.float64))
    out = np.zeros((len(states), scene.num_objects, 3))
    for k, obj in enumerate(scene.objects, start=1):
        c0 = scene.means[scene.labels == k]
        for t, s in enumerate(states):
            out[t, k - 1] = _apply(object_transform(obj, s[k - 1]), c0).mean(axis=0)
    return out


def _jitter(cam: dict[str, Any], t: float) -> np.ndarray:
    """[7] smooth jitter channels in about [-1, 1] at time t."""
    return np.sum(cam["weights"] * np.sin(2 * math.pi * cam["freqs"] * t + cam["phases"]), axis=-1)


def camera_c2w(scene: SynthScene, t: float, *, d_azimuth: float = 0.0, d_height: float = 0.0,
               d_radius: float = 0.0) -> Float[np.ndarray, "4 4"]:
    """True OpenCV camera-to-world of the camera path at time t, optionally displaced.

    Position: look-at point + radius * (sin phi, -cos phi, 0) at height ``height`` (+ a slow
    wobble), phi sweeping [-sweep/2, sweep/2] over t in [0, 1]; plus hand-held jitter (position,
    look-at point, roll). `d_azimuth` (rad), `d_height`, `d_radius` move the camera off the path
    (test views).
    """
    cam, cfg = scene.camera, scene.cfg
    j = _jitter(cam, t)
    phi = -cam["sweep"] / 2 + cam["sweep"] * t + d_azimuth
    rad = cam["radius"] + 0.05 * math.sin(2 * math.pi * 1.3 * t) + d_radius
    target = cam["target"] + 1.5 * cfg.jitter * j[3:6]
    pos = np.array([cam["target"][0] + rad * math.sin(phi), cam["target"][1] - rad * math.cos(phi),
                    cam["height"] + 0.06 * math.sin(2 * math.pi * 0.8 * t + cam["wobble_phase"]) + d_height])
    pos = pos + cfg.jitter * j[:3]
    z = _normalize(target - pos)
    x = _normalize(np.cross(z, [0.0, 0.0, 1.0]))
    y = np.cross(z, x)
    roll = math.radians(150.0 * cfg.jitter * j[6])
    rot = np.stack([x, y, z], axis=-1) @ _axis_angle_matrix([0, 0, 1], roll)
    return _rigid(rot, pos)


# ============================================================================ rendering


@dataclasses.dataclass(frozen=True, eq=False)
class Renders:
    """Rendered frames with per-pixel ground truth.

    Attributes:
        rgb: [T, H, W, 3] float32 in [0, 1] (lighting gain applied).
        alpha: [T, H, W] float32 accumulated opacity.
        depth: [T, H, W] float32 expected camera z-depth, 0 where alpha <= 1e-6.
        object_id: [T, H, W] int16 argmax of composited one-hot labels, -1 where not valid.
        valid: [T, H, W] bool, alpha >= 0.5.
    """

    rgb: Float[np.ndarray, "T H W 3"]
    alpha: Float[np.ndarray, "T H W"]
    depth: Float[np.ndarray, "T H W"]
    object_id: Int[np.ndarray, "T H W"]
    valid: Bool[np.ndarray, "T H W"]


@functools.partial(jax.jit, static_argnames=("width", "height", "capacity"))
def _render_frame(means, quats, scales, opacities, feats, viewmat, K, *, width, height, capacity):
    from fgjax.render.api import rasterization

    img, alpha, info = rasterization(means, quats, scales, opacities, feats, viewmat, K, width, height,
                                     capacity=capacity)
    return img, alpha, info["depth"], info["overflow"], info["n_isect"]


def _capacity(counts: Sequence[int]) -> int:
    """Fixed intersection capacity for a whole sequence: 1.5x the largest count, rounded up."""
    need = int(max(counts)) * 3 // 2 + 1024
    return -(-need // 4096) * 4096


def render_sequence(
    scene: SynthScene,
    viewmats: Float[np.ndarray, "T 4 4"],
    states: Float[np.ndarray, "T K"],
    *,
    gains: Float[np.ndarray, " T"] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Renders:
    """Render frames of the scene with the objects at `states` from the true `viewmats`.

    One jit-compiled render per resolution/capacity: the intersection capacity is fixed for the
    sequence (1.5x the largest count over its frames), and a frame that overflows it raises.

    Args:
        scene: the `SynthScene`.
        viewmats: [T, 4, 4] OpenCV world-to-camera (true poses).
        states: [T, K] object states.
        gains: [T] global brightness gains (None = 1).
        progress: called as progress(i, T) after each frame.

    Returns:
        `Renders`.
    """
    import jax.numpy as jnp

    from fgjax.render.api import count_intersections

    cfg = scene.cfg
    viewmats = np.asarray(viewmats, dtype=np.float64)
    states = np.asarray(states, dtype=np.float64)
    t = len(viewmats)
    if viewmats.shape != (t, 4, 4) or states.shape != (t, scene.num_objects):
        raise ValueError(f"render_sequence: viewmats [T, 4, 4] and states [T, K={scene.num_objects}] expected, "
                         f"got {viewmats.shape} and {states.shape}")
    gains = np.ones(t) if gains is None else np.asarray(gains, dtype=np.float64)
    k1 = scene.num_objects + 1
    onehot = np.eye(k1)[scene.labels]  # [N, K + 1]
    f32 = lambda x: jnp.asarray(np.asarray(x, dtype=np.float32))
    feats = f32(np.concatenate([scene.colors, onehot], axis=-1))
    scales, opac, K = f32(scene.scales), f32(scene.opacities), f32(scene.K)
    w, h = cfg.width, cfg.height
    deformed = [deform(scene, s) for s in states]
    counts = [
        int(count_intersections(f32(m), f32(q), scales, opac, f32(v), K, width=w, height=h))
        for (m, q), v in zip(deformed, viewmats, strict=True)
    ]
    cap = _capacity(counts)
    rgb = np.zeros((t, h, w, 3), np.float32)
    alpha = np.zeros((t, h, w), np.float32)
    depth = np.zeros((t, h, w), np.float32)
    ids = np.full((t, h, w), -1, np.int16)
    for i, ((m, q), v) in enumerate(zip(deformed, viewmats, strict=True)):
        img, a, d, overflow, n_isect = _render_frame(f32(m), f32(q), scales, opac, feats, f32(v), K,
                                                     width=w, height=h, capacity=cap)
        if bool(overflow):
            raise RuntimeError(f"render_sequence: frame {i} needs {int(n_isect)} intersections > capacity {cap}")
        img, a, d = np.asarray(img), np.asarray(a), np.asarray(d)
        rgb[i] = np.clip(img[..., :3] * gains[i], 0.0, 1.0)
        alpha[i] = a
        depth[i] = d
        ids[i] = np.where(a >= VALID_ALPHA, np.argmax(img[..., 3:], axis=-1), -1)
        if progress is not None:
            progress(i + 1, t)
    return Renders(rgb=rgb, alpha=alpha, depth=depth, object_id=ids, valid=alpha >= VALID_ALPHA)


# ============================================================================ ground-truth flow


def _pixel_grid(h: int, w: int) -> np.ndarray:
    xx, yy = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5, indexing="xy")
    return np.stack([xx, yy], axis=-1)  # [H, W, 2]


def ground_truth_flow(
    depth0: Float[np.ndarray, "H W"],
    object_id0: Int[np.ndarray, "H W"],
    K: Float[np.ndarray, "3 3"],
    viewmat0: Float[np.ndarray, "4 4"],
    viewmat1: Float[np.ndarray, "4 4"],
    motions: Float[np.ndarray, "K1 4 4"],
    *,
    depth1: Float[np.ndarray, "H W"] | None = None,
    near: float = 0.01,
) -> dict[str, np.ndarray]:
    """Optical, camera and object flow from frame 0 to frame 1 on frame 0's pixel grid.

    X = c2w_0 (depth0(m) K^-1 m~); X' = motions[id(m)] X; flow = pi_1(X') - m,
    camera_flow = pi_1(X) - m, object_flow = flow - camera_flow (0 where id = 0).

    Args:
        depth0: [H, W] expected camera z-depth of frame 0 (0 = none).
        object_id0: [H, W] per-pixel label of frame 0 (-1 = background/invalid).
        K: [3, 3] intrinsics (both frames).
        viewmat0, viewmat1: [4, 4] true OpenCV world-to-camera of frames 0 and 1.
        motions: [K + 1, 4, 4] world rigid motion of each label from frame 0 to 1
            (T_k(s_1) T_k(s_0)^-1; identity at index 0).
        depth1: optional [H, W] depth of frame 1, for the occlusion test.
        near: points at camera depth <= near in frame 1 are invalid.

    Returns:
        dict with flow, camera_flow, object_flow [H, W, 2] float32 (0 where not valid),
        valid [H, W] bool (frame-0 pixel has an id and positive depth, and its point lies in
        front of camera 1), occluded [H, W] bool (valid, and the point lands outside frame 1 or
        behind frame 1's surface by more than 3 % + 0.01; only with depth1).
    """
    h, w = depth0.shape
    m = _pixel_grid(h, w)
    kinv = np.linalg.inv(K)
    ok = (object_id0 >= 0) & (depth0 > 0)
    rays = np.concatenate([m, np.ones((h, w, 1))], axis=-1) @ kinv.T  # [H, W, 3], z = 1
    p0 = rays * depth0[..., None]
    c2w0 = _rigid_inv(viewmat0)
    xw = p0 @ c2w0[:3, :3].T + c2w0[:3, 3]  # [H, W, 3] world points
    lab = np.clip(object_id0, 0, len(motions) - 1)
    mo = motions[lab]  # [H, W, 4, 4]
    xw_moved = np.einsum("hwij,hwj->hwi", mo[..., :3, :3], xw) + mo[..., :3, 3]

    def project(x):
        pc = x @ viewmat1[:3, :3].T + viewmat1[:3, 3]
        z = pc[..., 2]
        zs = np.where(z > near, z, 1.0)
        uv = (pc[..., :2] / zs[..., None]) @ K[:2, :2].T + K[:2, 2]
        return uv, z

    uv_cam, z_cam = project(xw)
    uv, z1 = project(xw_moved)
    valid = ok & (z1 > near) & (z_cam > near)
    flow = np.where(valid[..., None], uv - m, 0.0)
    cam = np.where(valid[..., None], uv_cam - m, 0.0)
    obj = np.where((valid & (object_id0 > 0))[..., None], flow - cam, 0.0)
    flow = cam + obj  # exact decomposition (no rounding differences on static pixels)
    occluded = np.zeros((h, w), bool)
    if depth1 is not None:
        col = np.floor(uv[..., 0]).astype(np.int64)
        row = np.floor(uv[..., 1]).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        d1 = depth1[np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)]
        behind = (d1 <= 0) | (z1 > d1 * 1.03 + 0.01)
        occluded = valid & (~inside | behind)
    return {
        "flow": flow.astype(np.float32),
        "camera_flow": cam.astype(np.float32),
        "object_flow": obj.astype(np.float32),
        "valid": valid,
        "occluded": occluded,
    }


# ============================================================================ visualisation


def _color_wheel() -> np.ndarray:
    """Middlebury colour wheel [55, 3] (RY 15, YG 6, GC 4, CB 11, BM 13, MR 6), values in [0, 255]."""
    segs = [(15, (255, 0, 0), (255, 255, 0)), (6, (255, 255, 0), (0, 255, 0)), (4, (0, 255, 0), (0, 255, 255)),
            (11, (0, 255, 255), (0, 0, 255)), (13, (0, 0, 255), (255, 0, 255)), (6, (255, 0, 255), (255, 0, 0))]
    rows = []
    for n, a, b in segs:
        f = np.arange(n)[:, None] / n
        rows.append(np.asarray(a) * (1 - f) + np.asarray(b) * f)
    return np.concatenate(rows)


def flow_to_color(flow: Float[np.ndarray, "H W 2"], max_flow: float | None = None,
                  valid: Bool[np.ndarray, "H W"] | None = None) -> np.ndarray:
    """Middlebury colour coding of a flow field: hue = direction, saturation = magnitude.

    Args:
        flow: [H, W, 2] (dx, dy).
        max_flow: magnitude mapped to full saturation (None: the largest valid magnitude).
        valid: optional [H, W] mask; invalid pixels are black.

    Returns:
        [H, W, 3] uint8 RGB.
    """
    flow = np.asarray(flow, dtype=np.float64)
    ok = np.all(np.isfinite(flow), axis=-1) if valid is None else (np.asarray(valid, bool) & np.all(np.isfinite(flow), -1))
    u = np.where(ok, flow[..., 0], 0.0)
    v = np.where(ok, flow[..., 1], 0.0)
    mag = np.hypot(u, v)
    if max_flow is None:
        max_flow = float(mag[ok].max()) if np.any(ok) else 1.0
    max_flow = max(float(max_flow), 1e-9)
    rad = np.minimum(mag / max_flow, 1.0)
    wheel = _color_wheel()
    n = len(wheel)
    a = np.arctan2(-v, -u) / math.pi  # [-1, 1]
    fk = (a + 1) / 2 * (n - 1)
    k0 = np.floor(fk).astype(np.int64)
    k1 = (k0 + 1) % n
    f = (fk - k0)[..., None]
    col = ((1 - f) * wheel[k0] + f * wheel[k1]) / 255.0
    col = 1 - rad[..., None] * (1 - col)
    col = np.where(ok[..., None], col, 0.0)
    return np.round(col * 255).astype(np.uint8)


# ============================================================================ generation


def _lighting_gains(cfg: SynthConfig, times: np.ndarray) -> np.ndarray:
    return 1.0 - cfg.lighting_change * _smoothstep((np.asarray(times) - 0.3) / 0.4)


def _noisy_viewmats(cfg: SynthConfig, c2w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Written (possibly noisy) viewmats from true OpenCV c2w [T, 4, 4]."""
    out = c2w.copy()
    if cfg.pose_noise_deg > 0 or cfg.pose_noise_trans > 0:
        for i in range(len(out)):
            axis = _normalize(rng.normal(size=3))
            ang = math.radians(cfg.pose_noise_deg) * rng.normal()
            out[i, :3, :3] = _axis_angle_matrix(axis, ang) @ out[i, :3, :3]
            out[i, :3, 3] += cfg.pose_noise_trans * ROOM_SIZE * rng.normal(size=3)
    return _rigid_inv(out)


def _test_frames(scene: SynthScene, train_times: np.ndarray, train_states: np.ndarray,
                 rng: np.random.Generator) -> list[dict[str, Any]]:
    """Held-out frames: novel views at training times, and novel state combinations."""
    cfg = scene.cfg
    t = len(train_times)
    out = []
    view_idx = np.round(np.linspace(0, t - 1, cfg.test_views + 2)[1:-1]).astype(int) if cfg.test_views else []
    for j, i in enumerate(view_idx):
        sign = 1.0 if j % 2 == 0 else -1.0
        c2w = camera_c2w(scene, float(train_times[i]), d_azimuth=sign * math.radians(10.0), d_height=0.15,
                         d_radius=-0.15)
        out.append({"kind": "view", "time": float(train_times[i]), "source": int(i), "c2w": c2w,
                    "states": train_states[i].copy()})
    state_idx = np.round(np.linspace(0, t - 1, cfg.test_states + 2)[1:-1]).astype(int) if cfg.test_states else []
    kmax = np.array([o.key_states.max() for o in scene.objects])
    for j, i in enumerate(state_idx):
        states = kmax.copy() if j == 0 else rng.uniform(0.35, 1.0, size=scene.num_objects) * kmax
        out.append({"kind": "state", "time": float(train_times[i]), "source": int(i),
                    "c2w": camera_c2w(scene, float(train_times[i])), "states": states})
    for fr in out:
        fr["novelty"] = float(np.min(np.max(np.abs(train_states - fr["states"]), axis=-1)))
    return out


def _array_digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _prepare_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"synth: {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"synth: {out} is not empty (pass overwrite=True / --overwrite to replace it)")


def _install(tmp: Path, out: Path) -> None:
    """Move the finished tmp folder to `out` (replacing it), keeping `out` intact until the swap."""
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{uuid.uuid4().hex[:8]}")
        os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        if old is not None:
            os.replace(old, out)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def sequence_flow(scene: SynthScene, states: Float[np.ndarray, "T K"], viewmats: Float[np.ndarray, "T 4 4"],
                  renders: Renders) -> dict[str, np.ndarray]:
    """Ground-truth flows between consecutive frames of a rendered sequence (see `ground_truth_flow`).

    Returns:
        dict with flow, camera_flow, object_flow [T-1, H, W, 2] float32, flow_valid,
        flow_occluded [T-1, H, W] bool, and moving [T-1, K] bool (object k's state changes).
    """
    t, h, w = renders.depth.shape
    out = {
        "flow": np.zeros((t - 1, h, w, 2), np.float32),
        "camera_flow": np.zeros((t - 1, h, w, 2), np.float32),
        "object_flow": np.zeros((t - 1, h, w, 2), np.float32),
        "flow_valid": np.zeros((t - 1, h, w), bool),
        "flow_occluded": np.zeros((t - 1, h, w), bool),
        "moving": np.abs(np.diff(states, axis=0)) > 0,
    }
    transforms = [_object_transforms(scene, s) for s in states]
    for i in range(t - 1):
        motions = np.einsum("kij,kjl->kil", transforms[i + 1], _rigid_inv(transforms[i]))
        motions[1:][~out["moving"][i]] = np.eye(4)  # resting objects: exactly the identity
        g = ground_truth_flow(renders.depth[i], renders.object_id[i], scene.K, viewmats[i], viewmats[i + 1],
                              motions, depth1=renders.depth[i + 1])
        for name in ("flow", "camera_flow", "object_flow"):
            out[name][i] = g[name]
        out["flow_valid"][i], out["flow_occluded"][i] = g["valid"], g["occluded"]
    return out


_FILES_DOC = {
    "labels.npy": "[N] int32 per-Gaussian label, 0 = static, k = object k (label order = objects)",
    "canonical.npz": "canonical (all states 0) Gaussians: means, quats (wxyz), scales, opacities (activated), "
                     "colors, labels",
    "train/depth.npy": "[T, H, W] float32 expected camera z-depth (sum T a z / alpha), 0 = none",
    "train/alpha.npy": "[T, H, W] float32 accumulated opacity",
    "train/object_id.npy": "[T, H, W] int16 argmax of composited one-hot labels; -1 where alpha < 0.5",
    "train/valid.npy": "[T, H, W] bool alpha >= 0.5",
    "train/flow.npy": "[T-1, H, W, 2] float32 optical flow frame i -> i+1 on frame i's grid (dx, dy)",
    "train/camera_flow.npy": "[T-1, H, W, 2] float32 flow of the point held static (true poses)",
    "train/object_flow.npy": "[T-1, H, W, 2] float32 flow - camera_flow (0 on static pixels)",
    "train/flow_valid.npy": "[T-1, H, W] bool where the three flows are defined",
    "train/flow_occluded.npy": "[T-1, H, W] bool valid, but leaves the image or is hidden in frame i+1",
    "train/moving.npy": "[T-1, K] bool object k's state changes between frames i and i+1",
    "train/states.npy": "[T, K] float32 object states in [0, 1]",
    "train/centres.npy": "[T, K, 3] float32 mean of each object's deformed Gaussians",
    "train/times.npy": "[T] float64 times in [0, 1]",
    "train/gains.npy": "[T] float32 global lighting gain applied to the RGB",
    "train/Ks.npy": "[T, 3, 3] float64 intrinsics",
    "train/viewmats_true.npy": "[T, 4, 4] float64 true OpenCV world-to-camera (images rendered from them)",
    "train/viewmats_written.npy": "[T, 4, 4] float64 the (possibly noisy) poses in transforms_train.json",
    "test/*": "depth, alpha, object_id, valid, states, centres, times, gains, Ks, viewmats_true as for train; "
              "kind [T'] int8 (0 = novel view at a training time, 1 = novel state combination from a training "
              "camera); source_index [T'] the training frame used",
}


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0, 1) * 255).astype(np.uint8)


def _save_split(folder: Path, arrays: dict[str, np.ndarray]) -> None:
    folder.mkdir(parents=True)
    for name, arr in arrays.items():
        np.save(folder / f"{name}.npy", arr)


def _write_all(tmp: Path, scene: SynthScene, train: dict[str, Any], tests: list[dict[str, Any]],
               te: Renders | None) -> None:
    """Images, transforms json and gt/ of a generated scene into `tmp`."""
    from fgjax.data.loaders import write_transforms

    cfg = scene.cfg
    n = cfg.frames
    info = {"generator": GENERATOR, "scene": "fgjax-synth", "seed": cfg.seed}
    tr: Renders = train.pop("renders")
    write_transforms(tmp, "train", _to_u8(tr.rgb), train["Ks"], train["viewmats_written"], train["times"],
                     extra=dict(info, split="train"), frame_names=[f"train_{i:05d}" for i in range(n)])
    counters = {"view": 0, "state": 0}
    names = []
    for f in tests:
        names.append(f"test_{f['kind']}_{counters[f['kind']]:03d}")
        counters[f["kind"]] += 1
    gt = tmp / "gt"
    gt.mkdir()
    np.save(gt / "labels.npy", scene.labels.astype(np.int32))
    np.savez(gt / "canonical.npz", means=scene.means.astype(np.float32), quats=scene.quats.astype(np.float32),
             scales=scene.scales.astype(np.float32), opacities=scene.opacities.astype(np.float32),
             colors=scene.colors.astype(np.float32), labels=scene.labels.astype(np.int32))
    _save_split(gt / "train", {"depth": tr.depth, "alpha": tr.alpha, "object_id": tr.object_id, "valid": tr.valid,
                               **train})
    if tests and te is not None:
        vm = _rigid_inv(np.stack([f["c2w"] for f in tests]))
        times = np.array([f["time"] for f in tests])
        ks = np.tile(scene.K, (len(tests), 1, 1))
        write_transforms(tmp, "test", _to_u8(te.rgb), ks, vm, times, frame_names=names,
                         extra=dict(info, split="test", test_frame_kinds=[f["kind"] for f in tests]))
        states = np.stack([f["states"] for f in tests])
        _save_split(gt / "test", {
            "depth": te.depth, "alpha": te.alpha, "object_id": te.object_id, "valid": te.valid,
            "states": states.astype(np.float32), "centres": object_centres(scene, states).astype(np.float32),
            "times": times, "gains": _lighting_gains(cfg, times).astype(np.float32), "Ks": ks, "viewmats_true": vm,
            "kind": np.array([_TEST_VIEW if f["kind"] == "view" else _TEST_STATE for f in tests], np.int8),
            "source_index": np.array([f["source"] for f in tests], np.int32),
        })
    meta = {
        "generator": GENERATOR,
        "format_version": FORMAT_VERSION,
        "config": cfg.to_dict(),
        "units": "scene units; world z up, floor z = 0, room x, y in [-1.6, 1.6], z in [0, 1.6]",
        "camera_convention": "OpenCV viewmats (world-to-camera); transforms_*.json hold OpenGL c2w",
        "n_gaussians": len(scene.means),
        "n_gaussians_per_label": np.bincount(scene.labels, minlength=scene.num_objects + 1).tolist(),
        "objects": [o.to_dict() for o in scene.objects],
        "min_separation": scene.min_separation,
        "close_pair": [1, 2] if cfg.close_pair else None,
        "close_gap": scene.close_gap,
        "test_frames": [
            {"name": nm, "kind": f["kind"], "time": f["time"], "source_index": f["source"],
             "states": f["states"].tolist(), "novelty": f["novelty"]}
            for nm, f in zip(names, tests, strict=True)
        ],
        "digest": _array_digest(_to_u8(tr.rgb), train["flow"]),
        "files": _FILES_DOC,
        "flow_note": "flow = pi_{i+1}(T_k(s_{i+1}) T_k(s_i)^-1 X) - m with X back-projected from the composited "
                     "(expected) depth of frame i; approximate at object boundaries where the composite mixes "
                     "surfaces",
        "lighting_note": "rgb = clip(render * gain(t)), gain(t) = 1 - a smoothstep((t - 0.3) / 0.4)",
    }
    (gt / "meta.json").write_text(json.dumps(meta, indent=2), encoding="utf-8")


def generate(
    cfg: SynthConfig,
    out_dir: str | os.PathLike,
    *,
    overwrite: bool = False,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Generate a synthetic scene with ground truth into `out_dir` (atomically).

    Layout (D-NeRF/nerfstudio style, read by `fgjax.data.loaders.load_scene`):
      ``transforms_train.json``, ``transforms_test.json`` (per frame file_path, OpenGL c2w
      ``transform_matrix``, ``time``, fl_x, fl_y, cx, cy, w, h; top level camera_angle_x),
      ``images/train_00000.png ...``, ``images/test_view_000.png``, ``images/test_state_000.png``,
      and ``gt/``: ``meta.json`` (config, objects, schedules, test frame kinds, file list),
      ``labels.npy`` [N], ``canonical.npz``, ``train/*.npy``, ``test/*.npy`` (see meta.json).

    Everything is written to a temporary folder next to `out_dir` that is renamed at the end, so
    a failed run leaves nothing behind (nor any parent folder it created).

    Args:
        cfg: the options.
        out_dir: destination folder; must be absent or empty unless `overwrite`.
        overwrite: replace a non-empty `out_dir`.
        progress: called with one-line progress messages.

    Returns:
        The output folder (absolute).

    Raises:
        FileExistsError: `out_dir` is a file, or a non-empty folder without `overwrite`.
    """
    out = Path(out_dir).absolute()
    _prepare_out(out, overwrite)
    say = progress or (lambda msg: None)
    t_start = time.perf_counter()

    def frame_progress(split):
        def cb(i, total):
            if i == total or i % max(1, total // 10) == 0:
                say(f"synth: {split} frame {i}/{total} ({time.perf_counter() - t_start:.1f} s)")
        return cb

    made = [d for d in reversed([out.parent, *out.parent.parents]) if not d.exists()]
    for d in made:
        d.mkdir()
    tmp = out.with_name(f".{out.name}.synth-tmp-{uuid.uuid4().hex[:8]}")
    try:
        tmp.mkdir()
        scene = make_scene(cfg)
        rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 0xCA3E]))
        times = np.arange(cfg.frames) / (cfg.frames - 1)
        states = scene_states(scene, times)
        c2w_true = np.stack([camera_c2w(scene, float(t)) for t in times])
        vm_true = _rigid_inv(c2w_true)
        gains = _lighting_gains(cfg, times)
        say(f"synth: {len(scene.means)} Gaussians ({int(np.sum(scene.labels > 0))} on {scene.num_objects} "
            f"movable parts), {cfg.frames} training frames at {cfg.width}x{cfg.height}")
        tr = render_sequence(scene, vm_true, states, gains=gains, progress=frame_progress("train"))
        train = {
            "renders": tr, **sequence_flow(scene, states, vm_true, tr),
            "states": states.astype(np.float32), "centres": object_centres(scene, states).astype(np.float32),
            "times": times, "gains": gains.astype(np.float32), "Ks": np.tile(scene.K, (cfg.frames, 1, 1)),
            "viewmats_true": vm_true, "viewmats_written": _noisy_viewmats(cfg, c2w_true, rng),
        }
        tests = _test_frames(scene, times, states, rng)
        te = None
        if tests:
            te_times = np.array([f["time"] for f in tests])
            te = render_sequence(scene, _rigid_inv(np.stack([f["c2w"] for f in tests])),
                                 np.stack([f["states"] for f in tests]), gains=_lighting_gains(cfg, te_times),
                                 progress=frame_progress("test"))
        _write_all(tmp, scene, train, tests, te)
        _prepare_out(out, overwrite)  # re-check: someone may have filled it meanwhile
        _install(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        for d in reversed(made):  # parent folders this call created
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    say(f"synth: wrote {out} in {time.perf_counter() - t_start:.1f} s")
    return out


# ============================================================================ command line


def _parser() -> argparse.ArgumentParser:
    d = SynthConfig()
    p = argparse.ArgumentParser(prog="fgjax synth", description="Generate a synthetic articulated scene with "
                                "ground truth (depth, flow, object ids, states, centres).",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", required=True, help="output folder (must be absent or empty unless --overwrite)",
                   default=argparse.SUPPRESS)
    p.add_argument("--objects", default=",".join(d.objects),
                   help=f"comma-separated kinds from {{{','.join(OBJECT_KINDS)}}}, at most {MAX_OBJECTS}")
    p.add_argument("--width", type=int, default=d.width, help="image width in pixels")
    p.add_argument("--height", type=int, default=d.height, help="image height in pixels")
    p.add_argument("--frames", type=int, default=d.frames, help="number of training frames")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of every random choice")
    p.add_argument("--pose-noise-deg", type=float, default=d.pose_noise_deg,
                   help="std of rotation noise on the written training poses (degrees)")
    p.add_argument("--pose-noise-trans", type=float, default=d.pose_noise_trans,
                   help="std of translation noise on the written training poses (fraction of scene size 3.2)")
    p.add_argument("--lighting-change", type=float, nargs="?", const=0.3, default=d.lighting_change,
                   help="brightness drop over the sequence (flag alone: 0.3)")
    p.add_argument("--close-pair", action="store_true", help="put objects 1 and 2 side by side, --close-gap apart")
    p.add_argument("--close-gap", type=float, default=d.close_gap, help="gap of the close pair (scene units)")
    p.add_argument("--test-views", type=int, default=d.test_views,
                   help="test frames from other camera positions at training times")
    p.add_argument("--test-states", type=int, default=d.test_states,
                   help="test frames with object-state combinations unseen in training")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    """SynthConfig from parsed `fgjax synth` arguments (ValueError on bad values)."""
    objs = tuple(o.strip() for o in str(args.objects).split(",") if o.strip())
    return SynthConfig(
        objects=objs, width=args.width, height=args.height, frames=args.frames, seed=args.seed,
        pose_noise_deg=args.pose_noise_deg, pose_noise_trans=args.pose_noise_trans,
        lighting_change=args.lighting_change, close_pair=args.close_pair, close_gap=args.close_gap,
        test_views=args.test_views, test_states=args.test_states,
    )


def main(argv: list[str] | None = None) -> int:
    """``fgjax synth``: generate a scene; prints where things went. Returns the exit status."""
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        cfg = config_from_args(args)
    except ValueError as e:
        print(f"fgjax synth: error: {e}", file=sys.stderr)
        return 2
    say = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    try:
        out = generate(cfg, args.out, overwrite=args.overwrite, progress=say)
    except (FileExistsError, ValueError) as e:
        print(f"fgjax synth: error: {e}", file=sys.stderr)
        return 2
    print(f"scene:        {out}")
    print(f"train:        {out / 'transforms_train.json'}")
    if (out / "transforms_test.json").exists():
        print(f"test:         {out / 'transforms_test.json'}")
    print(f"images:       {out / 'images'}")
    print(f"ground truth: {out / 'gt'} (see gt/meta.json)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
