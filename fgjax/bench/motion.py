"""``fgjax bench motion``: how much of the objects' motion a stage-1 run learned, on a synthetic scene, and why.

For a trained stage-1 run and the ``fgjax synth`` dataset it was trained on (the ground truth under DATA/gt is read
here, never by the pipeline), prints:

- test-view PSNR over object pixels (ground-truth object id > 0) and over static pixels, pooled over the held-out
  views at training times (the "state" views are stage 2's);
- per part, its Gaussians: the model's live Gaussians whose centre at the first training time t0 (every part of a
  ``fgjax synth`` scene is in its canonical state then) lies on that part's canonical surface (nearest true canonical
  Gaussian within 0.05 scene units); the learned displacement L(t) = mean of their centres at t minus at t0, at each
  training time, against the true displacement D(t) of the part's centre from t0 (scene units). Measuring from t0
  rather than from the model's canonical Gaussians makes the numbers independent of where the deformation field puts
  its canonical space. At the time t* of the largest true displacement: the ratio |L(t*)| / |D(t*)| and the angle
  between L(t*) and D(t*). A part counts as learned (issue 53's acceptance) when the ratio is within 20 % of 1 and
  the angle under 15 degrees. A ratio near 0 means stage 1 renders the part in one state at all times. Beside it,
  what a monocular video can pin (`motion_observability`): the angle "in image" (L(t*) and D(t*) projected on the
  plane normal to the viewing ray at t*), D(t*)'s angle to that ray, and the widest angle between the rays to the
  part over the frames it spends in its t* state, the only parallax that fixes its motion along the rays;
- how many live Gaussians move more than 0.01, 0.05 and 0.1 scene units from where they are at t0, at any time;
- for a "bases" field (`fgjax.models.deform`), where the weights w(X) = softmax(logits(X)) sit (`basis_weights`):
  the mean weight on the static basis (basis 0) over every live Gaussian, and each part's mean weight on every
  basis. A part whose weight sits on basis 0 cannot move, whatever its bases' motions learn;
- with ``--flow``, the dynamic-flow diagnosis (DESIGN.md section 1, step 4), per part over the frame pairs in which
  it moves (median ground-truth object flow on its pixels above 0.5 px): on the part's pixels of frame t-1, the
  rendered dynamic Gaussian flow u~_GS against the target u - u_cam (u: the optical flow stage 1 trains with, u_cam:
  the reprojection of the rendered depth), as median end-point error and median magnitude ratio |u~_GS| / |u - u_cam|,
  the target's own error against the true object flow, and the gradient norms that L_uGS (unweighted) and the
  photometric loss send to the deformation field's motion at that frame (the displacement head's weights; for a
  "bases" field, the bases' control values).

``--oracle STEPS`` asks whether the deformation field can learn the motion at all when everything else is right: the
run's field architecture (a fresh one, the identity at t0: `fgjax.models.deform.DeformSpec.anchor`) on the scene's
true canonical Gaussians (gt/canonical.npz, the state at t0), fitted alone for STEPS Adam steps on L_uGS of frame
pairs drawn uniformly (`--oracle-flow true`: the true optical flow instead of the run's estimated one, ``none``: no
flow loss; ``--oracle-loss track``: the first frame's tracks, `fgjax.flow.track`, instead of L_uGS; with
``--oracle-photo W`` plus W times the photometric loss of frame t), learning rate ``train.lr_deform`` (hash tables
x ``train.lr_hash_factor``) unless ``--oracle-lr``. It prints L(t*) / D(t*) and the angle per part every 100 steps.

``--train CONFIG`` trains the run first (into ``--run``, with ``--set`` overrides) and records L(t*) / D(t*) per part
every ``train.log_every`` steps (the trace: learned against true displacement over training), with a "bases" field
also the static basis's mean weight over all live Gaussians and over each part's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from scipy.spatial import cKDTree

from fgjax.config import ConfigError, load_config
from fgjax.data.loaders import load_scene
from fgjax.data.opticalflow import chained_tracks
from fgjax.data.scene import Normalization
from fgjax.flow import dynamic_gaussian_flow, maps_camera_flow
from fgjax.gaussians import Gaussians, num_sh_coeffs, rgb_to_sh0
from fgjax.io import atomic_write
from fgjax.method.stage1 import (
    FlowBatch,
    StepSpec,
    compute_capacity,
    estimate_training_flows,
    flow_term,
    load_run,
    prepare_run_folder,
    previous_frames,
    render_frame,
    training_tracks,
)
from fgjax.method.stage1 import run as run_stage1
from fgjax.models import deform as dfm
from fgjax.models.deform import deform_init
from fgjax.models.model import deformed_gaussians, render_params
from fgjax.train.losses import photometric_loss
from fgjax.train.optim import guarded_step

__all__ = ["main", "motion_report", "part_gaussians", "learned_motion", "true_motion", "motion_scores", "basis_weights",
           "motion_observability", "true_observability",
           "flow_diagnosis", "means_at", "part_scores", "true_gaussians", "oracle_fit"]

RATIO_TOL = 0.2
ANGLE_TOL_DEG = 15.0
STATE_TOL = 0.02  # a part is in its t* state while its centre is within this share of |D(t*)| of it
ON_SURFACE = 0.05  # scene units: a model Gaussian this close to a true canonical Gaussian lies on its surface
MOVING_PX = 0.5


def _pooled_psnr(err2: np.ndarray) -> float:
    return float(-10.0 * np.log10(max(float(np.mean(err2)), 1e-12))) if err2.size else float("nan")


def _check_gt(data_dir: Path, files=("meta.json", "canonical.npz", "train/centres.npy", "train/times.npy",
                                       "train/viewmats_true.npy", "test/object_id.npy", "test/kind.npy")) -> Path:
    gt = Path(data_dir) / "gt"
    for f in files:
        if not (gt / f).exists():
            raise FileNotFoundError(f"{gt / f} is missing: `fgjax bench motion` needs a dataset written by "
                                    "`fgjax synth` (with its gt folder)")
    return gt


def part_gaussians(means: np.ndarray, alive: np.ndarray, gt: Path, norm: Normalization) -> list[np.ndarray]:
    """Per part (gt/meta.json order): indices of the live model Gaussians whose centre ``means`` [N, 3] (scene
    units, at the first training time) lies within `ON_SURFACE` of that part's true canonical Gaussians."""
    canon = np.load(gt / "canonical.npz")
    gt_pts = norm.points_to_scene(np.asarray(canon["means"], np.float64))
    gt_lab = np.asarray(canon["labels"])
    live = np.flatnonzero(alive)
    dist, nn = cKDTree(gt_pts).query(np.asarray(means)[live])
    near = dist < ON_SURFACE
    objects = json.loads((gt / "meta.json").read_text())["objects"]
    return [live[near & (gt_lab[nn] == o["label"])] for o in objects]


