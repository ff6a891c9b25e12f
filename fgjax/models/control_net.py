"""Control network f_Θ(E(v_c, X)) -> (ΔX, Δq, Δs) of stage 2 (DESIGN.md section 1, steps 7-8).

Each controllable Gaussian i gets the 3D control vector v_c of its cluster k (v_c = ς(t, k) - ς(0, k)
during training, a snapped user vector at run time) and its canonical centre X_i. The network is an
MLP on an encoding E(v_c, X) = [γ(v_c / v_scale), γ(X / x_scale)] (or a hash-grid encoding of X when
available), with a zero-initialised output layer, so that at initialisation every offset is exactly 0
and the scene renders as its canonical Gaussians. A mask sets the offsets of static (uncontrolled)
Gaussians to exactly zero, for any parameters, with zero gradient through them.

γ is the NeRF frequency encoding (Mildenhall et al. 2020, eq. 4), with the input kept:
γ(p) = [p, sin(2^0 π p), cos(2^0 π p), ..., sin(2^(L-1) π p), cos(2^(L-1) π p)].

Everything is a pure function of a parameter pytree (`ControlNet`, an `eqx.Module` whose arrays are
the trainable leaves and whose static fields fix the architecture); jit, vmap and grad apply.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from fgjax.models.encoding import (
    frequency_encoding,
    hash_grid_dim,
    hash_grid_encode,
    hash_grid_init,
    hash_grid_resolutions,
)

__all__ = [
    "ControlNet",
    "frequency_encoding",
    "control_init",
    "control_apply",
    "per_gaussian_vectors",
]

OUT_DIM = 10  # dX (3), dq (4, added to wxyz), ds (3, added to the log-scales)


class ControlNet(eqx.Module):
    """Parameters of the control MLP (final class).

    Attributes:
        weights, biases: per layer, [in, out] and [out]; the last layer maps to 10 outputs and
            is zero-initialised.
        grid: parameters of the hash-grid encoding of X (``encoding="hashgrid"``), else None.
        encoding: ``"frequency"`` or ``"hashgrid"`` (static).
        n_freqs_x, n_freqs_v: frequency bands of X and of v_c (static).
        x_scale, v_scale: X and v_c are divided by these before encoding (static; scene units).
    """

    weights: tuple[Float[Array, "din dout"], ...]
    biases: tuple[Float[Array, " dout"], ...]
    grid: object = None
    encoding: str = eqx.field(static=True, default="frequency")
    n_freqs_x: int = eqx.field(static=True, default=6)
    n_freqs_v: int = eqx.field(static=True, default=4)
    x_scale: float = eqx.field(static=True, default=2.0)
    v_scale: float = eqx.field(static=True, default=1.0)

    def __check_init__(self):
        if len(self.weights) != len(self.biases) or not self.weights:
            raise ValueError(f"ControlNet: {len(self.weights)} weight matrices and {len(self.biases)} biases")
        if self.weights[-1].shape[-1] != OUT_DIM:
            raise ValueError(f"ControlNet: last layer must have {OUT_DIM} outputs, got {self.weights[-1].shape}")
        if self.encoding not in ("frequency", "hashgrid"):
            raise ValueError(f"ControlNet.encoding must be 'frequency' or 'hashgrid', got {self.encoding!r}")


# The control network's hash grid over the canonical centre (Instant-NGP's multiresolution encoding,
# `fgjax.models.encoding`): levels, table size, features per level, coarsest and finest resolution.
HASH_LEVELS, HASH_LOG2_TABLE, HASH_FEATURES, HASH_BASE_RES, HASH_MAX_RES = 8, 14, 2, 8, 256
HASH_RESOLUTIONS = tuple(hash_grid_resolutions(HASH_LEVELS, HASH_BASE_RES, HASH_MAX_RES))


def _encode_x(params: ControlNet, x: Array) -> Array:
    if params.encoding == "hashgrid":  # X / x_scale in [-1, 1] mapped to the grid's [0, 1]
        return hash_grid_encode(params.grid, jnp.clip(x / params.x_scale * 0.5 + 0.5, 0.0, 1.0), HASH_RESOLUTIONS)
    return frequency_encoding(x / params.x_scale, params.n_freqs_x)


def control_init(
    key: jax.Array,
    *,
    encoding: Literal["frequency", "hashgrid"] = "frequency",
    hidden: int = 64,
    depth: int = 3,
    n_freqs_x: int = 6,
    n_freqs_v: int = 4,
    x_scale: float = 2.0,
    v_scale: float = 1.0,
    dtype=jnp.float32,
) -> ControlNet:
    """Initial control-network parameters.

    Hidden layers: He-uniform weights (ReLU), zero biases. Output layer: zeros, so that
    `control_apply` returns exactly zero offsets until trained (the canonical scene).

    Args:
        key: PRNG key.
        encoding: ``"frequency"`` (γ of X, in this file) or ``"hashgrid"`` (the multiresolution hash grid of
            `fgjax.models.encoding` over X, ``HASH_*`` above).
        hidden: width of the hidden layers.
        depth: number of hidden layers (>= 1).
        n_freqs_x, n_freqs_v: frequency bands of γ for X and v_c.
        x_scale, v_scale: divisors of X and v_c before the encoding (scene units: the scene
            half-size and a typical object displacement).
        dtype: parameter dtype.

    Returns:
        A `ControlNet`.
    """
    if depth < 1 or hidden < 1:
        raise ValueError(f"control_init: depth and hidden must be >= 1, got depth={depth}, hidden={hidden}")
    if n_freqs_x < 0 or n_freqs_v < 0:
        raise ValueError(f"control_init: n_freqs must be >= 0, got {n_freqs_x}, {n_freqs_v}")
    if not (x_scale > 0 and v_scale > 0):
        raise ValueError(f"control_init: x_scale and v_scale must be > 0, got {x_scale}, {v_scale}")
    k_grid, key = jax.random.split(key)
    grid = None
    if encoding == "hashgrid":
        grid = hash_grid_init(k_grid, HASH_LEVELS, HASH_LOG2_TABLE, HASH_FEATURES, dtype)
        dx = hash_grid_dim(HASH_LEVELS, HASH_FEATURES)
    elif encoding == "frequency":
        dx = 3 * (1 + 2 * n_freqs_x)
    else:
        raise ValueError(f"control_init: encoding must be 'frequency' or 'hashgrid', got {encoding!r}")
    din = dx + 3 * (1 + 2 * n_freqs_v)
    sizes = [din] + [hidden] * depth
    keys = jax.random.split(key, depth)
    weights, biases = [], []
    for k, (a, b) in zip(keys, zip(sizes[:-1], sizes[1:], strict=True), strict=True):
        lim = jnp.sqrt(6.0 / a)
        weights.append(jax.random.uniform(k, (a, b), dtype, -lim, lim))
        biases.append(jnp.zeros((b,), dtype))
    weights.append(jnp.zeros((hidden, OUT_DIM), dtype))
    biases.append(jnp.zeros((OUT_DIM,), dtype))
    return ControlNet(weights=tuple(weights), biases=tuple(biases), grid=grid, encoding=encoding,
                      n_freqs_x=n_freqs_x, n_freqs_v=n_freqs_v, x_scale=float(x_scale), v_scale=float(v_scale))


def control_apply(
    params: ControlNet,
    v_c: Float[ArrayLike, "N 3"],
    X: Float[ArrayLike, "N 3"],
    mask: Bool[ArrayLike, " N"] | None = None,
) -> tuple[Float[Array, "N 3"], Float[Array, "N 4"], Float[Array, "N 3"]]:
    """Offsets (ΔX, Δq, Δs) = f_Θ(E(v_c, X)) of each Gaussian (DESIGN.md section 1, step 7).

    Per Gaussian i: h = MLP([γ(v_c,i / v_scale), E(X_i)]); ΔX = h[0:3], Δq = h[3:7] (added to the
    wxyz quaternion), Δs = h[7:10] (added to the log-scales). Rows where `mask` is False get exactly
    zero (``jnp.where``, so no gradient flows from them either). Row i depends only on (v_c,i, X_i):
    a cluster's Gaussians move with their own cluster's vector only.

    Args:
        params: `ControlNet`.
        v_c: [N, 3] the control vector of each Gaussian's cluster (zeros for static Gaussians;
            see `per_gaussian_vectors`).
        X: [N, 3] canonical centres.
        mask: [N] bool, True for Gaussians of a controllable cluster; None = all.

    Returns:
        dX [N, 3], dq [N, 4], ds [N, 3].
    """
    v_c, X = jnp.asarray(v_c), jnp.asarray(X)
    if X.ndim != 2 or X.shape[-1] != 3:
        raise ValueError(f"control_apply: X must have shape [N, 3], got {list(X.shape)}")
    if v_c.shape != X.shape:
        raise ValueError(f"control_apply: v_c must have shape {list(X.shape)} like X, got {list(v_c.shape)}")
    dtype = params.weights[0].dtype
    v_c, X = v_c.astype(dtype), X.astype(dtype)
    h = jnp.concatenate([frequency_encoding(v_c / params.v_scale, params.n_freqs_v), _encode_x(params, X)],
                        axis=-1)  # [N, din]
    for w, b in zip(params.weights[:-1], params.biases[:-1], strict=True):
        h = jax.nn.relu(h @ w + b)
    out = h @ params.weights[-1] + params.biases[-1]  # [N, 10]
    if mask is not None:
        mask = jnp.asarray(mask)
        if mask.shape != X.shape[:1]:
            raise ValueError(f"control_apply: mask must have shape [N]=[{X.shape[0]}], got {list(mask.shape)}")
        out = jnp.where(mask.astype(bool)[:, None], out, 0.0)
    return out[:, :3], out[:, 3:7], out[:, 7:10]


def per_gaussian_vectors(
    cluster_vectors: Float[ArrayLike, "K 3"], labels: Int[ArrayLike, " N"]
) -> tuple[Float[Array, "N 3"], Bool[Array, " N"]]:
    """Scatter per-cluster control vectors to Gaussians: (v_c [N, 3], mask [N]).

    Args:
        cluster_vectors: [K, 3] one vector per cluster (v_c = ς(t, k) - ς(0, k)).
        labels: [N] cluster of each Gaussian, -1 = static / noise (gets zeros and mask False).

    Returns:
        v_c [N, 3] and the mask [N] of controlled Gaussians, for `control_apply`.
    """
    vec = jnp.asarray(cluster_vectors)
    lab = jnp.asarray(labels)
    if vec.ndim != 2 or vec.shape[-1] != 3:
        raise ValueError(f"per_gaussian_vectors: cluster_vectors must have shape [K, 3], got {list(vec.shape)}")
    if lab.ndim != 1:
        raise ValueError(f"per_gaussian_vectors: labels must have shape [N], got {list(lab.shape)}")
    mask = (lab >= 0) & (lab < vec.shape[0])
    if vec.shape[0] == 0:
        return jnp.zeros((lab.shape[0], 3), vec.dtype), mask
    v = vec[jnp.clip(lab, 0, vec.shape[0] - 1)]
    return jnp.where(mask[:, None], v, 0.0), mask
