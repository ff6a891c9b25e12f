"""Stage 1: deformable 4D Gaussian training (DESIGN.md section 1, step 1).

Library entry points: ``train_stage1(cfg, scene, out_dir, ...)``, and ``run(cfg, data_dir, out)`` which loads the
scene, trains, evaluates and writes the run folder (``fgjax train``). One jitted step renders a batch of training
cameras (one by one on one device; vmapped and data-parallel over a ``jax.sharding`` mesh when several devices
exist), with the deformation field applied (or not: the warm-up and a detected static scene use a separately traced
step without it, so they pay nothing for it), and applies one optax update. Densification runs between steps over
fixed-capacity arrays. Checkpoints hold everything needed to resume bit-for-bit.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from fgjax import metrics
from fgjax.config import Config, ConfigError, load_config, to_toml, validate_stage1
from fgjax.data.loaders import load_scene
from fgjax.data.testviews import load_test_views
from fgjax.flow import gaussian_flow_loss
from fgjax.flow.track import gaussian_track_loss
from fgjax.gaussians import Gaussians, activate, init_from_points, knn_graph
from fgjax.geometry import matmul, se3_exp
from fgjax.io import atomic_write
from fgjax.io import write_video as write_frames
from fgjax.method.bases_init import place_bases, static_points
from fgjax.method.flows import estimate_training_flows, previous_frames, training_tracks
from fgjax.method.init_points import depth_point_cloud, first_view_colors, flow_point_cloud, random_points, scene_box
from fgjax.method.poses import bundle_adjust
from fgjax.method.static import detect_static
from fgjax.models.deform import MOTION_KEYS, DeformSpec, deform_apply, deform_init
from fgjax.models.model import deformed_gaussians, refined_viewmats, render_params, scene_extent
from fgjax.provenance import PROVENANCE_NAME, read_provenance, scene_fingerprint, write_provenance
from fgjax.render.api import count_intersections, round_capacity
from fgjax.train import checkpoint as ckpt
from fgjax.train import densify as dens
from fgjax.train.densify import DensifyState, densify_accumulate, densify_apply, densify_init, opacity_reset
from fgjax.train.losses import (
    depth_loss,
    isometry_loss,
    photometric_loss,
    rigid_drift_loss,
    scale_change_loss,
    scale_regularizer,
)
from fgjax.train.optim import OptimSpec, active_sh_degree, make_optimizer
from fgjax.train.sampling import batch_indices, time_window
from fgjax.version import __version__

__all__ = ["train_stage1", "run", "TrainState", "deform_spec_from_config", "FlowBatch", "flow_term", "training_tracks",
           "estimate_training_flows", "previous_frames", "load_run", "render_frame", "evaluate", "template_state",
           "refined_viewmats", "load_test_views", "prepare_run_folder", "make_step", "compute_capacity",
           "active_sh_mask", "StepSpec"]


# ---------------------------------------------------------------------------------------------
# set-up helpers
# ---------------------------------------------------------------------------------------------


STATIC_POINTS = 4096  # the most static points `deform.gauge` prices the drift at (a fixed shape under jit)


@dataclasses.dataclass
class TrainState:
    """Everything a checkpoint holds (host-side container; arrays are device arrays)."""

    params: dict[str, Any]
    opt_state: Any
    densify: DensifyState
    step: int
    key: jax.Array
    capacity: int
    static: bool | None  # None: not decided yet (before the end of warm-up)
    frame_err: np.ndarray | None = None  # [T] last measured MSE per frame (NaN: not yet), with train.error_sampling
    static_points: np.ndarray | None = None  # [M, 4] the placement's static points and 1 (0: none), deform.gauge > 0


def init_gaussians(cfg: Config, scene, key, log=print, cache_dir=None) -> tuple[Gaussians, jax.Array]:
    """Initial Gaussians: points triangulated from optical flow (``model.init = "flow"``) or back-projected from the
    measured depth (``"depth"``, where the scene has depth maps), each with a fraction of random points, or random
    points in the scene box that some training camera sees."""
    lo, hi = scene_box(scene.viewmats, scene.Ks, scene.width, scene.height)
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).astype(np.uint64).tolist())
    want = cfg.model.init_points
    pts, cols = np.zeros((0, 3)), np.zeros((0, 3))
    init = cfg.model.init
    if init not in ("flow", "depth", "random"):
        raise ConfigError(f"config key 'model.init' must be 'flow', 'depth' or 'random'; got {init!r}")
    if init == "depth" and scene.depths is None:
        log("model.init = depth: the scene has no depth maps; triangulating points from optical flow instead")
        init = "flow"
    flow_ok = scene.num_frames > 1 and min(scene.width, scene.height) >= 16  # optical flow needs 16x16
    if init == "flow" and not flow_ok:
        log(f"model.init = flow: {scene.num_frames} frame(s) of {scene.width}x{scene.height} are too few or too "
            "small for optical flow; using random points")
    if init == "depth" or (init == "flow" and flow_ok):
        pc = (depth_point_cloud(scene, log=log) if init == "depth" else
              flow_point_cloud(scene, gap=cfg.model.init_flow_gap, cache_dir=cache_dir, log=log))
        c, r = 0.5 * (lo + hi), 0.5 * (hi - lo)
        inside = np.all(np.abs(pc["points"] - c) <= 2.0 * r, axis=-1)  # drop far-off mismatches
        n_flow = min(int(inside.sum()), int(round(want * (1.0 - cfg.model.init_random_fraction))))
        if n_flow == 0:
            why = ("no measured depth inside the scene box" if init == "depth"
                   else "no point could be triangulated (the "
                   "cameras barely move against the distance to what they see, or no pixel matched)")
            log(f"model.init = {init}: {why}; starting from random points in the scene box")
        sel = rng.choice(np.flatnonzero(inside), size=n_flow, replace=False) if n_flow else np.zeros(0, int)
        pts, cols = pc["points"][sel], pc["colors"][sel]
    rnd = random_points(rng, want - len(pts), lo, hi, scene)
    pts = np.concatenate([pts, rnd])
    cols = np.concatenate([cols, first_view_colors(rnd, scene)])
    cap = max(cfg.model.capacity, len(pts))
    return init_from_points(pts, cols, capacity=cap, sh_degree=cfg.model.sh_degree,
                            init_opacity=cfg.model.init_opacity, scale_factor=cfg.model.init_scale)


def deform_spec_from_config(cfg: Config, aabb, times=None) -> DeformSpec:
    """The field's static description; ``times`` (the training times) place ``deform.anchor = "first"``."""
    d = cfg.deform
    anchor = None
    if d.anchor == "first":
        if times is None or len(times) == 0:
            raise ValueError("deform.anchor = 'first' needs the training times")
        anchor = float(np.min(times))
    return DeformSpec(
        anchor=anchor, kind=d.kind, depth=d.depth, width=d.width, x_freqs=d.x_freqs, t_freqs=d.t_freqs, skip=d.skip,
        hash_levels=d.hash_levels, hash_log2_table=d.hash_log2_table, hash_features=d.hash_features,
        hash_base_res=d.hash_base_res, hash_max_res=d.hash_max_res, x_freqs_hash=d.x_freqs_hash, bases=d.bases,
        knots=d.knots, joint=d.joint, weights=d.weights, aabb=tuple(float(x) for x in aabb),
    )


