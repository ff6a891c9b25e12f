"""`fgjax bench field`: the deformation field alone, fitted to an exact local motion (docs/benchmarks.md, "Can the
field learn a local motion?"). Small fits (3,000 points, 300 steps) measured once: L1 learns a motion that every
point asks for (0.095 of it) and none of one that 3.7 % of the points ask for (0.000); L2 with a faster hash grid
learns 0.19 of the latter."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fgjax.bench import field
from fgjax.config import load_config

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


def test_cli_prints_a_row_per_loss_and_writes_json(tmp_path, capsys):
    out = tmp_path / "f.json"
    assert field.main(["--steps", "5", "--losses", "l1,l2", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "static max" in text and len(text.strip().splitlines()) == 3
    doc = json.loads(out.read_text())
    assert [r["loss"] for r in doc["rows"]] == ["l1", "l2"] and doc["command"].startswith("fgjax bench field")
