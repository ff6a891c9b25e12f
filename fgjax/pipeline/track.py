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

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from fgjax import geometry
from fgjax.geometry import HIGHEST, full_precision, matmul
from fgjax.pipeline.init_points import pixel_rays

__all__ = ["rigid_increment", "track_objects", "transform_gaussians", "fit_group_poses", "quat_multiply",
           "camera_correction", "fit_joint", "JOINT_KINDS"]

JOINT_KINDS = ("revolute", "prismatic")


def quat_multiply(a, b):
    """Hamilton product a * b of wxyz quaternions [..., 4] (rotation b first, then a)."""
    aw, ax, ay, az = jnp.moveaxis(jnp.asarray(a), -1, 0)
    bw, bx, by, bz = jnp.moveaxis(jnp.asarray(b), -1, 0)
    return jnp.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                      aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def transform_gaussians(means, quats, labels, poses):
    """Move each labelled Gaussian rigidly by its object's pose: (means [N, 3], raw quats [N, 4]).

    ``poses`` [K, 4, 4] world-space rigid transforms (x -> R x + t); ``labels`` [N] in -1..K-1 (-1: not
    moved). The raw quaternion keeps its norm (q' = q_R * q)."""
    labels = jnp.asarray(labels)
    k = jnp.clip(labels, 0)
    moved = labels >= 0
    rot = jnp.asarray(poses)[k, :3, :3]  # [N, 3, 3]
    tr = jnp.asarray(poses)[k, :3, 3]
    m = jnp.einsum("nij,nj->ni", rot, means, precision=HIGHEST) + tr
    q = quat_multiply(geometry.rotmat_to_quat(rot), quats)
    return jnp.where(moved[:, None], m, means), jnp.where(moved[:, None], q, quats)


def fit_group_poses(src, dst, labels, num_objects: int, min_points: int = 3):
    """Each object's best rigid motion of its points: poses [K, 4, 4] (x -> R x + t, world space) minimising
    sum_i |R src_i + t - dst_i|^2 over the points with ``labels`` [N] == k (Kabsch: t from the centroids, R from
    the SVD of their cross-covariance, its determinant made +1). ``src``, ``dst``: [N, 3]; labels in -1..K-1
    (-1: in no object). An object with fewer than ``min_points`` points gets its centroid shift only (R = I;
    none: the identity), so that one or two points never pick an arbitrary turn. Jitted for each K.

    Not differentiable: the result is held constant under differentiation (a rotation fitted by an SVD has no
    gradient where singular values coincide), so gradients of the poses are 0, never NaN."""
    return _fit_group_poses(jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32),
                            jnp.asarray(labels, jnp.int32), int(num_objects), int(min_points))


@functools.partial(jax.jit, static_argnums=(3, 4))
def _fit_group_poses(src, dst, labels, num_objects, min_points):
    src, dst = jax.lax.stop_gradient(src), jax.lax.stop_gradient(dst)
    w = (labels[:, None] == jnp.arange(num_objects)[None]).astype(src.dtype)  # [N, K]
    n = jnp.sum(w, 0)  # [K]
    inv = 1.0 / jnp.maximum(n, 1.0)
    c_src = jnp.matmul(w.T, src, precision=HIGHEST) * inv[:, None]  # [K, 3]
    c_dst = jnp.matmul(w.T, dst, precision=HIGHEST) * inv[:, None]
    k = jnp.clip(labels, 0)
    a, b = src - c_src[k], dst - c_dst[k]  # [N, 3] each, centred on their object's centroid
    cov = jnp.einsum("nk,ni,nj->kij", w, a, b, precision=HIGHEST)  # [K, 3, 3]
    u, _, vt = jnp.linalg.svd(cov)
    v = jnp.swapaxes(vt, -1, -2)
    d = jnp.sign(jnp.linalg.det(jnp.matmul(v, jnp.swapaxes(u, -1, -2), precision=HIGHEST)))  # [K]
    d = jnp.where(d == 0, 1.0, d)
    fix = jnp.ones((num_objects, 3), src.dtype).at[:, 2].set(d)
    rot = jnp.matmul(v * fix[:, None, :], jnp.swapaxes(u, -1, -2), precision=HIGHEST)  # [K, 3, 3] maps a -> b
    ok = (n >= min_points) & jnp.all(jnp.isfinite(rot), axis=(-1, -2))
    rot = jnp.where(ok[:, None, None], rot, jnp.eye(3, dtype=src.dtype))
    t = c_dst - jnp.einsum("kij,kj->ki", rot, c_src, precision=HIGHEST)
    return geometry.make_pose(rot, t)