# ---------------------------------------------------------------------------------------------
# the step
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class StepSpec:
    spec: DeformSpec | None  # None: no deformation (warm-up or static scene)
    sh_degree: int
    width: int
    height: int
    capacity: int
    tile_size: int
    lambda_dssim: float
    scale_reg: float
    scale_reg_max: float
    pose: bool
    flow_weight: float = 0.0  # beta of L_uGS (0: no flow pass; the step then takes no flow batch)
    flow_threshold: float = 0.0  # |u - u_cam| below this (pixels) counts as static (0: off)
    rigid_weight: float = 0.0  # weight of the isometry regulariser (needs the neighbour graph; deformation only)
    rigid_scale_weight: float = 0.0  # weight of the scale-change regulariser (deformation only)
    rigid_cap: float = 0.0  # saturation of a pair's stretch in the isometry regulariser (0: none)
    freeze_gaussians: bool = False  # only the deformation (and poses) update: the canonical Gaussians stay
    vmap_cameras: bool = False  # vmap the batch's cameras (a data-parallel mesh splits them); else a loop
    photo_motion: float = 1.0  # scale of the photometric loss's gradient into the field's displacements
    flow_loss: str = "pair"  # "pair": L_uGS of frames t-1, t; "track": the first frame's tracks (fgjax.flow.track)
    gaussian_flow: str = "isotropic"  # "pair": u~_GS isotropic (the paper) or anisotropic (GaussianFlow)
    camera_depth: str = "composited"  # "pair": u_cam from the composited ("composited") or expected depth
    depth_weight: float = 0.0  # weight of the measured-depth term (0: none; the step then takes no depth batch)
    flow_norm: str = "l1"  # the flow loss's per-pixel penalty, "l1" or "charbonnier" (fgjax.flow.flow_loss, .track)
    flow_scale: float = 10.0  # c of "charbonnier" (pixels)
    freeze_weights: bool = False  # "bases" field: only MOTION_KEYS update, the weights' network stays
    gauge: float = 0.0  # weight of the static points' rigid drift (the step then takes them)


class FlowBatch(NamedTuple):
    """Per-camera inputs of the flow loss (leading axis: the cameras of the batch). For the "track" loss, frame
    t-1 is the reference frame r and ``flow`` the tracks from r to t on r's grid."""

    flow: Any  # [B, H, W, 2] observed optical flow frame t-1 -> t on frame t-1's grid (NaN = unknown)
    viewmat_prev: Any  # [B, 4, 4] world-to-camera of frame t-1
    t_prev: Any  # [B] time of frame t-1
    idx_prev: Any  # [B] int32 index of frame t-1 (pose deltas)
    weight: Any  # [B] 1 where frame t-1 exists, else 0
    K_prev: Any = None  # [B, 3, 3] intrinsics of frame t-1 (None: frame t's)


def flow_term(ss: StepSpec, params, alive, viewmat, K, t, fl: FlowBatch):
    """The flow loss of one camera. ``ss.flow_loss`` "pair": L_uGS (``fgjax.flow.gaussian_flow_loss``), the model
    deformed to t-1 and t, both seen by camera t-1; "track": `fgjax.flow.track.gaussian_track_loss` of the
    reference frame (``fl``'s frame t-1) and frame t, each seen by its own camera. Returns (weighted loss, overflow
    flag)."""
    vm_prev = fl.viewmat_prev
    if ss.pose:
        vm_prev = matmul(se3_exp(params["pose"][fl.idx_prev]), vm_prev)
    m0, q0, s0, o0, _ = deformed_gaussians(params, alive, fl.t_prev, ss.spec)
    m1, q1, s1 = deformed_gaussians(params, alive, t, ss.spec)[:3]
    if ss.flow_loss == "track":
        k_prev = K if fl.K_prev is None else fl.K_prev
        loss, overflow = gaussian_track_loss(m0, q0, s0, o0, m1, vm_prev, k_prev, viewmat, K, fl.flow, ss.width,
                                             ss.height, threshold=ss.flow_threshold, capacity=ss.capacity,
                                             tile_size=ss.tile_size, norm=ss.flow_norm, scale=ss.flow_scale)
        return fl.weight * loss, overflow
    loss, overflow = gaussian_flow_loss(m0, q0, s0, o0, m1, vm_prev, viewmat, K, fl.flow, ss.width, ss.height,
                                        threshold=ss.flow_threshold if ss.flow_threshold > 0 else None,
                                        capacity=ss.capacity, tile_size=ss.tile_size,
                                        anisotropic=ss.gaussian_flow == "anisotropic", quats1=q1, scales1=s1,
                                        camera_depth=ss.camera_depth, norm=ss.flow_norm, scale=ss.flow_scale)
    return fl.weight * loss, overflow


