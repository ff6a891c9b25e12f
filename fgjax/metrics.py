"""Image and flow metrics: PSNR, SSIM, masked PSNR, end-point error, adjusted Rand index.

SSIM follows Wang et al. 2004 with the usual evaluation settings (skimage ``structural_similarity(...,
gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)``): an 11x11 Gaussian
window (sigma 1.5, truncated at 3.5 sigma), K1 = 0.01, K2 = 0.03, population (co)variances, the mean
of the SSIM map over pixels whose window lies inside the image (skimage crops (win - 1) / 2 pixels at
each border after filtering, so its padding never matters), averaged over channels.
All JAX functions are jit/grad-able; `ssim` is what the photometric loss uses.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

__all__ = ["psnr", "mse", "ssim", "ssim_map", "masked_psnr", "epe", "ari", "gaussian_window"]


def mse(a: Float[ArrayLike, "... C"], b: Float[ArrayLike, "... C"]) -> Float[Array, ""]:
    a, b = jnp.asarray(a), jnp.asarray(b)
    return jnp.mean((a - b) ** 2)


def psnr(a: Float[ArrayLike, "H W C"], b: Float[ArrayLike, "H W C"], data_range: float = 1.0) -> Float[Array, ""]:
    """PSNR = 10 log10(R^2 / MSE) in dB (inf for identical images)."""
    m = mse(a, b)
    return 10.0 * jnp.log10(data_range**2 / m)


def masked_psnr(
    a: Float[ArrayLike, "H W C"], b: Float[ArrayLike, "H W C"], mask: Bool[ArrayLike, "H W"], data_range: float = 1.0
) -> Float[Array, ""]:
    """PSNR over the pixels where `mask` is set (NaN when the mask is empty)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    w = jnp.asarray(mask).astype(a.dtype)[..., None]
    den = jnp.sum(w) * a.shape[-1]
    m = jnp.sum(w * (a - b) ** 2) / jnp.where(den > 0, den, 1.0)
    return jnp.where(den > 0, 10.0 * jnp.log10(data_range**2 / m), jnp.nan)


def gaussian_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """Normalised 1D Gaussian taps [size]."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    g = np.exp(-(x**2) / (2.0 * sigma**2))
    return g / g.sum()


def _filter_valid(x: Array, taps: Array) -> Array:
    """Separable 'valid' filtering of [H, W, C] with the 1D taps along H then W."""
    k = taps.shape[0]
    h, w = x.shape[0] - k + 1, x.shape[1] - k + 1
    y = sum(taps[i] * x[i : i + h] for i in range(k))
    return sum(taps[j] * y[:, j : j + w] for j in range(k))


def ssim_map(
    a: Float[ArrayLike, "H W C"],
    b: Float[ArrayLike, "H W C"],
    *,
    data_range: float = 1.0,
    win_size: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> Float[Array, "H-10 W-10 C"]:
    """Per-pixel SSIM over the interior (valid) region, [H - win + 1, W - win + 1, C] (Wang et al. eq. 13)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    dtype = jnp.result_type(a.dtype, b.dtype, jnp.float32)
    a, b = a.astype(dtype), b.astype(dtype)
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(f"ssim: images must share a shape [H, W, C]; got {a.shape} and {b.shape}")
    if a.shape[0] < win_size or a.shape[1] < win_size:
        raise ValueError(f"ssim: images must be at least {win_size}x{win_size}; got {a.shape[:2]}")
    taps = jnp.asarray(gaussian_window(win_size, sigma), dtype)
    mu_a = _filter_valid(a, taps)
    mu_b = _filter_valid(b, taps)
    s_aa = _filter_valid(a * a, taps) - mu_a * mu_a
    s_bb = _filter_valid(b * b, taps) - mu_b * mu_b
    s_ab = _filter_valid(a * b, taps) - mu_a * mu_b
    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2
    num = (2 * mu_a * mu_b + c1) * (2 * s_ab + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (s_aa + s_bb + c2)
    return num / den


def ssim(a: Float[ArrayLike, "H W C"], b: Float[ArrayLike, "H W C"], **kw) -> Float[Array, ""]:
    """Mean SSIM (channels averaged); see the module docstring for the exact definition."""
    return jnp.mean(ssim_map(a, b, **kw))


def epe(
    flow: Float[ArrayLike, "... 2"], ref: Float[ArrayLike, "... 2"], valid: Bool[ArrayLike, ...] | None = None
) -> Float[Array, ""]:
    """Mean end-point error ||flow - ref||_2 over valid entries."""
    d = jnp.asarray(flow) - jnp.asarray(ref)
    e = jnp.sqrt(jnp.sum(d * d, axis=-1))
    if valid is None:
        return jnp.mean(e)
    w = jnp.asarray(valid).astype(e.dtype)
    return jnp.sum(w * e) / jnp.maximum(jnp.sum(w), 1.0)


def ari(labels_true: ArrayLike, labels_pred: ArrayLike) -> float:
    """Adjusted Rand index (scikit-learn) of two flat labellings."""
    from sklearn.metrics import adjusted_rand_score

    a, b = np.asarray(labels_true).reshape(-1), np.asarray(labels_pred).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"ari: label arrays differ in size: {a.shape} vs {b.shape}")
    return float(adjusted_rand_score(a, b))


def psnr_from_mse(m: float, data_range: float = 1.0) -> float:
    return float(10.0 * math.log10(data_range**2 / max(m, 1e-30)))


_ = jax  # jax is part of the public contract (jit-able functions)
