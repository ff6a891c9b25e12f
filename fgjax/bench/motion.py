"""``fgjax bench motion``: how much of the objects' motion a stage-1 run learned, on a synthetic scene.

For a trained stage-1 run and the ``fgjax synth`` dataset it was trained on (the ground truth under
DATA/gt is read here, never by the pipeline), prints:

- test-view PSNR over object pixels (ground-truth object id > 0) and over static pixels, pooled over the
  held-out views at training times (the "state" views are stage 2's);
- per object: the true largest displacement of its centre (mean of its Gaussians) over the training
  times, against the learned one: the largest displacement of the mean of the model's Gaussians that lie
  on that object's canonical surface (nearest true canonical Gaussian within 0.05), deformed to times in
  [0, 1] (scene units). A ratio near 0 means stage 1 renders the object in one state at all times;
  near 1 means it follows it.
- how many live Gaussians move more than 0.01, 0.05 and 0.1 scene units at any time.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from fgjax.data.loaders import load_scene
from fgjax.data.scene import Normalization
from fgjax.io import atomic_write
from fgjax.method.stage1 import load_run, render_frame
from fgjax.models.model import deformed_gaussians

__all__ = ["main", "motion_report"]


def _pooled_psnr(err2: np.ndarray) -> float:
    return float(-10.0 * np.log10(max(float(np.mean(err2)), 1e-12))) if err2.size else float("nan")


def motion_report(run_dir: Path, data_dir: Path, num_times: int = 21) -> dict:
    """The measurements above as a dict (see the module docstring)."""
    gt = data_dir / "gt"
    for f in ("meta.json", "canonical.npz", "train/centres.npy", "test/object_id.npy", "test/kind.npy"):
        if not (gt / f).exists():
            raise FileNotFoundError(f"{gt / f} is missing: `fgjax bench motion` needs a dataset written by "
                                    "`fgjax synth` (with its gt folder)")
    cfg, state, spec, meta = load_run(run_dir)
    norm = Normalization.from_dict(meta["normalization"])
    test = load_scene(data_dir, "test", normalize=norm, downscale=cfg.data.downscale)
    ids = np.load(gt / "test" / "object_id.npy")  # [T', H, W]
    kind = np.load(gt / "test" / "kind.npy")  # [T'] 0 = novel view at a training time
    if ids.shape[1:] != (test.height, test.width):
        raise ValueError(f"{gt / 'test/object_id.npy'} has size {ids.shape[1:]}, the test images "
                         f"{(test.height, test.width)} (run trained with data.downscale?)")
    e_obj, e_sta = [], []
    for i in np.flatnonzero(kind == 0):
        img = render_frame(state, spec, cfg, test.viewmats[i], test.Ks[i], test.times[i], test.width, test.height)
        e = np.mean((img - test.images[i]) ** 2, axis=-1)  # [H, W]
        e_obj.append(e[ids[i] > 0])
        e_sta.append(e[ids[i] <= 0])
    res: dict = {"psnr_object_pixels": _pooled_psnr(np.concatenate(e_obj)) if e_obj else float("nan"),
                 "psnr_static_pixels": _pooled_psnr(np.concatenate(e_sta)) if e_sta else float("nan")}
    alive = np.asarray(state.densify.alive)
    can = np.asarray(state.params["gaussians"].means)  # [N, 3] scene units
    times = np.linspace(0.0, 1.0, num_times)
    deformed = [can]  # [num_times][N, 3]
    if spec is not None and not state.static:
        deformed = [np.asarray(deformed_gaussians(state.params, state.densify.alive, float(t), spec)[0]) for t in times]
    disp = np.max([np.linalg.norm(m - can, axis=-1) for m in deformed], axis=0)  # [N]
    res["moving_gaussians"] = {str(th): int(np.sum(alive & (disp > th))) for th in (0.01, 0.05, 0.1)}
    res["live_gaussians"] = int(alive.sum())
    canon = np.load(gt / "canonical.npz")
    gt_pts = norm.points_to_scene(np.asarray(canon["means"], np.float64))  # [M, 3]
    gt_lab = np.asarray(canon["labels"])
    centres = np.load(gt / "train" / "centres.npy")  # [T, K, 3] world units

    live = np.flatnonzero(alive)
    dist, nn = cKDTree(gt_pts).query(can[live])
    near = dist < 0.05  # a model Gaussian on some true surface
    objs = []
    meta_gt = json.loads((gt / "meta.json").read_text())
    for k, o in enumerate(meta_gt["objects"]):
        true = float(norm.lengths_to_scene(np.max(np.linalg.norm(centres[:, k] - centres[:1, k], axis=-1))))
        mine = live[near & (gt_lab[nn] == o["label"])]
        learned = (float(max(np.linalg.norm(np.mean(m[mine] - can[mine], axis=0)) for m in deformed))
                   if len(mine) else float("nan"))
        objs.append({"name": o["name"], "gaussians": int(len(mine)), "true_max_displacement": true,
                     "learned_max_displacement": learned})
    res["objects"] = objs
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench motion", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="stage-1 run folder (fgjax train --out)")
    p.add_argument("--data", required=True, help="the fgjax synth dataset it was trained on")
    p.add_argument("--json", default=None, help="also write the report to this file")
    args = p.parse_args(argv)
    try:
        r = motion_report(Path(args.run), Path(args.data))
    except (FileNotFoundError, ValueError) as e:
        print(f"fgjax bench motion: {e}", file=sys.stderr)
        return 2
    print(f"test views at training times: PSNR object pixels {r['psnr_object_pixels']:.2f}, "
          f"static pixels {r['psnr_static_pixels']:.2f}")
    print(f"{'object':<12} {'gaussians':>9} {'true_disp':>9} {'learned':>9} {'ratio':>6}")
    for o in r["objects"]:
        ratio = o["learned_max_displacement"] / max(o["true_max_displacement"], 1e-12)
        print(f"{o['name']:<12} {o['gaussians']:>9} {o['true_max_displacement']:>9.3f} "
              f"{o['learned_max_displacement']:>9.3f} {ratio:>6.2f}")
    mv = r["moving_gaussians"]
    print(f"live Gaussians {r['live_gaussians']}; moving more than 0.01 / 0.05 / 0.1: "
          f"{mv['0.01']} / {mv['0.05']} / {mv['0.1']}")
    if args.json:
        atomic_write(Path(args.json), lambda f: f.write(json.dumps(r, indent=1).encode()))
    return 0