@functools.lru_cache(maxsize=16)
def make_step(ss: StepSpec, ospec: OptimSpec, num_sh: int, background: tuple[float, ...]):
    """The jitted step for one static configuration. Memoised on its (hashable, immutable) static inputs
    so that repeated runs in one process (tests, resume, benchmarks) reuse compiled code."""
    optimizer = make_optimizer(ospec, num_sh)
    bg = jnp.asarray(background, jnp.float32)

    def cam_loss(params, alive, sh_mask, delta2d, image, viewmat, K, t, idx, fl, depth, nbr, pts):
        if ss.pose:
            viewmat = matmul(se3_exp(params["pose"][idx]), viewmat)
        img, _, info, geo = render_params(
            params, alive, viewmat, K, t, spec=ss.spec, sh_degree=ss.sh_degree, width=ss.width,
            height=ss.height, background=bg, capacity=ss.capacity, tile_size=ss.tile_size, delta2d=delta2d,
            sh_mask=sh_mask, motion_grad=ss.photo_motion, render_depth=depth is not None,
        )
        loss = photometric_loss(img, image, ss.lambda_dssim)
        if depth is not None:
            loss = loss + ss.depth_weight * depth_loss(info["depth_acc"], depth)
        if ss.scale_reg > 0:
            loss = loss + ss.scale_reg * scale_regularizer(geo["log_scales"], alive, ss.scale_reg_max)
        if nbr is not None:  # rigidity: neighbour distances keep their canonical lengths
            iso = isometry_loss(geo["means"], params["gaussians"].means, *nbr, cap=ss.rigid_cap)
            loss = loss + ss.rigid_weight * iso
        if ss.rigid_scale_weight > 0 and ss.spec is not None:  # ... and Gaussian sizes their canonical values
            loss = loss + ss.rigid_scale_weight * scale_change_loss(geo["log_scales"], params["gaussians"].log_scales,
                                                                    alive)
        if pts is not None:  # gauge: the static scene keeps the world frame (fgjax.train.losses.rigid_drift_loss)
            drift = deform_apply(ss.spec, params["deform"], pts[:, :3], t)[0]
            loss = loss + ss.gauge * rigid_drift_loss(pts[:, :3], drift, pts[:, 3], ospec.scene_extent)
        overflow = info["overflow"]
        if fl is not None:
            lf, of = flow_term(ss, params, alive, viewmat, K, t, fl)
            loss = loss + ss.flow_weight * lf
            overflow = overflow | of
        mse = jnp.mean((img - image) ** 2)
        return loss, (mse, overflow, info["valid"])

    def batch_loss(params, delta2d, alive, sh_mask, images, viewmats, Ks, times, idx, fl, depths, nbr, pts):
        per_cam = (delta2d, images, viewmats, Ks, times, idx, fl, depths)  # leading axis: the batch's cameras
        if ss.vmap_cameras:  # a data-parallel mesh: the partitioner splits the vmapped cameras over devices
            losses, aux = jax.vmap(cam_loss, in_axes=(None, None, None, 0, 0, 0, 0, 0, 0, 0, 0, None, None))(
                params, alive, sh_mask, *per_cam, nbr, pts)
        elif images.shape[0] == 1:
            # One device: no vmap. Under vmap the compositor's lax.cond (skip the unused chunk batches)
            # becomes a select that computes every batch: 1.4x the step at 20k Gaussians (docs/benchmarks.md).
            losses, aux = jax.tree_util.tree_map(
                lambda x: x[None], cam_loss(params, alive, sh_mask, *jax.tree_util.tree_map(lambda x: x[0], per_cam),
                                            nbr, pts))
        else:
            losses, aux = jax.lax.map(lambda a: cam_loss(params, alive, sh_mask, *a, nbr, pts), per_cam)
        return jnp.mean(losses), aux

    def step(params, opt_state, dstate: DensifyState, sh_mask, images, viewmats, Ks, times, idx, flow_batch=None,
             nbr=None, depths=None, pts=None):
        b = images.shape[0]
        n = params["gaussians"].means.shape[0]
        delta2d = jnp.zeros((b, n, 2), jnp.float32)
        fl = flow_batch if (ss.flow_weight > 0 and ss.spec is not None) else None
        nbr = nbr if (ss.rigid_weight > 0 and ss.spec is not None) else None
        depths = depths if ss.depth_weight > 0 else None
        pts = pts if (ss.gauge > 0 and ss.spec is not None) else None
        (loss, (mse, overflow, valid)), (grads, g2d) = jax.value_and_grad(batch_loss, argnums=(0, 1), has_aux=True)(
            params, delta2d, dstate.alive, sh_mask, images, viewmats, Ks, times, idx, fl, depths, nbr, pts)
        bad = jnp.any(overflow) | ~jnp.isfinite(loss)
        updates, new_opt = optimizer.update(grads, opt_state, params)
        if ss.freeze_gaussians:  # masked updates (zero gradients alone would still move them by momentum)
            updates = {**updates, "gaussians": jax.tree_util.tree_map(jnp.zeros_like, updates["gaussians"])}
        if ss.freeze_weights:
            updates = {**updates, "deform": {k: v if k in MOTION_KEYS else jax.tree_util.tree_map(
                jnp.zeros_like, v) for k, v in updates["deform"].items()}}
        new_params = optax.apply_updates(params, updates)
        # An overflowing (or non-finite) step is dropped, and reported to the host loop.
        keep = lambda new, old: jax.tree_util.tree_map(lambda a, c: jnp.where(bad, c, a), new, old)
        new_params, new_opt = keep(new_params, params), keep(new_opt, opt_state)
        # densification statistics: mean of per-camera screen gradients (x batch, since the loss is a mean)
        nd = dstate
        for i in range(b):
            nd = densify_accumulate(nd, g2d[i] * b, valid[i], ss.width, ss.height)
        nd = keep(nd, dstate)
        return new_params, new_opt, nd, loss, mse, bad  # mse: [B] per camera

    return jax.jit(step, donate_argnums=(0, 1, 2))


# ---------------------------------------------------------------------------------------------
# training
# ---------------------------------------------------------------------------------------------


