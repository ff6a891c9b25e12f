"""``fgjax eval --run RUN [--data DATA] [--maps DIR]``: control metrics against synthetic ground truth
(`fgjax.method.evaluate.evaluate_control`), or on a scene without it (a real capture) what can be measured
(`fgjax.method.evaluate.evaluate_measurable`: stage-1 test PSNR/SSIM, the objects and their share of the frame, depth
error on static pixels where there is depth), written into RUN/metrics.json under "control"."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from fgjax.method.evaluate import write_control_metrics
from fgjax.method.result import Stage2Error, load_stage2
from fgjax.train.checkpoint import CheckpointError


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax eval", description="Evaluate a run against ground truth, or measure "
                                "what a scene without it allows.")
    p.add_argument("--run", required=True, help="run folder with stage-2 results")
    p.add_argument("--data", default=None, help="dataset folder (default: the one stage 2 recorded)")
    p.add_argument("--maps", default=None, metavar="DIR",
                   help="also write each held-out state's render | image | error x4 to DIR/state_NNN.png")
    args = p.parse_args(argv)
    try:
        run = load_stage2(args.run)
    except (FileNotFoundError, CheckpointError, Stage2Error) as e:
        print(f"fgjax eval: {e}", file=sys.stderr)
        return 2
    res = write_control_metrics(run, Path(args.data) if args.data else None,
                                maps_dir=Path(args.maps) if args.maps else None)
    if res.get("ground_truth") is False:
        data = args.data or run.s2.meta.get("data_dir", "")
        print(f"fgjax eval: no ground truth at {Path(data) / 'gt'}; measured what the scene allows", file=sys.stderr)
    print(json.dumps({k: v for k, v in res.items() if not k.endswith("per_view") and not k.endswith("per_frame")}))
    print(f"wrote {Path(args.run) / 'metrics.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
