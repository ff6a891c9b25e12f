"""`fgjax bench field`: the deformation field alone, fitted to an exact local motion (docs/benchmarks.md, "Can the
field learn a local motion?"). Small fits (3,000 points, 300 steps) measured once: L1 learns a motion that every
point asks for (0.095 of it) and none of one that 3.7 % of the points ask for (0.000); L2 with a faster hash grid
learns 0.19 of the latter. Velocity targets (the form of L_uGS, the part moving over a fifth of the time), 3,000 points:
at stage 1's rates 300 steps of the displacement form learn 0.12 of the part's motion, of the velocity form 0.000;
with the field's rates x10, the velocity form learns 0.71 in 2,000 steps under L2 (static points at most 0.007) and
0.000 in 1,000 steps under L1."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fgjax.bench import field
from fgjax.config import load_config

pytestmark = pytest.mark.optimized  # run-time-bound: compiled as the command line compiles (tests/conftest.py)

CONFIG = Path(__file__).resolve().parents[2] / "experiments" / "family.toml"


@pytest.fixture(scope="module")
def cfg():
    return load_config(CONFIG)


def test_l1_follows_the_majority_of_the_points_and_l2_moves_a_small_part(cfg):
    kw = dict(steps=300, points=3000)
    everyone = field.fit_local_motion(cfg, loss="l1", part=2.0, **kw)
    assert everyone["part_points"] == 3000 and everyone["ratio"] > 0.05, everyone
    few = field.fit_local_motion(cfg, loss="l1", hash_factor=100, **kw)
    assert 0 < few["part_points"] < 0.05 * 3000 and abs(few["ratio"]) < 0.02, few
    squared = field.fit_local_motion(cfg, loss="l2", hash_factor=100, **kw)
    assert squared["part_points"] == few["part_points"] and squared["ratio"] > 0.1, squared
    assert squared["learned"] > squared["static_max"]  # it moves the part more than any static point
    with pytest.raises(ValueError, match="loss"):
        field.fit_local_motion(cfg, loss="huber", steps=1)


def test_velocity_targets_teach_the_field_only_squared_and_at_higher_rates(cfg):
    kw = dict(points=3000, ramp=0.2)
    disp = field.fit_local_motion(cfg, loss="l2", steps=300, **kw)
    vel = field.fit_local_motion(cfg, loss="l2", steps=300, target="velocity", **kw)
    assert disp["ratio"] > 0.05 and abs(vel["ratio"]) < 0.01, (disp, vel)
    fast = load_config(CONFIG, ["train.lr_deform=1.6e-3", "train.lr_deform_final=1.6e-4"])
    l1 = field.fit_local_motion(fast, loss="l1", steps=1000, target="velocity", **kw)
    assert abs(l1["ratio"]) < 0.01, l1
    l2 = field.fit_local_motion(fast, loss="l2", steps=2000, target="velocity", **kw)
    assert l2["ratio"] > 0.5 and l2["static_max"] < 0.1 * l2["learned"], l2
    with pytest.raises(ValueError, match="target"):
        field.fit_local_motion(cfg, target="acceleration", steps=1)
    with pytest.raises(ValueError, match="ramp"):
        field.fit_local_motion(cfg, ramp=-0.1, steps=1)


def test_cli_prints_a_row_per_loss_and_writes_json(tmp_path, capsys):
    out = tmp_path / "f.json"
    assert field.main(["--steps", "5", "--losses", "l1,l2", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "static max" in text and len(text.strip().splitlines()) == 3
    doc = json.loads(out.read_text())
    assert [r["loss"] for r in doc["rows"]] == ["l1", "l2"] and doc["command"].startswith("fgjax bench field")
    assert field.main(["--steps", "5", "--losses", "l2", "--target", "velocity", "--ramp", "0.2",
                       "--json", str(out)]) == 0
    assert json.loads(out.read_text())["rows"][0]["target"] == "velocity"
