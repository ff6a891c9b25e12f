"""``fgjax prepare``: a real capture to the scene layout fgjax loads (`fgjax.data.prepare`).

    fgjax prepare --video CLIP.mp4 --out SCENE [--max-side 320] [--stride N] [--frames A:B] [--test-every 8]
                  [--fov DEG] [--poses auto|rotation|still] [--camera-model SIMPLE_RADIAL|SIMPLE_PINHOLE]
    fgjax prepare --record3d DIR --out SCENE [--max-side 320] [--stride N] [--frames A:B] [--no-depth]

A clip's cameras come from structure from motion (pycolmap: ``pip install 'fgjax[video]'``), or, when it registers
too few frames, from a camera turning about a fixed centre or held still (one line says which and why); a Record3D
export brings its own poses and LiDAR depth. SCENE gets transforms_train.json, transforms_test.json (every 8th frame),
images/, depth/ (Record3D) and prepare.json (what was done). Nothing is left in SCENE when a step fails.
"""

from __future__ import annotations

import argparse
import sys
import time

from fgjax.data.prepare import POSE_MODES, prepare_record3d, prepare_video, write_scene
from fgjax.data.sfm import CAMERA_MODELS, focal_from_fov
from fgjax.data.video import parse_frame_range


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax prepare", description="A phone clip or a Record3D export to a scene "
                                "folder fgjax loads (transforms_train/test.json, images/, prepare.json).")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--video", metavar="CLIP", help="a video file (poses by structure from motion)")
    src.add_argument("--record3d", metavar="DIR", help="a Record3D export folder (metadata, rgbd/)")
    p.add_argument("--out", required=True, help="scene folder to write (new or empty)")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier prepared scene in --out")
    p.add_argument("--max-side", type=int, default=320, help="longer image side in pixels (default %(default)s)")
    p.add_argument("--stride", type=int, default=1, help="keep every N-th frame (default %(default)s)")
    p.add_argument("--frames", default=None, metavar="A:B", help="source frames A to B-1 (default: all)")
    p.add_argument("--test-every", type=int, default=8,
                   help="hold out every N-th frame as a test view (0: none; default %(default)s)")
    p.add_argument("--fov", type=float, default=60.0, metavar="DEG",
                   help="horizontal field of view when SfM gives no focal length (default %(default)s)")
    p.add_argument("--poses", choices=POSE_MODES, default="auto",
                   help="auto: SfM, falling back to a turning or still camera; rotation or still: skip SfM")
    p.add_argument("--camera-model", choices=CAMERA_MODELS, default="SIMPLE_RADIAL",
                   help="SfM camera model (SIMPLE_RADIAL: its k1 is undistorted away; default %(default)s)")
    p.add_argument("--min-registered", type=float, default=0.5,
                   help="share of the frames SfM must register to be used (default %(default)s)")
    p.add_argument("--no-depth", action="store_true", help="Record3D: do not read the LiDAR depth")
    args = p.parse_args(argv)
    first, last = parse_frame_range(args.frames)
    if not 0.0 < args.min_registered <= 1.0:
        raise ValueError(f"--min-registered must be in (0, 1], got {args.min_registered}")
    if args.test_every < 0 or args.test_every == 1:
        raise ValueError(f"--test-every must be 0 (no test split) or >= 2, got {args.test_every}")
    focal_from_fov(100, args.fov)  # checks --fov before any work
    say = lambda msg: print(msg, file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    if args.video:
        cap = prepare_video(args.video, max_side=args.max_side, stride=args.stride, first=first, last=last,
                            poses=args.poses, fov_deg=args.fov, camera_model=args.camera_model,
                            min_registered=args.min_registered, log=say)
    else:
        cap = prepare_record3d(args.record3d, max_side=args.max_side, stride=args.stride, first=first, last=last,
                               depth=not args.no_depth, log=say)
    out = write_scene(args.out, cap, test_every=args.test_every, overwrite=args.overwrite, log=say)
    info = cap.info
    sfm = info.get("sfm")
    print(f"scene: {out} ({len(cap.images)} frames, {cap.images.shape[2]}x{cap.images.shape[1]}; poses: "
          f"{info['poses']}" + (f", SfM registered {sfm['registered']} of {sfm['frames']}" if sfm else "")
          + f"; {time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
