"""Deformation field f(params, X, t) -> (dX, dq, ds): canonical Gaussians to time t.

Three kinds (DESIGN.md section 1, step 1):

- ``"frequency"``: Deformable-3DGS (Yang et al. 2024): gamma(X) with 10 frequencies, gamma(t) with 6,
  an MLP of depth 8 and width 256 with a skip connection (input re-concatenated) after layer 4, and
  three linear heads.
- ``"hash"``: a 3D multiresolution hash grid on X (normalised by the scene box) plus gamma(t), into a
  small MLP (2 x 64 by default): the fast option on CPU.
- ``"bases"``: a few rigid motions shared by the scene, blended per point (the motion bases of Shape of Motion,
  Wang et al. 2024, with weights read from position instead of stored per Gaussian): basis 0 is the identity
  (the static scene) and basis k >= 1 is a rotation R_k(t) = exp(omega_k(t)) about a learned pivot c_k plus a
  translation tau_k(t), both linear between ``knots`` evenly spaced control times on [0, 1]. The weights
  w(X) = softmax(logits(X)) come from the hash-grid MLP of X (no time input), and
  dX = sum_k w_k(X) [R_k(t) (X - c_k) + c_k + tau_k(t) - X]. A part is then a region whose weight sits on one
  basis, and its motion is that basis's few parameters, which every point of the part informs. Given the
  Gaussians' raw quaternions q, each turns with the blend r = normalise(w_0 (1, 0, 0, 0) + sum_k w_k r_k(t)) of
  the bases' unit quaternions (wxyz, each on the hemisphere w >= 0): dq = r q - q, exact for a point on one basis;
  without q, dq = 0. ds = 0. With an anchor t_a each basis's control values are taken relative to t_a
  (omega_k(t) - omega_k(t_a), tau_k(t) - tau_k(t_a)), so the field is the identity at t_a and stays rigid.
  With ``joint = "screw"`` each moving basis is one joint for the whole clip instead (the screw motions of
  articulated objects; the official FreeGaussian code predicts a screw axis per Gaussian): a unit axis a_k and a
  pivot c_k shared by all times, and per control time an angle theta_k(t) about the line through c_k along a_k and a
  translation h_k(t) along it, R_k(t) = exp(theta_k(t) a_k), tau_k(t) = h_k(t) a_k. A hinge or a spinning part is
  h = 0, a slide theta = 0; what one camera sees of a time's motion along its viewing ray then comes from the other
  times' cameras through the shared axis. The axes start as random unit vectors.
  With ``weights = "slot"`` the logits are stored per Gaussian slot instead (Shape of Motion's per-Gaussian
  weights): ``params["slots"] = {"logits": [N, K], "free": [N]}``, and a slot whose ``free`` is 0 sits on the
  static basis exactly (w = (1, 0, ..., 0); no gradient reaches its logits), so the weights of the Gaussians
  labelled static are held while each moving Gaussian's weights are its own, coupled to no other's through a
  shared network. The field is then evaluated at the N slots' centres, in slot order.

The heads of the first two kinds are initialised to zero, so the field starts at the identity (dX = 0, dq = 0,
ds = 0); the bases start at the identity (omega = tau = 0) with random logits (symmetry breaking).
dX is added to the means, dq to the raw (unnormalised) quaternions, ds to the log-scales.
Parameters are a plain pytree (dict of arrays); the spec is a frozen, hashable dataclass (static under jit).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from fgjax.geometry import quat_multiply, safe_norm, so3_exp
from fgjax.models.encoding import (
    frequency_dim,
    frequency_encoding,
    hash_grid_dim,
    hash_grid_encode,
    hash_grid_init,
    hash_grid_resolutions,
)

__all__ = ["MOTION_KEYS", "DeformSpec", "basis_logits", "basis_motions", "basis_weights", "deform_init", "deform_apply",
           "deform_num_params"]


@dataclasses.dataclass(frozen=True)
class DeformSpec:
    """Static description of a deformation field (hashable: usable as a jit static argument)."""

    kind: str = "frequency"
    """"frequency" (Deformable-3DGS MLP), "hash" (hash grid + small MLP) or "bases" (blended rigid motions)."""
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
    bases: int = 6
    """"bases" kind: rigid motions including the static one (>= 2)."""
    knots: int = 16
    """"bases" kind: control times of each motion over t in [0, 1] (>= 2)."""
    joint: str = "free"
    """"bases" kind: each moving basis's motion: "free" (a rotation vector and a translation per control time) or
    "screw" (one axis and pivot for the clip, an angle about it and a translation along it per control time)."""
    weights: str = "field"
    """"bases" kind: where the weights' logits come from: "field" (the hash-grid MLP of X) or "slot" (stored per
    Gaussian slot, with a held static set; module docstring)."""
    anchor: float | None = None
    """A time t_a at which the field is the identity, so the canonical Gaussians are the scene at t_a (None: a
    canonical space of the network's choosing): f(X, t) = g(X, t) - g(X, t_a) with g the network, or, for the
    "bases" kind, control values taken relative to t_a (module docstring)."""

    def __post_init__(self):
        if self.kind not in ("frequency", "hash", "bases"):
            raise ValueError(f"DeformSpec.kind must be 'frequency', 'hash' or 'bases'; got {self.kind!r}")
        if self.weights not in ("field", "slot") or (self.weights == "slot" and self.kind != "bases"):
            raise ValueError(f"DeformSpec.weights must be 'field' or, with kind 'bases', 'slot'; got {self.weights!r}")
        if self.joint not in ("free", "screw") or (self.joint == "screw" and self.kind != "bases"):
            raise ValueError(f"DeformSpec.joint must be 'free' or, with kind 'bases', 'screw'; got {self.joint!r}")
        if self.bases < 2 or self.knots < 2:
            raise ValueError(f"DeformSpec.bases and knots must be >= 2; got {self.bases}, {self.knots}")
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
        t_dim = 0 if self.kind == "bases" else frequency_dim(1, self.t_freqs)
        if self.kind == "frequency":
            return frequency_dim(3, self.x_freqs) + t_dim
        return hash_grid_dim(self.hash_levels, self.hash_features) + frequency_dim(3, self.x_freqs_hash) + t_dim


def _dense_init(key, fan_in, fan_out, dtype, zero=False):
    if zero:
        return {"w": jnp.zeros((fan_in, fan_out), dtype), "b": jnp.zeros((fan_out,), dtype)}
    lim = (6.0 / (fan_in + fan_out)) ** 0.5  # Glorot uniform
    return {"w": jax.random.uniform(key, (fan_in, fan_out), dtype, -lim, lim), "b": jnp.zeros((fan_out,), dtype)}


def deform_init(key: jax.Array, spec: DeformSpec, dtype=jnp.float32, slots: int = 0) -> dict[str, Any]:
    """Parameters of the field; the output heads are zero, so the field starts at the identity. With
    ``spec.weights = "slot"``, ``slots`` is the number N of Gaussian slots: their logits start at zero and every
    slot is held on the static basis (``free`` 0) until something places them (`fgjax.method.bases_init`)."""
    axis_key = jax.random.fold_in(key, 1)  # the screw axes' own stream: the other parameters' draws stay as they are
    if spec.weights == "slot":
        if slots < 1:
            raise ValueError("deform_init: DeformSpec.weights = 'slot' needs the number of Gaussian slots (slots >= 1)")
        return {**_motion_init(axis_key, spec, dtype),
                "slots": {"logits": jnp.zeros((slots, spec.bases), dtype), "free": jnp.zeros((slots,), dtype)}}
    keys = jax.random.split(key, spec.depth + 2)
    layers = []
    fan_in = spec.in_dim
    for i in range(spec.depth):
        if spec.skip > 0 and i == spec.skip:
            fan_in += spec.in_dim
        layers.append(_dense_init(keys[i], fan_in, spec.width, dtype))
        fan_in = spec.width
    if spec.kind == "bases":  # random logits break the symmetry between the (identical) moving bases
        head = _dense_init(keys[-2], spec.width, spec.bases, dtype)
        params: dict[str, Any] = {"layers": layers, "head": head, **_motion_init(axis_key, spec, dtype)}
    else:
        params = {"layers": layers, "head": _dense_init(keys[-2], spec.width, 10, dtype, zero=True)}
    if spec.kind in ("hash", "bases"):
        params["grid"] = hash_grid_init(keys[-1], spec.hash_levels, spec.hash_log2_table, spec.hash_features, dtype)
    return params


MOTION_KEYS = ("motion", "pivot", "axis")
"""The "bases" kind's parameters of the bases' motions (the rest are their weights' network or slots)."""


def _motion_init(key, spec: DeformSpec, dtype) -> dict[str, Array]:
    """The bases' motions at the identity: control values [K-1, knots, 6] ("free": rotation vector, translation) or
    [K-1, knots, 2] ("screw": angle, translation along the axis, with random unit axes [K-1, 3]); pivots [K-1, 3]."""
    k = spec.bases - 1
    out = {"motion": jnp.zeros((k, spec.knots, 6 if spec.joint == "free" else 2), dtype),
           "pivot": jnp.zeros((k, 3), dtype)}
    if spec.joint == "screw":
        a = jax.random.normal(key, (k, 3), dtype)
        out["axis"] = a / jnp.linalg.norm(a, axis=-1, keepdims=True)
    return out


def deform_num_params(params) -> int:
    return int(sum(x.size for x in jax.tree_util.tree_leaves(params)))


def _encode(spec: DeformSpec, params, x, t):
    n = x.shape[0]
    if spec.kind == "bases":
        t_enc = jnp.zeros((n, 0), x.dtype)
    else:
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
    spec: DeformSpec, params, x: Float[ArrayLike, "N 3"], t: Float[ArrayLike, ""] | Float[ArrayLike, " N"],
    quats: Float[ArrayLike, "N 4"] | None = None,
) -> tuple[Float[Array, "N 3"], Float[Array, "N 4"], Float[Array, "N 3"]]:
    """(dX, dq, ds) at canonical centres `x` [N, 3] and time `t` (scalar or [N]); ``quats`` [N, 4], the raw
    canonical quaternions, are read by the "bases" kind only (its dq turns them; module docstring).

    Add dX to the means, dq to the raw quaternions and ds to the log-scales. With ``spec.anchor`` = t_a the
    network's output at t_a is subtracted (one more evaluation; the "bases" kind shifts its control values
    instead), so the field is exactly zero at t_a. X is not
    detached (Deformable-3DGS detaches it only through the canonical optimiser step, which we do too by giving both
    the same gradient).
    """
    x = jnp.asarray(x)
    if spec.kind == "bases":  # the anchor is inside the bases' control values
        return _bases_apply(spec, params, x, t, quats)
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


def basis_logits(spec: DeformSpec, params, x: Float[ArrayLike, "N 3"]) -> Float[Array, "N K"]:
    """The "bases" kind's weight logits at canonical centres ``x``: w(X) = softmax(logits(X)) over the K bases."""
    return _network(spec, params, jnp.asarray(x), 0.0)


def basis_weights(spec: DeformSpec, params, x: Float[ArrayLike, "N 3"]) -> Float[Array, "N K"]:
    """The "bases" kind's weights w [N, K] at canonical centres ``x``: softmax of `basis_logits` ("field"), or of
    each slot's stored logits where the slot is free and (1, 0, ..., 0) where it is held ("slot"; ``x`` must then be
    the N slots' centres)."""
    x = jnp.asarray(x)
    if spec.weights == "field":
        return jax.nn.softmax(basis_logits(spec, params, x), axis=-1)
    slots = params["slots"]
    if x.shape[0] != slots["logits"].shape[0]:
        raise ValueError(f"the per-slot weights cover {slots['logits'].shape[0]} Gaussian slots; the field was "
                         f"evaluated at {x.shape[0]} points (it needs the slots' centres, in slot order)")
    free = jax.lax.stop_gradient(slots["free"])[:, None] > 0.5
    static = jnp.zeros_like(slots["logits"]).at[:, 0].set(1.0)
    return jnp.where(free, jax.nn.softmax(slots["logits"], axis=-1), static)


def _bases_apply(spec: DeformSpec, params, x, t, quats):
    weights = basis_weights(spec, params, x)  # [N, K]
    t = jnp.asarray(t, x.dtype)
    if t.ndim == 0:
        rot, off, rq = basis_motions(spec, params, t)
        disp = jnp.einsum("kij,nj->nki", rot, x) + off[None] - x[:, None]  # [N, K-1, 3]
        rq = jnp.broadcast_to(rq, (x.shape[0], *rq.shape))
    else:
        rot, off, rq = jax.vmap(lambda ti: basis_motions(spec, params, ti))(t)  # [N, K-1, ...]
        disp = jnp.einsum("nkij,nj->nki", rot, x) + off - x[:, None]
    dx = jnp.einsum("nk,nkd->nd", weights[:, 1:], disp)
    dq = jnp.zeros((x.shape[0], 4), x.dtype)
    if quats is not None:
        ident = jnp.asarray([1.0, 0.0, 0.0, 0.0], x.dtype)
        r = weights[:, :1] * ident + jnp.einsum("nk,nkd->nd", weights[:, 1:], rq)
        r = r / jnp.maximum(jnp.linalg.norm(r, axis=-1, keepdims=True), 1e-12)  # |r| >= r_w >= w_0 > 0
        q = jnp.asarray(quats, x.dtype)
        dq = quat_multiply(r, q) - q
    return dx, dq, jnp.zeros((x.shape[0], 3), x.dtype)


def basis_motions(
    spec: DeformSpec, params, t
) -> tuple[Float[Array, "K 3 3"], Float[Array, "K 3"], Float[Array, "K 4"]]:
    """The moving bases at a time t (scalar): rotations R_k(t) [K-1, 3, 3], offsets
    b_k(t) = c_k + tau_k(t) - R_k(t) c_k [K-1, 3] (basis k maps X to R_k(t) X + b_k(t)) and unit quaternions r_k(t)
    [K-1, 4] (wxyz, w >= 0) of R_k(t).
    Control values (``joint = "free"``: omega_k, tau_k; ``"screw"``: theta_k, h_k, with omega_k = theta_k a_k and
    tau_k = h_k a_k for the unit axis a_k) are linear between the knots (t clipped to [0, 1]) and relative to
    ``spec.anchor`` if set."""
    m = _knot_values(spec, params["motion"], t)  # [K-1, 6] or [K-1, 2]
    if spec.anchor is not None:
        m = m - _knot_values(spec, params["motion"], spec.anchor)
    if spec.joint == "screw":  # one axis for all times: theta a, h a
        a = params["axis"]
        a = a / jnp.maximum(safe_norm(a), 1e-12)[:, None]
        omega, tau = m[:, :1] * a, m[:, 1:] * a
    else:
        omega, tau = m[:, :3], m[:, 3:]
    rot = so3_exp(omega)
    c = params["pivot"]
    theta = safe_norm(omega)[:, None]  # zero derivative at omega = 0, where the quaternion's is zero too
    # (cos(theta / 2), sin(theta / 2) omega / theta); jnp.sinc(x) = sin(pi x) / (pi x), smooth at 0
    rq = jnp.concatenate([jnp.cos(0.5 * theta), 0.5 * jnp.sinc(theta / (2.0 * jnp.pi)) * omega], axis=-1)
    rq = rq * jnp.where(rq[:, :1] < 0, -1.0, 1.0)  # the w >= 0 hemisphere (|theta| > pi)
    return rot, c + tau - jnp.einsum("kij,kj->ki", rot, c), rq


def _knot_values(spec: DeformSpec, motion, t):
    s = jnp.clip(jnp.asarray(t, motion.dtype), 0.0, 1.0) * (spec.knots - 1)
    i0 = jnp.clip(jnp.floor(s).astype(jnp.int32), 0, spec.knots - 2)
    f = s - i0
    return (1.0 - f) * motion[:, i0] + f * motion[:, i0 + 1]