def compute_capacity(params, alive, viewmats, Ks, width, height, tile_size, margin) -> int:
    g = params["gaussians"]
    q, s, o = activate(g, alive)
    worst = 0
    for vm, K in zip(viewmats, Ks):
        worst = max(worst, int(count_intersections(g.means, q, s, o, jnp.asarray(vm, jnp.float32),
                                                   jnp.asarray(K, jnp.float32), width=width, height=height,
                                                   tile_size=tile_size)))
    return round_capacity(int(worst * margin) + 1024)


def _flow_batch(idx: np.ndarray, prev: np.ndarray, flows: np.ndarray, viewmats, times, Ks) -> FlowBatch:
    p = prev[idx]
    has = p >= 0
    pi = np.where(has, p, idx)
    return FlowBatch(flows[idx], viewmats[pi], times[pi], pi.astype(np.int32), has.astype(np.float32), Ks[pi])


def _mesh_shardings(batch: int, devices=None):
    devs = jax.devices() if devices is None else list(devices)
    if len(devs) < 2 or batch % len(devs) != 0:
        return None, None

    mesh = Mesh(np.asarray(devs), ("cams",))
    return NamedSharding(mesh, PartitionSpec("cams")), NamedSharding(mesh, PartitionSpec())


def _bundle_adjusted(cfg: Config, scene, cache_dir, log):
    """(scene with the bundle-adjusted cameras, their pose deltas [T, 6]) (``pose.bundle``): the initial
    Gaussians are placed with the corrected cameras, and training starts from the deltas, so that
    `refined_viewmats` and everything downstream see the corrected poses."""
    flows = estimate_training_flows(scene, cfg.flow.method, cache_dir=cache_dir, log=log)
    p = cfg.pose
    back = None if p.bundle_fb_px <= 0 else estimate_training_flows(scene, cfg.flow.method, cache_dir=cache_dir,
                                                                   log=log, backward=True)
    res = bundle_adjust(scene.viewmats, scene.Ks, flows, previous_frames(scene.times), prior_rot_deg=p.bundle_prior_deg,
                        prior_trans=p.bundle_prior_trans, cauchy_px=p.bundle_cauchy_px, backward=back,
                        fb_px=p.bundle_fb_px, log=log)
    return dataclasses.replace(scene, viewmats=res.viewmats.astype(np.float32)), res.deltas.astype(np.float32)


def initial_state(cfg: Config, scene, log=print, cache_dir=None) -> tuple[TrainState, DeformSpec, OptimSpec]:
    key = jax.random.key(cfg.model.seed)
    k_init, k_def, key = jax.random.split(key, 3)
    deltas = np.zeros((scene.num_frames, 6), np.float32)
    if cfg.pose.enabled and cfg.pose.bundle and scene.num_frames > 1:
        scene, deltas = _bundle_adjusted(cfg, scene, cache_dir, log)
    g, alive = init_gaussians(cfg, scene, k_init, log=log, cache_dir=cache_dir)
    lo, hi = scene_box(scene.viewmats, scene.Ks, scene.width, scene.height)
    spec = deform_spec_from_config(cfg, np.concatenate([lo, hi]), scene.times)
    params: dict[str, Any] = {"gaussians": g, "deform": deform_init(k_def, spec, slots=g.means.shape[0])}
    if cfg.pose.enabled:
        params["pose"] = jnp.asarray(deltas, jnp.float32)
    t = cfg.train
    ospec = OptimSpec(
        steps=t.steps, scene_extent=scene_extent(scene.viewmats), lr_means=t.lr_means,
        lr_means_final=t.lr_means_final, lr_deform=t.lr_deform, lr_deform_final=t.lr_deform_final,
        lr_hash_factor=t.lr_hash_factor, lr_opacity=t.lr_opacity, lr_scales=t.lr_scales, lr_quats=t.lr_quats,
        lr_sh=t.lr_sh, lr_pose=cfg.pose.lr, lr_pose_final=cfg.pose.lr_final, warmup_steps=t.warmup_steps,
    )
    opt = make_optimizer(ospec, g.sh.shape[1])
    state = TrainState(params, opt.init(params), densify_init(alive), 0, key, 0, None,
                       np.full(scene.num_frames, np.nan, np.float32) if cfg.train.error_sampling > 0 else None,
                       _no_static_points(cfg))
    if cfg.static.force in ("static", "dynamic"):
        state.static = cfg.static.force == "static"
    return state, spec, ospec


def template_state(cfg: Config, spec: DeformSpec, num_frames: int, scene_extent_: float = 1.0) -> TrainState:
    """A state with the shapes and tree structure a checkpoint of this config has (values are placeholders)."""
    n = cfg.model.capacity
    k = (cfg.model.sh_degree + 1) ** 2
    z = lambda *shape: jnp.zeros(shape, jnp.float32)
    g = Gaussians(z(n, 3), z(n, 3), z(n, 4).at[:, 0].set(1.0), z(n), z(n, k, 3))
    params: dict[str, Any] = {"gaussians": g, "deform": deform_init(jax.random.key(0), spec, slots=n)}
    if cfg.pose.enabled:
        params["pose"] = z(num_frames, 6)
    t = cfg.train
    ospec = OptimSpec(steps=t.steps, scene_extent=scene_extent_, warmup_steps=t.warmup_steps)
    opt = make_optimizer(ospec, k)
    return TrainState(params, opt.init(params), densify_init(jnp.zeros((n,), bool)), 0, jax.random.key(0), 0, None,
                      np.zeros(num_frames, np.float32) if t.error_sampling > 0 else None, _no_static_points(cfg))


def _bases_placed(cfg: Config) -> bool:
    """The "bases" field placed from the flow after the warm-up (`fgjax.method.bases_init`)."""
    return cfg.deform.kind == "bases" and cfg.deform.init == "flow"


def _no_static_points(cfg: Config) -> np.ndarray | None:
    """The static points' array before the placement fills it (deform.gauge > 0, flow-placed "field" weights)."""
    used = cfg.deform.gauge > 0 and _bases_placed(cfg) and cfg.deform.weights == "field"
    return np.zeros((STATIC_POINTS, 4), np.float32) if used else None