def means_at(params, alive, spec, t: float) -> np.ndarray:
    """[N, 3] the model's centres at time t (the canonical ones for a static model, ``spec`` None)."""
    if spec is None:
        return np.asarray(params["gaussians"].means)
    return np.asarray(deformed_gaussians(params, alive, float(t), spec)[0])


def basis_weights(params, alive, spec, parts: list[np.ndarray]) -> dict | None:
    """For a "bases" field (``spec.kind``), the weights w [N, B] (`fgjax.models.deform.basis_weights`) at the
    canonical centres: {"static_all": mean w_0 (the static basis) over the live Gaussians, "parts": per part (its
    indices in ``parts``) the mean of its Gaussians' weights, [B] (NaN for a part with no Gaussians)}; None for the
    other kinds and a static model (``spec`` None)."""
    if spec is None or spec.kind != "bases":
        return None
    w = np.asarray(dfm.basis_weights(spec, params["deform"], params["gaussians"].means))
    live = np.asarray(alive, bool)
    return {"static_all": float(np.mean(w[live, 0])) if live.any() else float("nan"),
            "parts": [w[idx].mean(axis=0).tolist() if len(idx) else [float("nan")] * w.shape[1] for idx in parts]}


def learned_motion(params, alive, spec, parts: list[np.ndarray], times: np.ndarray) -> np.ndarray:
    """[K, T, 3] displacement of each part's Gaussians' mean centre at ``times`` [T] from the one at times[0]
    (scene units); zeros for a static model (``spec`` None); NaN for a part with no Gaussians."""
    ref = means_at(params, alive, spec, float(times[0]))
    out = np.full((len(parts), len(times), 3), np.nan)
    for ti, t in enumerate(times):
        m = means_at(params, alive, spec, float(t))
        for k, idx in enumerate(parts):
            if len(idx):
                out[k, ti] = np.mean(m[idx] - ref[idx], axis=0)
    return out


def true_motion(gt: Path, norm: Normalization) -> tuple[np.ndarray, np.ndarray]:
    """(times [T], [K, T, 3] true displacement of each part's centre from the first training time, scene units)."""
    centres = norm.points_to_scene(np.load(gt / "train" / "centres.npy"))  # [T, K, 3]
    return np.load(gt / "train" / "times.npy"), np.transpose(centres - centres[:1], (1, 0, 2))


