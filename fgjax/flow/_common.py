"""Helpers shared by `fgjax.flow.motion`, `fgjax.flow.gaussian` and `fgjax.flow.track` (private to the package)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

from fgjax import geometry

mm = geometry.matmul  # full float32 precision on every backend (geometry.HIGHEST)


def check_shape(name: str, x: Array, tail: tuple[int, ...]) -> None:
    """ValueError naming `name` unless `x` has the trailing shape `tail`."""
    if x.shape[x.ndim - len(tail) :] != tail or x.ndim < len(tail):
        raise ValueError(f"{name} must have trailing shape {list(tail)}; got {list(x.shape)}.")


def safe_inv_depth(depth: Array) -> Array:
    """1/Z where Z is finite and > 0; 0 elsewhere (a point at infinity). Finite gradients (double-where)."""
    ok = jnp.isfinite(depth) & (depth > 0)
    return jnp.where(ok, 1.0 / jnp.where(ok, depth, 1.0), 0.0)


def intrinsics(K: Array) -> tuple[Array, Array, Array, Array]:
    """(fx, fy, cx, cy) of a 3x3 K."""
    return K[0, 0], K[1, 1], K[0, 2], K[1, 2]


def charbonnier(e2: Array, scale: float) -> Array:
    """c^2 (sqrt(1 + e2 / c^2) - 1) of squared residual norms e2, c = ``scale`` (Charbonnier 1994): e2 / 2 for
    small residuals, c |e| beyond; smooth at 0."""
    c2 = float(scale) ** 2
    return c2 * (jnp.sqrt(1.0 + e2 / c2) - 1.0)
