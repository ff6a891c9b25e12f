"""EWA projection of 3D Gaussians to screen space (gsplat rules, DESIGN.md section 2).

Conventions: OpenCV camera (x right, y down, z forward); ``viewmat`` is world-to-camera 4x4;
``K`` is 3x3 with pixel (j, i) centred at (j + 0.5, i + 0.5); quaternions are wxyz of any norm;
scales and opacities are *activated* (scales > 0, opacities in [0, 1]).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from fgjax.geometry import matmul as _mm  # full float32 precision on every backend

# Rasterization constants shared by the tile rasterizer and documented in DESIGN.md.
ALPHA_MIN = 1.0 / 255.0  # a Gaussian counts at a pixel exactly when alpha >= ALPHA_MIN
ALPHA_MAX = 0.99  # alpha = min(ALPHA_MAX, o * exp(-q / 2))
T_MIN = 1e-4  # compositing stops before transmittance would drop to <= T_MIN
LOWPASS = 0.3  # px^2 added to the diagonal of every 2D covariance
FOV_CLAMP = 0.3  # Jacobian evaluated with x/z, y/z clamped to the image frustum + 0.3 tan(fov/2)


class Projected(NamedTuple):
    """Per-Gaussian screen-space quantities (all leading dims [N])."""

    means2d: Float[Array, "N 2"]  # pixel coordinates of the projected centre (not clamped)
    conics: Float[Array, "N 3"]  # inverse 2D covariance (a, b, c): q = a dx^2 + 2 b dx dy + c dy^2
    cov2d: Float[Array, "N 3"]  # 2D covariance (xx, xy, yy) including the low-pass term
    depths: Float[Array, " N"]  # camera-space z of the centre
    extent: Float[Array, "N 2"]  # half-size in pixels of the bbox of the alpha >= 1/255 ellipse
    valid: Bool[Array, " N"]  # in front of the near plane, opacity >= 1/255, finite


def quat_to_rotmat(quats: Float[Array, "N 4"]) -> Float[Array, "N 3 3"]:
    """Rotation matrices of wxyz quaternions of any norm (a zero quaternion maps to identity).

    The rasterizer's form (as gsplat's): q normalised first, then the unit-quaternion matrix. It agrees with
    `fgjax.geometry.quat_to_rotmat` (the closed form R = I + 2/|q|^2 [...]) to rounding; the rasterizer keeps its own
    so that its renders, and the runs built on them, stay bit-for-bit as they are."""
    n2 = jnp.sum(quats * quats, axis=-1, keepdims=True)  # [N, 1]
    ok = n2 > 0
    q = jnp.where(ok, quats, jnp.array([1.0, 0.0, 0.0, 0.0], quats.dtype))
    q = q * jnp.reciprocal(jnp.sqrt(jnp.where(ok, n2, 1.0)))  # double-where: finite grads at 0
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)  # [N, 3, 3]


def covariance3d(quats: Float[Array, "N 4"], scales: Float[Array, "N 3"]) -> Float[Array, "N 3 3"]:
    """World-space covariance Sigma = R S^2 R^T of each Gaussian."""
    rot = quat_to_rotmat(quats)  # [N, 3, 3]
    m = rot * scales[..., None, :]  # R S, [N, 3, 3]
    return _mm(m, jnp.swapaxes(m, -1, -2))


def project_gaussians(
    means: Float[Array, "N 3"],
    quats: Float[Array, "N 4"],
    scales: Float[Array, "N 3"],
    opacities: Float[Array, " N"],
    viewmat: Float[Array, "4 4"],
    K: Float[Array, "3 3"],
    width: int,
    height: int,
    near_plane: float = 0.01,
) -> Projected:
    """EWA splatting: Sigma' = J W Sigma W^T J^T + 0.3 I, with J at the frustum-clamped centre.

    The 2D mean itself is the unclamped pinhole projection. Gaussians with depth <= near_plane,
    opacity < 1/255, or any non-finite input are marked invalid; their outputs stay finite.
    """
    dtype = means.dtype
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = _mm(means, R.T) + t  # [N, 3] camera coordinates
    finite = (
        jnp.all(jnp.isfinite(means), -1)
        & jnp.all(jnp.isfinite(quats), -1)
        & jnp.all(jnp.isfinite(scales), -1)
        & jnp.isfinite(opacities)
    )
    z_raw = p[:, 2]
    valid = finite & (z_raw > near_plane) & (opacities >= ALPHA_MIN)
    # Safe stand-ins for invalid Gaussians so that nothing below produces inf/NaN (double-where).
    p = jnp.where(valid[:, None], p, jnp.array([0.0, 0.0, 1.0], dtype))
    scales_s = jnp.where(valid[:, None], scales, 1.0)
    quats_s = jnp.where(valid[:, None], quats, jnp.array([1.0, 0.0, 0.0, 0.0], dtype))
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    inv_z = 1.0 / z
    means2d = jnp.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], axis=-1)  # [N, 2]

    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    tx = z * jnp.clip(x * inv_z, -cx / fx - FOV_CLAMP * tan_x, (width - cx) / fx + FOV_CLAMP * tan_x)
    ty = z * jnp.clip(y * inv_z, -cy / fy - FOV_CLAMP * tan_y, (height - cy) / fy + FOV_CLAMP * tan_y)
    zeros = jnp.zeros_like(z)
    J = jnp.stack(
        [
            jnp.stack([fx * inv_z, zeros, -fx * tx * inv_z * inv_z], -1),
            jnp.stack([zeros, fy * inv_z, -fy * ty * inv_z * inv_z], -1),
        ],
        axis=-2,
    )  # [N, 2, 3]
    cov_w = covariance3d(quats_s, scales_s)  # [N, 3, 3]
    JW = _mm(J, R)  # [N, 2, 3]
    cov = _mm(_mm(JW, cov_w), jnp.swapaxes(JW, -1, -2))  # [N, 2, 2]
    a = cov[:, 0, 0] + LOWPASS
    b = 0.5 * (cov[:, 0, 1] + cov[:, 1, 0])
    c = cov[:, 1, 1] + LOWPASS
    det = a * c - b * b  # >= 0.09 for a PSD covariance, but guard against round-off on huge scales
    det_ok = valid & (det > 0) & jnp.isfinite(det)
    inv_det = 1.0 / jnp.where(det_ok, det, 1.0)
    conics = jnp.stack([c * inv_det, -b * inv_det, a * inv_det], axis=-1)  # [N, 3]

    # alpha >= 1/255  <=>  q <= 2 ln(255 o); the ellipse's bounding box has half-sizes r sqrt(cov_ii).
    r2 = 2.0 * jnp.log(jnp.maximum(opacities * 255.0, 1.0))
    # Only used for binning (integers), never differentiated.
    extent = jax.lax.stop_gradient(jnp.sqrt(r2[:, None] * jnp.stack([a, c], axis=-1)))  # [N, 2]
    valid = det_ok & jnp.all(jnp.isfinite(means2d), -1) & jnp.all(jnp.isfinite(extent), -1)
    return Projected(
        means2d=means2d,
        conics=conics,
        cov2d=jnp.stack([a, b, c], axis=-1),
        depths=z_raw,
        extent=extent,
        valid=valid,
    )