def load_run(run_dir: str | Path) -> tuple[Config, TrainState, DeformSpec, dict[str, Any]]:
    """(config, state, deformation spec, model.json) of a finished or checkpointed run."""
    run_dir = Path(run_dir)
    for name in ("config.toml", "model.json", ckpt.CHECKPOINT_NAME):
        if not (run_dir / name).exists():
            raise FileNotFoundError(f"{run_dir} is not a trained run: {name} is missing")
    cfg = load_config(run_dir / "config.toml")
    meta = json.loads((run_dir / "model.json").read_text())
    spec = DeformSpec(**{**meta["deform_spec"], "aabb": tuple(meta["deform_spec"]["aabb"])})
    state = ckpt.load_checkpoint(run_dir / ckpt.CHECKPOINT_NAME, template_state(cfg, spec, meta["num_frames"]))
    return cfg, state, spec, meta


def train_stage1(
    cfg: Config,
    scene,
    out_dir: str | Path | None = None,
    *,
    test_scene=None,
    resume: bool = False,
    stop_at: int | None = None,
    progress: bool = True,
    log=print,
    devices=None,
    flows: np.ndarray | None = None,
    monitor: Callable[[int, TrainState, DeformSpec], None] | None = None,
) -> dict[str, Any]:
    """Train stage 1. Returns {"state", "spec", "losses" (per step), "static", "time_s", "capacity"}.

    Args:
        cfg: the run config.
        scene: training `Scene`.
        out_dir: run folder for checkpoints and the effective config (None: nothing written).
        test_scene: optional held-out `Scene` for periodic evaluation.
        resume: continue from out_dir/checkpoint.npz.
        stop_at: stop (and checkpoint) after this step, as if interrupted (tests).
        devices: devices of the data-parallel mesh over cameras (default all; used when there are >= 2
            and train.batch_size is a multiple of their number).
        flows: observed optical flow into each frame from its predecessor in time, [T, H, W, 2] on the
            predecessor's grid (NaN = unknown), for the flow loss (flow.enabled and flow.weight > 0);
            None: estimated with ``flow.method`` (cached under out_dir/flow_cache).
        monitor: called as monitor(step, state, spec) every ``train.log_every`` steps and at the end (after the
            losses are synced); it must not modify the state (`fgjax bench motion --train` records the learned
            motion with it).
    """
    validate_stage1(cfg)  # a Config built in code has not been through load_config's checks
    out = None if out_dir is None else Path(out_dir)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write(out / "config.toml", lambda f: f.write(to_toml(cfg).encode()))
    state, spec, ospec = initial_state(cfg, scene, log=log, cache_dir=None if out is None else out / "flow_cache")
    if resume:
        if out is None or not (out / ckpt.CHECKPOINT_NAME).exists():
            raise FileNotFoundError(f"--resume: no checkpoint at {out}/{ckpt.CHECKPOINT_NAME}")
        state = ckpt.load_checkpoint(out / ckpt.CHECKPOINT_NAME, state)
        if state.step > cfg.train.steps:
            raise ValueError(f"--resume: {out / ckpt.CHECKPOINT_NAME} is at step {state.step}, beyond "
                             f"train.steps={cfg.train.steps}; resume with at least that many steps")
        log(f"resumed from step {state.step}")
    t = cfg.train
    w, h = scene.width, scene.height
    images = scene.images.astype(np.float32)
    viewmats = scene.viewmats.astype(np.float32)
    Ks = scene.Ks.astype(np.float32)
    times = scene.times.astype(np.float32)
    if state.capacity == 0 and t.tile_capacity > 0:
        state.capacity = t.tile_capacity
    if state.capacity == 0:
        state.capacity = compute_capacity(state.params, state.densify.alive, viewmats, Ks, w, h, t.tile_size,
                                           t.capacity_margin)
    batch_sh, repl_sh = _mesh_shardings(t.batch_size, devices)
    if batch_sh is not None:
        state.params, state.opt_state, state.densify = jax.device_put(
            (state.params, state.opt_state, state.densify), repl_sh)
    steps_cache: dict[StepSpec, Any] = {}
    fc = cfg.flow
    use_flow = fc.enabled and fc.weight > 0
    prev = previous_frames(times)
    if use_flow and fc.loss == "track":
        if flows is not None:
            raise ValueError("train_stage1(flows=...) is the pair loss's input; "
                             "flow.loss = 'track' makes its own tracks")
        prev, flows = training_tracks(scene, fc.method, None if out is None else out / "flow_cache", log=log)
    elif use_flow and flows is None:
        flows = estimate_training_flows(scene, fc.method, None if out is None else out / "flow_cache", log=log)
    depths = depths_lo = None
    if t.depth_weight > 0 and scene.depths is None:
        log(f"train.depth_weight = {t.depth_weight}: the scene has no depth maps; training without the depth term")
    elif t.depth_weight > 0:
        depths = np.where(np.isfinite(scene.depths) & (scene.depths > 0), scene.depths, 0.0).astype(np.float32)
    if use_flow:
        flows = np.asarray(flows, np.float32)
        if flows.shape != (scene.num_frames, h, w, 2):
            raise ValueError(f"flows must have shape [{scene.num_frames}, {h}, {w}, 2]; got {list(flows.shape)}")

    # coarse-to-fine: the first `train.coarse_to_fine` steps see 2x2-averaged images and halved intrinsics
    # (pixel centres at +0.5 map exactly: new pixel j covers old pixels 2j, 2j + 1)
    w2, h2 = w // 2, h // 2
    coarse = t.coarse_to_fine > 0 and w2 >= 8 and h2 >= 8
    if coarse:
        images_lo = images[:, :2 * h2, :2 * w2].reshape(-1, h2, 2, w2, 2, 3).mean(axis=(2, 4))
        Ks_lo = (Ks * np.array([0.5, 0.5, 1.0], np.float32)[:, None]).astype(np.float32)  # rows fx, fy halved
        if depths is not None:  # a coarse pixel has a depth where all four of its pixels have one
            d4 = depths[:, :2 * h2, :2 * w2].reshape(-1, h2, 2, w2, 2)
            depths_lo = np.where(np.all(d4 > 0, axis=(2, 4)), d4.mean(axis=(2, 4)), 0.0).astype(np.float32)
    elif t.coarse_to_fine > 0:
        log(f"coarse-to-fine skipped: {w}x{h} images are too small to halve")

    def get_step(use_deform: bool, sh_deg: int, flow_on: bool = False, lo: bool = False, freeze: bool = False,
                 hold: bool = False, photo: float = 1.0):  # photo: the photometric share of the motion
        sw, sh_ = (w2, h2) if lo else (w, h)
        ss = StepSpec(spec if use_deform else None, sh_deg, sw, sh_, state.capacity, t.tile_size, t.lambda_dssim,
                      t.scale_reg, t.scale_reg_max, "pose" in state.params,
                      fc.weight if flow_on else 0.0, fc.threshold if flow_on else 0.0,
                      t.rigid_weight if use_deform else 0.0, t.rigid_scale_weight if use_deform else 0.0,
                      t.rigid_cap if use_deform else 0.0, freeze, batch_sh is not None,
                      photo if flow_on else 1.0, fc.loss, fc.gaussian_flow, fc.camera_depth,
                      t.depth_weight if depths is not None else 0.0, fc.norm, fc.charbonnier_px, hold,
                      cfg.deform.gauge if use_deform and state.static_points is not None else 0.0)
        if ss not in steps_cache:
            steps_cache[ss] = make_step(ss, ospec, state.params["gaussians"].sh.shape[1], tuple(cfg.model.background))
        return steps_cache[ss]

    d = cfg.densify
    extent = ospec.scene_extent
    n_frames = scene.num_frames
    losses: list[float] = []
    pending: list[tuple[Any, Any, Any]] = []
    end = t.steps if stop_at is None else min(int(stop_at), t.steps)
    t_start = time.time()
    cpu_start = time.process_time()
    t_last, s_last = t_start, state.step
    warned_full = False
    metrics_hist = []
    graph = None  # (indices [N, k], weights [N, k]) for the isometry regulariser

    def flush():
        """Bring the pending steps' losses to the host (one sync)."""
        nonlocal pending
        vals = jax.device_get(pending)
        pending = []
        losses.extend(float(l) for l, _, _, _ in vals)
        return vals

    placed = _bases_placed(cfg)
    pts = None if state.static_points is None else jax.device_put(state.static_points, repl_sh)  # the step's copy
    while state.step < end:
        s = state.step
        if state.static is None and s >= t.warmup_steps:
            if cfg.static.detect:
                state.static, score = detect_static(state.params, state.densify.alive, scene, cfg, state.capacity,
                                                     None if out is None else out / "flow_cache")
                log(f"static-scene check after warm-up: score {score:.4f} (threshold {cfg.static.threshold}) -> "
                    + ("static: training without the deformation field" if state.static else "dynamic"))
            else:
                state.static = False
        if s == t.warmup_steps and not state.static and placed:
            state.params, labels = place_bases(cfg, state.params, state.densify.alive, spec, scene,
                                               flows if use_flow and fc.loss == "pair" else None,
                                               capacity=state.capacity,
                                               cache_dir=None if out is None else out / "flow_cache", log=log)
            if state.static_points is not None:
                state.static_points = static_points(state.params["gaussians"].means, labels,
                                                    len(state.static_points), cfg.model.seed)
                pts = jax.device_put(state.static_points, repl_sh)
            if repl_sh is not None:  # the new logits network, replicated like the rest of the parameters
                state.params = jax.device_put(state.params, repl_sh)
        use_deform = s >= t.warmup_steps and not bool(state.static)
        lo = coarse and s < t.coarse_to_fine
        flow_on = use_flow and use_deform and s >= fc.start and not lo
        freeze = use_deform and s < t.warmup_steps + t.field_only_steps
        hold = use_deform and placed and s < t.warmup_steps + cfg.deform.hold  # placed weights stay, motions fit
        photo = fc.photo_motion if s >= fc.photo_motion_start else 0.0  # flow.photo_motion_start
        step_fn = get_step(use_deform, cfg.model.sh_degree, flow_on, lo, freeze, hold, photo)
        sh_mask = active_sh_mask(active_sh_degree(s, t.sh_increase_every, cfg.model.sh_degree), cfg.model.sh_degree)
        window = (time_window(s, times, t.warmup_steps, t.time_curriculum, t.time_window_start)
                  if t.time_curriculum > 0 else None)
        idx = batch_indices(cfg.model.seed, s, n_frames, t.batch_size, window, state.frame_err, t.error_sampling)
        batch = ((images_lo if lo else images)[idx], viewmats[idx], (Ks_lo if lo else Ks)[idx], times[idx],
                 idx.astype(np.int32))
        if flow_on:
            batch = (*batch, _flow_batch(idx, prev, flows, viewmats, times, Ks))
        dbatch = None if depths is None else (depths_lo if lo else depths)[idx]
        if batch_sh is not None:
            batch, dbatch = jax.device_put((batch, dbatch), batch_sh)
        nbr = None
        if use_deform and t.rigid_weight > 0:
            if graph is None:  # the canonical neighbour graph, rebuilt when densification changes the set
                graph = knn_graph(state.params["gaussians"].means, state.densify.alive, t.rigid_neighbours)
                if repl_sh is not None:
                    graph = jax.device_put(graph, repl_sh)
            nbr = graph
        state.params, state.opt_state, state.densify, loss, mse, bad = step_fn(
            state.params, state.opt_state, state.densify, sh_mask, *batch, nbr=nbr, depths=dbatch,
            pts=pts)
        pending.append((loss, mse, bad, idx))
        if state.frame_err is not None:  # error sampling: the next step's draw needs this one's error (a sync)
            m_host, bad_host = jax.device_get((mse, bad))
            if not bool(bad_host):
                state.frame_err[idx] = np.asarray(m_host, np.float32)
        state.step += 1
        s1 = state.step
        if d.enabled and d.start < s1 <= d.stop and s1 % d.every == 0 and not freeze:
            g, state.opt_state, state.densify, n_alive = densify_apply(
                state.params["gaussians"], state.opt_state, state.densify, jax.random.fold_in(state.key, s1),
                grad_threshold=d.grad_threshold, clone_max_scale=d.percent_dense * extent,
                prune_opacity=d.prune_opacity,
                # 3DGS prunes oversized Gaussians only once opacity resets have started
                prune_max_scale=d.max_world_scale * extent if 0 < d.reset_every < s1 else 1e9,
            )
            # per-slot weights ("slot" bases) follow their Gaussians
            state.params = {**state.params, "gaussians": g,
                            "deform": dens.follow_parents(state.params["deform"], state.densify)}
            graph = None
            if bool(state.densify.full) and not warned_full:
                warned_full = True
                log(f"densify: capacity reached ({g.means.shape[0]} Gaussian slots all in use); "
                    "raise model.capacity to allow more growth (further densification only re-uses pruned slots)")
            _maybe_grow_capacity(state, viewmats, Ks, w, h, t, log)
        if d.enabled and d.reset_every > 0 and s1 % d.reset_every == 0 and s1 < d.stop:
            g, state.opt_state = opacity_reset(state.params["gaussians"], state.opt_state)
            state.params = {**state.params, "gaussians": g}
        if s1 % t.log_every == 0 or s1 == end:
            vals = flush()
            n_bad = sum(bool(b) for _, _, b, _ in vals)
            if n_bad:
                log(f"warning: {n_bad} step(s) before step {s1} overflowed the tile capacity {state.capacity} "
                    "or had a non-finite loss and were skipped; recomputing the capacity")
                _maybe_grow_capacity(state, viewmats, Ks, w, h, t, log, force=True)
            now = time.time()
            rate = (s1 - s_last) / max(now - t_last, 1e-9)
            t_last, s_last = now, s1
            mse_mean = float(np.mean([float(np.mean(m)) for _, m, _, _ in vals])) if vals else float("nan")
            eta = (end - s1) / max(rate, 1e-9)
            if progress:
                log(f"step {s1:>6}/{t.steps}  {rate:6.1f} it/s  loss {float(vals[-1][0]):.4f}  "
                    f"PSNR {10 * math.log10(1.0 / max(mse_mean, 1e-12)):5.2f}  "
                    f"alive {int(jnp.sum(state.densify.alive))}  ETA {eta:6.0f} s")
            if monitor is not None:
                monitor(s1, state, spec)
        if test_scene is not None and t.eval_every and s1 % t.eval_every == 0:
            m = evaluate(state, spec, cfg, test_scene)
            metrics_hist.append({"step": s1, "time_s": time.time() - t_start,
                                 "cpu_s": time.process_time() - cpu_start, **m})
            log(f"eval step {s1}: PSNR {m['psnr']:.2f} SSIM {m['ssim']:.4f} ({time.time() - t_start:.0f} s)")
        if out is not None and t.checkpoint_every and s1 % t.checkpoint_every == 0 and s1 < end:
            ckpt.save_checkpoint(out / ckpt.CHECKPOINT_NAME, state, config_toml=to_toml(cfg))
    flush()
    if out is not None:
        ckpt.save_checkpoint(out / ckpt.CHECKPOINT_NAME, state, config_toml=to_toml(cfg))
        meta = {"deform_spec": dataclasses.asdict(spec), "static": bool(state.static), "step": state.step,
                "capacity": state.capacity, "width": w, "height": h, "num_frames": n_frames,
                "normalization": scene.normalization.to_dict(), "scene_extent": extent}
        (out / "model.json").write_text(json.dumps(meta, indent=1))
    return {"state": state, "spec": spec, "losses": losses, "static": state.static,
            "time_s": time.time() - t_start, "cpu_s": time.process_time() - cpu_start, "capacity": state.capacity,
            "eval_history": metrics_hist}


