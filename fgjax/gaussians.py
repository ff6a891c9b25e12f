"""The trainable Gaussian pytree: pre-activation parameters, activations, initialisation, fixed capacity.

Parameters are stored raw (DESIGN.md section 2): log-scales, opacity logits, unnormalised wxyz
quaternions, SH coefficients [N, K, 3] with K = (degree + 1)^2 (index 0 is the DC term; RGB =
max(SH sum + 0.5, 0)). The pytree holds only float arrays so that ``jax.grad`` and optax apply
directly; which of the N slots are in use (the alive mask) lives in ``fgjax.train.densify``'s state
and is passed to ``activate`` explicitly. Dead slots render with opacity 0 (the rasterizer culls
them: no tile intersections, no cost).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float
from scipy.spatial import cKDTree

__all__ = [
    "Gaussians",
    "num_sh_coeffs",
    "activate",
    "init_random",
    "init_from_points",
    "rgb_to_sh0",
    "knn_graph",
    "SH_C0",
]

SH_C0 = 0.28209479177387814


def num_sh_coeffs(degree: int) -> int:
    """K = (degree + 1)^2 coefficients per colour channel."""
    if not (0 <= int(degree) <= 3):
        raise ValueError(f"SH degree must be in 0..3; got {degree}")
    return (int(degree) + 1) ** 2


def rgb_to_sh0(rgb: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """DC coefficient whose rendered colour is `rgb` (inverse of RGB = C0 * sh0 + 0.5)."""
    return (jnp.asarray(rgb) - 0.5) / SH_C0


class Gaussians(eqx.Module):
    """Pre-activation parameters of up to N Gaussians (fixed capacity). Final: do not subclass."""

    means: Float[Array, "N 3"]
    log_scales: Float[Array, "N 3"]
    quats: Float[Array, "N 4"]  # wxyz, unnormalised
    opacity_logits: Float[Array, " N"]
    sh: Float[Array, "N K 3"]

    def __check_init__(self):
        n = self.means.shape[0]
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"Gaussians.means must be [N, 3]; got {self.means.shape}")
        shapes = {"log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"Gaussians.{name} must have shape {list(shape)} (N={n}); "
                                 f"got {list(getattr(self, name).shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3 or self.sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"Gaussians.sh must be [N, K, 3] with K in (1, 4, 9, 16), N={n}; "
                             f"got {list(self.sh.shape)}")

    @property
    def capacity(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(self.sh.shape[1] ** 0.5)) - 1


def activate(
    g: Gaussians, alive: Bool[ArrayLike, " N"] | None = None
) -> tuple[Float[Array, "N 4"], Float[Array, "N 3"], Float[Array, " N"]]:
    """(quats normalised, scales = exp(log_scales), opacities = sigmoid(logits) * alive)."""
    q = g.quats
    n2 = jnp.sum(q * q, axis=-1, keepdims=True)
    ok = n2 > 1e-24
    q = jnp.where(ok, q / jnp.sqrt(jnp.where(ok, n2, 1.0)), jnp.array([1.0, 0.0, 0.0, 0.0], q.dtype))
    scales = jnp.exp(g.log_scales)
    opac = jax.nn.sigmoid(g.opacity_logits)
    if alive is not None:
        opac = jnp.where(jnp.asarray(alive), opac, 0.0)
    return q, scales, opac


def _knn_scale(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean distance to the k nearest neighbours (3DGS's initial isotropic scale)."""
    if len(points) <= k:
        return np.full(len(points), 0.01)
    d, _ = cKDTree(points).query(points, k=k + 1)
    return np.maximum(d[:, 1:].mean(axis=1), 1e-4)


def knn_graph(means: Float[ArrayLike, "N 3"], alive: Bool[ArrayLike, " N"], k: int = 8
              ) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest live neighbours of every live slot (host-side, scipy KD-tree), with static shapes.

    Returns (indices [N, k] int32, weights [N, k] float32): weight 1 for a real pair of live slots, 0 for
    dead slots and padding (index 0). Used by the isometry regulariser (``fgjax.train.losses``)."""
    pts = np.asarray(means, np.float64)
    live = np.flatnonzero(np.asarray(alive))
    n = len(pts)
    idx = np.zeros((n, k), np.int32)
    w = np.zeros((n, k), np.float32)
    kk = min(k, len(live) - 1)
    if kk >= 1:
        _, nb = cKDTree(pts[live]).query(pts[live], k=kk + 1)
        idx[live, :kk] = live[nb[:, 1:]]
        w[live, :kk] = 1.0
    return idx, w


def init_from_points(
    points: Float[ArrayLike, "M 3"],
    colors: Float[ArrayLike, "M 3"] | None = None,
    *,
    capacity: int | None = None,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    scale_factor: float = 1.0,
    dtype=jnp.float32,
) -> tuple[Gaussians, Bool[Array, " N"]]:
    """Gaussians at `points` (3DGS init): isotropic scale = mean distance to 3 neighbours, identity rotation.

    Args:
        points: [M, 3] centres (scene units).
        colors: [M, 3] RGB in [0, 1] (default grey).
        capacity: N >= M slots; slots M..N-1 are dead (alive False) copies of zero Gaussians.
        sh_degree: highest SH degree stored (0..3).
        init_opacity: activated initial opacity.
        scale_factor: multiplies the neighbour-distance scale.

    Returns:
        (Gaussians with N rows, alive mask [N]).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"init_from_points: points must be [M, 3] with M >= 1; got {pts.shape}")
    m = len(pts)
    n = m if capacity is None else int(capacity)
    if n < m:
        raise ValueError(f"init_from_points: capacity {n} < number of points {m}")
    cols = np.full((m, 3), 0.5) if colors is None else np.asarray(colors, dtype=np.float64)
    k = num_sh_coeffs(sh_degree)
    means = np.zeros((n, 3))
    means[:m] = pts
    log_scales = np.full((n, 3), np.log(1e-3))
    log_scales[:m] = np.log(_knn_scale(pts) * scale_factor)[:, None]
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    p = float(np.clip(init_opacity, 1e-4, 1 - 1e-4))
    logits = np.full((n,), np.log(p / (1 - p)))
    sh = np.zeros((n, k, 3))
    sh[:m, 0] = (cols - 0.5) / SH_C0
    alive = np.zeros((n,), bool)
    alive[:m] = True
    g = Gaussians(*(jnp.asarray(x, dtype) for x in (means, log_scales, quats, logits, sh)))
    return g, jnp.asarray(alive)


def init_random(
    key: jax.Array,
    num: int,
    lo: Float[ArrayLike, 3],
    hi: Float[ArrayLike, 3],
    *,
    capacity: int | None = None,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    dtype=jnp.float32,
) -> tuple[Gaussians, Bool[Array, " N"]]:
    """`num` Gaussians uniformly in the box [lo, hi] with random colours (no depth, no SfM points)."""
    kp, kc = jax.random.split(key)
    lo_, hi_ = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if lo_.shape != (3,) or hi_.shape != (3,) or np.any(hi_ <= lo_):
        raise ValueError(f"init_random: need lo < hi, each [3]; got lo={lo_}, hi={hi_}")
    u = np.asarray(jax.random.uniform(kp, (int(num), 3), dtype=jnp.float32), np.float64)
    pts = lo_ + u * (hi_ - lo_)
    cols = np.asarray(jax.random.uniform(kc, (int(num), 3), dtype=jnp.float32), np.float64)
    return init_from_points(pts, cols, capacity=capacity, sh_degree=sh_degree, init_opacity=init_opacity, dtype=dtype)
