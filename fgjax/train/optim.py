"""optax optimiser for stage 1: per-group Adam learning rates with exponential decay, SH and warm-up schedules.

Trainable parameters are one pytree ``{"gaussians": Gaussians, "deform": {...}, "pose": [T, 6]?}``.
Groups (3DGS / Deformable-3DGS defaults): means 1.6e-4 -> 1.6e-6 times the scene extent, deformation
1.6e-4 -> 1.6e-5 (hash tables and per-slot weights x `hash_factor`: the weights' rate), opacity 0.05, scales 5e-3,
rotations 1e-3, SH DC 2.5e-3 and higher orders 2.5e-3 / 20, pose deltas 1e-4 -> 1e-6. Adam eps = 1e-15 as in 3DGS.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import optax

__all__ = ["OptimSpec", "make_optimizer", "param_labels", "exp_decay", "active_sh_degree", "guarded_update",
           "guarded_step"]


@dataclasses.dataclass(frozen=True)
class OptimSpec:
    steps: int
    scene_extent: float = 1.0
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_deform: float = 1.6e-4
    lr_deform_final: float = 1.6e-5
    lr_hash_factor: float = 10.0
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_sh: float = 2.5e-3
    lr_pose: float = 1e-4
    lr_pose_final: float = 1e-6
    warmup_steps: int = 0


def exp_decay(lr0: float, lr1: float, steps: int, delay: int = 0) -> optax.Schedule:
    """lr0 until step `delay`, then log-linear to lr1 at step `steps` (counted from 0, delay included), lr1 after."""
    steps = max(int(steps), 1)

    def sched(count):
        u = jnp.clip((count - delay) / max(steps - delay, 1), 0.0, 1.0)
        return jnp.exp((1 - u) * jnp.log(lr0) + u * jnp.log(lr1))

    return sched


def param_labels(params: dict[str, Any]) -> dict[str, Any]:
    """Label pytree matching `params` (one optax group per label)."""
    g = params["gaussians"]
    labels: dict[str, Any] = {
        # field order of Gaussians: means, log_scales, quats, opacity_logits, sh
        "gaussians": jax.tree_util.tree_unflatten(
            jax.tree_util.tree_structure(g), ["means", "scales", "quats", "opacity", "sh"]
        ),
    }
    if "deform" in params:
        labels["deform"] = {k: jax.tree_util.tree_map(lambda _: "hash" if k in ("grid", "slots") else "deform", v)
                            for k, v in params["deform"].items()}
    if "pose" in params:
        labels["pose"] = "pose"
    return labels


def _sh_scale(num_coeffs: int) -> optax.GradientTransformation:
    """Multiply SH updates by 1 (DC) and 1/20 (higher orders), per coefficient row."""
    factor = jnp.concatenate([jnp.ones((1,)), jnp.full((num_coeffs - 1,), 1.0 / 20.0)])

    def update(updates, state, params=None):
        return jax.tree_util.tree_map(lambda u: u * factor.astype(u.dtype)[None, :, None], updates), state

    return optax.GradientTransformation(lambda p: optax.EmptyState(), update)


def _adam(lr) -> optax.GradientTransformation:
    return optax.adam(lr, eps=1e-15)


def make_optimizer(spec: OptimSpec, num_sh_coeffs: int) -> optax.GradientTransformation:
    """The multi-group Adam (use with `param_labels`)."""
    ext = float(spec.scene_extent)
    d = spec.warmup_steps
    transforms = {
        "means": _adam(exp_decay(spec.lr_means * ext, spec.lr_means_final * ext, spec.steps)),
        "scales": _adam(spec.lr_scales),
        "quats": _adam(spec.lr_quats),
        "opacity": _adam(spec.lr_opacity),
        "sh": optax.chain(_adam(spec.lr_sh), _sh_scale(num_sh_coeffs)),
        "deform": _adam(exp_decay(spec.lr_deform, spec.lr_deform_final, spec.steps, delay=d)),
        "hash": _adam(exp_decay(spec.lr_deform * spec.lr_hash_factor, spec.lr_deform_final * spec.lr_hash_factor,
                                spec.steps, delay=d)),
        "pose": _adam(exp_decay(spec.lr_pose, spec.lr_pose_final, spec.steps)),
    }
    return optax.multi_transform(transforms, param_labels)


def active_sh_degree(step: int, increase_every: int, max_degree: int) -> int:
    """SH degree schedule: +1 every `increase_every` steps (3DGS: 1000), capped at `max_degree`."""
    if increase_every <= 0:
        return max_degree
    return min(max_degree, step // increase_every)


def guarded_update(loss_fn, opt, p, st, i):
    """(params, opt_state, loss, skipped): one `opt` step on ``loss_fn(params, i) -> (loss, overflow)``; a step
    whose render overflowed the tile capacity or whose loss is not finite leaves params and state unchanged."""
    (loss, over), gr = jax.value_and_grad(loss_fn, has_aux=True)(p, i)
    up, st2 = opt.update(gr, st, p)
    new = optax.apply_updates(p, up)
    bad = over | ~jnp.isfinite(loss)
    keep = lambda a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(bad, y, x), a, b)
    return keep(new, p), keep(st2, st), loss, bad


def guarded_step(loss_fn, opt):
    """jitted (params, opt_state, i) -> `guarded_update`."""
    return jax.jit(functools.partial(guarded_update, loss_fn, opt))
