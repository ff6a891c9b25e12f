"""Real captures to the scene layout fgjax loads (`fgjax prepare`): a phone clip (poses by structure from motion,
or a fallback) or a Record3D export (poses and LiDAR depth from ARKit).

The steps, each a function:

1. Frames: `fgjax.data.video.read_video` or `fgjax.data.record3d.read_record3d` (resized to at most ``max_side``
   pixels on the longer side).
2. Cameras (`video_cameras`): pycolmap's incremental SfM (`fgjax.data.sfm.run_sfm`) with one shared camera, unless
   the image hardly moves over the clip (the median optical flow of a frame, `fgjax.data.sfm.image_motion`, times
   the number of frames, under ``min_motion_deg`` at the ``fov_deg`` focal length): no parallax to triangulate. It is
   accepted when it registers at least ``min_registered`` of the frames (and 3) with enough points, a plausible
   field of view and distortion (`sfm_problem`); the frames it leaves out are dropped. SIMPLE_RADIAL's k1 is removed by
   undistorting the images (same K and size, border pixels replicated). Otherwise the clip falls back, with one line
   saying why, to a camera that turns about a fixed centre (`fgjax.data.sfm.rotation_poses`, fitted between
   consecutive frames) when it turns by more than ``still_deg`` somewhere, else to a still camera (identity poses);
   both with the focal length of a ``fov_deg`` horizontal field of view and no distortion.
3. Normalisation (`content_normalization`): centre = the median of the scene's points (SfM points, or LiDAR depth
   back-projected), or the point the cameras look at when there are none (`fgjax.geometry.look_at_point`: one unit
   in front of a still or turning camera); scale = 1 / the median distance of the cameras from that centre. So the
   content sits about one unit in front of the cameras in every path, and DBSCAN's eps and the configurations'
   lengths mean the same on all of them. The files keep world units (SfM units, or metres); the transforms record
   the normalisation (top-level ``normalization``, which `fgjax.data.loaders.load_scene` applies).
4. Writing (`write_scene`): times (source frame number - first) / (last - first) in [0, 1]; every ``test_every``-th
   frame (the 8th, 16th, ...) held out in ``transforms_test.json``, the rest in ``transforms_train.json``
   (`fgjax.data.write.write_transforms`), depth as 16-bit PNG in millimetres (``depth_scale`` 0.001), and
   ``prepare.json`` recording what was done (which pose path, how many frames SfM registered, the parallax, the
   normalisation, timings). The folder is written under a temporary name and renamed into place, so a failure leaves
   nothing behind.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import shutil
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fgjax.data.record3d import read_record3d
from fgjax.data.scene import Normalization
from fgjax.data.sfm import focal_from_fov, have_pycolmap, image_motion, rotation_poses, run_sfm
from fgjax.data.video import read_video
from fgjax.data.write import write_transforms
from fgjax.geometry import c2w_to_viewmat, look_at_point
from fgjax.io import replace_folder

__all__ = ["Capture", "MIN_FRAMES", "PREPARE_NAME", "content_normalization", "interleaved_split",
           "prepare_video", "prepare_record3d", "sfm_problem", "video_cameras", "write_scene"]

MIN_FRAMES = 4
PREPARE_NAME = "prepare.json"
POSE_MODES = ("auto", "rotation", "still")
DEPTH_PNG_SCALE = 1e-3  # 16-bit PNG depth in millimetres


@dataclasses.dataclass
class Capture:
    """Frames with cameras, ready to write.

    Attributes:
        images: [T, H, W, 3] uint8 RGB.
        K: [3, 3] pinhole intrinsics shared by the frames.
        c2w: [T, 4, 4] OpenCV camera-to-world, world units.
        indices: [T] source frame numbers.
        depths: [T, H, W] float32 z-depth in world units (0 unknown), or None.
        normalization: world -> scene units (`content_normalization`).
        info: what prepare.json records.
    """

    images: np.ndarray
    K: np.ndarray
    c2w: np.ndarray
    indices: np.ndarray
    depths: np.ndarray | None
    normalization: Normalization
    info: dict[str, Any]


def content_normalization(c2w: np.ndarray, points: np.ndarray | None = None) -> tuple[Normalization, str]:
    """(normalisation, how it was made) of cameras ``c2w`` [T, 4, 4] (OpenCV) and scene points [P, 3] (world units):
    centre = median of the points (or `fgjax.geometry.look_at_point` without points); scale = 1 / median camera
    distance to the centre (1 when the cameras sit at it)."""
    centres = c2w[:, :3, 3]
    if points is not None and len(points) >= 10:
        centre = np.median(np.asarray(points, np.float64), axis=0)
        how = f"centre: median of {len(points)} scene points"
    else:
        centre, _ = look_at_point(c2w_to_viewmat(c2w))
        how = "centre: the point the optical axes pass nearest (one unit ahead for a still or turning camera)"
    dist = float(np.median(np.linalg.norm(centres - centre, axis=-1)))
    scale = 1.0 / dist if dist > 1e-9 else 1.0
    return Normalization(centre, scale), how + "; scale: 1 / median camera distance to the centre"


def interleaved_split(n: int, test_every: int) -> tuple[np.ndarray, np.ndarray]:
    """(train indices, test indices) of n frames: frames test_every - 1, 2 test_every - 1, ... are held out
    (none when test_every is 0). ValueError when fewer than 2 training frames would remain."""
    if test_every < 0 or test_every == 1:
        raise ValueError(f"--test-every must be 0 (no test split) or >= 2, got {test_every}")
    idx = np.arange(n)
    test = (idx + 1) % test_every == 0 if test_every else np.zeros(n, bool)
    if (~test).sum() < 2:
        raise ValueError(f"{n} frames leave fewer than 2 training frames with --test-every {test_every}")
    return idx[~test], idx[test]


def _fov(K: np.ndarray, width: int) -> float:
    return math.degrees(2.0 * math.atan(width / (2.0 * K[0, 0])))


def _undistort(images: np.ndarray, K: np.ndarray, k1: float) -> np.ndarray:
    """Images with SIMPLE_RADIAL's k1 removed (same K and size; pixels beyond the source replicate its border)."""
    h, w = images.shape[1:3]
    mx, my = cv2.initUndistortRectifyMap(K, np.array([k1, 0.0, 0.0, 0.0]), None, K, (w, h), cv2.CV_32FC1)
    return np.stack([cv2.remap(im, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for im in images])


def sfm_problem(sfm, width: int, need: int) -> str | None:
    """Why an `fgjax.data.sfm.SfmResult` of frames ``width`` pixels wide is not used, or None: fewer than ``need``
    frames registered, fewer than max(100, 5 per registered frame) points, a horizontal field of view outside
    [20, 120] degrees, or |k1| > 0.5 (degenerate reconstructions of a clip with little parallax show all four)."""
    fov = _fov(sfm.K, width)
    if sfm.num_registered < need:
        return f"SfM registered {sfm.num_registered} of {len(sfm.registered)} frames (needs {need})"
    if len(sfm.points) < max(100, 5 * sfm.num_registered):
        return f"SfM's {len(sfm.points)} points for {sfm.num_registered} frames are too few (a degenerate model)"
    if not 20.0 <= fov <= 120.0:
        return f"SfM's field of view {fov:.1f} deg is implausible (outside 20-120)"
    if abs(sfm.k1) > 0.5:
        return f"SfM's radial distortion k1 = {sfm.k1:.3g} is implausible (|k1| > 0.5)"
    return None


def video_cameras(images: np.ndarray, *, poses: str = "auto", fov_deg: float = 60.0,
                  camera_model: str = "SIMPLE_RADIAL", min_registered: float = 0.5, still_deg: float = 0.5,
                  min_motion_deg: float = 1.0, log: Callable[[str], None] = print
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Normalization, dict[str, Any]]:
    """Cameras of frames ``images`` [T, H, W, 3] (module docstring, step 2): (kept frame numbers [T'] into images,
    images [T', H, W, 3] (undistorted where SfM found distortion), K [3, 3], c2w [T', 4, 4], normalisation, info)."""
    if poses not in POSE_MODES:
        raise ValueError(f"--poses must be one of {', '.join(POSE_MODES)}, got {poses!r}")
    if poses == "auto" and not have_pycolmap():
        raise ValueError("pycolmap is not installed; --video needs it for structure from motion: pip install "
                         "'fgjax[video]' (or pass --poses rotation or --poses still)")
    t, h, w = images.shape[:3]
    f0 = focal_from_fov(w, fov_deg)
    k_default = np.array([[f0, 0.0, w / 2], [0.0, f0, h / 2], [0.0, 0.0, 1.0]])
    t0 = time.perf_counter()
    motion = image_motion(images, f0)
    info: dict[str, Any] = {"motion_deg_per_frame": motion}
    log(f"prepare: the image moves by a median {motion:.3f} deg a frame (optical flow / the --fov focal length; "
        f"{time.perf_counter() - t0:.1f} s)")
    t0 = time.perf_counter()
    reason = f"--poses {poses}"
    total = motion * (t - 1)
    if poses == "auto" and total < min_motion_deg:
        reason = (f"SfM skipped: the image moves by {total:.2f} deg over the clip (< {min_motion_deg:g}), too little "
                  "for structure from motion")
        info["sfm"] = {"registered": 0, "frames": t, "skipped": reason}
    elif poses == "auto":
        sfm = run_sfm(images, camera_model=camera_model, log=log)
        need = max(3, math.ceil(min_registered * t))
        fov = _fov(sfm.K, w)
        info["sfm"] = {"registered": sfm.num_registered, "frames": t, "models": sfm.models,
                       "parallax_deg": sfm.parallax_deg, "reprojection_error_px": sfm.reprojection_error,
                       "points": len(sfm.points), "camera_model": camera_model, "focal_px": float(sfm.K[0, 0]),
                       "fov_deg": fov, "k1": sfm.k1, "time_s": time.perf_counter() - t0}
        log(f"prepare: SfM registered {sfm.num_registered} of {t} frames, {len(sfm.points)} points, median parallax "
            f"{sfm.parallax_deg:.2f} deg, field of view {fov:.1f} deg ({time.perf_counter() - t0:.1f} s)")
        reason = sfm_problem(sfm, w, need)
        if reason is None:
            keep = np.flatnonzero(sfm.registered)
            imgs = images[keep]
            if abs(sfm.k1) > 1e-4:
                imgs = _undistort(imgs, sfm.K, sfm.k1)
            norm, how = content_normalization(sfm.c2w[keep], sfm.points)
            info["sfm"]["unregistered_frames"] = [int(i) for i in np.flatnonzero(~sfm.registered)]
            info.update(poses="sfm", fallback=None,
                        distortion=(f"{camera_model} k1 = {sfm.k1:.4g}: images undistorted (same K and size)"
                                    if abs(sfm.k1) > 1e-4 else "none (k1 ~ 0 or SIMPLE_PINHOLE)"),
                        normalization_how=how)
            return keep, imgs, sfm.K, sfm.c2w[keep], norm, info
    rot = None
    if poses in ("auto", "rotation"):
        t1 = time.perf_counter()
        rot, on_key = rotation_poses(images, k_default)
        log(f"prepare: camera rotations fitted to the optical flow ({on_key} of {t - 1} frames against their key "
            f"frame; {time.perf_counter() - t1:.1f} s)")
        turn = max(math.degrees(math.acos(np.clip((np.trace(r[:3, :3]) - 1) / 2, -1, 1))) for r in rot)
        info["rotation"] = {"frames_on_key_frame": on_key, "frames": t, "max_turn_deg": turn}
        if poses == "auto" and turn <= still_deg:
            rot = None
            reason += f"; the camera turns by at most {turn:.2f} deg"
    mode = "still" if rot is None else "rotation"
    c2w = np.tile(np.eye(4), (t, 1, 1)) if rot is None else rot
    norm, how = content_normalization(c2w)
    what = ("a still camera (identity poses)" if rot is None else "a camera turning about a fixed centre (rotations "
            f"fitted to the optical flow, up to {info['rotation']['max_turn_deg']:.1f} deg)")
    how_k = f"focal {f0:.1f} px from a {fov_deg:g} deg horizontal field of view (--fov)"
    log(f"prepare: {reason}; falling back to {what}, {how_k}" if poses == "auto"
        else f"prepare: {reason}: {what}, {how_k}")
    info.update(poses=mode, fallback=reason, distortion="ignored (pinhole assumed)", fov_deg=fov_deg,
                normalization_how=how)
    return np.arange(t), images, k_default, c2w, norm, info


def prepare_video(path: str | os.PathLike, *, max_side: int = 320, stride: int = 1, first: int = 0,
                  last: int | None = None, poses: str = "auto", fov_deg: float = 60.0,
                  camera_model: str = "SIMPLE_RADIAL", min_registered: float = 0.5,
                  log: Callable[[str], None] = print) -> Capture:
    """Decode the clip at ``path`` and estimate its cameras (module docstring, steps 1-3). ValueError naming the file
    when it holds fewer than `MIN_FRAMES` frames in the range."""
    t0 = time.perf_counter()
    vid = read_video(path, max_side=max_side, stride=stride, first=first, last=last)
    t, h, w = vid.images.shape[:3]
    log(f"prepare: decoded {vid.decoded} frames of {path} ({vid.source_size[0]}x{vid.source_size[1]}, "
        f"{vid.fps:.3g} fps), kept {t} at {w}x{h} ({time.perf_counter() - t0:.1f} s)")
    if t < MIN_FRAMES:
        raise ValueError(f"{path}: {t} frame(s) after --frames/--stride; prepare needs at least {MIN_FRAMES}")
    t1 = time.perf_counter()
    keep, images, K, c2w, norm, info = video_cameras(vid.images, poses=poses, fov_deg=fov_deg,
                                                     camera_model=camera_model, min_registered=min_registered,
                                                     log=log)
    if "unregistered_frames" in info.get("sfm", {}):  # as source frame numbers
        info["sfm"]["unregistered_frames"] = [int(vid.indices[i]) for i in info["sfm"]["unregistered_frames"]]
    info = {"source": str(Path(path).absolute()), "kind": "video", **info,
            "frames": {"decoded": vid.decoded, "announced": vid.announced, "kept": int(len(keep)), "stride": stride,
                       "range": [first, last], "fps": vid.fps, "source_size": list(vid.source_size)},
            "time_s": {"decode": t1 - t0, "cameras": time.perf_counter() - t1}}
    return Capture(images, K, c2w, vid.indices[keep], None, norm, info)


def _depth_points(cap_images: int, K: np.ndarray, c2w: np.ndarray, depths: np.ndarray, per_frame: int = 500,
                  frames: int = 20) -> np.ndarray:
    """World points [P, 3] back-projected from up to ``frames`` depth maps, ``per_frame`` pixels each."""
    rng = np.random.default_rng(0)
    kinv = np.linalg.inv(K)
    pts = []
    for i in np.unique(np.linspace(0, cap_images - 1, min(frames, cap_images)).round().astype(int)):
        v, u = np.nonzero(depths[i] > 0)
        if not len(v):
            continue
        sel = rng.choice(len(v), size=min(per_frame, len(v)), replace=False)
        pix = np.stack([u[sel] + 0.5, v[sel] + 0.5, np.ones(len(sel))], axis=-1)  # pixel centres
        cam = (pix @ kinv.T) * depths[i][v[sel], u[sel], None]
        pts.append(cam @ c2w[i, :3, :3].T + c2w[i, :3, 3])
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def prepare_record3d(folder: str | os.PathLike, *, max_side: int = 320, stride: int = 1, first: int = 0,
                     last: int | None = None, depth: bool = True, log: Callable[[str], None] = print) -> Capture:
    """Read the Record3D export in ``folder`` (`fgjax.data.record3d`) and normalise it (module docstring, step 3:
    the centre is the median of LiDAR points where the export has depth)."""
    t0 = time.perf_counter()
    rec = read_record3d(folder, max_side=max_side, stride=stride, first=first, last=last, depth=depth, log=log)
    t, h, w = rec.images.shape[:3]
    log(f"prepare: read {t} Record3D frames at {w}x{h}; depth: {rec.depth_note} ({time.perf_counter() - t0:.1f} s)")
    if t < MIN_FRAMES:
        raise ValueError(f"{folder}: {t} frame(s) after --frames/--stride; prepare needs at least {MIN_FRAMES}")
    pts = _depth_points(t, rec.K, rec.c2w, rec.depths) if rec.depths is not None else None
    norm, how = content_normalization(rec.c2w, pts)
    info = {"source": str(Path(folder).absolute()), "kind": "record3d", "poses": "record3d", "fallback": None,
            "distortion": "none (ARKit intrinsics, pinhole)", "depth": rec.depth_note, "normalization_how": how,
            "frames": {"kept": t, "stride": stride, "range": [first, last], "fps": rec.fps},
            "time_s": {"read": time.perf_counter() - t0}}
    return Capture(rec.images, rec.K, rec.c2w, rec.indices, rec.depths, norm, info)


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise ValueError(f"--out {out} is not empty; pass --overwrite to replace an earlier prepared scene")
        if not (out / PREPARE_NAME).is_file():
            raise ValueError(f"--out {out} holds no prepared scene ({PREPARE_NAME}); --overwrite replaces only "
                             "those: choose another --out")


def write_scene(out: str | os.PathLike, cap: Capture, *, test_every: int = 8, overwrite: bool = False,
                log: Callable[[str], None] = print) -> Path:
    """Write ``cap`` as a scene folder (module docstring, step 4) at ``out``: a new or empty folder, or with
    ``overwrite`` one that holds an earlier prepared scene. Returns the folder."""
    out = Path(out).absolute()
    _check_out(out, overwrite)
    t0 = time.perf_counter()
    n = len(cap.images)
    train, test = interleaved_split(n, test_every)
    idx = cap.indices.astype(np.float64)
    times = (idx - idx[0]) / (idx[-1] - idx[0]) if n > 1 and idx[-1] > idx[0] else np.zeros(n)
    vm = c2w_to_viewmat(cap.c2w)
    ks = np.tile(cap.K, (n, 1, 1))
    extra = {"normalization": cap.normalization.to_dict(), "fgjax_prepare": PREPARE_NAME}
    if cap.depths is not None:
        extra["depth_format"] = "16-bit PNG, millimetres (depth_scale 0.001 m); 0 = unknown"
    made = [d for d in reversed([out.parent, *out.parent.parents]) if not d.exists()]
    for d in made:
        d.mkdir()
    tmp = out.with_name(f".{out.name}.prepare-tmp-{uuid.uuid4().hex[:8]}")
    try:
        tmp.mkdir()
        for split, sel in (("train", train), ("test", test)):
            if not len(sel):
                continue
            write_transforms(tmp, split, cap.images[sel], ks[sel], vm[sel], times[sel],
                             depths=None if cap.depths is None else cap.depths[sel],
                             depth_png_scale=DEPTH_PNG_SCALE if cap.depths is not None else None, extra=extra,
                             frame_names=[f"{split}_{int(i):05d}" for i in cap.indices[sel]])
        h, w = cap.images.shape[1:3]
        info = {**cap.info, "split": {"train": int(len(train)), "test": int(len(test)), "test_every": test_every},
                "camera": {"K": cap.K.tolist(), "width": int(w), "height": int(h), "fov_deg": _fov(cap.K, w)},
                "normalization": cap.normalization.to_dict(),
                "depth_files": ("16-bit PNG, millimetres (depth_scale 0.001)" if cap.depths is not None else None),
                "times": "(source frame - first kept) / (last kept - first kept)"}
        info["time_s"] = {**info.get("time_s", {}), "write": time.perf_counter() - t0}
        (tmp / PREPARE_NAME).write_text(json.dumps(info, indent=1), encoding="utf-8")
        _check_out(out, overwrite)  # re-check: someone may have filled it meanwhile
        replace_folder(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        for d in reversed(made):
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    log(f"prepare: wrote {out} ({len(train)} training and {len(test)} test frames, poses: {cap.info['poses']}) "
        f"in {time.perf_counter() - t0:.1f} s")
    return out
