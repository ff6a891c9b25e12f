"""``fgjax run --data SCENE --out RUN [--config FILE] [--set SECTION.KEY=VALUE ...] [--overwrite]``: the whole chain
on a scene folder (`fgjax.pipeline.run_pipeline`): optical flow, stage 1, stage 2, pictures (RUN/test_views.png,
RUN/objects.png, RUN/control_sheet.png, RUN/control.mp4, RUN/control_object<k>.png) and metrics (RUN/metrics.json:
stage 1's test ``psnr``, ``control`` from `fgjax eval`, ``pipeline`` timings).

The settings come from one named configuration, experiments/real.toml by default (real captures prepared with
`fgjax prepare`), or ``--config FILE``; ``--set`` overrides one key. Every override is checked before any work.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from fgjax.config import load_config
from fgjax.data.loaders import detect_layout
from fgjax.pipeline import run_pipeline

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax run", description="Optical flow, stage 1, stage 2, pictures and "
                                "metrics on a scene folder, in one command.")
    p.add_argument("--data", required=True, help="scene folder (e.g. from fgjax prepare)")
    p.add_argument("--out", required=True, help="run folder (new or empty)")
    p.add_argument("--config", default=None,
                   help="named configuration (default: experiments/real.toml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a setting (repeatable), e.g. train.steps=500")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out")
    args = p.parse_args(argv)
    cfg = load_config(args.config or EXPERIMENTS / "real.toml", args.overrides)
    data = Path(args.data)
    detect_layout(data, "train")  # a missing or unrecognised scene folder: one line, before any work
    say = lambda msg: print(msg, file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    res = run_pipeline(cfg, data, Path(args.out), overwrite=args.overwrite, log=say)
    c = res.get("control", {})
    shares = c.get("object_pixel_share", {})
    print(f"run: {args.out} ({time.perf_counter() - t0:.0f} s)")
    print(f"stage-1 test views: PSNR {res.get('psnr', float('nan')):.2f} dB, SSIM {res.get('ssim', float('nan')):.4f}")
    if "view_psnr_controlled" in c:
        print(f"controlled scene on the test views (each object replaying its trajectory): PSNR "
              f"{c['view_psnr_controlled']:.2f} dB, SSIM {c['view_ssim_controlled']:.4f}")
    print(f"objects found: {c.get('num_objects_found')}"
          + (" (" + ", ".join(f"object {k} on {100 * v:.1f}% of the frame" for k, v in shares.items()) + ")"
             if shares else ""))
    if "depth_error_static" in c:
        d = c["depth_error_static"]
        print(f"depth on static pixels: median error {d['median']:.3f} (mean {d['mean']:.3f}) world units, "
              f"{100 * d['median_relative']:.1f}% relative, {d['pixels']} pixels")
    print(f"metrics: {Path(args.out) / 'metrics.json'}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
