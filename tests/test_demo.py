"""`fgjax demo` on a tiny configuration: scene, contact sheet and video are written and readable."""

from __future__ import annotations

import imageio.v3 as iio

from fgjax import cli


def test_demo_tiny(tmp_path, capsys):
    out = tmp_path / "demo"
    args = ["demo", "--out", str(out), "--quick", "--synth-only", "--width", "64", "--height", "48", "--frames", "10"]
    assert cli.main(args) == 0
    printed = capsys.readouterr().out
    sheet = out / "contact_sheet.png"
    assert str(sheet) in printed
    img = iio.imread(sheet)
    assert img.ndim == 3 and img.shape[2] == 3 and img.shape[1] > 4 * 64
    video = out / "demo.mp4" if (out / "demo.mp4").exists() else out / "demo.gif"
    assert video.stat().st_size > 0 and str(video) in printed
    assert (out / "scene" / "transforms_train.json").is_file()
    # re-running replaces the demo's own scene
    assert cli.main(args) == 0
    # but never a folder that is not a demo scene
    (tmp_path / "other" / "scene").mkdir(parents=True)
    (tmp_path / "other" / "scene" / "keep.txt").write_text("x")
    assert cli.main(["demo", "--out", str(tmp_path / "other"), "--quick", "--synth-only"]) == 2
    assert (tmp_path / "other" / "scene" / "keep.txt").read_text() == "x"
