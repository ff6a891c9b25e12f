"""``fgjax bench placement`` on a tiny synthetic scene: the flow evidence by frame spans and the placement's shares."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest
from conftest import synth

from fgjax import config as C
from fgjax.bench import placement

pytestmark = pytest.mark.optimized  # run-time-bound: compiled as the command line compiles (tests/conftest.py)


def test_bench_placement_reads_the_evidence_and_places_by_span(tmp_path, capsys):
    synth.generate(synth.SynthConfig(width=64, height=48, frames=8), tmp_path / "scene", overwrite=True,
                   progress=None)
    quick = pathlib.Path(__file__).resolve().parents[2] / "experiments" / "demo_quick.toml"
    sets = ["--set", "train.warmup_steps=30", "--set", "densify.start=30"]
    assert placement.main(["--data", str(tmp_path / "scene"), "--config", str(quick), *sets]) == 2  # not "bases"
    assert "deform.kind = 'bases'" in capsys.readouterr().err
    out = tmp_path / "placement.json"
    assert placement.main(["--data", str(tmp_path / "scene"), "--config", str(quick), "--spans", "1;1,2",
                           "--shares", "0;0.2", "--vary", "deform.place_window=3", *sets,
                           "--set", "deform.kind=bases", "--set", "deform.init=flow", "--json", str(out)]) == 0
    (row,), text = json.loads(out.read_text()), capsys.readouterr().out
    parts = len(json.loads((tmp_path / "scene" / "gt" / "meta.json").read_text())["objects"])
    assert [e["spans"] for e in row["pixels"]] == [[1], [1, 2]]
    assert [(e["spans"], e["camera_share"], e["vary"]) for e in row["placed"]] == [
        (s, c, ["deform.place_window=3"]) for s in ([1], [1, 2]) for c in (0.0, 0.2)]
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
        assert len(e["part_cluster"]) == len(e["in_cluster"]) == len(e["part_size"]) == parts
        assert all(-1 <= c < e["clusters"] for c in e["part_cluster"])
        assert all(0.0 <= x <= y for x, y in zip(e["in_cluster"], e["parts"]) if x == x)  # in a cluster: freed
    assert max(max(x for x in e["parts"] if x == x) for e in row["placed"]) > 0.5  # a part is placed
    assert "spans 1,2" in text and "share 0.2" in text and "placed" in text and "warm-up" in text
    assert "part clusters" in text and "deform.place_window=3 placed" in text
    assert placement.main(["--data", str(tmp_path), "--pixels-only"]) == 2  # no gt/ there
    assert "gt/train/object_id.npy is missing" in capsys.readouterr().err
    assert placement.main(["--data", str(tmp_path / "scene"), "--shares", "0;-1", "--pixels-only"]) == 2
    assert "--shares must look like" in capsys.readouterr().err
    assert placement.main(["--data", str(tmp_path / "scene"), "--vary", "deform.place_window", "--pixels-only"]) == 2
    assert "--vary must look like" in capsys.readouterr().err
    with pytest.raises(C.ConfigError, match="deform.place_window"):
        placement.main(["--data", str(tmp_path / "scene"), "--vary", "deform.place_window=0;-2", "--pixels-only"])
    with pytest.raises(SystemExit, match="--spans"):
        placement.main(["--data", str(tmp_path / "scene"), "--spans", "0;1", "--pixels-only"])


def test_vary_measures_every_combination():
    assert placement._variants([]) == [[]]
    assert placement._variants(["deform.place_window=0; 3", "deform.hold=150"]) == [
        ["deform.place_window=0", "deform.hold=150"], ["deform.place_window=3", "deform.hold=150"]]
    assert placement._variants(["a=1;2", "b=x;y"]) == [["a=1", "b=x"], ["a=1", "b=y"], ["a=2", "b=x"],
                                                      ["a=2", "b=y"]]
    for bad in ("deform.place_window", "=3", "deform.place_window=;"):
        with pytest.raises(ValueError, match="--vary must look like"):
            placement._variants([bad])


def test_part_clusters_names_each_parts_cluster_and_shows_two_parts_on_one():
    labels = np.array([-2, 0, 0, 1, 1, 1, -1, 0])  # -2 static, -1 noise, j >= 0 cluster j
    cl, share = placement.part_clusters(labels, [np.array([1, 2, 7]), np.array([3, 4, 5]), np.array([0, 6]),
                                                 np.array([], np.int64)])
    assert cl == [0, 1, -1, -1] and share[:3] == [1.0, 1.0, 0.0] and np.isnan(share[3])
    cl, share = placement.part_clusters(labels, [np.array([1, 3, 4, 0]), np.array([2, 5])])
    assert cl == [1, 0] and share == [0.5, 0.5]  # a tie goes to the lower (larger) cluster
    cl, _ = placement.part_clusters(labels, [np.array([3, 4]), np.array([5, 6])])
    assert cl == [1, 1]  # two parts on one cluster: one basis for both


def test_painted_parts_counts_the_gaussians_that_render_a_part(tmp_path):
    """A wall of opaque Gaussians 2 units in front of the camera, its left half on part 1's pixels, one Gaussian
    hidden behind the left half and one dead slot there: part 1 gets the wall's left Gaussians, part 2 (the
    bottom-right quarter) its own, and neither the hidden nor the dead Gaussian."""
    import types

    import jax.numpy as jnp

    from fgjax.gaussians import Gaussians

    w, h, f = 32, 24, 20.0
    xs, ys = np.meshgrid(np.linspace(-1.5, 1.5, 16), np.linspace(-1.1, 1.1, 12))
    wall = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.0)], -1)
    means = np.concatenate([wall, [[-0.8, 0.0, 4.0], [-0.8, 0.2, 2.0]]]).astype(np.float32)  # hidden, then dead
    n = len(means)
    g = Gaussians(means=jnp.asarray(means), log_scales=jnp.full((n, 3), np.log(0.15), jnp.float32),
                  quats=jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (n, 1)),
                  opacity_logits=jnp.full((n,), 6.0), sh=jnp.zeros((n, 1, 3)))
    alive = np.ones(n, bool)
    alive[-1] = False
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], np.float32)
    scene = types.SimpleNamespace(times=np.zeros(2), width=w, height=h, viewmats=np.tile(np.eye(4, dtype=np.float32),
                                  (2, 1, 1)), Ks=np.tile(K, (2, 1, 1)))
    oid = np.zeros((2, h, w), np.int16)
    oid[:, :, : w // 2] = 1
    oid[:, h // 2:, 3 * w // 4:] = 2
    gt = tmp_path / "gt"
    (gt / "train").mkdir(parents=True)
    np.save(gt / "train" / "object_id.npy", oid)
    (gt / "meta.json").write_text(json.dumps({"objects": [{"label": 1}, {"label": 2}]}))
    one, two = placement.painted_parts({"gaussians": g}, alive, scene, gt, capacity=4096)
    u = f * means[:, 0] / means[:, 2] + w / 2  # the wall's pixel columns and rows
    v = f * means[:, 1] / means[:, 2] + h / 2
    wall_left = np.flatnonzero((np.arange(n) < len(wall)) & (u < w / 2 - 2))
    wall_quarter = np.flatnonzero((np.arange(n) < len(wall)) & (u > 3 * w / 4 + 2) & (v > h / 2 + 2) & (v < h))
    assert set(wall_left) <= set(one) and set(wall_quarter) <= set(two)
    assert not set(one) & set(two)
    assert n - 2 not in one and n - 1 not in one  # hidden behind the wall; dead
    assert all(u[i] < w / 2 + 2 for i in one)  # nothing from the static right half
    scene.height = h + 1
    with pytest.raises(ValueError, match="object_id.npy has shape"):
        placement.painted_parts({"gaussians": g}, alive, scene, gt, capacity=4096)
