"""Initial Gaussian centres without SfM: points triangulated from optical flow between posed frames.

3DGS starts from COLMAP's sparse points; here the poses are given, so a dense point cloud follows from
optical flow alone: each pixel m of frame i and its match m + u in frame j define two rays, and their
closest point is the surface point (midpoint triangulation). Matches are kept only where the flow is
forward-backward consistent, the rays meet in front of both cameras at a usable angle, and the
midpoint reprojects onto both pixels (which also rejects most points of moving objects: their motion
breaks the epipolar constraint). Everything here is numpy; no ground truth is read.

Conventions: OpenCV cameras, ``viewmat`` world-to-camera 4x4, pixel (j, i) centre at (j + 0.5, i + 0.5)
in K's coordinates; flow u(j, i) = (dx, dy) maps frame i's pixel to frame j's.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from fgjax.data.opticalflow import estimate_flow, forward_backward_mask
from fgjax.geometry import look_at_point

__all__ = ["triangulate_midpoint", "pixel_rays", "free_space_violations", "flow_point_cloud", "depth_point_cloud",
           "scene_box", "visible_any", "random_points", "first_view_colors"]


def pixel_rays(viewmat: np.ndarray, K: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World rays through pixel positions `xy` [..., 2] (K's coordinates): (centre [3], directions [..., 3]).

    Directions are R^T K^-1 (x, y, 1), not normalised: the ray parameter is the camera z-depth."""
    r = viewmat[:3, :3]
    centre = -r.T @ viewmat[:3, 3]  # [3]
    x = (xy[..., 0] - K[0, 2]) / K[0, 0]
    y = (xy[..., 1] - K[1, 2]) / K[1, 1]
    d_cam = np.stack([x, y, np.ones_like(x)], -1)  # [..., 3]
    return centre, d_cam @ r  # R^T d for row vectors