def motion_observability(centres: np.ndarray, cams: np.ndarray, tol: float = STATE_TOL) -> list[dict]:
    """How well a monocular video pins each part's motion along the viewing rays, from the true part centres
    ``centres`` [K, T, 3] and camera centres ``cams`` [T, 3] (scene units) at the training times. Per part, with t*
    the time of its largest displacement D(t*) from the first time:

    - "view_dir": the unit ray from the camera at t* to the part's centre [3];
    - "along_ray_deg": the angle between D(t*) and that ray (0: the motion is along the ray, and the image at t*
      sees it only as a change of scale);
    - "ray_spread_deg": the widest angle between the rays to the part's centre over the frames in which it is in its
      t* state (centre within ``tol`` |D(t*)| of it): the triangulation angle of that state. The component of D(t*)
      along the rays is pinned only by this parallax: 0 for a still camera, where a track or a photometric loss
      sees the motion only in the image plane.

    A part whose centre never moves (turning about it) has "along_ray_deg" NaN and its rays over every frame.
    """
    out = []
    for c in np.asarray(centres, np.float64):
        disp = np.linalg.norm(c - c[0], axis=-1)
        ts = int(np.argmax(disp))
        rays = c - np.asarray(cams, np.float64)
        rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
        held = np.linalg.norm(c - c[ts], axis=-1) <= tol * max(float(disp[ts]), 1e-12)
        r = rays[held]
        spread = float(np.degrees(np.arccos(np.clip(np.min(r @ r.T), -1.0, 1.0))))
        d = c[ts] - c[0]
        along = float(np.degrees(np.arccos(np.clip(abs(d @ rays[ts]) / max(float(disp[ts]), 1e-12), 0.0, 1.0))))
        out.append({"view_dir": rays[ts], "along_ray_deg": along if disp[ts] > 0 else float("nan"),
                    "ray_spread_deg": spread})
    return out


def motion_scores(learned: np.ndarray, true: np.ndarray, view_dirs: np.ndarray | None = None) -> list[dict]:
    """Per part, at the time t* of its largest true displacement: true and learned |D(t*)|, |L(t*)|, their ratio,
    the angle between them (degrees), and ``ok``: ratio within `RATIO_TOL` of 1 and angle under `ANGLE_TOL_DEG`.
    With ``view_dirs`` [K, 3] (`motion_observability`'s rays at t*), also "image_ratio" and "image_angle_deg": the
    ratio and angle of L(t*) and D(t*) projected on the plane normal to the ray, what the image at t* sees of them."""
    res = []
    for k, (lk, dk) in enumerate(zip(learned, true)):
        mags = np.linalg.norm(dk, axis=-1)
        ts = int(np.argmax(mags))
        d, lv = dk[ts], lk[ts]
        nl = float(np.linalg.norm(lv)) if np.all(np.isfinite(lv)) else float("nan")
        ratio = nl / max(float(mags[ts]), 1e-12)
        cos = float(np.dot(lv, d) / max(nl * float(mags[ts]), 1e-12)) if np.isfinite(nl) else float("nan")
        ang = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))) if np.isfinite(cos) else float("nan")
        res.append({"true": float(mags[ts]), "learned": nl, "ratio": ratio, "angle_deg": ang,
                    "ok": bool(abs(ratio - 1.0) <= RATIO_TOL and ang <= ANGLE_TOL_DEG)})
        if view_dirs is not None:
            r = np.asarray(view_dirs[k], np.float64)
            dp, lp = d - (d @ r) * r, lv - (lv @ r) * r
            den = float(np.linalg.norm(dp) * np.linalg.norm(lp))
            res[-1]["image_angle_deg"] = (float(np.degrees(np.arccos(np.clip(dp @ lp / den, -1.0, 1.0))))
                                          if np.isfinite(den) and den > 1e-24 else float("nan"))
            ndp = float(np.linalg.norm(dp))
            res[-1]["image_ratio"] = float(np.linalg.norm(lp)) / ndp if ndp > 1e-12 else float("nan")
    return res


def true_observability(gt: Path, norm: Normalization) -> list[dict]:
    """`motion_observability` of a ``fgjax synth`` dataset's parts, from gt/train/centres.npy and the true cameras
    gt/train/viewmats_true.npy (OpenCV world-to-camera), in the run's scene units."""
    centres = norm.points_to_scene(np.load(gt / "train" / "centres.npy"))  # [T, K, 3]
    vm = np.load(gt / "train" / "viewmats_true.npy").astype(np.float64)  # [T, 4, 4]
    cams = norm.points_to_scene(-np.einsum("tji,tj->ti", vm[:, :3, :3], vm[:, :3, 3]))
    return motion_observability(np.transpose(centres, (1, 0, 2)), cams)


def part_scores(params, alive, spec, gt: Path, norm: Normalization, times: np.ndarray, true: np.ndarray,
                view_dirs: np.ndarray | None = None):
    """(parts, learned [K, T, 3], `motion_scores`) of a model at one moment: its Gaussians on each part at times[0]
    (`part_gaussians`), their learned motion at ``times`` (`learned_motion`) against ``true`` (`true_motion`)."""
    parts = part_gaussians(means_at(params, alive, spec, float(times[0])), np.asarray(alive), gt, norm)
    learned = learned_motion(params, alive, spec, parts, times)
    return parts, learned, motion_scores(learned, true, view_dirs)


