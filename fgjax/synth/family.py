"""The scene family: a random articulated scene per seed (``fgjax synth --family SEED``).

The hand-made scenes (`fgjax.synth.scene.make_scene`) share one generator's habits: doors hang plumb, parts
are flat rectangles hinged on an edge, each part is coloured unlike its cabinet, every part opens and closes
again, the camera is level. A seed of the family draws each of these instead, so that a default chosen on
some seeds can be checked on others (docs/benchmarks.md, "Scene family": seeds 0-5 tune, 6-11 validate).

Per seed (`family_config` draws the `SynthConfig`, `make_family_scene` the scene; everything comes from
``numpy.random.default_rng(SeedSequence([seed, 0xFA417]))``, so the same seed gives the same scene bit for
bit, and any non-negative seed is a scene):

- room: random wall and floor colours and texture scales, 0-3 static distractors (boxes and balls);
- 1 to 4 moving parts, each one of (`FAMILY_KINDS`):
  ``hinge``: a panel on a box, hinged on one of its edges: a door (vertical axis), a flap or lid (horizontal
  axis), or either on a box tilted by up to 25 degrees about its front normal (a tilted axis);
  ``slide``: a drawer out of its box, a lid sliding sideways, or a panel sliding up, along a direction jittered
  by up to 20 degrees;
  ``spin``: a textured disc turning about its own axis through its centre (a wheel, knob or fan) on a box's
  front or top face, 120-300 degrees;
  ``free``: a box or ball with no joint, translated 0.2-0.45 units along a curved path and rotated about a
  random axis by 20-120 degrees;
  and, with probability 0.3 for each part after the first while a hinged or sliding panel is free, a part
  attached to another part (a small flap or a knob on a door, drawer front or flap, ``SynthObject.parent``),
  which moves with its parent and about its own joint;
- sizes: boxes 0.22-0.5 units; panels cover their face; discs 0.06-0.13 units in radius;
- colour: each part's own colour, or (probability 0.3) the colour and texture of the box it hangs on;
- schedule (`_family_schedule`): opens and closes again, opens and stays open, or moves twice; windows of
  0.3-0.6 of the sequence start anywhere in [0.03, 0.55], so parts overlap in time;
- camera (`fgjax.synth.scene._path_c2w`): an orbit of 20-90 degrees, a dolly (moving 25-40 % closer), a
  hand-held path (a 10-30 degree orbit, 0.02-0.04 units of jitter, roll jitter up to 5 degrees) or a still
  camera; every path has a fixed roll of up to 5 degrees and a height of 0.55-1.3 units, at a distance that
  frames every part's swept volume;
- test views: at times half-way between two training frames, seen from 3 degrees off the path, 0.05 units
  higher and closer (the hand-made scenes' 10 degrees would be far outside a still or short path);
- images: 128x96 to 320x240 (4:3), 40 to 60 frames, focal 0.65-1.0 x width; a lighting change (a up to 0.2)
  in 25 % of the scenes.

Distinct objects (and distractors) are at least `MIN_SEPARATION` apart at every state, a part attached to
another excepted (it touches its parent by construction). Units, frames and ground truth are those of
`fgjax.synth` (world z up, floor z = 0, OpenCV cameras).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from fgjax.synth.parts import (
    ROOM_HALF,
    ROOM_HEIGHT,
    Part,
    axis_angle_matrix,
    box_surface,
    normalize,
    rigid,
    sphere_surface,
    texture,
)
from fgjax.synth.scene import (
    FAMILY_KINDS,
    SynthConfig,
    SynthObject,
    SynthScene,
    compose_transforms,
    gaussians_of_parts,
    placed_object,
)

__all__ = ["family_config", "make_family_scene", "FAMILY_SIZES", "MIN_SEPARATION", "parse_seeds"]

FAMILY_SIZES = ((128, 96), (160, 120), (192, 144), (224, 168), (256, 192), (320, 240))
MIN_SEPARATION = 0.12  # scene units between distinct objects at every state
_TAG = 0xFA417


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), _TAG, stream]))


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``"0-5"``, ``"6,8,10"`` or ``"0-3,12"`` (inclusive ranges); ValueError naming the text."""
    out: list[int] = []
    for piece in str(text).split(","):
        piece = piece.strip()
        try:
            if "-" in piece:
                a, b = (int(x) for x in piece.split("-", 1))
                if b < a:
                    raise ValueError
                out.extend(range(a, b + 1))
            elif piece:
                out.append(int(piece))
        except ValueError:
            raise ValueError(f"seeds: cannot read {piece!r} in {text!r} (use e.g. 0-5 or 6,8,10)") from None
    if not out or min(out) < 0:
        raise ValueError(f"seeds: need one or more non-negative seeds, got {text!r}")
    return out