def label_onehot(labels, num_objects: int) -> np.ndarray:
    """Per-Gaussian features [N, K + 1] float32 for rendering object masks: channel 0 for the static
    Gaussians (label -1), channel k + 1 for object k."""
    labels = np.asarray(labels)
    out = np.zeros((len(labels), num_objects + 1), np.float32)
    out[np.arange(len(labels)), np.where(labels >= 0, labels + 1, 0)] = 1.0
    return out


def _pixel_centres(width: int, height: int) -> np.ndarray:
    """Pixel centres [H * W, 2] in K's coordinates, row-major."""
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2)


def _interior(own: np.ndarray, erode: int) -> np.ndarray:
    """The mask `own` [H, W] without the pixels within `erode` pixels of its edge (the flow is smoothed
    across object edges, towards the background's)."""
    import cv2

    if erode <= 0:
        return own
    return cv2.erode(own.astype(np.uint8), np.ones((2 * erode + 1, 2 * erode + 1), np.uint8)) > 0


def _project_rows(moved, viewmat, K):
    """Pixels [..., M, 2] of world points `moved` [..., M, 3] in cameras `viewmat` [..., 4, 4], `K` [..., 3, 3]
    (points at or behind z = 1e-3 give 0 and are flagged False)."""
    pc = jnp.einsum("...mj,...ij->...mi", moved, viewmat[..., :3, :3], precision=HIGHEST) + viewmat[..., None, :3, 3]
    z = pc[..., 2]
    ok = z > 1e-3
    zs = jnp.where(ok, z, 1.0)
    uv = jnp.stack([K[..., None, 0, 0] * pc[..., 0] / zs + K[..., None, 0, 2],
                    K[..., None, 1, 1] * pc[..., 1] / zs + K[..., None, 1, 2]], -1)
    return uv, ok


def _residuals(xi, args):
    pts, target, w, centre, viewmat, K = args
    rot = geometry.so3_exp(xi[:3])
    moved = matmul(pts - centre, rot.T) + centre + xi[3:]  # [M, 3]
    uv, ok = _project_rows(moved, viewmat, K)
    r = jnp.where(ok[:, None], uv - target, 0.0)
    return jnp.sqrt(w)[:, None] * r


@functools.partial(jax.jit, static_argnames=("irls",))
@full_precision  # the solver's normal equations too (no TF32 on GPUs)
def rigid_increment(pts, target, weights, viewmat, K, *, irls: int = 2, huber_px: float = 1.0):
    """Rigid motion (about the weighted centroid) moving world points `pts` [M, 3] onto pixels `target`
    [M, 2] of camera (`viewmat`, `K`): returns (Delta [4, 4] world transform, RMS pixel error of the inliers).

    ``weights`` [M] >= 0 (0 = padding). Huber weights are updated `irls` times, then a plain least-squares
    fit on the inliers (residual < 3 Huber widths) gives the result."""
    dt = jnp.result_type(float)  # the default float (geometry computes in it): float64 under jax_enable_x64
    pts = jnp.asarray(pts, dt)
    target = jnp.asarray(target, dt)
    w0 = jnp.asarray(weights, dt)
    viewmat = jnp.asarray(viewmat, dt)
    K = jnp.asarray(K, dt)
    centre = jnp.sum(w0[:, None] * pts, 0) / jnp.maximum(jnp.sum(w0), 1e-9)
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6)
    xi = jnp.zeros(6, dt)
    w = w0
    for _ in range(irls):
        sol = optx.least_squares(_residuals, solver, xi, args=(pts, target, w, centre, viewmat, K), max_steps=30,
                                 throw=False)
        xi = jnp.where(jnp.all(jnp.isfinite(sol.value)), sol.value, xi)
        r = jnp.linalg.norm(_residuals(xi, (pts, target, jnp.ones_like(w0), centre, viewmat, K)), axis=-1)
        w = w0 * jnp.minimum(1.0, huber_px / jnp.maximum(r, 1e-9))
    # a last least-squares fit on the inliers only (Huber weights still bias it by the outliers' pull)
    inl = (w0 > 0) & (r < 3.0 * huber_px)
    sol = optx.least_squares(_residuals, solver, xi, args=(pts, target, w0 * inl, centre, viewmat, K), max_steps=30,
                             throw=False)
    xi = jnp.where(jnp.all(jnp.isfinite(sol.value)) & (jnp.sum(inl) >= 6), sol.value, xi)
    rot = geometry.so3_exp(xi[:3])
    delta = jnp.eye(4, dtype=dt).at[:3, :3].set(rot).at[:3, 3].set(centre - matmul(rot, centre) + xi[3:])
    r = jnp.linalg.norm(_residuals(xi, (pts, target, jnp.ones_like(w0), centre, viewmat, K)), axis=-1)
    inl = (w0 > 0) & (r < 3.0 * huber_px)
    rms = jnp.sqrt(jnp.sum(jnp.where(inl, r * r, 0.0)) / jnp.maximum(jnp.sum(inl), 1))
    return delta, rms


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
    uv, ok = _project_rows(_joint_moved(x, pts, kind), viewmats, K)
    r = jnp.where(ok[..., None], uv - target, 0.0) * jnp.sqrt(w)[..., None]  # [J, M, 2]
    # gauge: a unit axis, and (revolute) the pivot's position along the axis pinned to the centroid's
    gauge = jnp.stack([jnp.sum(x[:3] ** 2) - 1.0, jnp.sum((x[3:6] - centre) * x[:3])])
    return r.reshape(-1), gauge, damp * x[6:]  # damp: a pair without data keeps amount 0


