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
    # re-running refuses the folder, and with --overwrite replaces the demo's own
    capsys.readouterr()
    assert cli.main(args) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert cli.main([*args, "--overwrite"]) == 0
    # but never a folder that is not a demo
    (tmp_path / "other" / "scene").mkdir(parents=True)
    (tmp_path / "other" / "scene" / "keep.txt").write_text("x")
    assert cli.main(["demo", "--out", str(tmp_path / "other"), "--quick", "--synth-only", "--overwrite"]) == 2
    assert (tmp_path / "other" / "scene" / "keep.txt").read_text() == "x"


def test_demo_set_overrides(tmp_path, capsys):
    """`fgjax demo --set`: stage2.*, articulate.* and SECTION.KEY on top of the demo's named configuration
    (experiments/articulated.toml, or demo_quick.toml with --quick); a bad override exits 2 naming the key, before
    anything is written."""
    from fgjax.apps import demo

    cfg = demo.pipeline_configs(tmp_path / "fc", quick=False,
                                overrides=["articulate.track_rest=false", "train.steps=123", "stage2.eps=0.07"])
    assert not cfg.articulate.track_rest and cfg.stage2.eps == 0.07 and cfg.train.steps == 123
    # the demo's own settings (experiments/articulated.toml) and flow cache
    assert cfg.stage2.variant == "articulated" and cfg.stage2.control_rigid
    assert cfg.articulate.track_photo == 40 and cfg.articulate.track_rounds == 3
    assert cfg.stage2.flow_cache == str(tmp_path / "fc")
    quick = demo.pipeline_configs(tmp_path / "fc", quick=True, overrides=[])
    assert quick.articulate.track_photo == 20 and quick.articulate.hinge_trial == 0 and quick.train.video_frames == 0
    for bad, msg in (("articulate.track_rest=maybe", "articulate.track_rest' expects a bool"),
                     ("stage2.nope=1", "unknown config key 'stage2.nope'"),
                     ("stage2.track_rest=false", "unknown config key 'stage2.track_rest'"),  # moved to articulate
                     ("articulate.hinge_radius=-1", "articulate.hinge_radius must be"),
                     ("train.stepz=3", "train.stepz")):
        out = tmp_path / "bad"
        assert cli.main(["demo", "--out", str(out), "--quick", "--set", bad]) == 2
        assert msg in capsys.readouterr().err
        assert not out.exists()
