"""``fgjax bench train``: stage-1 test-view PSNR against wall time, for the frequency and hash-grid fields.

Trains the same config twice (deform.kind = "frequency" with the Deformable-3DGS 8x256 MLP, and
"hash"), evaluating the held-out views every ``--eval-every`` steps, and prints one row per evaluation:
field, step, wall seconds, process CPU seconds, PSNR, SSIM. Without ``--data`` the default synthetic
scene is generated into a temporary folder first.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from fgjax.config import load_config
from fgjax.data.loaders import load_scene
from fgjax.method.stage1 import load_test_views, train_stage1
from fgjax.synth import SynthConfig, generate

__all__ = ["main"]

FIELDS = {
    "frequency": ["deform.kind=frequency", "deform.depth=8", "deform.width=256", "deform.skip=4"],
    "hash": ["deform.kind=hash"],
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench train", description=__doc__.splitlines()[0])
    p.add_argument("--data", default=None, help="dataset folder (default: generate the synthetic scene)")
    p.add_argument("--config", default="experiments/articulated.toml")
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--eval-every", type=int, default=500)
    p.add_argument("--fields", default="hash,frequency", help="comma list of: " + ", ".join(FIELDS))
    p.add_argument("--set", dest="overrides", action="append", default=[])
    p.add_argument("--json", default=None, help="also write the rows to this file")
    args = p.parse_args(argv)

    tmp = None
    data = Path(args.data) if args.data else None
    if data is None:
        tmp = tempfile.TemporaryDirectory()
        data = Path(tmp.name) / "synth"
        generate(SynthConfig(), data)
    rows = []
    print(f"{'field':<10} {'step':>6} {'wall_s':>8} {'cpu_s':>8} {'PSNR':>7} {'SSIM':>7}")
    for field in [f.strip() for f in args.fields.split(",") if f.strip()]:
        if field not in FIELDS:
            print(f"fgjax bench train: unknown field {field!r}", file=sys.stderr)
            return 2
        cfg = load_config(args.config, [f"train.steps={args.steps}", f"train.eval_every={args.eval_every}",
                                         *FIELDS[field], *args.overrides])
        scene = load_scene(data, "train", downscale=cfg.data.downscale)
        test, _, _ = load_test_views(data, cfg, scene.normalization)
        cpu0 = time.process_time()
        res = train_stage1(cfg, scene, None, test_scene=test, progress=False, log=lambda *_: None)
        for h in res["eval_history"]:
            row = {"field": field, **{k: h[k] for k in ("step", "time_s", "cpu_s", "psnr", "ssim")}}
            rows.append(row)
            print(f"{field:<10} {h['step']:>6} {h['time_s']:>8.1f} {h['cpu_s']:>8.1f} {h['psnr']:>7.2f} "
                  f"{h['ssim']:>7.4f}", flush=True)
        print(f"{field:<10} total  {res['time_s']:>8.1f} {time.process_time() - cpu0:>8.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
