"""Synthetic scene description: `SynthConfig`, the objects' kinematics and schedules, the layout,
`make_scene`, deformation to a state vector and the camera path (see `fgjax.synth`)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import numpy as np
from jaxtyping import Float, Int
from scipy.spatial import cKDTree

from fgjax.synth.parts import (
    PALETTE,
    LocalObject,
    Part,
    apply_rigid,
    axis_angle_matrix,
    build_door,
    build_drawer,
    build_free,
    build_lid,
    build_room,
    normalize,
    quat_from_z,
    quat_mul,
    rigid,
    rotmat_to_quat,
    smoothstep,
)

OBJECT_KINDS = ("door", "drawer", "lid", "free")
# the scene family's joint kinds (`fgjax.synth.family`): a revolute joint about any axis, a prismatic one along
# any direction, a revolute joint about an axis through the part itself, and a free rigid motion
FAMILY_KINDS = ("hinge", "slide", "spin", "free")
MAX_OBJECTS = 6


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
        family: None for the hand-made scenes above; an int for a scene of the random family
            (`fgjax.synth.family`): its seed, from which `fgjax.synth.family.family_config`
            draws the other fields and `fgjax.synth.family.make_family_scene` the scene.
        depth_maps: also write each frame's depth where the loader reads a measured one
            (``depth/<frame>.npy``, camera z in scene units, 0 = none): the rendered expected depth on the
            pixels the render covers (alpha >= 0.5), as an ideal RGB-D sensor would measure it.
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
    family: int | None = None
    depth_maps: bool = False

    def __post_init__(self):
        objs = (self.objects,) if isinstance(self.objects, str) else tuple(self.objects)
        object.__setattr__(self, "objects", objs)
        if not 1 <= len(objs) <= MAX_OBJECTS:
            raise ValueError(f"SynthConfig.objects: need 1 to {MAX_OBJECTS} objects, got {len(objs)}")
        if self.family is not None and (isinstance(self.family, bool) or not isinstance(self.family, int)
                                        or self.family < 0):
            raise ValueError(f"SynthConfig.family must be None or a non-negative integer seed, got {self.family!r}")
        kinds = FAMILY_KINDS if self.family is not None else OBJECT_KINDS
        for o in objs:
            if o not in kinds:
                raise ValueError(f"SynthConfig.objects: unknown kind {o!r} (choose from {', '.join(kinds)})")
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
        if not isinstance(self.depth_maps, bool):
            raise ValueError(f"SynthConfig.depth_maps must be true or false, got {self.depth_maps!r}")
        if self.close_pair and len(objs) < 2:
            raise ValueError("SynthConfig.close_pair needs at least 2 objects")

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""
        d = dataclasses.asdict(self)
        d["objects"] = list(self.objects)
        return d


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
        parent: 0, or the label of the part this one is attached to (a smaller label). The
            transform above is then relative to the parent in its canonical state, and the world
            transform is T_parent(s_parent) T(s) (`compose_transforms`).
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
    parent: int = 0

    def to_dict(self) -> dict[str, Any]:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
        return out


def object_transform(obj: SynthObject, s: float) -> Float[np.ndarray, "4 4"]:
    """Rigid world transform T(s) taking the canonical (s = 0) object to state s (see `SynthObject`)."""
    s = float(s)
    if obj.kind in ("door", "lid", "hinge", "spin"):
        r, d = axis_angle_matrix(obj.axis, s * obj.max_angle), np.zeros(3)
    elif obj.kind in ("drawer", "slide"):
        r, d = np.eye(3), s * obj.distance * obj.direction
    elif obj.kind == "free":
        d = s * obj.distance * obj.direction + obj.wiggle * math.sin(math.pi * s) * obj.lateral
        r = axis_angle_matrix(obj.axis, s * obj.distance / obj.radius)
    else:  # pragma: no cover - guarded by SynthConfig
        raise ValueError(f"object_transform: unknown kind {obj.kind!r}")
    return rigid(r, obj.pivot + d - r @ obj.pivot)


def object_state(obj: SynthObject, t: float | np.ndarray) -> np.ndarray:
    """State s(t) of the object's schedule (smoothstep between keyframes, constant outside)."""
    t = np.asarray(t, dtype=np.float64)
    kt, ks = obj.key_times, obj.key_states
    i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, len(kt) - 2)
    u = (t - kt[i]) / np.maximum(kt[i + 1] - kt[i], 1e-12)
    return ks[i] + (ks[i + 1] - ks[i]) * smoothstep(u)


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


