"""``fgjax stage2 --run RUN [--data SCENE] [--config FILE] [--set stage2.KEY=VALUE | articulate.KEY=VALUE ...]``.

Runs stage 2 on a trained stage-1 run: the paper's chain (`fgjax.method.run_stage2`) or the articulated variant
(`fgjax.articulate.run_articulated`), as ``[stage2] variant`` says. The settings are the [stage2] and [articulate]
tables of RUN/config.toml (the configuration stage 1 was trained with), or of ``--config FILE`` when given, then the
``--set`` overrides. Writes RUN/stage2.npz and RUN/stage2.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from fgjax.articulate.pipeline import run_articulated
from fgjax.config import Config, ConfigError, apply_overrides, load_config
from fgjax.method.result import Stage2Error
from fgjax.method.stage2 import run_stage2
from fgjax.provenance import PROVENANCE_NAME, read_provenance
from fgjax.train.checkpoint import CheckpointError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fgjax stage2", description="Stage 2: discovery, clustering, control network.")
    p.add_argument("--run", required=True, help="stage-1 run folder")
    p.add_argument("--data", default=None, help="the dataset the run was trained on (default: the one its "
                   "provenance.json names)")
    p.add_argument("--config", default=None, help="TOML file whose [stage2] and [articulate] tables to use "
                   "(default: the run's config.toml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a stage-2 option, e.g. --set stage2.eps=0.08 or --set articulate.track_rounds=2")
    return p


def stage2_config(run_dir: Path, config: str | None, overrides: list[str]) -> Config:
    """The run's configuration with the [stage2] and [articulate] tables of ``config`` (when given) and the
    overrides applied. Raises ConfigError naming the key or file."""
    own = run_dir / "config.toml"
    cfg = load_config(own) if own.is_file() else Config()
    if config is not None:
        other = load_config(config)
        cfg = dataclasses.replace(cfg, stage2=other.stage2, articulate=other.articulate)
    for o in overrides:
        if o.split("=", 1)[0].strip().split(".")[0] not in ("stage2", "articulate"):
            raise ConfigError(f"--set {o}: fgjax stage2 takes stage2.KEY=VALUE or articulate.KEY=VALUE")
    return apply_overrides(cfg, overrides)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    log = lambda m: print(m, file=sys.stderr, flush=True)
    try:
        cfg = stage2_config(Path(args.run), args.config, args.overrides)
        data = args.data
        if data is None:
            rec = read_provenance(args.run)
            if rec is None or not rec.get("data_dir"):
                raise ValueError(f"{args.run} does not record its data (no {PROVENANCE_NAME}); pass --data SCENE")
            data = rec["data_dir"]
        if cfg.stage2.variant == "articulated":
            run_articulated(args.run, data, cfg.stage2, cfg.articulate, log=log)
        else:
            run_stage2(args.run, data, cfg.stage2, log=log)
    except (ValueError, FileNotFoundError, Stage2Error, CheckpointError) as e:
        print(f"fgjax stage2: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
