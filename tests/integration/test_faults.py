"""Fault injection through the command line: every bad input or refusing file system gives exit status 2 and one line
naming the file or option (no traceback), nothing stale is served, and nothing is half-written.

One tiny run is made through the CLI (so it has its provenance), then each case works on a copy of it."""

from __future__ import annotations

import errno
import json
import os
import shutil
import socket
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli, synth

from fgjax import cli

REPO = Path(__file__).resolve().parents[2]
QUICK = ["--config", str(REPO / "experiments" / "quick.toml"), "--set", "train.steps=8", "--set",
         "train.warmup_steps=2", "--set", "densify.enabled=false", "--set", "train.video_frames=0", "--set",
         "train.log_every=4", "--set", "train.checkpoint_every=0", "--set", "static.detect=false"]
FAST_STAGE2 = ["--set", "stage2.auto_eps=true", "--set", "stage2.distill_steps=3", "--set", "stage2.photo_steps=0"]


def one_line_error(err: str, *needles: str) -> None:
    """The error output is one line (besides progress lines) that names every needle; no traceback."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if "error" in ln or ln.startswith("fgjax")]
    assert lines, err
    for n in needles:
        assert n in lines[-1], (n, lines[-1])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """(scene, other scene of the same size, run with stage 2) made through the CLI."""
    base = tmp_path_factory.mktemp("faults")
    scenes = []
    for seed in (0, 1):
        d = base / f"scene{seed}"
        synth.generate(synth.SynthConfig(width=48, height=36, frames=8, test_views=1, test_states=1, seed=seed), d,
                       overwrite=True, progress=None)
        scenes.append(d)
    run = base / "run"
    assert cli.main(["train", "--data", str(scenes[0]), "--out", str(run), *QUICK]) == 0
    assert cli.main(["stage2", "--run", str(run), *FAST_STAGE2]) == 0  # --data from the run's provenance
    return scenes[0], scenes[1], run


@pytest.fixture
def run(made, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(made[2], dst)
    return dst


def test_the_run_records_what_made_it(made):
    scene, _, run = made
    rec = json.loads((run / "provenance.json").read_text())
    assert rec["data_dir"] == str(scene.resolve()) and len(rec["data_fingerprint"]) == 64
    assert rec["checkpoint"]["step"] == 8 and len(rec["checkpoint"]["sha256"]) == 64
    assert rec["fgjax_version"] and rec["config_sha256"]
    meta = json.loads((run / "stage2.json").read_text())
    assert meta["stage1_checkpoint"]["sha256"] == rec["checkpoint"]["sha256"]
    assert meta["data_fingerprint"] == rec["data_fingerprint"]


def test_train_into_an_existing_run_refuses_without_resume_or_overwrite(made, run, capsys):
    scene = made[0]
    before = (run / "checkpoint.npz").read_bytes()
    code, _, err = run_cli(capsys, "train", "--data", scene, "--out", run, *QUICK)
    assert code == 2
    one_line_error(err, str(run), "--resume", "--overwrite")
    assert (run / "checkpoint.npz").read_bytes() == before and (run / "stage2.npz").exists()


def test_overwrite_replaces_the_run_and_its_stage2(made, run, capsys):
    code, _, _ = run_cli(capsys, "train", "--data", made[0], "--out", run, "--overwrite", *QUICK)
    assert code == 0
    assert not (run / "stage2.npz").exists() and (run / "provenance.json").exists()


def test_resume_refuses_other_data_and_a_smaller_step_count(made, run, capsys):
    code, _, err = run_cli(capsys, "train", "--data", made[1], "--out", run, "--resume", *QUICK)
    assert code == 2
    one_line_error(err, "--resume", str(made[1]))
    code, _, err = run_cli(capsys, "train", "--data", made[0], "--out", run, "--resume", *QUICK,
                           "--set", "train.steps=4")
    assert code == 2
    one_line_error(err, "step 8", "train.steps=4")


def test_stage2_left_by_an_earlier_stage1_is_refused_naming_both(made, run, capsys):
    # stage 1 trained further in the same folder: the old stage 2 stays, and is refused
    code, _, _ = run_cli(capsys, "train", "--data", made[0], "--out", run, "--resume", *QUICK,
                         "--set", "train.steps=10")
    assert code == 0 and (run / "stage2.npz").exists()
    cams = made[0] / "transforms_test.json"
    for argv in (["render", "--run", run, "--cameras", cams, "--out", run.parent / "r", "--clusters"],
                 ["control", "--run", run, "--object", "1", "--vector", "0,0,0", "--out", run.parent / "c"],
                 ["export", "--run", run, "--object", "1", "--vector", "0,0,0", "--out", run.parent / "e.ply"],
                 ["eval", "--run", run]):
        code, _, err = run_cli(capsys, *argv)
        assert code == 2, argv
        one_line_error(err, "stage-1 checkpoint", "step 8", "step 10", "run stage 2 again")


def test_stage2_on_other_data_is_refused(made, run, capsys):
    code, _, err = run_cli(capsys, "stage2", "--run", run, "--data", made[1], *FAST_STAGE2)
    assert code == 2
    one_line_error(err, str(made[1]), "not the data")


def test_a_truncated_stage2_result_is_one_line(made, run, capsys):
    p = run / "stage2.npz"
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    code, _, err = run_cli(capsys, "eval", "--run", run)
    assert code == 2
    one_line_error(err, "stage2.npz", "not a readable stage-2 result")


def test_a_corrupt_checkpoint_is_one_line(made, run, capsys):
    (run / "checkpoint.npz").write_bytes(b"not a checkpoint")
    for argv in (["eval", "--run", run], ["export", "--run", run, "--out", run.parent / "e.ply"],
                 ["view", "--run", run, "--port", free_port()]):
        code, _, err = run_cli(capsys, *argv)
        assert code == 2, argv
        one_line_error(err, "checkpoint.npz")


def test_a_read_only_folder_is_one_line_and_leaves_no_temporary_file(made, run, capsys, monkeypatch):
    """As root no folder is read-only, so the file system's refusal is injected where every writer goes through:
    `fgjax.io.atomic_write`'s final rename."""
    import fgjax.io

    def refuse(src, dst):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(dst))

    monkeypatch.setattr(fgjax.io.os, "replace", refuse)
    before = (run / "metrics.json").read_bytes() if (run / "metrics.json").exists() else None
    code, _, err = run_cli(capsys, "eval", "--run", run)
    assert code == 2
    one_line_error(err, "metrics.json", os.strerror(errno.EROFS))
    assert not list(run.glob(".*.tmp*"))
    assert ((run / "metrics.json").read_bytes() if (run / "metrics.json").exists() else None) == before


