"""``fgjax eval --run RUN [--data DATA]``: control metrics against ground truth (synthetic gt/), or what can be
measured without it (a real capture).

Only this module reads ground truth; the pipeline never does. RUN/metrics.json gets a ``"control"`` entry (written
atomically, other entries kept). A scene without gt/meta.json (a real capture, `fgjax prepare`) gets
`evaluate_measurable`'s entries:

- ``ground_truth``: false.
- ``num_objects_found``; ``object_pixel_share`` {object (1-based): the share of the pixels it covers in the
  held-out test views, the stage-1 model's object ids at each view's time (`fgjax.method.result.render_clusters`),
  averaged over the views}; ``views``: how many.
- ``view_psnr_stage1``, ``view_ssim_stage1``: stage 1 on the held-out test views at their times.
- ``view_psnr_controlled``, ``view_ssim_controlled``: the controlled scene on the same views, each object moved to
  its trajectory vector at the view's time (v_c(t, k), `fgjax.method.result.cluster_vectors_at`: stage 2 replaying
  the motion it learned); with no object found, the controlled scene at rest.
- ``depth_error_static`` (where the test views have depth, e.g. LiDAR): over the pixels with depth that the
  stage-1 model covers (alpha >= 0.5) and labels static (id 0), the median and mean of |rendered depth - measured
  depth| in world units (metres for a Record3D capture), the median relative error |d - d*| / d*, and the number of
  pixels. The rendered depth is the expected depth (sum T alpha z / alpha).

With ground truth (DATA/gt/meta.json, `fgjax.synth`):

- ``ari``: adjusted Rand index of per-pixel object ids (`fgjax.method.result.render_clusters` with the stage-1
  model at the frame's time, 0 = static included) against gt object ids, over the test frames of
  kind "view" (pixels with gt id >= 0). It measures the discovery and clustering: which Gaussians of
  the reconstruction belong to which object.
- ``ari_controlled``: the same with the controlled scene at the frame's time (each object moved to
  its trajectory vector v_c(t, k)): this one also carries the errors of the trajectories.
- ``ari_gt_labels`` and ``ari_controlled_gt_labels``: ceilings of the two, the same renders with every
  Gaussian labelled from the ground truth instead of by stage 2 (`gt_labels_of_gaussians`, radius 0.06;
  a larger radius changes them by < 0.002 on the default scene): what perfect clustering would give with
  this geometry (and, for the second, these trajectories). The first is bounded by stage 1's geometry.
- ``ari_controlled_true_motion`` and ``ari_controlled_true_motion_gt_labels``: ``ari_controlled`` with each
  matched cluster moved rigidly by the gt motion of its object instead of by the control network, with the
  discovered labels and with the labels from the gt (radius 0.06): what perfect tracking, then perfect
  tracking and clustering, would give these "view" frames.
- ``state_psnr``: PSNR of controlled renders of the held-out "state" test frames. Each discovered
  cluster is matched to the gt object under most of its pixels in the training frames (majority
  vote: evaluation only). A control vector is the displacement of the cluster's centroid (its
  trajectory ς(t, k) is the mean centre of its Gaussians), so the gt state is turned into a vector
  the same way: the gt rigid motion of the matched object from its state at the reference (first)
  training frame to the held-out state (`fgjax.synth.object_transform`) applied to the
  cluster's reference centroid; the vector is snapped to the cluster's trajectory and fed to the
  control network.
- ``state_psnr_moving``: ``state_psnr`` over the pixels of the moving parts only (gt id >= 1 in the held-out
  frame; `masked_psnr`), mean over the state frames.
- ``part_iou``, ``parts_found``, ``parts_true`` (`part_ious`): for each gt part, the best IoU of its pixels with
  one discovered object's pixels over the "view" frames (the ids of ``ari``); found when >= 0.5.
- ``state_psnr_centre``: the same with the displacement of the gt object's centre instead. For a rotating part this
  differs from the centroid's displacement whenever the cluster covers the part unevenly, so it mixes an error of
  the protocol into the control error.
- ``state_mse_by_object`` and ``state_pixels_by_object``: where ``state_psnr`` loses, per gt object id (0 =
  static): {id: [per state frame]}: the id's pixels' squared error as a share of the frame's MSE (the shares
  sum to it: `error_by_object`), and the fraction of the pixels they are.
- ``state_mse_static_swept`` and ``state_pixels_static_swept``: the static pixels' share split in two,
  {"swept": [per state frame], "rest": [...]}: "swept" are the static pixels within 4 px of a part in the
  state frame or in the training frame it was made from (the same camera; `swept_mask`), which a part uncovers
  or passes over between the two states; "rest" the other static pixels. Their shares sum to ``state_mse_by_object``'s
  "0". ``fgjax eval --maps DIR`` also writes each state frame's render, image and error (`error_map_image`).
- ``state_psnr_stage1`` is stage 1 rendered at the frame's time, for reference.
- ``state_psnr_true_motion`` and ``state_psnr_true_motion_labels``: ceilings, no control network. The
  reference Gaussians with each matched cluster moved by the gt motion of its object (the discovered
  labels, then labels taken from the nearest gt Gaussian): what perfect tracking, then perfect tracking
  and clustering, would give this reconstruction.
- ``camera_rotation_error_{written,used}_deg`` and ``camera_centre_error_{written,used}`` (scene units):
  the training cameras as written and as the run used them (stage 1's pose deltas, which start from the
  flow bundle adjustment with ``pose.bundle``) against the gt cameras; means over the frames.
- ``camera_alignment`` and ``camera_{rotation,centre}_error_aligned``: a run that refines its cameras
  reconstructs the scene in its own frame, fixed only up to a similarity (the gauge; with pose noise, the
  noisy written poses pin it), so the exact test cameras see that scene shifted. As in the pose-refining
  NeRF literature (BARF's Procrustes alignment), every test-view metric above (``ari*``, ``state_psnr*``)
  is computed with the test cameras carried into the run's frame by the similarity x_run = s R x_true + t
  that best maps the gt training cameras onto the ones the run used (`align_cameras`:
  ``camera_alignment`` = {scale, rotation_deg, translation}; the identity, to round-off, when the
  cameras were not refined), and the training frames' metrics use the run's own cameras.
  ``state_psnr_unaligned`` and ``view_psnr_stage1_unaligned`` keep the exact test cameras; ``view_psnr_stage1``
  is stage 1 on the "view" test frames with the aligned ones.
- ``state_psnr_run_cameras`` (and ``_per_frame``): ``state_psnr`` with each state frame seen through the
  camera the run used for the training frame it was made from (`run_camera`; the synthetic scenes' state
  frames are training cameras at other object states, so this is the run's own estimate of the camera,
  per-frame error included, where the alignment above removes only the error common to all frames). The
  difference is what the cameras' per-frame error costs the held-out states (none where the cameras are exact).
- ``motion_preference`` (per matched cluster): does the image loss prefer the learned motion or the true
  one? On up to 8 training frames where the gt motion moves the cluster's centroid by more than 0.01
  (scene units) from the reference, the controlled scene's reference with only this cluster moved, once
  by the control network (its trajectory vector at the frame's time, ``l1_learned``) and once by the gt
  motion of its object (``l1_true``; ``l1_true_gt_labels`` with labels from the gt,
  `gt_labels_of_gaussians`, radius 0.03), is compared with the training image (mean absolute error over
  the image; the other objects stay at the reference in all three, so the differences come from this
  cluster). ``true_wins`` (``true_wins_gt_labels``) is the fraction of those frames where the true motion
  renders closer. A cluster whose true motion loses under its discovered labels but wins under gt labels
  cannot be tracked right by any photometric optimiser with those labels: its labels are the limit.
- ``trajectory_error``: mean over the matched clusters and the training times of the distance (scene
  units) between the cluster's centroid trajectory ς(t, k) and where the gt motion of its object takes
  the cluster's reference centroid: the tracking error alone, free of appearance and label errors.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np
from sklearn.neighbors import NearestNeighbors

from fgjax import metrics
from fgjax.data.loaders import load_scene
from fgjax.data.scene import Normalization
from fgjax.io import atomic_write
from fgjax.method import result
from fgjax.method.stage1 import evaluate as evaluate_stage1
from fgjax.method.stage1 import load_test_views, refined_viewmats, render_frame
from fgjax.method.stage2 import discover_run, prepare_run
from fgjax.metrics import rotation_angle_deg
from fgjax.synth import SynthObject, compose_transforms

__all__ = ["write_control_metrics", "evaluate_measurable", "align_cameras", "run_camera", "apply_alignment",
           "camera_errors", "error_by_object", "evaluate_control", "gt_labels_of_gaussians", "gt_motion_scene",
           "gt_objects", "gt_point_motion", "gt_transform", "masked_psnr", "part_ious"]


def gt_transform(objs: dict, label: int, states) -> np.ndarray:
    """World transform [4, 4] of gt object `label` of `objs` (`gt_objects`) at the state vector `states` [K_gt]
    (`fgjax.synth.compose_transforms`: a part attached to another moves with it)."""
    ordered = [objs[k] for k in sorted(objs)]
    return compose_transforms(ordered, np.asarray(states, np.float64).reshape(-1))[label]


def gt_motion_scene(objs: dict, label: int, s_from, s_to, norm) -> np.ndarray:
    """The gt rigid motion [4, 4] (x -> R x + t) of synthetic object `label` of `objs` (`gt_objects`) from the
    state vector `s_from` [K_gt] to `s_to` [K_gt], in the run's scene units (`norm`: the run's `Normalization`,
    x_scene = scale (x_world - centre)): R is unchanged and t = scale (R c + t_world - c)."""
    mo = gt_transform(objs, label, s_to) @ np.linalg.inv(gt_transform(objs, label, s_from))
    out = np.eye(4)
    out[:3, :3] = mo[:3, :3]
    out[:3, 3] = norm.scale * (mo[:3, :3] @ norm.centre + mo[:3, 3] - norm.centre)
    return out


def gt_point_motion(objs: dict, label: int, s_from, s_to, point, norm):
    """Where the gt motion of synthetic object `label` of `objs` (`gt_objects`) from the state vector `s_from`
    [K_gt] to `s_to` [K_gt] takes a point given in the run's scene units (`norm`: the run's `Normalization`);
    scene units [3]."""
    tr = gt_motion_scene(objs, label, s_from, s_to, norm)
    return tr[:3, :3] @ np.asarray(point, np.float64) + tr[:3, 3]


def camera_errors(viewmats, true) -> tuple[float, float]:
    """Mean rotation error (degrees) and mean camera-centre distance (the viewmats' units) of world-to-camera
    `viewmats` [T, 4, 4] against `true` [T, 4, 4]."""
    a, b = np.asarray(viewmats, np.float64), np.asarray(true, np.float64)

    rel = a[:, :3, :3] @ np.transpose(b[:, :3, :3], (0, 2, 1))
    ca = -np.einsum("tji,tj->ti", a[:, :3, :3], a[:, :3, 3])
    cb = -np.einsum("tji,tj->ti", b[:, :3, :3], b[:, :3, 3])
    return float(rotation_angle_deg(rel).mean()), float(np.linalg.norm(ca - cb, axis=1).mean())


def run_camera(test_true, source_true, source_used, scale: float = 1.0) -> np.ndarray:
    """A test camera [4, 4] in the run's frame by way of the training camera it was made from: the gt
    relative pose D = test_true source_true^-1 (its translation times the alignment's `scale`) applied to
    the camera the run used for that training frame, D source_used. For a held-out state seen from a
    training camera (D = I) this is the run's own estimate of that camera, with its per-frame error."""
    d = np.asarray(test_true, np.float64) @ np.linalg.inv(np.asarray(source_true, np.float64))
    d[:3, 3] *= float(scale)
    return d @ np.asarray(source_used, np.float64)


def _centres(viewmats) -> np.ndarray:
    """Camera centres [T, 3] of world-to-camera `viewmats` [T, 4, 4]: -R^T t."""
    v = np.asarray(viewmats, np.float64)
    return -np.einsum("tji,tj->ti", v[:, :3, :3], v[:, :3, 3])


def align_cameras(viewmats, true) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, R [3, 3], t [3]) with x = s R x_true + t that carries the cameras `true` [T, 4, 4]
    (world-to-camera, OpenCV) onto `viewmats` [T, 4, 4] of the same frames: R from the cameras' orientations
    (R_i R ~ R_true_i, the chordal mean of R_true_i^T R_i, transposed), then s and t by least squares on the
    camera centres. Needs T >= 1; with one camera (or all centres at one point) s is 1."""
    v, tr = np.asarray(viewmats, np.float64), np.asarray(true, np.float64)
    if v.ndim != 3 or v.shape[1:] != (4, 4) or v.shape != tr.shape or len(v) == 0:
        raise ValueError(f"align_cameras: viewmats and true must both be [T, 4, 4] with T >= 1, got {list(v.shape)} "
                         f"and {list(tr.shape)}")
    m = np.einsum("tji,tjk->ik", tr[:, :3, :3], v[:, :3, :3])  # sum_i R_true_i^T R_i = T R^T for exact cameras
    u, _, vt = np.linalg.svd(m)
    rot = (u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt).T
    a, b = _centres(tr) @ rot.T, _centres(v)  # [T, 3] R c_true, c
    da, db = a - a.mean(0), b - b.mean(0)
    den = float(np.sum(da * da))
    s = float(np.sum(da * db) / den) if den > 1e-12 * max(1.0, float(np.sum(a * a))) else 1.0
    if not s > 0:  # degenerate centres: no scale can be told
        s = 1.0
    return s, rot, b.mean(0) - s * a.mean(0)


def apply_alignment(viewmats, s: float, rot, t) -> np.ndarray:
    """Cameras `viewmats` [T, 4, 4] of the frame x_true carried into the frame x = s R x_true + t: [T, 4, 4]
    world-to-camera with rotation R_i R^T and translation s t_i - R_i R^T t (the same image of every point;
    camera-space lengths are scaled by s, which a projection does not see)."""
    v = np.array(viewmats, np.float64)
    rc = v[:, :3, :3] @ np.asarray(rot, np.float64).T
    out = v.copy()
    out[:, :3, :3] = rc
    out[:, :3, 3] = float(s) * v[:, :3, 3] - rc @ np.asarray(t, np.float64)
    return out


def masked_psnr(img, ref, mask) -> float:
    """PSNR (peak 1) of `img` against `ref` [H, W, 3] over the pixels of `mask` [H, W] (nan where it is empty)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return float("nan")
    err = np.mean((np.asarray(img, np.float64)[m] - np.asarray(ref, np.float64)[m]) ** 2)
    return float(10.0 * np.log10(1.0 / max(err, 1e-12)))


def part_ious(gt_ids, pred_ids, num_parts: int, found_iou: float = 0.5) -> dict:
    """Which gt parts were discovered: for each gt part j in 1..`num_parts`, the largest IoU of its pixels
    (``gt_ids == j``, pooled over the frames given) with the pixels of one discovered object
    (``pred_ids == c``, c >= 1). A part counts as found when that IoU is >= `found_iou`.

    Args:
        gt_ids, pred_ids: [P] int per-pixel ids of the same pixels (0 = static).
        num_parts: the number of gt parts.

    Returns:
        {"part_iou": {str(j): IoU}, "part_best_object": {str(j): c or 0}, "parts_true": num_parts,
        "parts_found": count}.
    """
    g, p = np.asarray(gt_ids, np.int64).ravel(), np.asarray(pred_ids, np.int64).ravel()
    ious, best = {}, {}
    for j in range(1, num_parts + 1):
        gj = g == j
        top, arg = 0.0, 0
        for c in np.unique(p[gj | (p > 0)]):
            if c < 1:
                continue
            pc = p == c
            union = int(np.sum(gj | pc))
            iou = float(np.sum(gj & pc)) / union if union else 0.0
            if iou > top:
                top, arg = iou, int(c)
        ious[str(j)], best[str(j)] = top, arg
    return {"part_iou": ious, "part_best_object": best, "parts_true": int(num_parts),
            "parts_found": int(sum(v >= found_iou for v in ious.values()))}


def gt_objects(meta: dict) -> dict:
    """The synthetic objects of a scene's gt/meta.json, by label: {label: `fgjax.synth.SynthObject`}."""
    return {int(o["label"]): SynthObject(**{f: (np.asarray(v, np.float64) if isinstance(v, list) else v)
                                            for f, v in o.items()}) for o in meta.get("objects", [])}


def gt_labels_of_gaussians(means, gt_dir: Path, objs: dict, states, norm, match: dict[int, int],
                           radius: float) -> np.ndarray:
    """Evaluation only: each reconstructed Gaussian (centres `means` [N, 3], scene units, at the gt `states`
    [K_gt] of the objects `objs`, `gt_objects`) labelled with the cluster index (0-based, -1 = static) that
    `match` (cluster -> gt label) gives the gt object of its nearest gt Gaussian (gt_dir/canonical.npz),
    when that one lies within `radius` (scene units) and is on a moving part; [N] int."""
    z = np.load(gt_dir / "canonical.npz")
    pts, lab = np.asarray(z["means"], np.float64), np.asarray(z["labels"], np.int64)  # world, state 0
    for label in objs:
        sel = lab == label
        tr = gt_transform(objs, label, states)
        pts[sel] = pts[sel] @ tr[:3, :3].T + tr[:3, 3]
    nn = NearestNeighbors(n_neighbors=1).fit(norm.points_to_scene(pts))
    d, j = nn.kneighbors(np.asarray(means, np.float64))
    near = lab[j[:, 0]]
    to_cluster = {g: c for c, g in sorted(match.items(), reverse=True) if g >= 1}
    return np.array([to_cluster.get(int(g), -1) if (dd <= radius and g >= 1) else -1
                     for g, dd in zip(near, d[:, 0])], np.int32)


def evaluate_control(run, data_dir: Path, log=print, maps_dir: Path | None = None) -> dict:
    """The metrics above (a dict); raises FileNotFoundError without ground truth. With `maps_dir`, each held-out
    state frame's render, image and error (`error_map_image`) go to maps_dir/state_NNN.png (NNN its test index)."""
    gt = data_dir / "gt"
    meta = json.loads((gt / "meta.json").read_text())
    norm = Normalization.from_dict(run.meta["normalization"])
    ds = run.cfg.data.downscale
    train = load_scene(data_dir, "train", normalize=norm, downscale=ds)
    test = load_scene(data_dir, "test", normalize=norm, downscale=ds)
    s2 = run.s2
    kinds = [f.get("kind", "view") for f in meta.get("test_frames", [])]
    ids_test = np.load(gt / "test" / "object_id.npy")
    ids_train = np.load(gt / "train" / "object_id.npy")
    res: dict = {"num_objects_found": s2.num_objects, "num_objects_gt": len(meta.get("objects", []))}

    used = np.asarray(refined_viewmats(run.state.params, train.viewmats), np.float64)
    test_exact = test
    true_train = None  # the gt training cameras (scene units)
    if (gt / "train" / "viewmats_true.npy").is_file():  # the training cameras: written, then as used
        true_train = true = norm.viewmats_to_scene(np.load(gt / "train" / "viewmats_true.npy"))
        for key, vm in (("written", train.viewmats), ("used", used)):
            res[f"camera_rotation_error_{key}_deg"], res[f"camera_centre_error_{key}"] = camera_errors(vm, true)
        s, rot, t = align_cameras(used, true)
        res["camera_alignment"] = {"scale": s, "rotation_deg": float(metrics.rotation_angle_deg(rot)),
                                   "translation": [float(x) for x in t]}
        res["camera_rotation_error_aligned_deg"], res["camera_centre_error_aligned"] = camera_errors(
            used, apply_alignment(true, s, rot, t))
        # the test cameras into the run's frame (module docstring)
        test = dataclasses.replace(test, viewmats=apply_alignment(test.viewmats, s, rot, t).astype(
            np.asarray(test.viewmats).dtype))
    train = dataclasses.replace(train, viewmats=used.astype(np.asarray(train.viewmats).dtype))  # the run's own cameras
    def view_aris(source: str, labels=None, keep: list | None = None) -> list[float]:
        """ARI of each "view" test frame's rendered ids (`fgjax.method.result.render_clusters`) against the gt ids
        (the (gt, predicted) id pairs of the valid pixels appended to ``keep``)."""
        out = []
        for i, kd in enumerate(kinds):
            if kd != "view":
                continue
            pred = result.render_clusters(run, test.viewmats[i], test.Ks[i], test.width, test.height,
                                          t=test.times[i], source=source, labels=labels)
            ok = ids_test[i] >= 0
            out.append(float(metrics.ari(ids_test[i][ok], pred[ok])))
            if keep is not None:
                keep.append((ids_test[i][ok], pred[ok]))
        return out

    for key, source in (("ari", "stage1"), ("ari_controlled", "control")):
        pairs: list = []
        aris = view_aris(source, keep=pairs)
        if aris:
            res[key] = float(np.mean(aris))
            res[f"{key}_per_view"] = aris
            if source == "stage1":
                res.update(part_ious(np.concatenate([a for a, _ in pairs]), np.concatenate([b for _, b in pairs]),
                                     len(meta.get("objects", []))))
    # stage 1 on the "view" test frames, with the aligned cameras (and the exact ones when they differ)
    for key, cams in (("view_psnr_stage1", test),
                      ("view_psnr_stage1_unaligned", test_exact))[:1 + (test_exact is not test)]:
        ps_v = [float(metrics.psnr(render_frame(run.state, run.spec, run.cfg, cams.viewmats[i], cams.Ks[i],
                                                cams.times[i], cams.width, cams.height), cams.images[i]))
                for i, kd in enumerate(kinds) if kd == "view"]
        if ps_v:
            res[key] = float(np.mean(ps_v))
    # cluster -> gt object matching by pixel majority over training frames
    k = s2.num_objects
    votes = np.zeros((k + 1, int(ids_train.max()) + 1 if ids_train.size else 1))
    for i in np.linspace(0, train.num_frames - 1, min(train.num_frames, 8)).round().astype(int):
        pred = result.render_clusters(run, train.viewmats[i], train.Ks[i], train.width, train.height,
                                      t=train.times[i])
        ok = ids_train[i] >= 0
        np.add.at(votes, (pred[ok], ids_train[i][ok]), 1)
    match = {c: int(np.argmax(votes[c + 1])) for c in range(k)}  # cluster c (0-based) -> gt label (0 static)
    res["match"] = {str(c + 1): match[c] for c in range(k)}
    # held-out states
    c_train = np.load(gt / "train" / "centres.npy")  # [T, Kobj, 3] world units
    t_train = np.load(gt / "train" / "times.npy")
    ref = int(np.argmin(np.abs(t_train - s2.t0)))
    c_test = np.load(gt / "test" / "centres.npy")
    objs = gt_objects(meta)
    states_train = np.load(gt / "train" / "states.npy") if (gt / "train" / "states.npy").is_file() else None
    if states_train is not None and k and "view" in kinds:  # the ARI ceilings: labels from the gt
        for key, source, means in (("ari_gt_labels", "stage1", run.deformed(s2.t0)[0]),
                                   ("ari_controlled_gt_labels", "control", run.base()[0])):
            lab = gt_labels_of_gaussians(np.asarray(means), gt, objs, states_train[ref], norm, match, 0.06)
            res[key] = float(np.mean(view_aris(source, lab)))
            if source == "control":
                res.update(_true_motion_aris(run, test, ids_test, meta, kinds, objs, match, states_train[ref], norm,
                                             lab))
    # trajectory error: each cluster's centroid trajectory against the gt motion of the same point
    if states_train is not None and k:
        errs = {}
        for c in range(k):
            if match[c] not in objs:
                continue
            true = [gt_point_motion(objs, match[c], states_train[ref],
                                    states_train[int(np.argmin(np.abs(t_train - tt)))], s2.traj[c, 0], norm)
                    for tt in s2.traj_times]
            errs[str(c + 1)] = float(np.mean(np.linalg.norm(np.asarray(true) - s2.traj[c], axis=-1)))
        if errs:
            res["trajectory_error"] = float(np.mean(list(errs.values())))
            res["trajectory_error_per_object"] = errs
    ps, ps_c, ps1, by_obj, ps_exact, ps_run, swept, ps_mov = [], [], [], [], [], [], [], []
    if maps_dir is not None:
        maps_dir = Path(maps_dir)
        maps_dir.mkdir(parents=True, exist_ok=True)
    for i, kd in enumerate(kinds):
        if kd != "state":
            continue
        src = meta["test_frames"][i].get("source_index")
        vecs, vecs_c = np.zeros((max(k, 1), 3)), np.zeros((max(k, 1), 3))
        for c in range(k):
            j = match[c]
            if j < 1:
                continue
            d = norm.lengths_to_scene(c_test[i, j - 1] - c_train[ref, j - 1])
            vecs_c[c] = result.snap_vector(s2, c, d)[0]
            s_test = meta["test_frames"][i].get("states")
            if j not in objs or s_test is None:
                vecs[c] = vecs_c[c]
                continue
            s_ref = states_train[ref] if states_train is not None else np.zeros(len(objs))
            d = gt_point_motion(objs, j, s_ref, s_test, s2.traj[c, 0], norm) - s2.traj[c, 0]
            vecs[c] = result.snap_vector(s2, c, d)[0]
        for v, out in ((vecs, ps), (vecs_c, ps_c)):
            img = result.render_controlled(run, v[:k] if k else v, test.viewmats[i], test.Ks[i], test.width,
                                           test.height)
            out.append(float(metrics.psnr(img, test.images[i])))
            if out is ps:
                by_obj.append(error_by_object(img, test.images[i], ids_test[i]))
                mov = ids_test[i] >= 1
                if mov.any():
                    ps_mov.append(masked_psnr(img, test.images[i], mov))
                if src is not None and 0 <= int(src) < len(ids_train):
                    sw = swept_mask(ids_test[i], ids_train[int(src)]) & (ids_test[i] == 0)
                    swept.append(error_by_object(img, test.images[i],
                                                 np.where(sw, 1, np.where(ids_test[i] == 0, 0, -1))))
                if maps_dir is not None:
                    emap = error_map_image(img, test.images[i])
                    atomic_write(maps_dir / f"state_{i:03d}.png", lambda f: iio.imwrite(f, emap, extension=".png"))
        if test_exact is not test:
            img = result.render_controlled(run, vecs[:k] if k else vecs, test_exact.viewmats[i], test.Ks[i],
                                           test.width, test.height)
            ps_exact.append(float(metrics.psnr(img, test.images[i])))
        if true_train is not None and src is not None and 0 <= int(src) < len(used):
            img = result.render_controlled(run, vecs[:k] if k else vecs,
                                           run_camera(test_exact.viewmats[i], true_train[int(src)], used[int(src)],
                                                      res["camera_alignment"]["scale"]),
                                           test.Ks[i], test.width, test.height)
            ps_run.append(float(metrics.psnr(img, test.images[i])))
        img1 = render_frame(run.state, run.spec, run.cfg, test.viewmats[i], test.Ks[i], test.times[i], test.width,
                            test.height)
        ps1.append(float(metrics.psnr(img1, test.images[i])))
    if ps:
        res["state_psnr"] = float(np.mean(ps))
        res["state_psnr_per_frame"] = ps
        if ps_mov:
            res["state_psnr_moving"] = float(np.mean(ps_mov))
        res["state_psnr_centre"] = float(np.mean(ps_c))
        res["state_psnr_stage1"] = float(np.mean(ps1))
        if ps_exact:
            res["state_psnr_unaligned"] = float(np.mean(ps_exact))
        if len(ps_run) == len(ps):
            res["state_psnr_run_cameras"] = float(np.mean(ps_run))
            res["state_psnr_run_cameras_per_frame"] = ps_run
        labels_seen = sorted({g for row in by_obj for g in row})
        ids = {g: g for g in labels_seen}
        res["state_mse_by_object"], res["state_pixels_by_object"] = (_per_frame(by_obj, f, ids)
                                                                     for f in ("mse", "pixels"))
        if swept and len(swept) == len(ps):  # the static pixels' share split: swept by a part (1) or not (0)
            ids = {"swept": "1", "rest": "0"}
            res["state_mse_static_swept"], res["state_pixels_static_swept"] = (_per_frame(swept, f, ids)
                                                                               for f in ("mse", "pixels"))
    if k and states_train is not None:
        # the controlled scene's reference labelled from the gt (radius 0.03): the ceilings' and motion_preference's
        lab_gt = gt_labels_of_gaussians(np.asarray(run.base()[0]), gt, objs, states_train[ref], norm, match, 0.03)
        if ps:
            res.update(_true_motion_psnr(run, test, meta, objs, match, states_train[ref], norm, lab_gt))
        pref = _motion_preference(run, train, objs, match, states_train, ref, norm, lab_gt)
        if pref:
            res["motion_preference"] = pref
    return res


def error_by_object(img, image, ids) -> dict[str, dict[str, float]]:
    """The squared error of a render `img` [H, W, 3] against `image` split by the gt object id of each pixel
    (`ids` [H, W], 0 static, < 0 left out): {str(id): {"mse": that id's share of the image's MSE (its pixels'
    squared error summed, over all H W pixels and the channels), "pixels": the fraction of the pixels it
    holds}}. Over the ids the shares sum to the MSE of the pixels with id >= 0 (the whole image's when no id is
    negative), so they say where a PSNR is lost."""
    se = np.mean((np.asarray(img, np.float64) - np.asarray(image, np.float64)) ** 2, axis=-1)  # [H, W]
    ids = np.asarray(ids)
    if ids.shape != se.shape:
        raise ValueError(f"error_by_object: ids must have shape {list(se.shape)}, got {list(ids.shape)}")
    return {str(int(g)): {"mse": float(se[ids == g].sum() / se.size), "pixels": float(np.mean(ids == g))}
            for g in np.unique(ids) if g >= 0}


def _per_frame(rows: list[dict], field: str, ids: dict[str, str]) -> dict[str, list[float]]:
    """{name: [row[id][field] for each frame's row]} from per-frame `error_by_object` rows, 0 where a frame lacks
    the id."""
    return {name: [row.get(g, {field: 0.0})[field] for row in rows] for name, g in ids.items()}


def swept_mask(ids_state, ids_source, radius: int = 4) -> np.ndarray:
    """Pixels [H, W] (bool) a part covers in either of two views from the same camera: a held-out state frame
    (`ids_state` [H, W], gt object ids, 0 static, < 0 no gt) and the training frame it was made from
    (`ids_source` [H, W]), grown by `radius` pixels (a square neighbourhood). Its static pixels are those a
    part uncovers or sweeps past between the two states: where a reconstruction that blurs the parts' states
    leaves ghosts."""
    a, b = np.asarray(ids_state), np.asarray(ids_source)
    if a.shape != b.shape:
        raise ValueError(f"swept_mask: ids_source must have shape {list(a.shape)}, got {list(b.shape)}")
    m = ((a > 0) | (b > 0)).astype(np.uint8)
    if radius > 0:
        m = cv2.dilate(m, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    return m.astype(bool)


def error_map_image(img, image, gain: float = 4.0) -> np.ndarray:
    """uint8 [H, 3 W, 3]: the render `img`, the image and their absolute difference x `gain` (per channel,
    clipped), side by side, for looking at where a held-out state loses (`fgjax eval --maps`)."""
    img, image = np.clip(np.asarray(img, np.float64), 0, 1), np.clip(np.asarray(image, np.float64), 0, 1)
    err = np.clip(np.abs(img - image) * gain, 0, 1)
    return (np.concatenate([img, image, err], axis=1) * 255 + 0.5).astype(np.uint8)


def _render_posed(run, labels, poses, viewmat, K, width: int, height: int) -> np.ndarray:
    """Image [H, W, 3] in [0, 1] of the controlled scene's reference (`LoadedRun.base`, no control network)
    with each cluster's Gaussians (`labels` [N], -1 static) moved by its pose (`poses` [K, 4, 4])."""
    img, _, _ = run.render_geometry(*result.posed_base(run, labels, poses), viewmat, K, width, height,
                                    params=run.control_params())
    return np.clip(np.asarray(img), 0.0, 1.0)


def _motion_preference(run, train, objs: dict, match: dict[int, int], states, ref: int, norm, lab_gt,
                       max_frames: int = 8, min_move: float = 0.01) -> dict:
    """``motion_preference`` (module docstring): {cluster (1-based, str): {frames, l1_learned, l1_true,
    l1_true_gt_labels, true_wins, true_wins_gt_labels}} over training frames `train` with gt `states`
    [T, K_gt] (``ref``: the reference frame's row); ``lab_gt`` [N]: the reference's labels from the gt."""
    s2 = run.s2
    out: dict = {}
    for c, j in sorted(match.items()):
        if j < 1 or j not in objs:
            continue
        s_ref = states[ref]
        moved = [i for i in range(train.num_frames)
                 if np.linalg.norm(gt_point_motion(objs, j, s_ref, states[i], s2.traj[c, 0], norm)
                                   - s2.traj[c, 0]) > min_move]
        if not moved:
            continue
        frames = [moved[a] for a in np.unique(np.linspace(0, len(moved) - 1, min(len(moved), max_frames)).round()
                                              .astype(int))]
        rows = []
        for i in frames:
            image = np.asarray(train.images[i], np.float64)
            vec = np.zeros((s2.num_objects, 3))
            vec[c] = result.cluster_vectors_at(s2, float(train.times[i]))[c]
            learned = result.render_controlled(run, vec, train.viewmats[i], train.Ks[i], train.width, train.height)
            poses = np.tile(np.eye(4), (s2.num_objects, 1, 1))
            poses[c] = gt_motion_scene(objs, j, s_ref, states[i], norm)
            row = [float(np.abs(learned - image).mean())]
            for labels in (s2.labels, lab_gt):
                img = _render_posed(run, labels, poses, train.viewmats[i], train.Ks[i], train.width, train.height)
                row.append(float(np.abs(img - image).mean()))
            rows.append(row)
        r = np.asarray(rows)
        out[str(c + 1)] = {"frames": len(frames), "l1_learned": float(r[:, 0].mean()), "l1_true": float(r[:, 1].mean()),
                           "l1_true_gt_labels": float(r[:, 2].mean()), "true_wins": float(np.mean(r[:, 1] < r[:, 0])),
                           "true_wins_gt_labels": float(np.mean(r[:, 2] < r[:, 0]))}
    return out


def _gt_poses(k: int, match: dict[int, int], objs: dict, s_from, s_to, norm) -> np.ndarray:
    """[k, 4, 4]: each matched cluster's pose, the gt motion of its object from state ``s_from`` [K_gt] to
    ``s_to`` [K_gt] (`gt_motion_scene`); the identity for a cluster matched to no gt object."""
    poses = np.tile(np.eye(4), (k, 1, 1))
    for c, j in match.items():
        if j >= 1 and j in objs:
            poses[c] = gt_motion_scene(objs, j, s_from, s_to, norm)
    return poses


def _true_motion_aris(run, test, ids_test, meta: dict, kinds, objs: dict, match: dict[int, int], s_ref, norm,
                      lab_gt) -> dict:
    """``ari_controlled_true_motion`` and ``ari_controlled_true_motion_gt_labels`` (module docstring): the ARI of
    each "view" test frame's ids with every matched cluster moved by the gt motion of its object from the
    reference state `s_ref` [K_gt] to the frame's (`fgjax.method.result.render_clusters` with ``poses``), the discovered
    labels and then ``lab_gt`` [N]; means over the frames."""
    s2 = run.s2
    out: dict = {"ari_controlled_true_motion": [], "ari_controlled_true_motion_gt_labels": []}
    for i, kd in enumerate(kinds):
        states = meta["test_frames"][i].get("states")
        if kd != "view" or states is None:
            continue
        poses = _gt_poses(s2.num_objects, match, objs, s_ref, states, norm)
        ok = ids_test[i] >= 0
        for key, labels in zip(out, (None, lab_gt)):
            pred = result.render_clusters(run, test.viewmats[i], test.Ks[i], test.width, test.height, poses=poses,
                                          labels=labels)
            out[key].append(float(metrics.ari(ids_test[i][ok], pred[ok])))
    return {key: float(np.mean(v)) for key, v in out.items() if v}


def _true_motion_psnr(run, test, meta: dict, objs: dict, match: dict[int, int], s_ref, norm, lab_gt) -> dict:
    """Ceilings of the state PSNR: the controlled scene's reference Gaussians (`LoadedRun.base`, no control
    network) with every matched cluster moved by the gt motion of its object from the reference state
    `s_ref` [K_gt] to the held-out state. ``state_psnr_true_motion`` keeps the discovered labels,
    ``state_psnr_true_motion_labels`` takes them from the gt (`gt_labels_of_gaussians`, radius 0.03): the
    first is what perfect tracking would give, the second what perfect tracking and clustering would
    (``lab_gt`` [N]: the reference's labels from the gt)."""
    s2 = run.s2
    label_sets = {"state_psnr_true_motion": np.asarray(s2.labels), "state_psnr_true_motion_labels": lab_gt}
    out: dict = {key: [] for key in label_sets}
    for i, f in enumerate(meta.get("test_frames", [])):
        if f.get("kind") != "state" or f.get("states") is None:
            continue
        poses = _gt_poses(s2.num_objects, match, objs, s_ref, f["states"], norm)
        for key, labels in label_sets.items():
            img = _render_posed(run, labels, poses, test.viewmats[i], test.Ks[i], test.width, test.height)
            out[key].append(float(metrics.psnr(img, test.images[i])))
    return {key: float(np.mean(v)) for key, v in out.items() if v}


def evaluate_measurable(run, data_dir: Path, log=print, min_alpha: float = 0.5) -> dict:
    """The metrics of a scene without ground truth (module docstring: ``ground_truth`` false, objects and their
    share of the frame, stage-1 test PSNR/SSIM, depth error on static pixels where the test views have depth; a
    pixel's depth counts where the model covers it, alpha >= ``min_alpha``)."""
    norm = Normalization.from_dict(run.meta["normalization"])
    test, _, _ = load_test_views(Path(data_dir), run.cfg, norm)
    k = run.s2.num_objects
    res: dict = {"ground_truth": False, "num_objects_found": k}
    if test is None or not test.num_frames:
        log("eval: the scene has no test views; only the number of objects is measured")
        return res
    m = evaluate_stage1(run.state, run.spec, run.cfg, test)
    res.update(view_psnr_stage1=m["psnr"], view_ssim_stage1=m["ssim"], views=test.num_frames)
    shares = np.zeros(k)
    errs, rel, ps_c, ss_c = [], [], [], []
    for i in range(test.num_frames):
        args = (test.viewmats[i], test.Ks[i])
        vec = result.cluster_vectors_at(run.s2, float(test.times[i])) if k else np.zeros((0, 3))
        img = result.render_controlled(run, vec, *args, test.width, test.height)
        ps_c.append(float(metrics.psnr(img, test.images[i])))
        ss_c.append(float(metrics.ssim(img, test.images[i])))
        ids = result.render_clusters(run, *args, test.width, test.height, t=float(test.times[i]))
        shares += np.array([np.mean(ids == c + 1) for c in range(k)]) / test.num_frames
        if test.depths is not None:
            _, d, alpha = render_frame(run.state, run.spec, run.cfg, *args, float(test.times[i]), test.width,
                                       test.height, depth=True)
            ref = np.asarray(test.depths[i], np.float64)
            ok = (ref > 0) & (alpha >= min_alpha) & (ids == 0) & (d > 0)
            errs.append(norm.lengths_to_world(np.abs(d[ok] - ref[ok])))
            rel.append(np.abs(d[ok] - ref[ok]) / ref[ok])
    res["object_pixel_share"] = {str(c + 1): float(shares[c]) for c in range(k)}
    res["view_psnr_controlled"], res["view_ssim_controlled"] = float(np.mean(ps_c)), float(np.mean(ss_c))
    if errs and sum(len(e) for e in errs):
        e, r = np.concatenate(errs), np.concatenate(rel)
        res["depth_error_static"] = {"median": float(np.median(e)), "mean": float(np.mean(e)),
                                     "median_relative": float(np.median(r)), "pixels": int(len(e)),
                                     "unit": "world units of the scene (metres for a Record3D capture)"}
    return res


def write_control_metrics(run, data_dir: Path | None = None, maps_dir: Path | None = None, log=print) -> dict:
    """`evaluate_control` of a loaded run (`fgjax.method.result.load_stage2`), or `evaluate_measurable` where the
    dataset has no ground truth (gt/meta.json), written into RUN/metrics.json under "control" (atomically; the other
    entries kept). ``data_dir`` defaults to the dataset stage 2 recorded. Returns the metrics."""
    data = Path(data_dir) if data_dir is not None else Path(run.s2.meta.get("data_dir", ""))
    if (data / "gt" / "meta.json").is_file():
        res = evaluate_control(run, data, log=log, maps_dir=maps_dir)
    else:
        res = evaluate_measurable(run, data, log=log)
    path = Path(run.run_dir) / "metrics.json"
    old = json.loads(path.read_text()) if path.is_file() else {}
    old["control"] = res
    atomic_write(path, lambda f: f.write(json.dumps(old, indent=1).encode()))
    return res


def discovery_trace(run_dir: Path, data_dir: Path, cfg, log=print, flow_threshold: float = 0.5) -> dict:
    """Where discovery (step 5) loses a moving part, against the synthetic ground truth: step 5 is run again on
    the stage-1 run (`fgjax.method.stage2.discover_run` with the stage-2 options `cfg`), and its per-pixel
    flags |u - u_cam| and its dynamic set D are compared with the truth.

    - ``moving_pixels_flagged``: share of the true moving pixels (|gt object flow| > `flow_threshold` px, gt flow
      valid) that the flag marks, pooled over the training pairs; per part in ``part_pixels_flagged``;
    - ``static_pixels_flagged``: share of the true static pixels (gt id 0) it marks;
    - per part (``part_gaussians``): how many live reconstructed Gaussians lie on it (nearest gt Gaussian within
      0.06 scene units, at the first training time), how many of those entered D, and how many stage 2 put in an
      object (``RUN/stage2.npz``'s labels, where present);
    - in the first training frame, with D drawn as a one-channel image (1 for its members) by the stage-1 model:
      ``dynamic_pixels_on_parts``, the share of D's drawn weight on the parts' true pixels (a precision of D in the
      image, whatever the depth of its Gaussians), and per part (``part_pixels_dynamic``) the share of its pixels
      that D draws with weight >= 0.5.

    A part lost with few flagged pixels is lost to the flow or camera flow or the threshold; one with flagged
    pixels but few Gaussians in D to the back-projection (scores); one with Gaussians in D but none in an object
    to the clustering. Returns {} with a ``note`` when the run's image size is not the ground truth's.
    """
    run_dir, data_dir = Path(run_dir), Path(data_dir)
    gt = data_dir / "gt"
    meta = json.loads((gt / "meta.json").read_text())
    run, scene, _ = prepare_run(run_dir, data_dir, log=lambda *_: None)
    cache = Path(cfg.flow_cache) if getattr(cfg, "flow_cache", None) else run_dir / "flow_cache"
    disc, _, _, (order, _, _) = discover_run(run, scene, cfg, cache, log=lambda *_: None)
    ids = np.load(gt / "train" / "object_id.npy")
    if ids.shape[1:] != (scene.height, scene.width):
        return {"note": f"ground truth is {ids.shape[2]}x{ids.shape[1]}, the run {scene.width}x{scene.height}"}
    obj_flow = np.load(gt / "train" / "object_flow.npy")
    fvalid = np.load(gt / "train" / "flow_valid.npy")
    n_parts = len(meta.get("objects", []))
    flagged = {"moving": [0, 0], "static": [0, 0]}
    per_part = {j: [0, 0] for j in range(1, n_parts + 1)}
    for p, (a, b) in enumerate(zip(order[:-1], order[1:], strict=True)):
        if b != a + 1:  # the gt flow is between consecutive frames (time order = index order for fgjax synth)
            continue
        mask = np.asarray(disc.masks[p], bool)
        mov = fvalid[a] & (np.linalg.norm(obj_flow[a], axis=-1) > flow_threshold)
        sta = fvalid[a] & (ids[a] == 0)
        flagged["moving"][0] += int(np.sum(mask & mov))
        flagged["moving"][1] += int(np.sum(mov))
        flagged["static"][0] += int(np.sum(mask & sta))
        flagged["static"][1] += int(np.sum(sta))
        for j in per_part:
            mj = mov & (ids[a] == j)
            per_part[j][0] += int(np.sum(mask & mj))
            per_part[j][1] += int(np.sum(mj))
    share = lambda x: float(x[0] / x[1]) if x[1] else float("nan")
    res: dict = {"moving_pixels_flagged": share(flagged["moving"]), "static_pixels_flagged": share(flagged["static"]),
                 "part_pixels_flagged": {str(j): share(v) for j, v in per_part.items()},
                 "part_moving_pixels": {str(j): v[1] for j, v in per_part.items()}}
    states = np.load(gt / "train" / "states.npy")
    norm = Normalization.from_dict(run.meta["normalization"])
    objs = gt_objects(meta)
    first = int(order[0])
    m, q, ls = run.deformed(float(scene.times[first]))
    means = np.asarray(m)
    lab = gt_labels_of_gaussians(means, gt, objs, states[first], norm, {j - 1: j for j in objs}, 0.06)
    alive = np.asarray(run.state.densify.alive, bool)
    s2_labels = None
    if (run_dir / "stage2.npz").is_file():
        with np.load(run_dir / "stage2.npz") as z:
            s2_labels = np.asarray(z["labels"]) if len(z["labels"]) == len(lab) else None
    res["part_gaussians"] = {}
    for j in objs:
        on = alive & (lab == j - 1)
        row = {"on_part": int(on.sum()), "in_dynamic_set": int(np.sum(on & disc.dynamic))}
        if s2_labels is not None:
            row["in_an_object"] = int(np.sum(on & (s2_labels >= 0)))
        res["part_gaussians"][str(j)] = row
    res["dynamic_set"] = int(np.sum(disc.dynamic))
    res["dynamic_set_on_static"] = int(np.sum(disc.dynamic & alive & (lab < 0)))
    colors = np.asarray(disc.dynamic, np.float32)[:, None]
    img, _, _ = run.render_geometry(m, q, ls, scene.viewmats[first], scene.Ks[first], scene.width, scene.height,
                                    colors=colors, capacity=result.render_capacity(run))
    d_px = np.asarray(img, np.float64)[..., 0]  # D's share of each pixel of the first frame
    on = ids[first] > 0
    res["dynamic_pixels_on_parts"] = float(d_px[on].sum() / max(d_px.sum(), 1e-9))
    res["part_pixels_dynamic"] = {str(j): float(np.mean(d_px[ids[first] == j] >= 0.5)) if np.any(ids[first] == j)
                                  else float("nan") for j in objs}
    return res