def _layout(cfg: SynthConfig, locals_: list[LocalObject], rng: np.random.Generator) -> list[np.ndarray]:
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
            place = rigid(axis_angle_matrix([0, 0, 1], yaw), np.array([gx, gy, 0.0]))
            off = -gw / 2
            front = min(locals_[i].front for i in g)  # align the pair's front faces
            for i in g:
                lw = locals_[i].width
                out[i] = place @ rigid(np.eye(3), np.array([off + lw / 2, front - locals_[i].front, 0.0]))
                off += lw + cfg.close_gap
            x += gw + gap
    return out  # type: ignore[return-value]


def _tighten_pair(a: LocalObject, place_a: np.ndarray, b: LocalObject, place_b: np.ndarray,
                  gap: float) -> np.ndarray:
    """Slide object b along the pair's x axis so that the nearest Gaussian centres of the two moving
    parts (canonical state) are `gap` apart, unless that would bring the whole objects (bodies
    included) closer than 0.8 gap; then they stop there (the parts' gap is larger, e.g. a ball
    next to a chest whose lid sits higher than the ball).

    Each distance is solved by the fixed-point iteration delta <- delta - (d(delta) - target): d
    changes by at most |step|, and by exactly |step| once the nearest points line up with the axis.
    """
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
        return apply_rigid(place, np.concatenate([o.part.points] + ([o.body.points] if o.body is not None else [])))

    d_parts = solve(apply_rigid(place_a, a.part.points), apply_rigid(place_b, b.part.points), gap)
    d_whole = solve(whole(a, place_a), whole(b, place_b), 0.8 * gap)
    out = place_b.copy()
    out[:3, 3] += max(d_parts, d_whole) * axis
    return out


def _seed_of(key_or_seed) -> int:
    if key_or_seed is None:
        raise ValueError("make_scene: seed is None")
    if isinstance(key_or_seed, int | np.integer) and not isinstance(key_or_seed, bool):
        return int(key_or_seed)
    return int(jax.random.randint(key_or_seed, (), 0, 2**31 - 1))


def make_scene(cfg: SynthConfig, key_or_seed: int | Any | None = None) -> SynthScene:
    """Build the room, the objects, their schedules and the camera path.

    Args:
        cfg: the options.
        key_or_seed: an int seed or a JAX PRNG key; None uses ``cfg.seed``.

    Returns:
        The `SynthScene` (canonical Gaussians with every object at state 0).
    """
    if cfg.family is not None:
        raise ValueError("make_scene: a family scene (SynthConfig.family set) is built by "
                         "fgjax.synth.family.make_family_scene")
    seed = cfg.seed if key_or_seed is None else _seed_of(key_or_seed)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5EED]))
    room = build_room(rng, cfg.room_spacing)
    builders = {"door": build_door, "drawer": build_drawer, "lid": build_lid}
    locals_: list[LocalObject] = []
    for i, kind in enumerate(cfg.objects):
        pal = PALETTE[i % len(PALETTE)]
        if kind == "free":
            locals_.append(build_free(rng, cfg.object_spacing, pal, straight=cfg.close_pair and i < 2))
        else:
            locals_.append(builders[kind](rng, cfg.object_spacing, pal))
    places = _layout(cfg, locals_, rng)
    if cfg.close_pair:
        places[1] = _tighten_pair(locals_[0], places[0], locals_[1], places[1], cfg.close_gap)
    scheds = _schedules(len(locals_), rng)

    parts: list[tuple[Part, int, int]] = [(room, 0, 0)]  # (part, label, owner)
    objects = []
    for i, (lo, place) in enumerate(zip(locals_, places, strict=True)):
        label = i + 1
        if lo.body is not None:
            parts.append((lo.body.transformed(place), 0, label))
        parts.append((lo.part.transformed(place), label, label))
        objects.append(placed_object(label, cfg.objects[i], lo.kin, place, scheds[i][0], scheds[i][1]))

    means, quats, scales, opacities, colors, labels, owner = gaussians_of_parts(parts)

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


def placed_object(label: int, kind: str, kin: dict[str, Any], place: Float[np.ndarray, "4 4"],
                  key_times: np.ndarray, key_states: np.ndarray, parent: int = 0) -> SynthObject:
    """The `SynthObject` of kinematics `kin` given in an object's local frame (``pivot`` a point; ``axis``,
    ``direction``, ``lateral`` directions; ``max_angle``, ``distance``, ``wiggle``, ``radius`` numbers; a missing one
    is zero), placed in the world by the rigid `place` [4, 4]."""
    def vec(name: str, point: bool = False) -> np.ndarray:
        if name not in kin:
            return np.zeros(3)
        return apply_rigid(place, kin[name]) if point else place[:3, :3] @ kin[name]

    return SynthObject(
        label=label, kind=kind, name=f"{kind}_{label}", pivot=vec("pivot", point=True), axis=vec("axis"),
        direction=vec("direction"), lateral=vec("lateral"), max_angle=float(kin.get("max_angle", 0.0)),
        distance=float(kin.get("distance", 0.0)), wiggle=float(kin.get("wiggle", 0.0)),
        radius=float(kin.get("radius", 0.0)), key_times=key_times, key_states=key_states, parent=int(parent))


