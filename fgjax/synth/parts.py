"""Building blocks of the synthetic scenes: numpy rigid-motion helpers, surface samplers, textures,
the room and the four object kinds in their local frames.

All of it is numpy float64. The quaternion and rotation helpers here are kept apart from the JAX ones in
`fgjax.geometry` so that the generated scenes stay bit-for-bit reproducible.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

ROOM_HALF = 1.6  # room spans [-1.6, 1.6] in x and y
ROOM_HEIGHT = 1.6
ROOM_SIZE = 2 * ROOM_HALF  # "scene size" for the translational pose noise


def normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by `angle` (rad) about the unit `axis`."""
    a = normalize(np.asarray(axis, dtype=np.float64))
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
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


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
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


def quat_from_z(n: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz rotations taking the local z axis to the unit normals n [N, 3]."""
    n = normalize(np.asarray(n, dtype=np.float64))
    w = 1.0 + n[:, 2]  # (1 + z.n, z x n) normalised = rotation z -> n
    q = np.stack([w, -n[:, 1], n[:, 0], np.zeros_like(w)], axis=-1)
    flip = w < 1e-8  # n = -z: half turn about x
    q[flip] = np.array([0.0, 1.0, 0.0, 0.0])
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def rigid(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def rigid_inv(m: np.ndarray) -> np.ndarray:
    r = m[..., :3, :3]
    out = np.zeros_like(m)
    out[..., :3, :3] = np.swapaxes(r, -1, -2)
    out[..., :3, 3] = -np.einsum("...ji,...j->...i", r, m[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def apply_rigid(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ m[:3, :3].T + m[:3, 3]


# ============================================================================ geometry builders


@dataclasses.dataclass
class Part:
    """Gaussian centres, normals and colours of one surface group (local or world frame)."""

    points: np.ndarray  # [n, 3]
    normals: np.ndarray  # [n, 3]
    colors: np.ndarray  # [n, 3]
    spacing: float

    def transformed(self, m: np.ndarray) -> Part:
        return Part(apply_rigid(m, self.points), self.normals @ m[:3, :3].T, self.colors, self.spacing)


def box_surface(lo, hi, spacing: float, skip: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray]:
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


def sphere_surface(centre, radius: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
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
        k = normalize(rng.normal(size=3)) * (2 * math.pi / scale) * rng.uniform(0.6, 1.4)
        out += np.sin(p @ k + rng.uniform(0, 2 * math.pi))
    return out / n


def texture(p: np.ndarray, base, rng: np.random.Generator, *, checker: float, contrast: float = 0.18,
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


def build_room(rng: np.random.Generator, spacing: float) -> Part:
    """Floor and back/left/right walls (the front wall is behind the camera and not built)."""
    h, r = ROOM_HALF, ROOM_HEIGHT
    groups = []
    # floor: wooden checker
    p, n = box_surface([-h, -h, 0.0], [h, h, 0.0], spacing, skip=("-x", "+x", "-y", "+y", "+z"))
    groups.append((p, n, texture(p, (0.62, 0.45, 0.30), rng, checker=0.25, second=(0.45, 0.30, 0.18))))
    # walls: each its own colour, stripes via the checker, and a few "posters"
    wall_specs = [
        (([-h, h, 0.0], [h, h, r]), ("-x", "+x", "-z", "+z", "+y"), (0.55, 0.62, 0.70)),  # back, normal -y
        (([-h, -h, 0.0], [-h, h, r]), ("-y", "+y", "-z", "+z", "-x"), (0.70, 0.66, 0.52)),  # left, normal +x
        (([h, -h, 0.0], [h, h, r]), ("-y", "+y", "-z", "+z", "+x"), (0.60, 0.70, 0.58)),  # right, normal -x
    ]
    for (lo, hi), skip, base in wall_specs:
        p, n = box_surface(lo, hi, spacing, skip=skip)
        col = texture(p, base, rng, checker=0.3, contrast=0.22)
        for _ in range(4):  # posters: rectangles of random colour
            c = p[rng.integers(len(p))]
            half = rng.uniform(0.12, 0.3, size=3)
            inside = np.all(np.abs(p - c) <= half, axis=-1) & (p[:, 2] > 0.15)
            col[inside] = np.clip(rng.uniform(0.1, 0.9, size=3) + rng.normal(scale=0.06, size=(inside.sum(), 3)), 0, 1)
        groups.append((p, n, col))
    return Part(*(np.concatenate([g[i] for g in groups]) for i in range(3)), spacing=spacing)


@dataclasses.dataclass
class LocalObject:
    """An object in its local frame (origin at the footprint centre on the floor, front facing -y)."""

    body: Part | None
    part: Part
    width: float  # x extent [-width/2, width/2] of the part (and body) in the canonical state
    depth: float  # y extent of the footprint including swept space in front (for layout)
    kin: dict[str, Any]  # kinematics in the local frame

    @property
    def front(self) -> float:
        """Smallest y of the moving part (its front face) in the canonical state."""
        return float(self.part.points[:, 1].min())


def build_door(rng, sp: float, palette) -> LocalObject:
    w, d, h, th = 0.32, 0.28, 0.5, 0.02
    bsp = 1.6 * sp
    bp, bn = box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("-y",))
    body = Part(bp, bn, texture(bp, palette[1], rng, checker=0.08), bsp)
    pp, pn = box_surface([-w / 2, -d / 2 - th, 0.0], [w / 2, -d / 2, h], sp)
    part = Part(pp, pn, texture(pp, palette[0], rng, checker=0.05, contrast=0.3), sp)
    kin = {"pivot": np.array([-w / 2, -d / 2 - th, 0.0]), "axis": np.array([0.0, 0.0, -1.0]),
           "max_angle": math.radians(85.0)}
    return LocalObject(body, part, w, d + w, kin)


def build_drawer(rng, sp: float, palette) -> LocalObject:
    w, d, h, th, inset = 0.36, 0.30, 0.30, 0.02, 0.03
    bsp = 1.6 * sp
    bp, bn = box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("-y",))
    body = Part(bp, bn, texture(bp, palette[1], rng, checker=0.08), bsp)
    fp, fn = box_surface([-w / 2, -d / 2 - th, 0.0], [w / 2, -d / 2, h], sp)  # front panel
    tp, tn = box_surface([-w / 2 + inset, -d / 2, inset], [w / 2 - inset, d / 2 - inset, h - 2 * inset], sp,
                          skip=("-y", "+z"))  # open tray behind the panel
    pp, pn = np.concatenate([fp, tp]), np.concatenate([fn, tn])
    col = texture(pp, palette[0], rng, checker=0.05, contrast=0.3)
    part = Part(pp, pn, col, sp)
    travel = 0.75 * d
    kin = {"direction": np.array([0.0, -1.0, 0.0]), "distance": travel}
    return LocalObject(body, part, w, d + travel, kin)


def build_lid(rng, sp: float, palette) -> LocalObject:
    w, d, h, th = 0.36, 0.26, 0.24, 0.02
    bsp = 1.6 * sp
    bp, bn = box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("+z",))
    body = Part(bp, bn, texture(bp, palette[1], rng, checker=0.08), bsp)
    pp, pn = box_surface([-w / 2, -d / 2, h], [w / 2, d / 2, h + th], sp)
    part = Part(pp, pn, texture(pp, palette[0], rng, checker=0.05, contrast=0.3), sp)
    kin = {"pivot": np.array([0.0, d / 2, h]), "axis": np.array([-1.0, 0.0, 0.0]),
           "max_angle": math.radians(75.0)}
    return LocalObject(body, part, w, d, kin)


def build_free(rng, sp: float, palette, *, straight: bool) -> LocalObject:
    r = 0.09
    pp, pn = sphere_surface([0.0, 0.0, r], r, sp)
    part = Part(pp, pn, texture(pp, palette[0], rng, checker=0.045, contrast=0.45), sp)
    length = 0.4
    wiggle = 0.0 if straight else 0.12
    kin = {"pivot": np.array([0.0, 0.0, r]), "direction": np.array([0.0, -1.0, 0.0]),
           "lateral": np.array([1.0, 0.0, 0.0]), "distance": length, "wiggle": wiggle, "radius": r,
           "axis": np.array([1.0, 0.0, 0.0])}  # rolling towards -y turns about +x
    return LocalObject(None, part, 2 * r, 2 * r + length, kin)


PALETTE = [
    ((0.85, 0.25, 0.20), (0.40, 0.32, 0.28)),
    ((0.20, 0.55, 0.85), (0.35, 0.35, 0.40)),
    ((0.95, 0.75, 0.15), (0.30, 0.38, 0.30)),
    ((0.60, 0.30, 0.80), (0.42, 0.36, 0.30)),
    ((0.20, 0.80, 0.45), (0.38, 0.30, 0.34)),
    ((0.95, 0.50, 0.75), (0.32, 0.34, 0.38)),
]
