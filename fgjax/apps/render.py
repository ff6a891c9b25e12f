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

import imageio.v3 as iio
import numpy as np

from fgjax.data.cameras import read_cameras
from fgjax.data.scene import Normalization
from fgjax.method.result import (
    LoadedRun,
    Stage2Error,
    cluster_vectors_at,
    load_stage2,
    render_clusters,
    render_controlled,
)
from fgjax.method.stage1 import load_run, render_frame
from fgjax.train.checkpoint import CheckpointError
from fgjax.viz import ids_to_color, to_u8

__all__ = ["main", "write_cluster_maps", "write_controlled_frames"]


def write_cluster_maps(run_dir: str | Path | LoadedRun, cams, out: str | Path, log=print,
                       source: str = "control") -> int:
    """``fgjax render --clusters``: from a run folder (or a run already loaded by `load_stage2`), per camera (name,
    viewmat, K, time, w, h) write OUT/{name}_ids.npy (int32 object ids, 0 = static) and OUT/{name}_ids.png
    (colour-coded), drawn from ``source`` (`render_clusters`): "control", the controlled scene with each object at
    its trajectory at the camera's time (what `fgjax eval` scores as ``ari_controlled``), or "stage1", the stage-1
    model at that time (``ari``). Returns the exit status."""
    return _write_renders(run_dir, cams, out, log, clusters=True, source=source)


def write_controlled_frames(run_dir: str | Path | LoadedRun, cams, out: str | Path, log=print) -> int:
    """``fgjax render --source control``: from a run folder (or a run already loaded by `load_stage2`), per camera
    (name, viewmat, K, time, w, h) write OUT/{name}.png, the controlled scene with each object at its trajectory at
    the camera's time (`cluster_vectors_at`, `render_controlled`). Returns the exit status."""
    return _write_renders(run_dir, cams, out, log, clusters=False, source="control")


def _write_renders(run_dir, cams, out, log, *, clusters: bool, source: str) -> int:
    """`write_cluster_maps` (``clusters``) or `write_controlled_frames`: 2 where the run cannot be loaded."""


    run = run_dir if isinstance(run_dir, LoadedRun) else _load_for_render(run_dir)
    if run is None:
        return 2
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name, vm, K, t, w, h in cams:
        if clusters:
            ids = render_clusters(run, vm, K, w, h, t=t, source=source)
            np.save(out / f"{name}_ids.npy", ids.astype(np.int32))
            iio.imwrite(out / f"{name}_ids.png", ids_to_color(ids))
        else:
            img = render_controlled(run, cluster_vectors_at(run.s2, float(t)), vm, K, w, h)
            iio.imwrite(out / f"{name}.png", to_u8(img))
    what = "object-id maps" if clusters else "cameras of the controlled scene"
    log(f"rendered {len(cams)} {what} ({run.s2.num_objects} object(s), {source}) to {out}")
    return 0


def _load_for_render(run_dir: str | Path) -> LoadedRun | None:
    """`load_stage2`, or None after printing why to stderr (a missing run, checkpoint or stage-2 result)."""

    try:
        return load_stage2(run_dir)
    except (FileNotFoundError, CheckpointError, Stage2Error) as e:
        print(f"fgjax render: {e}", file=sys.stderr)
        return None


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

    needs_stage2 = args.clusters or source == "control"
    try:  # loaded once: stage 2's renders take the loaded run
        if needs_stage2:
            run = load_stage2(args.run)
            meta = run.meta
        else:
            cfg, state, spec, meta = load_run(args.run)
            state.static = meta["static"]
    except (FileNotFoundError, CheckpointError, Stage2Error) as e:
        print(f"fgjax render: {e}", file=sys.stderr)
        return 2
    try:
        cams = read_cameras(args.cameras, Normalization.from_dict(meta["normalization"]), meta["width"], meta["height"])
    except (ValueError, FileNotFoundError) as e:
        print(f"fgjax render: {e}", file=sys.stderr)
        return 2
    if args.clusters:
        return write_cluster_maps(run, cams, args.out, source=source)
    if needs_stage2:
        return write_controlled_frames(run, cams, args.out)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, vm, K, t, w, h in cams:
        img = render_frame(state, spec, cfg, vm, K, t, w, h)
        iio.imwrite(out / f"{name}.png", to_u8(img))
    print(f"rendered {len(cams)} cameras to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
