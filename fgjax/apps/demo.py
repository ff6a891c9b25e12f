"""``fgjax demo`` (``make demo``): the built-in synthetic scene and pictures of its ground truth.

The demo generates the default synthetic articulated scene (`fgjax.synth`) into ``OUT/scene``,
then (unless ``--synth-only``) runs optical flow -> stage 1 -> discovery -> stage 2 -> control -> eval
on it (``OUT/run``; ``OUT/control_sheet.png``: a training frame, the controlled scene at v = 0, the
per-pixel object ids and each object moved; ``OUT/control.mp4``: each object swept through its range
while the others stay still; ``OUT/run/metrics.json``). Ground-truth pictures:

- ``OUT/contact_sheet.png``: a few training frames (rows) where objects move, as RGB, depth,
  ground-truth optical flow (Middlebury colour wheel, one scale for the sheet) and per-pixel
  object ids (columns);
- ``OUT/demo.mp4``: the training sequence next to its flow visualisation (imageio + ffmpeg;
  ``OUT/demo.gif`` when mp4 writing fails).

The settings of both stages come from one named configuration: experiments/articulated.toml, or
experiments/demo_quick.toml with ``--quick`` (a smaller scene, 96x72 and 24 frames, for a smoke run), or ``--config
FILE``. ``--set SECTION.KEY=VALUE`` (repeatable) overrides one key, e.g. ``--set train.steps=3000``, ``--set
stage2.eps=0.08`` or ``--set articulate.track_rest=false``. Every override is checked before anything is written,
and a bad one exits with status 2 and names the key.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np

from fgjax import synth
from fgjax.articulate.pipeline import run_articulated
from fgjax.config import Config, load_config
from fgjax.data.loaders import load_scene
from fgjax.data.opticalflow import estimate_flow
from fgjax.io import write_video
from fgjax.method import stage1
from fgjax.method.evaluate import write_control_metrics
from fgjax.method.result import cluster_vectors_at, load_stage2, render_clusters, render_controlled
from fgjax.method.stage2 import run_stage2
from fgjax.viz import depth_to_color, ids_to_color, pad16, to_u8, upscale

__all__ = ["main", "contact_sheet", "pipeline_configs", "sweep_times", "changed_share"]

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"


def _label(img: np.ndarray, text: str) -> np.ndarray:
    """A strip with `text` above `img` (same width)."""
    h = 16
    strip = np.full((h, img.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([strip, img], axis=0)


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
            _label(upscale(rgb, s), f"frame {i} RGB"),
            _label(upscale(depth_to_color(depth[i], valid[i], near=near, far=far), s), "depth"),
            _label(upscale(synth.flow_to_color(f, max_flow, valid=fv), s), f"flow {i}->{i + 1} (max {max_flow:.1f}px)"),
            _label(upscale(ids_to_color(ids[i]), s), "object id"),
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
        frames.append(pad16(upscale(np.concatenate([rgb, fc], axis=1), s)))
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
    p.add_argument("--overwrite", action="store_true", help="replace an earlier demo in --out")
    p.add_argument("--synth-only", action="store_true",
                   help="only the synthetic scene and its ground-truth pictures (no training)")
    p.add_argument("--config", default=None, help="named configuration (default: experiments/articulated.toml, "
                   "or experiments/demo_quick.toml with --quick)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a setting (repeatable), e.g. train.steps=3000, stage2.eps=0.08, "
                        "articulate.track_rest=false")
    args = p.parse_args(argv)
    out = Path(args.out)
    try:
        scfg = _scene_config(args)
        cfg = pipeline_configs(out / "flow_cache", quick=args.quick, overrides=args.overrides, config=args.config)
    except ValueError as e:
        print(f"fgjax demo: error: {e}", file=sys.stderr)
        return 2
    scene_dir = out / "scene"
    if out.exists() and not out.is_dir():
        print(f"fgjax demo: error: --out {out} is a file, not a folder", file=sys.stderr)
        return 2
    if out.is_dir() and any(out.iterdir()):
        if not args.overwrite:
            print(f"fgjax demo: error: {out} is not empty; pass --overwrite to replace an earlier demo there, or "
                  "choose another --out", file=sys.stderr)
            return 2
        if not _is_synth_output(scene_dir):
            print(f"fgjax demo: error: {out} does not hold an earlier demo (no {scene_dir / 'gt' / 'meta.json'} "
                  "from fgjax synth); --overwrite replaces only a demo's folder: choose another --out", file=sys.stderr)
            return 2
        shutil.rmtree(out)
    t0 = time.perf_counter()
    say = lambda msg: print(msg, file=sys.stderr, flush=True)
    synth.generate(scfg, scene_dir, overwrite=True, progress=say)
    say(f"demo: drawing ({time.perf_counter() - t0:.1f} s)")
    sheet_path = out / "contact_sheet.png"
    iio.imwrite(sheet_path, contact_sheet(scene_dir))
    video_path = write_video(_video_frames(scene_dir), out / "demo.mp4")
    print(f"scene:         {scene_dir} (transforms_train.json, transforms_test.json, images/, gt/)")
    print(f"contact sheet: {sheet_path}")
    print(f"video:         {video_path}")
    if not args.synth_only:
        _pipeline(out, scene_dir, cfg, say=say)
    say(f"demo: done in {time.perf_counter() - t0:.1f} s")
    return 0


def pipeline_configs(flow_cache: Path, *, quick: bool, overrides: list[str], config: str | None = None) -> Config:
    """The demo's configuration: experiments/demo_quick.toml (``quick``) or experiments/articulated.toml, or the file
    ``config``, with the ``--set SECTION.KEY=VALUE`` `overrides` applied (stage 1's sections, ``stage2.*`` and
    ``articulate.*``) and the flow cache in ``flow_cache``. Raises `fgjax.config.ConfigError` naming the key or file,
    before any work is done."""
    toml = config or EXPERIMENTS / ("demo_quick.toml" if quick else "articulated.toml")
    cfg = load_config(toml, overrides)
    return dataclasses.replace(cfg, stage2=dataclasses.replace(cfg.stage2, flow_cache=str(flow_cache)))


def sweep_times(s2, k: int, n: int = 9) -> np.ndarray:
    """[n] times from the reference time t0 to the time where object ``k``'s trajectory is farthest from its
    reference position (`fgjax.method.result.cluster_vectors_at`): the sweep moves it through its whole range."""
    disp = np.linalg.norm(s2.traj[k] - s2.traj[k, :1], axis=-1)  # [T]
    return np.linspace(s2.traj_times[0], s2.traj_times[int(np.argmax(disp))], n)


def changed_share(a: np.ndarray, b: np.ndarray, mask: np.ndarray, threshold: int = 20) -> float:
    """Share of the pixels in ``mask`` [H, W] where the uint8 images ``a`` and ``b`` [H, W, 3] differ by more than
    ``threshold`` in some channel (0 where the mask is empty)."""
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16)).max(-1) > threshold  # [H, W]
    return float(diff[mask].mean()) if mask.any() else 0.0


def write_control_pictures(out: Path, run, train) -> list[float]:
    """OUT/control_sheet.png (a training frame, the controlled scene at v = 0, its object ids, each object at its
    largest displacement) and OUT/control.mp4 (each object swept from rest to that displacement and back, captioned),
    seen from the first training camera; prints where they went and how visibly each object moves
    (`changed_share` over its pixels at both ends). Returns those shares, one per object."""
    s2 = run.s2
    vm, K, w, h = train.viewmats[0], train.Ks[0], train.width, train.height
    v0 = np.zeros((max(s2.num_objects, 1), 3))  # v = 0 for every object
    ids = render_clusters(run, vm, K, w, h, vectors=v0 if s2.num_objects else None)  # the scene beside it
    rgb0 = render_controlled(run, v0, vm, K, w, h)
    tiles = [_label(upscale(to_u8(train.images[0]), max(1, 240 // w)), "training frame 0"),
             _label(upscale(to_u8(rgb0), max(1, 240 // w)), "stage 2, v = 0"),
             _label(upscale(ids_to_color(ids), max(1, 240 // w)), f"{s2.num_objects} object(s) found")]
    frames, moved = [], []
    for k in range(s2.num_objects):
        times = sweep_times(s2, k)
        raw = []
        for t in np.concatenate([times, times[::-1][1:]]):
            vec = np.zeros((s2.num_objects, 3))
            vec[k] = cluster_vectors_at(s2, t)[k]
            raw.append(to_u8(render_controlled(run, vec, vm, K, w, h)))
            frames.append(pad16(_label(upscale(raw[-1], max(1, 320 // w)), f"object {k + 1}")))
        far = len(times) - 1  # the object at its largest displacement
        ids_far = render_clusters(run, vm, K, w, h, vectors=np.where(np.arange(s2.num_objects)[:, None] == k,
                                                                      cluster_vectors_at(s2, times[-1]), 0.0))
        moved.append(changed_share(raw[0], raw[far], (ids == k + 1) | (ids_far == k + 1)))
        tiles.append(_label(upscale(raw[far], max(1, 240 // w)), f"object {k + 1} moved"))
    sheet = out / "control_sheet.png"
    iio.imwrite(sheet, np.concatenate([np.pad(x, ((2, 2), (2, 2), (0, 0)), constant_values=255) for x in tiles], 1))
    print(f"control sheet: {sheet}")
    if frames:
        print(f"control video: {write_video(frames, out / 'control.mp4')}")
    return moved


def _pipeline(out: Path, scene_dir: Path, cfg: Config, *, say) -> None:
    """Optical flow -> stage 1 -> discovery/stage 2 -> control (sweep videos, cluster map) -> eval."""
    t0 = time.perf_counter()
    cache = Path(cfg.stage2.flow_cache)
    train = load_scene(scene_dir, "train")
    order = np.argsort(train.times, kind="stable")
    for a, b in zip(order[:-1], order[1:], strict=True):
        estimate_flow(to_u8(train.images[a]), to_u8(train.images[b]), "dis_deepflow", cache_dir=cache)
    say(f"demo: optical flow of {len(order) - 1} pairs ({time.perf_counter() - t0:.1f} s)")
    run_dir = out / "run"
    stage1.run(cfg, scene_dir, run_dir, log=say)
    say(f"demo: stage 1 done ({time.perf_counter() - t0:.1f} s)")
    if cfg.stage2.variant == "articulated":
        run_articulated(run_dir, scene_dir, cfg.stage2, cfg.articulate, log=say)
    else:
        run_stage2(run_dir, scene_dir, cfg.stage2, log=say)
    run = load_stage2(run_dir)
    moved = write_control_pictures(out, run, train)
    print(f"run:           {run_dir} (stage 1 + stage2.npz)")
    res = write_control_metrics(run, scene_dir)
    print(f"metrics:       {run_dir / 'metrics.json'}")
    if moved:
        print("visible motion: " + ", ".join(f"object {k + 1} {100 * m:.0f}%" for k, m in enumerate(moved))
              + " of its pixels change by more than 20/255 between the ends of its sweep")
    if res:
        print(f"objects found: {res['num_objects_found']} of {res['num_objects_gt']}; ARI {res['ari']:.3f}, "
              f"ARI of the controlled scene {res['ari_controlled']:.3f}; held-out states "
              f"{res.get('state_psnr', float('nan')):.2f} dB; stage-1 test views {res['view_psnr_stage1']:.2f} dB")
    say(f"demo: pipeline done ({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