def flow_diagnosis(cfg, state, spec, data_dir: Path, norm: Normalization, flows: np.ndarray | None = None,
                   cache_dir: Path | None = None, max_frames: int = 8) -> list[dict]:
    """The ``--flow`` measurements (module docstring), per part: {"frames", "epe_gs_target", "ratio_gs_target",
    "epe_target_true", "grad_flow", "grad_photo"} as medians over up to ``max_frames`` frame pairs in which it
    moves (evenly spaced among them); empty for a static model."""
    gt = _check_gt(data_dir, ("meta.json", "train/object_id.npy", "train/object_flow.npy"))
    sc = load_scene(data_dir, "train", normalize=norm, downscale=cfg.data.downscale)
    oid = np.load(gt / "train" / "object_id.npy")
    oflow = np.load(gt / "train" / "object_flow.npy")
    if oid.shape[1:] != (sc.height, sc.width):
        raise ValueError(f"{gt / 'train/object_id.npy'} has size {oid.shape[1:]}, the training images "
                         f"{(sc.height, sc.width)} (run trained with data.downscale?)")
    labels = [o["label"] for o in json.loads((gt / "meta.json").read_text())["objects"]]
    if spec is None or state.static:
        return [{} for _ in labels]
    if flows is None:
        flows = estimate_training_flows(sc, cfg.flow.method, cache_dir=cache_dir, log=lambda *a: None)
    prev = previous_frames(sc.times)
    p, alive = state.params, state.densify.alive
    w, h = sc.width, sc.height
    bg = jnp.asarray(cfg.model.background, jnp.float32)
    ss = StepSpec(spec, cfg.model.sh_degree, w, h, None, cfg.train.tile_size, cfg.train.lambda_dssim, 0.0, 0.0, False,
                  1.0, cfg.flow.threshold, flow_norm=cfg.flow.norm, flow_scale=cfg.flow.charbonnier_px)
    out = []
    for lab in labels:
        frames = []
        for i in range(sc.num_frames):
            j = int(prev[i])
            if j < 0 or j >= len(oflow):
                continue
            part = oid[j] == lab
            if part.sum() >= 20 and np.median(np.linalg.norm(oflow[j][part], axis=-1)) > MOVING_PX:
                frames.append((i, j))
        if len(frames) > max_frames:
            frames = [frames[k] for k in np.linspace(0, len(frames) - 1, max_frames).round().astype(int)]
        rows = []
        for i, j in frames:
            vm0, vm1, K = (jnp.asarray(a, jnp.float32) for a in (sc.viewmats[j], sc.viewmats[i], sc.Ks[i]))
            m0, q0, s0, o0, _ = deformed_gaussians(p, alive, float(sc.times[j]), spec)
            m1 = deformed_gaussians(p, alive, float(sc.times[i]), spec)[0]
            maps = dynamic_gaussian_flow(m0, q0, s0, o0, m1, vm0, K, w, h)
            u_cam, ok = maps_camera_flow(maps, vm0, vm1, K)
            target = flows[i] - np.asarray(u_cam)
            sel = (oid[j] == lab) & np.asarray(ok) & np.all(np.isfinite(target), -1) & (np.asarray(maps.alpha) > 0.5)
            if sel.sum() < 10:
                continue
            gs = np.asarray(maps.flow)[sel]
            tg = target[sel]
            fb = FlowBatch(jnp.asarray(flows[i]), vm0, jnp.float32(sc.times[j]), jnp.int32(j), jnp.float32(1.0))

            def l_flow(d, i=i, K=K, vm1=vm1, fb=fb):
                return flow_term(ss, {**p, "deform": d}, alive, vm1, K, float(sc.times[i]), fb)[0]

            def l_photo(d, i=i, K=K, vm1=vm1):
                img = render_params({**p, "deform": d}, alive, vm1, K, float(sc.times[i]), spec=spec,
                                    sh_degree=cfg.model.sh_degree, width=w, height=h, background=bg, capacity=None)[0]
                return photometric_loss(img, jnp.asarray(sc.images[i]), cfg.train.lambda_dssim)

            head = lambda g: float(np.linalg.norm(np.asarray(g["motion"]) if spec.kind == "bases"
                                                  else np.asarray(g["head"]["w"])[:, :3]))
            rows.append((np.median(np.linalg.norm(gs - tg, axis=-1)),
                         np.median(np.linalg.norm(gs, axis=-1)) / max(np.median(np.linalg.norm(tg, axis=-1)), 1e-9),
                         np.median(np.linalg.norm(tg - oflow[j][sel], axis=-1)),
                         head(jax.grad(l_flow)(p["deform"])), head(jax.grad(l_photo)(p["deform"]))))
        med = np.median(np.asarray(rows), axis=0) if rows else np.full(5, np.nan)
        out.append({"frames": len(rows), "epe_gs_target": float(med[0]), "ratio_gs_target": float(med[1]),
                    "epe_target_true": float(med[2]), "grad_flow": float(med[3]), "grad_photo": float(med[4])})
    return out


