"""Training losses: photometric (0.8 L1 + 0.2 (1 - SSIM)), measured depth, scale and isometry regularisers; the
flow loss is fgjax.flow.flow_loss."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from fgjax.geometry import abs0, safe_norm
from fgjax.metrics import ssim

__all__ = ["l1", "photometric_loss", "depth_loss", "scale_regularizer", "isometry_loss", "scale_change_loss",
           "rigid_drift_loss"]


def l1(a: Float[ArrayLike, "H W C"], b: Float[ArrayLike, "H W C"]) -> Float[Array, ""]:
    return jnp.mean(jnp.abs(jnp.asarray(a) - jnp.asarray(b)))


def photometric_loss(
    render: Float[ArrayLike, "H W C"], target: Float[ArrayLike, "H W C"], lambda_dssim: float = 0.2
) -> Float[Array, ""]:
    """L = (1 - l) L1 + l (1 - SSIM) (3DGS eq. 7, l = 0.2); SSIM as in ``fgjax.metrics.ssim``."""
    out = (1.0 - lambda_dssim) * l1(render, target)
    if lambda_dssim > 0:
        out = out + lambda_dssim * (1.0 - ssim(render, target))
    return out


def depth_loss(depth_acc: Float[ArrayLike, "H W"], measured: Float[ArrayLike, "H W"]) -> Float[Array, ""]:
    """Relative L1 of the rendered depth against a measured one (an RGB-D sensor), over the pixels with a
    measurement (finite and > 0; 0 = unknown, as ``Scene.depths`` stores it):

        L = sum_p v_p |sum_i T_i a_i z_i(p) - D(p)| / D(p) / sum_p v_p

    ``depth_acc`` is the accumulated depth sum_i T_i a_i z_i of `fgjax.render.rasterization(render_depth=True)`
    (``info["depth_acc"]``, camera z), not the expected depth sum_i T_i a_i z_i / alpha: a pixel the sensor sees a
    surface at but the Gaussians leave half covered costs too, so the term fills surfaces as well as placing them.
    Relative, so it weighs near and far alike and does not depend on the scene's normalisation. 0 without any
    measured pixel."""
    d = jnp.asarray(measured)
    z = jnp.asarray(depth_acc)
    valid = jnp.isfinite(d) & (d > 0)
    d_safe = jnp.where(valid, d, 1.0)
    err = jnp.where(valid, abs0(z - d_safe) / d_safe, 0.0)
    return jnp.sum(err) / jnp.maximum(jnp.sum(valid), 1)


def scale_regularizer(
    log_scales: Float[ArrayLike, "N 3"], weights: Float[ArrayLike, " N"], max_scale: float
) -> Float[Array, ""]:
    """mean_i w_i relu(max_k s_ik - max_scale): discourages needle/blob Gaussians larger than `max_scale`."""
    s = jnp.exp(jnp.max(jnp.asarray(log_scales), axis=-1))
    w = jnp.asarray(weights).astype(s.dtype)
    return jnp.sum(w * jax.nn.relu(s - max_scale)) / jnp.maximum(jnp.sum(w), 1.0)


def isometry_loss(
    means_t: Float[ArrayLike, "N 3"], means_c: Float[ArrayLike, "N 3"], nbr_idx, nbr_w: Float[ArrayLike, "N K"],
    eps: float = 1e-6, cap: float = 0.0,
) -> Float[Array, ""]:
    """Local rigidity of a deformation: mean over neighbour pairs (i, j) of | |x_i(t) - x_j(t)| / |X_i - X_j| - 1 |.

    ``means_c`` are the canonical centres X, ``means_t`` the deformed ones; ``nbr_idx`` [N, K] int and
    ``nbr_w`` [N, K] (0 = no pair) from ``fgjax.gaussians.knn_graph``. Rigid motion (static parts, a
    rotating door, a sliding drawer) costs nothing; stretching or shrinking a part does. In a monocular
    video a moving part is seen from about one viewpoint per state, so its depth is ambiguous up to
    scale; the part's size, known from the frames where it rests, then fixes it.

    With ``cap`` > 0 each pair costs the robust (Geman-McClure) cap e^2 / (e^2 + cap^2) of its stretch e:
    quadratic near 0, so a part can start to move before it moves as one piece (the plain |e| has a
    gradient of 1 / |X_i - X_j| as soon as a pair stretches at all, which holds every Gaussian in place), and
    bounded by cap, so a pair that spans a part's boundary (a door Gaussian and its static frame) breaks once the
    part moves, instead of pulling it back with a cost that grows without bound."""
    xt = jnp.asarray(means_t)
    xc = jax.lax.stop_gradient(jnp.asarray(means_c))
    w = jnp.asarray(nbr_w).astype(xt.dtype)
    d_t = safe_norm(xt[:, None, :] - xt[nbr_idx])  # [N, K]
    d_c = safe_norm(xc[:, None, :] - xc[nbr_idx])
    err = abs0(d_t / (d_c + eps) - d_c / (d_c + eps))
    if cap > 0:
        err = cap * err**2 / (err**2 + cap**2)
    return jnp.sum(w * err) / jnp.maximum(jnp.sum(w), 1.0)


def scale_change_loss(
    log_scales_t: Float[ArrayLike, "N 3"], log_scales_c: Float[ArrayLike, "N 3"], weights: Float[ArrayLike, " N"]
) -> Float[Array, ""]:
    """mean_i w_i mean_k |s_ik(t) - s_ik| in log-scale: rigid parts keep their Gaussians' sizes. Without it a
    deformation field can fake motion by shrinking Gaussians to nothing at one place and growing others
    elsewhere (appearance by scale), which leaves no trajectory to control."""
    d = jnp.mean(abs0(jnp.asarray(log_scales_t) - jax.lax.stop_gradient(jnp.asarray(log_scales_c))), axis=-1)
    w = jnp.asarray(weights).astype(d.dtype)
    return jnp.sum(w * d) / jnp.maximum(jnp.sum(w), 1.0)


def rigid_drift_loss(
    points: Float[ArrayLike, "M 3"], disp: Float[ArrayLike, "M 3"], mask: Float[ArrayLike, " M"], scale: float,
    eps: float = 1e-3,
) -> Float[Array, ""]:
    """The rigid part of a deformation at points that must not move, as one smooth length.

    With c the masked centroid of ``points`` X_i, r^2 = mean_i |X_i - c|^2, a = mean_i d_i (the mean displacement)
    and L = mean_i (X_i - c) x d_i (a rigid motion a + w x (X - c) has L = (tr S - S) w, S the points' covariance,
    so |L| / r is about the displacement that the rotation w gives at distance r), the loss is
    sqrt((|a|^2 + |L|^2 / r^2) / scale^2 + eps^2) - eps: 0 for no motion, |a| / scale for a pure translation large
    against eps, and a bounded gradient everywhere. Only the rigid component is measured: a few of the points that
    do move shift a and L by their share only, unlike a per-point pin.

    In a monocular video a rigid motion of the whole static scene at time t is a change of camera; a deformation
    field that blends rigid motions can fit such a per-frame camera correction with the static scene's weight on a
    moving basis, which this term prices (gauge fixing: the static scene defines the world frame). ``mask`` [M]
    (1: a point, 0: padding), ``scale``: the scene's extent (the loss is then unitless)."""
    x = jax.lax.stop_gradient(jnp.asarray(points))
    d = jnp.asarray(disp)
    m = jnp.asarray(mask).astype(d.dtype)[:, None]
    n = jnp.maximum(jnp.sum(m), 1.0)
    c = jnp.sum(m * x, axis=0) / n
    xc = x - c
    r2 = jnp.maximum(jnp.sum(m * xc**2) / n, 1e-12)
    a = jnp.sum(m * d, axis=0) / n
    ang = jnp.sum(m * jnp.cross(xc, d), axis=0) / n
    q = (jnp.sum(a**2) + jnp.sum(ang**2) / r2) / (scale * scale)
    return jnp.sqrt(q + eps * eps) - eps
