"""``fgjax bench track``: the photometric tracker's time per frame, drawing every Gaussian at every step
against drawing only the ones near the parts it fits (`fgjax.articulate.phototrack.track_photometric`'s
``subset_margin``), and how far apart their poses come out.

On a run with stage 2 (its labels; the scene stage 2 tracks: stage 1's Gaussians at the first training
time), the objects (all, or ``--objects``) are fitted over ``--frames`` consecutive training frames from
``--start``, with stage 2's level schedule for ``--steps`` steps a frame. The two modes alternate in one
process, ``--repeats`` times each. Prints, per run, the median seconds a frame after the first (the first
compiles), the Gaussians drawn per step, and at the end the ratio of the medians and the largest
difference of the two modes' pose entries (0 up to round-off while the parts stay within the margin).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from fgjax.articulate.phototrack import track_photometric
from fgjax.articulate.pipeline import photo_level_steps
from fgjax.data.loaders import load_scene
from fgjax.data.scene import Normalization
from fgjax.method.result import load_stage2, reference_scene, render_capacity

__all__ = ["main", "track_bench"]


def track_bench(run_dir: Path, data_dir: Path, *, start: int = 20, frames: int = 6, steps: int = 40,
                objects: list[int] | None = None, repeats: int = 2, margin: int = 2, log=print) -> dict:
    """The measurements above as a dict: per mode ("all", "subset") the seconds a frame of each run and
    the Gaussians drawn per step; "ratio" (median subset / median all) and "max_pose_difference"."""
    run = load_stage2(run_dir)
    scene = load_scene(data_dir, "train", normalize=Normalization.from_dict(run.meta["normalization"]),
                       downscale=run.cfg.data.downscale)
    order = np.argsort(scene.times, kind="stable")
    if not 0 <= start or start + frames >= len(order) or frames < 2:
        raise ValueError(f"--start {start} --frames {frames}: need 2 <= frames and start + frames < "
                         f"{len(order)} (the training frames of {data_dir})")
    num_objects = int(run.s2.meta["num_objects"])
    if num_objects == 0:
        raise ValueError(f"{run_dir}: stage 2 found no object to track")
    objects = list(range(num_objects)) if objects is None else objects
    if any(not 0 <= k < num_objects for k in objects):
        raise ValueError(f"--objects {objects}: the run has objects 0..{num_objects - 1}")
    sel = order[start:start + frames + 1]
    moving = np.zeros((num_objects, frames), bool)
    moving[objects] = True
    ref = reference_scene(run, float(scene.times[order[0]]))
    kw = dict(moving=moving, sh_degree=run.cfg.model.sh_degree, background=run.cfg.model.background,
              capacity=render_capacity(run), tile_size=run.cfg.train.tile_size, steps=photo_level_steps(steps))
    out: dict = {mode: {"frame_s": [], "drawn": [], "fitted_again": []} for mode in ("all", "subset")}
    poses = {}
    for r in range(repeats):
        for mode, m in (("all", None), ("subset", margin)):
            poses[mode], _, st = track_photometric(ref, run.state.densify.alive, run.s2.labels, num_objects,
                                                   scene.images[sel], scene.viewmats[sel], scene.Ks[sel],
                                                   subset_margin=m, progress_every=0, return_stats=True,
                                                   log=lambda _m: None, **kw)
            out[mode]["fitted_again"].append(st["fitted_again"])
            out[mode]["frame_s"].append(float(np.median(st["frame_seconds"][1:])) if st["frames_fitted"] > 1
                                        else float("nan"))
            out[mode]["drawn"].append(int(round(st["drawn_per_step"])))
            out["gaussians"] = st["gaussians"]
            log(f"run {r + 1}/{repeats} {mode:<6}: {out[mode]['frame_s'][-1]:.2f} s a frame after the first, "
                f"{out[mode]['drawn'][-1]} of {out['gaussians']} Gaussians drawn per step, "
                f"{out[mode]['fitted_again'][-1]} frame(s) fitted again with all, {st['seconds']:.1f} s in all")
    out["ratio"] = float(np.median(out["subset"]["frame_s"]) / np.median(out["all"]["frame_s"]))
    out["max_pose_difference"] = float(np.max(np.abs(poses["subset"] - poses["all"])))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench track", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="run folder with stage 2 (fgjax stage2 --run)")
    p.add_argument("--data", required=True, help="the dataset it was trained on")
    p.add_argument("--start", type=int, default=20, help="first training frame (time order; default: %(default)s)")
    p.add_argument("--frames", type=int, default=6, help="frames fitted (default: %(default)s)")
    p.add_argument("--steps", type=int, default=40, help="Adam steps a frame (default: %(default)s)")
    p.add_argument("--objects", default=None, help="comma-separated object ids from 0 (default: all)")
    p.add_argument("--repeats", type=int, default=2, help="runs of each mode, alternated (default: %(default)s)")
    p.add_argument("--margin", type=int, default=2, help="subset_margin in tiles (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        objects = None if args.objects is None else [int(k) for k in args.objects.split(",")]
        r = track_bench(Path(args.run), Path(args.data), start=args.start, frames=args.frames, steps=args.steps,
                        objects=objects, repeats=args.repeats, margin=args.margin)
    except (FileNotFoundError, ValueError, RuntimeError) as e:  # RuntimeError: Stage2Error (no stage 2)
        print(f"fgjax bench track: {e}", file=sys.stderr)
        return 2
    a, s = np.median(r["all"]["frame_s"]), np.median(r["subset"]["frame_s"])
    print(f"median s a frame: all {a:.2f}, subset {s:.2f} (ratio {r['ratio']:.2f}); Gaussians drawn per step: "
          f"all {r['all']['drawn'][0]}, subset {int(np.median(r['subset']['drawn']))} of {r['gaussians']}; "
          f"largest pose difference {r['max_pose_difference']:.2e}")
    return 0
