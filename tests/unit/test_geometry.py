"""SO(3)/SE(3), quaternions, camera conventions and projection (fgjax.geometry).

Oracles: the exponential power series of the (4x4) twist matrix, finite differences (``check_grads``) in
float64, and explicit formulas. Tolerances are float64 unless a test says otherwise. Everything is run
under ``jax.jit`` with few distinct shapes: eager dispatch compiles every primitive separately and
would dominate the run time.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from jax.test_util import check_grads

from fgjax import geometry as g

# Angles crossing every branch: 0, the float64 small-angle threshold (theta^2 = eps^(1/4) -> theta ~ 0.011),
# generic, and the near-pi branch (cos theta < -0.8 -> theta > 2.498) up to pi.
ANGLES = jnp.array([0.0, 1e-12, 1e-7, 1e-4, 1e-2, 0.0109, 0.0111, 0.105, 0.5, 2.0, 2.6, 3.0, np.pi - 1e-3,
                    np.pi - 1e-7])
NEAR_PI = ANGLES > 3.1

exp_j = jax.jit(g.so3_exp)
log_j = jax.jit(g.so3_log)
log_exp_j = jax.jit(lambda w: g.so3_log(g.so3_exp(w)))


def _rand_axis(key, shape):
    a = jr.normal(key, shape + (3,))
    return a / jnp.linalg.norm(a, axis=-1, keepdims=True)


def _expm_series(m, terms=40, shift=0):
    """sum_k M^k / (k + shift)!: exp(M) for shift 0, the SO(3) left Jacobian of hat(w) for shift 1. Exact to
    float64 for |M| <= ~pi (pi^40 / 40! ~ 1e-28). A fori_loop keeps the compiled graph small."""

    def body(k, carry):
        out, term = carry
        term = term @ m / (k + shift)
        return out + term, term

    eye = jnp.eye(m.shape[-1], dtype=m.dtype)
    return jax.lax.fori_loop(1, terms, body, (eye, eye))[0]


def _twist_matrix(xi):
    return jnp.zeros((4, 4)).at[:3, :3].set(g.hat(xi[:3])).at[:3, 3].set(xi[3:])


# ------------------------------------------------------------------------------------- SO(3)


def test_hat_vee_cross():
    kw, kp = jr.split(jr.key(1))
    w, p = jr.normal(kw, (2, 3, 3)), jr.normal(kp, (2, 3, 3))
    np.testing.assert_allclose((g.hat(w) @ p[..., None])[..., 0], jnp.cross(w, p), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g.vee(g.hat(w)), w, rtol=0, atol=1e-15)


@jax.jit
def _exp_and_oracle(w):
    r = g.so3_exp(w)
    expected = jax.vmap(lambda x: _expm_series(g.hat(x)))(w)
    jac = jax.vmap(jax.jacfwd(g.so3_exp))(w)
    jac_expected = jax.vmap(jax.jacfwd(lambda x: _expm_series(g.hat(x))))(w)
    return r, expected, jac, jac_expected


def test_so3_exp_and_jacobian_match_series():
    """exp and its Jacobian across the small-angle branch against the power series (abs 1e-12 / 1e-11)."""
    w = _rand_axis(jr.key(2), (1,)) * ANGLES[:, None]  # [A, 3]
    r, expected, jac, jac_expected = _exp_and_oracle(w)
    np.testing.assert_allclose(r, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(r @ jnp.swapaxes(r, -1, -2), jnp.broadcast_to(jnp.eye(3), r.shape), atol=1e-13)
    np.testing.assert_allclose(jnp.linalg.det(r), 1.0, atol=1e-13)
    assert jnp.all(jnp.isfinite(jac))
    np.testing.assert_allclose(jac, jac_expected, rtol=0, atol=1e-11)


def test_so3_exp_batch_shapes():
    w = _rand_axis(jr.key(3), (2, 3)) * 0.7
    r = exp_j(w)
    assert r.shape == (2, 3, 3, 3)
    np.testing.assert_allclose(r[1, 2], exp_j(w[1, 2]), atol=1e-15)


def test_so3_log_inverts_exp():
    """log(exp(w)) == w for |w| < pi, relative 1e-12, across the Taylor thresholds and the near-pi branch."""
    w = _rand_axis(jr.key(4), (16, 1)) * ANGLES[None, :, None]  # [16, A, 3]
    err = jnp.linalg.norm(log_exp_j(w) - w, axis=-1)
    assert jnp.all(err <= 1e-12 * ANGLES[None] + 1e-300), err.max(axis=0)


def test_so3_log_at_pi_is_a_valid_log():
    """At exactly pi the sign is arbitrary, but exp(log(R)) must give R back and |log R| = pi."""
    w = _rand_axis(jr.key(5), (16, 1)) * jnp.full((1, 14, 1), np.pi)  # same shape as above: no recompile
    r = exp_j(w)
    out = log_j(r)
    np.testing.assert_allclose(jnp.linalg.norm(out, axis=-1), np.pi, atol=1e-12)
    np.testing.assert_allclose(exp_j(out), r, atol=1e-12)


def test_so3_log_jacobian_inverts_exp_jacobian():
    """d log(exp(w)) / dw = I for |w| < pi (reverse mode, through all three branches); 1e-10 absolute,
    2e-8 within 1e-3 of pi (the Jacobian of log grows like 1 / (pi - theta) there)."""
    w = _rand_axis(jr.key(6), (1,)) * ANGLES[:, None]
    jac = jax.jit(jax.vmap(jax.jacrev(lambda x: g.so3_log(g.so3_exp(x)))))(w)
    atol = jnp.where(NEAR_PI, 2e-8, 1e-10)
    dev = jnp.abs(jac - jnp.eye(3)[None]).max(axis=(1, 2))
    assert jnp.all(dev <= atol), dev


def test_so3_log_grad_nan_regression_identity_and_pi():
    """Regression (NaN bug class): gradients of log at R = I and at angle exactly pi are finite (reverse mode,
    the one training uses); at identity d log along each generator hat(e_k) is e_k."""
    rots = jnp.stack(
        [jnp.eye(3), g.so3_exp(jnp.array([0.0, 0.0, np.pi])), g.so3_exp(jnp.array([1.0, 2.0, 2.0]) / 3 * np.pi)]
    )
    jac_r = jax.jit(jax.vmap(jax.jacrev(g.so3_log)))(rots)
    assert jnp.all(jnp.isfinite(jac_r))
    for k in range(3):
        e = jnp.zeros(3).at[k].set(1.0)
        np.testing.assert_allclose(jnp.tensordot(jac_r[0], g.hat(e), axes=2), e, atol=1e-14)


def test_so3_check_grads_generic():
    """Finite differences (float64, 1e-7) on the generic and near-pi branches."""
    w = jnp.array([0.3, -0.7, 1.1])
    check_grads(exp_j, (w,), order=1, modes=("rev",), atol=1e-7, rtol=1e-7)
    check_grads(log_j, (g.so3_exp(w),), order=1, modes=("rev",), atol=1e-7, rtol=1e-7)
    check_grads(log_j, (g.so3_exp(jnp.array([0.3, -0.7, 2.9])),), order=1, modes=("rev",), atol=1e-7, rtol=1e-7)


def test_so3_float32():
    """float32: thresholds follow the dtype (theta^2 < eps32^(1/4) -> theta < 0.136); round trip to 2e-6
    absolute below 3 rad (3e-4 within 1e-2 of pi, where float32 trace/cos lose digits), finite gradients
    everywhere, Jacobian = I to 1e-4 below 3 rad."""
    angles = jnp.array([0.0, 1e-6, 0.05, 0.135, 0.137, 1.5, np.pi - 1e-2], dtype=jnp.float32)
    w = (_rand_axis(jr.key(7), (4, 1)) * angles[None, :, None]).astype(jnp.float32).reshape(-1, 3)  # [28, 3]

    @jax.jit
    def run(w):
        return g.so3_log(g.so3_exp(w)), jax.vmap(jax.jacrev(lambda x: g.so3_log(g.so3_exp(x))))(w)

    out, jac = run(w)
    assert out.dtype == jnp.float32 and jac.dtype == jnp.float32
    small = jnp.tile(angles < 3, 4)
    err = jnp.abs(out - w).max(axis=-1)
    assert jnp.all(err <= jnp.where(small, 2e-6, 3e-4)), err
    assert jnp.all(jnp.isfinite(jac))
    assert jnp.all(jnp.abs(jac - jnp.eye(3, dtype=jnp.float32)[None])[small] <= 1e-4)


def test_left_jacobian_and_inverse():
    """V against its series sum_k hat(w)^k / (k+1)!, and V V^-1 = I, across branches (1e-12)."""
    w = _rand_axis(jr.key(8), (1,)) * jnp.array([0.0, 1e-6, 0.011, 1.0, 3.0])[:, None]

    @jax.jit
    def run(w):
        v_series = jax.vmap(lambda x: _expm_series(g.hat(x), shift=1))(w)  # V = sum_k hat^k / (k+1)!
        return g.so3_left_jacobian(w), g.so3_left_jacobian_inv(w), v_series

    v, vi, v_ser = run(w)
    np.testing.assert_allclose(v @ vi, jnp.broadcast_to(jnp.eye(3), v.shape), atol=1e-12)
    np.testing.assert_allclose(v, v_ser, atol=1e-12)


# ------------------------------------------------------------------------------------- quaternions


def test_quaternions():
    """wxyz of any norm (and sign) -> the axis-angle rotation; Shepperd's inverse in all four branches."""
    k1, k2 = jr.split(jr.key(9))
    w = _rand_axis(k1, (2, 3)) * jnp.array([0.1, 1.0, 3.1])[None, :, None]  # [2, 3, 3]
    angle = jnp.linalg.norm(w, axis=-1, keepdims=True)
    q = jnp.concatenate([jnp.cos(angle / 2), jnp.sin(angle / 2) * w / angle], axis=-1)  # [2, 3, 4]
    scale = jr.uniform(k2, (2, 3, 1), minval=0.1, maxval=10.0)

    @jax.jit
    def run(q, w):
        r = g.so3_exp(w)
        return r, g.quat_to_rotmat(q * scale), g.quat_to_rotmat(-q * scale), g.rotmat_to_quat(r)

    r, r1, r2, qq = run(q, w)
    np.testing.assert_allclose(r1, r, atol=1e-13)
    np.testing.assert_allclose(r2, r, atol=1e-13)
    np.testing.assert_allclose(jnp.linalg.norm(qq, axis=-1), 1.0, atol=1e-14)
    assert jnp.all(qq[..., 0] >= 0)
    np.testing.assert_allclose(qq, q * jnp.sign(q[..., :1]), atol=1e-13)
    # 180-degree turns about x, y, z: w = 0 and one dominant component (branches 2-4); branch 1 above
    turns = g.so3_exp(jnp.eye(3) * np.pi)
    np.testing.assert_allclose(jnp.abs(jax.jit(g.rotmat_to_quat)(turns)), jnp.eye(4)[1:], atol=1e-15)


