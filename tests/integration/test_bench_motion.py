"""``fgjax bench motion`` on the tiny synthetic run: a known deformation gives known numbers."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from fgjax.bench import motion


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _pipeline_run import shared_base, tiny_run

    return tiny_run(shared_base(tmp_path_factory) / "pipeline", stage2=False)


def test_motion_report_measures_a_known_translation(tiny, monkeypatch, tmp_path, capsys):
    run_dir, data = tiny
    shift = np.array([0.036, -0.048, 0.0])  # |shift| = 0.06
    real = motion.deformed_gaussians

    def shifted(params, alive, t, spec):
        m, *rest = real(params, alive, t, None)  # the canonical Gaussians ...
        return (m + shift * (t > 0.5), *rest)  # ... translated in the second half of the video only

    monkeypatch.setattr(motion, "deformed_gaussians", shifted)
    r = motion.motion_report(run_dir, data, num_times=5)
    live = r["live_gaussians"]
    assert live > 0
    assert r["moving_gaussians"] == {"0.01": live, "0.05": live, "0.1": 0}
    meta = json.loads((data / "gt" / "meta.json").read_text())
    assert [o["name"] for o in r["objects"]] == [o["name"] for o in meta["objects"]]
    for o in r["objects"]:
        assert o["true_max_displacement"] > 0.06  # the synthetic parts do move
        if o["gaussians"]:
            assert o["learned_max_displacement"] == pytest.approx(0.06, rel=1e-5)
    assert np.isfinite(r["psnr_static_pixels"])
    # the CLI prints the table and writes the same report
    monkeypatch.setattr(motion, "deformed_gaussians", real)
    out = tmp_path / "m.json"
    assert motion.main(["--run", str(run_dir), "--data", str(data), "--json", str(out)]) == 0
    assert "learned" in capsys.readouterr().out and json.loads(out.read_text())["objects"]


def test_motion_report_needs_the_ground_truth(tiny, tmp_path, capsys):
    run_dir, _ = tiny
    assert motion.main(["--run", str(run_dir), "--data", str(tmp_path)]) == 2
    assert "needs a dataset written by `fgjax synth`" in capsys.readouterr().err
