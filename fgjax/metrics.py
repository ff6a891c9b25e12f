"""Image and flow metrics: PSNR, SSIM, masked PSNR, end-point error, adjusted Rand index; rotation angles.

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
from sklearn.metrics import adjusted_rand_score

__all__ = ["psnr", "mse", "ssim", "ssim_map", "masked_psnr", "epe", "ari", "gaussian_window", "filter_valid",
           "rotation_angle_deg"]


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


def _band(taps, n: int) -> Array:
    """The 'valid' correlation with `taps` [k] (numpy or jax, traceable) along an axis of length n as a matrix
    [n - k + 1, n]: band[i, j] = taps[j - i] for 0 <= j - i < k, else 0."""
    k = taps.shape[0]
    d = np.arange(n)[None, :] - np.arange(n - k + 1)[:, None]  # [n - k + 1, n]: j - i
    inside = (d >= 0) & (d < k)
    return jnp.where(inside, jnp.asarray(taps)[np.clip(d, 0, k - 1)], 0.0)


def _filter_last(x: Array, taps, block: int = 256) -> Array:
    """'Valid' correlation of [M, n] with `taps` [k] (numpy or jax) along the last axis: [M, n - k + 1].

    Outputs in nb = ceil((n - k + 1) / block) equal blocks of T: each block is one product of its T + k - 1
    inputs with a banded matrix [T, T + k - 1], so the cost per output is at most block + k - 1 multiplies
    whatever n."""
    k = taps.shape[0]
    n_out = x.shape[1] - k + 1
    nb = -(-n_out // int(block))
    t = -(-n_out // nb)
    hi = jax.lax.Precision.HIGHEST
    band = _band(taps, t + k - 1).astype(x.dtype)  # [T, T + k - 1]
    if nb == 1:  # t + k - 1 = n: the band is the whole axis
        return jnp.einsum("mj,tj->mt", x, band, precision=hi)
    r = -(-(t + k - 1) // t)  # blocks spanned by one window
    xp = jnp.pad(x, ((0, 0), (0, (nb + r - 1) * t - x.shape[1])))  # [M, (nb + r - 1) T]
    # window b = inputs b T ... b T + T + k - 2: block b and the start of the next r - 1 blocks
    win = jnp.concatenate([xp[:, s * t : (s + nb) * t].reshape(-1, nb, t)[:, :, : min(t, t + k - 1 - s * t)]
                           for s in range(r)], axis=2)  # [M, nb, T + k - 1]
    return jnp.einsum("mbj,tj->mbt", win, band, precision=hi).reshape(x.shape[0], nb * t)[:, :n_out]


def filter_valid(x: Array, taps) -> Array:
    """Separable 'valid' filtering of a stack [B, H, W] with the 1D `taps` [k] (numpy or jax, traceable) along
    H and W: [B, H - k + 1, W - k + 1]. SSIM's local means, and the photometric tracker's blur.

    Products with banded matrices (`_filter_last`; full float32 precision on every backend): the same numbers
    as a sum of k shifted slices per axis, with a shorter XLA:CPU compile and a
    faster run; two 1-D convolutions are slower still."""
    k = taps.shape[0]
    if x.ndim != 3 or x.shape[1] < k or x.shape[2] < k or taps.ndim != 1 or k < 1:
        raise ValueError(f"filter_valid: needs a stack [B, H, W] with H, W >= the {k} taps and 1-D taps; got x "
                         f"{tuple(x.shape)} and taps {tuple(taps.shape)}")
    b, h, w = x.shape
    y = _filter_last(x.reshape(b * h, w), taps).reshape(b, h, w - k + 1)  # along W
    y = _filter_last(jnp.swapaxes(y, 1, 2).reshape(b * (w - k + 1), h), taps)  # along H
    return jnp.swapaxes(y.reshape(b, w - k + 1, h - k + 1), 1, 2)


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
    taps = gaussian_window(win_size, sigma)
    c = a.shape[-1]
    stack = jnp.stack([a, b, a * a, b * b, a * b])  # [5, H, W, C]: the five local means, one filter call
    f = filter_valid(jnp.moveaxis(stack, -1, 1).reshape(5 * c, *a.shape[:2]), taps)  # [5 C, H', W']
    mu_a, mu_b, e_aa, e_bb, e_ab = jnp.moveaxis(f.reshape(5, c, *f.shape[1:]), 1, -1)  # each [H', W', C]
    s_aa = e_aa - mu_a * mu_a
    s_bb = e_bb - mu_b * mu_b
    s_ab = e_ab - mu_a * mu_b
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
    a, b = np.asarray(labels_true).reshape(-1), np.asarray(labels_pred).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"ari: label arrays differ in size: {a.shape} vs {b.shape}")
    return float(adjusted_rand_score(a, b))


def psnr_from_mse(m: float, data_range: float = 1.0) -> float:
    return float(10.0 * math.log10(data_range**2 / max(m, 1e-30)))


_ = jax  # jax is part of the public contract (jit-able functions)


def rotation_angle_deg(rot: Float[ArrayLike, "*batch 3 3"]) -> Float[np.ndarray, "*batch"]:
    """Rotation angle in degrees, in [0, 180], of rotation matrices [..., 3, 3]: arccos((tr R - 1) / 2) with the
    cosine clipped to [-1, 1], in numpy float64. For errors and thresholds, not gradients
    (`fgjax.geometry.so3_log` has those): near 0 arccos leaves about 1e-6 degrees of round-off. NaN in, NaN out."""
    r = np.asarray(rot, np.float64)
    return np.degrees(np.arccos(np.clip((np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)))