def test_quat_zero_is_finite():
    np.testing.assert_allclose(g.quat_to_rotmat(jnp.zeros(4)), jnp.eye(3))
    assert jnp.all(jnp.isfinite(jax.jit(jax.jacrev(g.quat_to_rotmat))(jnp.zeros(4))))


# ------------------------------------------------------------------------------------- SE(3)


def test_se3_exp_matches_series_and_log_inverts():
    """se3_exp = exp of the 4x4 twist matrix (1e-12); se3_log inverts it (1e-11); d log exp = I (1e-8)."""
    k1, k2 = jr.split(jr.key(11))
    angles = jnp.array([0.0, 1e-8, 1e-3, 0.0111, 0.7, 3.0])
    xi = jnp.concatenate([_rand_axis(k1, (1,)) * angles[:, None], jr.normal(k2, (6, 3))], axis=-1)  # [6, 6]

    @jax.jit
    def run(xi):
        t = g.se3_exp(xi)
        return (
            t,
            jax.vmap(lambda x: _expm_series(_twist_matrix(x), 60))(xi),  # |xi| up to ~4: 60 terms
            g.se3_log(t),
            jax.vmap(jax.jacrev(lambda x: g.se3_log(g.se3_exp(x))))(xi),
        )

    t, t_ser, log_t, jac = run(xi)
    np.testing.assert_allclose(t, t_ser, atol=1e-12)
    np.testing.assert_allclose(log_t, xi, atol=1e-11)
    np.testing.assert_allclose(jac, jnp.broadcast_to(jnp.eye(6), jac.shape), atol=1e-8)


