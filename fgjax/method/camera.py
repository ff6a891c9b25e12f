"""Rigid motion from pixel correspondences, and the camera-pose correction of discovery (DESIGN.md section 1, step 5).

`rigid_increment` solves

    min_{omega, tau}  sum_m  w_m  rho( | pi(K, V (R(omega) (P_m - c) + c + tau)) - target_m |^2 )

for world points P_m (centroid c) and their observed pixels in a camera V (world-to-camera 4x4, OpenCV), rho a Huber
loss (iteratively reweighted), with optimistix's Levenberg-Marquardt on 6 unknowns. `camera_correction` applies it to
the back-projected pixels of a whole frame: most pixels are static, so the rigid motion that best explains their
optical flow is the error of the relative camera pose, and moving parts are its outliers.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from fgjax import geometry
from fgjax.geometry import HIGHEST, full_precision, matmul
from fgjax.method.init_points import pixel_rays

__all__ = ["project_rows", "rigid_increment", "bucket_size", "pixel_points", "fit_pixels", "camera_correction"]


def project_rows(moved: Float[ArrayLike, "*batch M 3"], viewmat: Float[ArrayLike, "*batch 4 4"],
                 K: Float[ArrayLike, "*batch 3 3"]) -> tuple[Float[Array, "*batch M 2"], Bool[Array, "*batch M"]]:
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
    uv, ok = project_rows(moved, viewmat, K)
    r = jnp.where(ok[:, None], uv - target, 0.0)
    return jnp.sqrt(w)[:, None] * r


@functools.partial(jax.jit, static_argnames=("irls",))
@full_precision  # the solver's normal equations too (no TF32 on GPUs)
def rigid_increment(pts: Float[ArrayLike, "M 3"], target: Float[ArrayLike, "M 2"], weights: Float[ArrayLike, " M"],
                    viewmat: Float[ArrayLike, "4 4"], K: Float[ArrayLike, "3 3"], *, irls: int = 2,
                    huber_px: float = 1.0) -> tuple[Float[Array, "4 4"], Float[Array, ""]]:
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


def bucket_size(n: int) -> int:
    return max(256, 1 << int(np.ceil(np.log2(max(n, 1)))))


def pixel_points(xy, depth, flow, viewmat0, K0, m: int):
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


def fit_pixels(xy, depth, flow, viewmat0, K0, viewmat1, K1, **kw):
    """`rigid_increment` of pixels `xy` [M, 2] of camera 0, back-projected at their camera z-`depth` [M],
    onto ``xy + flow`` [M, 2] in camera 1: (Delta [4, 4], inlier RMS). The arrays are padded with zero
    weights to a power-of-two length, so a handful of compiled sizes serve every call."""
    pts, target, w = pixel_points(xy, depth, flow, viewmat0, K0, bucket_size(len(xy)))
    return rigid_increment(pts, target, w, jnp.asarray(viewmat1), jnp.asarray(K1), **kw)


def camera_correction(depth: Float[ArrayLike, "H W"], valid: Bool[ArrayLike, "H W"], flow: Float[ArrayLike, "H W 2"],
                      viewmat0: Float[ArrayLike, "4 4"], viewmat1: Float[ArrayLike, "4 4"], K: Float[ArrayLike, "3 3"],
                      *, huber_px: float = 1.0, irls: int = 5, min_pixels: int = 100,
                      max_pixels: int = 4096) -> tuple[Float[np.ndarray, "4 4"], float, int]:
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
    delta, rms = fit_pixels(xy, depth.reshape(-1)[idx], flow.reshape(-1, 2)[idx], np.asarray(viewmat0, np.float64),
                             K, vm1, K, irls=irls, huber_px=huber_px)
    return vm1 @ np.asarray(delta, np.float64), float(rms), int(len(idx))
