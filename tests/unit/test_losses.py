"""Training losses (fgjax.train.losses) against closed forms and finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fgjax.gaussians import knn_graph
from fgjax.geometry import so3_exp
from fgjax.train.losses import (
    depth_loss,
    isometry_loss,
    photometric_loss,
    rigid_drift_loss,
    scale_regularizer,
)


def _cloud(seed=0, n=60):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3))
    alive = np.ones(n, bool)
    alive[-7:] = False
    return rng, x, alive


def _assert_gradient_matches_central_differences(f, x, rng):
    """jax.grad of the scalar f at a random point near x, against a central difference along a random
    direction (float64)."""
    xt = x + 0.05 * rng.normal(size=x.shape)
    g = np.asarray(jax.grad(f)(jnp.asarray(xt)))
    d = rng.normal(size=x.shape)
    h = 1e-6
    fd = (float(f(xt + h * d)) - float(f(xt - h * d))) / (2 * h)
    assert np.sum(g * d) == pytest.approx(fd, rel=1e-5)


def test_knn_graph_matches_brute_force_and_masks_dead_slots():
    _, x, alive = _cloud()
    idx, w = knn_graph(x, alive, 5)
    assert idx.shape == (60, 5) and w.shape == (60, 5) and idx.dtype == np.int32
    live = np.flatnonzero(alive)
    d = np.linalg.norm(x[live, None] - x[None, live], axis=-1)
    np.fill_diagonal(d, np.inf)
    brute = live[np.argsort(d, axis=1)[:, :5]]
    np.testing.assert_array_equal(np.sort(idx[live], 1), np.sort(brute, 1))
    assert np.all(w[live] == 1) and np.all(w[~alive] == 0) and np.all(alive[idx[live]])
    # fewer live slots than k: padded with weight 0; one or none: no pairs
    few = np.zeros(60, bool)
    few[:3] = True
    idx, w = knn_graph(x, few, 5)
    assert w.sum() == 3 * 2 and np.all(w[:3, 2:] == 0)
    assert knn_graph(x, np.zeros(60, bool), 5)[1].sum() == 0


def test_isometry_loss_zero_for_rigid_motion_and_exact_for_scaling():
    rng, x, alive = _cloud(1)
    idx, w = knn_graph(x, alive, 6)
    r = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    assert float(isometry_loss(x @ r.T + np.array([0.3, -1.0, 2.0]), x, idx, w)) < 1e-6
    assert float(isometry_loss(1.1 * x, x, idx, w)) == pytest.approx(0.1, rel=1e-5)
    # a dead slot moving anywhere costs nothing
    far = x.copy()
    far[~alive] += 100.0
    assert float(isometry_loss(far, x, idx, w)) < 1e-9
    # gradients: finite where points coincide, and match central differences elsewhere (float64)
    x2 = x.copy()
    x2[1] = x2[0]
    g = jax.grad(lambda m: isometry_loss(m, x2, idx, w))(jnp.asarray(x2))
    assert bool(jnp.all(jnp.isfinite(g)))
    _assert_gradient_matches_central_differences(lambda m: isometry_loss(m, x, idx, w), x, rng)


def test_isometry_loss_cap_is_quadratic_at_rest_bounded_and_matches_central_differences():
    rng, x, alive = _cloud(2)
    idx, w = knn_graph(x, alive, 6)
    cap = 0.5
    r = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    assert float(isometry_loss(x @ r.T + 1.0, x, idx, w, cap=cap)) < 1e-9  # rigid motion is still free
    # a uniform 1.1x stretch: every pair has e = 0.1, so the cost is cap e^2 / (e^2 + cap^2) exactly
    assert float(isometry_loss(1.1 * x, x, idx, w, cap=cap)) == pytest.approx(cap * 0.01 / (0.01 + cap**2), rel=1e-4)
    # at rest the capped loss has no gradient (the plain one has |grad| ~ 1 / pair length: it pins parts)
    g0 = np.asarray(jax.grad(lambda m: isometry_loss(m, x, idx, w, cap=cap))(jnp.asarray(x)))
    g1 = np.asarray(jax.grad(lambda m: isometry_loss(m, x, idx, w))(jnp.asarray(x + 1e-4 * rng.normal(size=x.shape))))
    assert np.abs(g0).max() < 1e-6 < np.abs(g1).max()
    # bounded: tearing the cloud apart costs at most cap per pair
    assert float(isometry_loss(1000.0 * x, x, idx, w, cap=cap)) <= cap + 1e-6
    # finite differences (float64) away from rest
    _assert_gradient_matches_central_differences(lambda m: isometry_loss(m, x, idx, w, cap=cap), x, rng)


def test_photometric_and_scale_regulariser_values():
    a = jnp.zeros((16, 16, 3))
    b = jnp.full((16, 16, 3), 0.5)
    assert float(photometric_loss(a, a)) == pytest.approx(0.0, abs=1e-12)
    assert float(photometric_loss(a, b, 0.0)) == pytest.approx(0.5)
    ls = jnp.log(jnp.array([[0.01, 0.02, 0.03], [0.2, 0.01, 0.01], [0.5, 0.5, 0.5]]))
    w = jnp.array([1.0, 1.0, 0.0])
    assert float(scale_regularizer(ls, w, 0.05)) == pytest.approx((0.0 + 0.15) / 2)


def test_scale_change_loss():
    from fgjax.train.losses import scale_change_loss

    ls = jnp.log(jnp.full((4, 3), 0.02))
    w = jnp.array([1.0, 1.0, 1.0, 0.0])
    assert float(scale_change_loss(ls, ls, w)) == 0.0
    shrunk = ls.at[0].add(-2.0).at[3].add(5.0)  # the dead slot's change is ignored
    assert float(scale_change_loss(shrunk, ls, w)) == pytest.approx(2.0 / 3)
    g = jax.grad(lambda x: scale_change_loss(x, ls, w))(shrunk)
    assert bool(jnp.all(jnp.isfinite(g))) and float(jnp.abs(g[3]).max()) == 0.0


def test_l1_terms_push_nothing_at_a_zero_residual():
    """jnp.abs has derivative 1 at 0: the isometry and scale-change priors at rest, and the flow loss where target and
    Gaussian flow agree, must have zero gradient instead (`fgjax.geometry.abs0`)."""
    import jax

    from fgjax.flow import flow_loss
    from fgjax.geometry import abs0
    from fgjax.train.losses import isometry_loss, scale_change_loss

    assert float(jax.grad(abs0)(0.0)) == 0.0 and float(jax.grad(abs0)(-2.0)) == -1.0
    x = jnp.asarray(np.random.default_rng(0).normal(size=(6, 3)), jnp.float32)
    idx = jnp.asarray([[1, 2], [0, 2], [0, 1], [4, 5], [3, 5], [3, 4]])
    g = jax.grad(lambda m: isometry_loss(m, x, idx, jnp.ones((6, 2))))(x)
    assert float(jnp.abs(g).max()) == 0.0
    ls = jnp.zeros((6, 3))
    assert float(jnp.abs(jax.grad(lambda s: scale_change_loss(s, ls, jnp.ones(6)))(ls)).max()) == 0.0
    f = jnp.zeros((4, 5, 2))
    assert float(jnp.abs(jax.grad(lambda gs: flow_loss(f, f, gs))(f)).max()) == 0.0
    # and a stretched pair still pulls back
    g2 = jax.grad(lambda m: isometry_loss(m, x, idx, jnp.ones((6, 2))))(x.at[0].add(0.3))
    assert float(jnp.abs(g2).max()) > 0.0



def test_depth_loss_is_the_relative_l1_on_measured_pixels_with_exact_gradients():
    """Against a loop over pixels (float64), gradients against central differences; unknown pixels (0, NaN, inf,
    negative) count for nothing, a map with none gives 0 with a zero, finite gradient."""
    rng = np.random.default_rng(3)
    z = rng.uniform(0.5, 3.0, (7, 9))
    d = rng.uniform(0.5, 3.0, (7, 9))
    d[0, :4] = [0.0, np.nan, np.inf, -1.0]
    ref, n = 0.0, 0
    for i in range(7):
        for j in range(9):
            if np.isfinite(d[i, j]) and d[i, j] > 0:
                ref += abs(z[i, j] - d[i, j]) / d[i, j]
                n += 1
    assert float(depth_loss(z, d)) == pytest.approx(ref / n, rel=1e-12)
    _assert_gradient_matches_central_differences(lambda x: depth_loss(x, d), z, rng)
    g = np.asarray(jax.grad(depth_loss)(jnp.asarray(z), jnp.asarray(d)))
    assert np.all(np.isfinite(g)) and np.all(g[0, :4] == 0)
    none = np.full((7, 9), np.nan)
    none[1] = 0.0
    assert float(depth_loss(z, none)) == 0.0
    g0 = np.asarray(jax.grad(depth_loss)(jnp.asarray(z), jnp.asarray(none)))
    assert np.all(g0 == 0)
    # an exact match costs nothing and pushes nothing (|x| with a zero derivative at 0)
    assert float(depth_loss(d[1:], d[1:])) == 0.0
    assert np.all(np.asarray(jax.grad(depth_loss)(jnp.asarray(d[1:]), jnp.asarray(d[1:]))) == 0)


def _cube():
    """The 8 corners of [-1, 1]^3 shifted to (2, -1, 0.5): covariance exactly the identity about the centroid."""
    c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    return c + np.array([2.0, -1.0, 0.5])


def test_rigid_drift_loss_measures_the_rigid_part_only():
    x = _cube()
    one = np.ones(8)
    eps, scale = 1e-3, 2.0
    ref = lambda q: np.sqrt(q / scale**2 + eps**2) - eps
    assert float(rigid_drift_loss(x, np.zeros_like(x), one, scale)) == 0.0
    a = np.array([0.3, -0.1, 0.2])
    assert float(rigid_drift_loss(x, np.broadcast_to(a, x.shape), one, scale)) == pytest.approx(ref(a @ a), rel=1e-5)
    # a rotation w about the centroid, linearised: d = w x (X - c); S = I, so L = (tr S - S) w = 2 w and r^2 = 3
    w = np.array([0.02, -0.05, 0.01])
    xc = x - x.mean(0)
    d = np.cross(w, xc)
    assert float(rigid_drift_loss(x, d, one, scale)) == pytest.approx(ref(4 * (w @ w) / 3), rel=1e-4)
    # the same rotation, exact (not linearised), measured about as large
    rot = np.asarray(so3_exp(jnp.asarray(w)))
    d_exact = xc @ rot.T - xc
    assert float(rigid_drift_loss(x, d_exact, one, scale)) == pytest.approx(ref(4 * (w @ w) / 3), rel=2e-2)
    # a pure stretch (symmetric, trace-free) has no rigid part
    stretch = xc @ np.diag([0.1, -0.1, 0.0])
    assert float(rigid_drift_loss(x, stretch, one, scale)) < 1e-6
    # padding rows (mask 0) do not count, whatever they hold
    xp = np.concatenate([x, np.full((3, 3), 50.0)])
    dp = np.concatenate([np.broadcast_to(a, x.shape), np.full((3, 3), 7.0)])
    assert float(rigid_drift_loss(xp, dp, np.r_[one, np.zeros(3)], scale)) == pytest.approx(ref(a @ a), rel=1e-5)


def test_rigid_drift_loss_gradients_match_finite_differences_and_stay_finite():
    rng = np.random.default_rng(3)
    x = jnp.asarray(rng.normal(size=(12, 3)), jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    d = jnp.asarray(rng.normal(scale=0.05, size=(12, 3)), x.dtype)
    m = jnp.asarray((rng.random(12) > 0.2).astype(np.float32))
    f = lambda dd: rigid_drift_loss(x, dd, m, 1.5)
    g = jax.grad(f)(d)
    v = jnp.asarray(rng.normal(size=(12, 3)), x.dtype)
    h = 1e-3
    fd = (f(d + h * v) - f(d - h * v)) / (2 * h)
    assert float(jnp.sum(g * v)) == pytest.approx(float(fd), rel=2e-2, abs=1e-5)
    # degenerate input: no displacement, every point masked off, all points at one place
    for xx, dd, mm in [(x, jnp.zeros_like(d), m), (x, d, jnp.zeros(12)), (jnp.zeros_like(x), d, m)]:
        val, gr = jax.value_and_grad(lambda q: rigid_drift_loss(xx, q, mm, 1.5))(dd)
        assert np.isfinite(float(val)) and bool(jnp.all(jnp.isfinite(gr)))
    assert float(jnp.max(jnp.abs(jax.grad(lambda q: rigid_drift_loss(x, q, jnp.zeros(12), 1.5))(d)))) == 0.0
