"""Rigid object trajectories from optical flow: a pose T_k(t) per discovered object and training time.

Movable parts (doors, drawers, lids, toys) move rigidly. Given the clustered Gaussians of object k in
their reference geometry (the stage-1 scene at t0) and the observed flow between consecutive frames,
each step solves for the rigid increment of every object:

    min_{omega, tau}  sum_m  w_m  rho( | pi(K, V_{t} (R(omega) (P_m - c) + c + tau)) - (m + u(m)) |^2 )

over the pixels m that object k paints in frame t-1 (rendered with its current pose T_k(t-1): the
one-hot object channel dominates, alpha > 0.5, flow known), where P_m is the pixel back-projected with
the rendered depth from camera t-1 (world coordinates), c their centroid, V_t camera t's world-to-camera
matrix, and rho a Huber loss (iteratively reweighted, 1 px). T_k(t) = Delta_k T_k(t-1) with
Delta(x) = R (x - c) + c + tau. The camera's own motion is in the projection, so a still object gets
the identity. Solved with optimistix's Levenberg-Marquardt on 6 unknowns; pixel arrays are padded to
H * W with zero weights, so one compiled solver serves every frame and object.

Over the pairs in which an object moves (`moving`), and with pixels taken from the scene as reconstructed
at each frame (so they do not depend on the poses), the same data are also fitted as one articulation
(`fit_joint`): a revolute joint (one axis and pivot for all pairs, an angle per pair) or a prismatic one
(one direction, a distance per pair). Pair by pair, six unknowns from the flow of a nearly planar part
are ill-conditioned (a door turning 10 degrees about its hinge and a 1-degree turn with a shift explain
its flow within half a pixel), and the articulation replaces the pair-by-pair poses unless it explains
the flow much worse (``joint_tolerance``).

Conventions: OpenCV cameras, world-to-camera 4x4 ``viewmat``, wxyz quaternions, flow t-1 -> t on frame
t-1's grid (pixel centres at +0.5). Pure functions; the pipeline decides what to do with the poses.
"""

from __future__ import annotations

import functools
import time

import cv2
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Bool, Float, Int

from fgjax import geometry
from fgjax.geometry import HIGHEST, full_precision
from fgjax.method.camera import fit_pixels, pixel_points, project_rows
from fgjax.models.posed import label_onehot, transform_gaussians
from fgjax.render.api import rasterization

__all__ = ["track_objects", "field_poses", "fit_joint", "JOINT_KINDS"]

JOINT_KINDS = ("revolute", "prismatic")


def _pixel_centres(width: int, height: int) -> np.ndarray:
    """Pixel centres [H * W, 2] in K's coordinates, row-major."""
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2)


def _interior(own: np.ndarray, erode: int) -> np.ndarray:
    """The mask `own` [H, W] without the pixels within `erode` pixels of its edge (the flow is smoothed
    across object edges, towards the background's)."""
    if erode <= 0:
        return own
    return cv2.erode(own.astype(np.uint8), np.ones((2 * erode + 1, 2 * erode + 1), np.uint8)) > 0


def _joint_moved(x, pts, kind: str):
    """Points [J, M, 3] moved by each pair's joint increment. x = (axis or direction [3], pivot [3], amounts
    [J]); the revolute increment of pair j turns by amounts[j] about the unit axis through the pivot, the
    prismatic one slides by amounts[j] along the unit direction (the pivot is unused)."""
    a = x[:3] / jnp.sqrt(jnp.sum(x[:3] ** 2) + 1e-12)
    amt = x[6:]
    if kind == "revolute":
        rot = geometry.so3_exp(amt[:, None] * a)  # [J, 3, 3]
        piv = x[3:6]
        return jnp.einsum("jmk,jik->jmi", pts - piv, rot, precision=HIGHEST) + piv
    return pts + amt[:, None, None] * a


