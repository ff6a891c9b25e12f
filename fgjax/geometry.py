"""Rotations and rigid motions: SO(3), SE(3), quaternions, camera conventions, pinhole projection.

Conventions (see ../shared/DESIGN.md section 2):

- Rotation vectors ``omega`` are axis * angle (radians); ``so3_exp`` maps them to 3x3 rotation
  matrices, ``so3_log`` back, with angle in [0, pi].
- Quaternions are ``wxyz`` and need not be normalised on input.
- Twists are ordered ``[omega, v]`` (rotation first). ``se3_exp(xi)`` is the 4x4 matrix exponential of
  ``[[hat(omega), v], [0, 0]]``; its translation is ``V(omega) v``, not ``v``.
- Poses are 4x4 homogeneous matrices. ``c2w`` is camera-to-world, ``viewmat`` world-to-camera.
- Cameras are OpenCV (x right, y down, z forward) unless a name says otherwise; OpenGL/Blender cameras
  (x right, y up, z back) are converted by right-multiplying the c2w with diag(1, -1, -1, 1).
- Pixel (j, i) (column j, row i) has its centre at (j + 0.5, i + 0.5); ``K``'s cx, cy live in that
  continuous coordinate system (as in gsplat).

Every public function is pure and broadcasts over leading batch dimensions. The camera-convention
conversions (``opengl_to_opencv_c2w``, ``opencv_to_opengl_c2w``, ``c2w_to_viewmat``, ``viewmat_to_c2w``) are
numpy float64, used once at load time; every other function is wrapped in ``jax.jit`` (so
eager calls run as one compiled program; inside other jitted code it is simply inlined), and is vmap- and
grad-safe:
small-angle Taylor branches use dtype-dependent thresholds and the double-``where`` so that neither
values nor gradients are ever NaN, including at angle 0 and angle pi.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

__all__ = [
    "hat",
    "vee",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "quat_multiply",
    "fit_group_poses",
    "se3_exp",
    "se3_log",
    "se3_compose",
    "matmul",
    "full_precision",
    "HIGHEST",
    "se3_inverse",
    "make_pose",
    "opengl_to_opencv_c2w",
    "opencv_to_opengl_c2w",
    "c2w_to_viewmat",
    "viewmat_to_c2w",
    "look_at_point",
    "project_points",
    "as_float",
    "safe_norm",
    "abs0",
]

_FLIP_YZ = (1.0, -1.0, -1.0, 1.0)

HIGHEST = jax.lax.Precision.HIGHEST
"""Precision of every matrix product in fgjax's geometry, rendering, flow and tracking. JAX's default lets
recent NVIDIA GPUs multiply float32 matrices in TF32 (a 10-bit mantissa): on an H200 that put errors of 4e-2
into rendered colours against the float64 reference, against 4e-7 at full precision, for the same run time
(docs/benchmarks.md, "GPU"). CPUs compute in full float32 either way. The learned fields' MLPs keep the
backend's default."""


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------


def matmul(a: ArrayLike, b: ArrayLike) -> Array:
    """``a @ b`` (``jnp.matmul`` broadcasting) at full float32 precision on every backend (`HIGHEST`)."""
    return jnp.matmul(a, b, precision=HIGHEST)


def full_precision(fn):
    """``fn`` traced with every matrix product at `HIGHEST` precision, those of the libraries it calls included
    (optimistix's and lineax's normal equations, say). Wrap it inside ``jax.jit`` (``jax.jit(full_precision(f))``):
    the precision is fixed when the function is traced."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapped


def as_float(x: ArrayLike) -> Array:
    """As a JAX array of a floating dtype (integers promote to the default float)."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def abs0(x: ArrayLike) -> Array:
    """|x| with a zero derivative at x = 0, where jnp.abs's is 1: a residual that is exactly zero (a deformation
    at rest, a flow target that the prediction matches) pushes nothing."""
    x = jnp.asarray(x)
    return jnp.where(x != 0, jnp.abs(x), 0.0)


def _small_angle_threshold(dtype) -> float:
    """Threshold on theta^2 under which the Taylor branches are used.

    eps ** 0.25 (1.2e-4 in float64, 1.9e-2 in float32): the closed forms lose about eps / theta^2 of
    relative accuracy in their derivatives (cancellation in e.g. theta cos(theta) - sin(theta)), while the
    Taylor series below (kept to theta^6) are exact to ~theta^8 / 9!; at this threshold both errors sit
    far below the dtype's resolution of the result.
    """
    return float(jnp.finfo(dtype).eps) ** 0.25


