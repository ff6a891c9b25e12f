"""`generate`: render a synthetic scene and write it with its ground truth, atomically (see `fgjax.synth`)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fgjax.data.write import write_transforms
from fgjax.io import replace_folder
from fgjax.synth.family import make_family_scene
from fgjax.synth.parts import ROOM_SIZE, axis_angle_matrix, normalize, rigid_inv, smoothstep
from fgjax.synth.render import Renders, render_sequence, sequence_flow
from fgjax.synth.scene import SynthConfig, SynthScene, camera_c2w, make_scene, object_centres, scene_states

GENERATOR = "fgjax.data.synth"  # the generator tag in gt/meta.json (a stable format identifier)
FORMAT_VERSION = 1
TEST_VIEW, TEST_STATE = 0, 1  # gt/test/kind.npy codes


def _lighting_gains(cfg: SynthConfig, times: np.ndarray) -> np.ndarray:
    return 1.0 - cfg.lighting_change * smoothstep((np.asarray(times) - 0.3) / 0.4)


def _noisy_viewmats(cfg: SynthConfig, c2w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Written (possibly noisy) viewmats from true OpenCV c2w [T, 4, 4]."""
    out = c2w.copy()
    if cfg.pose_noise_deg > 0 or cfg.pose_noise_trans > 0:
        for i in range(len(out)):
            axis = normalize(rng.normal(size=3))
            ang = math.radians(cfg.pose_noise_deg) * rng.normal()
            out[i, :3, :3] = axis_angle_matrix(axis, ang) @ out[i, :3, :3]
            out[i, :3, 3] += cfg.pose_noise_trans * ROOM_SIZE * rng.normal(size=3)
    return rigid_inv(out)


def _test_frames(scene: SynthScene, train_times: np.ndarray, train_states: np.ndarray,
                 rng: np.random.Generator) -> list[dict[str, Any]]:
    """Held-out frames: novel views at training times, and novel state combinations."""
    cfg = scene.cfg
    t = len(train_times)
    out = []
    view_idx = np.round(np.linspace(0, t - 1, cfg.test_views + 2)[1:-1]).astype(int) if cfg.test_views else []
    # the hand-made scenes: 10 degrees off the arc, higher and closer, at a training time; the family's paths
    # (some still, some short) give their own offset and a time between two training frames
    d_az, d_h, d_r = scene.camera.get("test_offset", (math.radians(10.0), 0.15, -0.15))
    shift = float(scene.camera.get("test_time_shift", 0.0))
    for j, i in enumerate(view_idx):
        sign = 1.0 if j % 2 == 0 else -1.0
        tt = float(train_times[i]) + shift * (float(train_times[min(i + 1, t - 1)]) - float(train_times[i]))
        c2w = camera_c2w(scene, tt, d_azimuth=sign * d_az, d_height=d_h, d_radius=d_r)
        st = train_states[i].copy() if tt == float(train_times[i]) else scene_states(scene, np.array([tt]))[0]
        out.append({"kind": "view", "time": tt, "source": int(i), "c2w": c2w, "states": st})
    state_idx = np.round(np.linspace(0, t - 1, cfg.test_states + 2)[1:-1]).astype(int) if cfg.test_states else []
    kmax = np.array([o.key_states.max() for o in scene.objects])
    for j, i in enumerate(state_idx):
        states = kmax.copy() if j == 0 else rng.uniform(0.35, 1.0, size=scene.num_objects) * kmax
        out.append({"kind": "state", "time": float(train_times[i]), "source": int(i),
                    "c2w": camera_c2w(scene, float(train_times[i])), "states": states})
    for fr in out:
        fr["novelty"] = float(np.min(np.max(np.abs(train_states - fr["states"]), axis=-1)))
    return out


def _array_digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _prepare_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"synth: {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"synth: {out} is not empty (pass overwrite=True / --overwrite to replace it)")


_FILES_DOC = {
    "labels.npy": "[N] int32 per-Gaussian label, 0 = static, k = object k (label order = objects)",
    "canonical.npz": "canonical (all states 0) Gaussians: means, quats (wxyz), scales, opacities (activated), "
                     "colors, labels",
    "train/depth.npy": "[T, H, W] float32 expected camera z-depth (sum T a z / alpha), 0 = none",
    "train/alpha.npy": "[T, H, W] float32 accumulated opacity",
    "train/object_id.npy": "[T, H, W] int16 argmax of composited one-hot labels; -1 where alpha < 0.5",
    "train/valid.npy": "[T, H, W] bool alpha >= 0.5",
    "train/flow.npy": "[T-1, H, W, 2] float32 optical flow frame i -> i+1 on frame i's grid (dx, dy)",
    "train/camera_flow.npy": "[T-1, H, W, 2] float32 flow of the point held static (true poses)",
    "train/object_flow.npy": "[T-1, H, W, 2] float32 flow - camera_flow (0 on static pixels)",
    "train/flow_valid.npy": "[T-1, H, W] bool where the three flows are defined",
    "train/flow_occluded.npy": "[T-1, H, W] bool valid, but leaves the image or is hidden in frame i+1",
    "train/moving.npy": "[T-1, K] bool object k's state changes between frames i and i+1",
    "train/states.npy": "[T, K] float32 object states in [0, 1]",
    "train/centres.npy": "[T, K, 3] float32 mean of each object's deformed Gaussians",
    "train/times.npy": "[T] float64 times in [0, 1]",
    "train/gains.npy": "[T] float32 global lighting gain applied to the RGB",
    "train/Ks.npy": "[T, 3, 3] float64 intrinsics",
    "train/viewmats_true.npy": "[T, 4, 4] float64 true OpenCV world-to-camera (images rendered from them)",
    "train/viewmats_written.npy": "[T, 4, 4] float64 the (possibly noisy) poses in transforms_train.json",
    "test/*": "depth, alpha, object_id, valid, states, centres, times, gains, Ks, viewmats_true as for train; "
              "kind [T'] int8 (0 = novel view at a training time, 1 = novel state combination from a training "
              "camera); source_index [T'] the training frame used",
}


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0, 1) * 255).astype(np.uint8)


