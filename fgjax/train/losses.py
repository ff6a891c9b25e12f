"""Training losses: photometric (0.8 L1 + 0.2 (1 - SSIM)), scale regulariser; the flow loss is fgjax.flow.flow_loss."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from fgjax.metrics import ssim

__all__ = ["l1", "photometric_loss", "scale_regularizer"]


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


def scale_regularizer(
    log_scales: Float[ArrayLike, "N 3"], weights: Float[ArrayLike, " N"], max_scale: float
) -> Float[Array, ""]:
    """mean_i w_i relu(max_k s_ik - max_scale): discourages needle/blob Gaussians larger than `max_scale`."""
    s = jnp.exp(jnp.max(jnp.asarray(log_scales), axis=-1))
    w = jnp.asarray(weights).astype(s.dtype)
    return jnp.sum(w * jax.nn.relu(s - max_scale)) / jnp.maximum(jnp.sum(w), 1.0)