def motion_report(run_dir: Path, data_dir: Path, num_times: int = 21, flow: bool = False) -> dict:
    """The measurements above as a dict (see the module docstring)."""
    gt = _check_gt(data_dir)
    cfg, state, spec, meta = load_run(run_dir)
    norm = Normalization.from_dict(meta["normalization"])
    test = load_scene(data_dir, "test", normalize=norm, downscale=cfg.data.downscale)
    ids = np.load(gt / "test" / "object_id.npy")  # [T', H, W]
    kind = np.load(gt / "test" / "kind.npy")  # [T'] 0 = novel view at a training time
    if ids.shape[1:] != (test.height, test.width):
        raise ValueError(f"{gt / 'test/object_id.npy'} has size {ids.shape[1:]}, the test images "
                         f"{(test.height, test.width)} (run trained with data.downscale?)")
    e_obj, e_sta = [], []
    for i in np.flatnonzero(kind == 0):
        img = render_frame(state, spec, cfg, test.viewmats[i], test.Ks[i], test.times[i], test.width, test.height)
        e = np.mean((img - test.images[i]) ** 2, axis=-1)  # [H, W]
        e_obj.append(e[ids[i] > 0])
        e_sta.append(e[ids[i] <= 0])
    res: dict = {"psnr_object_pixels": _pooled_psnr(np.concatenate(e_obj)) if e_obj else float("nan"),
                 "psnr_static_pixels": _pooled_psnr(np.concatenate(e_sta)) if e_sta else float("nan")}
    alive = np.asarray(state.densify.alive)
    use = None if state.static else spec
    times, true = true_motion(gt, norm)
    ref = means_at(state.params, state.densify.alive, use, float(times[0]))  # [N, 3] at the first time
    disp = np.max([np.linalg.norm(means_at(state.params, state.densify.alive, use, float(t)) - ref, axis=-1)
                   for t in np.linspace(0.0, 1.0, num_times)], axis=0)  # [N]
    res["moving_gaussians"] = {str(th): int(np.sum(alive & (disp > th))) for th in (0.01, 0.05, 0.1)}
    res["live_gaussians"] = int(alive.sum())
    obs = true_observability(gt, norm)
    parts, lm, scores = part_scores(state.params, state.densify.alive, use, gt, norm, times, true,
                                    np.stack([o["view_dir"] for o in obs]))
    objects = json.loads((gt / "meta.json").read_text())["objects"]
    diag = flow_diagnosis(cfg, state, use, data_dir, norm, cache_dir=Path(run_dir) / "flow_cache") if flow else None
    bw = basis_weights(state.params, state.densify.alive, use, parts)
    res["static_weight"] = None if bw is None else bw["static_all"]
    res["objects"] = []
    for k, (o, idx, sc) in enumerate(zip(objects, parts, scores)):
        learned_max = float(np.max(np.linalg.norm(lm[k], axis=-1))) if len(idx) else float("nan")
        row = {"name": o["name"], "gaussians": int(len(idx)),
               "true_max_displacement": float(np.max(np.linalg.norm(true[k], axis=-1))),
               "learned_max_displacement": learned_max, **{f"at_tmax_{n}": v for n, v in sc.items()},
               "along_ray_deg": obs[k]["along_ray_deg"], "ray_spread_deg": obs[k]["ray_spread_deg"],
               "basis_weights": None if bw is None else bw["parts"][k]}
        if diag is not None:
            row["flow"] = diag[k]
        res["objects"].append(row)
    res["parts_learned"] = int(sum(s["ok"] for s in scores))
    return res


def true_gaussians(gt: Path, norm: Normalization, sh_degree: int) -> Gaussians:
    """The synthetic scene's true Gaussians in their canonical state (gt/canonical.npz: world means, scales,
    wxyz quaternions, opacities in (0, 1), RGB colours) as raw model parameters in the normalised scene (``norm``):
    log-scales, opacity logits and SH coefficients of ``sh_degree`` (degree 0 from the colour, the rest zero)."""
    c = np.load(gt / "canonical.npz")
    n = len(c["means"])
    sh = np.zeros((n, num_sh_coeffs(sh_degree), 3), np.float32)
    sh[:, 0] = np.asarray(rgb_to_sh0(np.asarray(c["colors"], np.float32)))
    op = np.clip(np.asarray(c["opacities"], np.float64), 1e-4, 1.0 - 1e-4)
    return Gaussians(jnp.asarray(norm.points_to_scene(c["means"]), jnp.float32),
                     jnp.asarray(np.log(norm.lengths_to_scene(np.asarray(c["scales"], np.float64))), jnp.float32),
                     jnp.asarray(c["quats"], jnp.float32), jnp.asarray(np.log(op / (1.0 - op)), jnp.float32),
                     jnp.asarray(sh))


