"""``fgjax bench family``: the whole pipeline on seeds of the scene family, with the error beside the time.

For each seed (`fgjax.synth.family`): the scene is generated (``DIR/seed_NNN/scene``, reused when it is already
there with the same configuration), then optical flow, stage 1, stage 2 (the configuration's variant) and the
evaluation against the scene's ground truth (`fgjax.method.evaluate`) run into ``DIR/seed_NNN/run``. Printed per
seed and as the mean, and written to ``DIR/family.json``::

    {"seeds": [{"seed", "ari", "ari_controlled", "parts_true", "parts_found", "state_psnr", "state_psnr_moving",
                "stage1_psnr", "wall_s", ...}, ...], "mean": {same keys}, "parts_found_share", "config", "command"}

- ``ari``: adjusted Rand index of the per-pixel object ids (static pixels included) on the held-out "view" frames,
  the labelled Gaussians drawn by stage 1's model at each frame's time;
- ``ari_controlled``: the same with the controlled scene (each object moved to its pose at the frame's time):
  the ids of the model a user moves (`fgjax.method.evaluate`, ``ari_controlled``);
- ``parts_found``: true parts with IoU >= 0.5 against one discovered object's pixels on those frames (`part_ious`);
- ``state_psnr`` / ``state_psnr_moving``: the controlled scene at the held-out object states, on all pixels / on the
  moving parts' pixels;
- ``stage1_psnr``: stage 1 on the held-out views;
- ``wall_s``: the seed's wall time (scene generation excluded; with ``--stage1-from DIR``, which reuses an earlier
  benchmark's scenes and stage-1 runs, stage 2 and the evaluation only);
- ``discovery``: where step 5 loses a part (`fgjax.method.evaluate.discovery_trace`), with ``--trace``.

With ``--depth-maps`` every scene also carries its true depth as a measured one (`fgjax.synth.SynthConfig.depth_maps`:
an ideal RGB-D sensor), which ``model.init = "depth"`` and ``train.depth_weight`` use.

Progress goes to stderr: per seed, stage 1's and stage 2's own lines at most one a minute (`progress_log`), and
each stage's time when it ends.

A PNG sheet per seed, ``DIR/seed_NNN/sheet.png``: for each "view" test frame, the gt ids, the predicted ids, the
controlled render and the gt image. The protocol (seeds 0-5 tune, 6-11 validate) is in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from fgjax.config import Config, load_config
from fgjax.data.loaders import load_scene
from fgjax.data.scene import Normalization
from fgjax.io import atomic_write
from fgjax.method import stage1
from fgjax.method.evaluate import discovery_trace, write_control_metrics
from fgjax.method.result import cluster_vectors_at, render_clusters, render_controlled
from fgjax.pipeline import discover_objects
from fgjax.synth import family_config, generate, make_family_scene, parse_seeds
from fgjax.viz import ids_to_color, to_u8

__all__ = ["main", "run_seed", "KEYS"]

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"
DEFAULT_CONFIG = EXPERIMENTS / "family.toml"
KEYS = ("ari", "ari_controlled", "parts_true", "parts_found", "state_psnr", "state_psnr_moving", "stage1_psnr",
        "wall_s")


def _scene(seed: int, root: Path, size, frames, say, depth_maps: bool = False) -> Path:
    """The seed's scene under ``root/scene``, generated unless it is there with the same configuration, objects
    and camera path."""
    cfg = family_config(seed, size=size, frames=frames, depth_maps=depth_maps)
    out = root / "scene"
    meta = out / "gt" / "meta.json"
    if meta.is_file():
        try:
            old = json.loads(meta.read_text())
            want = json.loads(json.dumps({"config": cfg.to_dict(), "objects": family_description(cfg)}))
            if {"config": old.get("config"), "objects": [old.get("objects"), old.get("camera_path")]} == want:
                return out
        except (OSError, ValueError):
            pass
    generate(cfg, out, overwrite=True, progress=say)
    return out


def family_description(cfg) -> list:
    """[objects, camera path] of a family scene as `fgjax.synth.generate` writes them to gt/meta.json."""
    sc = make_family_scene(cfg)
    cam = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in sc.camera.items()
           if k not in ("freqs", "phases", "weights")}
    return [[o.to_dict() for o in sc.objects], cam]


def _sheet(run, scene_dir: Path, path: Path) -> None:
    """gt ids | predicted ids | controlled render | gt image, one row per "view" test frame."""
    meta = json.loads((scene_dir / "gt" / "meta.json").read_text())
    kinds = [f.get("kind", "view") for f in meta.get("test_frames", [])]
    norm = Normalization.from_dict(run.meta["normalization"])
    test = load_scene(scene_dir, "test", normalize=norm, downscale=run.cfg.data.downscale)
    ids = np.load(scene_dir / "gt" / "test" / "object_id.npy")
    s2, rows = run.s2, []
    for i in [i for i, k in enumerate(kinds) if k == "view"][:4]:
        vm, K, w, h = test.viewmats[i], test.Ks[i], test.width, test.height
        pred = render_clusters(run, vm, K, w, h, t=test.times[i])
        vec = cluster_vectors_at(s2, float(test.times[i])) if s2.num_objects else np.zeros((1, 3))
        rgb = render_controlled(run, vec, vm, K, w, h)
        tiles = [ids_to_color(np.where(ids[i] < 0, 0, ids[i])), ids_to_color(pred), to_u8(rgb), to_u8(test.images[i])]
        rows.append(np.concatenate([np.pad(t, ((1, 1), (1, 1), (0, 0)), constant_values=255) for t in tiles], 1))
    if rows:
        sheet = np.concatenate(rows, 0)
        atomic_write(path, lambda f: iio.imwrite(f, sheet, extension=".png"))


PROGRESS_EVERY_S = 60.0  # the longest silence of a stage's progress lines


def progress_log(say, prefix: str, seconds: float = PROGRESS_EVERY_S, clock=time.monotonic):
    """A log for a long stage that `say`s ``prefix + message``: the first message, every warning or error at once,
    and any other message only when `seconds` have passed since the last one said (a stage 1 of 3,000 steps logs a
    line per 100 steps; this shows one a minute). `clock` gives seconds."""
    last = [-np.inf]

    def log(message, *_):
        text, now = str(message), clock()
        if text.lower().startswith(("warning", "error")) or now - last[0] >= seconds:
            last[0] = now
            say(prefix + text)

    return log


def _copy_stage1(src: Path, dst: Path) -> None:
    """The stage-1 run folder `src` copied to `dst` without its stage-2 results (its flow cache, RUN/flow_cache, which
    stage 1 and stage 2 share, comes along)."""
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("stage2.*", "control*"))
    metrics = dst / "metrics.json"
    if metrics.is_file():
        m = json.loads(metrics.read_text())
        m.pop("control", None)
        metrics.write_text(json.dumps(m, indent=1))


def run_seed(seed: int, out: Path, cfg: Config, *, size=None, frames=None, trace: bool = False, say=print,
             stage1_from: Path | None = None, depth_maps: bool = False) -> dict:
    """The pipeline on family seed `seed` in ``out/seed_NNN`` (see the module docstring); its row of family.json.
    With `depth_maps` the scene carries each frame's depth as a measured one (an RGB-D scene: what
    ``model.init = "depth"`` and ``train.depth_weight`` use).
    With `stage1_from` (an earlier benchmark's folder), that benchmark's scene and stage-1 run of the seed are used
    and only stage 2 and the evaluation run (``wall_s`` then counts stage 2 and the evaluation only)."""
    root = out / f"seed_{seed:03d}"
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    run_dir = root / "run"
    quiet = lambda *_: None
    if stage1_from is not None:
        src = Path(stage1_from) / f"seed_{seed:03d}"
        if not (src / "run" / "checkpoint.npz").is_file():
            raise FileNotFoundError(f"--stage1-from: {src / 'run' / 'checkpoint.npz'} is missing (run the benchmark "
                                    f"on seed {seed} into {stage1_from} first)")
        scene_dir = src / "scene"
        _copy_stage1(src / "run", run_dir)
    else:
        scene_dir = _scene(seed, root, size, frames, say, depth_maps)
        t0 = time.perf_counter()
        stage1.run(cfg, scene_dir, run_dir, log=progress_log(say, f"bench family: seed {seed}: stage 1: "),
                   overwrite=True)
        say(f"bench family: seed {seed}: stage 1 done ({time.perf_counter() - t0:.0f} s)")
    train = load_scene(scene_dir, "train")
    t2 = time.perf_counter()
    run = discover_objects(cfg, scene_dir, run_dir, log=progress_log(say, f"bench family: seed {seed}: stage 2: "))
    say(f"bench family: seed {seed}: stage 2 done ({time.perf_counter() - t2:.0f} s)")
    res = write_control_metrics(run, scene_dir, log=quiet) or {}
    wall = time.perf_counter() - t0
    row = {"seed": seed, "ari": res.get("ari", float("nan")),
           "ari_controlled": res.get("ari_controlled", float("nan")), "parts_true": res.get("parts_true", 0),
           "parts_found": res.get("parts_found", 0), "state_psnr": res.get("state_psnr", float("nan")),
           "state_psnr_moving": res.get("state_psnr_moving", float("nan")),
           "stage1_psnr": res.get("view_psnr_stage1", float("nan")), "wall_s": wall,
           "objects_found": run.s2.num_objects, "part_iou": res.get("part_iou", {}),
           "kinds": list(json.loads((scene_dir / "gt" / "meta.json").read_text())["config"]["objects"]),
           "size": [train.width, train.height], "frames": train.num_frames}
    if trace:
        row["discovery"] = discovery_trace(run_dir, scene_dir, cfg.stage2, log=quiet)
    _sheet(run, scene_dir, root / "sheet.png")
    return row


def summarise(rows: list[dict]) -> dict:
    """Means over the seeds of `KEYS` (nan-aware), and the share of the true parts found."""
    mean = {k: float(np.nanmean([r[k] for r in rows])) if rows else float("nan") for k in KEYS}
    true = sum(r["parts_true"] for r in rows)
    return {"mean": mean,
            "parts_found_share": float(sum(r["parts_found"] for r in rows) / true) if true else float("nan")}


def _fmt(r: dict, name) -> str:
    return (f"{name!s:>6} {r['ari']:6.3f} {r['ari_controlled']:6.3f} {r['parts_found']:>5.4g}/{r['parts_true']:<4.4g} "
            f"{r['state_psnr']:7.2f} {r['state_psnr_moving']:7.2f} {r['stage1_psnr']:7.2f} {r['wall_s']:7.0f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench family", description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="0-11", help="seeds, e.g. 0-5 (tuning), 6-11 (validation), 0-3,12")
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="named configuration (default: %(default)s)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a setting (repeatable)")
    p.add_argument("--out", default="outputs/bench_family", help="output folder (default: %(default)s)")
    p.add_argument("--size", default=None, metavar="WxH", help="render every scene at this size instead of its own")
    p.add_argument("--frames", type=int, default=None, help="training frames per scene instead of the seed's own")
    p.add_argument("--trace", action="store_true", help="also trace discovery per part (discovery_trace)")
    p.add_argument("--depth-maps", action="store_true",
                   help="the scenes carry each frame's true depth as a measured one (an ideal RGB-D sensor)")
    p.add_argument("--stage1-from", default=None, metavar="DIR",
                   help="reuse the scenes and stage-1 runs of an earlier benchmark in DIR; run stage 2 and the "
                        "evaluation only (to compare stage-2 configurations on the same stage 1)")
    args = p.parse_args(argv)
    seeds = parse_seeds(args.seeds)
    size = None
    if args.size:
        try:
            size = tuple(int(x) for x in args.size.lower().split("x"))
            if len(size) != 2 or min(size) < 16:
                raise ValueError
        except ValueError:
            raise ValueError(f"--size: expected WIDTHxHEIGHT (e.g. 320x240), got {args.size!r}") from None
    cfg = load_config(args.config, args.overrides)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    say = lambda msg: print(msg, file=sys.stderr, flush=True)
    rows = []
    print(f"{'seed':>6} {'ARI':>6} {'ctrl':>6} {'parts':>10} {'state':>7} {'moving':>7} {'stage1':>7} {'wall_s':>7}",
          flush=True)
    for seed in seeds:
        row = run_seed(seed, out, cfg, size=size, frames=args.frames, trace=args.trace, say=say,
                       stage1_from=None if args.stage1_from is None else Path(args.stage1_from),
                       depth_maps=args.depth_maps)
        rows.append(row)
        print(_fmt(row, seed), flush=True)
        summary = summarise(rows)
        doc = {"seeds": rows, **summary, "config": str(args.config), "overrides": args.overrides,
               "size": args.size,
               "command": "fgjax bench family " + " ".join(argv if argv is not None else sys.argv[2:])}
        atomic_write(out / "family.json", lambda f, d=doc: f.write(json.dumps(d, indent=1).encode()))
    summary = summarise(rows)
    print(_fmt(summary["mean"] | {"parts_found": sum(r["parts_found"] for r in rows),
                                  "parts_true": sum(r["parts_true"] for r in rows)}, "mean"))
    print(f"parts found: {100 * summary['parts_found_share']:.0f}% of the true parts; results: {out / 'family.json'}")
    return 0