def test_se3_compose_inverse():
    k1, k2 = jr.split(jr.key(12))
    xa, xb = jr.normal(k1, (2, 3, 6)), jr.normal(k2, (2, 3, 6))
    a, b = g.se3_exp(xa), g.se3_exp(xb)
    eye = jnp.broadcast_to(jnp.eye(4), a.shape)
    np.testing.assert_allclose(g.se3_compose(a, g.se3_inverse(a)), eye, atol=1e-13)
    np.testing.assert_allclose(g.se3_inverse(a), jnp.linalg.inv(a), atol=1e-12)
    np.testing.assert_allclose(g.se3_compose(a, g.se3_exp(-xa)), eye, atol=1e-13)
    p = jnp.ones((2, 3, 4, 1))
    np.testing.assert_allclose(g.se3_compose(a, b) @ p, a @ (b @ p), atol=1e-12)
    np.testing.assert_allclose(
        g.se3_inverse(g.se3_compose(a, b)), g.se3_compose(g.se3_inverse(b), g.se3_inverse(a)), atol=1e-12
    )


# ------------------------------------------------------------------------------------- cameras


def test_opengl_opencv_conversion():
    """A point straight ahead of an OpenGL camera (along -z_gl) has z > 0 in the converted OpenCV camera,
    and a point above it (+y_gl) has y < 0 (OpenCV y points down). The conversion is an involution and keeps
    the camera centre."""
    c2w_gl = g.se3_exp(jnp.array([0.4, -0.2, 0.9, 1.0, 2.0, 3.0]))
    c2w_cv = g.opengl_to_opencv_c2w(c2w_gl)
    np.testing.assert_allclose(g.opencv_to_opengl_c2w(c2w_cv), c2w_gl, atol=0)
    np.testing.assert_allclose(c2w_cv[:3, 3], c2w_gl[:3, 3], atol=0)
    centre, fwd_gl, up_gl = c2w_gl[:3, 3], -c2w_gl[:3, 2], c2w_gl[:3, 1]
    w2c = g.se3_inverse(c2w_cv)
    ahead = w2c[:3, :3] @ (centre + 2.0 * fwd_gl) + w2c[:3, 3]
    above = w2c[:3, :3] @ (centre + 2.0 * fwd_gl + 0.5 * up_gl) + w2c[:3, 3]
    np.testing.assert_allclose(ahead, [0.0, 0.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(above, [0.0, -0.5, 2.0], atol=1e-12)
    both = g.opengl_to_opencv_c2w(jnp.stack([c2w_gl, c2w_gl]))
    np.testing.assert_allclose(both[1], c2w_cv)


@pytest.mark.parametrize("batch", [(), (2, 3)])
def test_project_points(batch):
    K = jnp.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    p = jr.normal(jr.key(13), batch + (3,)) + jnp.array([0.0, 0.0, 4.0]).reshape((1,) * len(batch) + (3,))
    uv = g.project_points(p, K)
    assert uv.shape == batch + (2,)
    np.testing.assert_allclose(uv[..., 0], 500.0 * p[..., 0] / p[..., 2] + 320.0, rtol=1e-14)
    np.testing.assert_allclose(uv[..., 1], 480.0 * p[..., 1] / p[..., 2] + 240.0, rtol=1e-14)
    # on the optical axis: lands on (cx, cy) (the corner shared by pixels 319 and 320 in our convention)
    np.testing.assert_allclose(g.project_points(jnp.array([0.0, 0.0, 3.0]), K), [320.0, 240.0])


def test_project_points_z0_finite():
    """Regression (NaN bug class): z = 0 gives finite values and gradients."""
    K = jnp.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    z0 = jnp.array([1.0, 1.0, 0.0])
    assert jnp.all(jnp.isfinite(g.project_points(z0, K)))
    assert jnp.all(jnp.isfinite(jax.jit(jax.jacrev(g.project_points))(z0, K)))


def test_jit_vmap():
    w = _rand_axis(jr.key(14), (14,)) * ANGLES[:, None]
    r = exp_j(w)
    np.testing.assert_allclose(jax.jit(jax.vmap(g.so3_log))(r), log_j(r), atol=1e-15)


def test_the_rasterizers_quaternion_matrix_agrees_with_geometrys():
    """`fgjax.render.project.quat_to_rotmat` (normalise first, as gsplat) and `fgjax.geometry.quat_to_rotmat` (closed
    form) are two forms of one map: equal to float64 rounding for any norm, the identity for a zero quaternion."""
    from fgjax.render.project import quat_to_rotmat as raster_form

    q = np.random.default_rng(0).normal(size=(64, 4)) * np.random.default_rng(1).uniform(0.01, 10.0, (64, 1))
    q = np.concatenate([q, np.zeros((1, 4))])
    np.testing.assert_allclose(np.asarray(raster_form(jnp.asarray(q))), np.asarray(g.quat_to_rotmat(q)),
                               rtol=0, atol=1e-12)


def test_safe_norm_is_the_norm_with_a_zero_gradient_at_zero():
    x = np.array([[3.0, 4.0], [0.0, 0.0], [-1.0, 2.0]])
    np.testing.assert_allclose(np.asarray(g.safe_norm(x)), np.linalg.norm(x, axis=-1), rtol=1e-6)
    grad = np.asarray(jax.grad(lambda v: jnp.sum(g.safe_norm(v)))(jnp.asarray(x)))
    np.testing.assert_allclose(grad[0], [0.6, 0.8], rtol=1e-6)
    assert np.array_equal(grad[1], [0.0, 0.0])
