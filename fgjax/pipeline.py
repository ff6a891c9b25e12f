"""The whole chain on a scene folder, as `fgjax run` (and, for its stages and control pictures, `fgjax demo`) runs it:
optical flow -> stage 1 -> stage 2 (the paper's chain or the articulated variant, as the configuration's
``stage2.variant`` says) -> pictures -> metrics.

Pictures of a run (`write_run_pictures`, in the run folder):

- ``test_views.png``: the held-out test views, ground truth | stage-1 render at the view's time, with PSNR;
- ``objects.png``: training frames with the discovered objects (the stage-1 model's per-pixel object ids at the
  frame's time, `fgjax.method.result.render_clusters`) tinted over the image;
- ``control_sheet.png``, ``control.mp4`` and ``control_object<k>.png`` (`write_control_pictures`): the controlled
  scene from the first training camera, each object swept from its reference position to its largest displacement
  and back (the video: all objects in turn; the strips: one per object).

Metrics (RUN/metrics.json): stage 1's (``psnr``, ``ssim`` on the test views), ``control`` from
`fgjax.method.evaluate.write_control_metrics` (against ground truth where the scene has it, else what can be
measured), and ``pipeline`` (wall time per phase).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np

from fgjax import metrics
from fgjax.articulate.pipeline import run_articulated
from fgjax.config import Config
from fgjax.data.loaders import load_scene
from fgjax.data.scene import Normalization
from fgjax.io import atomic_write, write_video
from fgjax.method import stage1
from fgjax.method.evaluate import write_control_metrics
from fgjax.method.result import LoadedRun, cluster_vectors_at, load_stage2, render_clusters, render_controlled
from fgjax.method.stage2 import run_stage2
from fgjax.viz import caption, grid, ids_to_color, overlay_ids, pad16, to_u8, upscale

__all__ = ["run_pipeline", "train_and_discover", "discover_objects", "write_run_pictures", "write_control_pictures",
           "test_view_sheet", "objects_sheet", "sweep_times", "changed_share"]


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


def _scale(w: int, target: int = 240) -> int:
    return max(1, target // w)


def write_control_pictures(out: Path, run: LoadedRun, train, say: Callable[[str], None] = print) -> list[float]:
    """OUT/control_sheet.png (a training frame, the controlled scene at v = 0, its object ids, each object at its
    largest displacement), OUT/control.mp4 (each object swept from rest to that displacement and back, captioned) and
    OUT/control_object<k>.png (object k's sweep as a strip of 5 frames), seen from the first training camera; says
    where they went. Returns how visibly each object moves (`changed_share` over its pixels at both ends of its
    sweep), one share per object."""
    s2 = run.s2
    vm, K, w, h = train.viewmats[0], train.Ks[0], train.width, train.height
    s = _scale(w)
    v0 = np.zeros((max(s2.num_objects, 1), 3))  # v = 0 for every object
    ids = render_clusters(run, vm, K, w, h, vectors=v0 if s2.num_objects else None)  # the scene beside it
    rgb0 = render_controlled(run, v0, vm, K, w, h)
    tiles = [caption(upscale(to_u8(train.images[0]), s), "training frame 0"),
             caption(upscale(to_u8(rgb0), s), "stage 2, v = 0"),
             caption(upscale(ids_to_color(ids), s), f"{s2.num_objects} object(s) found")]
    frames, moved = [], []
    for k in range(s2.num_objects):
        times = sweep_times(s2, k)
        raw = []
        for t in np.concatenate([times, times[::-1][1:]]):
            vec = np.zeros((s2.num_objects, 3))
            vec[k] = cluster_vectors_at(s2, t)[k]
            raw.append(to_u8(render_controlled(run, vec, vm, K, w, h)))
            frames.append(pad16(caption(upscale(raw[-1], max(1, 320 // w)), f"object {k + 1}")))
        far = len(times) - 1  # the object at its largest displacement
        ids_far = render_clusters(run, vm, K, w, h, vectors=np.where(np.arange(s2.num_objects)[:, None] == k,
                                                                      cluster_vectors_at(s2, times[-1]), 0.0))
        moved.append(changed_share(raw[0], raw[far], (ids == k + 1) | (ids_far == k + 1)))
        tiles.append(caption(upscale(raw[far], s), f"object {k + 1} moved"))
        strip = [caption(upscale(raw[j], s), f"object {k + 1}: {j}/{far}") for j in np.linspace(0, far, 5).astype(int)]
        path = out / f"control_object{k + 1}.png"
        atomic_write(path, lambda f, a=grid([strip]): f.write(iio.imwrite("<bytes>", a, extension=".png")))
    sheet = out / "control_sheet.png"
    atomic_write(sheet, lambda f: f.write(iio.imwrite("<bytes>", grid([tiles]), extension=".png")))
    say(f"control sheet: {sheet}")
    if frames:
        say(f"control video: {write_video(frames, out / 'control.mp4')} (and {s2.num_objects} strip(s) "
            f"control_object<k>.png)")
    return moved


def test_view_sheet(run: LoadedRun, test, max_rows: int = 6) -> tuple[np.ndarray, list[float]]:
    """([H', W', 3] uint8: up to ``max_rows`` evenly spaced test views, one row each, ground truth | stage-1 render at
    the view's time; the PSNR of every view shown)."""
    s = _scale(test.width)
    rows, ps = [], []
    for i in np.unique(np.linspace(0, test.num_frames - 1, min(max_rows, test.num_frames)).round().astype(int)):
        img = stage1.render_frame(run.state, run.spec, run.cfg, test.viewmats[i], test.Ks[i], test.times[i],
                                  test.width, test.height)
        ps.append(float(metrics.psnr(img, test.images[i])))
        rows.append([caption(upscale(to_u8(test.images[i]), s), f"{test.frame_names[i].split('/')[-1]} (GT)"),
                     caption(upscale(to_u8(img), s), f"stage 1, t = {test.times[i]:.2f}: {ps[-1]:.2f} dB")])
    return grid(rows), ps


def objects_sheet(run: LoadedRun, train, n: int = 4) -> np.ndarray:
    """[H', W', 2 n', 3] uint8: ``n`` evenly spaced training frames with the discovered objects tinted over them
    (top row) and the object ids (bottom row), from the stage-1 model at each frame's time."""
    s = _scale(train.width)
    top, bottom = [], []
    for i in np.unique(np.linspace(0, train.num_frames - 1, min(n, train.num_frames)).round().astype(int)):
        ids = render_clusters(run, train.viewmats[i], train.Ks[i], train.width, train.height, t=float(train.times[i]))
        share = 100 * float(np.mean(ids >= 1))
        top.append(caption(upscale(overlay_ids(to_u8(train.images[i]), ids), s),
                           f"t = {train.times[i]:.2f}: objects on {share:.0f}%"))
        bottom.append(caption(upscale(ids_to_color(ids), s), f"{run.s2.num_objects} object(s)"))
    return grid([top, bottom])


def write_run_pictures(run: LoadedRun, scene_dir: Path, out: Path, say: Callable[[str], None] = print) -> list[Path]:
    """The pictures of the module docstring in ``out``; returns their paths."""
    norm = Normalization.from_dict(run.meta["normalization"])
    train = load_scene(scene_dir, "train", normalize=norm, downscale=run.cfg.data.downscale)
    test, _, _ = stage1.load_test_views(scene_dir, run.cfg, norm)
    made = []
    if test is not None and test.num_frames:
        sheet, _ = test_view_sheet(run, test)
        made.append(atomic_write(out / "test_views.png", lambda f: f.write(iio.imwrite("<bytes>", sheet,
                                                                                       extension=".png"))))
        say(f"test views:    {made[-1]}")
    obj = objects_sheet(run, train)
    made.append(atomic_write(out / "objects.png", lambda f: f.write(iio.imwrite("<bytes>", obj, extension=".png"))))
    say(f"objects:       {made[-1]}")
    write_control_pictures(out, run, train, say=say)
    made.append(out / "control_sheet.png")
    made += sorted(out.glob("control_object*.png"))
    made += [p for p in (out / "control.mp4", out / "control.gif") if p.exists()]
    return made


def train_and_discover(cfg: Config, scene_dir: Path, run_dir: Path, *, log: Callable[[str], None] = print,
                       overwrite: bool = False) -> LoadedRun:
    """Stage 1 (`fgjax.method.stage1.run`: RUN/checkpoint, test renders, metrics.json) then stage 2 as
    ``cfg.stage2.variant`` says (``"articulated"``: `fgjax.articulate.run_articulated`, else the paper's
    `fgjax.method.stage2.run_stage2`); returns the loaded run."""
    t0 = time.perf_counter()
    stage1.run(cfg, scene_dir, run_dir, log=log, overwrite=overwrite)
    log(f"stage 1 done ({time.perf_counter() - t0:.1f} s)")
    run = discover_objects(cfg, scene_dir, run_dir, log=log)
    log(f"stage 2 done ({time.perf_counter() - t0:.1f} s)")
    return run


def discover_objects(cfg: Config, scene_dir: Path, run_dir: Path, *, log: Callable[[str], None] = print) -> LoadedRun:
    """Stage 2 on the stage-1 run ``run_dir`` as ``cfg.stage2.variant`` says (``"articulated"``:
    `fgjax.articulate.run_articulated`, else the paper's `fgjax.method.stage2.run_stage2`); returns the loaded run."""
    if cfg.stage2.variant == "articulated":
        run_articulated(run_dir, scene_dir, cfg.stage2, cfg.articulate, log=log)
    else:
        run_stage2(run_dir, scene_dir, cfg.stage2, log=log)
    return load_stage2(run_dir)


def run_pipeline(cfg: Config, scene_dir: str | Path, run_dir: str | Path, *, overwrite: bool = False,
                 log: Callable[[str], None] = print) -> dict[str, Any]:
    """Optical flow (the training pairs, cached in RUN/flow_cache where stage 1 and stage 2 find them) -> stage 1 ->
    stage 2 -> pictures -> metrics on the scene ``scene_dir``, into the run folder ``run_dir`` (new or empty, or an
    earlier run replaced with ``overwrite``: `fgjax.method.stage1.prepare_run_folder`). Returns RUN/metrics.json's
    content."""
    scene_dir, run_dir = Path(scene_dir), Path(run_dir)
    stage1.prepare_run_folder(run_dir, scene_dir, overwrite=overwrite)  # refuses before any work
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    train = load_scene(scene_dir, "train", downscale=cfg.data.downscale)
    run_dir.mkdir(parents=True, exist_ok=True)
    stage1.estimate_training_flows(train, cfg.flow.method, cache_dir=run_dir / "flow_cache", log=log)
    times["flow"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    run = train_and_discover(cfg, scene_dir, run_dir, log=log)
    times["stages"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    pictures = write_run_pictures(run, scene_dir, run_dir, say=log)
    times["pictures"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    write_control_metrics(run, scene_dir, log=log)
    times["eval"] = time.perf_counter() - t3
    times["total"] = time.perf_counter() - t0
    path = run_dir / "metrics.json"
    out = json.loads(path.read_text())
    out["pipeline"] = {"scene": str(scene_dir.absolute()), "time_s": times,
                       "pictures": [str(p.relative_to(run_dir)) for p in pictures]}
    atomic_write(path, lambda f: f.write(json.dumps(out, indent=1).encode()))
    return out
