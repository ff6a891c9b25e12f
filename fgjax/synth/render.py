"""Rendering of synthetic sequences with per-pixel ground truth (depth, object id), the ground-truth
optical flow, and the Middlebury flow colour coding."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, Int

from fgjax.render.api import count_intersections, rasterization
from fgjax.synth.parts import rigid_inv
from fgjax.synth.scene import SynthScene, deform, moving_labels, object_transforms

VALID_ALPHA = 0.5  # pixels with alpha below this are background (id -1, no flow)


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
    c2w0 = rigid_inv(viewmat0)
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
    ok = np.all(np.isfinite(flow), axis=-1)
    if valid is not None:
        ok = np.asarray(valid, bool) & ok
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


def sequence_flow(scene: SynthScene, states: Float[np.ndarray, "T K"], viewmats: Float[np.ndarray, "T 4 4"],
                  renders: Renders) -> dict[str, np.ndarray]:
    """Ground-truth flows between consecutive frames of a rendered sequence (see `ground_truth_flow`).

    Returns:
        dict with flow, camera_flow, object_flow [T-1, H, W, 2] float32, flow_valid,
        flow_occluded [T-1, H, W] bool, and moving [T-1, K] bool (object k moves: `fgjax.synth.scene.moving_labels`).
    """
    t, h, w = renders.depth.shape
    out = {
        "flow": np.zeros((t - 1, h, w, 2), np.float32),
        "camera_flow": np.zeros((t - 1, h, w, 2), np.float32),
        "object_flow": np.zeros((t - 1, h, w, 2), np.float32),
        "flow_valid": np.zeros((t - 1, h, w), bool),
        "flow_occluded": np.zeros((t - 1, h, w), bool),
        "moving": moving_labels(scene.objects, states),
    }
    transforms = [object_transforms(scene, s) for s in states]
    for i in range(t - 1):
        motions = np.einsum("kij,kjl->kil", transforms[i + 1], rigid_inv(transforms[i]))
        motions[1:][~out["moving"][i]] = np.eye(4)  # resting objects: exactly the identity
        g = ground_truth_flow(renders.depth[i], renders.object_id[i], scene.K, viewmats[i], viewmats[i + 1],
                              motions, depth1=renders.depth[i + 1])
        for name in ("flow", "camera_flow", "object_flow"):
            out[name][i] = g[name]
        out["flow_valid"][i], out["flow_occluded"][i] = g["valid"], g["occluded"]
    return out