def oracle_fit(run_dir: Path, data_dir: Path, steps: int, *, flow: str = "estimated", loss: str = "pair",
               photo: float = 0.0,
               lr: float | None = None, log_every: int = 100, seed: int = 0, log=print) -> dict:
    """``--oracle`` (module docstring): {"trace": [{"step", "loss", "ratios", "angles"}], "objects": final
    `motion_scores` per part with "name", "parts_learned", "wall_s"}."""
    if steps < 1:
        raise ValueError(f"--oracle needs a number of steps >= 1; got {steps}")
    if photo < 0:
        raise ValueError(f"--oracle-photo must be >= 0; got {photo}")
    if flow not in ("estimated", "true", "none"):
        raise ValueError(f"--oracle-flow must be estimated, true or none; got {flow!r}")
    if loss not in ("pair", "track"):
        raise ValueError(f"--oracle-loss must be pair or track; got {loss!r}")
    if flow == "none" and photo == 0:
        raise ValueError("--oracle-flow none needs --oracle-photo > 0 (nothing to fit)")
    gt = _check_gt(data_dir)
    cfg, _, spec, meta = load_run(run_dir)
    if spec is None:
        raise ValueError(f"{run_dir} has no deformation field (deform disabled)")
    norm = Normalization.from_dict(meta["normalization"])
    sc = load_scene(data_dir, "train", normalize=norm, downscale=cfg.data.downscale)
    prev = previous_frames(sc.times)
    if flow == "true":
        f = np.load(gt / "train" / "flow.npy")  # [T-1, H, W, 2], frame i -> i+1 in file order
        if f.shape[1:3] != (sc.height, sc.width) or np.any(np.diff(sc.times) <= 0):
            raise ValueError(f"{gt / 'train/flow.npy'} pairs consecutive frames at {f.shape[1:3]}; the run trains "
                             f"{(sc.height, sc.width)} frames (data.downscale?) or not in time order")
        if loss == "track":  # chained from frame 0, stopping at the true occlusions
            flows = chained_tracks(f, ~np.load(gt / "train" / "flow_occluded.npy"))
            prev = np.where(np.arange(sc.num_frames) == 0, -1, 0)
        else:
            flows = np.concatenate([np.zeros_like(f[:1]), f])  # flows[i]: frame i-1 -> i
    elif flow == "none":
        flows = np.zeros((sc.num_frames, sc.height, sc.width, 2), np.float32)
    elif loss == "track":
        prev, flows = training_tracks(sc, cfg.flow.method, cache_dir=Path(run_dir) / "flow_cache",
                                      log=lambda *a: None)
    else:
        flows = estimate_training_flows(sc, cfg.flow.method, cache_dir=Path(run_dir) / "flow_cache",
                                        log=lambda *a: None)
    times, true = true_motion(gt, norm)
    obs = true_observability(gt, norm)
    dirs = np.stack([o["view_dir"] for o in obs])
    spec = dataclasses.replace(spec, anchor=float(times[0]))
    g = true_gaussians(gt, norm, cfg.model.sh_degree)
    alive = jnp.ones(g.means.shape[0], bool)
    params = {"gaussians": g, "deform": deform_init(jax.random.PRNGKey(seed), spec)}
    parts = part_gaussians(np.asarray(g.means), np.ones(g.means.shape[0], bool), gt, norm)
    rate = cfg.train.lr_deform if lr is None else lr
    groups = {k: jax.tree_util.tree_map(lambda _, k=k: "hash" if k == "grid" else "mlp", v)
              for k, v in params["deform"].items()}
    opt = optax.multi_transform({"mlp": optax.adam(rate), "hash": optax.adam(rate * cfg.train.lr_hash_factor)},
                                groups)
    # the tile-intersection buffer of the true Gaussians, with the training margin (as in stage 1)
    capacity = compute_capacity(params, alive, sc.viewmats, sc.Ks, sc.width, sc.height, cfg.train.tile_size,
                                cfg.train.capacity_margin)
    ss = StepSpec(spec, cfg.model.sh_degree, sc.width, sc.height, capacity, cfg.train.tile_size,
                  cfg.train.lambda_dssim, 0.0, 0.0, False, 1.0, cfg.flow.threshold, flow_loss=loss,
                  flow_norm=cfg.flow.norm, flow_scale=cfg.flow.charbonnier_px)
    bg = jnp.asarray(cfg.model.background, jnp.float32)

    def objective(d, batch):
        vm0, vm1, K, t0, t1, uv, image = batch
        p = {**params, "deform": d}
        val, over = 0.0, jnp.zeros((), bool)
        if flow != "none":
            val, over = flow_term(ss, p, alive, vm1, K, t1, FlowBatch(uv, vm0, t0, jnp.int32(0), jnp.float32(1.0)))
        if photo > 0:
            img, _, info, _ = render_params(p, alive, vm1, K, t1, spec=spec, sh_degree=cfg.model.sh_degree,
                                            width=sc.width, height=sc.height, background=bg, capacity=capacity)
            val = val + photo * photometric_loss(img, image, cfg.train.lambda_dssim)
            over = over | info["overflow"]
        return val, over

    step = guarded_step(objective, opt)  # a step whose render overflows or whose loss is not finite is dropped

    pairs = np.flatnonzero(prev >= 0)
    rng = np.random.default_rng(seed)
    d, ostate = params["deform"], opt.init(params["deform"])
    trace, losses, dropped, t_start = [], [], 0, time.perf_counter()
    for k in range(1, steps + 1):
        i = int(rng.choice(pairs))
        j = int(prev[i])
        d, ostate, val, bad = step(d, ostate, tuple(jnp.asarray(a, jnp.float32) for a in (
            sc.viewmats[j], sc.viewmats[i], sc.Ks[i], sc.times[j], sc.times[i], flows[i], sc.images[i])))
        dropped += int(bad)
        losses.append(float(val))
        if k % log_every == 0 or k == steps:
            sco = motion_scores(learned_motion({**params, "deform": d}, alive, spec, parts, times), true, dirs)
            trace.append({"step": k, "loss": float(np.mean(losses)), "ratios": [s["ratio"] for s in sco],
                          "angles": [s["angle_deg"] for s in sco]})
            losses = []
            log(f"oracle step {k}/{steps}: loss {trace[-1]['loss']:.4f}; L/D, angle per part: "
                + ", ".join(f"{r:.2f} {a:.0f} deg" for r, a in zip(trace[-1]["ratios"], trace[-1]["angles"]))
                + f" ({time.perf_counter() - t_start:.0f} s)")
    objects = json.loads((gt / "meta.json").read_text())["objects"]
    sco = motion_scores(learned_motion({**params, "deform": d}, alive, spec, parts, times), true, dirs)
    return {"trace": trace, "objects": [{"name": o["name"], "gaussians": int(len(idx)), **s,
                                         "along_ray_deg": ob["along_ray_deg"], "ray_spread_deg": ob["ray_spread_deg"]}
                                        for o, idx, s, ob in zip(objects, parts, sco, obs)],
            "parts_learned": int(sum(s["ok"] for s in sco)), "dropped_steps": dropped,
            "wall_s": time.perf_counter() - t_start}