LAYER_JITTER = 0.5
"""Each Gaussian of the room sits behind its surface (against the normal, which points into the room) by a uniform
draw in [0, 1] x this x the room's spacing (`gaussians_of_parts`)."""


def gaussians_of_parts(parts: list[tuple[Part, int, int]]) -> tuple[np.ndarray, ...]:
    """The Gaussians of surface groups `parts` [(part, label, owner)] (world frame), as `SynthScene` stores them:
    (means [N, 3], quats [N, 4] taking local z to each normal, scales [N, 3] = (0.6, 0.6, 0.12) x the group's
    spacing, opacities [N] = 0.97, colors [N, 3], labels [N] int32, owner [N] int32).

    The rasterizer composites a pixel's Gaussians in the order of their centres' depth. On a flat grid of
    overlapping splats that order is set by the view direction alone, and it reverses for the whole grid at once when
    the camera looks square onto the surface: the texture then jumps by up to half a spacing between two frames while
    the poses (and so the ground-truth flow) move smoothly. Each centre of the room (owner 0: the walls and the floor)
    therefore sits behind its surface, against its normal, by `LAYER_JITTER` x spacing x a uniform draw in [0, 1]
    (seeded by the number of Gaussians, so the same scene is the same bit for bit): each pair of neighbours swaps at
    its own view angle instead, and the texture stays where the geometry puts it. Nothing moves into the room, where
    the objects stand on the floor, and the objects' bodies and parts keep their exact surfaces (their gaps and hinges
    are part of the ground truth)."""
    means = np.concatenate([p.points for p, _, _ in parts])
    normals = np.concatenate([p.normals for p, _, _ in parts])
    colors = np.concatenate([p.colors for p, _, _ in parts])
    labels = np.concatenate([np.full(len(p.points), lab, dtype=np.int32) for p, lab, _ in parts])
    owner = np.concatenate([np.full(len(p.points), own, dtype=np.int32) for p, _, own in parts])
    sig = np.concatenate([np.full(len(p.points), p.spacing) for p, _, _ in parts])
    off = np.random.default_rng(np.random.SeedSequence([0x1A7E5, len(means)])).uniform(0.0, 1.0, len(means))
    means = means - normals * (LAYER_JITTER * sig * off * (owner == 0))[:, None]
    scales = np.stack([0.6 * sig, 0.6 * sig, 0.12 * sig], axis=-1)
    return means, quat_from_z(normals), scales, np.full(len(means), 0.97), colors, labels, owner


def _separations(scene: SynthScene, owner: np.ndarray) -> tuple[float, float | None]:
    """(min distance between different objects over a sweep of states, canonical close-pair gap).

    `owner` [N]: 0 for the room, k for object k's static body and moving part.
    """
    sweep = np.linspace(0.0, 1.0, 5)
    clouds = {}
    for k, obj in enumerate(scene.objects, start=1):
        part = scene.means[scene.labels == k]
        body = scene.means[(owner == k) & (scene.labels == 0)]
        clouds[k] = np.concatenate([body] + [apply_rigid(object_transform(obj, s), part) for s in sweep])
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


def compose_transforms(objects, states: np.ndarray) -> np.ndarray:
    """[K + 1, 4, 4] world transforms by label (identity for label 0) of `objects` (in label order, label k =
    objects[k - 1]) at one state vector [K]: T_k = T_parent(k) T_k(s_k) (`SynthObject.parent`; parents have
    smaller labels)."""
    out = np.tile(np.eye(4), (len(objects) + 1, 1, 1))
    for k, obj in enumerate(objects, start=1):
        out[k] = object_transform(obj, states[k - 1])
        if obj.parent:
            out[k] = out[obj.parent] @ out[k]
    return out


def object_transforms(scene: SynthScene, states: np.ndarray) -> np.ndarray:
    """[K + 1, 4, 4] world transforms by label (identity for label 0) at one state vector [K]
    (`compose_transforms`)."""
    return compose_transforms(scene.objects, states)


def moving_labels(objects, states: Float[np.ndarray, "T K"]) -> Float[np.ndarray, "T-1 K"]:
    """[T - 1, K] bool: object k moves in the world between consecutive state vectors (its own state
    changes, or that of a part it is attached to)."""
    moving = np.abs(np.diff(np.asarray(states), axis=0)) > 0
    for k, obj in enumerate(objects):
        if obj.parent:
            moving[:, k] |= moving[:, obj.parent - 1]
    return moving