def triangulate_midpoint(c0: np.ndarray, d0: np.ndarray, c1: np.ndarray, d1: np.ndarray,
                         eps: float = 1e-12) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closest point between rays c0 + s d0 and c1 + u d1 (broadcast over leading axes of d0, d1).

    Returns (midpoint [..., 3], s [...], u [...], sin of the angle between the rays [...]).
    Parallel rays give s = u = 0 and sin = 0 (filter on the angle)."""
    w = c0 - c1  # [3]
    a = np.sum(d0 * d0, -1)
    b = np.sum(d0 * d1, -1)
    c = np.sum(d1 * d1, -1)
    d = d0 @ w
    e = d1 @ w
    den = a * c - b * b
    ok = den > eps * a * c
    den_safe = np.where(ok, den, 1.0)
    s = np.where(ok, (b * e - c * d) / den_safe, 0.0)
    u = np.where(ok, (a * e - b * d) / den_safe, 0.0)
    p = 0.5 * ((c0 + s[..., None] * d0) + (c1 + u[..., None] * d1))
    sin = np.sqrt(np.maximum(den, 0.0) / np.maximum(a * c, eps))
    return p, s, u, sin


def _project(viewmat, K, p):
    q = p @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = q[..., 2]
    zs = np.where(z > 1e-9, z, 1.0)
    return np.stack([K[0, 0] * q[..., 0] / zs + K[0, 2], K[1, 1] * q[..., 1] / zs + K[1, 2]], -1), z


def free_space_violations(points: np.ndarray, depth_maps: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray,
                          tol: float = 0.05) -> np.ndarray:
    """[M] bool: the point lies clearly in front of the surface a reference view saw at its pixel.

    A static point can never be in front of what a camera saw through it (free space); a point of a
    moving part is, in views from times when the part was elsewhere.

    Args:
        points: [M, 3] world points.
        depth_maps: [R, H, W] camera z-depth seen by each reference view (NaN = unknown).
        viewmats, Ks: [R, 4, 4], [R, 3, 3] of the reference views.
        tol: relative margin: violation when z < (1 - tol) * depth.
    """
    r, h, w = depth_maps.shape
    # the nearest surface over each pixel's 3x3 neighbourhood: a point near a depth edge is not "in front"
    # of the far side of the edge
    pad = np.pad(np.where(np.isfinite(depth_maps), depth_maps, np.inf), ((0, 0), (1, 1), (1, 1)),
                 constant_values=np.inf)
    near = np.min(np.stack([pad[:, a:a + h, b:b + w] for a in range(3) for b in range(3)]), axis=0)
    depth_maps = np.where(np.isfinite(near), near, np.nan)
    bad = np.zeros(len(points), bool)
    for k in range(r):
        uv, z = _project(viewmats[k], Ks[k], points)
        j = np.floor(uv[:, 0]).astype(np.int64)
        i = np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > 1e-6) & (j >= 0) & (j < w) & (i >= 0) & (i < h)
        d = np.full(len(points), np.nan)
        d[inside] = depth_maps[k][i[inside], j[inside]]
        with np.errstate(invalid="ignore"):
            bad |= inside & np.isfinite(d) & (z < (1.0 - tol) * d)
    return bad


def flow_point_cloud(scene, *, gap: int = 4, stride: int = 2, method: str = "dis", cache_dir=None,
                     min_angle_deg: float = 1.0, max_reproj_px: float = 0.75, near: float = 0.05,
                     canonical: bool = True, max_references: int = 8, log=print) -> dict[str, Any]:
    """Triangulate every consistently matched pixel of frame pairs (i, i + gap) in time order.

    Args:
        scene: a `fgjax.data.Scene` (images, Ks, viewmats, times).
        gap: frame offset of each pair (larger: wider baseline, harder matching).
        stride: a pair starts at every `stride`-th frame.
        method: optical-flow method (`fgjax.data.opticalflow.METHODS`); forward and backward flows.
        min_angle_deg: rays meeting at a smaller angle are dropped (depth too uncertain).
        max_reproj_px: the midpoint must reproject within this many pixels of both matched pixels.
        canonical: keep only points consistent with the earliest state of the scene: a point seen at time t
            is dropped when it lies in free space for a view from an earlier time (`free_space_violations`
            against up to `max_references` earlier views' triangulated depth). Parts that moved before t
            would otherwise appear twice (ghosts); the deformation field's canonical space is then the
            scene at the first time.

    Returns:
        {"points" [M, 3], "colors" [M, 3] in [0, 1], "times" [M] and "frames" [M] (time and index of the frame
        each point was seen in), "pixels" [M, 2] (its pixel there, K's coordinates), "pairs", "kept_fraction"}.
    """
    order = np.argsort(np.asarray(scene.times), kind="stable")
    t = len(order)
    gap = max(1, min(int(gap), t - 1))
    h, w = scene.height, scene.width
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([xs + 0.5, ys + 0.5], -1)  # [H, W, 2]
    imgs = (np.clip(np.asarray(scene.images), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    sin_min = np.sin(np.radians(min_angle_deg))
    pts, cols, tms, src, pxs, depth_maps = [], [], [], [], [], []
    total = 0
    t0 = time.time()
    pairs = [(int(order[k]), int(order[k + gap])) for k in range(0, t - gap, max(1, int(stride)))] if t > 1 else []
    for i, j in pairs:
        fw = estimate_flow(imgs[i], imgs[j], method, cache_dir=cache_dir)
        bw = estimate_flow(imgs[j], imgs[i], method, cache_dir=cache_dir)
        ok = forward_backward_mask(fw, bw)
        m0 = pix[ok]  # [P, 2]
        m1 = m0 + fw[ok].astype(np.float64)
        total += h * w
        # every pair appends one entry to each list below (empty when nothing matched), so that list index k
        # stays pair k: the ghost filter looks up reference pairs by index
        c0, d0 = pixel_rays(scene.viewmats[i], scene.Ks[i], m0)
        c1, d1 = pixel_rays(scene.viewmats[j], scene.Ks[j], m1)
        p, s, u, sin = triangulate_midpoint(c0, d0, c1, d1)
        r0, z0 = _project(scene.viewmats[i], scene.Ks[i], p)
        r1, z1 = _project(scene.viewmats[j], scene.Ks[j], p)
        err = np.maximum(np.linalg.norm(r0 - m0, axis=-1), np.linalg.norm(r1 - m1, axis=-1))
        keep = (s > near) & (u > near) & (z0 > near) & (z1 > near) & (sin > sin_min) & (err < max_reproj_px)
        keep &= np.all(np.isfinite(p), -1)
        dmap = np.full((h, w), np.nan)
        dmap[ok] = np.where(keep, s, np.nan)
        depth_maps.append(dmap)
        pts.append(p[keep])
        cols.append(np.asarray(scene.images[i], np.float64)[ok][keep])
        tms.append(np.full(int(keep.sum()), float(scene.times[i])))
        src.append(np.full(int(keep.sum()), i, np.int64))
        pxs.append(m0[keep])
    cat = lambda parts, shape: np.concatenate(parts) if parts else np.zeros(shape)
    n_ghost = 0
    if canonical and len(pts) > 1:  # pairs are in time order: test pair k's points against earlier pairs
        refs = np.unique(np.round(np.linspace(0, len(pts) - 2, min(max_references, len(pts) - 1))).astype(int))
        ref_i = [pairs[r][0] for r in refs]
        for k in range(1, len(pts)):
            earlier = [n for n, r in enumerate(refs) if r < k]
            if not earlier or len(pts[k]) == 0:
                continue
            bad = free_space_violations(pts[k], np.stack([depth_maps[refs[n]] for n in earlier]),
                                        scene.viewmats[[ref_i[n] for n in earlier]],
                                        scene.Ks[[ref_i[n] for n in earlier]])
            n_ghost += int(bad.sum())
            pts[k], cols[k], tms[k], src[k], pxs[k] = (a[~bad] for a in (pts[k], cols[k], tms[k], src[k], pxs[k]))
    points, colors, ptimes = cat(pts, (0, 3)), cat(cols, (0, 3)), cat(tms, (0,))
    frac = len(points) / max(total, 1)
    log(f"flow point cloud ({method}): {len(pairs)} pairs, {len(points)} points "
        f"({100 * frac:.1f}% of pixels; {n_ghost} in earlier free space dropped) in {time.time() - t0:.1f} s")
    return {"points": points, "colors": colors, "times": ptimes, "frames": cat(src, (0,)).astype(np.int64),
            "pixels": cat(pxs, (0, 2)), "pairs": pairs, "kept_fraction": frac}


def depth_point_cloud(scene, *, frames: int = 8, canonical: bool = True, log=print) -> dict[str, Any]:
    """Back-project every pixel with a measured depth (``scene.depths`` > 0: an RGB-D sensor) of up to `frames`
    training frames evenly spaced in time: X = c2w (D(m) K^-1 m~), m the pixel centre.

    With ``canonical`` a point of a later frame is dropped where it lies in free space for an earlier one of these
    frames (`free_space_violations` against their measured depth), as in `flow_point_cloud`: a part that moved
    keeps its points of the earliest frame only, so the canonical space is the scene at the first time, without
    ghosts. Returns the keys of `flow_point_cloud` ("pairs": []; "kept_fraction": kept points over the pixels
    with a depth)."""
    if scene.depths is None:
        raise ValueError("depth_point_cloud: the scene has no depth maps")
    order = np.argsort(np.asarray(scene.times), kind="stable")
    pick = order[np.unique(np.round(np.linspace(0, len(order) - 1, max(1, min(int(frames), len(order))))).astype(int))]
    h, w = scene.height, scene.width
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([xs + 0.5, ys + 0.5], -1)
    depths = np.asarray(scene.depths, np.float64)
    depths = np.where(np.isfinite(depths) & (depths > 0), depths, np.nan)  # NaN: unknown, for the free-space test
    t0 = time.time()
    pts, cols, tms, src, pxs = [], [], [], [], []
    total = n_ghost = 0
    for k, i in enumerate(pick):
        d = depths[i]
        ok = np.isfinite(d)
        total += int(ok.sum())
        c, rays = pixel_rays(scene.viewmats[i], scene.Ks[i], pix[ok])
        p = c + d[ok][:, None] * rays  # rays are scaled so that the parameter is the camera z-depth
        keep = np.ones(len(p), bool)
        if canonical and k > 0:
            ref = pick[:k]
            keep = ~free_space_violations(p, depths[ref], scene.viewmats[ref], scene.Ks[ref])
            n_ghost += int((~keep).sum())
        pts.append(p[keep])
        cols.append(np.asarray(scene.images[i], np.float64)[ok][keep])
        tms.append(np.full(int(keep.sum()), float(scene.times[i])))
        src.append(np.full(int(keep.sum()), int(i), np.int64))
        pxs.append(pix[ok][keep])
    points = np.concatenate(pts)
    log(f"depth point cloud: {len(pick)} frames, {len(points)} points ({n_ghost} in earlier free space dropped) in "
        f"{time.time() - t0:.1f} s")
    return {"points": points, "colors": np.concatenate(cols), "times": np.concatenate(tms),
            "frames": np.concatenate(src), "pixels": np.concatenate(pxs), "pairs": [],
            "kept_fraction": len(points) / max(total, 1)}


def scene_box(viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """A box the cameras look into: centred on the least-squares closest point to all optical axes,
    half-size the median camera distance to it (`fgjax.geometry.look_at_point`: one unit in front of cameras
    that share one centre; no depth, no SfM points needed)."""
    centre, rad = look_at_point(viewmats)
    rad = max(rad, 1e-3)
    return centre - rad, centre + rad


def visible_any(points, viewmats, Ks, width, height):
    vis = np.zeros(len(points), bool)
    for vm, K in zip(viewmats, Ks):
        p = points @ vm[:3, :3].T + vm[:3, 3]
        z = p[:, 2]
        ok = z > 0.05
        u = K[0, 0] * p[:, 0] / np.where(ok, z, 1) + K[0, 2]
        v = K[1, 1] * p[:, 1] / np.where(ok, z, 1) + K[1, 2]
        vis |= ok & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return vis


def random_points(rng, want: int, lo, hi, scene) -> np.ndarray:
    pts = np.zeros((0, 3))
    for _ in range(20):
        cand = lo + rng.uniform(size=(want * 2, 3)) * (hi - lo)
        pts = np.concatenate([pts, cand[visible_any(cand, scene.viewmats, scene.Ks, scene.width, scene.height)]])
        if len(pts) >= want:
            break
    return pts[:want]


def first_view_colors(pts, scene) -> np.ndarray:
    """Colour of each point: the pixel of the first camera that sees it (a cheap, depth-free guess)."""
    cols = np.full((len(pts), 3), 0.5)
    vm, K = scene.viewmats[0], scene.Ks[0]
    p = pts @ vm[:3, :3].T + vm[:3, 3]
    z = np.where(p[:, 2] > 0.05, p[:, 2], np.inf)
    u = np.floor(K[0, 0] * p[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.floor(K[1, 1] * p[:, 1] / z + K[1, 2]).astype(np.int64)
    ok = np.isfinite(z) & (u >= 0) & (u < scene.width) & (v >= 0) & (v < scene.height)
    cols[ok] = scene.images[0][v[ok], u[ok]]
    return cols
