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


def test_demo_set_overrides(tmp_path, capsys):
    """`fgjax demo --set`: stage2.* on top of the demo's own stage-2 settings, SECTION.KEY on top of stage 1's
    TOML; a bad override exits 2 naming the key, before anything is written."""
    from fgjax.pipeline import demo

    s1, s2 = demo.pipeline_configs(tmp_path / "fc", quick=False,
                                   overrides=["stage2.track_rest=false", "train.steps=123", "stage2.eps=0.07"])
    assert not s2.track_rest and s2.eps == 0.07 and s1.train.steps == 123
    assert s2.track_photo == 40 and s2.track_rounds == 3 and s2.flow_cache == str(tmp_path / "fc")  # the demo's own
    q1, q2 = demo.pipeline_configs(tmp_path / "fc", quick=True, overrides=[])
    assert q2.track_photo == 0 and q1.train.video_frames == 0
    for bad, msg in (("stage2.track_rest=maybe", "stage2.track_rest=maybe: expected true or false"),
                     ("stage2.nope=1", "stage2.nope: unknown stage-2 option"),
                     ("stage2.hinge_radius=-1", "hinge_radius must be"),
                     ("train.stepz=3", "train.stepz")):
        out = tmp_path / "bad"
        assert cli.main(["demo", "--out", str(out), "--quick", "--set", bad]) == 2
        assert msg in capsys.readouterr().err
        assert not out.exists()
