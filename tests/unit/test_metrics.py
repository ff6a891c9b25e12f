"""Metrics against independent numpy/scipy references and hand-computed values."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from fgjax import metrics


def _ssim_reference(a, b, data_range=1.0):
    """skimage.structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False),
    re-written with scipy.ndimage.gaussian_filter (truncate=3.5 gives the 11-tap window) and the
    (win - 1) / 2 border crop that skimage applies before averaging."""
    out = []
    for c in range(a.shape[-1]):
        x, y = a[..., c].astype(np.float64), b[..., c].astype(np.float64)
        f = lambda z: gaussian_filter(z, sigma=1.5, truncate=3.5, mode="reflect")
        ux, uy = f(x), f(y)
        vx, vy, vxy = f(x * x) - ux * ux, f(y * y) - uy * uy, f(x * y) - ux * uy
        c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
        s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux**2 + uy**2 + c1) * (vx + vy + c2))
        out.append(s[5:-5, 5:-5].mean())
    return float(np.mean(out))


@pytest.mark.parametrize("seed", range(3))
def test_ssim_matches_scipy_reference(seed):
    rng = np.random.default_rng(seed)
    a = rng.uniform(size=(32, 40, 3))
    b = np.clip(a + 0.1 * rng.normal(size=a.shape), 0, 1)
    # float64 (conftest enables x64): both sides are exact up to rounding.
    assert float(metrics.ssim(a, b)) == pytest.approx(_ssim_reference(a, b), abs=1e-10)


@pytest.mark.parametrize("shape", [(12, 300, 2), (280, 14, 1)])
def test_ssim_matches_scipy_reference_beyond_one_filter_block(shape):
    """Sides above `_filter_last`'s block (256 outputs): the filter runs in several banded blocks."""
    rng = np.random.default_rng(5)
    a = rng.uniform(size=shape)
    b = np.clip(a + 0.2 * rng.normal(size=a.shape), 0, 1)
    assert float(metrics.ssim(a, b)) == pytest.approx(_ssim_reference(a, b), abs=1e-10)


@pytest.mark.parametrize("n", [11, 12, 20, 37])
@pytest.mark.parametrize("block", [1, 3, 4, 256])
def test_filter_blocks_match_numpy_valid_correlation(n, block):
    """Every block split (equal blocks, the last one padded) gives numpy's 'valid' correlation."""
    rng = np.random.default_rng(n)
    x = rng.normal(size=(3, n))
    taps = metrics.gaussian_window(11, 1.5) * rng.uniform(0.5, 1.5, 11)  # not symmetric: orientation matters
    ref = np.stack([np.correlate(r, taps, mode="valid") for r in x])
    out = np.asarray(metrics._filter_last(jnp.asarray(x), taps, block=block))
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)


def test_filter_valid_names_bad_shapes():
    taps = metrics.gaussian_window(11, 1.5)
    for bad in (jnp.zeros((2, 10, 20)), jnp.zeros((2, 20, 10)), jnp.zeros((20, 20))):
        with pytest.raises(ValueError, match="filter_valid: needs a stack"):
            metrics.filter_valid(bad, taps)
    with pytest.raises(ValueError, match="1-D taps"):
        metrics.filter_valid(jnp.zeros((1, 20, 20)), np.ones((3, 3)))
    assert metrics.filter_valid(jnp.zeros((1, 11, 12)), taps).shape == (1, 1, 2)


def test_ssim_known_values():
    a = np.full((16, 16, 1), 0.3)
    assert float(metrics.ssim(a, a)) == pytest.approx(1.0, abs=1e-12)
    # Constant images: variances vanish, SSIM = (2 mu_a mu_b + C1) / (mu_a^2 + mu_b^2 + C1) exactly.
    b = np.full((16, 16, 1), 0.5)
    c1 = 0.01**2
    expect = (2 * 0.3 * 0.5 + c1) / (0.3**2 + 0.5**2 + c1)
    assert float(metrics.ssim(a, b)) == pytest.approx(expect, abs=1e-12)
    # An image against its negative about the mean: correlation -1 on a zero-mean-ish pattern.
    rng = np.random.default_rng(0)
    x = rng.uniform(size=(24, 24, 1))
    assert float(metrics.ssim(x, 1 - x)) < 0.0


