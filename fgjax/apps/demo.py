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
experiments/demo_quick.toml with ``--quick`` (a smaller scene, 128x96 and 24 frames: `QUICK_SCENE`), or ``--config
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

import imageio.v3 as iio
import numpy as np

from fgjax import synth
from fgjax.config import Config, load_config
from fgjax.data.loaders import load_scene
from fgjax.data.opticalflow import estimate_flow
from fgjax.io import write_video
from fgjax.method.evaluate import write_control_metrics
from fgjax.pipeline import train_and_discover, write_control_pictures
from fgjax.viz import caption, depth_to_color, ids_to_color, pad16, to_u8, upscale

__all__ = ["main", "contact_sheet", "pipeline_configs", "QUICK_SCENE"]

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"
QUICK_SCENE = dict(width=128, height=96, frames=24, test_views=2, test_states=2)
"""`fgjax.synth.SynthConfig` fields of ``fgjax demo --quick``'s scene (with the seed, default 0)."""


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
            caption(upscale(rgb, s), f"frame {i} RGB"),
            caption(upscale(depth_to_color(depth[i], valid[i], near=near, far=far), s), "depth"),
            caption(upscale(synth.flow_to_color(f, max_flow, valid=fv), s),
                    f"flow {i}->{i + 1} (max {max_flow:.1f}px)"),
            caption(upscale(ids_to_color(ids[i]), s), "object id"),
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
    base = dict(QUICK_SCENE) if args.quick else {}
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
    p.add_argument("--quick", action="store_true", help="smaller scene (128x96, 24 frames)")
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


def _pipeline(out: Path, scene_dir: Path, cfg: Config, *, say) -> None:
    """Optical flow -> stage 1 -> discovery/stage 2 (`fgjax.pipeline.train_and_discover`) -> control (sweep videos,
    cluster map: `fgjax.pipeline.write_control_pictures`) -> eval."""
    t0 = time.perf_counter()
    cache = Path(cfg.stage2.flow_cache)
    train = load_scene(scene_dir, "train")
    order = np.argsort(train.times, kind="stable")
    for a, b in zip(order[:-1], order[1:], strict=True):
        estimate_flow(to_u8(train.images[a]), to_u8(train.images[b]), "dis_deepflow", cache_dir=cache)
    say(f"demo: optical flow of {len(order) - 1} pairs ({time.perf_counter() - t0:.1f} s)")
    run_dir = out / "run"
    run = train_and_discover(cfg, scene_dir, run_dir, log=say)
    moved = write_control_pictures(out, run, train)
    print(f"run:           {run_dir} (stage 1 + stage2.npz)")
    res = write_control_metrics(run, scene_dir)
    print(f"metrics:       {run_dir / 'metrics.json'}")
    if moved:
        print("visible motion: " + ", ".join(f"object {k + 1} {100 * m:.0f}%" for k, m in enumerate(moved))
              + " of its pixels change by more than 20/255 between the ends of its sweep")
    if res and "ari" in res:
        print(f"objects found: {res['num_objects_found']} of {res['num_objects_gt']}; ARI {res['ari']:.3f}, "
              f"ARI of the controlled scene {res['ari_controlled']:.3f}; held-out states "
              f"{res.get('state_psnr', float('nan')):.2f} dB; stage-1 test views {res['view_psnr_stage1']:.2f} dB")
    say(f"demo: pipeline done ({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
