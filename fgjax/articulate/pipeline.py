"""The articulated variant of stage 2: the paper's discovery and control network with rigid part tracking between.

Movable parts are rigid bodies on revolute or prismatic joints. The paper's trajectories come from the stage-1
deformation field; here each part's motion is instead tracked in the training images (photometric tracking,
`fgjax.articulate.phototrack`, or flow-based, `fgjax.articulate.track`), fitted as one joint per part
(`fgjax.articulate.phototrack.joint_poses`), checked by the hinge trial (`fgjax.articulate.trial`), and the scene is
re-fitted under that motion (`fgjax.articulate.refit`) over a few rounds before the label passes
(`fgjax.articulate.labels`). Selected by ``[stage2] variant = "articulated"`` (experiments/articulated.toml).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
from jaxtyping import Bool, Float, Int

from fgjax import cluster
from fgjax.articulate.articulation import (
    LEVEL_AMBIGUITY,
    LEVEL_TILT_DEG,
    camera_tilt,
    camera_up,
    hinge_made_vertical,
)
from fgjax.articulate.labels import (
    drop_isolated,
    fade_dropped,
    fade_ghosts,
    fill_hinges,
    fill_hulls,
    joined,
    label_passes_on,
    posed_geometry,
    prune_seen_through,
    refine_by_colour,
    settle,
)
from fgjax.articulate.phototrack import (
    converged_joints,
    is_far_hinge,
    joint_poses,
    largest_turn_deg,
    track_photometric,
)
from fgjax.articulate.refit import refit_gaussians
from fgjax.articulate.track import field_poses, track_objects
from fgjax.articulate.trial import hinge_trial, trial_held
from fgjax.config import ArticulateConfig, Stage2Config, validate_articulate, validate_stage2
from fgjax.data.scene import Scene
from fgjax.gaussians import Gaussians, activate
from fgjax.method.discover import Discovery
from fgjax.method.result import LoadedRun, Stage2Result, reference_scene, render_capacity, with_geometry
from fgjax.method.stage2 import deformed_geometry, discover_run, finish, prepare_run

__all__ = ["run_articulated", "select_parts", "tracked_poses", "photometric_poses", "photo_level_steps",
           "label_passes"]


def select_parts(canonical: Float[np.ndarray, "N 3"], disc: Discovery, cfg: Stage2Config, acfg: ArticulateConfig,
                 candidates: Bool[np.ndarray, " N"], *, log=print, t_start: float | None = None):
    """Step 6 with motion: DBSCAN (or HDBSCAN) on the canonical centres [N, 3] of D (DBSCAN's neighbours gated by
    the correlation of their activity profiles, ``acfg.link_min_corr``, `fgjax.cluster.cluster_by_motion`),
    fragments whose motion profiles correlate merged (``acfg.merge_eps``), clusters whose members move at different
    times split (``acfg.split_motion``), a second selection pass in each cluster's own moving frames
    (``acfg.local_radius``; ``candidates`` [N] bool: the Gaussians it may join), and the size cut (after that pass
    with ``acfg.cut_after_local``). Returns (labels [N] in -1..K-1, largest first; `disc` with D widened by the joined
    Gaussians; `fgjax.cluster.cluster_report` of D's labels)."""
    t_start = time.perf_counter() if t_start is None else t_start
    n_dyn = int(disc.dynamic.sum())
    idx = np.flatnonzero(disc.dynamic)
    merge = acfg.merge_eps > 0 and disc.scores.moving_t is not None
    kw = dict(eps=cfg.eps, min_samples=cfg.min_samples, min_fraction=0.0 if merge else cfg.min_fraction,
              auto_eps=cfg.auto_eps)
    by_motion = acfg.link_min_corr > -1 and disc.scores.moving_t is not None and cfg.cluster_method == "dbscan"
    if by_motion:
        lab_d = cluster.cluster_by_motion(canonical[idx], disc.scores.moving_t[:, idx], disc.scores.total_t[:, idx],
                                          min_corr=acfg.link_min_corr, **kw)
    else:
        if acfg.link_min_corr > -1:
            log(f"stage 2: articulate.link_min_corr={acfg.link_min_corr:g} has no effect "
                + ("with cluster_method='hdbscan'" if cfg.cluster_method != "dbscan" else
                   "without per-frame discovery scores") + "; position alone")
        lab_d = cluster.cluster_dynamic(canonical[idx], cfg.cluster_method, **kw)
    cut_late = merge and acfg.cut_after_local and acfg.local_radius > 0
    if merge:  # fragments of one part first, then the size cut (late: only the floor now)
        lab_d = cluster.merge_fragments(canonical[idx], lab_d, disc.scores.moving_t[:, idx],
                                        disc.scores.total_t[:, idx], eps=acfg.merge_eps)
        frac = acfg.local_floor if cut_late else cfg.min_fraction
        lab_d = cluster.relabel_by_size(lab_d, min_size=cluster.size_cut(frac, len(idx)))
    labels = np.full(len(canonical), -1, np.int64)
    labels[idx] = lab_d
    report = cluster.cluster_report(lab_d)
    log(f"stage 2: {n_dyn} dynamic Gaussians (score threshold {disc.threshold:.3f}); {report} "
        f"({time.perf_counter() - t_start:.1f} s)")
    if acfg.split_motion and report.n_clusters:
        split = cluster.split_by_motion(canonical, labels, disc.scores.moving_t, disc.scores.total_t)
        new = cluster.cluster_report(split[split >= 0])
        if new.n_clusters != report.n_clusters:
            log(f"stage 2: split by the times their members move: {report.n_clusters} -> {new.n_clusters} "
                f"cluster(s), sizes {list(new.sizes)}")
        labels, report = split, cluster.cluster_report(split[disc.dynamic | (split >= 0)])
    if acfg.local_radius > 0 and report.n_clusters:
        dyn_before = disc.dynamic
        loc = cluster.localize_clusters(canonical, labels, disc.scores.moving_t, disc.scores.total_t,
                                        radius=acfg.local_radius, threshold=acfg.local_threshold,
                                        candidates=candidates)
        labels = loc.labels
        disc = disc._replace(dynamic=disc.dynamic | (labels >= 0))
        report = cluster.cluster_report(labels[disc.dynamic])
        log(f"stage 2: each cluster's moving frames {[int(f.sum()) for f in loc.frames]}; "
            f"{list(loc.joined)} Gaussians joined (score >= {acfg.local_threshold} in those frames within "
            f"{acfg.local_radius} of the cluster); sizes {list(report.sizes)}")
        if cut_late:
            cut = cluster.size_cut(acfg.local_min_fraction, int(np.sum(labels >= 0)))
            labels = cluster.relabel_by_size(labels, min_size=cut)
            disc = disc._replace(dynamic=dyn_before | (labels >= 0))  # the dropped clusters' joined ones leave D
            report = cluster.cluster_report(labels[disc.dynamic])
            log(f"stage 2: the size cut ({acfg.local_min_fraction:g} of the clustered Gaussians: {cut}) keeps "
                f"{report.n_clusters} cluster(s) of sizes {list(report.sizes)}")
    return labels, disc, report




def tracked_poses(run: LoadedRun, scene: Scene, order: Int[np.ndarray, " T"], ref: Gaussians,
                   labels: Int[np.ndarray, " N"], num_objects: int, flows,
                   cfg: ArticulateConfig, moving=None, log=print, seed: int = 0,
                   centres: Float[np.ndarray, "T N 3"] | None = None) -> tuple[Float[np.ndarray, "K T 4 4"], dict]:
    """(poses [K, T, 4, 4] of each object at each training time (time order), tracked from the flow (or the
    images, ``cfg.track_photo``; or read off stage 1's field, ``cfg.track_from``) against the reference scene `ref`
    (stage 1 at t0, raw parameters), the joint fits' kinds and costs (`photometric_poses`; {} for the others)).
    ``moving`` [K, T-1]: the pairs in which each object moves (`fgjax.cluster.moving_frames`; None: all).
    ``centres``: stage 1's centres at each training time (time order) where the caller has them
    (`fgjax.method.stage2.discover_run`'s), which the field's poses read; None: deformed here."""

    if cfg.track_from == "field":
        if centres is None:
            centres = np.stack([np.asarray(run.deformed(float(scene.times[i]))[0]) for i in order])
        log(f"stage 2: poses of {num_objects} object(s) read off stage 1's field over {len(order)} frames")
        return field_poses(np.asarray(ref.means), centres, labels, num_objects), {}
    if cfg.track_photo > 0:
        return photometric_poses(run, scene, order, ref, labels, num_objects, cfg, moving, log, seed=seed)
    alive = run.state.densify.alive
    qa, sa, oa = activate(ref, alive)
    ms, qs, ss = [], [], []  # object pixels from the stage-1 model at each frame's time
    for i in order:
        m, q, ls = run.deformed(float(scene.times[i]))
        q_i, s_i, _ = activate(with_geometry(run.state.params, m, q, ls)["gaussians"], alive)
        ms.append(np.asarray(m))
        qs.append(np.asarray(q_i))
        ss.append(np.asarray(s_i))
    geo = (np.stack(ms), np.stack(qs), np.stack(ss))
    poses = track_objects(*geo, oa, labels, num_objects, scene.viewmats[order], scene.Ks[order], flows,
                          scene.width, scene.height, moving=moving, joints=cfg.track_joints,
                          tile_size=run.cfg.train.tile_size, log=log)
    return poses, {}


def photo_level_steps(n: int) -> tuple[int, int, int]:
    """The photometric tracker's Adam steps per blur level (4, 2, 0.7 pixels) for ``n`` steps a frame (2:2:1)."""
    return max(1, round(0.4 * n)), max(1, round(0.4 * n)), max(1, n - 2 * round(0.4 * n))


def photometric_poses(run: LoadedRun, scene: Scene, order: Int[np.ndarray, " T"], ref: Gaussians,
                       labels: Int[np.ndarray, " N"], num_objects: int,
                       cfg: ArticulateConfig, moving, log=print, init_poses=None, fixed=None,
                       prev_joints: dict | None = None, seed: int = 0) -> tuple[Float[np.ndarray, "K T 4 4"], dict]:
    """`tracked_poses` by `fgjax.articulate.phototrack` (``cfg.track_photo`` steps per frame; with
    ``init_poses``, ``cfg.track_photo_next`` where set) from the reference scene `ref` (raw parameters;
    ``init_poses`` [K, T, 4, 4]: an earlier round's poses, a further start of each frame): (poses [K, T, 4, 4],
    {"joint_kinds": [K], "joint_costs": [K] robust costs in px^2, None where kept, "joint_axes": [K] unit axes
    [3], None where kept, "joint_hinge_offsets": [K] a hinge's distance from its part's centre in the part's radii
    (`phototrack.hinge_offset`; over 2: likely a shift fitted as a turn), None for the other joints,
    "hinge_trials": [K] `hinge_trial`'s record, None where none ran}). ``fixed`` [K]
    bool (needs ``init_poses`` and ``prev_joints``, the earlier round's dict): objects neither tracked nor fitted
    again; they keep ``init_poses`` and their earlier joints."""

    n = cfg.track_photo_next if init_poses is not None and cfg.track_photo_next > 0 else cfg.track_photo
    steps = photo_level_steps(int(n))
    vms, Ks = scene.viewmats[order], scene.Ks[order]
    poses, _ = track_photometric(ref, run.state.densify.alive, labels, num_objects, scene.images[order], vms, Ks,
                                 moving=moving, sh_degree=run.cfg.model.sh_degree,
                                 background=run.cfg.model.background, capacity=render_capacity(run),
                                 tile_size=run.cfg.train.tile_size, steps=steps, radius=cfg.track_photo_radius,
                                 init_poses=init_poses, only_moving=cfg.track_only_moving,
                                 subset_margin=None if cfg.track_subset_margin < 0 else int(cfg.track_subset_margin),
                                 fixed=fixed, rest_check=cfg.track_rest, log=log)
    fixed = np.zeros(num_objects, bool) if fixed is None else np.asarray(fixed, bool)
    rng = np.random.default_rng(seed)
    m0 = np.asarray(ref.means)
    pts = []
    for k in range(num_objects):
        idx = np.flatnonzero(labels == k)
        # 64 points over every frame pin a joint (the fit's cost grows with the points)
        sel = m0[rng.choice(idx, min(len(idx), 64), replace=False)] if len(idx) else np.zeros((0, 3))
        # a fixed object: no fit (its poses are kept); its points are still drawn, so that the others' draws
        # (and joints) are those of a round that fits every object
        pts.append(np.zeros((0, 3)) if fixed[k] else sel)
    poses, kinds, costs, axes, offsets = joint_poses(pts, poses, vms, Ks, return_axes=True, return_offsets=True,
                                                     log=log)
    if cfg.hinge_up_deg > 0:

        up = camera_up(vms)
        tilt, ambiguity = camera_tilt(vms)
        level = tilt <= LEVEL_TILT_DEG and ambiguity <= LEVEL_AMBIGUITY
        alive = np.asarray(run.state.densify.alive, bool)
        hinges = (np.asarray(kinds) == "revolute") & ~fixed  # [K] the round's fitted hinges
        if not level and np.any(hinges):
            log(f"stage 2: the cameras' up is not trusted (tilt {tilt:.2f} degrees RMS, at most {LEVEL_TILT_DEG:g}; "
                f"ambiguity {ambiguity:.3f}, at most {LEVEL_AMBIGUITY:g}): hinges kept as tracked (hinge_up_deg)")
        for k in np.flatnonzero(hinges & level):
            if is_far_hinge(offsets[k], largest_turn_deg(poses[k])):
                continue  # a hinge far off its part is not trusted as a hinge at all (the hinge trial's)
            made = hinge_made_vertical(m0[(labels == k) & alive], poses[k], up, float(cfg.hinge_up_deg))
            if made is not None:
                poses[k], axes[k] = made[0], made[1]
                log(f"stage 2: object {k + 1}'s hinge, {made[2]:.1f} degrees off the cameras' up "
                    f"{np.round(up, 3).tolist()}, made vertical (hinge_up_deg={cfg.hinge_up_deg:g})")
    trials = {}
    if cfg.hinge_trial > 0:
        poses, trials = hinge_trial(run, scene, order, ref, labels, num_objects, poses, kinds, offsets, cfg, ~fixed,
                                     seed, log)
        for k, t in trials.items():
            if t["replaced"]:
                kinds[k], axes[k] = t["kind"], np.asarray(t["axis"])
                offsets[k] = np.nan if t["offset"] is None else t["offset"]
    out = {"joint_kinds": list(kinds), "joint_costs": [None if not np.isfinite(c) else float(c) for c in costs],
           "joint_axes": [None if not np.all(np.isfinite(a)) else [float(x) for x in a] for a in axes],
           "joint_hinge_offsets": [None if not np.isfinite(r) else float(r) for r in offsets],
           "hinge_trials": [trials.get(k) for k in range(num_objects)]}
    for k in np.flatnonzero(fixed):  # the earlier round's joint
        for key in out:
            out[key][k] = prev_joints.get(key, [None] * num_objects)[k]
    return poses, out


def run_articulated(run_dir: str | Path, data_dir: str | Path, cfg: Stage2Config = Stage2Config(),
                    acfg: ArticulateConfig = ArticulateConfig(), *, log=print) -> Stage2Result:
    """The articulated variant of stage 2 on a trained stage-1 run; writes RUN/stage2.npz and RUN/stage2.json.

    The paper's discovery, then `select_parts`; each part's rigid poses tracked (`tracked_poses`) against the
    reference scene (stage 1 at t0); then ``acfg.track_rounds`` rounds of re-fitting the scene under those poses
    (`fgjax.articulate.refit.refit_gaussians`, with relabelling) and tracking again on the re-fitted scene (objects
    whose joint converged or was chosen by a hinge trial are kept); the label passes (`fgjax.articulate.labels`) and
    a last re-fit; the control network distilled from the posed geometry (`fgjax.method.stage2.finish`).

    Args:
        run_dir: stage-1 run folder.
        data_dir: the dataset the run was trained on (only the training split is read; never gt/).
        cfg: `Stage2Config` (discovery, clustering and the control network).
        acfg: `ArticulateConfig`.
    """
    validate_stage2(cfg)
    validate_articulate(acfg)
    if acfg.track_rounds > 1 and (acfg.track_photo == 0 or acfg.refit_steps == 0):
        log(f"stage 2: track_rounds={acfg.track_rounds} has no effect without track_photo > 0 and refit_steps > 0; "
            "one round")
    t_start = time.perf_counter()
    run_dir, data_dir = Path(run_dir), Path(data_dir)
    run, scene, fingerprint = prepare_run(run_dir, data_dir, log)
    cache = Path(cfg.flow_cache) if cfg.flow_cache else run_dir / "flow_cache"
    disc, centres, times, (order, flows, _) = discover_run(run, scene, cfg, cache, per_frame=True, log=log)
    n_dyn = int(disc.dynamic.sum())
    canonical = np.asarray(run.state.params["gaussians"].means)
    labels, disc, report = select_parts(canonical, disc, cfg, acfg, np.asarray(run.state.densify.alive), log=log,
                                        t_start=t_start)
    alive = run.state.densify.alive
    refit, joints, fills, history = None, {}, {}, []
    meta: dict = {"variant": "articulated", "articulate": dataclasses.asdict(acfg), "num_dynamic": n_dyn,
                  "data_fingerprint": fingerprint}
    if not report.n_clusters:
        qs, ls = deformed_geometry(run, times)
        return finish(run_dir, data_dir, run, scene, order, labels, disc.dynamic, disc, (centres, qs, ls), flows,
                      cfg, meta, t_start, log=log)
    moving = None
    if acfg.track_active > 0 and disc.scores.moving_t is not None:
        moving = cluster.moving_frames(labels, disc.scores.moving_t, disc.scores.total_t, active=acfg.track_active,
                                       dilate=1)
        log(f"stage 2: tracking each object over its moving pairs {[int(f.sum()) for f in moving]} of "
            f"{moving.shape[1]} ({time.perf_counter() - t_start:.1f} s)")
    reference = reference_scene(run, float(times[0]))  # the scene the poses move
    base = (reference.means, reference.quats, reference.log_scales)
    poses, joints = tracked_poses(run, scene, order, reference, labels, report.n_clusters, flows, acfg, moving, log,
                                  seed=cfg.seed, centres=centres)
    if acfg.refit_steps > 0:
        rounds = int(acfg.track_rounds) if acfg.track_photo > 0 else 1
        refit = reference  # the first re-fit starts from the reference the poses move
        history = [joints]
        for r in range(rounds):
            fixed = None
            if r >= 2 and acfg.track_converged_deg > 0:  # objects whose joint stayed put in the last round
                a, b = history[-2], history[-1]
                nan3 = [np.nan] * 3
                fixed = converged_joints(a["joint_kinds"], [x or nan3 for x in a["joint_axes"]],
                                         b["joint_kinds"], [x or nan3 for x in b["joint_axes"]],
                                         acfg.track_converged_deg)
                if fixed.all():
                    log(f"stage 2: every joint converged (the same kind, the axis within "
                        f"{acfg.track_converged_deg:g} degrees of the last round's); no round {r + 1}")
                    break
            held = trial_held(history, report.n_clusters)  # joints chosen by a hinge trial are kept
            if r > 0 and held.any():
                fixed = held if fixed is None else fixed | held
                if fixed.all():
                    log(f"stage 2: every joint converged or was chosen by a hinge trial; no round {r + 1}")
                    break
            if r > 0:  # track again, rendering the last re-fit
                log(f"stage 2: tracking and re-fitting, round {r + 1} of {rounds}"
                    + ("" if fixed is None or not fixed.any() else
                       f": objects {(np.flatnonzero(~fixed) + 1).tolist()} only (the joints of "
                       f"{(np.flatnonzero(fixed) + 1).tolist()} converged"
                       + (" or were chosen by a hinge trial)" if held.any() else ")")))
                poses, joints = photometric_poses(run, scene, order, refit, labels, report.n_clusters, acfg, moving,
                                                  log, init_poses=poses, fixed=fixed, prev_joints=joints,
                                                  seed=cfg.seed)
                history.append(joints)
            if acfg.ghost_radius > 0:
                refit = fade_ghosts(refit, labels, poses, alive, acfg, log)
            refit, labels = refit_gaussians(run, scene, order, labels, poses, acfg.refit_steps, seed=cfg.seed + r,
                                            relabel_steps=acfg.relabel_steps, relabel_radius=acfg.relabel_radius,
                                            init=refit, lr_scale=acfg.refit_lr_scale, log=log)
        refit, labels, poses, fills = label_passes(run, scene, order, reference, refit, labels, poses, moving, acfg,
                                                   cfg.seed, rounds, log)
        base = (refit.means, refit.quats, refit.log_scales)
    geometry = posed_geometry(base, labels, poses)
    meta.update({key: v for key, v in joints.items() if key != "hinge_trials"})
    if acfg.hinge_trial > 0 and history:
        meta["hinge_trials"] = [h.get("hinge_trials") for h in history]
    meta.update(fills)
    return finish(run_dir, data_dir, run, scene, order, labels, disc.dynamic, disc, geometry, flows, cfg, meta,
                  t_start, refit=refit, log=log)


def label_passes(run: LoadedRun, scene: Scene, order: Int[np.ndarray, " T"], reference: Gaussians, refit: Gaussians,
                 labels: Int[np.ndarray, " N"], poses: Float[np.ndarray, "K T 4 4"], moving, acfg: ArticulateConfig,
                 seed: int, rounds: int, log=print):
    """After the last round: hull and hinge fills, isolated members, colour outlines, still spans settled at rest,
    static Gaussians seen through the parts pruned (each where its `ArticulateConfig` key turns it on; the fills, the
    isolated members, the colour outlines and the pruning are off by default, docs/benchmarks.md "Label passes"),
    then ``acfg.hull_refit_steps`` of re-fit under the new labels.
    Returns (re-fitted scene, labels [N], poses [K, T, 4, 4], a record of what each pass changed)."""
    alive = run.state.densify.alive
    fills: dict = {}
    filled = labels
    if acfg.hull_fill:
        filled = fill_hulls(filled, refit, alive, acfg.hull_opacity, acfg.hull_max_growth, log)
        fills["hull_joined"] = joined(labels, filled)
    if acfg.hinge_fill:
        before = filled
        filled, fills["hinges"] = fill_hinges(before, refit, alive, poses, acfg, log)
        fills["hinge_joined"] = joined(before, filled)
    if acfg.isolated_factor > 0:
        before = filled
        filled, fills["isolated_dropped"] = drop_isolated(before, refit, alive, acfg.isolated_factor, log)
        refit = fade_dropped(refit, before, filled, acfg, "of them", log)
    if acfg.colour_radius > 0:
        before = filled
        filled, rep = refine_by_colour(before, refit, alive, acfg, seed, log)
        fills["colour_joined"] = [r["joined"] for r in rep]
        fills["colour_left"] = [r["left"] for r in rep]
        refit = fade_dropped(refit, before, filled, acfg, "of those that left", log)
    if acfg.settle_rest and acfg.track_rest and moving is not None and acfg.track_photo > 0:
        poses, settled = settle(run, scene, order, reference, filled, poses, moving, log)
        fills["settled"] = [list(x) for x in settled]
    if acfg.through_prune > 0:
        refit, fills["through_pruned"] = prune_seen_through(refit, filled, poses, run, scene, order,
                                                            acfg.through_prune, log)
    if (label_passes_on(acfg) or fills.get("settled")) and acfg.hull_refit_steps > 0:
        refit, _ = refit_gaussians(run, scene, order, filled, poses, acfg.hull_refit_steps, seed=seed + rounds,
                                   init=refit, lr_scale=acfg.refit_lr_scale, log=log)
    return refit, filled, poses, fills
