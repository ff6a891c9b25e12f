"""``fgjax bench placement`` on a tiny synthetic scene: the flow evidence by frame spans and the placement's shares."""

from __future__ import annotations

import json
import pathlib

import numpy as np
from conftest import synth

from fgjax.bench import placement


def test_bench_placement_reads_the_evidence_and_places_by_span(tmp_path, capsys):
    synth.generate(synth.SynthConfig(width=64, height=48, frames=8), tmp_path / "scene", overwrite=True,
                   progress=None)
    quick = pathlib.Path(__file__).resolve().parents[2] / "experiments" / "demo_quick.toml"
    sets = ["--set", "train.warmup_steps=30", "--set", "densify.start=30"]
    assert placement.main(["--data", str(tmp_path / "scene"), "--config", str(quick), *sets]) == 2  # not "bases"
    assert "deform.kind = 'bases'" in capsys.readouterr().err
    out = tmp_path / "placement.json"
    assert placement.main(["--data", str(tmp_path / "scene"), "--config", str(quick), "--spans", "1;1,2", "--shares", "0;0.2", *sets,
                           "--set", "deform.kind=bases", "--set", "deform.init=flow", "--json", str(out)]) == 0
    (row,), text = json.loads(out.read_text()), capsys.readouterr().out
    parts = len(json.loads((tmp_path / "scene" / "gt" / "meta.json").read_text())["objects"])
    assert [e["spans"] for e in row["pixels"]] == [[1], [1, 2]]
    assert [(e["spans"], e["camera_share"]) for e in row["placed"]] == [([1], 0.0), ([1], 0.2), ([1, 2], 0.0),
                                                                        ([1, 2], 0.2)]
    for e in row["pixels"]:
        assert len(e["parts"]) == parts and 0.0 <= e["static"] <= 1.0
    assert row["pixels"][0]["static"] < 0.3  # consecutive frames (64x48, 8 frames: the camera moves fast)
    one, both = (np.asarray(e["parts"]) for e in row["pixels"])
    # the parts of the default scene move several pixels a frame: the flow marks them, well above the static pixels
    assert np.nanmax(one) > 0.5 and np.nanmax(one) > 3 * row["pixels"][0]["static"]
    assert np.all(np.isfinite(one) == np.isfinite(both))
    for e in row["placed"]:
        assert len(e["parts"]) == parts and e["clusters"] >= 1 and e["others"] >= 0
        assert all(0.0 <= x <= 1.0 for x in e["parts"] if x == x)
        assert len(e["part_cluster"]) == len(e["in_cluster"]) == parts
        assert all(-1 <= c < e["clusters"] for c in e["part_cluster"])
        assert all(0.0 <= x <= y for x, y in zip(e["in_cluster"], e["parts"]) if x == x)  # in a cluster: freed
    assert max(max(x for x in e["parts"] if x == x) for e in row["placed"]) > 0.5  # a part is placed
    assert "spans 1,2" in text and "share 0.2" in text and "placed" in text and "warm-up" in text
    assert "part clusters" in text
    assert placement.main(["--data", str(tmp_path), "--pixels-only"]) == 2  # no gt/ there
    assert "gt/train/object_id.npy is missing" in capsys.readouterr().err
    assert placement.main(["--data", str(tmp_path / "scene"), "--shares", "0;-1", "--pixels-only"]) == 2
    assert "--shares must look like" in capsys.readouterr().err
    with __import__("pytest").raises(SystemExit, match="--spans"):
        placement.main(["--data", str(tmp_path / "scene"), "--spans", "0;1", "--pixels-only"])


def test_part_clusters_names_each_parts_cluster_and_shows_two_parts_on_one():
    labels = np.array([-2, 0, 0, 1, 1, 1, -1, 0])  # -2 static, -1 noise, j >= 0 cluster j
    cl, share = placement.part_clusters(labels, [np.array([1, 2, 7]), np.array([3, 4, 5]), np.array([0, 6]),
                                                 np.array([], np.int64)])
    assert cl == [0, 1, -1, -1] and share[:3] == [1.0, 1.0, 0.0] and np.isnan(share[3])
    cl, share = placement.part_clusters(labels, [np.array([1, 3, 4, 0]), np.array([2, 5])])
    assert cl == [1, 0] and share == [0.5, 0.5]  # a tie goes to the lower (larger) cluster
    cl, _ = placement.part_clusters(labels, [np.array([3, 4]), np.array([5, 6])])
    assert cl == [1, 1]  # two parts on one cluster: one basis for both
