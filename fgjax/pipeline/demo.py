"""``fgjax demo`` (``make demo``): the built-in synthetic scene and pictures of its ground truth.

The demo generates the default synthetic articulated scene (`fgjax.data.synth`) into ``OUT/scene``,
then (unless ``--synth-only``) runs optical flow -> stage 1 -> discovery -> stage 2 -> control -> eval
on it (``OUT/run``; ``OUT/control_sheet.png``: a training frame, the controlled scene at v = 0, the
per-pixel object ids and each object moved; ``OUT/control.mp4``: each object swept through its range
while the others stay still; ``OUT/run/metrics.json``). Ground-truth pictures:

- ``OUT/contact_sheet.png``: a few training frames (rows) where objects move, as RGB, depth,
  ground-truth optical flow (Middlebury colour wheel, one scale for the sheet) and per-pixel
  object ids (columns);
- ``OUT/demo.mp4``: the training sequence next to its flow visualisation (imageio + ffmpeg;
  ``OUT/demo.gif`` when mp4 writing fails).

``--quick`` makes a smaller scene (96x72, 24 frames) and uses experiments/demo_quick.toml, for a smoke run.
``--set KEY=VALUE`` (repeatable) overrides a setting of the pipeline: ``stage2.FIELD=VALUE`` a `Stage2Config`
field on top of the demo's own stage-2 settings (e.g. ``--set stage2.track_rest=false``), ``SECTION.KEY=VALUE``
a stage-1 config key on top of experiments/default.toml (e.g. ``--set train.steps=3000``). Every override is
checked before anything is written, and a bad one exits with status 2 and names the key.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np

from fgjax.data import synth
from fgjax.io import write_video

__all__ = ["main", "contact_sheet", "depth_to_color", "ids_to_color", "write_video"]

_ID_COLORS = np.array(
    [[70, 70, 70], [230, 60, 50], [50, 140, 230], [240, 200, 40], [160, 80, 220], [60, 200, 110], [240, 130, 190]],
    dtype=np.uint8,
)


def depth_to_color(depth: np.ndarray, valid: np.ndarray | None = None, *, near: float | None = None,
                   far: float | None = None) -> np.ndarray:
    """[H, W] depth -> [H, W, 3] uint8 RGB (turbo colour map of inverse depth; invalid black)."""
    depth = np.asarray(depth, dtype=np.float64)
    ok = depth > 0 if valid is None else (np.asarray(valid, bool) & (depth > 0))
    if not np.any(ok):
        return np.zeros((*depth.shape, 3), np.uint8)
    near = float(depth[ok].min()) if near is None else near
    far = float(depth[ok].max()) if far is None else far
    inv = np.where(ok, 1.0 / np.where(ok, depth, 1.0), 0.0)
    lo, hi = 1.0 / far, 1.0 / near
    x = np.clip((inv - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    bgr = cv2.applyColorMap(np.round(x * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    rgb = bgr[..., ::-1]
    return np.where(ok[..., None], rgb, 0).astype(np.uint8)


def ids_to_color(ids: np.ndarray) -> np.ndarray:
    """[H, W] object ids (-1 invalid, 0 static, k object) -> [H, W, 3] uint8 RGB."""
    ids = np.asarray(ids)
    out = _ID_COLORS[np.clip(ids, 0, None) % len(_ID_COLORS)]
    return np.where((ids < 0)[..., None], 0, out).astype(np.uint8)


def _up(img: np.ndarray, s: int) -> np.ndarray:
    return np.repeat(np.repeat(img, s, axis=0), s, axis=1) if s > 1 else img


def _label(img: np.ndarray, text: str) -> np.ndarray:
    """A strip with `text` above `img` (same width)."""
    h = 16
    strip = np.full((h, img.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([strip, img], axis=0)


def _pad16(img: np.ndarray) -> np.ndarray:
    """Pad to multiples of 16 pixels (ffmpeg's macro-block size) with black."""
    h, w = img.shape[:2]
    return np.pad(img, ((0, -h % 16), (0, -w % 16), (0, 0)))


def _pick_frames(object_flow: np.ndarray, n: int) -> list[int]:
    """Up to n frame indices with the largest object motion, spread over the sequence."""
    t = object_flow.shape[0]
    score = np.linalg.norm(object_flow, axis=-1).reshape(t, -1).mean(axis=1)
    order = [int(i) for i in np.argsort(-score) if score[i] > 0]
    picked: list[int] = []
    gap = max(1, t // (2 * n))
    for i in order:
        if all(abs(i - j) >= gap for j in picked):
            picked.append(i)
        if len(picked) == n:
            break
    for i in np.linspace(0, t - 1, n).round().astype(int):  # fill with evenly spaced frames
        if len(picked) == n:
            break
        if int(i) not in picked:
            picked.append(int(i))
    return sorted(picked)


def contact_sheet(scene_dir: Path, n_rows: int = 4) -> np.ndarray:
    """[H', W', 3] uint8 sheet: rows = frames, columns = RGB, depth, GT flow, object ids."""
    gt = scene_dir / "gt" / "train"
    depth, valid, ids = (np.load(gt / f"{k}.npy") for k in ("depth", "valid", "object_id"))
    flow, fvalid, oflow = (np.load(gt / f"{k}.npy") for k in ("flow", "flow_valid", "object_flow"))
    t, h, w = depth.shape
    s = max(1, 240 // w)
    max_flow = float(np.percentile(np.linalg.norm(flow, axis=-1)[fvalid], 99)) if np.any(fvalid) else 1.0
    near, far = float(depth[valid].min()), float(depth[valid].max())
    rows = []
    for i in _pick_frames(oflow, min(n_rows, max(t - 1, 1))):
        rgb = iio.imread(scene_dir / "images" / f"train_{i:05d}.png")[..., :3]
        f = flow[min(i, t - 2)] if t > 1 else np.zeros((h, w, 2), np.float32)
        fv = fvalid[min(i, t - 2)] if t > 1 else np.zeros((h, w), bool)
        tiles = [
            _label(_up(rgb, s), f"frame {i} RGB"),
            _label(_up(depth_to_color(depth[i], valid[i], near=near, far=far), s), "depth"),
            _label(_up(synth.flow_to_color(f, max_flow, valid=fv), s), f"flow {i}->{i + 1} (max {max_flow:.1f}px)"),
            _label(_up(ids_to_color(ids[i]), s), "object id"),
        ]
        rows.append(np.concatenate([np.pad(x, ((2, 2), (2, 2), (0, 0)), constant_values=255) for x in tiles], 1))
    return np.concatenate(rows, axis=0)


def _video_frames(scene_dir: Path) -> list[np.ndarray]:
    gt = scene_dir / "gt" / "train"
    flow, fvalid = np.load(gt / "flow.npy"), np.load(gt / "flow_valid.npy")
    t = len(np.load(gt / "times.npy"))
    max_flow = float(np.percentile(np.linalg.norm(flow, axis=-1)[fvalid], 99)) if np.any(fvalid) else 1.0
    frames = []
    for i in range(t):
        rgb = iio.imread(scene_dir / "images" / f"train_{i:05d}.png")[..., :3]
        if i < t - 1:
            fc = synth.flow_to_color(flow[i], max_flow, valid=fvalid[i])
        else:
            fc = np.zeros_like(rgb)
        s = max(1, 320 // rgb.shape[1])
        frames.append(_pad16(_up(np.concatenate([rgb, fc], axis=1), s)))
    return frames


def _scene_config(args: argparse.Namespace) -> synth.SynthConfig:
    base = dict(width=96, height=72, frames=24, test_views=2, test_states=2) if args.quick else {}
    for k in ("width", "height", "frames"):
        if getattr(args, k) is not None:
            base[k] = getattr(args, k)
    return synth.SynthConfig(seed=args.seed, **base)


def _is_synth_output(d: Path) -> bool:
    try:
        meta = json.loads((d / "gt" / "meta.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("generator") == synth.GENERATOR


def main(argv: list[str] | None = None) -> int:
    """``fgjax demo [--out outputs/demo] [--quick]``. Returns the exit status."""
    p = argparse.ArgumentParser(prog="fgjax demo", description="Generate the built-in synthetic articulated scene "
                                "and pictures of its ground truth (contact sheet, video).")
    p.add_argument("--out", default="outputs/demo", help="output folder (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="smaller scene (96x72, 24 frames)")
    p.add_argument("--width", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--height", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--frames", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--synth-only", action="store_true",
                   help="only the synthetic scene and its ground-truth pictures (no training)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a setting (repeatable): stage2.FIELD=VALUE for stage 2 (e.g. stage2.track_rest=false), "
                        "SECTION.KEY=VALUE for stage 1 (e.g. train.steps=3000)")
    args = p.parse_args(argv)
    out = Path(args.out)
    try:
        cfg = _scene_config(args)
        s1cfg, s2cfg = pipeline_configs(out / "flow_cache", quick=args.quick, overrides=args.overrides)
    except ValueError as e:
        print(f"fgjax demo: error: {e}", file=sys.stderr)
        return 2
    scene_dir = out / "scene"
    if scene_dir.exists() and (not scene_dir.is_dir() or (any(scene_dir.iterdir()) and not _is_synth_output(scene_dir))):
        print(f"fgjax demo: error: {scene_dir} exists and is not a synthetic scene from an earlier demo; "
              "choose another --out", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    say = lambda msg: print(msg, file=sys.stderr, flush=True)
    synth.generate(cfg, scene_dir, overwrite=True, progress=say)
    say(f"demo: drawing ({time.perf_counter() - t0:.1f} s)")
    sheet_path = out / "contact_sheet.png"
    iio.imwrite(sheet_path, contact_sheet(scene_dir))
    video_path = write_video(_video_frames(scene_dir), out / "demo.mp4")
    print(f"scene:         {scene_dir} (transforms_train.json, transforms_test.json, images/, gt/)")
    print(f"contact sheet: {sheet_path}")
    print(f"video:         {video_path}")
    if not args.synth_only:
        _pipeline(out, scene_dir, s1cfg, s2cfg, say=say)
    say(f"demo: done in {time.perf_counter() - t0:.1f} s")
    return 0


def pipeline_configs(flow_cache: Path, *, quick: bool, overrides: list[str]):
    """The demo's stage-1 `Config` and `Stage2Config`, with ``--set`` `overrides` applied (``stage2.FIELD=VALUE``
    to stage 2, ``SECTION.KEY=VALUE`` to stage 1). Raises ValueError (`fgjax.config.ConfigError` is one) naming
    the key of a bad override, before any work is done."""
    from fgjax.config import load_config
    from fgjax.pipeline import stage2

    s1_items, s2_items = [], []
    for o in overrides:  # stage2.FIELD=VALUE -> FIELD=VALUE for stage 2; the rest as they are for stage 1
        if o.split("=", 1)[0].strip().startswith("stage2."):
            s2_items.append(o.split(".", 1)[1])
        else:
            s1_items.append(o)
    toml = Path(__file__).resolve().parents[2] / "experiments" / ("demo_quick.toml" if quick else "default.toml")
    s1cfg = load_config(toml if toml.exists() else None, (["train.video_frames=0"] if quick else []) + s1_items)
    # the quick demo: the flow tracking and fewer steps; both skip the control network's photometric phase
    # (from the re-fitted scene it did not lower the loss: 0.0121 -> 0.0122 in the full demo; in the quick one
    # 20 steps took 16 s of its 3 minutes, 0.0408 -> 0.0390; tests/test_stage2.py covers the phase); the full
    # demo: stage 2's defaults less 20% of the photometric tracking's steps, to stay under 15 minutes
    # (docs/benchmarks.md, session 9),
    # and session 9's re-fit (300 steps, the first 150 relabelling: 75 s in session 9; the default's 600 of 600
    # took 93 s in session 10, not timed side by side). The quick demo keeps the flow tracker's pair-by-pair poses
    # (no joint fits): on its 24 frames the fits took 23 s of stage 2's 65 s and gave no better control (state
    # PSNR 22.68 against 23.68 dB without; docs/benchmarks.md, session 20). The full demo's second round of tracking
    # and re-fitting (stage 2's default) tracks with 20 steps a frame, from the first round's poses: 27.73 dB
    # against 27.55 with 40 and 26.56 with one round, on one stage-1 run (session 22); halving the re-fits
    # (150 steps each) lost the gain (26.59 dB), and so did 20 steps in the first round (25.36). The third round
    # (stage 2's default) tracks only the objects whose joint has not converged (`Stage2Config.track_converged_deg`;
    # on the default scene the lid alone, about 60 s: 28.51 dB; docs/benchmarks.md, session 23)
    s2cfg = stage2.Stage2Config(flow_cache=str(flow_cache), auto_eps=quick, photo_steps=0,
                                **({"distill_steps": 100, "refit_steps": 100, "track_photo": 0, "track_joints": "off",
                                    "relabel_steps": 0, "local_threshold": 0.4, "track_rounds": 1} if quick else
                                   {"track_photo": 40, "track_photo_next": 20, "distill_steps": 300,
                                    "refit_steps": 300, "relabel_steps": 150, "track_rounds": 3}))
    s2cfg = stage2.config_from_overrides(s2_items, base=s2cfg, prefix="stage2.")
    stage2.validate_config(s2cfg)
    return s1cfg, s2cfg


def _pipeline(out: Path, scene_dir: Path, s1cfg, s2cfg, *, say) -> None:
    """Optical flow -> stage 1 -> discovery/stage 2 -> control (sweep videos, cluster map) -> eval."""
    from fgjax.data.loaders import load_scene
    from fgjax.data.opticalflow import estimate_flow
    from fgjax.pipeline import evaluate, stage1, stage2

    t0 = time.perf_counter()
    cache = Path(s2cfg.flow_cache)
    train = load_scene(scene_dir, "train")
    u8 = lambda x: (np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)
    order = np.argsort(train.times, kind="stable")
    for a, b in zip(order[:-1], order[1:], strict=True):
        estimate_flow(u8(train.images[a]), u8(train.images[b]), "dis_deepflow", cache_dir=cache)
    say(f"demo: optical flow of {len(order) - 1} pairs ({time.perf_counter() - t0:.1f} s)")
    run_dir = out / "run"
    stage1.run(s1cfg, scene_dir, run_dir, log=say)
    say(f"demo: stage 1 done ({time.perf_counter() - t0:.1f} s)")
    s2 = stage2.run_stage2(run_dir, scene_dir, s2cfg, log=say)
    run = stage2.load_stage2(run_dir)
    vm, K, w, h = train.viewmats[0], train.Ks[0], train.width, train.height
    v0 = np.zeros((max(s2.num_objects, 1), 3))  # v = 0 for every object
    ids = stage2.render_clusters(run, vm, K, w, h, vectors=v0 if s2.num_objects else None)  # the scene beside it
    rgb0 = stage2.render_controlled(run, v0, vm, K, w, h)
    tiles = [_label(_up(u8(train.images[0]), max(1, 240 // w)), "training frame 0"),
             _label(_up(u8(rgb0), max(1, 240 // w)), "stage 2, v = 0"),
             _label(_up(ids_to_color(ids), max(1, 240 // w)), f"{s2.num_objects} object(s) found")]
    frames = []
    for k in range(s2.num_objects):
        raw = []
        for t in np.concatenate([np.linspace(0, 1, 9), np.linspace(1, 0, 9)[1:]]):
            vec = np.zeros((s2.num_objects, 3))
            vec[k] = stage2.cluster_vectors_at(s2, s2.traj_times[0] + t * (s2.traj_times[-1] - s2.traj_times[0]))[k]
            raw.append(u8(stage2.render_controlled(run, vec, vm, K, w, h)))
            frames.append(_pad16(_up(raw[-1], max(1, 320 // w))))
        tiles.append(_label(_up(raw[8], max(1, 240 // w)), f"object {k + 1} moved"))  # t = 1: end of its range
    sheet = out / "control_sheet.png"
    iio.imwrite(sheet, np.concatenate([np.pad(x, ((2, 2), (2, 2), (0, 0)), constant_values=255) for x in tiles], 1))
    print(f"run:           {run_dir} (stage 1 + stage2.npz)")
    print(f"control sheet: {sheet}")
    if frames:
        print(f"control video: {write_video(frames, out / 'control.mp4')}")
    if evaluate.main(["--run", str(run_dir)]) == 0:
        print(f"metrics:       {run_dir / 'metrics.json'}")
    say(f"demo: pipeline done ({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
