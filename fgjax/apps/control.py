"""``fgjax control``: move one discovered object and render (DESIGN.md section 1, step 8).

    fgjax control --run RUN --object K --vector x,y,z [--cameras FILE.json] --out DIR [--sweep]

K is 1-based (the per-pixel id of `render_clusters`; clusters are numbered by decreasing size).
The vector is a displacement of the object's centre in the run's normalised scene units, from its
position at the reference time (the first training frame). It is snapped to the nearest point of the
object's stored trajectory ς(·, K) (`fgjax.cluster.snap_to_trajectory`) and fed to the control
network; the other objects stay at the reference state. Cameras: a transforms json as for
``fgjax render`` (default: the first training camera of the run's dataset). Writes
DIR/object{K}_{camera}.png per camera; ``--sweep`` instead writes DIR/object{K}_sweep.mp4 (GIF
without ffmpeg), moving object K through its whole trajectory from the first camera.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from fgjax.data.cameras import read_cameras
from fgjax.data.scene import Normalization
from fgjax.io import write_video
from fgjax.method import result as stage2
from fgjax.train.checkpoint import CheckpointError
from fgjax.viz import pad16, to_u8, upscale

__all__ = ["main", "parse_vector", "default_cameras"]


def parse_vector(text: str) -> np.ndarray:
    """'x,y,z' -> [3] float64; ValueError with a clear message otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise ValueError(f"--vector must be three comma-separated numbers x,y,z, got {text!r}")
    try:
        v = np.array([float(p) for p in parts])
    except ValueError:
        raise ValueError(f"--vector must be three comma-separated numbers x,y,z, got {text!r}") from None
    if not np.all(np.isfinite(v)):
        raise ValueError(f"--vector must be finite, got {text!r}")
    return v


def default_cameras(run, cameras: str | None):
    """[(name, viewmat, K, time, w, h)] from `cameras` or the first training camera of the run's data."""
    norm = Normalization.from_dict(run.meta["normalization"])
    w, h = run.meta["width"], run.meta["height"]
    if cameras is not None:
        return read_cameras(cameras, norm, w, h)
    data = Path(run.s2.meta.get("data_dir", ""))
    tj = data / "transforms_train.json"
    if not tj.is_file():
        raise FileNotFoundError(f"no --cameras given and {tj} (the run's training cameras) is not readable; "
                                "pass --cameras FILE.json")
    return read_cameras(tj, norm, w, h)[:1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax control", description="Move a discovered object and render.")
    p.add_argument("--run", required=True, help="run folder with stage-2 results")
    p.add_argument("--object", type=int, required=True, help="object id K (1-based)")
    p.add_argument("--vector", default=None, help="displacement x,y,z in scene units (snapped to the trajectory); "
                   "required unless --sweep")
    p.add_argument("--cameras", default=None, help="transforms json (default: first training camera)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--sweep", action="store_true", help="write a video moving the object through its range")
    p.add_argument("--frames", type=int, default=24, help="video frames for --sweep (default: %(default)s)")
    args = p.parse_args(argv)

    err = lambda m: print(f"fgjax control: {m}", file=sys.stderr)
    try:
        if args.vector is None and not args.sweep:
            raise ValueError("give --vector x,y,z (the object's displacement) or --sweep (its whole range)")
        if args.vector is not None and args.sweep:
            raise ValueError("give --vector or --sweep, not both")
        vec = parse_vector(args.vector) if args.vector is not None else None
        run = stage2.load_stage2(args.run)
        n = run.s2.num_objects
        if n == 0:
            raise ValueError(f"{args.run}: stage 2 found no objects; nothing to control")
        if not 1 <= args.object <= n:
            raise ValueError(f"--object {args.object} out of range: the run has {n} object(s) (1..{n})")
        cams = default_cameras(run, args.cameras)
        if args.sweep and args.frames < 2:
            raise ValueError(f"--frames must be >= 2, got {args.frames}")
    except (ValueError, FileNotFoundError, CheckpointError, stage2.Stage2Error) as e:
        err(e)
        return 2
    k = args.object - 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    s2 = run.s2
    vectors = np.zeros((n, 3))
    if not args.sweep:
        v, t = stage2.snap_vector(s2, k, vec)
        vectors[k] = v
        for name, vm, K, _, w, h in cams:
            img = stage2.render_controlled(run, vectors, vm, K, w, h)
            path = out / f"object{args.object}_{name}.png"
            iio.imwrite(path, to_u8(img))
            print(f"wrote {path}")
        off = float(np.linalg.norm(np.asarray(v) - vec))
        print(f"object {args.object}: vector {vec.tolist()} snapped to {np.round(v, 5).tolist()} on its trajectory "
              f"(time {t:.4f}; moved by {off:.4g} scene units"
              + (", more than the trajectory's own reach: the vector lies far off it" if off > float(np.max(
                  np.linalg.norm(s2.traj[k] - s2.traj[k, :1], axis=-1), initial=0.0)) else "") + ")")
        return 0

    name, vm, K, _, w, h = cams[0]
    frames = []
    for t in np.concatenate([np.linspace(0, 1, args.frames // 2 + 1), np.linspace(1, 0, args.frames // 2 + 1)[1:]]):
        tt = s2.traj_times[0] + t * (s2.traj_times[-1] - s2.traj_times[0])
        vectors[:] = 0
        vectors[k] = stage2.cluster_vectors_at(s2, tt)[k]
        img = stage2.render_controlled(run, vectors, vm, K, w, h)
        frames.append(pad16(upscale(to_u8(img), max(1, 320 // w))))
    path = write_video(frames, out / f"object{args.object}_sweep.mp4")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
