"""``fgjax export``: a run's scene as a standard 3DGS .ply file (`fgjax.ply`: binary little-endian, the INRIA
layout that splat viewers read).

    fgjax export --run RUN --out FILE.ply [--time T]
    fgjax export --run RUN --out FILE.ply --object K --vector x,y,z [--object K --vector x,y,z ...]

Without controls: the stage-1 scene at normalised time T (default 0, the start of the sequence), the scene
``fgjax render`` draws at T. With ``--object K --vector x,y,z`` pairs (K 1-based, as in ``fgjax control``): the
controlled scene, each named object's vector snapped to its trajectory as ``fgjax control`` snaps it, the other
objects at rest. Only the active Gaussians are written, with the SH degree the run renders with; the file is
written atomically.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from fgjax.method import result as stage2
from fgjax.method.splats import scene_gaussians
from fgjax.ply import write_ply

__all__ = ["main"]


def _vector(text: str) -> np.ndarray:
    """'x,y,z' -> [3] float64 (finite); ValueError naming --vector otherwise."""
    try:
        v = np.array([float(p) for p in str(text).split(",")])
    except ValueError:
        v = np.array([])
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"--vector must be three finite comma-separated numbers x,y,z, got {text!r}")
    return v


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fgjax export", description="Write a run's scene as a standard 3DGS .ply file.")
    p.add_argument("--run", required=True, help="run folder (stage 1; stage 2 for --object)")
    p.add_argument("--out", required=True, help="output .ply file")
    p.add_argument("--time", type=float, default=None,
                   help="normalised time 0..1 of the stage-1 scene (default 0); not with --object")
    p.add_argument("--object", type=int, action="append", default=[],
                   help="object id K (1-based) to move; repeat with one --vector each")
    p.add_argument("--vector", action="append", default=[],
                   help="displacement x,y,z of the matching --object in scene units (snapped to its trajectory); "
                   "a negative first number as --vector=-x,y,z")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    out = Path(args.out)
    if len(args.object) != len(args.vector):
        raise ValueError(f"give one --vector per --object: got {len(args.object)} --object and "
                         f"{len(args.vector)} --vector")
    if args.object and args.time is not None:
        raise ValueError("give --time (the stage-1 scene) or --object/--vector (the controlled scene), not both")
    if args.time is not None and not (math.isfinite(args.time) and 0.0 <= args.time <= 1.0):
        raise ValueError(f"--time must lie in [0, 1] (normalised time), got {args.time}")
    if len(set(args.object)) != len(args.object):
        raise ValueError(f"--object repeated: {args.object}; give each object once")
    vecs = [_vector(v) for v in args.vector]
    if out.suffix.lower() != ".ply":
        raise ValueError(f"--out {out}: the file name must end in .ply")
    try:
        run = stage2.load_stage2(args.run, require_stage2=bool(args.object))
    except stage2.Stage2Error as e:
        raise ValueError(str(e)) from None
    notes = []
    if args.object:
        s2 = run.s2
        n = s2.num_objects
        vectors = np.zeros((n, 3))
        for obj, vec in zip(args.object, vecs, strict=True):
            if not 1 <= obj <= n:
                raise ValueError(f"--object {obj} out of range: the run has {n} object(s) (1..{n})")
            v, t = stage2.snap_vector(s2, obj - 1, vec)
            vectors[obj - 1] = v
            where = ("lies on its trajectory" if np.allclose(v, vec, rtol=0.0, atol=1e-9) else
                     f"snapped to {np.round(v, 5).tolist()} on its trajectory")
            notes.append(f"object {obj}: vector {vec.tolist()} {where} (time {t:.4f})")
        g = scene_gaussians(run, vectors=vectors)
        what = "the controlled scene"
    else:
        t = 0.0 if args.time is None else args.time
        g = scene_gaussians(run, time=t)
        what = f"the stage-1 scene at time {t:g}"
    out.parent.mkdir(parents=True, exist_ok=True)
    degree = int(run.cfg.model.sh_degree)
    write_ply(out, g, sh_degree=degree)
    for line in notes:
        print(line)
    print(f"wrote {out}: {what}, {g.capacity} Gaussians (the active ones of {len(run.state.densify.alive)} "
          f"slots), SH degree {degree}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
