"""Camera-motion flow: pixel centres, camera velocity, the motion field u = A v / Z + B omega, exact
reprojection flow and per-Gaussian image velocity (DESIGN.md section 1, step 3; conventions in `fgjax.flow`)."""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from fgjax import geometry
from fgjax.flow._common import check_shape, intrinsics, mm, safe_inv_depth
from fgjax.geometry import as_float


@functools.partial(jax.jit, static_argnames=("height", "width", "dtype"))
def pixel_centers(height: int, width: int, dtype=None) -> Float[Array, "H W 2"]:
    """Pixel centres m[i, j] = (j + 0.5, i + 0.5) as (x, y), shape [H, W, 2]."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    x = jnp.arange(width, dtype=dtype) + 0.5
    y = jnp.arange(height, dtype=dtype) + 0.5
    xx, yy = jnp.meshgrid(x, y, indexing="xy")  # [H, W] each
    return jnp.stack([xx, yy], axis=-1)


# ----------------------------------------------------------------------------------------------
# camera flow
# ----------------------------------------------------------------------------------------------


@jax.jit
def camera_velocity(
    c2w0: Float[ArrayLike, "4 4"], c2w1: Float[ArrayLike, "4 4"], dt: float | ArrayLike = 1.0
) -> tuple[Float[Array, 3], Float[Array, 3]]:
    """Camera velocity (v, omega) between two OpenCV camera-to-world poses, in camera-0 coordinates.

    v = R0^T (c1 - c0) / dt,  omega = log(R0^T R1) / dt  (DESIGN section 1, step 3), with c_i the camera
    centres (translation column of c2w_i) and log the SO(3) logarithm (rotation vector, angle <= pi).

    Relation to twists: if c2w1 = c2w0 @ se3_exp(dt [w, u]) then omega == w but v == V(dt w) u (the
    SE(3) exponential moves the centre along an arc); v == u exactly when c1 = c0 + dt R0 u. Both agree
    with the instantaneous velocity as dt -> 0. Batched poses: use ``jax.vmap``.

    Args:
        c2w0: camera-to-world pose at t-1 (OpenCV), [4, 4].
        c2w1: camera-to-world pose at t (OpenCV), [4, 4].
        dt: time between the frames (non-zero; dt == 0 returns zeros rather than inf).

    Returns:
        (v [3], omega [3]) in camera-0 coordinates, per unit of dt.
    """
    c2w0, c2w1 = as_float(c2w0), as_float(c2w1)
    check_shape("c2w0", c2w0, (4, 4))
    check_shape("c2w1", c2w1, (4, 4))
    dt = jnp.asarray(dt, dtype=c2w0.dtype)
    inv_dt = jnp.where(dt != 0, 1.0 / jnp.where(dt != 0, dt, 1.0), 0.0)
    r0t = c2w0[:3, :3].T
    v = mm(r0t, c2w1[:3, 3] - c2w0[:3, 3]) * inv_dt
    omega = geometry.so3_log(mm(r0t, c2w1[:3, :3])) * inv_dt
    return v, omega


@jax.jit
def motion_field_matrices(
    xy: Float[ArrayLike, "*batch 2"], K: Float[ArrayLike, "3 3"]
) -> tuple[Float[Array, "*batch 2 3"], Float[Array, "*batch 2 3"]]:
    """The translational and rotational motion-field matrices A(m), B(m) (DESIGN section 1, step 3).

    A = [[-fx, 0, x~], [0, -fy, y~]],
    B = [[x~ y~ / fy, -fx - x~^2 / fx, y~ fx / fy], [fy + y~^2 / fy, -x~ y~ / fx, -x~ fy / fx]],
    with x~ = x - cx, y~ = y - cy. The projection Jacobian is J(P) = -A(pi(P)) / Z and
    B(pi(P)) omega = J(P) (-omega x P) exactly.

    Args:
        xy: pixel coordinates (centres at +0.5), [..., 2].
        K: intrinsics, [3, 3] (zero skew assumed).

    Returns:
        (A [..., 2, 3], B [..., 2, 3]).
    """
    xy, K = as_float(xy), as_float(K)
    fx, fy, cx, cy = intrinsics(K)
    xt, yt = xy[..., 0] - cx, xy[..., 1] - cy
    zero = jnp.zeros_like(xt)
    a = jnp.stack(
        [jnp.stack([-fx + zero, zero, xt], -1), jnp.stack([zero, -fy + zero, yt], -1)], axis=-2
    )
    b = jnp.stack(
        [
            jnp.stack([xt * yt / fy, -fx - xt * xt / fx, yt * fx / fy], -1),
            jnp.stack([fy + yt * yt / fy, -xt * yt / fx, -xt * fy / fx], -1),
        ],
        axis=-2,
    )
    return a, b


@jax.jit
def motion_field_inv_depth(
    xy: Float[ArrayLike, "*batch 2"],
    inv_depth: Float[ArrayLike, "*batch"],
    K: Float[ArrayLike, "3 3"],
    v: Float[ArrayLike, 3],
    omega: Float[ArrayLike, 3],
) -> Float[Array, "*batch 2"]:
    """Motion field u = A v rho + B omega with the inverse depth rho = 1/Z given directly.

    Linear in rho, which is what makes Lemma 1 exact with the composited inverse depth
    (``composited_inverse_depth``); rho = 0 is a point at infinity (pure rotational flow).

    Args:
        xy: pixel coordinates (centres at +0.5), [..., 2].
        inv_depth: inverse camera-frame depth 1/Z, [...] (broadcast against xy[..., 0]).
        K: intrinsics, [3, 3] (zero skew assumed).
        v: camera translational velocity in camera-0 coordinates, [3].
        omega: camera angular velocity in camera-0 coordinates, [3].

    Returns:
        Flow in pixels per unit time, [..., 2].
    """
    xy, K, v, omega = as_float(xy), as_float(K), as_float(v), as_float(omega)
    rho = as_float(inv_depth)
    fx, fy, cx, cy = intrinsics(K)
    xt, yt = xy[..., 0] - cx, xy[..., 1] - cy
    # A v and B omega written out (cheaper than building the [..., 2, 3] matrices)
    av_x = -fx * v[0] + xt * v[2]
    av_y = -fy * v[1] + yt * v[2]
    bw_x = xt * yt / fy * omega[0] - (fx + xt * xt / fx) * omega[1] + yt * fx / fy * omega[2]
    bw_y = (fy + yt * yt / fy) * omega[0] - xt * yt / fx * omega[1] - xt * fy / fx * omega[2]
    return jnp.stack([av_x * rho + bw_x, av_y * rho + bw_y], axis=-1)


@jax.jit
def motion_field(
    xy: Float[ArrayLike, "*batch 2"],
    depth: Float[ArrayLike, "*batch"],
    K: Float[ArrayLike, "3 3"],
    v: Float[ArrayLike, 3],
    omega: Float[ArrayLike, 3],
) -> Float[Array, "*batch 2"]:
    """First-order camera flow u = A(m) v / Z + B(m) omega of static points (DESIGN section 1, step 3).

    Follows from P' = -v - omega x P and the projection Jacobian J(P) = -A / Z; it is the exact
    instantaneous image velocity, and a first-order approximation of the flow between two frames when
    (v, omega) come from ``camera_velocity`` with dt = 1 frame.

    Args:
        xy: pixel coordinates (centres at +0.5), [..., 2].
        depth: camera-frame depth Z (z coordinate, not ray length), [...]. Non-positive or non-finite
            depth is treated as a point at infinity (rotational flow only); mask such pixels yourself.
        K: intrinsics, [3, 3] (zero skew assumed).
        v: camera translational velocity in camera-0 coordinates, [3].
        omega: camera angular velocity in camera-0 coordinates, [3].

    Returns:
        Flow (dx, dy) in pixels per unit time, [..., 2].
    """
    return motion_field_inv_depth(xy, safe_inv_depth(as_float(depth)), K, v, omega)


@jax.jit
def reprojection_flow(
    depth: Float[ArrayLike, "H W"],
    K: Float[ArrayLike, "3 3"],
    c2w0: Float[ArrayLike, "4 4"],
    c2w1: Float[ArrayLike, "4 4"],
) -> tuple[Float[Array, "H W 2"], Bool[Array, "H W"]]:
    """Exact camera flow by reprojection: u(m) = pi(K, T1^-1 T0 Z K^-1 m~) - m.

    Each frame-0 pixel centre m is back-projected with its depth Z (camera z), moved into camera 1 with
    the OpenCV camera-to-world poses, and projected with the same K.

    Args:
        depth: frame-0 depth map (camera z), [H, W].
        K: intrinsics, [3, 3] (skew honoured).
        c2w0: camera-to-world pose of frame 0 (OpenCV), [4, 4].
        c2w1: camera-to-world pose of frame 1 (OpenCV), [4, 4].

    Returns:
        flow: [H, W, 2] (dx, dy) in pixels, 0 where invalid.
        valid: [H, W] bool, False for non-positive or non-finite depth and for points that land on or
            behind camera 1's image plane (z1 <= eps * Z).
    """
    depth, K, c2w0, c2w1 = as_float(depth), as_float(K), as_float(c2w0), as_float(c2w1)
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape [H, W]; got {list(depth.shape)}.")
    check_shape("K", K, (3, 3))
    check_shape("c2w0", c2w0, (4, 4))
    check_shape("c2w1", c2w1, (4, 4))
    h, w = depth.shape
    m = pixel_centers(h, w, depth.dtype)  # [H, W, 2]
    ok0 = jnp.isfinite(depth) & (depth > 0)
    z = jnp.where(ok0, depth, 1.0)
    fx, fy, cx, cy = intrinsics(K)
    yn = (m[..., 1] - cy) / fy
    xn = (m[..., 0] - cx - K[0, 1] * yn) / fx
    rel = mm(geometry.se3_inverse(c2w1), c2w0)  # camera 0 -> camera 1, [4, 4]
    # P1 = R (Z xn, Z yn, Z) + t, written out per component: one fused elementwise kernel
    # (a [H*W, 3] x [3, 3] matmul would not fuse with the rest on CPU)
    r, t = rel[:3, :3], rel[:3, 3]
    x1 = z * (r[0, 0] * xn + r[0, 1] * yn + r[0, 2]) + t[0]
    y1 = z * (r[1, 0] * xn + r[1, 1] * yn + r[1, 2]) + t[1]
    z1 = z * (r[2, 0] * xn + r[2, 1] * yn + r[2, 2]) + t[2]
    valid = ok0 & (z1 > jnp.finfo(depth.dtype).eps * z)
    p1 = jnp.stack([x1, y1, jnp.where(valid, z1, 1.0)], axis=-1)  # [H, W, 3]
    flow = geometry.project_points(p1, K) - m
    return jnp.where(valid[..., None], flow, 0.0), valid


# ----------------------------------------------------------------------------------------------
# per-Gaussian image velocity
# ----------------------------------------------------------------------------------------------


@jax.jit
def gaussian_image_velocity(
    p_cam: Float[ArrayLike, "*batch 3"],
    v_obj: Float[ArrayLike, "*batch 3"],
    K: Float[ArrayLike, "3 3"],
    v: Float[ArrayLike, 3],
    omega: Float[ArrayLike, 3],
) -> Float[Array, "*batch 2"]:
    """Analytic image velocity of Gaussian centres: A v / Z_i + B omega - A v_i / Z_i.

    Sign convention: ``v_obj`` (v_i) is the Gaussian's own velocity in camera-0 coordinates
    (R0^T dX_i/dt for a world-frame velocity dX_i/dt), so the centre moves as P_i' = -v - omega x P_i + v_i
    and its image velocity is J(P_i) P_i' with J = -A / Z_i: positive v_i[0] moves it right in the image
    (+fx v_i[0] / Z_i), while positive camera v[0] moves the image left. Exact (not first order) for
    instantaneous velocities; equals ``gaussian_image_velocity_jvp`` to rounding.

    Args:
        p_cam: Gaussian centres in camera-0 coordinates (OpenCV), [..., 3], z > 0 expected.
        v_obj: Gaussian velocities in camera-0 coordinates, [..., 3].
        K: intrinsics, [3, 3] (zero skew assumed).
        v, omega: camera velocity in camera-0 coordinates, [3] each.

    Returns:
        Image velocities (dx/dt, dy/dt) in pixels per unit time, [..., 2]; centres with z <= 0 get the
        rotational term only (their inverse depth is taken as 0).
    """
    p_cam, v_obj, K, v = as_float(p_cam), as_float(v_obj), as_float(K), as_float(v)
    xy = geometry.project_points(p_cam, K)
    rho = safe_inv_depth(p_cam[..., 2])
    fx, fy, _, _ = intrinsics(K)
    xt = xy[..., 0] - K[0, 2]
    yt = xy[..., 1] - K[1, 2]
    # A (v - v_i) / Z_i, written out, plus B omega (the camera flow at rho = 0)
    dv = jnp.broadcast_to(v, v_obj.shape) - v_obj  # [..., 3]
    tx = (-fx * dv[..., 0] + xt * dv[..., 2]) * rho
    ty = (-fy * dv[..., 1] + yt * dv[..., 2]) * rho
    rot = motion_field_inv_depth(xy, jnp.zeros_like(rho), K, jnp.zeros(3, dtype=rho.dtype), omega)
    return jnp.stack([tx, ty], axis=-1) + rot


def gaussian_image_velocity_jvp(
    means_fn: Callable[[Array], Float[Array, "N 3"]],
    c2w_fn: Callable[[Array], Float[Array, "4 4"]],
    K: Float[ArrayLike, "3 3"],
    t: float | ArrayLike,
) -> tuple[Float[Array, "N 2"], Float[Array, "N 2"]]:
    """Exact image velocity d/dt pi(K, c2w(t)^-1 X(t)) of moving centres under a moving camera (``jax.jvp``).

    The oracle for ``gaussian_image_velocity`` and ``motion_field``: no formula, only autodiff of the
    projection through both trajectories.

    Args:
        means_fn: t -> world-frame centres X(t), [N, 3].
        c2w_fn: t -> OpenCV camera-to-world pose, [4, 4].
        K: intrinsics, [3, 3].
        t: time (scalar) at which to differentiate.

    Returns:
        (xy [N, 2], dxy/dt [N, 2]): projections at t and their time derivative.
    """
    K = as_float(K)
    t = jnp.asarray(t, dtype=jnp.result_type(float))

    def proj(tt):
        view = geometry.se3_inverse(c2w_fn(tt))
        p = mm(means_fn(tt), view[:3, :3].T) + view[None, :3, 3]
        return geometry.project_points(p, K)

    return jax.jvp(proj, (t,), (jnp.ones_like(t),))
