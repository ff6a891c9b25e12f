"""Adaptive density control (3DGS) over fixed-capacity arrays with an alive mask, in optax shape.

``densify_init`` -> ``DensifyState``; ``densify_accumulate`` adds each step's screen-space gradient norms
(NDC units, as 3DGS: pixel gradients times W/2, H/2); ``densify_apply`` clones small and splits large
Gaussians whose mean gradient exceeds the threshold into free slots, prunes transparent/huge ones and
resets the accumulators; ``opacity_reset`` clamps opacities to 0.01. All shapes are fixed, so nothing
recompiles as the number of live Gaussians changes. When candidates outnumber free slots, the ones with
the largest gradients win and ``DensifyState.full`` is set (the host loop prints a message).
Adam moments of re-used slots are zeroed (``reset_rows``). ``DensifyState.parent`` says which slot each slot was
copied from, so that per-slot data kept beside the Gaussians follows them (``follow_parents``).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from fgjax.gaussians import Gaussians
from fgjax.geometry import HIGHEST as HI
from fgjax.geometry import quat_to_rotmat

__all__ = ["DensifyState", "densify_init", "densify_accumulate", "densify_apply", "follow_parents", "opacity_reset",
           "reset_rows"]


class DensifyState(eqx.Module):
    alive: Bool[Array, " N"]
    grad_sum: Float[Array, " N"]
    count: Int[Array, " N"]
    full: Bool[Array, ""]  # the last densify_apply ran out of free slots
    parent: Int[Array, " N"]  # the slot each slot's Gaussian was copied from by the last densify_apply (itself if none)


def densify_init(alive: Bool[Array, " N"]) -> DensifyState:
    n = alive.shape[0]
    return DensifyState(jnp.asarray(alive), jnp.zeros((n,), jnp.float32), jnp.zeros((n,), jnp.int32),
                        jnp.zeros((), bool), jnp.arange(n, dtype=jnp.int32))


def follow_parents(tree: dict[str, Any], state: DensifyState) -> dict[str, Any]:
    """``tree`` with its per-slot data (the [N, ...] leaves under its "slots" key: `fgjax.models.deform`'s per-slot
    weights) after `densify_apply`: each slot takes its parent's row, so a clone or split carries its parent's data.
    Idempotent until the next `densify_apply` (a parent is never itself a copy)."""
    if "slots" not in tree:
        return tree
    return {**tree, "slots": jax.tree_util.tree_map(lambda a: a[state.parent], tree["slots"])}


def densify_accumulate(
    state: DensifyState, grad2d: Float[Array, "N 2"], visible: Bool[Array, " N"], width: int, height: int
) -> DensifyState:
    """Add ||dL/d means2d|| (NDC units) for the visible Gaussians."""
    g = grad2d * jnp.array([0.5 * width, 0.5 * height], grad2d.dtype)
    norm = jnp.sqrt(jnp.sum(g * g, axis=-1)).astype(jnp.float32)
    vis = visible & state.alive
    return DensifyState(state.alive, state.grad_sum + jnp.where(vis, norm, 0.0),
                        state.count + vis.astype(jnp.int32), state.full, state.parent)


def _rows_set(x, dst, src_vals):
    return x.at[dst].set(src_vals, mode="drop")


def reset_rows(opt_state: Any, rows_mask: Bool[Array, " N"], n: int, only: tuple[str, ...] | None = None) -> Any:
    """Zero the optimiser-state rows (Adam moments) of the Gaussian parameters where `rows_mask` is set.

    Leaves are recognised by a 'gaussians' or 'slots' (per-slot data beside the Gaussians) dict key on their path
    and a leading dimension N; with `only`, just those fields (e.g. ("opacity_logits",)).
    """

    def fix(path, leaf):
        keys = [getattr(k, "key", getattr(k, "name", None)) for k in path]
        per_row = hasattr(leaf, "shape") and leaf.ndim > 0 and leaf.shape[0] == n
        if not ("gaussians" in keys or "slots" in keys) or not per_row:
            return leaf
        if only is not None and not any(k in only for k in keys):
            return leaf
        m = rows_mask.reshape((n,) + (1,) * (leaf.ndim - 1))
        return jnp.where(m, jnp.zeros_like(leaf), leaf)

    return jax.tree_util.tree_map_with_path(fix, opt_state)


@jax.jit
def densify_apply(
    g: Gaussians,
    opt_state: Any,
    state: DensifyState,
    key: jax.Array,
    *,
    grad_threshold: float,
    clone_max_scale: float,
    prune_opacity: float,
    prune_max_scale: float,
) -> tuple[Gaussians, Any, DensifyState, Int[Array, ""]]:
    """One densify-and-prune step (3DGS, Kerbl et al. 2023, section 5).

    Candidates: alive with mean accumulated gradient >= grad_threshold. Those with max scale <=
    clone_max_scale are cloned (copy into a free slot), the others split (both copies resampled
    inside the parent, scales / 1.6). Then alive Gaussians with opacity < prune_opacity or max scale >
    prune_max_scale are pruned. Returns (g, opt_state, state with zeroed accumulators, live count).
    """
    n = g.means.shape[0]
    alive = state.alive
    avg = state.grad_sum / jnp.maximum(state.count, 1).astype(jnp.float32)
    cand = alive & (avg >= grad_threshold)
    n_cand = jnp.sum(cand)
    n_free = jnp.sum(~alive)
    # k-th strongest candidate -> k-th free slot
    order = jnp.argsort(jnp.where(cand, -avg, jnp.inf))  # candidates first, by gradient
    free = jnp.argsort(alive)  # dead slots first (stable)
    k = jnp.arange(n)
    take = k < jnp.minimum(n_cand, n_free)
    src = order
    dst = jnp.where(take, free, n)  # n = out of bounds -> dropped
    is_src = jnp.zeros((n,), bool).at[jnp.where(take, src, n)].set(True, mode="drop")

    scales = jnp.exp(g.log_scales)
    max_s = jnp.max(scales, axis=-1)
    split = is_src & (max_s > clone_max_scale)  # per source slot
    rot = quat_to_rotmat(g.quats)  # [N, 3, 3]
    k1, k2 = jax.random.split(key)
    off1 = jnp.einsum("nij,nj->ni", rot, scales * jax.random.normal(k1, scales.shape, scales.dtype), precision=HI)
    off2 = jnp.einsum("nij,nj->ni", rot, scales * jax.random.normal(k2, scales.shape, scales.dtype), precision=HI)
    shrink = jnp.log(jnp.asarray(1.6, g.log_scales.dtype))
    # the new copy of each source (split: resampled position, smaller scale)
    new_means = jnp.where(split[:, None], g.means + off2, g.means)
    new_log_scales = jnp.where(split[:, None], g.log_scales - shrink, g.log_scales)
    # the source itself (split: resampled too)
    means = jnp.where(split[:, None], g.means + off1, g.means)
    log_scales = jnp.where(split[:, None], g.log_scales - shrink, g.log_scales)
    means = _rows_set(means, dst, new_means[src])
    log_scales = _rows_set(log_scales, dst, new_log_scales[src])
    quats = _rows_set(g.quats, dst, g.quats[src])
    logits = _rows_set(g.opacity_logits, dst, g.opacity_logits[src])
    sh = _rows_set(g.sh, dst, g.sh[src])
    new_alive = _rows_set(alive, dst, jnp.ones((n,), bool))
    is_new = jnp.zeros((n,), bool).at[dst].set(True, mode="drop")
    parent = _rows_set(jnp.arange(n, dtype=jnp.int32), dst, src.astype(jnp.int32))

    # prune (new Gaussians inherit their parent's opacity; huge ones go)
    opac = jax.nn.sigmoid(logits)
    big = jnp.max(jnp.exp(log_scales), axis=-1) > prune_max_scale
    prune = new_alive & ((opac < prune_opacity) | big)
    new_alive = new_alive & ~prune
    g2 = Gaussians(means, log_scales, quats, logits, sh)
    opt_state = reset_rows(opt_state, is_new | split, n)
    state2 = DensifyState(new_alive, jnp.zeros_like(state.grad_sum), jnp.zeros_like(state.count), n_cand > n_free,
                          parent)
    return g2, opt_state, state2, jnp.sum(new_alive)


@jax.jit
def opacity_reset(g: Gaussians, opt_state: Any, value: float = 0.01) -> tuple[Gaussians, Any]:
    """Clamp opacities to at most `value` (3DGS) and zero the opacity Adam moments."""
    cap = jnp.log(value / (1.0 - value))
    g2 = Gaussians(g.means, g.log_scales, g.quats, jnp.minimum(g.opacity_logits, cap), g.sh)
    n = g.means.shape[0]
    return g2, reset_rows(opt_state, jnp.ones((n,), bool), n, only=("opacity_logits",))