def _save_split(folder: Path, arrays: dict[str, np.ndarray]) -> None:
    folder.mkdir(parents=True)
    for name, arr in arrays.items():
        np.save(folder / f"{name}.npy", arr)


def _write_all(tmp: Path, scene: SynthScene, train: dict[str, Any], tests: list[dict[str, Any]],
               te: Renders | None) -> None:
    """Images, transforms json and gt/ of a generated scene into `tmp`."""
    cfg = scene.cfg
    n = cfg.frames
    info = {"generator": GENERATOR, "scene": "fgjax-synth", "seed": cfg.seed}
    tr: Renders = train.pop("renders")
    write_transforms(tmp, "train", _to_u8(tr.rgb), train["Ks"], train["viewmats_written"], train["times"],
                     extra=dict(info, split="train"), frame_names=[f"train_{i:05d}" for i in range(n)])
    counters = {"view": 0, "state": 0}
    names = []
    for f in tests:
        names.append(f"test_{f['kind']}_{counters[f['kind']]:03d}")
        counters[f["kind"]] += 1
    if cfg.depth_maps:  # the loader's sibling folder: depth/<image stem>.npy, camera z in scene units
        (tmp / "depth").mkdir()
        measured = [(f"train_{i:05d}", d) for i, d in enumerate(np.where(tr.valid, tr.depth, 0.0).astype(np.float32))]
        if tests and te is not None:
            measured += list(zip(names, np.where(te.valid, te.depth, 0.0).astype(np.float32), strict=True))
        for name, d in measured:
            np.save(tmp / "depth" / f"{name}.npy", d)
    gt = tmp / "gt"
    gt.mkdir()
    np.save(gt / "labels.npy", scene.labels.astype(np.int32))
    np.savez(gt / "canonical.npz", means=scene.means.astype(np.float32), quats=scene.quats.astype(np.float32),
             scales=scene.scales.astype(np.float32), opacities=scene.opacities.astype(np.float32),
             colors=scene.colors.astype(np.float32), labels=scene.labels.astype(np.int32))
    _save_split(gt / "train", {"depth": tr.depth, "alpha": tr.alpha, "object_id": tr.object_id, "valid": tr.valid,
                               **train})
    if tests and te is not None:
        vm = rigid_inv(np.stack([f["c2w"] for f in tests]))
        times = np.array([f["time"] for f in tests])
        ks = np.tile(scene.K, (len(tests), 1, 1))
        write_transforms(tmp, "test", _to_u8(te.rgb), ks, vm, times, frame_names=names,
                         extra=dict(info, split="test", test_frame_kinds=[f["kind"] for f in tests]))
        states = np.stack([f["states"] for f in tests])
        _save_split(gt / "test", {
            "depth": te.depth, "alpha": te.alpha, "object_id": te.object_id, "valid": te.valid,
            "states": states.astype(np.float32), "centres": object_centres(scene, states).astype(np.float32),
            "times": times, "gains": _lighting_gains(cfg, times).astype(np.float32), "Ks": ks, "viewmats_true": vm,
            "kind": np.array([TEST_VIEW if f["kind"] == "view" else TEST_STATE for f in tests], np.int8),
            "source_index": np.array([f["source"] for f in tests], np.int32),
        })
    meta = {
        "generator": GENERATOR,
        "format_version": FORMAT_VERSION,
        "config": cfg.to_dict(),
        "units": "scene units; world z up, floor z = 0, room x, y in [-1.6, 1.6], z in [0, 1.6]",
        "camera_convention": "OpenCV viewmats (world-to-camera); transforms_*.json hold OpenGL c2w",
        "n_gaussians": len(scene.means),
        "n_gaussians_per_label": np.bincount(scene.labels, minlength=scene.num_objects + 1).tolist(),
        "objects": [o.to_dict() for o in scene.objects],
        "min_separation": scene.min_separation,
        "close_pair": [1, 2] if cfg.close_pair else None,
        "close_gap": scene.close_gap,
        **({"family": cfg.family, "camera_path": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                                                  for k, v in scene.camera.items()
                                                  if k not in ("freqs", "phases", "weights")}}
           if cfg.family is not None else {}),
        "test_frames": [
            {"name": nm, "kind": f["kind"], "time": f["time"], "source_index": f["source"],
             "states": f["states"].tolist(), "novelty": f["novelty"]}
            for nm, f in zip(names, tests, strict=True)
        ],
        "digest": _array_digest(_to_u8(tr.rgb), train["flow"]),
        "files": _FILES_DOC,
        "flow_note": "flow = pi_{i+1}(T_k(s_{i+1}) T_k(s_i)^-1 X) - m with X back-projected from the composited "
                     "(expected) depth of frame i; approximate at object boundaries where the composite mixes "
                     "surfaces",
        "lighting_note": "rgb = clip(render * gain(t)), gain(t) = 1 - a smoothstep((t - 0.3) / 0.4)",
    }
    (gt / "meta.json").write_text(json.dumps(meta, indent=2), encoding="utf-8")