def _print(r: dict) -> None:
    print(f"test views at training times: PSNR object pixels {r['psnr_object_pixels']:.2f}, "
          f"static pixels {r['psnr_static_pixels']:.2f}")
    print(f"{'part':<12} {'gaussians':>9} {'true_disp':>9} {'learned':>9} {'ratio':>6} {'angle':>6} "
          f"{'in image':>13}  ok   {'D to ray':>8} {'rays':>5}")
    for o in r["objects"]:
        print(f"{o['name']:<12} {o['gaussians']:>9} {o['at_tmax_true']:>9.3f} {o['at_tmax_learned']:>9.3f} "
              f"{o['at_tmax_ratio']:>6.2f} {o['at_tmax_angle_deg']:>6.1f} {o['at_tmax_image_ratio']:>6.2f} "
              f"{o['at_tmax_image_angle_deg']:>6.1f}  "
              f"{'yes' if o['at_tmax_ok'] else 'no ':<3} {o['along_ray_deg']:>8.1f} {o['ray_spread_deg']:>5.1f}")
    print("(angle: learned against true displacement at t*; in image: ratio and angle of the two projected "
          "on the plane normal to the "
          "ray at t*; D to ray: the true displacement's angle to that ray; rays: the widest angle between the rays to "
          "the part over the frames it spends in its t* state, the parallax that pins its motion along the rays)")
    print(f"parts learned (ratio within {RATIO_TOL:.0%} of 1, angle under {ANGLE_TOL_DEG:.0f} deg): "
          f"{r['parts_learned']} of {len(r['objects'])}")
    mv = r["moving_gaussians"]
    print(f"live Gaussians {r['live_gaussians']}; moving more than 0.01 / 0.05 / 0.1: "
          f"{mv['0.01']} / {mv['0.05']} / {mv['0.1']}")
    if r.get("static_weight") is not None:
        print(f"bases' weights: the static basis holds {r['static_weight']:.3f} of the live Gaussians' weight (mean); "
              "per part, its Gaussians' mean weight on each basis (basis 0: static):")
        for o in r["objects"]:
            print(f"{o['name']:<12} " + " ".join(f"{v:.3f}" for v in o["basis_weights"]))
    if any("flow" in o for o in r["objects"]):
        print("dynamic flow on each part's pixels (medians over the frame pairs in which it moves):")
        print(f"{'part':<12} {'pairs':>5} {'EPE GS-target':>13} {'|GS|/|target|':>13} {'EPE target-true':>15} "
              f"{'grad L_uGS':>10} {'grad photo':>10}")
        for o in r["objects"]:
            f = o.get("flow") or {}
            if f:
                print(f"{o['name']:<12} {f['frames']:>5} {f['epe_gs_target']:>13.2f} {f['ratio_gs_target']:>13.3f} "
                      f"{f['epe_target_true']:>15.2f} {f['grad_flow']:>10.3g} {f['grad_photo']:>10.3g}")
    if r.get("trace"):
        bases = any(row.get("static_weight") is not None for row in r["trace"])
        print("learned / true displacement at t* over training"
              + (" (then the static basis's mean weight: all live Gaussians, each part's):" if bases else ":"))
        names = [o["name"] for o in r["objects"]]
        print(f"{'step':>6} " + " ".join(f"{n:>12}" for n in names)
              + ("  w0 " + " ".join(f"{n:>12}" for n in ["all", *names]) if bases else ""))
        for row in r["trace"]:
            w0 = [row["static_weight"], *row["part_static_weights"]] if row.get("static_weight") is not None else None
            print(f"{row['step']:>6} " + " ".join(f"{v:>12.2f}" for v in row["ratios"])
                  + ("" if not bases else "     " + (" ".join(f"{v:>12.3f}" for v in w0) if w0 else "")))


