"""Dense reference rasterizer: every Gaussian at every pixel, sequential compositing.

Written independently of the tile code (its own projection formulas, no binning, no chunks, no
custom VJP) to serve as the oracle in tests and benchmarks. Cost O(H W N) time and, under
``jax.grad``, O(H W N) memory: small scenes only. Use float64 inputs (``jax_enable_x64``).
Same rules as DESIGN.md section 2.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

_HI = jax.lax.Precision.HIGHEST


def _rotmat(q):
    # R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]_x, for the normalised quaternion (w, v).
    n = jnp.linalg.norm(q, axis=-1, keepdims=True)
    q = jnp.where(n > 0, q / jnp.where(n > 0, n, 1.0), jnp.array([1.0, 0, 0, 0], q.dtype))
    w, v = q[:, 0], q[:, 1:]
    eye = jnp.eye(3, dtype=q.dtype)
    vx = jnp.zeros((q.shape[0], 3, 3), q.dtype)
    vx = vx.at[:, 0, 1].set(-v[:, 2]).at[:, 0, 2].set(v[:, 1]).at[:, 1, 0].set(v[:, 2])
    vx = vx.at[:, 1, 2].set(-v[:, 0]).at[:, 2, 0].set(-v[:, 1]).at[:, 2, 1].set(v[:, 0])
    return ((w * w - jnp.sum(v * v, -1))[:, None, None] * eye
            + 2.0 * v[:, :, None] * v[:, None, :] + 2.0 * w[:, None, None] * vx)


def project_reference(means, quats, scales, opacities, viewmat, K, width, height, near_plane=0.01):
    """means2d [N,2], conic [N,3], cov2d [N,3], depth [N], valid [N] by direct formulas."""
    Rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    pc = jnp.einsum("ij,nj->ni", Rw, means, precision=_HI) + tw
    z = pc[:, 2]
    valid = (z > near_plane) & (opacities >= 1.0 / 255.0)
    zs = jnp.where(valid, z, 1.0)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = pc[:, 0] / zs
    v = pc[:, 1] / zs
    means2d = jnp.stack([fx * u + cx, fy * v + cy], -1)
    tanx, tany = width / (2 * fx), height / (2 * fy)
    uc = jnp.clip(u, -cx / fx - 0.3 * tanx, (width - cx) / fx + 0.3 * tanx)
    vc = jnp.clip(v, -cy / fy - 0.3 * tany, (height - cy) / fy + 0.3 * tany)
    J = jnp.zeros((means.shape[0], 2, 3), means.dtype)
    J = J.at[:, 0, 0].set(fx / zs).at[:, 0, 2].set(-fx * uc / zs)
    J = J.at[:, 1, 1].set(fy / zs).at[:, 1, 2].set(-fy * vc / zs)
    R = _rotmat(quats)
    S2 = jnp.where(valid[:, None], scales, 1.0) ** 2
    Sig = jnp.einsum("nij,nj,nkj->nik", R, S2, R, precision=_HI)
    Sc = jnp.einsum("ij,njk,lk->nil", Rw, Sig, Rw, precision=_HI)
    cov = jnp.einsum("nij,njk,nlk->nil", J, Sc, J, precision=_HI) + 0.3 * jnp.eye(2, dtype=means.dtype)
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    valid = valid & (det > 0)
    det = jnp.where(valid, det, 1.0)
    conic = jnp.stack([c / det, -b / det, a / det], -1)
    return means2d, conic, jnp.stack([a, b, c], -1), z, valid


def rasterize_dense(means, quats, scales, opacities, colors, viewmat, K, width, height,
                    background=None, near_plane=0.01):
    """Reference render: returns image [H, W, C], alpha [H, W], expected depth [H, W]."""
    if means.shape[0] == 0:
        img = jnp.zeros((height, width, colors.shape[1]), means.dtype)
        img = img if background is None else img + background
        zero = jnp.zeros((height, width), means.dtype)
        return img, zero, zero
    means2d, conic, _, z, valid = project_reference(
        means, quats, scales, opacities, viewmat, K, width, height, near_plane)
    order = jnp.argsort(jnp.where(valid, z, jnp.inf), stable=True)
    jj, ii = jnp.meshgrid(jnp.arange(width), jnp.arange(height))
    pix = jnp.stack([jj, ii], -1).reshape(-1, 2).astype(means.dtype) + 0.5  # [P, 2]
    C = colors.shape[1]

    def step(carry, g):
        T, done, col, dep = carry
        d = pix - means2d[g]
        q = conic[g, 0] * d[:, 0] ** 2 + 2 * conic[g, 1] * d[:, 0] * d[:, 1] + conic[g, 2] * d[:, 1] ** 2
        alpha = jnp.minimum(0.99, opacities[g] * jnp.exp(-0.5 * q))
        counts = valid[g] & (alpha >= 1.0 / 255.0) & ~done
        nextT = T * (1.0 - alpha)
        stop = counts & (nextT <= 1e-4)
        use = counts & ~stop
        w = jnp.where(use, alpha * T, 0.0)
        col = col + w[:, None] * colors[g]
        dep = dep + w * jnp.where(valid[g], z[g], 0.0)
        T = jnp.where(use, nextT, T)
        return (T, done | stop, col, dep), None

    P = pix.shape[0]
    init = (jnp.ones(P, means.dtype), jnp.zeros(P, bool), jnp.zeros((P, C), means.dtype), jnp.zeros(P, means.dtype))
    (T, _, col, dep), _ = jax.lax.scan(step, init, order)
    alpha = 1.0 - T
    if background is not None:
        col = col + T[:, None] * background
    has = alpha > 1e-6
    depth = jnp.where(has, dep / jnp.where(has, alpha, 1.0), 0.0)
    return col.reshape(height, width, C), alpha.reshape(height, width), depth.reshape(height, width)