def family_config(seed: int, *, size: tuple[int, int] | None = None, frames: int | None = None,
                  depth_maps: bool = False) -> SynthConfig:
    """The `SynthConfig` of family scene `seed`: its resolution, frame count, part kinds and lighting.

    Args:
        seed: any non-negative integer.
        size: (width, height) instead of the seed's own (the scene's geometry and motion stay the seed's).
        frames: number of training frames instead of the seed's own.
        depth_maps: write each frame's depth as a measured one (`SynthConfig.depth_maps`: an RGB-D scene).
    """
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"family: the seed must be a non-negative integer, got {seed!r}")
    rng = _rng(seed, 0)
    w, h = FAMILY_SIZES[int(rng.integers(len(FAMILY_SIZES)))]
    n_frames = int(rng.integers(40, 61))
    lighting = float(rng.uniform(0.05, 0.2)) if rng.uniform() < 0.25 else 0.0
    kinds = tuple(k for k, _ in _draw_parts(seed))
    if size is not None:
        w, h = (int(x) for x in size)
    return SynthConfig(objects=kinds, width=w, height=h, frames=int(frames or n_frames), seed=int(seed),
                       lighting_change=lighting, family=int(seed), depth_maps=bool(depth_maps))


# ============================================================================ drawing the parts


def _draw_parts(seed: int) -> list[tuple[str, int]]:
    """[(kind, parent)] of the seed's moving parts, in label order (parent 0 = none, else a label)."""
    rng = _rng(seed, 1)
    n = int(rng.integers(1, 5))
    out: list[tuple[str, int]] = []
    hosts: list[int] = []  # labels of hinged / sliding panels a part may be attached to
    for i in range(n):
        if hosts and rng.uniform() < 0.3:
            parent = hosts.pop(int(rng.integers(len(hosts))))
            out.append(("hinge" if rng.uniform() < 0.5 else "spin", parent))
            continue
        kind = str(rng.choice(["hinge", "slide", "spin", "free"], p=[0.35, 0.25, 0.2, 0.2]))
        out.append((kind, 0))
        if kind in ("hinge", "slide"):
            hosts.append(i + 1)
    return out


def _colour(rng: np.random.Generator, sat: tuple[float, float] = (0.35, 0.9)) -> np.ndarray:
    """A random RGB colour in [0.1, 0.95] (hue uniform, saturation in `sat`, value in [0.45, 0.95])."""
    hue, sat, val = rng.uniform(), rng.uniform(*sat), rng.uniform(0.45, 0.95)
    k = (np.array([5.0, 3.0, 1.0]) + hue * 6.0) % 6.0
    return np.clip(val - val * sat * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0), 0.1, 0.95)


@dataclasses.dataclass
class _Built:
    """One object in its local frame (origin at the footprint centre on the floor, front facing -y)."""

    body: Part | None
    parts: list[tuple[int, str, Part, dict[str, Any], int]]  # (label, kind, part, kinematics, parent label or 0)
    radius: float  # footprint radius including the swept space (for the layout)


def _panel_texture(rng, pts, colour, body_colour, like_body: bool):
    if like_body:
        return texture(pts, body_colour, rng, checker=0.08)
    return texture(pts, colour, rng, checker=float(rng.uniform(0.03, 0.07)), contrast=float(rng.uniform(0.2, 0.45)))