def active_sh_mask(active: int, max_degree: int) -> jax.Array:
    k = (max_degree + 1) ** 2
    return (jnp.arange(k) < (active + 1) ** 2).astype(jnp.float32)


def _maybe_grow_capacity(state: TrainState, viewmats, Ks, w, h, t, log, force: bool = False) -> None:
    need = compute_capacity(state.params, state.densify.alive, viewmats, Ks, w, h, t.tile_size, t.capacity_margin)
    if force:
        need = max(need, int(state.capacity * 1.5))
    if need > state.capacity:
        log(f"tile capacity {state.capacity} -> {need} (recompiling the step)")
        state.capacity = need


# ---------------------------------------------------------------------------------------------
# evaluation and outputs
# ---------------------------------------------------------------------------------------------


def render_frame(state: TrainState, spec: DeformSpec, cfg: Config, viewmat, K, t, width, height, depth=False):
    """Render the trained model (deformation unless the scene is static) at time t: image [H, W, 3] numpy; with
    `depth`, (image, expected depth [H, W], alpha [H, W]).

    Runs outside jit so that the rasterizer sizes its intersection buffer exactly (no overflow)."""
    use = None if state.static else spec
    img, alpha, info, _ = render_params(state.params, state.densify.alive, jnp.asarray(viewmat, jnp.float32),
                                        jnp.asarray(K, jnp.float32), jnp.asarray(t, jnp.float32), spec=use,
                                        sh_degree=cfg.model.sh_degree, width=int(width), height=int(height),
                                        background=jnp.asarray(cfg.model.background, jnp.float32), capacity=None,
                                        tile_size=cfg.train.tile_size, render_depth=depth)
    img = np.clip(np.asarray(img), 0.0, 1.0)
    return (img, np.asarray(info["depth"]), np.asarray(alpha)) if depth else img


