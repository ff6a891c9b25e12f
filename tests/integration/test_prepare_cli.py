"""`fgjax prepare` through the command line: a still clip written end to end, and every bad input gives exit status 2
and one line naming the file or option, with nothing left in --out."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _captures import TexturedRoom, look_at_c2w, pinhole, write_record3d
from conftest import run_cli

from fgjax.data import prepare as prepare_lib
from fgjax.io import write_video


def one_line_error(err: str, *needles: str) -> None:
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if "error" in ln]
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], (n, lines[0])


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    """10 frames of a still camera (96x72), as H.264."""
    d = tmp_path_factory.mktemp("clips")
    K = pinhole(96, 72, 80.0)
    cam = look_at_c2w((0.3, -1.6, 1.0), (0.0, 0.0, 0.4))
    room = TexturedRoom(seed=2)
    return write_video([room.render(cam, K, 96, 72, cube_offset=(0.03 * i, 0, 0), supersample=1)
                        for i in range(10)], d / "still.mp4", fps=10)


def _left_nothing(out: Path) -> None:
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]


def test_still_clip_end_to_end(clip, tmp_path, capsys):
    out = tmp_path / "scene"
    code, printed, err = run_cli(capsys, "prepare", "--video", clip, "--out", out, "--poses", "still", "--fov", "65",
                                 "--test-every", "4")
    assert code == 0, err
    assert f"scene: {out}" in printed and "poses: still" in printed
    for phase in ("prepare: decoded", "--poses still: a still camera (identity poses)", "prepare: wrote"):
        assert phase in err
    info = json.loads((out / "prepare.json").read_text())
    assert info["poses"] == "still" and info["split"] == {"train": 8, "test": 2, "test_every": 4}
    train = json.loads((out / "transforms_train.json").read_text())
    assert [f["time"] for f in train["frames"]][:3] == [0.0, 1 / 9, 2 / 9]
    assert train["normalization"] == info["normalization"]
    # a second run refuses the folder, --overwrite replaces a prepared scene but never another folder
    code, _, err = run_cli(capsys, "prepare", "--video", clip, "--out", out, "--poses", "still")
    assert code == 2 and "--overwrite" in err
    assert run_cli(capsys, "prepare", "--video", clip, "--out", out, "--poses", "still", "--overwrite")[0] == 0
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    code, _, err = run_cli(capsys, "prepare", "--video", clip, "--out", other, "--poses", "still", "--overwrite")
    assert code == 2 and (other / "keep.txt").read_text() == "x"
    one_line_error(err, str(other), "prepare.json")


@pytest.mark.parametrize("case", ["missing", "empty", "not a video"])
def test_unreadable_videos_name_the_file(case, tmp_path, capsys):
    path = tmp_path / "clip.mp4"
    if case == "empty":
        path.write_bytes(b"")
    elif case == "not a video":
        path.write_text("this is not a video\n" * 50)
    out = tmp_path / "scene"
    code, _, err = run_cli(capsys, "prepare", "--video", path, "--out", out, "--poses", "still")
    assert code == 2
    one_line_error(err, str(path))
    _left_nothing(out)


def test_too_few_frames_and_bad_options(clip, tmp_path, capsys):
    out = tmp_path / "scene"
    code, _, err = run_cli(capsys, "prepare", "--video", clip, "--out", out, "--poses", "still", "--frames", "2:5")
    assert code == 2
    one_line_error(err, str(clip), "3 frame(s)", "at least 4")
    for opts, needle in ((["--frames", "5:2"], "--frames"), (["--frames", "x"], "--frames"),
                         (["--stride", "0"], "--stride"), (["--max-side", "8"], "--max-side"),
                         (["--fov", "200"], "--fov"), (["--test-every", "1"], "--test-every")):
        code, _, err = run_cli(capsys, "prepare", "--video", clip, "--out", out, "--poses", "still", *opts)
        assert code == 2, opts
        one_line_error(err, needle)
    _left_nothing(out)


def test_missing_pycolmap_is_one_line(clip, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(prepare_lib, "have_pycolmap", lambda: False)
    code, _, err = run_cli(capsys, "prepare", "--video", clip, "--out", tmp_path / "scene")
    assert code == 2
    one_line_error(err, "pycolmap", "fgjax[video]")


def test_a_failure_while_writing_leaves_nothing(clip, tmp_path, capsys, monkeypatch):
    real = prepare_lib.write_transforms

    def fail_on_test(out, split, *a, **k):
        if split == "test":
            raise OSError(28, "No space left on device", str(out))
        return real(out, split, *a, **k)

    monkeypatch.setattr(prepare_lib, "write_transforms", fail_on_test)
    out = tmp_path / "deep" / "scene"
    code, _, err = run_cli(capsys, "prepare", "--video", clip, "--out", out, "--poses", "still")
    assert code == 2
    one_line_error(err, "No space left on device")
    assert not (tmp_path / "deep").exists()  # the parent folders it made are gone too


def test_record3d_bad_exports_name_the_file(tmp_path, capsys):
    out = tmp_path / "scene"
    code, _, err = run_cli(capsys, "prepare", "--record3d", tmp_path / "nowhere", "--out", out)
    assert code == 2
    one_line_error(err, "nowhere")
    imgs = [np.full((32, 32, 3), 100, np.uint8)] * 5
    folder = write_record3d(tmp_path / "r3d", np.tile(np.eye(4), (5, 1, 1)), pinhole(32, 32, 30.0), imgs,
                            drop="poses")
    code, _, err = run_cli(capsys, "prepare", "--record3d", folder, "--out", out)
    assert code == 2
    one_line_error(err, str(folder / "metadata"), "`poses`")
    meta = json.loads((folder / "metadata").read_text())
    meta["poses"] = [[0, 0, 0, 1, 0, 0, 0]] * 4 + [[0, 0, 0, 0, 0, 0, 0]]
    (folder / "metadata").write_text(json.dumps(meta))
    code, _, err = run_cli(capsys, "prepare", "--record3d", folder, "--out", out)
    assert code == 2
    one_line_error(err, "`poses`[4]")
    _left_nothing(out)