@functools.partial(jax.jit, static_argnames=("kind", "irls"))
@full_precision  # the Cholesky of the normal equations too (no TF32 on GPUs)
def _fit_joint_jit(x0, pts, target, weights, viewmats, K, centre, *, kind: str, irls: int, huber_px: float):
    # the damped normal equations (J^T J + lambda I, 6 + J unknowns) by Cholesky instead of the default QR of the
    # [J M 2 + ..., 6 + J] Jacobian: the same fits (inlier RMS equal to 1e-7 px on the default scene's objects)
    # 5-15x faster (docs/benchmarks.md, session 17)
    solver = optx.LevenbergMarquardt(rtol=1e-7, atol=1e-7, linear_solver=lx.Normal(lx.Cholesky()))
    fn = functools.partial(_joint_residuals, kind=kind)

    def round_(carry, _):  # one reweighting round; a loop, so that the solver compiles once, not irls + 1 times
        x, w, _r = carry
        sol = optx.least_squares(fn, solver, x, args=(pts, target, w, viewmats, K, 1e-3, centre), max_steps=60,
                                 throw=False)
        x = jnp.where(jnp.all(jnp.isfinite(sol.value)), sol.value, x)
        uv, ok = _project_rows(_joint_moved(x, pts, kind), viewmats, K)
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


def fit_joint(pts, target, weights, viewmats, K, kind: str, *, axes=None, huber_px: float = 1.0, irls: int = 2):
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


def _bucket(n: int) -> int:
    return max(256, 1 << int(np.ceil(np.log2(max(n, 1)))))


def _pixel_points(xy, depth, flow, viewmat0, K0, m: int):
    """Pixels `xy` [n, 2] of camera 0 back-projected at their camera z-`depth` [n] (world points), with their
    targets ``xy + flow`` [n, 2], padded with zero weights to length m >= n: (pts [m, 3], target [m, 2],
    weights [m] float32)."""
    n = len(xy)
    centre, rays = pixel_rays(viewmat0, K0, xy)  # ray parameter = camera z-depth
    pts = np.zeros((m, 3))
    pts[:n] = centre + depth[:, None] * rays
    target = np.zeros((m, 2))
    target[:n] = xy + flow
    w = np.zeros(m, np.float32)
    w[:n] = 1.0
    return pts, target, w


def _fit_pixels(xy, depth, flow, viewmat0, K0, viewmat1, K1, **kw):
    """`rigid_increment` of pixels `xy` [M, 2] of camera 0, back-projected at their camera z-`depth` [M],
    onto ``xy + flow`` [M, 2] in camera 1: (Delta [4, 4], inlier RMS). The arrays are padded with zero
    weights to a power-of-two length, so a handful of compiled sizes serve every call."""
    pts, target, w = _pixel_points(xy, depth, flow, viewmat0, K0, _bucket(len(xy)))
    return rigid_increment(pts, target, w, jnp.asarray(viewmat1), jnp.asarray(K1), **kw)