def generate(
    cfg: SynthConfig,
    out_dir: str | os.PathLike,
    *,
    overwrite: bool = False,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Generate a synthetic scene with ground truth into `out_dir` (atomically).

    Layout (D-NeRF/nerfstudio style, read by `fgjax.data.loaders.load_scene`):
      ``transforms_train.json``, ``transforms_test.json`` (per frame file_path, OpenGL c2w
      ``transform_matrix``, ``time``, fl_x, fl_y, cx, cy, w, h; top level camera_angle_x),
      ``images/train_00000.png ...``, ``images/test_view_000.png``, ``images/test_state_000.png``,
      and ``gt/``: ``meta.json`` (config, objects, schedules, test frame kinds, file list),
      ``labels.npy`` [N], ``canonical.npz``, ``train/*.npy``, ``test/*.npy`` (see meta.json). With
      ``cfg.depth_maps`` also ``depth/<frame>.npy``, each frame's measured depth as the loader reads it.

    Everything is written to a temporary folder next to `out_dir` that is renamed at the end, so
    a failed run leaves nothing behind (nor any parent folder it created).

    Args:
        cfg: the options.
        out_dir: destination folder; must be absent or empty unless `overwrite`.
        overwrite: replace a non-empty `out_dir`.
        progress: called with one-line progress messages.

    Returns:
        The output folder (absolute).

    Raises:
        FileExistsError: `out_dir` is a file, or a non-empty folder without `overwrite`.
    """
    out = Path(out_dir).absolute()
    _prepare_out(out, overwrite)
    say = progress or (lambda msg: None)
    t_start = time.perf_counter()

    def frame_progress(split):
        def cb(i, total):
            if i == total or i % max(1, total // 10) == 0:
                say(f"synth: {split} frame {i}/{total} ({time.perf_counter() - t_start:.1f} s)")
        return cb

    made = [d for d in reversed([out.parent, *out.parent.parents]) if not d.exists()]
    for d in made:
        d.mkdir()
    tmp = out.with_name(f".{out.name}.synth-tmp-{uuid.uuid4().hex[:8]}")
    try:
        tmp.mkdir()
        scene = make_family_scene(cfg) if cfg.family is not None else make_scene(cfg)
        rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 0xCA3E]))
        times = np.arange(cfg.frames) / (cfg.frames - 1)
        states = scene_states(scene, times)
        c2w_true = np.stack([camera_c2w(scene, float(t)) for t in times])
        vm_true = rigid_inv(c2w_true)
        gains = _lighting_gains(cfg, times)
        say(f"synth: {len(scene.means)} Gaussians ({int(np.sum(scene.labels > 0))} on {scene.num_objects} "
            f"movable parts), {cfg.frames} training frames at {cfg.width}x{cfg.height}")
        tr = render_sequence(scene, vm_true, states, gains=gains, progress=frame_progress("train"))
        train = {
            "renders": tr, **sequence_flow(scene, states, vm_true, tr),
            "states": states.astype(np.float32), "centres": object_centres(scene, states).astype(np.float32),
            "times": times, "gains": gains.astype(np.float32), "Ks": np.tile(scene.K, (cfg.frames, 1, 1)),
            "viewmats_true": vm_true, "viewmats_written": _noisy_viewmats(cfg, c2w_true, rng),
        }
        tests = _test_frames(scene, times, states, rng)
        te = None
        if tests:
            te_times = np.array([f["time"] for f in tests])
            te = render_sequence(scene, rigid_inv(np.stack([f["c2w"] for f in tests])),
                                 np.stack([f["states"] for f in tests]), gains=_lighting_gains(cfg, te_times),
                                 progress=frame_progress("test"))
        _write_all(tmp, scene, train, tests, te)
        _prepare_out(out, overwrite)  # re-check: someone may have filled it meanwhile
        replace_folder(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        for d in reversed(made):  # parent folders this call created
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    say(f"synth: wrote {out} in {time.perf_counter() - t_start:.1f} s")
    return out
