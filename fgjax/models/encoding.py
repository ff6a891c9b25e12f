"""Input encodings for coordinate networks: frequency (NeRF positional) and multiresolution hash grid.

Pure functions over parameter pytrees; hyperparameters are static Python values.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = ["frequency_encoding", "frequency_dim", "hash_grid_init", "hash_grid_encode", "hash_grid_dim",
           "hash_grid_resolutions"]

# Instant-NGP primes (the first is 1 so that dimension 0 stays coherent in memory).
_PRIMES = (1, 2654435761, 805459861, 3674653429)


def frequency_dim(d: int, num_freqs: int, include_input: bool = True) -> int:
    """Output width of `frequency_encoding` for d inputs."""
    return d * (2 * num_freqs + int(include_input))


def frequency_encoding(
    x: Float[ArrayLike, "... D"], num_freqs: int, include_input: bool = True
) -> Float[Array, "... E"]:
    """gamma(x) = [x, sin(2^k pi x), cos(2^k pi x)]_{k<L} (NeRF eq. 4; Deformable-3DGS uses it for X and t).

    Args:
        x: [..., D] inputs.
        num_freqs: L (static).
        include_input: prepend x itself.

    Returns:
        [..., D (2 L + include_input)], ordered [x, sin(f0 x), cos(f0 x), sin(f1 x), ...] per frequency.
    """
    x = jnp.asarray(x)
    freqs = (2.0 ** jnp.arange(num_freqs, dtype=x.dtype)) * math.pi  # [L]
    xf = x[..., None, :] * freqs[:, None]  # [..., L, D]
    enc = jnp.concatenate([jnp.sin(xf), jnp.cos(xf)], axis=-1).reshape(*x.shape[:-1], -1)
    return jnp.concatenate([x, enc], axis=-1) if include_input else enc


def hash_grid_resolutions(num_levels: int, base_res: int, max_res: int) -> list[int]:
    """Per-level grid resolutions N_l = floor(N_min b^l), b = exp((ln N_max - ln N_min) / (L - 1))."""
    if num_levels == 1:
        return [int(base_res)]
    b = math.exp((math.log(max_res) - math.log(base_res)) / (num_levels - 1))
    return [int(math.floor(base_res * b**level)) for level in range(num_levels)]


def hash_grid_dim(num_levels: int, features: int) -> int:
    return num_levels * features


def hash_grid_init(key: jax.Array, num_levels: int, log2_table: int, features: int,
                   dtype=jnp.float32) -> Float[Array, "L T F"]:
    """Hash tables [L, 2^log2_table, F], uniform in [-1e-4, 1e-4] (Instant-NGP init)."""
    return jax.random.uniform(key, (num_levels, 2**log2_table, features), dtype, -1e-4, 1e-4)


def _corner_offsets(d: int) -> np.ndarray:
    return np.array([[(c >> k) & 1 for k in range(d)] for c in range(2**d)], np.uint32)  # [2^D, D]


def hash_grid_encode(
    tables: Float[Array, "L T F"],
    x: Float[ArrayLike, "N D"],
    resolutions: tuple[int, ...],
) -> Float[Array, "N LF"]:
    """Multiresolution hash encoding (Instant-NGP, Muller et al. 2022, eq. 3-4), d-linear interpolation.

    Levels whose dense grid fits the table ((N_l + 1)^D <= T) index it densely; finer ones hash with
    xor of coordinate-prime products mod T. Inputs are expected in [0, 1]^D (clipped).

    Args:
        tables: [L, T, F] parameters.
        x: [N, D] points in [0, 1]^D, D <= 4.
        resolutions: L static grid resolutions.

    Returns:
        [N, L F] features.
    """
    x = jnp.clip(jnp.asarray(x, tables.dtype), 0.0, 1.0)
    n, d = x.shape
    n_levels, t_size, _ = tables.shape
    if len(resolutions) != n_levels:
        raise ValueError(f"hash_grid_encode: {len(resolutions)} resolutions for {n_levels} levels")
    if d > 4:
        raise ValueError(f"hash_grid_encode: at most 4 input dimensions; got {d}")
    corners = jnp.asarray(_corner_offsets(d))  # [C, D]
    feats = []
    for level, res in enumerate(resolutions):
        pos = x * res  # [N, D]
        base = jnp.floor(pos)
        frac = pos - base  # [N, D]
        base = jnp.clip(base.astype(jnp.uint32), 0, res - 1)
        idx = base[:, None, :] + corners[None]  # [N, C, D]
        w = jnp.prod(jnp.where(corners[None].astype(bool), frac[:, None, :], 1.0 - frac[:, None, :]), axis=-1)  # [N, C]
        if (res + 1) ** d <= t_size:
            strides = np.array([(res + 1) ** k for k in range(d)], np.uint32)
            h = jnp.sum(idx * strides, axis=-1)
        else:
            h = idx[..., 0] * np.uint32(_PRIMES[0])
            for k in range(1, d):
                h = h ^ (idx[..., k] * np.uint32(_PRIMES[k]))
        h = (h % np.uint32(t_size)).astype(jnp.int32)  # [N, C]
        f = tables[level][h]  # [N, C, F]
        feats.append(jnp.sum(w[..., None] * f, axis=1))
    return jnp.concatenate(feats, axis=-1)
