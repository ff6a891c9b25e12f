"""Gaussians moved rigidly per object: per-label transforms and one-hot object features (the per-label Kabsch fit
is `fgjax.geometry.fit_group_poses`).

Poses are world-space rigid transforms [K, 4, 4] (x -> R x + t, scene units); labels [N] in -1..K-1 (-1: static,
not moved); quaternions wxyz, raw (not normalised), as in `fgjax.gaussians.Gaussians`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from fgjax import geometry
from fgjax.geometry import HIGHEST

__all__ = ["transform_gaussians", "label_onehot"]


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


def label_onehot(labels: Int[ArrayLike, " N"], num_objects: int) -> Float[np.ndarray, "N K+1"]:
    """Per-Gaussian features [N, K + 1] float32 for rendering object masks: channel 0 for the static
    Gaussians (label -1), channel k + 1 for object k."""
    labels = np.asarray(labels)
    out = np.zeros((len(labels), num_objects + 1), np.float32)
    out[np.arange(len(labels)), np.where(labels >= 0, labels + 1, 0)] = 1.0
    return out