def _joint_arrays(data: list, m: int, viewmats0, Ks0, viewmats1, Ks1):
    """`fit_joint`'s padded inputs [J, M = m, ...] from a list of (xy, depth, flow), one per pair, and
    the pairs' first- and second-frame cameras."""
    rows = [_pixel_points(xy, depth, flow, viewmats0[i], Ks0[i], m) for i, (xy, depth, flow) in enumerate(data)]
    pts, tgt, w = (np.stack(a) for a in zip(*rows, strict=True))
    return pts, tgt, w, np.stack(viewmats1), np.stack(Ks1)


def track_objects(means, quats, scales, opacities, labels, num_objects: int, viewmats, Ks, flows, width: int,
                  height: int, *, moving=None, joints: str = "auto", joint_pixels: int = 256, joint_tolerance: float = 3.0,
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
    from fgjax.render.api import rasterization

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
            delta, rms = _fit_pixels(pix[idx], depth.reshape(-1)[idx], flow[idx], viewmats[j], Ks[j],
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


def camera_correction(depth, valid, flow, viewmat0, viewmat1, K, *, huber_px: float = 1.0, irls: int = 5,
                      min_pixels: int = 100, max_pixels: int = 4096) -> tuple[np.ndarray, float, int]:
    """Camera t's pose corrected so that the static scene explains the observed flow t-1 -> t.

    With noisy poses, u_cam (the flow the camera alone causes) inherits the pose error, about one pixel
    per 0.5 degree here, and u - u_cam then marks static pixels as moving. Most pixels are static, so
    the rigid motion of the whole back-projected frame (pixels of frame t-1 at their rendered ``depth``
    [H, W], where ``valid`` [H, W] and the ``flow`` [H, W, 2] is finite) that best moves them onto
    m + u(m) in camera t (`rigid_increment`: Huber IRLS, then a fit on the inliers; moving parts are its
    outliers) is the pose error: viewmat1' = viewmat1 @ Delta. Returns (viewmat1' [4, 4] OpenCV
    world-to-camera, inlier RMS in pixels, pixels used); fewer than ``min_pixels`` usable pixels
    return viewmat1 unchanged (RMS NaN). Six unknowns need few pixels: at most ``max_pixels``, evenly
    strided over the usable ones, enter the fit."""
    depth = np.asarray(depth, np.float64)
    flow = np.asarray(flow, np.float64)
    h, w = depth.shape
    ok = np.asarray(valid, bool) & np.all(np.isfinite(flow), -1) & np.isfinite(depth) & (depth > 0)
    idx = np.flatnonzero(ok.reshape(-1))
    vm1 = np.asarray(viewmat1, np.float64)
    if len(idx) < min_pixels:
        return vm1, float("nan"), int(len(idx))
    if len(idx) > max_pixels:
        idx = idx[np.linspace(0, len(idx) - 1, max_pixels).round().astype(int)]
    ys, xs = np.divmod(idx, w)
    xy = np.stack([xs + 0.5, ys + 0.5], -1)  # pixel centres at +0.5
    K = np.asarray(K, np.float64)
    # more reweighting rounds than for one object: a quarter of the frame may move, and the first
    # (unweighted) fit is pulled far enough that some moving pixels look like inliers after two rounds
    delta, rms = _fit_pixels(xy, depth.reshape(-1)[idx], flow.reshape(-1, 2)[idx], np.asarray(viewmat0, np.float64),
                             K, vm1, K, irls=irls, huber_px=huber_px)
    return vm1 @ np.asarray(delta, np.float64), float(rms), int(len(idx))


def chained_joint_poses(means, quats, scales, opacities, labels, poses, moving, viewmats, Ks, flows, width: int,
                        height: int, *, points: int = 512, dominance: float = 0.6, erode: int = 1,
                        huber_px: float = 1.5, tile_size: int = 8, log=print):
    """Poses [K, T, 4, 4] of each object from its reference points followed through chained flow, one
    articulation per object (`fit_joint` on absolute amounts); objects whose fit fails keep `poses`.

    Pair-by-pair increments see only the flow of one pair: a door turning towards the camera barely moves
    in the image from one frame to the next, and the increments under-rotate it (9 of 76 degrees on the
    default scene). Over a whole moving run its outline shrinks by many pixels. For each run [a, b] of an
    object's moving pairs (`moving` [K, T-1]), the pixels it paints in frame a (the reference Gaussians
    `means` [N, 3], `quats`, `scales`, `opacities`, labels [N], moved by its pose in frame a; interior
    pixels only) are back-projected at that render's depth to reference-space points, and followed through
    the flows `flows` [T-1, H, W, 2] to frames a+1..b+1 (lost where the flow is unknown). Every (point,
    frame) pair then constrains that frame's absolute pose; one revolute or prismatic joint with one
    amount per frame, fitted to all of them (the kind with the lower robust cost), gives the poses (frames
    after a run keep its last pose).
    A run's points are seeded with the object's pose in frame a from `poses`; a second call re-seeds
    later runs with the poses the first one fitted.

    Returns:
        (poses [K, T, 4, 4], per-object inlier RMS [K] in pixels (NaN: not re-fitted)).
    """
    from fgjax.cluster import true_runs
    from fgjax.pipeline.poses import sample_bilinear
    from fgjax.render.api import rasterization

    poses = np.array(poses, np.float64)
    num_objects, t = poses.shape[:2]
    labels = np.asarray(labels)
    onehot = label_onehot(labels, num_objects)
    pix = _pixel_centres(width, height)
    rms_out = np.full(num_objects, np.nan)
    for k in range(num_objects):
        runs = true_runs(np.asarray(moving[k], bool))
        if not runs:
            continue
        rows = []  # (reference points [M, 3], pixels [M, 2], frame)
        for run in runs:
            a, b = int(run[0]), int(run[-1])
            m_a, q_a = transform_gaussians(jnp.asarray(means), jnp.asarray(quats), jnp.asarray(labels),
                                           jnp.asarray(poses[:, a], jnp.float32))
            feat, alpha, info = rasterization(m_a, q_a, jnp.asarray(scales), jnp.asarray(opacities),
                                              jnp.asarray(onehot), jnp.asarray(viewmats[a], jnp.float32),
                                              jnp.asarray(Ks[a], jnp.float32), width, height, render_depth=True,
                                              tile_size=tile_size)
            alpha, depth = np.asarray(alpha), np.asarray(info["depth"])
            own = _interior((np.asarray(feat)[..., k + 1] / np.maximum(alpha, 1e-9) > dominance) & (alpha > 0.5)
                            & (depth > 0), erode)
            idx = np.flatnonzero(own.reshape(-1))
            if len(idx) < 30:
                continue
            idx = idx[np.linspace(0, len(idx) - 1, min(len(idx), points)).round().astype(int)]
            centre, rays = pixel_rays(viewmats[a], Ks[a], pix[idx])
            world = centre + depth.reshape(-1)[idx, None] * rays  # [M, 3] in frame a
            inv = np.linalg.inv(poses[k, a])
            ref = world @ inv[:3, :3].T + inv[:3, 3]  # reference-space points
            pos = pix[idx].astype(np.float64)
            for j in range(a, b + 1):
                pos = pos + sample_bilinear(np.asarray(flows[j], np.float64), pos)
                ok = np.all(np.isfinite(pos), -1)  # a track is lost for good where the flow is unknown
                ref, pos = ref[ok], pos[ok]
                if len(pos) < 30:
                    break
                rows.append((ref, pos, j + 1))
        if len(rows) < 2:
            continue
        m = _bucket(max(len(r[0]) for r in rows))
        pts = np.zeros((len(rows), m, 3))
        tgt = np.zeros((len(rows), m, 2))
        w = np.zeros((len(rows), m))
        for i, (p, q, _) in enumerate(rows):
            pts[i, :len(p)], tgt[i, :len(p)], w[i, :len(p)] = p, q, 1.0
        frames = [r[2] for r in rows]
        fits = {kind: fit_joint(pts, tgt, w, viewmats[frames], Ks[frames], kind, huber_px=huber_px)
                for kind in JOINT_KINDS}
        kind = min(fits, key=lambda c: fits[c][5])  # the lower robust cost
        inc, rms, frac = fits[kind][:3]
        rms_out[k] = rms
        new = poses[k].copy()
        at = dict(zip(frames, inc, strict=True))  # each frame's absolute pose (runs do not share frames)
        for j in range(1, t):
            new[j] = at.get(j, new[j - 1])
        poses[k] = new
        log(f"tracking: object {k + 1}: chained flow over {len(runs)} run(s), {len(rows)} frames -> {kind}, inlier "
            f"RMS {rms:.2f} px ({100 * frac:.0f}% inliers)")
    return poses, rms_out
