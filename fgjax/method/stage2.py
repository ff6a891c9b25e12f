"""Stage 2, the paper's chain (DESIGN.md section 1, steps 5-7): discovery -> DBSCAN -> trajectories -> control network.

Library entry point: ``run_stage2(run_dir, data_dir, cfg)`` writes RUN/stage2.npz and RUN/stage2.json
(`fgjax.method.result`). The chain never reads ground truth (no ``gt/``): only the training images, poses and times.

1. **Discovery** (`discover_run`, on `fgjax.method.discover`): |u - u_cam| per training pair, binarised and
   back-projected through the rasterizer's contribution weights; D is Otsu's cut of the per-Gaussian scores.
2. **Clustering** (`select_objects`): DBSCAN (or HDBSCAN) on the canonical centres of D; clusters under
   ``min_fraction`` of D are dropped; the rest are numbered by decreasing size.
3. **Trajectories** ς(t, k): the mean deformed centre of cluster k at each training time (time order), from the
   stage-1 deformation field. The reference time t0 is the first training time; v_c(t, k) = ς(t, k) - ς(t0, k).
4. **Control network** (`fgjax.method.control.train_control`): distilled from the deformed geometry, then fine-tuned
   photometrically with beta L_uGS.

The articulated variant (`fgjax.articulate.run_articulated`) composes the same pieces with rigid tracking in
between; `prepare_run`, `select_objects`, `deformed_geometry` and `finish` are shared.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, Int

from fgjax import cluster
from fgjax.config import Stage2Config, validate_stage2
from fgjax.data.loaders import load_scene
from fgjax.data.opticalflow import estimate_flow, forward_backward_mask
from fgjax.data.scene import Normalization, Scene
from fgjax.gaussians import activate
from fgjax.geometry import viewmat_to_c2w
from fgjax.method.camera import camera_correction
from fgjax.method.control import train_control
from fgjax.method.discover import (
    Discovery,
    Reference,
    agreement,
    camera_flow_from_depth,
    discover,
    nearest_on_segment,
)
from fgjax.method.flows import training_tracks
from fgjax.method.result import (
    FORMAT_VERSION,
    STAGE2_NAME,
    LoadedRun,
    Stage2Error,
    Stage2Result,
    load_stage2,
    render_capacity,
    save_stage2,
    with_geometry,
)
from fgjax.models.model import refined_viewmats
from fgjax.provenance import file_sha256, read_provenance, scene_fingerprint
from fgjax.render.api import rasterization
from fgjax.train.checkpoint import CHECKPOINT_NAME
from fgjax.viz import to_u8

__all__ = ["run_stage2", "prepare_run", "discover_run", "select_objects", "deformed_geometry", "finish"]


def prepare_run(run_dir: Path, data_dir: Path, log=print) -> tuple[LoadedRun, Scene, str]:
    """The stage-1 run (without stage-2 results), its training scene, normalised as the run was (the cameras
    replaced by stage 1's refined ones where it refined them), and the data's `fgjax.provenance.scene_fingerprint`.

    Raises:
        Stage2Error: the data are not those the run's provenance records, the images' size differs from the run's,
            or fewer than 2 training frames.
    """
    run = load_stage2(run_dir, require_stage2=False)
    rec = read_provenance(run_dir)
    fingerprint = scene_fingerprint(data_dir)
    if rec is not None and rec.get("data_fingerprint") not in (None, fingerprint):
        raise Stage2Error(f"{data_dir} is not the data {run_dir} was trained on ({rec.get('data_dir')}): their files "
                          "differ; run stage 2 on the run's own data")
    scene = load_scene(data_dir, "train", normalize=Normalization.from_dict(run.meta["normalization"]),
                       downscale=run.cfg.data.downscale)
    if (scene.width, scene.height) != (run.meta["width"], run.meta["height"]):
        raise Stage2Error(f"{data_dir}: images are {scene.width}x{scene.height} but the run was trained on "
                          f"{run.meta['width']}x{run.meta['height']}")
    if scene.num_frames < 2:
        raise Stage2Error(f"{data_dir}: stage 2 needs at least 2 training frames, got {scene.num_frames}")
    if "pose" in run.state.params:  # discovery's u_cam and the tracking need the cameras stage 1 refined
        try:
            vms = refined_viewmats(run.state.params, scene.viewmats)
        except ValueError as e:
            raise Stage2Error(f"{data_dir}: {e}") from None
        scene = dataclasses.replace(scene, viewmats=vms.astype(scene.viewmats.dtype))
        log("stage 2: using stage 1's refined camera poses")
    return run, scene, fingerprint


def discover_run(run: LoadedRun, scene: Scene, cfg: Stage2Config, cache_dir: Path, *, per_frame: bool = False,
                 log=print):
    """Step 5 on a stage-1 run (`discover` on every training pair in time order).

    For each pair (t-1, t): the stage-1 Gaussians deformed to time t-1 are rendered from camera t-1 for their
    expected depth (and, with ``cfg.agree_sigma`` > 0, their colours, whose agreement with image t-1 weights each
    pixel of the back-projection: `fgjax.method.discover.agreement`); the camera flow is `camera_flow_from_depth` of
    that depth (with ``cfg.camera_correction``, camera t's pose first corrected from the static flow,
    `fgjax.method.camera.camera_correction`; with ``cfg.depth_tolerance`` delta > 0, the camera flow of the depth
    in Z / (1 + delta) .. Z (1 + delta) nearest the optical flow, `fgjax.method.discover.nearest_on_segment`); the
    optical flow t-1 -> t comes from `fgjax.data.opticalflow.estimate_flow` (cached in ``cache_dir``; with
    ``cfg.fb_px`` > 0 the pixels whose flow fails the round trip through the flow t -> t-1 are left out). With
    ``cfg.backproject = "track"`` the moving pixels that the first frame's tracks reach (`fgjax.method.flows.
    training_tracks`, on the same cached flows) are back-projected onto the Gaussians at the first time, from the
    first camera (`fgjax.method.discover.Reference`).

    Returns:
        (`Discovery` with D restricted to alive Gaussians, deformed centres [T, N, 3] in time order, times [T],
        (order [T] of the training frames by time, flows [T-1, H, W, 2], camera flows [T-1, H, W, 2])).
        ``per_frame``: keep the per-pair score terms (`Scores`), which the articulated variant reads.
    """

    order = np.argsort(scene.times, kind="stable")
    times = scene.times[order]
    alive = run.state.densify.alive
    w, h = scene.width, scene.height
    means_t, quats_t, centres = [], [], []
    depths, alphas, agree = [], [], []
    g = run.state.params["gaussians"]
    for i in order:
        m, q, ls = run.deformed(float(scene.times[i]))
        centres.append(np.asarray(m))
        params = with_geometry(run.state.params, m, q, ls)
        qa, sa, oa = activate(params["gaussians"], alive)
        means_t.append(np.asarray(m))
        quats_t.append(np.asarray(qa))
        _, alpha, info = rasterization(m, qa, sa, oa, jnp.zeros((m.shape[0], 1), jnp.float32),
                                       jnp.asarray(scene.viewmats[i], jnp.float32),
                                       jnp.asarray(scene.Ks[i], jnp.float32), w, h, render_depth=True,
                                       tile_size=run.cfg.train.tile_size)
        depths.append(np.asarray(info["depth"]))
        alphas.append(np.asarray(alpha))
        if cfg.agree_sigma > 0:
            img, _, _ = run.render_geometry(m, q, ls, scene.viewmats[i], scene.Ks[i], w, h,
                                            capacity=render_capacity(run))
            agree.append(agreement(np.asarray(img), np.asarray(scene.images[i], np.float32), cfg.agree_sigma))
    _, sa, oa = activate(g, alive)
    c2w = viewmat_to_c2w(scene.viewmats[order])
    flows, cams, valid = [], [], []
    correct = cfg.camera_correction == "on" or (cfg.camera_correction == "auto" and "pose" in run.state.params)
    rms_all: list[float] = []
    t_flow = time.perf_counter()
    for j in range(len(order) - 1):
        a, b = order[j], order[j + 1]
        flows.append(estimate_flow(to_u8(scene.images[a]), to_u8(scene.images[b]), cfg.flow_method,
                                   cache_dir=cache_dir))
        trusted = alphas[j] >= cfg.min_alpha  # pixels with a rendered depth to trust
        if cfg.fb_px > 0:  # and a flow that the backward flow confirms
            back = estimate_flow(to_u8(scene.images[b]), to_u8(scene.images[a]), cfg.flow_method, cache_dir=cache_dir)
            trusted = trusted & forward_backward_mask(flows[-1], back, alpha=0.0, beta=cfg.fb_px ** 2)
        c2w_b = c2w[j + 1]
        if correct:
            vm_b, rms, _ = camera_correction(depths[j], trusted, flows[-1], scene.viewmats[a], scene.viewmats[b],
                                             scene.Ks[a])
            c2w_b = viewmat_to_c2w(vm_b[None])[0]
            rms_all.append(rms)
        if cfg.depth_tolerance > 0:  # u_cam: the camera flow of the depth in Z / (1 + delta) .. Z (1 + delta) nearest u
            grow = 1.0 + cfg.depth_tolerance
            near, ok_n = camera_flow_from_depth(depths[j] / grow, scene.Ks[a], c2w[j], c2w_b)
            far, ok_f = camera_flow_from_depth(depths[j] * grow, scene.Ks[a], c2w[j], c2w_b)
            # Z lies between both ends on its ray, so it is valid (positive, in front of camera t) where both are
            cf, ok = nearest_on_segment(flows[-1], near, far).astype(np.float32), ok_n & ok_f
        else:
            cf, ok = camera_flow_from_depth(depths[j], scene.Ks[a], c2w[j], c2w_b)
        cams.append(cf)
        valid.append(ok & trusted)
    log(f"stage 2: optical flow of {len(flows)} pairs ({time.perf_counter() - t_flow:.1f} s)"
        + (f"; camera poses corrected from the static flow (median inlier RMS {np.nanmedian(rms_all):.2f} px)"
           if correct and rms_all and np.any(np.isfinite(rms_all)) else ""))
    n = len(order) - 1
    thr = cfg.threshold_px if cfg.threshold_px == "otsu" else float(cfg.threshold_px)
    # the deformed scales differ from canonical ones only by ds; discovery uses the canonical ones
    reference = None
    if cfg.backproject == "track":
        tracks = training_tracks(scene, cfg.flow_method, cache_dir=cache_dir, log=log)[1][order]  # time order
        reference = Reference(tracks, means_t[0], quats_t[0], scene.viewmats[order[0]], scene.Ks[order[0]])
    disc = discover(np.stack(means_t[:n]), np.stack(quats_t[:n]), np.asarray(sa), np.asarray(oa),
                    scene.viewmats[order][:n], scene.Ks[order][:n], np.stack(flows), np.stack(cams),
                    valid=np.stack(valid), threshold_px=thr, min_px=cfg.min_px, noise_sigmas=cfg.threshold_sigmas,
                    score_threshold=cfg.score_threshold, min_score=cfg.min_score, per_frame=per_frame,
                    confidence=np.stack(agree[:n]) if agree else None, reference=reference)
    dyn = disc.dynamic & np.asarray(alive)
    return disc._replace(dynamic=dyn), np.stack(centres), times, (order, np.stack(flows), np.stack(cams))


def select_objects(canonical: Float[np.ndarray, "N 3"], disc: Discovery, cfg: Stage2Config, *,
                   log=print) -> tuple[Int[np.ndarray, " N"], cluster.ClusterReport]:
    """Step 6: DBSCAN (or HDBSCAN, ``cfg.cluster_method``) on the canonical centres of D, the size cut
    (``cfg.min_fraction`` of D). Returns (labels [N] in -1..K-1, largest cluster first; the cluster report)."""
    idx = np.flatnonzero(disc.dynamic)
    lab_d = cluster.cluster_dynamic(canonical[idx], cfg.cluster_method, eps=cfg.eps, min_samples=cfg.min_samples,
                                    min_fraction=cfg.min_fraction, auto_eps=cfg.auto_eps)
    labels = np.full(len(canonical), -1, np.int64)
    labels[idx] = lab_d
    report = cluster.cluster_report(lab_d)
    log(f"stage 2: {len(idx)} dynamic Gaussians (score threshold {disc.threshold:.3f}); {report}")
    return labels, report


def deformed_geometry(run: LoadedRun, times: Float[np.ndarray, " T"]
                      ) -> tuple[Float[np.ndarray, "T N 4"], Float[np.ndarray, "T N 3"]]:
    """(raw quats [T, N, 4], log-scales [T, N, 3]) of the stage-1 model at each of ``times``."""
    qs, ls = [], []
    for t in times:
        _, q, s = run.deformed(float(t))
        qs.append(np.asarray(q))
        ls.append(np.asarray(s))
    return np.stack(qs), np.stack(ls)


def finish(run_dir: Path, data_dir: Path, run: LoadedRun, scene: Scene, order: Int[np.ndarray, " T"],
           labels: Int[np.ndarray, " N"], dynamic: Bool[np.ndarray, " N"], disc: Discovery, geometry, flows,
           cfg: Stage2Config, meta: dict[str, Any], t_start: float, *, refit=None, log=print) -> Stage2Result:
    """Steps 3-4 and the result: trajectories ς(t, k) from ``geometry`` (means [T, N, 3], raw quats [T, N, 4],
    log-scales [T, N, 3] in time order), the control network trained on them, RUN/stage2.npz written. ``meta`` (the
    caller's entries: its variant, the data fingerprint of `prepare_run`, ...) joins the result's metadata."""
    report = cluster.cluster_report(labels[dynamic | (labels >= 0)])
    times = scene.times[order]
    centres = geometry[0]
    traj = cluster.trajectories(centres, labels) if report.n_clusters else np.zeros((0, len(times), 3))
    control, stats = train_control(run, scene, order, labels, traj, cfg, geometry, flows, log, refit=refit)
    meta = {
        "format_version": FORMAT_VERSION,
        "data_dir": str(data_dir.resolve()),
        "config": dataclasses.asdict(cfg),
        "num_dynamic": int(disc.dynamic.sum()),
        "score_threshold": disc.threshold,
        "num_objects": report.n_clusters,
        "cluster_sizes": list(report.sizes),
        "num_noise": report.n_noise,
        "moving_pixel_fraction": float(disc.masks.mean()),
        "flow_loss": bool(stats.get("photometric", {}).get("flow_weight", 0.0) > 0),
        "stage1_checkpoint": {"step": int(run.state.step), "sha256": file_sha256(run_dir / CHECKPOINT_NAME)},
        **meta,
        "time_s": time.perf_counter() - t_start,
        **stats,
    }
    res = Stage2Result(labels, dynamic, disc.scores.score, traj, times, control, meta, refit)
    save_stage2(run_dir, res)
    log(f"stage 2: wrote {run_dir / STAGE2_NAME} ({meta['time_s']:.1f} s)")
    return res


def run_stage2(run_dir: str | Path, data_dir: str | Path, cfg: Stage2Config = Stage2Config(), *,
               log=print) -> Stage2Result:
    """The paper's stage 2 on a trained stage-1 run; writes RUN/stage2.npz and RUN/stage2.json.

    Args:
        run_dir: stage-1 run folder (`fgjax train`).
        data_dir: the dataset the run was trained on (only the training split is read; never gt/).
        cfg: `Stage2Config` (``cfg.variant`` is not read here: this is the paper's chain).

    Returns:
        `Stage2Result`.
    """
    validate_stage2(cfg)  # before any work is done
    t_start = time.perf_counter()
    run_dir, data_dir = Path(run_dir), Path(data_dir)
    run, scene, fingerprint = prepare_run(run_dir, data_dir, log)
    cache = Path(cfg.flow_cache) if cfg.flow_cache else run_dir / "flow_cache"
    disc, centres, times, (order, flows, _) = discover_run(run, scene, cfg, cache, log=log)
    labels, _ = select_objects(np.asarray(run.state.params["gaussians"].means), disc, cfg, log=log)
    qs, ls = deformed_geometry(run, times)
    return finish(run_dir, data_dir, run, scene, order, labels, disc.dynamic, disc, (centres, qs, ls), flows, cfg,
                  {"variant": "paper", "data_fingerprint": fingerprint}, t_start, log=log)