def safe_norm(x: ArrayLike) -> Array:
    """|x| over the last axis, with a zero (not NaN) gradient at x = 0 (double-where)."""
    return _safe_norm_sq(jnp.asarray(x))[1]


def _safe_norm_sq(x: Array) -> tuple[Array, Array]:
    """(|x|^2, |x|) over the last axis with a finite (zero) gradient at x = 0 (double-where)."""
    n2 = jnp.sum(x * x, axis=-1)
    pos = n2 > 0
    n = jnp.where(pos, jnp.sqrt(jnp.where(pos, n2, 1.0)), 0.0)
    return n2, n


@jax.jit
def hat(w: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Skew-symmetric matrix [w]_x with hat(w) @ p == cross(w, p)."""
    w = as_float(w)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], axis=-2
    )


@jax.jit
def vee(m: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Inverse of ``hat`` on the antisymmetric part: vee(M) = axial vector of (M - M^T) / 2."""
    m = as_float(m)
    return 0.5 * jnp.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1
    )


def _so3_coeffs(theta2: Array) -> tuple[Array, Array, Array]:
    """A = sin(t)/t, B = (1 - cos t)/t^2, C = (t - sin t)/t^3 as functions of t^2, NaN-free at t = 0."""
    small = theta2 < _small_angle_threshold(theta2.dtype)
    t2 = jnp.where(small, 1.0, theta2)  # double-where: the closed forms never see 0
    t = jnp.sqrt(t2)
    s, half_s = jnp.sin(t), jnp.sin(0.5 * t)
    a_big = s / t
    b_big = 2.0 * half_s * half_s / t2  # 1 - cos t = 2 sin^2(t/2): no cancellation
    c_big = (t - s) / (t2 * t)
    x = theta2
    a_small = 1.0 - x / 6.0 + x * x / 120.0 - x * x * x / 5040.0
    b_small = 0.5 - x / 24.0 + x * x / 720.0 - x * x * x / 40320.0
    c_small = 1.0 / 6.0 - x / 120.0 + x * x / 5040.0 - x * x * x / 362880.0
    return (
        jnp.where(small, a_small, a_big),
        jnp.where(small, b_small, b_big),
        jnp.where(small, c_small, c_big),
    )


# ----------------------------------------------------------------------------------------------
# SO(3)
# ----------------------------------------------------------------------------------------------


@jax.jit
def so3_exp(omega: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix exp(hat(omega)) of a rotation vector (Rodrigues).

    R = I + A(t) W + B(t) W^2 with W = hat(omega), t = |omega|, A = sin t / t, B = (1 - cos t) / t^2;
    A and B switch to their Taylor series below a dtype-dependent threshold on t^2, so the value and the
    gradient are exact and finite at omega = 0.

    Args:
        omega: rotation vectors (axis times angle in radians), shape [..., 3].

    Returns:
        Rotation matrices, shape [..., 3, 3].
    """
    omega = as_float(omega)
    theta2 = jnp.sum(omega * omega, axis=-1)
    a, b, _ = _so3_coeffs(theta2)
    w = hat(omega)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=omega.dtype), w.shape)
    return eye + a[..., None, None] * w + b[..., None, None] * matmul(w, w)


@jax.jit
def so3_left_jacobian(omega: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Left Jacobian V(omega) = I + B(t) W + C(t) W^2 of SO(3); the translation part of ``se3_exp``.

    Args:
        omega: rotation vectors, shape [..., 3].

    Returns:
        V, shape [..., 3, 3], with se3_exp([omega, v])[:3, 3] == V @ v.
    """
    omega = as_float(omega)
    theta2 = jnp.sum(omega * omega, axis=-1)
    _, b, c = _so3_coeffs(theta2)
    w = hat(omega)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=omega.dtype), w.shape)
    return eye + b[..., None, None] * w + c[..., None, None] * matmul(w, w)