def deform(scene: SynthScene,
           states: Float[np.ndarray, " K"]) -> tuple[Float[np.ndarray, "N 3"], Float[np.ndarray, "N 4"]]:
    """Means and quaternions of the Gaussians with the objects at `states` [K]."""
    states = np.asarray(states, dtype=np.float64).reshape(-1)
    if states.shape != (scene.num_objects,):
        raise ValueError(f"deform: states must have shape [K] = [{scene.num_objects}], got {states.shape}")
    tr = object_transforms(scene, states)  # [K + 1, 4, 4]
    m = tr[scene.labels]  # [N, 4, 4]
    means = np.einsum("nij,nj->ni", m[:, :3, :3], scene.means) + m[:, :3, 3]
    qk = np.stack([rotmat_to_quat(t[:3, :3]) for t in tr])  # [K + 1, 4]
    quats = quat_mul(qk[scene.labels], scene.quats)
    return means, quats


def object_centres(scene: SynthScene, states: Float[np.ndarray, "T K"]) -> Float[np.ndarray, "T K 3"]:
    """3D centre (mean of the deformed Gaussians of each object's moving part) per state vector."""
    states = np.atleast_2d(np.asarray(states, dtype=np.float64))
    out = np.zeros((len(states), scene.num_objects, 3))
    for t, s in enumerate(states):
        tr = object_transforms(scene, s)
        for k in range(1, scene.num_objects + 1):
            out[t, k - 1] = apply_rigid(tr[k], scene.means[scene.labels == k]).mean(axis=0)
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
    if "path" in cam:
        return _path_c2w(cam, t, d_azimuth=d_azimuth, d_height=d_height, d_radius=d_radius)
    j = _jitter(cam, t)
    phi = -cam["sweep"] / 2 + cam["sweep"] * t + d_azimuth
    rad = cam["radius"] + 0.05 * math.sin(2 * math.pi * 1.3 * t) + d_radius
    target = cam["target"] + 1.5 * cfg.jitter * j[3:6]
    pos = np.array([cam["target"][0] + rad * math.sin(phi), cam["target"][1] - rad * math.cos(phi),
                    cam["height"] + 0.06 * math.sin(2 * math.pi * 0.8 * t + cam["wobble_phase"]) + d_height])
    pos = pos + cfg.jitter * j[:3]
    z = normalize(target - pos)
    x = normalize(np.cross(z, [0.0, 0.0, 1.0]))
    y = np.cross(z, x)
    roll = math.radians(150.0 * cfg.jitter * j[6])
    rot = np.stack([x, y, z], axis=-1) @ axis_angle_matrix([0, 0, 1], roll)
    return rigid(rot, pos)


def _path_c2w(cam: dict[str, Any], t: float, *, d_azimuth: float, d_height: float,
              d_radius: float) -> Float[np.ndarray, "4 4"]:
    """OpenCV camera-to-world of the scene family's camera paths (`fgjax.synth.family`).

    The camera looks at ``target`` from azimuth phi(t) = azimuth + sweep (t - 1/2) (+ `d_azimuth`), at horizontal
    distance r(t) = radius + (radius_end - radius) smoothstep(t) (+ `d_radius`: a dolly when radius_end differs)
    and height ``height`` (+ `d_height`), plus hand-held jitter of amplitude ``jitter`` (position; the look-at
    point 1.5x) and a roll of ``roll_deg`` + ``roll_jitter_deg`` j(t) degrees about the viewing axis.
    A still camera has sweep 0, radius_end = radius and no jitter.
    """
    j = _jitter(cam, t)
    phi = cam["azimuth"] + cam["sweep"] * (t - 0.5) + d_azimuth
    rad = cam["radius"] + (cam["radius_end"] - cam["radius"]) * float(smoothstep(np.asarray(t))) + d_radius
    target = np.asarray(cam["target"]) + 1.5 * cam["jitter"] * j[3:6]
    pos = np.array([cam["target"][0] + rad * math.sin(phi), cam["target"][1] - rad * math.cos(phi),
                    cam["height"] + d_height]) + cam["jitter"] * j[:3]
    z = normalize(target - pos)
    x = normalize(np.cross(z, [0.0, 0.0, 1.0]))
    y = np.cross(z, x)
    roll = math.radians(cam["roll_deg"] + cam["roll_jitter_deg"] * j[6])
    return rigid(np.stack([x, y, z], axis=-1) @ axis_angle_matrix([0, 0, 1], roll), pos)
