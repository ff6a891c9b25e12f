"""``fgjax synth --family`` and ``fgjax bench family`` end to end on a tiny family scene, and the evaluation pieces
the benchmark reports (parts found by IoU, PSNR over the moving parts, discovery's trace)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fgjax.cli import main as cli
from fgjax.method.evaluate import gt_objects, gt_transform, masked_psnr, part_ious

QUICK = Path(__file__).resolve().parents[2] / "experiments" / "quick.toml"


def test_part_ious_counts_a_part_found_at_half_overlap():
    gt = np.array([0, 0, 1, 1, 1, 1, 2, 2, 0, 0])
    pred = np.array([0, 1, 1, 1, 1, 0, 0, 0, 2, 0])  # part 1: 3 of 4 pixels + 1 extra -> 3/5; part 2 missed
    r = part_ious(gt, pred, 2)
    assert r["part_iou"]["1"] == pytest.approx(0.6) and r["part_iou"]["2"] == 0.0
    assert r["parts_found"] == 1 and r["parts_true"] == 2 and r["part_best_object"] == {"1": 1, "2": 0}
    assert part_ious(gt, np.zeros_like(gt), 2)["parts_found"] == 0


def test_masked_psnr_counts_only_the_mask():
    ref = np.zeros((4, 4, 3))
    img = ref.copy()
    img[0, 0] = 0.1  # error on one pixel
    mask = np.zeros((4, 4), bool)
    mask[0, :2] = True
    assert masked_psnr(img, ref, mask) == pytest.approx(10 * np.log10(1 / (0.01 / 2)))
    assert masked_psnr(img, ref, ~mask) == pytest.approx(10 * np.log10(1e12))
    assert np.isnan(masked_psnr(img, ref, np.zeros((4, 4), bool)))


def test_gt_transform_composes_an_attached_part(tmp_path):
    """The evaluation's gt motion of an attached part is its parent's motion times its own."""
    from fgjax.synth import family as fam

    seed = next(s for s in range(40) if any(o.parent for o in fam.make_family_scene(fam.family_config(s)).objects))
    sc = fam.make_family_scene(fam.family_config(seed))
    meta = {"objects": json.loads(json.dumps([o.to_dict() for o in sc.objects]))}
    objs = gt_objects(meta)
    child = next(o for o in sc.objects if o.parent)
    states = np.linspace(0.2, 0.9, sc.num_objects)
    from fgjax.synth import compose_transforms, object_transform

    want = compose_transforms(sc.objects, states)[child.parent] @ object_transform(child, states[child.label - 1])
    np.testing.assert_allclose(gt_transform(objs, child.label, states), want, atol=1e-12)


def test_synth_family_cli(tmp_path, capsys):
    assert cli(["synth", "--family", "4", "--width", "40", "--height", "30", "--frames", "4", "--quiet",
                "--out", str(tmp_path / "s")]) == 0
    meta = json.loads((tmp_path / "s" / "gt" / "meta.json").read_text())
    assert meta["family"] == 4 and meta["config"]["width"] == 40 and len(meta["objects"]) >= 1
    assert cli(["synth", "--family", "4", "--width", "40", "--out", str(tmp_path / "t")]) == 2
    assert "--height" in capsys.readouterr().err


def _check_trace_against_oracles(seed_dir: Path, monkeypatch) -> None:
    """`discovery_trace`'s shares with step 5's output replaced by answers whose shares are known from the ground
    truth alone: the flags set to exactly the true moving pixels (all of them flagged, no static one), or to none;
    D set to every live Gaussian (its drawing covers the frame, so the share of it on the parts is the parts' share
    of the first frame's pixels, and every part pixel is drawn), or to none."""
    from fgjax.config import load_config
    from fgjax.method import evaluate

    real, found = evaluate.discover_run, []  # step 5 runs once; both oracles replace its answer
    run_dir, scene_dir = seed_dir / "run", seed_dir / "scene"
    gt = scene_dir / "gt" / "train"
    ids, obj_flow, fvalid = (np.load(gt / f) for f in ("object_id.npy", "object_flow.npy", "flow_valid.npy"))
    moving_px = 0.5  # the trace's flow_threshold, passed to it below

    def oracle(everything: bool):
        def discover_run(run, scene, cfg, cache, log=print):
            if not found:
                found.append(real(run, scene, cfg, cache, log=log))
            disc, centres, times, (order, flows, cam) = found[0]
            pairs = zip(order[:-1], order[1:], strict=True)
            truth = np.stack([fvalid[a] & (np.linalg.norm(obj_flow[a], axis=-1) > moving_px) for a, _ in pairs])
            alive = np.asarray(run.state.densify.alive, bool)
            disc = disc._replace(masks=truth if everything else np.zeros_like(truth),
                                 dynamic=alive if everything else np.zeros_like(alive))
            return disc, centres, times, (order, flows, cam)
        return discover_run

    cfg = load_config(QUICK, ["stage2.photo_steps=0", "stage2.distill_steps=20"]).stage2
    monkeypatch.setattr(evaluate, "discover_run", oracle(True))
    tr = evaluate.discovery_trace(run_dir, scene_dir, cfg, flow_threshold=moving_px)
    assert tr["moving_pixels_flagged"] == 1.0 and tr["static_pixels_flagged"] == 0.0
    assert all(v == 1.0 for v in tr["part_pixels_flagged"].values() if np.isfinite(v))
    first = ids[0]  # fgjax synth writes frames in time order
    assert tr["dynamic_pixels_on_parts"] == pytest.approx(np.mean(first > 0), abs=0.02)
    assert all(v >= 0.9 for v in tr["part_pixels_dynamic"].values() if np.isfinite(v)), tr["part_pixels_dynamic"]
    assert all(r["in_dynamic_set"] == r["on_part"] for r in tr["part_gaussians"].values())
    assert tr["dynamic_set"] == tr["dynamic_set_on_static"] + sum(r["on_part"] for r in tr["part_gaussians"].values())
    monkeypatch.setattr(evaluate, "discover_run", oracle(False))
    tr = evaluate.discovery_trace(run_dir, scene_dir, cfg, flow_threshold=moving_px)
    assert tr["moving_pixels_flagged"] == 0.0 and tr["static_pixels_flagged"] == 0.0
    assert tr["dynamic_pixels_on_parts"] == 0.0 and tr["dynamic_set"] == 0
    assert all(v == 0.0 for v in tr["part_pixels_dynamic"].values() if np.isfinite(v))


def test_bench_family_end_to_end(tmp_path, capsys, monkeypatch):
    """Two tiny seeds through flow, stage 1, stage 2 and the evaluation: family.json has every key of the issue's
    format, per seed and as the mean, a sheet per seed, and the discovery trace; a second run reuses the scenes."""
    out = tmp_path / "bench"
    args = ["bench", "family", "--seeds", "1,2", "--size", "48x36", "--frames", "6", "--config", str(QUICK),
            "--out", str(out), "--trace", "--set", "stage2.photo_steps=0", "--set", "stage2.distill_steps=20"]
    assert cli(args) == 0
    said = capsys.readouterr()
    text = said.out
    assert "mean" in text and "parts found" in text
    for seed in (1, 2):  # each stage's progress on stderr: its first line at once, then its time
        assert f"bench family: seed {seed}: stage 1: train: 6 frames 48x36" in said.err, said.err
        assert f"seed {seed}: stage 1 done" in said.err and f"seed {seed}: stage 2 done" in said.err
        assert f"bench family: seed {seed}: stage 2: " in said.err
    doc = json.loads((out / "family.json").read_text())
    keys = {"seed", "ari", "ari_controlled", "parts_true", "parts_found", "state_psnr", "state_psnr_moving",
            "stage1_psnr", "wall_s"}
    assert [r["seed"] for r in doc["seeds"]] == [1, 2]
    for r in doc["seeds"]:
        assert keys <= set(r) and r["parts_true"] >= 1 and 0 <= r["parts_found"] <= r["parts_true"]
        assert np.isfinite(r["stage1_psnr"]) and r["wall_s"] > 0 and r["size"] == [48, 36]
        tr = r["discovery"]
        assert "moving_pixels_flagged" in tr and tr["part_gaussians"]
        assert 0.0 <= tr["dynamic_pixels_on_parts"] <= 1.0
        assert set(tr["part_pixels_dynamic"]) == set(tr["part_gaussians"])
        assert (out / f"seed_{r['seed']:03d}" / "sheet.png").is_file()
    assert keys - {"seed"} <= set(doc["mean"])
    _check_trace_against_oracles(out / "seed_001", monkeypatch)
    stamp = (out / "seed_001" / "scene" / "gt" / "meta.json").stat().st_mtime_ns
    assert cli(args[:3] + ["1"] + args[4:]) == 0  # the scene is reused, not regenerated
    assert (out / "seed_001" / "scene" / "gt" / "meta.json").stat().st_mtime_ns == stamp
    # another stage-2 configuration on the same stage 1
    paper = tmp_path / "paper"
    assert cli(["bench", "family", "--seeds", "1", "--stage1-from", str(out), "--out", str(paper),
                "--config", str(QUICK), "--set", "stage2.variant=paper", "--set", "stage2.photo_steps=0",
                "--set", "stage2.distill_steps=20"]) == 0
    row = json.loads((paper / "family.json").read_text())["seeds"][0]
    assert row["seed"] == 1 and (paper / "seed_001" / "run" / "stage2.npz").is_file()
    assert not (paper / "seed_001" / "scene").exists()  # the earlier benchmark's scene was used in place
    assert cli(["bench", "family", "--seeds", "2", "--stage1-from", str(paper), "--out", str(tmp_path / "x")]) == 2
    assert "--stage1-from" in capsys.readouterr().err


def test_progress_log_says_the_first_line_warnings_at_once_and_then_one_line_a_minute():
    from fgjax.bench.family import progress_log

    said, now = [], [0.0]
    log = progress_log(said.append, "seed 3: ", 60.0, clock=lambda: now[0])
    for t, msg in [(0, "train: 8 frames"), (10, "step 100"), (59, "step 200"), (61, "step 300"), (62, "Warning: x"),
                   (100, "step 400"), (122, "step 500"), (130, "error: y")]:
        now[0] = float(t)
        log(msg)
    assert said == ["seed 3: train: 8 frames", "seed 3: step 300", "seed 3: Warning: x", "seed 3: step 500",
                    "seed 3: error: y"]


def test_bench_family_rejects_bad_arguments(tmp_path, capsys):
    assert cli(["bench", "family", "--seeds", "3-1", "--out", str(tmp_path)]) == 2
    assert "seeds" in capsys.readouterr().err
    assert cli(["bench", "family", "--seeds", "1", "--size", "big", "--out", str(tmp_path)]) == 2
    assert "--size" in capsys.readouterr().err