def evaluate(state: TrainState, spec, cfg: Config, test_scene, masks=None, out_dir: Path | None = None,
             names=None) -> dict[str, Any]:
    """PSNR, SSIM (and masked PSNR of the dynamic region where masks exist) over the test views; where they have a
    measured depth, "depth_error": |expected depth - measured| / measured on their pixels with one that the model
    covers (alpha >= 0.5), median and mean, and the median in world units."""
    ps, ss, mps, rel, absw = [], [], [], [], []
    has_depth = test_scene.depths is not None
    for i in range(test_scene.num_frames):
        img = render_frame(state, spec, cfg, test_scene.viewmats[i], test_scene.Ks[i], test_scene.times[i],
                           test_scene.width, test_scene.height, depth=has_depth)
        if has_depth:
            img, d, alpha = img
            ref = test_scene.depths[i]
            ok = (ref > 0) & (alpha >= 0.5)
            rel.append(np.abs(d[ok] - ref[ok]) / ref[ok])
            absw.append(test_scene.normalization.lengths_to_world(np.abs(d[ok] - ref[ok])))
        gt = test_scene.images[i]
        ps.append(float(metrics.psnr(img, gt)))
        ss.append(float(metrics.ssim(img, gt)))
        if masks is not None and np.any(masks[i]):
            mps.append(float(metrics.masked_psnr(img, gt, masks[i])))
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            name = (names[i] if names else f"{i:03d}").replace("/", "_")
            iio.imwrite(out_dir / f"{name}.png", (img * 255 + 0.5).astype(np.uint8))
    res: dict[str, Any] = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "per_view_psnr": ps,
                           "num_views": len(ps)}
    if mps:
        res["masked_psnr_dynamic"] = float(np.mean(mps))
    if rel and sum(map(len, rel)):
        r = np.concatenate(rel)
        res["depth_error"] = {"median_relative": float(np.median(r)), "mean_relative": float(np.mean(r)),
                              "median": float(np.median(np.concatenate(absw))), "pixels": int(len(r))}
    return res


