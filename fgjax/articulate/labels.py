"""Label passes of the articulated variant, on the re-fitted reference scene: hull and hinge fills, isolated members,
colour outlines, Gaussians seen through the parts, ghosts of the parts' swept volume, and settling still spans at
rest. Each wraps a pure function of `fgjax.cluster` with the scene's centres, opacities and colours.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float, Int
from scipy.special import expit

from fgjax import cluster
from fgjax.articulate.phototrack import settle_at_rest
from fgjax.config import ArticulateConfig
from fgjax.data.scene import Scene
from fgjax.gaussians import SH_C0, Gaussians, activate
from fgjax.method.result import LoadedRun, render_capacity
from fgjax.models.posed import transform_gaussians
from fgjax.render.api import gaussian_weights, rasterization

__all__ = ["posed_geometry", "opaque", "joined", "fill_hulls", "drop_isolated", "refine_by_colour", "settle",
           "fill_hinges", "cap_opacity", "fade_dropped", "TileOverflow", "seen_through", "prune_seen_through",
           "fade_ghosts", "LABEL_PASSES", "label_passes_on"]

LABEL_PASSES = ("hull_fill", "hinge_fill", "isolated_factor", "colour_radius", "through_prune")
"""The `ArticulateConfig` keys that turn on a label pass (`fgjax.articulate.pipeline.label_passes`; a pass is on when
its key is true or non-zero)."""


def label_passes_on(acfg: ArticulateConfig) -> tuple[str, ...]:
    """The keys of `LABEL_PASSES` that ``acfg`` turns on, in that order."""
    return tuple(k for k in LABEL_PASSES if getattr(acfg, k))


def posed_geometry(base, labels: Int[np.ndarray, " N"], poses: Float[np.ndarray, "K T 4 4"]):
    """The reference geometry `base` (means, raw quats, log-scales) with each object moved by its pose, per
    time: (means [T, N, 3], raw quats [T, N, 4], log-scales [T, N, 3])."""

    m0, q0, ls0 = base
    ms, qs = [], []
    for j in range(poses.shape[1]):
        m, q = transform_gaussians(jnp.asarray(m0), jnp.asarray(q0), jnp.asarray(labels),
                                   jnp.asarray(poses[:, j], jnp.float32))
        ms.append(np.asarray(m))
        qs.append(np.asarray(q))
    return np.stack(ms), np.stack(qs), np.repeat(np.asarray(ls0)[None], poses.shape[1], axis=0)


def opaque(gs: Gaussians, alive, min_opacity: float) -> tuple[np.ndarray, np.ndarray]:
    """(alive [N] bool, core [N] bool: alive with opacity >= ``min_opacity``) of ``gs``: the fills' core (labels
    select the members). The sigmoid is scipy's expit, without exp's overflow at pruned logits."""

    alive = np.asarray(alive, bool)
    return alive, alive & (expit(np.asarray(gs.opacity_logits, np.float64)) >= min_opacity)


def joined(before: np.ndarray, after: np.ndarray) -> list[int]:
    """How many Gaussians joined each cluster from `before` [N] to `after` [N] labels: [K]."""
    return [int(np.sum((after == k) & (before != k))) for k in range(int(after.max(initial=-1)) + 1)]


def fill_hulls(labels: Int[np.ndarray, " N"], gs: Gaussians, alive, min_opacity: float, max_growth: float = np.inf,
                log=print) -> Int[np.ndarray, " N"]:
    """`ArticulateConfig.hull_fill`: `fgjax.cluster.fill_hulls` on the reference scene ``gs`` (its centres, and
    its members with opacity >= ``min_opacity`` as each hull's core); labels [N] -> labels [N]. Logs how many
    joined each cluster."""
    alive, core = opaque(gs, alive, min_opacity)
    new = cluster.fill_hulls(np.asarray(gs.means, np.float64), labels, core, alive, max_growth=max_growth)
    log(f"stage 2: {joined(labels, new)} static Gaussians (objects 1, 2, ...) inside the hulls of the clusters' opaque "
        f"members joined them (a hull holding more than {max_growth:g}x its cluster's size is not filled)")
    return new


def drop_isolated(labels: Int[np.ndarray, " N"], gs: Gaussians, alive, factor: float,
                  log=print) -> tuple[Int[np.ndarray, " N"], list[int]]:
    """`ArticulateConfig.isolated_factor`: `fgjax.cluster.drop_isolated` on the reference scene ``gs`` (centres of the
    alive Gaussians). Returns (labels [N], how many left each cluster [K]) and logs the counts."""
    new = cluster.drop_isolated(np.asarray(gs.means, np.float64), labels, factor, np.asarray(alive, bool))
    left = [int(np.sum((labels == k) & (new != k))) for k in range(int(labels.max(initial=-1)) + 1)]
    log(f"stage 2: {left} members (objects 1, 2, ...) farther than {factor:g}x their cluster's median spacing from "
        f"every other member made static")
    return new, left


COLOUR_MIN_OPACITY = 0.1  # `refine_by_colour`: fainter Gaussians' colours do not count (nor change label)


def refine_by_colour(labels: Int[np.ndarray, " N"], gs: Gaussians, alive, cfg: ArticulateConfig, seed: int,
                      log=print) -> tuple[Int[np.ndarray, " N"], list]:
    """`ArticulateConfig.colour_radius`: `fgjax.cluster.refine_by_colour` on the reference scene ``gs`` (centres and DC
    colours of the alive Gaussians with opacity >= 0.1). Returns (labels [N], the per-cluster report) and logs it."""

    _, usable = opaque(gs, alive, COLOUR_MIN_OPACITY)
    rgb = np.asarray(gs.sh, np.float64)[:, 0, :] * SH_C0 + 0.5  # [N, 3]
    new, report = cluster.refine_by_colour(np.asarray(gs.means, np.float64), np.nan_to_num(rgb), labels, usable,
                                           radius=cfg.colour_radius, n_components=cfg.colour_components,
                                           min_separation=cfg.colour_separation, seed=seed)
    log(f"stage 2: outlines by colour (objects 1, 2, ...): joined {[r['joined'] for r in report]}, left "
        f"{[r['left'] for r in report]}, colours apart by "
        f"{[None if r['separation'] is None else round(r['separation'], 2) for r in report]}"
        + "".join(f"; object {k + 1} stopped: {r['skipped']}" for k, r in enumerate(report) if r["skipped"]))
    return new, report


def settle(run: LoadedRun, scene: Scene, order: Int[np.ndarray, " T"], ref: Gaussians, labels: Int[np.ndarray, " N"],
            poses: Float[np.ndarray, "K T 4 4"], moving, log=print) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """`ArticulateConfig.settle_rest`: `fgjax.articulate.phototrack.settle_at_rest` on the scene ``ref`` (stage 1's)
    with ``labels`` [N], the training frames in time order (`order`)."""

    return settle_at_rest(ref, run.state.densify.alive, labels, int(poses.shape[0]), scene.images[order],
                          scene.viewmats[order], scene.Ks[order], poses, moving, sh_degree=run.cfg.model.sh_degree,
                          background=run.cfg.model.background, capacity=render_capacity(run),
                          tile_size=run.cfg.train.tile_size, log=log)


def fill_hinges(labels: Int[np.ndarray, " N"], gs: Gaussians, alive, poses: Float[np.ndarray, "K T 4 4"],
                 cfg: ArticulateConfig, log=print) -> tuple[Int[np.ndarray, " N"], list]:
    """`ArticulateConfig.hinge_fill`: `fgjax.cluster.fill_hinges` on the reference scene ``gs`` (centres; the core:
    alive members with opacity >= ``cfg.hull_opacity``) with the hinges of ``poses`` [K, T, 4, 4]
    (`fgjax.cluster.hinge_axes`). Returns (labels [N], hinges: per cluster {"axis", "pivot", "angle_deg"} or
    None where it does not turn by ``cfg.hinge_min_deg``). Logs the hinges and how many joined."""
    alive, core = opaque(gs, alive, cfg.hull_opacity)
    axes, pivots, angles = cluster.hinge_axes(poses, min_deg=cfg.hinge_min_deg)
    new = cluster.fill_hinges(np.asarray(gs.means, np.float64), labels, core, alive, axes, pivots,
                              radius=cfg.hinge_radius, reach=cfg.hinge_reach, max_growth=cfg.hull_max_growth)
    hinges = [None if not np.all(np.isfinite(a)) else
              {"axis": [float(v) for v in a], "pivot": [float(v) for v in p], "angle_deg": float(g)}
              for a, p, g in zip(axes, pivots, angles)]
    turning = [k + 1 for k, h in enumerate(hinges) if h is not None]
    log(f"stage 2: {joined(labels, new)} static Gaussians (objects 1, 2, ...) along the hinges of the objects that "
        f"turn by >= {cfg.hinge_min_deg:g} degrees {turning} joined them")
    return new, hinges


def cap_opacity(gs: Gaussians, mask, opacity: float) -> tuple[Gaussians, np.ndarray]:
    """``gs`` with the opacity of the Gaussians in ``mask`` [N] capped at ``opacity`` in (0, 1); (scene, [N] bool:
    those whose opacity was above it)."""
    cap = float(np.log(opacity) - np.log1p(-opacity))  # logit
    o = np.asarray(gs.opacity_logits)  # [N]
    faded = np.asarray(mask, bool) & (o > cap)
    return Gaussians(gs.means, gs.log_scales, gs.quats, np.where(faded, np.asarray(cap, o.dtype), o), gs.sh), faded


def fade_dropped(gs: Gaussians, before: np.ndarray, after: np.ndarray, cfg: ArticulateConfig, what: str,
                  log=print) -> Gaussians:
    """With ``cfg.ghost_radius`` > 0, as the ghosts: the members of ``before`` [N] that are static in ``after`` [N]
    start the last re-fit with their opacity capped at ``cfg.ghost_opacity`` (the re-fit brings back those the
    static frames need); logs how many, "``what`` faded ..."."""
    if cfg.ghost_radius <= 0:
        return gs
    gs, faded = cap_opacity(gs, (before >= 0) & (after < 0), cfg.ghost_opacity)
    log(f"stage 2: {int(faded.sum())} {what} faded to opacity {cfg.ghost_opacity:g} before the re-fit")
    return gs


PRUNED_OPACITY = 1e-6  # the opacity `prune_seen_through` sets


class TileOverflow(ValueError):
    """A render overflowed its tile capacity, so the per-Gaussian weights it gave would be incomplete."""


def seen_through(gs: Gaussians, alive, labels: Int[np.ndarray, " N"], poses: Float[np.ndarray, "K T 4 4"], viewmats, Ks,
                 width: int, height: int, *, capacity: int | None = None, tile_size: int = 16) -> np.ndarray:
    """Per Gaussian, the fraction of the weight it paints over the frames (sum over pixels p of T_p alpha_p, as in
    `fgjax.render.api.gaussian_weights`) that falls where the parts' members cover the pixel: [N] in [0, 1] (0 for
    a Gaussian that paints nothing, or is dead).

    Frame i renders the reference scene ``gs`` (raw parameters) with each cluster's members (``labels`` [N], -1
    static) moved by its pose ``poses[:, i]`` ([K, T, 4, 4], `fgjax.articulate.track.transform_gaussians`) from the
    camera ``viewmats[i]`` ([T, 4, 4] OpenCV world-to-camera) with ``Ks[i]`` ([T, 3, 3]). The members' coverage
    of a pixel is their composited share of it (an image of 1 for members and 0 for the rest, no background),
    in [0, 1]. A static Gaussian whose weight lies mostly there is seen through a part (or mixed into its edge)
    in the training frames: it lends the part its colour where the part's own Gaussians are sparse, and shows
    when a held-out state moves the part away.

    Raises ValueError on mismatched shapes, and `TileOverflow` (a ValueError) when a frame's render overflows the
    tile ``capacity`` (its weights would be incomplete)."""

    n = int(np.shape(gs.means)[0])
    k = int(np.asarray(labels).max(initial=-1)) + 1
    if np.shape(labels) != (n,) or np.shape(alive) != (n,):
        raise ValueError(f"seen_through: labels and alive must have shape [{n}], got {list(np.shape(labels))} and "
                         f"{list(np.shape(alive))}")
    t = int(np.shape(poses)[1]) if np.ndim(poses) == 4 else -1
    if np.ndim(poses) != 4 or np.shape(poses)[0] < k or np.shape(poses)[2:] != (4, 4) \
            or np.shape(viewmats) != (t, 4, 4) or np.shape(Ks) != (t, 3, 3):
        raise ValueError(f"seen_through: poses must be [K >= {k}, T, 4, 4] with viewmats [T, 4, 4] and Ks [T, 3, 3], "
                         f"got {list(np.shape(poses))}, {list(np.shape(viewmats))} and {list(np.shape(Ks))}")
    alive_j = jnp.asarray(np.asarray(alive, bool))
    lab = jnp.asarray(np.asarray(labels, np.int32))
    member = (lab >= 0).astype(jnp.float32)[:, None]  # [N, 1]
    q0 = jnp.asarray(gs.quats)
    _, s, o = activate(jax.tree_util.tree_map(jnp.asarray, gs), alive_j)
    poses_j = jnp.asarray(poses, jnp.float32)  # [K, T, 4, 4]

    @jax.jit
    def frame(pose, vm, K):  # ([N] weight under the members' coverage, [N] weight)
        m, q = transform_gaussians(jnp.asarray(gs.means), q0, lab, pose)
        cov, _, info = rasterization(m, q, s, o, member, vm, K, int(width), int(height), capacity=capacity,
                                     tile_size=tile_size, render_depth=False)
        kw = dict(capacity=capacity, tile_size=tile_size)
        return (gaussian_weights(m, q, s, o, vm, K, width, height, jnp.clip(cov[..., 0], 0.0, 1.0), **kw),
                gaussian_weights(m, q, s, o, vm, K, width, height, jnp.ones((int(height), int(width))), **kw),
                info["overflow"])

    inside = np.zeros(len(lab))
    total = np.zeros(len(lab))
    for i in range(int(poses_j.shape[1])):
        a, b, over = frame(poses_j[:, i], jnp.asarray(viewmats[i], jnp.float32), jnp.asarray(Ks[i], jnp.float32))
        if bool(over):
            raise TileOverflow(f"seen_through: frame {i}'s render overflowed the tile capacity ({capacity})")
        inside += np.asarray(a, np.float64)
        total += np.asarray(b, np.float64)
    ratio = np.where(total > 0, inside / np.maximum(total, 1e-30), 0.0)
    return np.clip(np.where(np.asarray(alive, bool), ratio, 0.0), 0.0, 1.0)


def prune_seen_through(gs: Gaussians, labels: Int[np.ndarray, " N"], poses: Float[np.ndarray, "K T 4 4"],
                        run: LoadedRun, scene: Scene, order: Int[np.ndarray, " T"], max_ratio: float,
                        log=print) -> tuple[Gaussians, int]:
    """`ArticulateConfig.through_prune`: the alive static Gaussians of ``gs`` whose `seen_through` share over the
    training frames (time order ``order``, the parts at ``poses``) exceeds ``max_ratio`` get opacity ~0
    (`PRUNED_OPACITY`, which no re-fit brings back: the sigmoid's gradient vanishes there). Returns (scene, how
    many)."""
    t0 = time.perf_counter()
    try:
        ratio = seen_through(gs, run.state.densify.alive, labels, poses, scene.viewmats[order], scene.Ks[order],
                             scene.width, scene.height, capacity=render_capacity(run),
                             tile_size=run.cfg.train.tile_size)
    except TileOverflow as e:  # prune nothing rather than on partial weights
        log(f"stage 2: no static Gaussians pruned as seen through the parts: {e}")
        return gs, 0
    sel = (np.asarray(labels) < 0) & np.asarray(run.state.densify.alive, bool) & (ratio > max_ratio)
    gs, pruned = cap_opacity(gs, sel, PRUNED_OPACITY)
    log(f"stage 2: {int(pruned.sum())} static Gaussians seen through the parts (more than {max_ratio:g} of their "
        f"weight where the members cover the pixel) pruned ({time.perf_counter() - t0:.1f} s)")
    return gs, int(pruned.sum())


def fade_ghosts(gs: Gaussians, labels: Int[np.ndarray, " N"], poses: Float[np.ndarray, "K T 4 4"], alive,
                 cfg: ArticulateConfig, log=print) -> Gaussians:
    """`ArticulateConfig.ghost_radius`: the opacity of alive static Gaussians of ``gs`` near the volume the parts
    sweep under ``poses`` [K, T, 4, 4] (`fgjax.cluster.near_swept`) capped at ``cfg.ghost_opacity``."""
    near = cluster.near_swept(np.asarray(gs.means, np.float64), labels, poses,
                              cfg.ghost_radius) & np.asarray(alive, bool)
    gs, faded = cap_opacity(gs, near, cfg.ghost_opacity)
    log(f"stage 2: {int(faded.sum())} static Gaussians near the parts' swept volume faded to opacity "
        f"{cfg.ghost_opacity:g} before the re-fit ({int(near.sum())} within {cfg.ghost_radius:g})")
    return gs