@jax.jit
def so3_left_jacobian_inv(omega: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Inverse V^-1 = I - W/2 + D(t) W^2 of the left Jacobian, D = (1 - t sin t / (2 (1 - cos t))) / t^2.

    Valid for angles t < 2 pi (``so3_log`` returns t <= pi). D uses its Taylor series
    1/12 + t^2/720 + t^4/30240 + t^6/1209600 near 0.

    Args:
        omega: rotation vectors, shape [..., 3].

    Returns:
        V^-1, shape [..., 3, 3].
    """
    omega = as_float(omega)
    theta2 = jnp.sum(omega * omega, axis=-1)
    small = theta2 < _small_angle_threshold(theta2.dtype)
    t2 = jnp.where(small, 1.0, theta2)
    t = jnp.sqrt(t2)
    half = 0.5 * t
    # t sin t / (2 (1 - cos t)) = (t/2) cot(t/2) = (t/2) cos(t/2) / sin(t/2)
    d_big = (1.0 - half * jnp.cos(half) / jnp.sin(half)) / t2
    x = theta2
    d_small = 1.0 / 12.0 + x / 720.0 + x * x / 30240.0 + x * x * x / 1209600.0
    d = jnp.where(small, d_small, d_big)
    w = hat(omega)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=omega.dtype), w.shape)
    return eye - 0.5 * w + d[..., None, None] * matmul(w, w)


@jax.jit
def so3_log(rot: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Rotation vector of a rotation matrix, angle in [0, pi]; finite value and gradient everywhere.

    Three branches, each fed only inputs it is accurate and NaN-free on (double-where):

    - small angle (sin^2 t below a dtype-dependent threshold, cos t > 0): omega = (asin(s)/s) w with
      w = vee(R) = sin(t) * axis, s = |w|, and asin(s)/s from its Taylor series in s^2 (smooth in R);
    - generic: omega = atan2(s, c) / s * w with c = (tr R - 1) / 2;
    - near pi (c < -0.8): the axis from the symmetric part, (R + R^T)/2 - c I = (1 - c) a a^T, taking the
      column with the largest diagonal (>= 1/3 of the norm, so never a division by ~0), signed so that
      a . w >= 0; omega = atan2(s, c) a. At exactly pi the sign is arbitrary (both are valid logs).

    Args:
        rot: rotation matrices, shape [..., 3, 3]. Slightly non-orthonormal input is tolerated.

    Returns:
        Rotation vectors, shape [..., 3].
    """
    rot = as_float(rot)
    dtype = rot.dtype
    w = vee(rot)  # [..., 3] = sin(t) * axis
    c = 0.5 * (jnp.trace(rot, axis1=-2, axis2=-1) - 1.0)
    c = jnp.clip(c, -1.0, 1.0)
    s2, s = _safe_norm_sq(w)
    theta = jnp.arctan2(s, c)

    thr = _small_angle_threshold(dtype)
    small = (s2 < thr) & (c > 0)
    near_pi = c < -0.8
    generic = ~(small | near_pi)

    # small: asin(s)/s = 1 + s^2/6 + 3 s^4/40 + 5 s^6/112 + 35 s^8/1152
    x = s2
    f_small = 1.0 + x / 6.0 + 3.0 * x * x / 40.0 + 5.0 * x * x * x / 112.0 + 35.0 * x**4 / 1152.0
    # generic: theta / s with s bounded away from 0
    s_safe = jnp.where(generic, s, 1.0)
    f_generic = jnp.where(generic, theta, 1.0) / s_safe
    f = jnp.where(small, f_small, f_generic)
    omega_regular = f[..., None] * w

    # near pi: axis from the symmetric part
    sym = 0.5 * (rot + jnp.swapaxes(rot, -1, -2))
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), sym.shape)
    one_minus_c = jnp.where(near_pi, 1.0 - c, 1.0)  # >= 1.8 on this branch
    aat = (sym - c[..., None, None] * eye) / one_minus_c[..., None, None]  # [..., 3, 3] = a a^T
    diag = jnp.diagonal(aat, axis1=-2, axis2=-1)  # [..., 3]
    onehot = jax.nn.one_hot(jnp.argmax(diag, axis=-1), 3, dtype=dtype)  # [..., 3], no gathers
    col = jnp.sum(aat * onehot[..., None, :], axis=-1)  # [..., 3] = a_k a
    dk = jnp.sum(diag * onehot, axis=-1)  # a_k^2
    dk_safe = jnp.where(near_pi & (dk > 0), dk, 1.0)
    axis = col / jnp.sqrt(dk_safe)[..., None]
    sign = jnp.where(jnp.sum(axis * w, axis=-1) < 0, -1.0, 1.0)
    omega_pi = (sign * jnp.where(near_pi, theta, 0.0))[..., None] * axis

    return jnp.where(near_pi[..., None], omega_pi, omega_regular)


# ----------------------------------------------------------------------------------------------
# quaternions (wxyz)
# ----------------------------------------------------------------------------------------------