def write_video(state, spec, cfg: Config, scene, path: Path, frames: int) -> Path:
    """Time sweep t = 0..1 from the first training camera, as mp4 (GIF without ffmpeg; `fgjax.io.write_video`)."""
    imgs = [(render_frame(state, spec, cfg, scene.viewmats[0], scene.Ks[0], t, scene.width, scene.height) * 255
             + 0.5).astype(np.uint8) for t in np.linspace(0, 1, frames)]
    return write_frames(imgs, path, fps=15)


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------


def prepare_run_folder(out: Path, data_dir: Path, *, resume: bool = False, overwrite: bool = False) -> None:
    """Check that stage 1 may write the run folder ``out`` for the data in ``data_dir``, and clear it with
    ``overwrite``. A new run needs a missing or empty folder; an existing run is continued with ``resume`` (only on
    the data it was trained on, by `fgjax.provenance.scene_fingerprint`) or replaced whole with ``overwrite`` (its
    stage-2 results too). A folder that holds only a flow cache (``flow_cache/``, filled before training) counts as
    empty. Raises ValueError naming the folder and what to pass otherwise."""
    out, data_dir = Path(out), Path(data_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a folder")
    is_run = any((out / n).exists() for n in ("config.toml", "model.json", ckpt.CHECKPOINT_NAME, PROVENANCE_NAME))
    if resume:
        rec = read_provenance(out)
        if rec is not None and rec.get("data_fingerprint") not in (None, scene_fingerprint(data_dir)):
            raise ValueError(f"--resume: {out} was trained on {rec.get('data_dir')}, whose data differ from "
                             f"{data_dir}; resume it on its own data or train a new run")
        return
    if is_run and not overwrite:
        raise ValueError(f"{out} holds a trained run; pass --resume to continue it or --overwrite to replace it "
                         "(its stage-2 results too)")
    if is_run:
        shutil.rmtree(out)
    elif out.is_dir() and any(p.name != "flow_cache" for p in out.iterdir()):
        raise ValueError(f"--out {out} is a folder that is not empty and holds no run; choose another --out")


def run(cfg: Config, data_dir: Path, out: Path, resume: bool = False, log=print, *,
        overwrite: bool = False, monitor=None) -> dict[str, Any]:
    """Load, train, evaluate and write RUN/{config.toml, checkpoint.npz, metrics.json, provenance.json, test/*.png,
    sweep.mp4}; ``monitor`` as in `train_stage1`. The folder must be new or empty, or hold a run to continue
    (``resume``) or replace (``overwrite``): `prepare_run_folder`."""
    out, data_dir = Path(out), Path(data_dir)
    prepare_run_folder(out, data_dir, resume=resume, overwrite=overwrite)
    scene = load_scene(data_dir, "train", downscale=cfg.data.downscale)
    test, masks, names = load_test_views(data_dir, cfg, scene.normalization)
    log(f"train: {scene.num_frames} frames {scene.width}x{scene.height}; "
        f"test: {0 if test is None else test.num_frames} views")
    res = train_stage1(cfg, scene, out, test_scene=test, resume=resume, log=log, monitor=monitor)
    metrics: dict[str, Any] = {"train_time_s": res["time_s"], "steps": cfg.train.steps, "static": bool(res["static"]),
                               "num_gaussians": int(jnp.sum(res["state"].densify.alive)),
                               "eval_history": res["eval_history"]}
    if test is not None and test.num_frames:
        m = evaluate(res["state"], res["spec"], cfg, test, masks, out / "test", names)
        metrics.update(m)
        log(f"test views: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}"
            + (f", dynamic-region PSNR {m['masked_psnr_dynamic']:.2f} dB" if "masked_psnr_dynamic" in m else "")
            + (f", depth error {100 * m['depth_error']['median_relative']:.1f}% (median)"
               if "depth_error" in m else ""))
    atomic_write(out / "metrics.json", lambda f: f.write(json.dumps(metrics, indent=1).encode()))
    if cfg.train.video_frames > 0:
        v = write_video(res["state"], res["spec"], cfg, scene, out / "sweep.mp4", cfg.train.video_frames)
        log(f"time sweep: {v}")
    write_provenance(out, data_dir, out / ckpt.CHECKPOINT_NAME, int(res["state"].step), __version__)
    return {**res, "metrics": metrics}