def _disc(rng, centre, normal, radius: float, sp: float, colour) -> Part:
    """A disc of thickness 0.02 (both faces and the rim) about `normal` through `centre`, coloured in four
    sectors (so that its turning shows)."""
    nrm = normalize(np.asarray(normal, np.float64))
    u = normalize(np.cross(nrm, [0.0, 0.0, 1.0]) if abs(nrm[2]) < 0.9 else np.cross(nrm, [1.0, 0.0, 0.0]))
    v = np.cross(nrm, u)
    n_r = max(2, math.ceil(radius / sp))
    pts, nrms, ang = [], [], []
    for side in (0.0, 0.02):
        for i in range(n_r + 1):
            r = radius * i / n_r
            n_a = max(1, math.ceil(2 * math.pi * r / sp))
            a = np.arange(n_a) * 2 * math.pi / n_a
            p = np.asarray(centre) + side * nrm + r * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v)
            pts.append(p)
            nrms.append(np.tile(nrm if side > 0 else -nrm, (n_a, 1)))
            ang.append(a)
    n_a = max(8, math.ceil(2 * math.pi * radius / sp))
    a = np.arange(n_a) * 2 * math.pi / n_a
    radial = np.cos(a)[:, None] * u + np.sin(a)[:, None] * v
    pts.append(np.asarray(centre) + 0.01 * nrm + radius * radial)
    nrms.append(radial)
    ang.append(a)
    p, n, a = np.concatenate(pts), np.concatenate(nrms), np.concatenate(ang)
    col = texture(p, colour, rng, checker=0.04, contrast=0.2)
    sector = (np.floor(a / (math.pi / 2)).astype(int) % 2) == 1
    col[sector] = np.clip(1.0 - col[sector] * 0.8, 0.05, 0.95)
    return Part(p, n, col, sp)


def _build_hinge(rng, sp: float, colour, body_colour, like_body: bool) -> _Built:
    w, d, h, th = rng.uniform(0.24, 0.5), rng.uniform(0.2, 0.4), rng.uniform(0.22, 0.55), 0.02
    bsp = 1.6 * sp
    if rng.uniform() < 0.7:  # a panel on the front face, hinged on one of its four edges
        bp, bn = box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("-y",))
        pp, pn = box_surface([-w / 2, -d / 2 - th, 0.0], [w / 2, -d / 2, h], sp)
        edge = str(rng.choice(["left", "right", "bottom", "top"]))
        y = -d / 2 - th
        pivot, axis, hi = {"left": ([-w / 2, y, 0.0], [0, 0, -1], 110), "right": ([w / 2, y, 0.0], [0, 0, 1], 110),
                           "bottom": ([0.0, y, 0.0], [1, 0, 0], 85), "top": ([0.0, y, h], [-1, 0, 0], 100)}[edge]
        reach = max(w, h)
    else:  # a lid on the top face, hinged on its back, left or right edge
        bp, bn = box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("+z",))
        pp, pn = box_surface([-w / 2, -d / 2, h], [w / 2, d / 2, h + th], sp)
        edge = str(rng.choice(["back", "left", "right"]))
        pivot, axis = {"back": ([0.0, d / 2, h], [-1, 0, 0]), "left": ([-w / 2, 0.0, h], [0, -1, 0]),
                       "right": ([w / 2, 0.0, h], [0, 1, 0])}[edge]
        hi, reach = 100, max(w, d)
    body = Part(bp, bn, texture(bp, body_colour, rng, checker=0.08), bsp)
    part = Part(pp, pn, _panel_texture(rng, pp, colour, body_colour, like_body), sp)
    kin = {"pivot": np.array(pivot, np.float64), "axis": np.array(axis, np.float64),
           "max_angle": math.radians(rng.uniform(50, hi))}
    return _Built(body, [(0, "hinge", part, kin, 0)], 0.5 * math.hypot(w, d) + reach)


def _build_slide(rng, sp: float, colour, body_colour, like_body: bool) -> _Built:
    w, d, h, th = rng.uniform(0.26, 0.5), rng.uniform(0.22, 0.4), rng.uniform(0.2, 0.5), 0.02
    bsp = 1.6 * sp
    style = str(rng.choice(["drawer", "sideways", "up"], p=[0.6, 0.2, 0.2]))
    if style == "drawer":
        inset = 0.03
        bp, bn = box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("-y",))
        fp, fn = box_surface([-w / 2, -d / 2 - th, 0.0], [w / 2, -d / 2, h], sp)
        tp, tn = box_surface([-w / 2 + inset, -d / 2, inset], [w / 2 - inset, d / 2 - inset, h - 2 * inset], sp,
                              skip=("-y", "+z"))
        pp, pn = np.concatenate([fp, tp]), np.concatenate([fn, tn])
        direction, dist = np.array([0.0, -1.0, 0.0]), rng.uniform(0.45, 0.8) * d
    elif style == "sideways":
        bp, bn = box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("+z",))
        pp, pn = box_surface([-w / 2, -d / 2, h], [w / 2, d / 2, h + th], sp)
        direction, dist = np.array([1.0 if rng.uniform() < 0.5 else -1.0, 0.0, 0.0]), rng.uniform(0.4, 0.8) * w
    else:
        bp, bn = box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp, skip=("-y",))
        pp, pn = box_surface([-w / 2, -d / 2 - 2 * th, 0.0], [w / 2, -d / 2 - th, h], sp)
        direction, dist = np.array([0.0, 0.0, 1.0]), rng.uniform(0.4, 0.8) * h
    tilt = axis_angle_matrix(normalize(rng.normal(size=3)), math.radians(rng.uniform(0, 20)))
    body = Part(bp, bn, texture(bp, body_colour, rng, checker=0.08), bsp)
    part = Part(pp, pn, _panel_texture(rng, pp, colour, body_colour, like_body), sp)
    kin = {"direction": normalize(tilt @ direction), "distance": float(dist)}
    return _Built(body, [(0, "slide", part, kin, 0)], 0.5 * math.hypot(w, d) + dist)