@jax.jit
def quat_to_rotmat(quats: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of a wxyz quaternion of any (non-zero) norm; q and -q give the same matrix.

    Uses R = I + 2/|q|^2 [[-(y^2+z^2), xy - wz, xz + wy], ...], so no explicit normalisation (and no
    square root) is needed. A zero quaternion gives the identity (finite gradient).

    Args:
        quats: quaternions (w, x, y, z), shape [..., 4].

    Returns:
        Rotation matrices, shape [..., 3, 3].
    """
    q = as_float(quats)
    n2 = jnp.sum(q * q, axis=-1)
    pos = n2 > 0
    s = jnp.where(pos, 2.0 / jnp.where(pos, n2, 1.0), 0.0)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1.0 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)],
        [s * (x * y + w * z), 1.0 - s * (x * x + z * z), s * (y * z - w * x)],
        [s * (x * z - w * y), s * (y * z + w * x), 1.0 - s * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


@jax.jit
def quat_multiply(a: Float[ArrayLike, "*batch 4"], b: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Hamilton product a * b of wxyz quaternions [..., 4] (rotation b first, then a)."""
    aw, ax, ay, az = jnp.moveaxis(jnp.asarray(a), -1, 0)
    bw, bx, by, bz = jnp.moveaxis(jnp.asarray(b), -1, 0)
    return jnp.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                      aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def rotmat_to_quat(rot: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 4"]:
    """Unit wxyz quaternion of a rotation matrix (Shepperd's method), with w >= 0.

    Of the four candidate formulas the one with the largest pivot (1 + tr, or 1 + 2 R_kk - tr) is used,
    so the square root and the division are always well conditioned (pivot >= 1 for rotations).

    Args:
        rot: rotation matrices, shape [..., 3, 3].

    Returns:
        Unit quaternions (w, x, y, z), shape [..., 4], sign chosen so that w >= 0.
    """
    r = as_float(rot)
    r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    tr = r00 + r11 + r22
    pivots = jnp.stack([1.0 + tr, 1.0 + 2 * r00 - tr, 1.0 + 2 * r11 - tr, 1.0 + 2 * r22 - tr], axis=-1)
    onehot = jax.nn.one_hot(jnp.argmax(pivots, axis=-1), 4, dtype=r.dtype)  # [..., 4]
    p = jnp.sum(pivots * onehot, axis=-1)
    p = jnp.where(p > 0, p, 1.0)
    sq = jnp.sqrt(p)  # = 2 |q_k|
    d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    s21, s02, s10 = r[..., 2, 1] + r[..., 1, 2], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 0] + r[..., 0, 1]
    cands = jnp.stack(
        [
            jnp.stack([sq, d21 / sq, d02 / sq, d10 / sq], -1),
            jnp.stack([d21 / sq, sq, s10 / sq, s02 / sq], -1),
            jnp.stack([d02 / sq, s10 / sq, sq, s21 / sq], -1),
            jnp.stack([d10 / sq, s02 / sq, s21 / sq, sq], -1),
        ],
        axis=-2,
    )  # [..., 4 candidates, 4]
    q = 0.5 * jnp.sum(cands * onehot[..., :, None], axis=-2)
    return jnp.where(q[..., :1] < 0, -q, q)


# ----------------------------------------------------------------------------------------------
# SE(3)
# ----------------------------------------------------------------------------------------------


@jax.jit
def make_pose(rot: Float[ArrayLike, "*batch 3 3"], trans: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 4 4"]:
    """4x4 homogeneous matrix [[R, t], [0, 0, 0, 1]]."""
    rot, trans = as_float(rot), as_float(trans)
    rot, trans = jnp.broadcast_arrays(rot, trans[..., None])
    top = jnp.concatenate([rot, trans[..., :1]], axis=-1)  # [..., 3, 4]
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], dtype=top.dtype), top.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


@jax.jit
def se3_exp(xi: Float[ArrayLike, "*batch 6"]) -> Float[Array, "*batch 4 4"]:
    """Matrix exponential of a twist xi = [omega, v] (rotation first): [[exp(omega), V(omega) v], [0, 1]].

    Right-multiplying a camera-to-world pose by ``se3_exp(dt * xi)`` moves the camera by the twist
    expressed in its own (body) frame: after time dt its centre has moved by R0 V(dt omega) v dt, not
    R0 v dt (the two agree to first order in dt).

    Args:
        xi: twists [omega (3), v (3)], shape [..., 6].

    Returns:
        Rigid transforms, shape [..., 4, 4].
    """
    xi = as_float(xi)
    omega, v = xi[..., :3], xi[..., 3:]
    rot = so3_exp(omega)
    trans = matmul(so3_left_jacobian(omega), v[..., None])[..., 0]
    return make_pose(rot, trans)


