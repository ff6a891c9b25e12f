"""``fgjax render --run RUN --cameras FILE.json --out DIR``: render any camera list from a trained run.

The camera file is in the nerfstudio / Blender / D-NeRF ``transforms`` format (OpenGL camera-to-world
``transform_matrix`` per frame, ``time`` in [0, 1], intrinsics per frame or at the top level: ``fl_x``...
or ``camera_angle_x``; image files need not exist). Poses are mapped with the run's scene normalisation.
Frames without ``w``/``h`` use the training image size. ``--source control`` draws stage 2's controlled scene
(each object at its learned trajectory at the camera's time) instead of the stage-1 model; ``--clusters`` writes
per-pixel object ids instead of colour, from the controlled scene unless ``--source stage1``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

__all__ = ["main", "read_cameras"]


def read_cameras(path: str | Path, normalization, width: int, height: int):
    """[(name, viewmat [4, 4] normalised OpenCV w2c, K [3, 3], time, w, h)] from a transforms json."""
    from fgjax.data import loaders

    listing = loaders._parse_transforms(Path(path), None)
    out = []
    for i, f in enumerate(listing.frames):
        w = int(round(f.intr["w"])) if f.intr.get("w") is not None else width
        h = int(round(f.intr["h"])) if f.intr.get("h") is not None else height
        K = loaders._intrinsics(f, w, h)
        vm = normalization.viewmats_to_scene(loaders.c2w_to_viewmat(f.c2w))
        name = (f.name or f"{i:05d}").replace("/", "_")
        out.append((name, vm, K, float(f.time), w, h))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax render", description="Render cameras from a trained run.")
    p.add_argument("--run", required=True, help="run folder written by `fgjax train`")
    p.add_argument("--cameras", required=True, help="transforms json (nerfstudio/Blender/D-NeRF, with times)")
    p.add_argument("--out", required=True, help="output folder for PNGs")
    p.add_argument("--clusters", action="store_true",
                   help="write per-pixel object-id maps (0 = static; needs stage 2) instead of colour")
    p.add_argument("--source", choices=("control", "stage1"), default=None,
                   help="the scene drawn: 'control', stage 2's controlled scene with each object at its learned "
                        "trajectory at the camera's time, or 'stage1', the deformable stage-1 model at that time "
                        "(default: control with --clusters, stage1 otherwise)")
    args = p.parse_args(argv)
    source = args.source or ("control" if args.clusters else "stage1")
    import imageio.v3 as iio

    from fgjax.data.scene import Normalization
    from fgjax.pipeline import stage2
    from fgjax.pipeline.stage1 import load_run, render_frame
    from fgjax.train.checkpoint import CheckpointError

    needs_stage2 = args.clusters or source == "control"
    try:  # loaded once: stage 2's renders take the loaded run
        if needs_stage2:
            run = stage2.load_stage2(args.run)
            meta = run.meta
        else:
            cfg, state, spec, meta = load_run(args.run)
            state.static = meta["static"]
    except (FileNotFoundError, CheckpointError, stage2.Stage2Error) as e:
        print(f"fgjax render: {e}", file=sys.stderr)
        return 2
    try:
        cams = read_cameras(args.cameras, Normalization.from_dict(meta["normalization"]), meta["width"], meta["height"])
    except (ValueError, FileNotFoundError) as e:
        print(f"fgjax render: {e}", file=sys.stderr)
        return 2
    if args.clusters:
        return stage2.write_cluster_maps(run, cams, args.out, source=source)
    if needs_stage2:
        return stage2.write_controlled_frames(run, cams, args.out)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, vm, K, t, w, h in cams:
        img = render_frame(state, spec, cfg, vm, K, t, w, h)
        iio.imwrite(out / f"{name}.png", (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
    print(f"rendered {len(cams)} cameras to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