def test_out_paths_that_are_files_or_under_files(made, tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("x")
    code, _, err = run_cli(capsys, "train", "--data", made[0], "--out", f, *QUICK)
    assert code == 2
    one_line_error(err, str(f), "is a file")
    code, _, err = run_cli(capsys, "synth", "--out", f / "sub", "--width", "32", "--height", "24", "--frames", "4")
    assert code == 2
    one_line_error(err, str(f))
    code, _, err = run_cli(capsys, "export", "--run", made[2], "--out", f / "sub" / "s.ply")
    assert code == 2
    one_line_error(err, str(f))


@pytest.mark.parametrize("override,key", [("train.steps=-5", "train.steps"), ("train.lr_means=-1", "train.lr_means"),
                                          ("model.sh_degree=7", "model.sh_degree"), ("stage2.eps=0", "stage2.eps"),
                                          ("articulate.track_rounds=0", "articulate.track_rounds"),
                                          ("train.nope=1", "train.nope"), ("stage2.variant=other", "stage2.variant")])
def test_invalid_values_name_the_option(made, tmp_path, capsys, override, key):
    code, _, err = run_cli(capsys, "train", "--data", made[0], "--out", tmp_path / "r", *QUICK, "--set", override)
    assert code == 2
    one_line_error(err, key)
    assert not (tmp_path / "r").exists()


def test_stage2_set_refuses_stage1_keys(made, run, capsys):
    code, _, err = run_cli(capsys, "stage2", "--run", run, "--set", "train.steps=3")
    assert code == 2
    one_line_error(err, "train.steps=3", "stage2.KEY")


def test_a_malformed_test_split_fails_training_naming_the_file(made, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(made[0], scene)
    (scene / "transforms_test.json").write_text('{"frames": [{"file_path": 3}]}')
    code, _, err = run_cli(capsys, "train", "--data", scene, "--out", tmp_path / "r", *QUICK)
    assert code == 2
    one_line_error(err, "transforms_test.json")


def test_a_corrupt_image_names_the_file(made, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(made[0], scene)
    img = sorted((scene / "images").glob("*.png"))[0]
    img.write_bytes(b"\x89PNG broken")
    code, _, err = run_cli(capsys, "train", "--data", scene, "--out", tmp_path / "r", *QUICK)
    assert code == 2
    one_line_error(err, img.name)


def test_render_cameras_a_folder_says_so(made, run, capsys):
    code, _, err = run_cli(capsys, "render", "--run", run, "--cameras", made[0], "--out", run.parent / "r")
    assert code == 2
    one_line_error(err, str(made[0]))
    assert "not found" not in err.lower() and "does not exist" not in err


def test_demo_refuses_a_folder_that_is_not_empty(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    code, _, err = run_cli(capsys, "demo", "--out", out, "--synth-only", "--quick")
    assert code == 2
    one_line_error(err, str(out), "--overwrite")
    code, _, err = run_cli(capsys, "demo", "--out", out, "--synth-only", "--quick", "--overwrite")
    assert code == 2 and (out / "mine.txt").read_text() == "keep me"  # not an earlier demo: never removed
    one_line_error(err, "does not hold an earlier demo")


def test_demo_overwrite_replaces_an_earlier_demo(tmp_path, capsys):
    out = tmp_path / "demo"
    assert run_cli(capsys, "demo", "--out", out, "--synth-only", "--quick")[0] == 0
    (out / "stale.txt").write_text("old")
    assert run_cli(capsys, "demo", "--out", out, "--synth-only", "--quick")[0] == 2
    assert run_cli(capsys, "demo", "--out", out, "--synth-only", "--quick", "--overwrite")[0] == 0
    assert not (out / "stale.txt").exists() and (out / "scene" / "gt" / "meta.json").exists()


def test_version_and_public_api(capsys):
    import fgjax

    code, out, _ = run_cli(capsys, "--version")
    assert code == 0 and out.strip() == f"fgjax {fgjax.__version__}"
    names = dir(fgjax)
    for name in ("rasterization", "estimate_flow", "load_config", "run_stage1", "run_stage2", "run_articulated",
                 "load_stage2", "render_controlled", "snap_vector", "flow", "geometry", "scene_gaussians",
                 "viewer_gaussians", "write_ply", "read_ply"):
        assert name in names
    assert callable(fgjax.run_articulated) and np.isfinite(float(fgjax.geometry.so3_exp(np.zeros(3))[0, 0]))


def _edit_transforms(scene: Path, edit) -> Path:
    p = scene / "transforms_train.json"
    d = json.loads(p.read_text())
    edit(d)
    p.write_text(json.dumps(d))
    return p


@pytest.mark.parametrize("case,needle", [
    ("missing transform_matrix", "transform_matrix"),
    ("NaN pose", "transform_matrix"),
    ("missing image", ".png"),
    ("wrong image size", ".png"),
])
def test_bad_data_sets_name_the_file_and_field(made, tmp_path, capsys, case, needle):
    scene = tmp_path / "scene"
    shutil.copytree(made[0], scene)
    if case == "missing transform_matrix":
        _edit_transforms(scene, lambda d: d["frames"][2].pop("transform_matrix"))
    elif case == "NaN pose":
        _edit_transforms(scene, lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")))
    elif case == "missing image":
        sorted((scene / "images").glob("*.png"))[3].unlink()
    else:
        import imageio.v3 as iio

        img = sorted((scene / "images").glob("*.png"))[3]
        iio.imwrite(img, np.zeros((10, 12, 3), np.uint8))
    code, _, err = run_cli(capsys, "train", "--data", scene, "--out", tmp_path / "r", *QUICK)
    assert code == 2, err
    one_line_error(err, needle)
    assert not (tmp_path / "r" / "checkpoint.npz").exists()