@jax.jit
def se3_log(pose: Float[ArrayLike, "*batch 4 4"]) -> Float[Array, "*batch 6"]:
    """Twist [omega, v] with se3_exp(se3_log(T)) == T; rotation angle in [0, pi], v = V(omega)^-1 t.

    Args:
        pose: rigid transforms, shape [..., 4, 4] (the last row is ignored).

    Returns:
        Twists [omega, v], shape [..., 6].
    """
    pose = as_float(pose)
    omega = so3_log(pose[..., :3, :3])
    v = matmul(so3_left_jacobian_inv(omega), pose[..., :3, 3:4])[..., 0]
    return jnp.concatenate([omega, v], axis=-1)


@jax.jit
def se3_compose(a: Float[ArrayLike, "*batch 4 4"], b: Float[ArrayLike, "*batch 4 4"]) -> Float[Array, "*batch 4 4"]:
    """Composition a ∘ b = a @ b of rigid transforms (apply b first)."""
    return matmul(as_float(a), as_float(b))


@jax.jit
def se3_inverse(pose: Float[ArrayLike, "*batch 4 4"]) -> Float[Array, "*batch 4 4"]:
    """Inverse [[R^T, -R^T t], [0, 1]] of a rigid transform (exact for orthonormal R, no solve)."""
    pose = as_float(pose)
    rt = jnp.swapaxes(pose[..., :3, :3], -1, -2)
    t = pose[..., :3, 3:4]
    return make_pose(rt, -matmul(rt, t)[..., 0])


# ----------------------------------------------------------------------------------------------
# cameras
# ----------------------------------------------------------------------------------------------


_GL_FLIP = np.diag(np.asarray(_FLIP_YZ))  # [4, 4]


def opengl_to_opencv_c2w(c2w: Float[ArrayLike, "*batch 4 4"]) -> Float[np.ndarray, "*batch 4 4"]:
    """OpenGL/Blender camera-to-world (x right, y up, z back) -> OpenCV camera-to-world (y down, z fwd).

    c2w_cv = c2w_gl @ diag(1, -1, -1, 1): the camera centre is unchanged, the camera's y and z axes flip.
    The same matrix converts back (`opencv_to_opengl_c2w`). For world-to-camera matrices left-multiply
    instead: viewmat_cv = diag(1, -1, -1, 1) @ viewmat_gl. Numpy float64 in and out: datasets are converted
    once, at load and write time (`fgjax.data.loaders`, `fgjax.data.write`).
    """
    return np.asarray(c2w, dtype=np.float64) @ _GL_FLIP


def opencv_to_opengl_c2w(c2w: Float[ArrayLike, "*batch 4 4"]) -> Float[np.ndarray, "*batch 4 4"]:
    """OpenCV camera-to-world -> OpenGL/Blender camera-to-world; c2w_gl = c2w_cv @ diag(1, -1, -1, 1), the
    inverse of `opengl_to_opencv_c2w`. Numpy float64 in and out."""
    return np.asarray(c2w, dtype=np.float64) @ _GL_FLIP


def _rigid_inverse_f64(m: ArrayLike) -> np.ndarray:
    """Inverse of (near-)rigid 4x4s by a full LU solve, bottom row set to (0, 0, 0, 1); numpy float64.

    An LU inverse rather than [R^T | -R^T t], so that float32 poses whose R is orthonormal only to ~1e-7
    still round-trip to float64 precision."""
    out = np.linalg.inv(np.asarray(m, dtype=np.float64))
    out[..., 3, :] = np.array([0.0, 0.0, 0.0, 1.0])
    return out


def c2w_to_viewmat(c2w: Float[ArrayLike, "*batch 4 4"]) -> Float[np.ndarray, "*batch 4 4"]:
    """Rigid camera-to-world -> world-to-camera (same convention), [R^T | -R^T c] for orthonormal R.

    Numpy float64 (LU inverse, see `_rigid_inverse_f64`); `se3_inverse` is the JAX version."""
    return _rigid_inverse_f64(c2w)


