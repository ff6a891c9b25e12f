"""Quality floors of the named configurations on the quick demo scene (`fgjax.apps.demo.QUICK_SCENE`: 128x96, 24 frames,
three moving parts).

The full pipeline runs once per configuration: flow, stage 1 (experiments/demo_quick.toml), stage 2 as the articulated
variant (that file's [stage2] and [articulate]) and as the paper's chain (`Stage2Config` defaults with the file's
automatic eps), then `fgjax.method.evaluate.evaluate_control` against the scene's ground truth. A change that lowers
ARI or held-out PSNR below the floor fails here; so does an articulated run that does not find each of the three parts
as its own object or does not visibly move each object over its sweep (what `make demo` shows). The floors sit a margin
below the values measured in this test on this 2-core CPU (docs/benchmarks.md, "Regression floors"): articulated 3
objects (3 parts found), ari_controlled 0.749, held-out states 23.49 dB, visible motion 0.84, 0.92, 0.79; paper 3
objects, ari_controlled 0.702, held-out states 21.89 dB. Both runs are deterministic on one machine.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from fgjax import synth
from fgjax.apps.demo import QUICK_SCENE
from fgjax.articulate.pipeline import run_articulated
from fgjax.config import Stage2Config, load_config
from fgjax.data.loaders import load_scene
from fgjax.data.opticalflow import estimate_flow
from fgjax.method.evaluate import write_control_metrics
from fgjax.method.result import load_stage2
from fgjax.method.stage1 import run as run_stage1
from fgjax.method.stage2 import run_stage2
from fgjax.pipeline import write_control_pictures
from fgjax.viz import to_u8

pytestmark = [pytest.mark.slow, pytest.mark.optimized]  # long fits: compiled as the command line compiles

REPO = Path(__file__).resolve().parents[2]
FLOORS = {  # name -> (objects found at least, ari_controlled at least, held-out state PSNR at least)
    "articulated": (3, 0.60, 22.8),
    "paper": (3, 0.65, 21.3),
}
VISIBLE = 0.5  # the articulated run: each object's visible motion at least (`fgjax.pipeline.write_control_pictures`)


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """(config, scene folder, stage-1 run folder) of the quick demo scene, trained once for the module."""
    base = tmp_path_factory.mktemp("quick")
    scene_dir = base / "scene"
    synth.generate(synth.SynthConfig(seed=0, **QUICK_SCENE), scene_dir, overwrite=True, progress=lambda *_: None)
    cfg = load_config(REPO / "experiments" / "demo_quick.toml")
    cfg = dataclasses.replace(cfg, stage2=dataclasses.replace(cfg.stage2, flow_cache=str(base / "flow_cache")))
    train = load_scene(scene_dir, "train")
    order = np.argsort(train.times, kind="stable")
    for a, b in zip(order[:-1], order[1:], strict=True):
        estimate_flow(to_u8(train.images[a]), to_u8(train.images[b]), "dis_deepflow", cache_dir=base / "flow_cache")
    run_stage1(cfg, scene_dir, base / "run", log=lambda *_: None)
    return cfg, scene_dir, base / "run"


@pytest.mark.parametrize("name", ["articulated", "paper"])
def test_named_configuration_meets_its_floor(quick_run, tmp_path, name):
    cfg, scene_dir, run_dir = quick_run
    run_dir = Path(shutil.copytree(run_dir, tmp_path / "run"))
    if name == "articulated":
        run_articulated(run_dir, scene_dir, cfg.stage2, cfg.articulate, log=lambda *_: None)
    else:
        paper = Stage2Config(flow_cache=cfg.stage2.flow_cache, auto_eps=cfg.stage2.auto_eps)
        run_stage2(run_dir, scene_dir, paper, log=lambda *_: None)
    run = load_stage2(run_dir)
    assert run.s2.meta["variant"] == name
    res = write_control_metrics(run, scene_dir, log=lambda *_: None)
    objects, ari, psnr = FLOORS[name]
    got = (res["num_objects_found"], res["ari_controlled"], res["state_psnr"])
    print(f"{name}: objects {got[0]}, parts found {res['parts_found']}, ari_controlled {got[1]:.3f}, held-out states "
          f"{got[2]:.2f} dB")  # shown with pytest -s
    assert got[0] >= objects and got[1] >= ari and got[2] >= psnr, (
        f"{name}: objects {got[0]}, ari_controlled {got[1]:.3f}, held-out states {got[2]:.2f} dB; floors "
        f"{objects}, {ari}, {psnr}")
    assert np.isfinite(res["view_psnr_stage1"]) and res["view_psnr_stage1"] > 27.0
    if name == "articulated":  # what `make demo` shows: each part its own object, each visibly moving over its sweep
        assert res["parts_found"] == 3, f"{name}: {res['parts_found']} of 3 parts found (part IoU {res['part_iou']})"
        moved = write_control_pictures(tmp_path, run, load_scene(scene_dir, "train"), say=lambda *_: None)
        print(f"{name}: visible motion {np.round(moved, 2)}")
        assert len(moved) == res["num_objects_found"] and min(moved) >= VISIBLE, (
            f"{name}: visible motion {np.round(moved, 3)} (share of each object's pixels that change by more than "
            f"20/255 over its sweep); floor {VISIBLE}")
