"""`fgjax run` end to end on a tiny real-capture-like scene (a Record3D export of the ray-cast room, with exact depth,
prepared with `fgjax prepare`): metrics and pictures are written, `fgjax eval` measures what a scene without ground
truth allows, and bad input is one line before any work."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from _captures import TexturedRoom, look_at_c2w, pinhole, write_record3d
from conftest import run_cli

from fgjax import cli
from fgjax.config import load_config, to_dict
from fgjax.method.evaluate import evaluate_measurable
from fgjax.method.result import load_stage2

REPO = Path(__file__).resolve().parents[2]
TINY = ["--config", REPO / "experiments" / "quick.toml", "--set", "train.steps=8", "--set", "train.warmup_steps=2",
        "--set", "densify.enabled=false", "--set", "train.video_frames=0", "--set", "train.checkpoint_every=0",
        "--set", "static.detect=false", "--set", "stage2.auto_eps=true", "--set", "stage2.distill_steps=3",
        "--set", "stage2.photo_steps=0", "--set", "stage2.camera_correction=on"]


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """(scene, run): 10 Record3D frames (48x36, the camera sliding past the cube while it moves; with depth where
    lzfse, a test dependency) prepared and run."""
    base = tmp_path_factory.mktemp("run")
    K = pinhole(48, 36, 40.0)
    c2w = np.stack([look_at_c2w((0.05 * i, -1.6, 1.0), (0.0, 0.0, 0.4)) for i in range(10)])
    room = TexturedRoom(seed=3)
    shots = [room.render(m, K, 48, 36, cube_offset=(0.0, 0.03 * i, 0.0), supersample=1, depth=True)
             for i, m in enumerate(c2w)]
    depths = [s[1] for s in shots]
    folder = write_record3d(base / "r3d", c2w, K, [s[0] for s in shots], depths)
    scene, run = base / "scene", base / "run"
    assert cli.main(["prepare", "--record3d", str(folder), "--out", str(scene), "--test-every", "5"]) == 0
    assert cli.main(["run", "--data", str(scene), "--out", str(run), *[str(a) for a in TINY]]) == 0
    return scene, run


def test_run_writes_metrics_and_pictures(made):
    scene, run = made
    m = json.loads((run / "metrics.json").read_text())
    assert np.isfinite(m["psnr"]) and m["num_views"] == 2  # stage 1 on the held-out frames 4 and 9
    c = m["control"]
    assert c["ground_truth"] is False and c["num_objects_found"] >= 0 and c["views"] == 2
    assert np.isfinite(c["view_psnr_stage1"]) and abs(c["view_psnr_stage1"] - m["psnr"]) < 1e-3
    assert set(c["object_pixel_share"]) == {str(k + 1) for k in range(c["num_objects_found"])}
    assert all(0.0 <= v <= 1.0 for v in c["object_pixel_share"].values())
    # the controlled scene replaying stage 2's trajectories renders the held-out views about as stage 1 does
    assert 0.0 < c["view_ssim_controlled"] <= 1.0
    assert c["view_psnr_controlled"] > c["view_psnr_stage1"] - 6.0, (c["view_psnr_controlled"], c["view_psnr_stage1"])
    assert set(m["pipeline"]["time_s"]) == {"flow", "stages", "pictures", "eval", "total"}
    for name in ("test_views.png", "objects.png", "control_sheet.png"):
        img = iio.imread(run / name)
        assert img.ndim == 3 and img.shape[2] == 3 and name in m["pipeline"]["pictures"]
    assert iio.imread(run / "test_views.png").shape[0] > 2 * 36  # two rows: GT | render
    assert len(list(run.glob("control_object*.png"))) == c["num_objects_found"]


def test_eval_without_ground_truth_measures_depth_on_static_pixels(made, capsys):
    """The stage-1 model of 8 steps covers the frame thinly (alpha ~0.15), so the depth error is measured here with
    every covered pixel counted (min_alpha 0); `fgjax eval` itself counts alpha >= 0.5."""
    scene, run = made
    res = evaluate_measurable(load_stage2(run), scene, log=lambda m: None, min_alpha=0.0)
    d = res["depth_error_static"]
    assert d["pixels"] > 0 and np.isfinite(d["median"]) and d["median"] >= 0 and "metres" in d["unit"]
    code, out, err = run_cli(capsys, "eval", "--run", run)
    assert code == 0 and "measured what the scene allows" in err
    assert json.loads(out.splitlines()[0])["ground_truth"] is False


def test_bad_runs_are_one_line_before_any_work(made, tmp_path, capsys):
    scene, run = made
    code, _, err = run_cli(capsys, "run", "--data", tmp_path / "nowhere", "--out", tmp_path / "r")
    assert code == 2 and "nowhere" in err and "Traceback" not in err
    code, _, err = run_cli(capsys, "run", "--data", scene, "--out", tmp_path / "r", "--set", "train.stepz=3")
    assert code == 2 and "train.stepz" in err
    code, _, err = run_cli(capsys, "run", "--data", scene, "--out", run)
    assert code == 2 and "--overwrite" in err
    assert not (tmp_path / "r").exists()


def test_real_configuration_loads():
    cfg = load_config(REPO / "experiments" / "real.toml")
    assert cfg.stage2.variant == "paper" and cfg.stage2.camera_correction == "on" and cfg.model.sh_degree == 1
    assert cfg.train.steps <= 2000


def test_real_configurations_differ_only_in_the_stage1_motion():
    """experiments/real.toml (motion bases placed from the flow, the flow loss on) and real_hash.toml (the hash
    deformation field) are compared clip by clip in docs/benchmarks.md ("Real captures"): everything but the motion
    model, its learning rates, its warm-up and its losses must be the same for the comparison to mean anything."""
    bases, hashed = (load_config(REPO / "experiments" / f"{n}.toml") for n in ("real", "real_hash"))
    assert (bases.deform.kind, bases.deform.init, bases.flow.enabled) == ("bases", "flow", True)
    assert (hashed.deform.kind, hashed.flow.enabled) == ("hash", False)
    motion = {"deform": {"kind", "init", "weights"}, "flow": {"enabled", "norm", "start"},
              "train": {"warmup_steps", "lr_deform", "lr_deform_final", "rigid_weight"}}

    def shared(cfg):
        return {name: {k: v for k, v in sec.items() if k not in motion.get(name, set())} if isinstance(sec, dict)
                else sec for name, sec in to_dict(cfg).items()}

    assert shared(bases) == shared(hashed)
