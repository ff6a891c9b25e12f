"""A tiny trained stage-1 + stage-2 run shared by the pipeline tests (built once per session, and once for
all the workers of ``pytest -n``: the folder is shared and its building is locked)."""

from __future__ import annotations

import fcntl
import os
import shutil
from contextlib import contextmanager
from pathlib import Path

from fgjax.config import ArticulateConfig, Stage2Config


def shared_base(tmp_path_factory) -> Path:
    """The session's temporary folder, or under ``pytest -n`` (pytest-xdist) the one its workers share."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextmanager
def _locked(path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)  # released when the file closes
        yield

QUICK = ["train.steps=8", "train.warmup_steps=2", "densify.enabled=false", "train.video_frames=0",
         "train.log_every=4", "train.checkpoint_every=0", "static.detect=false"]


# the articulated variant's settings for the tiny run: the flow tracking and a few re-fit steps (seconds, not minutes)
TINY_STAGE2 = (Stage2Config(auto_eps=True, distill_steps=5, photo_steps=2, control_rigid=True),
               ArticulateConfig(refit_steps=4, track_photo=0, relabel_steps=0, local_threshold=0.4, hull_refit_steps=4))


def tiny_run(base: Path, *, stage2: bool = True) -> tuple[Path, Path]:
    """(run_dir, data_dir) under `base` (48x36, 8 frames, 8 stage-1 steps); cached on disk, built under a
    lock so that parallel test workers build it once."""
    with _locked(base.parent / f"{base.name}.lock"):
        return _tiny_run(base, stage2=stage2)


def _tiny_run(base: Path, *, stage2: bool) -> tuple[Path, Path]:
    from conftest import synth

    from fgjax.articulate import run_articulated
    from fgjax.config import load_config
    from fgjax.method import stage1
    from fgjax.method.result import STAGE2_NAME

    data, run = base / "scene", base / "run"
    if not (data / "gt" / "meta.json").exists():
        synth.generate(synth.SynthConfig(width=48, height=36, frames=8, test_views=1, test_states=1), data,
                       overwrite=True, progress=None)
    if not (run / "model.json").exists():
        shutil.rmtree(run, ignore_errors=True)
        cfg = load_config(Path(__file__).resolve().parents[1] / "experiments" / "quick.toml", QUICK)
        from fgjax.data.loaders import load_scene

        stage1.train_stage1(cfg, load_scene(data, "train"), run, progress=False, log=lambda m: None)
    if stage2 and not (run / STAGE2_NAME).exists():
        run_articulated(run, data, *TINY_STAGE2, log=lambda m: None)
    return run, data