def _train(args, data_dir: Path, run_dir: Path) -> list[dict]:
    cfg = load_config(args.train, overrides=args.set)
    prepare_run_folder(run_dir, data_dir, overwrite=args.overwrite)
    gt = _check_gt(data_dir)
    scene = load_scene(data_dir, "train", downscale=cfg.data.downscale)
    norm = scene.normalization
    times, true = true_motion(gt, norm)
    trace: list[dict] = []

    def monitor(step, state, spec):
        if state.static is None or state.static:
            return
        use = spec if step > cfg.train.warmup_steps else None
        parts, _, sc = part_scores(state.params, state.densify.alive, use, gt, norm, times, true)
        bw = basis_weights(state.params, state.densify.alive, use, parts)
        trace.append({"step": step, "ratios": [s["ratio"] for s in sc], "angles": [s["angle_deg"] for s in sc],
                      "static_weight": None if bw is None else bw["static_all"],
                      "part_static_weights": None if bw is None else [w[0] for w in bw["parts"]]})

    run_stage1(cfg, data_dir, run_dir, monitor=monitor)
    return trace


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench motion", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="stage-1 run folder (fgjax train --out)")
    p.add_argument("--data", required=True, help="the fgjax synth dataset it was trained on")
    p.add_argument("--flow", action="store_true", help="also the dynamic-flow diagnosis on each part's pixels")
    p.add_argument("--train", default=None, metavar="CONFIG",
                   help="train the run first with this config (the trace of learned motion over training)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (with --train)")
    p.add_argument("--overwrite", action="store_true", help="with --train: replace a run in --run")
    p.add_argument("--oracle", type=int, default=0, metavar="STEPS",
                   help="fit a fresh field alone on the true canonical Gaussians for STEPS steps (module docstring)")
    p.add_argument("--oracle-flow", choices=("estimated", "true", "none"), default="estimated",
                   help="with --oracle: the flow loss on the run's estimated optical flow, on the true one, or none")
    p.add_argument("--oracle-loss", choices=("pair", "track"), default="pair",
                   help="with --oracle: L_uGS of frame pairs or the first frame's tracks (flow.loss)")
    p.add_argument("--oracle-photo", type=float, default=0.0, metavar="W",
                   help="with --oracle: add W x the photometric loss (default 0: the flow loss alone)")
    p.add_argument("--oracle-lr", type=float, default=None, help="with --oracle: Adam rate (default train.lr_deform)")
    p.add_argument("--json", default=None, help="also write the report to this file")
    args = p.parse_args(argv)
    if args.oracle:
        try:
            r = oracle_fit(Path(args.run), Path(args.data), args.oracle, flow=args.oracle_flow, loss=args.oracle_loss,
                           photo=args.oracle_photo, lr=args.oracle_lr)
        except (FileNotFoundError, ValueError, ConfigError) as e:
            print(f"fgjax bench motion: {e}", file=sys.stderr)
            return 2
        for o in r["objects"]:
            print(f"{o['name']:<12} {o['gaussians']:>6} Gaussians  true {o['true']:.3f}  learned {o['learned']:.3f}  "
                  f"ratio {o['ratio']:.2f}  angle {o['angle_deg']:.1f} (in image {o['image_ratio']:.2f}, "
                  f"{o['image_angle_deg']:.1f})  "
                  f"{'yes' if o['ok'] else 'no'}  (D {o['along_ray_deg']:.0f} deg to the ray, rays "
                  f"{o['ray_spread_deg']:.1f} deg apart in its t* state)")
        print(f"parts learned from the true canonical Gaussians: {r['parts_learned']} of {len(r['objects'])} "
              f"({r['wall_s']:.0f} s; {r['dropped_steps']} step(s) dropped: tile buffer overflow or a non-finite loss)")
        if args.json:
            atomic_write(Path(args.json), lambda f: f.write(json.dumps(r, indent=1).encode()))
        return 0
    try:
        trace = _train(args, Path(args.data), Path(args.run)) if args.train else None
        r = motion_report(Path(args.run), Path(args.data), flow=args.flow)
    except (FileNotFoundError, ValueError, ConfigError) as e:
        print(f"fgjax bench motion: {e}", file=sys.stderr)
        return 2
    if trace is not None:
        r["trace"] = trace
    _print(r)
    if args.json:
        atomic_write(Path(args.json), lambda f: f.write(json.dumps(r, indent=1).encode()))
    return 0