def _joint_residuals(x, args, kind: str):
    pts, target, w, viewmats, K, damp, centre = args
    uv, ok = project_rows(_joint_moved(x, pts, kind), viewmats, K)
    r = jnp.where(ok[..., None], uv - target, 0.0) * jnp.sqrt(w)[..., None]  # [J, M, 2]
    # gauge: a unit axis, and (revolute) the pivot's position along the axis pinned to the centroid's
    gauge = jnp.stack([jnp.sum(x[:3] ** 2) - 1.0, jnp.sum((x[3:6] - centre) * x[:3])])
    return r.reshape(-1), gauge, damp * x[6:]  # damp: a pair without data keeps amount 0


@functools.partial(jax.jit, static_argnames=("kind", "irls"))
@full_precision  # the Cholesky of the normal equations too (no TF32 on GPUs)
def _fit_joint_jit(x0, pts, target, weights, viewmats, K, centre, *, kind: str, irls: int, huber_px: float):
    # the damped normal equations (J^T J + lambda I, 6 + J unknowns) by Cholesky instead of the default QR of the
    # [J M 2 + ..., 6 + J] Jacobian: the same fits, several times faster
    solver = optx.LevenbergMarquardt(rtol=1e-7, atol=1e-7, linear_solver=lx.Normal(lx.Cholesky()))
    fn = functools.partial(_joint_residuals, kind=kind)

    def round_(carry, _):  # one reweighting round; a loop, so that the solver compiles once, not irls + 1 times
        x, w, _r = carry
        sol = optx.least_squares(fn, solver, x, args=(pts, target, w, viewmats, K, 1e-3, centre), max_steps=60,
                                 throw=False)
        x = jnp.where(jnp.all(jnp.isfinite(sol.value)), sol.value, x)
        uv, ok = project_rows(_joint_moved(x, pts, kind), viewmats, K)
        r = jnp.where(ok, jnp.linalg.norm(uv - target, axis=-1), 1e3)  # [J, M]
        w = weights * jnp.minimum(1.0, huber_px / jnp.maximum(r, 1e-9))
        return (x, w, r), None

    (x, _, r), _ = jax.lax.scan(round_, (x0, weights, jnp.zeros_like(weights)), None, length=irls + 1)
    inl = (weights > 0) & (r < 3.0 * huber_px)
    rms = jnp.sqrt(jnp.sum(jnp.where(inl, r * r, 0.0)) / jnp.maximum(jnp.sum(inl), 1))
    frac = jnp.sum(inl) / jnp.maximum(jnp.sum(weights > 0), 1)
    # the robust cost the reweighting minimises: the mean Huber loss of every weighted residual
    hub = jnp.where(r <= huber_px, 0.5 * r * r, huber_px * (r - 0.5 * huber_px))
    cost = jnp.sum(weights * hub) / jnp.maximum(jnp.sum(weights), 1e-12)
    return x, rms, frac, cost


