"""Gaussians moved rigidly per object: per-label transforms, per-label Kabsch fits, one-hot object features.

Poses are world-space rigid transforms [K, 4, 4] (x -> R x + t, scene units); labels [N] in -1..K-1 (-1: static,
not moved); quaternions wxyz, raw (not normalised), as in `fgjax.gaussians.Gaussians`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from fgjax import geometry
from fgjax.geometry import HIGHEST

__all__ = ["transform_gaussians", "fit_group_poses", "label_onehot"]


def transform_gaussians(means: Float[ArrayLike, "N 3"], quats: Float[ArrayLike, "N 4"], labels: Int[ArrayLike, " N"],
                        poses: Float[ArrayLike, "K 4 4"]) -> tuple[Float[Array, "N 3"], Float[Array, "N 4"]]:
    """Move each labelled Gaussian rigidly by its object's pose: (means [N, 3], raw quats [N, 4]).

    ``poses`` [K, 4, 4] world-space rigid transforms (x -> R x + t); ``labels`` [N] in -1..K-1 (-1: not
    moved). The raw quaternion keeps its norm (q' = q_R * q)."""
    labels = jnp.asarray(labels)
    k = jnp.clip(labels, 0)
    moved = labels >= 0
    rot = jnp.asarray(poses)[k, :3, :3]  # [N, 3, 3]
    tr = jnp.asarray(poses)[k, :3, 3]
    m = jnp.einsum("nij,nj->ni", rot, means, precision=HIGHEST) + tr
    q = geometry.quat_multiply(geometry.rotmat_to_quat(rot), quats)
    return jnp.where(moved[:, None], m, means), jnp.where(moved[:, None], q, quats)


def fit_group_poses(src: Float[ArrayLike, "N 3"], dst: Float[ArrayLike, "N 3"], labels: Int[ArrayLike, " N"],
                    num_objects: int, min_points: int = 3) -> Float[Array, "K 4 4"]:
    """Each object's best rigid motion of its points: poses [K, 4, 4] (x -> R x + t, world space) minimising
    sum_i |R src_i + t - dst_i|^2 over the points with ``labels`` [N] == k (Kabsch: t from the centroids, R from
    the SVD of their cross-covariance, its determinant made +1). ``src``, ``dst``: [N, 3]; labels in -1..K-1
    (-1: in no object). An object with fewer than ``min_points`` points gets its centroid shift only (R = I;
    none: the identity), so that one or two points never pick an arbitrary turn. Jitted for each K.

    Not differentiable: the result is held constant under differentiation (a rotation fitted by an SVD has no
    gradient where singular values coincide), so gradients of the poses are 0, never NaN."""
    return _fit_group_poses(jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32),
                            jnp.asarray(labels, jnp.int32), int(num_objects), int(min_points))


@functools.partial(jax.jit, static_argnums=(3, 4))
def _fit_group_poses(src, dst, labels, num_objects, min_points):
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
    return geometry.make_pose(rot, t)


def label_onehot(labels: Int[ArrayLike, " N"], num_objects: int) -> Float[np.ndarray, "N K+1"]:
    """Per-Gaussian features [N, K + 1] float32 for rendering object masks: channel 0 for the static
    Gaussians (label -1), channel k + 1 for object k."""
    labels = np.asarray(labels)
    out = np.zeros((len(labels), num_objects + 1), np.float32)
    out[np.arange(len(labels)), np.where(labels >= 0, labels + 1, 0)] = 1.0
    return out