def test_gaussian_window_is_scipy_kernel():
    imp = np.zeros(21)
    imp[10] = 1.0
    from scipy.ndimage import gaussian_filter1d

    k = gaussian_filter1d(imp, 1.5, truncate=3.5)[5:16]
    np.testing.assert_allclose(metrics.gaussian_window(11, 1.5), k, atol=1e-12)


def test_psnr_and_masked_psnr():
    a = np.zeros((4, 4, 3))
    b = np.full((4, 4, 3), 0.1)
    assert float(metrics.psnr(a, b)) == pytest.approx(20.0, abs=1e-9)
    b2 = b.copy()
    b2[:2] = 0.0
    mask = np.zeros((4, 4), bool)
    mask[2:] = True
    assert float(metrics.masked_psnr(a, b2, mask)) == pytest.approx(20.0, abs=1e-9)
    assert np.isnan(float(metrics.masked_psnr(a, b2, np.zeros((4, 4), bool))))


def test_epe_and_ari():
    f = np.zeros((3, 3, 2))
    g = np.zeros((3, 3, 2))
    g[..., 0] = 3.0
    g[..., 1] = 4.0
    assert float(metrics.epe(f, g)) == pytest.approx(5.0)
    valid = np.zeros((3, 3), bool)
    assert float(metrics.epe(f, g, valid)) == 0.0
    assert metrics.ari([0, 0, 1, 1], [5, 5, 2, 2]) == pytest.approx(1.0)
    assert metrics.ari([0, 0, 1, 1], [0, 1, 0, 1]) < 0.0


def test_ssim_gradient_matches_finite_differences_and_vanishes_at_its_maximum():
    """d SSIM / d a against central differences (float64), and zero at a = b, where SSIM = 1 is its maximum."""
    import jax
    from jax.test_util import check_grads

    rng = np.random.default_rng(1)
    a = jnp.asarray(rng.uniform(size=(16, 16, 3)), jnp.float64)
    b = jnp.asarray(rng.uniform(size=(16, 16, 3)), jnp.float64)
    g = jax.grad(lambda x: metrics.ssim(x, b))(a)
    assert np.all(np.isfinite(np.asarray(g))) and float(jnp.abs(g).max()) > 1e-4
    check_grads(lambda x: metrics.ssim(x, b), (a,), order=1, modes=("rev",), atol=1e-6, rtol=1e-5)
    assert float(metrics.ssim(b, b)) == pytest.approx(1.0)
    assert float(jnp.abs(jax.grad(lambda x: metrics.ssim(x, b))(b)).max()) < 1e-9


def test_rotation_angle_deg_matches_the_norm_of_so3_log():
    """`fgjax.metrics.rotation_angle_deg` (numpy, for errors and thresholds) against |so3_log| in float64 on
    random rotations of every size, batched; 0 and 180 degrees exactly; slightly non-orthonormal input stays in
    [0, 180]; NaN propagates."""
    from fgjax import geometry
    from fgjax.metrics import rotation_angle_deg

    rng = np.random.default_rng(0)
    axes = rng.normal(size=(4, 50, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    angles = rng.uniform(1e-3, np.pi - 1e-3, size=(4, 50))
    rot = np.asarray(geometry.so3_exp(jnp.asarray(axes * angles[..., None], jnp.float64)))  # float64: conftest's x64
    ref = np.degrees(np.linalg.norm(np.asarray(geometry.so3_log(jnp.asarray(rot, jnp.float64))), axis=-1))
    got = rotation_angle_deg(rot)
    assert got.shape == (4, 50)
    np.testing.assert_allclose(got, ref, atol=1e-6)
    np.testing.assert_allclose(got, np.degrees(angles), atol=1e-6)
    flip = np.diag([1.0, -1.0, -1.0])
    assert rotation_angle_deg(np.eye(3)) == 0.0 and rotation_angle_deg(flip) == 180.0
    assert rotation_angle_deg(1.001 * np.eye(3)) == 0.0 and rotation_angle_deg(1.001 * flip) == 180.0
    assert np.isnan(rotation_angle_deg(np.full((3, 3), np.nan)))