def viewmat_to_c2w(viewmat: Float[ArrayLike, "*batch 4 4"]) -> Float[np.ndarray, "*batch 4 4"]:
    """Rigid world-to-camera -> camera-to-world (same convention), [R^T | -R^T t] for orthonormal R.

    Numpy float64 (LU inverse, see `_rigid_inverse_f64`); `se3_inverse` is the JAX version."""
    return _rigid_inverse_f64(viewmat)


def look_at_point(viewmats: Float[ArrayLike, "T 4 4"]) -> tuple[np.ndarray, float]:
    """The point OpenCV cameras `viewmats` [T, 4, 4] (world-to-camera) look at, and their distance to it.

    The point is the least-squares closest point to the optical axes (sum_i (I - d_i d_i^T)(p - c_i) = 0, centres
    c_i, axes d_i); the distance is the median camera distance to it. Where that is undefined or zero, the point is
    one unit in front of the cameras (mean centre + mean axis) and the distance 1: parallel axes (a still camera)
    and axes that meet at the cameras' common centre (a camera that only turns). Numpy float64.
    """
    v = np.asarray(viewmats, dtype=np.float64)
    r = v[:, :3, :3]
    c = -np.einsum("tji,tj->ti", r, v[:, :3, 3])  # [T, 3] camera centres
    d = r[:, 2, :]  # [T, 3] optical axes (world)
    proj = np.eye(3) - np.einsum("ti,tj->tij", d, d)  # [T, 3, 3]
    a, b = proj.sum(0), np.einsum("tij,tj->i", proj, c)
    ahead = c.mean(0) + d.mean(0)
    centre = np.linalg.solve(a, b) if np.linalg.cond(a) < 1e8 else ahead
    rad = float(np.median(np.linalg.norm(c - centre, axis=-1)))
    if rad <= 1e-6 * (1.0 + float(np.linalg.norm(centre))):
        return ahead, 1.0
    return centre, rad


@jax.jit
def project_points(p_cam: Float[ArrayLike, "*batch 3"], K: Float[ArrayLike, "3 3"]) -> Float[Array, "*batch 2"]:
    """Pinhole projection of OpenCV camera-frame points: (fx x/z + s y/z + cx, fy y/z + cy).

    Pixel (j, i) has its centre at (j + 0.5, i + 0.5) when K follows our convention (gsplat's), i.e. a
    point on the optical axis lands at (cx, cy) in that continuous coordinate system.
    No clipping and no culling: points behind the camera (z < 0) project through the centre like any
    other; |z| below the dtype's eps is replaced by eps (signed) so the result stays finite. Callers mask
    with ``z > 0`` (or a near plane).

    Args:
        p_cam: points in camera coordinates (OpenCV), shape [..., 3].
        K: intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]], shape [3, 3].

    Returns:
        Pixel coordinates (x, y), shape [..., 2].
    """
    p = as_float(p_cam)
    K = as_float(K)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    eps = jnp.finfo(p.dtype).eps
    z_safe = jnp.where(jnp.abs(z) > eps, z, jnp.where(z < 0, -eps, eps))
    xn, yn = x / z_safe, y / z_safe
    u = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
    v = K[1, 1] * yn + K[1, 2]
    return jnp.stack([u, v], axis=-1)


def fit_group_poses(src: Float[ArrayLike, "N 3"], dst: Float[ArrayLike, "N 3"], labels: Int[ArrayLike, " N"],
                    num_objects: int, min_points: int = 3) -> Float[Array, "K 4 4"]:
    """Each object's best rigid motion of its points: poses [K, 4, 4] (x -> R x + t, world space) minimising
    sum_i |R src_i + t - dst_i|^2 over the points with ``labels`` [N] == k (Kabsch: t from the centroids, R from
    the SVD of their cross-covariance, its determinant made +1). ``src``, ``dst``: [N, 3]; labels in -1..K-1
    (-1: in no object). An object with fewer than ``min_points`` points gets its centroid shift only (R = I;
    none: the identity), so that one or two points never pick an arbitrary turn. Jitted for each K.

    Not differentiable: the result is held constant under differentiation (a rotation fitted by an SVD has no
    gradient where singular values coincide), so gradients of the poses are 0, never NaN."""
    return _fit_group_poses_jit(jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32),
                            jnp.asarray(labels, jnp.int32), int(num_objects), int(min_points))


@functools.partial(jax.jit, static_argnums=(3, 4))
def _fit_group_poses_jit(src, dst, labels, num_objects, min_points):
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
    return make_pose(rot, t)