def _build_spin(rng, sp: float, colour, body_colour, like_body: bool) -> _Built:
    w, d, h = rng.uniform(0.24, 0.45), rng.uniform(0.2, 0.4), rng.uniform(0.22, 0.5)
    bsp = 1.6 * sp
    bp, bn = box_surface([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], bsp)
    if rng.uniform() < 0.65:  # on the front face
        r = min(rng.uniform(0.06, 0.13), 0.5 * min(w, h) - 0.02)
        centre, normal = np.array([rng.uniform(-1, 1) * (w / 2 - r - 0.01), -d / 2 - 0.022,
                                   h / 2 + rng.uniform(-1, 1) * (h / 2 - r - 0.01)]), np.array([0.0, -1.0, 0.0])
    else:  # on the top face
        r = min(rng.uniform(0.06, 0.13), 0.5 * min(w, d) - 0.02)
        centre, normal = np.array([rng.uniform(-1, 1) * (w / 2 - r - 0.01),
                                   rng.uniform(-1, 1) * (d / 2 - r - 0.01), h + 0.002]), np.array([0.0, 0.0, 1.0])
    body = Part(bp, bn, texture(bp, body_colour, rng, checker=0.08), bsp)
    part = _disc(rng, centre, normal, r, sp, body_colour if like_body else colour)
    sign = 1.0 if rng.uniform() < 0.5 else -1.0
    kin = {"pivot": centre + 0.01 * normal, "axis": sign * normal, "max_angle": math.radians(rng.uniform(120, 300))}
    return _Built(body, [(0, "spin", part, kin, 0)], 0.5 * math.hypot(w, d))


def _build_free(rng, sp: float, colour, body_colour, like_body: bool) -> _Built:
    if rng.uniform() < 0.5:
        e = rng.uniform(0.1, 0.22, size=3)
        pp, pn = box_surface([-e[0] / 2, -e[1] / 2, 0.0], [e[0] / 2, e[1] / 2, e[2]], sp)
        centre = np.array([0.0, 0.0, e[2] / 2])
        size = float(e.max())
    else:
        r = rng.uniform(0.06, 0.12)
        pp, pn = sphere_surface([0.0, 0.0, r], r, sp)
        centre, size = np.array([0.0, 0.0, r]), 2 * r
    part = Part(pp, pn, texture(pp, colour, rng, checker=0.045, contrast=0.45), sp)
    heading = rng.uniform(0, 2 * math.pi)
    direction = np.array([math.cos(heading), math.sin(heading), 0.0])
    dist, angle = rng.uniform(0.2, 0.45), math.radians(rng.uniform(20, 120))
    kin = {"pivot": centre, "direction": direction, "lateral": np.array([-direction[1], direction[0], 0.0]),
           "distance": float(dist), "wiggle": float(rng.uniform(0.0, 0.1)), "radius": float(dist / angle),
           "axis": normalize(rng.normal(size=3))}
    return _Built(None, [(0, "free", part, kin, 0)], 0.5 * size + dist + 0.1)


