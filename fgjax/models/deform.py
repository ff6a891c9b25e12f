"""Deformation field f(params, X, t) -> (dX, dq, ds): canonical Gaussians to time t.

Two encodings (DESIGN.md section 1, step 1):

- ``"frequency"``: Deformable-3DGS (Yang et al. 2024): gamma(X) with 10 frequencies, gamma(t) with 6,
  an MLP of depth 8 and width 256 with a skip connection (input re-concatenated) after layer 4, and
  three linear heads.
- ``"hash"``: a 3D multiresolution hash grid on X (normalised by the scene box) plus gamma(t), into a
  small MLP (2 x 64 by default): the fast option on CPU.

The heads are initialised to zero, so the field starts at the identity (dX = 0, dq = 0, ds = 0).
dX is added to the means, dq to the raw (unnormalised) quaternions, ds to the log-scales.
Parameters are a plain pytree (dict of arrays); the spec is a frozen, hashable dataclass (static under jit).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from fgjax.models.encoding import (
    frequency_dim,
    frequency_encoding,
    hash_grid_dim,
    hash_grid_encode,
    hash_grid_init,
    hash_grid_resolutions,
)

__all__ = ["DeformSpec", "deform_init", "deform_apply", "deform_num_params"]


@dataclasses.dataclass(frozen=True)
class DeformSpec:
    """Static description of a deformation field (hashable: usable as a jit static argument)."""

    kind: str = "frequency"
    """"frequency" (Deformable-3DGS MLP) or "hash" (hash grid + small MLP)."""
    depth: int = 8
    """Hidden layers of the MLP."""
    width: int = 256
    """Hidden width of the MLP."""
    x_freqs: int = 10
    """Frequencies of gamma(X) ("frequency" kind; "hash" uses x_freqs_hash)."""
    t_freqs: int = 6
    """Frequencies of gamma(t)."""
    skip: int = 4
    """Re-concatenate the input after this hidden layer (<= 0: none)."""
    hash_levels: int = 8
    hash_log2_table: int = 14
    hash_features: int = 2
    hash_base_res: int = 8
    hash_max_res: int = 256
    x_freqs_hash: int = 2
    """Low frequencies of gamma(X) added next to the hash features."""
    aabb: tuple[float, ...] = (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0)
    """Scene box (lo xyz, hi xyz) that the hash grid covers."""
    anchor: float | None = None
    """A time t_a at which the field is the identity: f(X, t) = g(X, t) - g(X, t_a) with g the network, so the
    canonical Gaussians are the scene at t_a (None: f = g, a canonical space of the network's choosing)."""

    def __post_init__(self):
        if self.kind not in ("frequency", "hash"):
            raise ValueError(f"DeformSpec.kind must be 'frequency' or 'hash'; got {self.kind!r}")
        if self.depth < 1 or self.width < 1:
            raise ValueError(f"DeformSpec.depth and width must be >= 1; got {self.depth}, {self.width}")
        if len(self.aabb) != 6 or any(self.aabb[i + 3] <= self.aabb[i] for i in range(3)):
            raise ValueError(f"DeformSpec.aabb must be (lo x, y, z, hi x, y, z) with lo < hi; got {self.aabb}")
        object.__setattr__(self, "aabb", tuple(float(a) for a in self.aabb))
        if self.anchor is not None:
            object.__setattr__(self, "anchor", float(self.anchor))

    @property
    def resolutions(self) -> tuple[int, ...]:
        return tuple(hash_grid_resolutions(self.hash_levels, self.hash_base_res, self.hash_max_res))

    @property
    def in_dim(self) -> int:
        t_dim = frequency_dim(1, self.t_freqs)
        if self.kind == "frequency":
            return frequency_dim(3, self.x_freqs) + t_dim
        return hash_grid_dim(self.hash_levels, self.hash_features) + frequency_dim(3, self.x_freqs_hash) + t_dim


def _dense_init(key, fan_in, fan_out, dtype, zero=False):
    if zero:
        return {"w": jnp.zeros((fan_in, fan_out), dtype), "b": jnp.zeros((fan_out,), dtype)}
    lim = (6.0 / (fan_in + fan_out)) ** 0.5  # Glorot uniform
    return {"w": jax.random.uniform(key, (fan_in, fan_out), dtype, -lim, lim), "b": jnp.zeros((fan_out,), dtype)}


def deform_init(key: jax.Array, spec: DeformSpec, dtype=jnp.float32) -> dict[str, Any]:
    """Parameters of the field; the output heads are zero, so the field starts at the identity."""
    keys = jax.random.split(key, spec.depth + 2)
    layers = []
    fan_in = spec.in_dim
    for i in range(spec.depth):
        if spec.skip > 0 and i == spec.skip:
            fan_in += spec.in_dim
        layers.append(_dense_init(keys[i], fan_in, spec.width, dtype))
        fan_in = spec.width
    params: dict[str, Any] = {"layers": layers, "head": _dense_init(keys[-2], spec.width, 10, dtype, zero=True)}
    if spec.kind == "hash":
        params["grid"] = hash_grid_init(keys[-1], spec.hash_levels, spec.hash_log2_table, spec.hash_features, dtype)
    return params


def deform_num_params(params) -> int:
    return int(sum(x.size for x in jax.tree_util.tree_leaves(params)))


def _encode(spec: DeformSpec, params, x, t):
    n = x.shape[0]
    t = jnp.broadcast_to(jnp.asarray(t, x.dtype).reshape(-1, 1), (n, 1))
    t_enc = frequency_encoding(t, spec.t_freqs)
    if spec.kind == "frequency":
        return jnp.concatenate([frequency_encoding(x, spec.x_freqs), t_enc], axis=-1)
    lo = jnp.asarray(spec.aabb[:3], x.dtype)
    hi = jnp.asarray(spec.aabb[3:], x.dtype)
    u = (x - lo) / (hi - lo)  # [N, 3] in [0, 1] inside the box
    h = hash_grid_encode(params["grid"], u, spec.resolutions)
    return jnp.concatenate([h, frequency_encoding(2.0 * u - 1.0, spec.x_freqs_hash), t_enc], axis=-1)


def deform_apply(
    spec: DeformSpec, params, x: Float[ArrayLike, "N 3"], t: Float[ArrayLike, ""] | Float[ArrayLike, " N"]
) -> tuple[Float[Array, "N 3"], Float[Array, "N 4"], Float[Array, "N 3"]]:
    """(dX, dq, ds) at canonical centres `x` [N, 3] and time `t` (scalar or [N]).

    Add dX to the means, dq to the raw quaternions and ds to the log-scales. With ``spec.anchor`` = t_a the
    network's output at t_a is subtracted (one more evaluation), so the field is exactly zero at t_a. X is not
    detached (Deformable-3DGS detaches it only through the canonical optimiser step, which we do too by giving both
    the same gradient).
    """
    x = jnp.asarray(x)
    out = _network(spec, params, x, t)  # [N, 10]
    if spec.anchor is not None:  # zero at the anchor time: the canonical space is the scene then
        out = out - _network(spec, params, x, spec.anchor)
    return out[:, :3], out[:, 3:7], out[:, 7:10]


def _network(spec: DeformSpec, params, x, t):
    inp = _encode(spec, params, x, t)  # [N, E]
    h = inp
    for i, layer in enumerate(params["layers"]):
        if spec.skip > 0 and i == spec.skip:
            h = jnp.concatenate([h, inp], axis=-1)
        h = jax.nn.relu(h @ layer["w"] + layer["b"])
    return h @ params["head"]["w"] + params["head"]["b"]