def fit_joint(pts: Float[ArrayLike, "J M 3"], target: Float[ArrayLike, "J M 2"], weights: Float[ArrayLike, "J M"],
              viewmats: Float[ArrayLike, "J 4 4"], K: Float[ArrayLike, "J 3 3"], kind: str, *, axes=None,
              huber_px: float = 1.0, irls: int = 2):
    """One articulation explaining an object's flow over J frame pairs: the same axis (and pivot) or
    direction in every pair, one amount per pair.

    Doors and lids turn about a hinge; drawers slide. Fitted pair by pair, six unknowns from the flow
    of a (nearly planar) part are ill-conditioned: a door turning 10 degrees about its hinge and a
    1-degree turn with a shift explain its flow within half a pixel (measured on the default scene),
    and the small explanation wins. Shared over every pair, the axis is pinned by all of them.

    Args:
        pts: [J, M, 3] world points of the object in the first frame of each pair (padding: weight 0).
        target: [J, M, 2] their observed positions in the second frame (pixels).
        weights: [J, M] >= 0.
        viewmats, K: [J, 4, 4], [J, 3, 3] the second frame's cameras.
        kind: "revolute" or "prismatic".
        axes: [A, 3] initial axes (directions) to try (default: the three coordinate axes); the fit
            with the lowest robust cost wins. The pivot starts at the weighted centroid.
        huber_px, irls: robust loss width and reweighting rounds (as `rigid_increment`).

    Returns:
        (increments [J, 4, 4] world transforms, inlier RMS in pixels (inliers: residual < 3 ``huber_px``),
        inlier fraction, axis [3], pivot [3], robust cost: the weighted mean Huber loss (px^2) of every
        residual, the loss the fit minimises). Compare fits by the cost: the inlier RMS leaves out exactly
        the large residuals that tell a wrong joint from a right one when a part moves far in few pairs.
    """
    if kind not in JOINT_KINDS:
        raise ValueError(f"fit_joint: kind must be one of {JOINT_KINDS}, got {kind!r}")
    dt = jnp.result_type(float)
    pts, target, weights = (jnp.asarray(a, dt) for a in (pts, target, weights))
    viewmats, K = jnp.asarray(viewmats, dt), jnp.asarray(K, dt)
    if pts.ndim != 3 or target.shape != pts.shape[:2] + (2,) or weights.shape != pts.shape[:2]:
        raise ValueError(f"fit_joint: pts [J, M, 3], target [J, M, 2] and weights [J, M] expected, got "
                         f"{list(pts.shape)}, {list(target.shape)}, {list(weights.shape)}")
    j = pts.shape[0]
    centre = jnp.sum(weights[..., None] * pts, (0, 1)) / jnp.maximum(jnp.sum(weights), 1e-9)
    # pairs padded to a multiple of 8 (weight 0, amount damped to 0), so that objects moving over different
    # numbers of pairs share compiled solvers (each compile takes seconds)
    jp = -(-j // 8) * 8
    pad = lambda a: jnp.concatenate([a, jnp.zeros((jp - j,) + a.shape[1:], a.dtype)])  # [jp, ...]
    pts, target, weights = pad(pts), pad(target), pad(weights)
    viewmats, K = pad(viewmats), pad(K)  # zero cameras: their rows have weight 0 (projections masked)
    axes = np.eye(3) if axes is None else np.asarray(axes, np.float64).reshape(-1, 3)
    best = None
    for a in axes:
        a = a / max(np.linalg.norm(a), 1e-12)
        x0 = jnp.concatenate([jnp.asarray(a, dt), centre, jnp.zeros(jp, dt)])
        x, rms, frac, cost = _fit_joint_jit(x0, pts, target, weights, viewmats, K, centre, kind=kind, irls=irls,
                                            huber_px=huber_px)
        if best is None or float(cost) < best[3]:
            best = (x, float(rms), float(frac), float(cost))
    x = np.asarray(best[0], np.float64)
    axis = x[:3] / max(np.linalg.norm(x[:3]), 1e-12)
    pivot, amt = x[3:6], x[6:6 + j]
    inc = np.tile(np.eye(4), (j, 1, 1))
    if kind == "revolute":
        rot = np.asarray(geometry.so3_exp(jnp.asarray(amt[:, None] * axis)), np.float64)
        inc[:, :3, :3] = rot
        inc[:, :3, 3] = pivot - rot @ pivot
    else:
        inc[:, :3, 3] = amt[:, None] * axis
    return inc, best[1], best[2], axis, pivot, best[3]


def _joint_arrays(data: list, m: int, viewmats0, Ks0, viewmats1, Ks1):
    """`fit_joint`'s padded inputs [J, M = m, ...] from a list of (xy, depth, flow), one per pair, and
    the pairs' first- and second-frame cameras."""
    rows = [pixel_points(xy, depth, flow, viewmats0[i], Ks0[i], m) for i, (xy, depth, flow) in enumerate(data)]
    pts, tgt, w = (np.stack(a) for a in zip(*rows, strict=True))
    return pts, tgt, w, np.stack(viewmats1), np.stack(Ks1)


def track_objects(means: Float[ArrayLike, "*T N 3"], quats: Float[ArrayLike, "*T N 4"],
                  scales: Float[ArrayLike, "*T N 3"], opacities: Float[ArrayLike, " N"], labels: Int[ArrayLike, " N"],
                  num_objects: int, viewmats: Float[ArrayLike, "T 4 4"], Ks: Float[ArrayLike, "T 3 3"],
                  flows: Float[ArrayLike, "T-1 H W 2"], width: int, height: int, *,
                  moving: Bool[ArrayLike, "K T-1"] | None = None, joints: str = "auto", joint_pixels: int = 256,
                  joint_tolerance: float = 3.0,
                  min_pixels: int = 30, dominance: float = 0.6, erode: int = 1, tile_size: int = 8,
                  log=print) -> np.ndarray:
    """Poses [K, T, 4, 4] of each object at each frame (T = len(viewmats), frames in time order; pose 0 = I).

    Args:
        means, quats, scales, opacities: the reference Gaussians (activated quats/scales/opacities) [N, ...];
            object k's pixels in frame t are those it paints when moved by its current pose T_k(t). Or
            means [T, N, 3], quats [T, N, 4] and scales [T, N, 3]: the scene as reconstructed at each frame (the stage-1
            model at that frame's time), which paints each object where the image shows it, so a pose
            error does not move the pixels the next increment is measured on.
        labels: [N] object of each Gaussian (-1: static).
        viewmats, Ks: [T, 4, 4], [T, 3, 3] cameras in time order.
        flows: [T-1, H, W, 2] observed flow frame j -> j + 1 (NaN = unknown).
        moving: [K, T-1] bool, the pairs in which each object moves (None: all). An object keeps its pose
            over the other pairs, so its pose does not drift while it rests.
        joints: "auto": with the per-frame geometry (pixels that do not depend on the poses), each object's
            pairs are also fitted as one articulation (`fit_joint`, revolute and prismatic); the one with
            the lower robust cost replaces the pair-by-pair fits when its inlier RMS is within
            ``joint_tolerance`` x theirs (+ 0.25 px); "off": pair by pair only.
        joint_pixels: at most this many pixels per pair (evenly strided) enter the articulation fits.
        min_pixels: objects painting fewer pixels in a frame keep their pose for that step.
        dominance: a pixel belongs to object k when k's share of the composited weight exceeds this.
        erode: pixels within this many pixels of the edge of object k's mask are not used.
    """
    t = len(viewmats)
    labels = np.asarray(labels)
    poses = np.tile(np.eye(4), (num_objects, t, 1, 1))
    if num_objects == 0 or t < 2:
        return poses
    onehot = label_onehot(labels, num_objects)
    pix = _pixel_centres(width, height)
    t0 = time.perf_counter()
    rms_all = []
    if joints not in ("auto", "off"):
        raise ValueError(f"track_objects: joints must be 'auto' or 'off', got {joints!r}")
    per_frame = np.ndim(means) == 3
    collect = per_frame and joints == "auto"
    data: list[dict[int, tuple]] = [{} for _ in range(num_objects)]  # object -> pair -> (xy, depth, flow)
    rms_obj: list[list[float]] = [[] for _ in range(num_objects)]
    for j in range(t - 1):
        s_j = scales[j] if per_frame else scales
        if per_frame:
            m_j, q_j = jnp.asarray(means[j]), jnp.asarray(quats[j])
        else:
            m_j, q_j = transform_gaussians(jnp.asarray(means), jnp.asarray(quats), jnp.asarray(labels),
                                           jnp.asarray(poses[:, j], jnp.float32))
        feat, alpha, info = rasterization(m_j, q_j, s_j, opacities, jnp.asarray(onehot), jnp.asarray(viewmats[j]),
                                          jnp.asarray(Ks[j]), width, height, render_depth=True, tile_size=tile_size)
        feat, alpha, depth = np.asarray(feat), np.asarray(alpha), np.asarray(info["depth"])
        share = feat / np.maximum(alpha, 1e-9)[..., None]
        flow = np.asarray(flows[j]).reshape(-1, 2)
        known = np.all(np.isfinite(flow), -1) & (alpha.reshape(-1) > 0.5) & (depth.reshape(-1) > 0)
        for k in range(num_objects):
            if moving is not None and not moving[k, j]:
                poses[k, j + 1] = poses[k, j]
                continue
            own = _interior(share[..., k + 1] > dominance, erode)
            sel = known & own.reshape(-1)
            if sel.sum() < min_pixels:
                poses[k, j + 1] = poses[k, j]
                continue
            idx = np.flatnonzero(sel)
            delta, rms = fit_pixels(pix[idx], depth.reshape(-1)[idx], flow[idx], viewmats[j], Ks[j],
                                     viewmats[j + 1], Ks[j + 1])
            poses[k, j + 1] = np.asarray(delta, np.float64) @ poses[k, j]
            rms_all.append(float(rms))
            rms_obj[k].append(float(rms))
            if collect:
                sub = idx[np.linspace(0, len(idx) - 1, min(len(idx), joint_pixels)).round().astype(int)]
                data[k][j] = (pix[sub], depth.reshape(-1)[sub], flow[sub])
    for k in range(num_objects):
        if not collect or len(data[k]) < 2:
            continue
        which = sorted(data[k])  # the pairs with data; the others keep the pose
        arrays = _joint_arrays([data[k][j] for j in which], joint_pixels,
                               [viewmats[j] for j in which], [Ks[j] for j in which],
                               [viewmats[j + 1] for j in which], [Ks[j + 1] for j in which])
        free = float(np.median(rms_obj[k]))
        fits = {kind: fit_joint(*arrays, kind) for kind in JOINT_KINDS}
        kind = min(fits, key=lambda c: fits[c][5])  # the lower robust cost
        inc, rms_j = fits[kind][0], fits[kind][1]
        use = rms_j <= joint_tolerance * free + 0.25
        log(f"tracking: object {k + 1}: pair by pair median RMS {free:.2f} px; revolute "
            f"{fits['revolute'][1]:.2f} px (cost {fits['revolute'][5]:.3f}), prismatic {fits['prismatic'][1]:.2f} px "
            f"(cost {fits['prismatic'][5]:.3f}) -> "
            f"{kind if use else 'pair by pair'}")
        if use:
            step = dict(zip(which, inc, strict=True))
            for j in range(t - 1):
                poses[k, j + 1] = step.get(j, np.eye(4)) @ poses[k, j]
    log(f"tracking: {num_objects} object(s) over {t} frames in {time.perf_counter() - t0:.1f} s "
        f"(median inlier reprojection RMS {np.median(rms_all) if rms_all else float('nan'):.2f} px)")
    return poses


def field_poses(ref_means: Float[ArrayLike, "N 3"], means: Float[ArrayLike, "T N 3"], labels: Int[ArrayLike, " N"],
                num_objects: int) -> np.ndarray:
    """Poses [K, T, 4, 4] of each object at each frame read off a deformation field instead of tracked: object k's
    pose at frame t is the rigid motion that best carries its Gaussians from the reference centres ``ref_means``
    [N, 3] to their centres ``means[t]`` [N, 3] under the field at that frame's time (least squares, Kabsch:
    `fgjax.geometry.fit_group_poses`). These are the paper's trajectories (the deformation field's motion of each
    cluster), made rigid; a field that moves nothing gives the identity. ``labels`` [N] in -1..K-1."""
    means = np.asarray(means)
    poses = np.tile(np.eye(4), (num_objects, len(means), 1, 1))
    if num_objects == 0:
        return poses
    for t, m in enumerate(means):
        poses[:, t] = np.asarray(geometry.fit_group_poses(ref_means, m, labels, num_objects), np.float64)
    return poses