def _attach(rng, sp: float, built: _Built, kind: str, colour, label: int, parent: int) -> None:
    """Add a small flap (``hinge``) or knob (``spin``) on the outer face of `built`'s first panel."""
    pts = built.parts[0][2].points
    face_y = float(pts[:, 1].min())
    lo, hi = pts.min(0), pts.max(0)
    if hi[2] - lo[2] < 0.03:  # a panel lying flat (a lid): attach on its top face
        top = float(hi[2])
        cx, cy = rng.uniform(lo[0] + 0.06, hi[0] - 0.06), rng.uniform(lo[1] + 0.06, hi[1] - 0.06)
        if kind == "spin":
            r = min(0.05, 0.4 * (hi[0] - lo[0]), 0.4 * (hi[1] - lo[1]))
            c = np.array([cx, cy, top + 0.002])
            part = _disc(rng, c, [0.0, 0.0, 1.0], r, sp, colour)
            kin = {"pivot": c, "axis": np.array([0.0, 0.0, 1.0]), "max_angle": math.radians(rng.uniform(120, 300))}
        else:
            a = 0.5 * min(hi[0] - lo[0], hi[1] - lo[1]) * rng.uniform(0.4, 0.8)
            pp, pn = box_surface([cx - a, cy - a, top], [cx + a, cy + a, top + 0.015], sp)
            part = Part(pp, pn, texture(pp, colour, rng, checker=0.03, contrast=0.4), sp)
            kin = {"pivot": np.array([cx, cy + a, top]), "axis": np.array([-1.0, 0.0, 0.0]),
                   "max_angle": math.radians(rng.uniform(60, 110))}
    else:  # a panel facing -y: attach on its front
        cx = rng.uniform(lo[0] + 0.06, hi[0] - 0.06)
        cz = rng.uniform(lo[2] + 0.06, hi[2] - 0.06)
        if kind == "spin":
            r = min(0.05, 0.4 * (hi[0] - lo[0]), 0.4 * (hi[2] - lo[2]))
            c = np.array([cx, face_y - 0.022, cz])
            part = _disc(rng, c, [0.0, -1.0, 0.0], r, sp, colour)
            kin = {"pivot": c + np.array([0.0, -0.01, 0.0]), "axis": np.array([0.0, -1.0, 0.0]),
                   "max_angle": math.radians(rng.uniform(120, 300))}
        else:
            a = 0.5 * min(hi[0] - lo[0], hi[2] - lo[2]) * rng.uniform(0.4, 0.8)
            pp, pn = box_surface([cx - a, face_y - 0.017, cz - a], [cx + a, face_y - 0.002, cz + a], sp)
            part = Part(pp, pn, texture(pp, colour, rng, checker=0.03, contrast=0.4), sp)
            kin = {"pivot": np.array([cx - a, face_y - 0.017, cz]), "axis": np.array([0.0, 0.0, -1.0]),
                   "max_angle": math.radians(rng.uniform(60, 110))}
    built.parts.append((label, kind, part, kin, parent))


_BUILDERS = {"hinge": _build_hinge, "slide": _build_slide, "spin": _build_spin, "free": _build_free}


# ============================================================================ schedules, room, camera


