"""``fgjax train --data SCENE --out RUN [--config FILE] [--set SECTION.KEY=VALUE ...] [--resume | --overwrite]``.

Stage 1 into a new run folder; an existing run is continued (``--resume``, on its own data) or replaced
(``--overwrite``), never overwritten silently. RUN/provenance.json records what made the run.

The configuration (stage 1's sections and, for a later ``fgjax stage2``, [stage2] and [articulate]) is saved as
RUN/config.toml. Named configurations are in experiments/ (docs/architecture.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fgjax.config import ConfigError, load_config
from fgjax.method.stage1 import run
from fgjax.train.checkpoint import CheckpointError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fgjax train", description="Stage 1: deformable Gaussian training.")
    p.add_argument("--data", required=True, help="dataset folder (nerfstudio/Blender/D-NeRF/...)")
    p.add_argument("--out", required=True, help="run folder (config, checkpoint, metrics, renders)")
    p.add_argument("--config", default=None, help="TOML config (e.g. experiments/articulated.toml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, e.g. --set train.steps=3000 (repeatable)")
    p.add_argument("--resume", action="store_true", help="continue from RUN/checkpoint.npz")
    p.add_argument("--overwrite", action="store_true", help="replace the run in RUN (its stage-2 results too)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        cfg = load_config(args.config, args.overrides)
    except ConfigError as e:
        print(f"fgjax train: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    try:
        if args.resume and args.overwrite:
            raise ValueError("give --resume or --overwrite, not both")
        run(cfg, Path(args.data), out, resume=args.resume, overwrite=args.overwrite)
    except (CheckpointError, ValueError) as e:
        print(f"fgjax train: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