def _family_schedule(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Keyframes (times, states) of one part: open and close again, open and stay open, or move twice, inside
    a window of 0.3-0.6 of the sequence starting in [0.03, 0.55]; the largest state is in [0.7, 1]."""
    start = rng.uniform(0.03, 0.55)
    end = min(0.97, start + rng.uniform(0.3, 0.6))
    s_max = rng.uniform(0.7, 1.0)
    pattern = str(rng.choice(["open_close", "stay_open", "twice"], p=[0.4, 0.3, 0.3]))
    if pattern == "open_close":
        u, s = [0.0, 0.4, 0.6, 1.0], [0.0, s_max, s_max, 0.0]
    elif pattern == "stay_open":
        u, s = [0.0, 0.6], [0.0, s_max]
    else:
        mid = rng.uniform(0.3, 0.6) * s_max
        u, s = [0.0, 0.25, 0.45, 0.7, 1.0], [0.0, s_max, mid, s_max, rng.choice([0.0, s_max])]
    times = np.concatenate([[0.0], start + (end - start) * np.asarray(u), [1.0]])
    states = np.concatenate([[0.0], s, [s[-1]]])
    return times, states


def _room(rng: np.random.Generator, spacing: float) -> Part:
    """Floor and back/left/right walls with random colours and texture scales."""
    hx, r = ROOM_HALF, ROOM_HEIGHT
    specs = [(([-hx, -hx, 0.0], [hx, hx, 0.0]), ("-x", "+x", "-y", "+y", "+z")),
             (([-hx, hx, 0.0], [hx, hx, r]), ("-x", "+x", "-z", "+z", "+y")),
             (([-hx, -hx, 0.0], [-hx, hx, r]), ("-y", "+y", "-z", "+z", "-x")),
             (([hx, -hx, 0.0], [hx, hx, r]), ("-y", "+y", "-z", "+z", "+x"))]
    groups = []
    for (lo, hi), skip in specs:
        p, n = box_surface(lo, hi, spacing, skip=skip)
        base = _colour(rng, (0.1, 0.6))
        col = texture(p, base, rng, checker=float(rng.uniform(0.15, 0.4)), contrast=float(rng.uniform(0.1, 0.3)),
                       second=np.clip(base * rng.uniform(0.5, 0.9) + rng.uniform(-0.1, 0.1, 3), 0.05, 0.95))
        for _ in range(int(rng.integers(0, 5))):  # posters
            c = p[rng.integers(len(p))]
            half = rng.uniform(0.1, 0.3, size=3)
            inside = np.all(np.abs(p - c) <= half, axis=-1)
            col[inside] = np.clip(_colour(rng) + rng.normal(scale=0.06, size=(int(inside.sum()), 3)), 0, 1)
        groups.append((p, n, col))
    return Part(*(np.concatenate([g[i] for g in groups]) for i in range(3)), spacing=spacing)


def _camera(rng: np.random.Generator, points: np.ndarray, fx: float, w: int, h: int) -> dict[str, Any]:
    """A camera path (`fgjax.synth.scene._path_c2w`) that frames `points` [N, 3] (every part's swept volume)."""
    path = str(rng.choice(["orbit", "dolly", "handheld", "still"], p=[0.4, 0.2, 0.25, 0.15]))
    lo, hi = points.min(0), points.max(0)
    target = 0.5 * (lo + hi)
    target[2] = min(target[2], 0.45)
    extent = float(np.max(np.linalg.norm(points - target, axis=1)))
    half_fov = math.atan(0.5 * w / fx)
    height = rng.uniform(0.55, 1.3)
    dist = 1.05 * extent / math.sin(half_fov)  # the bounding sphere fits the horizontal field of view
    horiz = math.sqrt(max(dist**2 - (height - target[2]) ** 2, 0.25))
    horiz = min(max(horiz, 0.8), 2.6)
    sweep = math.radians({"orbit": rng.uniform(20, 90), "dolly": rng.uniform(0, 10),
                          "handheld": rng.uniform(10, 30), "still": 0.0}[path])
    azimuth = math.radians(rng.uniform(-20, 20))
    # the camera (and test views up to 10 degrees further round) stays inside the side walls (|x| <= 1.35): a
    # narrower sweep first, then a shorter distance
    test_off = math.radians(10.0)
    start = horiz * (1.2 if path == "dolly" else 1.0)
    reach = (ROOM_HALF - 0.25 - abs(float(target[0]))) / start
    if reach < 1.0:
        lim = math.asin(reach) - test_off
        if abs(azimuth) + sweep / 2 > lim:
            sweep = max(min(sweep, 2 * (lim - abs(azimuth))), math.radians(20) if path == "orbit" else 0.0)
            azimuth = math.copysign(max(0.0, min(abs(azimuth), lim - sweep / 2)), azimuth)
        worst = math.sin(min(abs(azimuth) + sweep / 2 + test_off, math.pi / 2))
        if worst > reach:
            horiz *= reach / worst
    cam = {
        "path": path, "target": target, "azimuth": azimuth, "sweep": sweep,
        "radius": horiz * (1.2 if path == "dolly" else 1.0), "radius_end": horiz * (rng.uniform(0.75, 0.9)
                                                                                    if path == "dolly" else 1.0),
        "height": height, "jitter": {"handheld": rng.uniform(0.02, 0.04), "still": 0.0}.get(path, 0.008),
        "roll_deg": rng.uniform(-5, 5), "roll_jitter_deg": rng.uniform(1.5, 5) if path == "handheld" else 0.0,
        "freqs": rng.uniform(2.0, 6.0, size=(7, 3)), "phases": rng.uniform(0.0, 2 * math.pi, size=(7, 3)),
        "weights": rng.uniform(0.5, 1.0, size=(7, 3)) / 2.25,
        # test views: half-way between two training frames, 3 degrees off the path, a little higher and closer
        "test_offset": (math.radians(3.0), 0.05, -0.05), "test_time_shift": 0.5,
    }
    return cam


# ============================================================================ the scene


def _owned_clouds(objects, means, labels, owner, sweep=np.linspace(0.0, 1.0, 5)) -> dict[int, np.ndarray]:
    """Per owner (an object and its attached parts, or a distractor): its points over a sweep of states."""
    clouds: dict[int, list[np.ndarray]] = {}
    k = len(objects)
    for s in sweep:
        tr = compose_transforms(objects, np.full(k, s))
        for o in np.unique(owner):
            if o == 0:
                continue
            sel = owner == o
            clouds.setdefault(int(o), []).append(
                np.einsum("nij,nj->ni", tr[labels[sel]][:, :3, :3], means[sel]) + tr[labels[sel]][:, :3, 3])
    return {o: np.concatenate(v) for o, v in clouds.items()}


def make_family_scene(cfg: SynthConfig) -> SynthScene:
    """The scene of family seed ``cfg.family`` (`family_config`), at ``cfg``'s resolution."""
    if cfg.family is None:
        raise ValueError("make_family_scene: SynthConfig.family is None (use fgjax.synth.make_scene)")
    seed = int(cfg.family)
    drawn = _draw_parts(seed)
    if tuple(k for k, _ in drawn) != cfg.objects:
        raise ValueError(f"make_family_scene: SynthConfig.objects {cfg.objects} are not family seed {seed}'s "
                         f"{tuple(k for k, _ in drawn)} (build the config with family_config)")
    rng = _rng(seed, 2)
    sp = cfg.object_spacing
    room = _room(rng, cfg.room_spacing)

    # the objects: each top-level part with its box, and the parts attached to it
    builts: list[_Built] = []
    owner_of_label: list[int] = []  # for each label (part), the index of its _Built
    for kind, parent in drawn:
        colour, body_colour = _colour(rng), _colour(rng)
        like = rng.uniform() < 0.3
        label = len(owner_of_label) + 1
        if parent:
            b = owner_of_label[parent - 1]
            _attach(rng, sp, builts[b], kind, body_colour if like else colour, label, parent)
            owner_of_label.append(b)
            continue
        built = _BUILDERS[kind](rng, sp, colour, body_colour, like)
        built.parts[0] = (label,) + built.parts[0][1:]
        builts.append(built)
        owner_of_label.append(len(builts) - 1)
    n_distract = int(rng.integers(0, 4))
    distractors = []
    for _ in range(n_distract):
        if rng.uniform() < 0.5:
            e = rng.uniform(0.08, 0.25, size=3)
            p, n = box_surface([-e[0] / 2, -e[1] / 2, 0.0], [e[0] / 2, e[1] / 2, e[2]], 1.6 * sp)
            size = float(np.hypot(e[0], e[1]) / 2)
        else:
            r = rng.uniform(0.05, 0.12)
            p, n = sphere_surface([0.0, 0.0, r], r, 1.6 * sp)
            size = r
        distractors.append((Part(p, n, texture(p, _colour(rng), rng, checker=0.06, contrast=0.3), 1.6 * sp), size))

    # tilt some hinged objects about their front normal (a tilted hinge axis), keeping them on the floor
    tilts = []
    for b in builts:
        tilt = np.eye(4)
        if b.parts[0][1] == "hinge" and rng.uniform() < 0.35:
            rot = axis_angle_matrix([0.0, 1.0, 0.0], math.radians(rng.uniform(-25, 25)))
            pts = np.concatenate([b.body.points, b.parts[0][2].points]) @ rot.T
            tilt = rigid(rot, np.array([0.0, 0.0, -pts[:, 2].min()]))
        tilts.append(tilt)

    # layout: objects on the floor in front of the back wall, facing the camera side, far enough apart
    sched_rng = _rng(seed, 3)
    schedules = [_family_schedule(sched_rng) for _ in drawn]
    items = [(b.radius, i) for i, b in enumerate(builts)] + [(s + 0.05, len(builts) + j)
                                                             for j, (_, s) in enumerate(distractors)]
    for _attempt in range(200):
        places: list[tuple[np.ndarray, float]] = []
        for radius, _ in items:  # the free spot nearest to the objects placed so far (a compact group)
            lim = max(ROOM_HALF - 0.15 - radius, 0.05)
            cand = np.stack([rng.uniform(-lim, lim, 40), rng.uniform(-0.6, min(lim, 1.0), 40)], axis=-1)
            centre = np.mean([q[:2, 3] for q, _ in places], axis=0) if places else np.array([0.0, 0.2])
            ok = [c for c in cand if all(np.linalg.norm(c - q[:2, 3]) > radius + r2 + 0.5 * MIN_SEPARATION
                                         for q, r2 in places)]
            xy = min(ok, key=lambda c: float(np.linalg.norm(c - centre))) if ok else cand[0]
            yaw = math.radians(rng.uniform(-40, 40))
            places.append((rigid(axis_angle_matrix([0, 0, 1], yaw), np.array([xy[0], xy[1], 0.0])), radius))
        scene = _assemble(cfg, room, builts, tilts, distractors, [p for p, _ in places], drawn, schedules, rng)
        if scene is not None:
            return scene
    raise RuntimeError(f"make_family_scene: no layout of seed {seed} keeps the objects {MIN_SEPARATION} apart")


def _assemble(cfg, room, builts, tilts, distractors, places, drawn, schedules, rng,
              lift: np.ndarray | None = None) -> SynthScene | None:
    """The scene with every object at its place, or None when two objects come closer than `MIN_SEPARATION`
    at some state or an object leaves the room. An object that would pass below the floor at some state (a
    tilted door, a flap) is raised by as much (`lift` [objects], found by a first pass)."""
    lift = np.zeros(len(builts)) if lift is None else lift
    groups: list[tuple[Part, int, int]] = [(room, 0, 0)]  # (part, label, owner)
    objects: list[SynthObject] = []
    for i, (b, tilt) in enumerate(zip(builts, tilts, strict=True)):
        m = rigid(np.eye(3), np.array([0.0, 0.0, lift[i]])) @ places[i] @ tilt
        if b.body is not None:
            groups.append((b.body.transformed(m), 0, i + 1))
        for label, kind, part, kin, parent in b.parts:
            groups.append((part.transformed(m), label, i + 1))
            times, states = schedules[label - 1]
            objects.append(placed_object(label, kind, kin, m, times, states, parent))
    objects.sort(key=lambda o: o.label)
    for j, (part, _) in enumerate(distractors):
        groups.append((part.transformed(places[len(builts) + j]), 0, len(builts) + 1 + j))
    kinds = tuple(o.kind for o in objects)
    if kinds != tuple(k for k, _ in drawn):
        raise AssertionError(f"family: built {kinds}, drawn {drawn}")  # pragma: no cover - construction order

    means, quats, scales, opacities, colors, labels, owner = gaussians_of_parts(groups)

    clouds = _owned_clouds(objects, means, labels, owner)
    below = np.array([max(0.0, -float(clouds[i + 1][:, 2].min())) for i in range(len(builts))])
    if np.any(below > 1e-6):
        return _assemble(cfg, room, builts, tilts, distractors, places, drawn, schedules, rng, lift + below)
    sep = math.inf
    for a in clouds:
        if np.any(np.abs(clouds[a][:, :2]) > ROOM_HALF - 0.1) or clouds[a][:, 2].max() > ROOM_HEIGHT - 0.1:
            return None
        tree = cKDTree(clouds[a])
        for b in clouds:
            if b > a:
                sep = min(sep, float(tree.query(clouds[b], k=1)[0].min()))
    if sep < MIN_SEPARATION:
        return None

    fx = _focal(cfg)
    moving = np.concatenate([clouds[o] for o in range(1, len(builts) + 1)])
    camera = _camera(rng, moving, fx, cfg.width, cfg.height)
    K = np.array([[fx, 0.0, cfg.width / 2.0], [0.0, fx, cfg.height / 2.0], [0.0, 0.0, 1.0]])
    return SynthScene(cfg=cfg, means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                      labels=labels, objects=tuple(objects), K=K, camera=camera, min_separation=sep, close_gap=None)


def _focal(cfg: SynthConfig) -> float:
    """fx = fy of family seed ``cfg.family``: 0.65-1.0 x the width."""
    return float(_rng(int(cfg.family), 4).uniform(0.65, 1.0)) * cfg.width


assert set(FAMILY_KINDS) == set(_BUILDERS)
