"""`fgjax control` and `fgjax eval` on the tiny shared run: outputs and clear errors."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from fgjax import cli
from fgjax.apps.control import parse_vector

ARI_FLOOR = -0.1  # the tiny run measures -0.023 (ARI) and -0.016 (controlled): see test_eval_writes_metrics


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _pipeline_run import shared_base, tiny_run

    return tiny_run(shared_base(tmp_path_factory) / "pipeline")


def test_parse_vector():
    np.testing.assert_array_equal(parse_vector("1, -2,3.5"), [1.0, -2.0, 3.5])
    for bad in ("1,2", "a,b,c", "1,2,3,4", "nan,0,0"):
        with pytest.raises(ValueError, match="--vector"):
            parse_vector(bad)


def test_control_renders_and_sweeps(tiny, tmp_path, capsys):
    from fgjax.method import result as stage2

    run_dir, _ = tiny
    n = stage2.load_stage2(run_dir).s2.num_objects
    assert n > 0, "no clusters in the tiny run"
    out = tmp_path / "ctl"
    assert cli.main(["control", "--run", str(run_dir), "--object", "1", "--vector", "0.01,0,0", "--out", str(out)]) == 0
    pngs = list(out.glob("object1_*.png"))
    assert len(pngs) == 1
    assert cli.main(["control", "--run", str(run_dir), "--object", "1", "--sweep", "--frames", "2",
                     "--out", str(out)]) == 0
    vids = list(out.glob("object1_sweep.*"))
    assert vids and vids[0].stat().st_size > 0
    capsys.readouterr()
    # errors: object out of range, malformed vector, missing run, no vector, both vector and sweep
    v = ["--vector", "0.01,0,0"]
    assert cli.main(["control", "--run", str(run_dir), "--object", str(n + 1), *v, "--out", str(out)]) == 2
    assert "out of range" in capsys.readouterr().err
    assert cli.main(["control", "--run", str(run_dir), "--object", "1", "--vector", "1,2", "--out", str(out)]) == 2
    assert "--vector" in capsys.readouterr().err
    assert cli.main(["control", "--run", str(tmp_path / "none"), "--object", "1", *v, "--out", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert cli.main(["control", "--run", str(run_dir), "--object", "1", "--out", str(out)]) == 2
    assert "--vector x,y,z" in capsys.readouterr().err
    assert cli.main(["control", "--run", str(run_dir), "--object", "1", *v, "--sweep", "--out", str(out)]) == 2
    assert "not both" in capsys.readouterr().err
    # a vector far off the trajectory is snapped, and the command says by how much
    assert cli.main(["control", "--run", str(run_dir), "--object", "1", "--vector", "1e9,0,0", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "snapped to" in said and "far off it" in said


def test_eval_writes_metrics(tiny, tmp_path, capsys):
    run_dir = tmp_path / "run"  # a copy: the shared run is read by other test workers at the same time
    shutil.copytree(tiny[0], run_dir)
    assert cli.main(["eval", "--run", str(run_dir), "--maps", str(tmp_path / "maps")]) == 0
    m = json.loads((run_dir / "metrics.json").read_text())["control"]
    # the tiny deterministic run (8 stage-1 steps) finds one object; its ARIs are at chance level (measured -0.023,
    # controlled -0.016: the geometry after 8 steps is poor) and its held-out state PSNR 16.7 dB. The floors below
    # leave a margin; the quality floors of real runs are in tests/regression.
    assert m["num_objects_found"] == 1, m["num_objects_found"]
    assert m["ari"] > ARI_FLOOR and m["ari_controlled"] > ARI_FLOOR, (m["ari"], m["ari_controlled"])
    assert m["state_psnr"] > 15.0, m["state_psnr"]
    assert len(m["ari_per_view"]) == len(m["ari_controlled_per_view"]) >= 1
    # the ceilings: the same renders with labels from the gt
    assert -1.0 <= m["ari_gt_labels"] <= 1.0 and -1.0 <= m["ari_controlled_gt_labels"] <= 1.0
    assert m["num_objects_gt"] == 3
    # the tiny scene's poses are written exactly and not refined: both camera errors ~0
    assert m["camera_rotation_error_written_deg"] < 1e-3 and m["camera_centre_error_written"] < 1e-5
    assert m["camera_rotation_error_used_deg"] == m["camera_rotation_error_written_deg"]
    # ... so the test cameras' alignment into the run's frame is the identity and changes no metric
    al = m["camera_alignment"]
    assert abs(al["scale"] - 1.0) < 1e-6 and al["rotation_deg"] < 1e-3 and np.abs(al["translation"]).max() < 1e-6
    assert abs(m["state_psnr_unaligned"] - m["state_psnr"]) < 1e-3
    # ... and the state frames, seen from training cameras, get the run's own cameras: the same exact ones
    assert abs(m["state_psnr_run_cameras"] - m["state_psnr"]) < 1e-3
    assert len(m["state_psnr_run_cameras_per_frame"]) == len(m["state_psnr_per_frame"])
    assert abs(m["view_psnr_stage1_unaligned"] - m["view_psnr_stage1"]) < 1e-3 and np.isfinite(m["view_psnr_stage1"])
    assert np.isfinite(m["state_psnr_true_motion"]) and np.isfinite(m["state_psnr_true_motion_labels"])
    assert -1.0 <= m["ari_controlled_true_motion"] <= 1.0
    assert -1.0 <= m["ari_controlled_true_motion_gt_labels"] <= 1.0
    # where the state frames' error lies: per gt id, shares that sum to each frame's MSE (its PSNR)
    shares = np.array(list(m["state_mse_by_object"].values()))  # [ids, frames]
    pixels = np.array(list(m["state_pixels_by_object"].values()))
    assert shares.shape == pixels.shape == (len(m["state_mse_by_object"]), len(m["state_psnr_per_frame"]))
    assert "0" in m["state_mse_by_object"] and np.all(shares >= 0) and np.all(pixels >= 0)
    np.testing.assert_allclose(-10 * np.log10(shares.sum(0)), m["state_psnr_per_frame"], atol=1e-3)
    # ... and the static pixels' share split into those a part sweeps and the rest
    sw = m["state_mse_static_swept"]
    np.testing.assert_allclose(np.add(sw["swept"], sw["rest"]), m["state_mse_by_object"]["0"], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.add(*m["state_pixels_static_swept"].values()), m["state_pixels_by_object"]["0"])
    # --maps: one render | image | error picture per state frame
    import imageio.v3 as iio

    maps = sorted((tmp_path / "maps").glob("state_*.png"))
    assert len(maps) == len(m["state_psnr_per_frame"])
    h, w = np.load(tiny[1] / "gt" / "test" / "object_id.npy").shape[1:]
    assert iio.imread(maps[0]).shape == (h, 3 * w, 3)
    assert not list((tmp_path / "maps").glob("*.tmp*"))
    for row in m.get("motion_preference", {}).values():
        assert 1 <= row["frames"] <= 8 and 0.0 <= row["true_wins"] <= 1.0 and 0.0 <= row["true_wins_gt_labels"] <= 1.0
        assert all(0.0 < row[key] < 1.0 for key in ("l1_learned", "l1_true", "l1_true_gt_labels"))


def test_error_by_object_splits_the_squared_error_by_gt_id():
    """Shares of a hand-made error: id 2's four pixels off by 0.5 in one channel, id 0 by 0.1 everywhere,
    id -1 (no gt) left out even when wrong."""
    from fgjax.method.evaluate import error_by_object

    image = np.zeros((4, 5, 3))
    ids = np.zeros((4, 5), int)
    ids[:2, :2] = 2
    ids[3, 4] = -1
    img = image + np.array([0.1, 0.1, 0.1])
    img[:2, :2] = [0.5, 0.0, 0.0]
    img[3, 4] = 1.0
    out = error_by_object(img, image, ids)
    assert sorted(out) == ["0", "2"]
    np.testing.assert_allclose(out["2"]["mse"], 4 * 0.25 / 3 / 20)
    np.testing.assert_allclose(out["0"]["mse"], 15 * 0.01 / 20)
    assert out["2"]["pixels"] == 4 / 20 and out["0"]["pixels"] == 15 / 20
    with pytest.raises(ValueError, match="ids must have shape"):
        error_by_object(img, image, ids[:3])


def test_swept_mask_and_error_map_image():
    """`swept_mask`: the union of the two frames' part pixels, grown by the radius (a square); `error_map_image`:
    render | image | |difference| x gain, clipped."""
    from fgjax.method.evaluate import error_map_image, swept_mask

    a = np.zeros((7, 9), int)
    b = np.zeros((7, 9), int)
    a[1, 1] = 2
    b[5, 7] = 1
    b[0, 8] = -1  # no gt: not a part
    m = swept_mask(a, b, radius=1)
    want = np.zeros((7, 9), bool)
    want[0:3, 0:3] = True
    want[4:7, 6:9] = True
    np.testing.assert_array_equal(m, want)
    np.testing.assert_array_equal(swept_mask(a, b, radius=0), (a > 0) | (b > 0))
    with pytest.raises(ValueError, match="swept_mask"):
        swept_mask(a, b[:3])
    img = np.full((2, 3, 3), 0.5)
    image = img.copy()
    image[0, 0] = [0.4, 0.5, 1.5]  # off by 0.1 (x 4 = 0.4), 0, and beyond 1 (clipped to 1 first: 0.5 x 4 -> 1)
    out = error_map_image(img, image, gain=4.0)
    assert out.shape == (2, 9, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[0, 6], [102, 0, 255])
    np.testing.assert_array_equal(out[1, 6:], 0)
    np.testing.assert_array_equal(out[:, :3], 128)


def test_motion_preference_compares_the_three_renders_with_the_same_frames(tiny, monkeypatch):
    """With the gt motion replaced by the identity and the learned render by the unmoved reference (both
    then draw the same scene), every frame ties: l1_learned == l1_true and the true motion never wins; a
    learned render that is all black loses every frame to the true motion."""
    from fgjax.method import evaluate
    from fgjax.method import result as stage2

    run_dir, data = tiny
    seen = {}
    orig = evaluate._motion_preference
    monkeypatch.setattr(evaluate, "_motion_preference", lambda *a, **kw: seen.setdefault("args", a) and {})
    evaluate.evaluate_control(stage2.load_stage2(run_dir), Path(data))
    run, train, objs = seen["args"][:3]
    assert run.s2.num_objects > 0, "the tiny run found no object"
    args = list(seen["args"])
    args[3] = {c: 1 + c % len(objs) for c in range(run.s2.num_objects)}  # every cluster on a gt object

    def reference(run_, vec, vm, K, w, h):
        img, _, _ = run_.render_geometry(*run_.base(), vm, K, w, h, params=run_.control_params())
        return np.clip(np.asarray(img), 0.0, 1.0)

    monkeypatch.setattr(evaluate, "gt_motion_scene", lambda *a: np.eye(4))
    monkeypatch.setattr(stage2, "render_controlled", reference)
    out = orig(*args, min_move=-1.0)
    assert len(out) == run.s2.num_objects and all(r["frames"] >= 1 for r in out.values())
    for r in out.values():
        assert r["l1_learned"] == pytest.approx(r["l1_true"], rel=1e-6) and r["true_wins"] == 0.0
    monkeypatch.setattr(stage2, "render_controlled", lambda run_, vec, vm, K, w, h: np.zeros((h, w, 3)))
    out = orig(*args, min_move=-1.0)
    assert all(r["true_wins"] == 1.0 and r["l1_learned"] > r["l1_true"] for r in out.values())


def test_render_clusters_writes_id_maps(tiny, tmp_path):
    from fgjax.method import result as stage2

    run_dir, data = tiny
    out = tmp_path / "ids"
    args = ["render", "--run", str(run_dir), "--cameras", str(data / "transforms_test.json"), "--out", str(out)]
    assert cli.main(args + ["--clusters"]) == 0
    maps = sorted(out.glob("*_ids.npy"))
    assert maps and len(maps) == len(list(out.glob("*_ids.png")))
    n = stage2.load_stage2(run_dir).s2.num_objects
    for path in maps:
        ids = np.load(path)
        assert ids.dtype.kind in "iu" and ids.min() >= 0 and ids.max() <= n


def test_gt_point_motion_matches_hinge_and_slide_geometry():
    """The evaluation's gt motion of a point, against closed forms: a point at distance r from a hinge
    turned by theta moves by 2 r sin(theta / 2) and keeps its distance to the axis; a drawer point
    moves by s * distance along the direction. In the run's scene units (centre and scale applied)."""
    from conftest import synth

    from fgjax.data.scene import Normalization

    SynthObject = synth.SynthObject
    from fgjax.method.evaluate import gt_point_motion

    norm = Normalization(centre=np.array([0.3, -0.2, 0.5]), scale=0.8)
    z = np.zeros(3)
    door = SynthObject(label=1, kind="door", name="door_1", pivot=np.array([1.0, 0.0, 0.0]),
                       axis=np.array([0.0, 0.0, 1.0]), direction=z, lateral=z, max_angle=1.2, distance=0.0,
                       wiggle=0.0, radius=0.0, key_times=np.array([0.0, 1.0]), key_states=np.array([0.0, 1.0]))
    p_world = np.array([1.0, 0.4, 0.7])  # 0.4 from the hinge axis
    p = norm.points_to_scene(p_world)
    q = gt_point_motion({1: door}, 1, [0.25], [0.75], p, norm)  # turns by 0.5 * 1.2 rad
    assert np.linalg.norm(q - p) == pytest.approx(0.8 * 2 * 0.4 * np.sin(0.3), rel=1e-9)
    q_world = norm.points_to_world(q)
    assert np.hypot(q_world[0] - 1.0, q_world[1]) == pytest.approx(0.4, rel=1e-9) and q_world[2] == pytest.approx(0.7)
    np.testing.assert_allclose(gt_point_motion({1: door}, 1, [0.75], [0.25], q, norm), p, atol=1e-12)  # and back
    drawer = SynthObject(label=1, kind="drawer", name="drawer_1", pivot=z, axis=z, direction=np.array([0.0, -1.0, 0.0]),
                         lateral=z, max_angle=0.0, distance=0.3, wiggle=0.0, radius=0.0,
                         key_times=np.array([0.0, 1.0]), key_states=np.array([0.0, 1.0]))
    np.testing.assert_allclose(gt_point_motion({1: drawer}, 1, [0.0], [0.5], p, norm) - p, [0.0, -0.8 * 0.15, 0.0],
                               atol=1e-12)


def test_gt_motion_scene_matches_point_motion():
    """The gt motion as a scene-unit matrix moves points where the world-space round trip does (scene ->
    world, the object's transform, world -> scene; written out here), and `gt_point_motion` agrees."""
    from conftest import synth

    from fgjax.data.scene import Normalization

    SynthObject, object_transform = synth.SynthObject, synth.object_transform
    from fgjax.method.evaluate import gt_motion_scene, gt_point_motion

    norm = Normalization(centre=np.array([0.3, -0.2, 0.5]), scale=0.8)
    z = np.zeros(3)
    lid = SynthObject(label=1, kind="lid", name="lid_1", pivot=np.array([0.2, 1.0, -0.3]),
                      axis=np.array([1.0, 0.0, 0.0]), direction=z, lateral=z, max_angle=1.0, distance=0.0,
                      wiggle=0.0, radius=0.0, key_times=np.array([0.0, 1.0]), key_states=np.array([0.0, 1.0]))
    pts = np.random.default_rng(0).normal(size=(5, 3))
    tr = gt_motion_scene({1: lid}, 1, [0.1], [0.9], norm)
    np.testing.assert_allclose(tr[:3, :3] @ tr[:3, :3].T, np.eye(3), atol=1e-12)
    mo = object_transform(lid, 0.9) @ np.linalg.inv(object_transform(lid, 0.1))  # world units
    for x in pts:
        ref = norm.points_to_scene(mo[:3, :3] @ norm.points_to_world(x) + mo[:3, 3])
        np.testing.assert_allclose(tr[:3, :3] @ x + tr[:3, 3], ref, atol=1e-12)
        np.testing.assert_allclose(gt_point_motion({1: lid}, 1, [0.1], [0.9], x, norm), ref, atol=1e-12)


def test_gt_labels_of_gaussians_labels_the_gt_parts(tiny):
    """The gt Gaussians themselves, moved to some states and put in scene units, get their own labels
    through the cluster matching; a point far from everything is static."""
    from conftest import synth

    from fgjax.data.scene import Normalization

    SynthObject, object_transform = synth.SynthObject, synth.object_transform
    from fgjax.method.evaluate import gt_labels_of_gaussians

    _, data = tiny
    gt = data / "gt"
    meta = json.loads((gt / "meta.json").read_text())
    z = np.load(gt / "canonical.npz")
    pts, lab = np.array(z["means"], np.float64), np.asarray(z["labels"])
    states = np.linspace(0.2, 0.8, len(meta["objects"]))
    for o in meta["objects"]:
        obj = SynthObject(**{f: (np.asarray(v, np.float64) if isinstance(v, list) else v) for f, v in o.items()})
        tr = object_transform(obj, states[o["label"] - 1])
        pts[lab == o["label"]] = pts[lab == o["label"]] @ tr[:3, :3].T + tr[:3, 3]
    norm = Normalization(centre=np.array([0.1, 0.2, -0.1]), scale=0.5)
    query = np.concatenate([norm.points_to_scene(pts), [[50.0, 50.0, 50.0]]])
    match = {c: c + 1 for c in range(len(meta["objects"]))}  # cluster c <-> gt object c + 1
    from fgjax.method.evaluate import gt_objects

    got = gt_labels_of_gaussians(query, gt, gt_objects(meta), states, norm, match, radius=1e-6)
    np.testing.assert_array_equal(got[:-1], np.where(lab > 0, lab - 1, -1))
    assert got[-1] == -1


def test_render_source_control_draws_the_controlled_scene(tiny, tmp_path, capsys):
    """``fgjax render --source control`` writes the controlled scene at each camera's time (each object at its
    trajectory there); ``--clusters --source stage1`` the stage-1 ids; a run without stage 2: exit 2, naming the
    file it lacks."""
    from fgjax.data.cameras import read_cameras
    from fgjax.data.scene import Normalization
    from fgjax.method import result as stage2
    from fgjax.viz import to_u8

    run_dir, data = tiny
    cams_file = data / "transforms_test.json"
    args = ["render", "--run", str(run_dir), "--cameras", str(cams_file)]
    assert cli.main(args + ["--out", str(tmp_path / "ctl"), "--source", "control"]) == 0
    assert cli.main(args + ["--out", str(tmp_path / "s1")]) == 0  # the default: the stage-1 model
    run = stage2.load_stage2(run_dir)
    meta = json.loads((run_dir / "model.json").read_text())
    name, vm, K, t, w, h = read_cameras(cams_file, Normalization.from_dict(meta["normalization"]), meta["width"],
                                        meta["height"])[0]
    import imageio.v3 as iio

    got = iio.imread(tmp_path / "ctl" / f"{name}.png")
    want = stage2.render_controlled(run, stage2.cluster_vectors_at(run.s2, t), vm, K, w, h)
    np.testing.assert_array_equal(got, to_u8(want))
    assert np.any(got != iio.imread(tmp_path / "s1" / f"{name}.png"))
    assert cli.main(args + ["--out", str(tmp_path / "ids"), "--clusters", "--source", "stage1"]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "ids" / f"{name}_ids.npy"),
                                  stage2.render_clusters(run, vm, K, w, h, t=t, source="stage1"))
    bare = tmp_path / "bare"
    shutil.copytree(run_dir, bare, ignore=shutil.ignore_patterns(stage2.STAGE2_NAME))
    capsys.readouterr()
    assert cli.main(["render", "--run", str(bare), "--cameras", str(cams_file), "--out", str(tmp_path / "x"),
                     "--source", "control"]) == 2
    assert stage2.STAGE2_NAME in capsys.readouterr().err


def test_render_clusters_with_given_labels(tiny):
    """``labels`` replaces the clustering: stage 2's own labels give the same map, no labels an all-static
    one, and object 1's members alone paint object 1 only where the full map does (the other objects'
    weight joins the static channel), and somewhere when the full map has object 1 in view."""
    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization
    from fgjax.method import result as stage2

    run_dir, data = tiny
    run = stage2.load_stage2(run_dir)
    assert run.s2.num_objects > 0, "no clusters in the tiny run"

    train = load_scene(data, "train", normalize=Normalization.from_dict(run.meta["normalization"]),
                       downscale=run.cfg.data.downscale)
    vm, K, w, h = train.viewmats[0], train.Ks[0], train.width, train.height
    lab = run.s2.labels
    for source in ("stage1", "control"):
        own = stage2.render_clusters(run, vm, K, w, h, source=source)
        np.testing.assert_array_equal(stage2.render_clusters(run, vm, K, w, h, source=source, labels=lab.copy()), own)
        assert not stage2.render_clusters(run, vm, K, w, h, source=source, labels=np.full_like(lab, -1)).any()
        one = stage2.render_clusters(run, vm, K, w, h, source=source, labels=np.where(lab == 0, 0, -1))
        assert set(np.unique(one)) <= {0, 1}
        assert np.all(own[one == 1] == 1)
        assert (one == 1).any() or not (own == 1).any()
    with pytest.raises(ValueError, match="labels must have shape"):
        stage2.render_clusters(run, vm, K, w, h, labels=lab[:-1])


def test_render_clusters_with_poses(tiny):
    """``poses`` moves each cluster rigidly from the controlled scene's reference: the identity gives the
    controlled scene at zero vectors, and a pose that carries object 1 far behind a camera that sees it takes
    it out of that camera's map while the others stay where they were."""
    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization
    from fgjax.method import result as stage2

    run_dir, data = tiny
    run = stage2.load_stage2(run_dir)
    k = run.s2.num_objects
    assert k > 0, "no clusters in the tiny run"
    train = load_scene(data, "train", normalize=Normalization.from_dict(run.meta["normalization"]),
                       downscale=run.cfg.data.downscale)
    w, h = train.width, train.height
    eye = np.tile(np.eye(4), (k, 1, 1))
    for i in range(train.num_frames):  # the first training camera that sees object 1
        vm, K = train.viewmats[i], train.Ks[i]
        at_rest = stage2.render_clusters(run, vm, K, w, h, vectors=np.zeros((k, 3)))
        np.testing.assert_array_equal(stage2.render_clusters(run, vm, K, w, h, poses=eye), at_rest)
        if (at_rest == 1).any():
            break
    else:
        raise AssertionError("no training camera sees object 1 in the tiny run")
    away = eye.copy()
    away[0, :3, 3] = -1e3 * np.linalg.inv(np.asarray(vm, np.float64))[:3, 2]  # far behind the camera
    gone = stage2.render_clusters(run, vm, K, w, h, poses=away)
    assert not (gone == 1).any()
    others = (at_rest > 1) & (gone > 0)
    np.testing.assert_array_equal(gone[others], at_rest[others])
    with pytest.raises(ValueError, match="poses must have shape"):
        stage2.render_clusters(run, vm, K, w, h, poses=eye[:, :3])
    bad = eye.copy()
    bad[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="poses must be finite"):
        stage2.render_clusters(run, vm, K, w, h, poses=bad)
    with pytest.raises(ValueError, match="not both"):
        stage2.render_clusters(run, vm, K, w, h, poses=eye, vectors=np.zeros((k, 3)))


def test_camera_errors_against_a_known_perturbation():
    """A camera turned by 3 degrees about its own centre and one moved by (0.3, 0.4, 0) without turning:
    rotation errors (3, 0), centre errors (0, 0.5)."""
    from fgjax.method.evaluate import camera_errors

    a = np.radians(3.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    true = np.tile(np.eye(4), (2, 1, 1))
    true[:, :3, 3] = [[0.1, -0.2, 0.5], [1.0, 0.0, -1.0]]
    turned = true.copy()
    turned[0, :3, :3] = rz  # R' = Rz, t' = Rz t keeps the centre -R'^T t' = -t
    turned[0, :3, 3] = rz @ true[0, :3, 3]
    turned[1, :3, 3] = true[1, :3, 3] - np.array([0.3, 0.4, 0.0])  # centre -t moves by (0.3, 0.4, 0)
    rot, centre = camera_errors(turned, true)
    assert rot == pytest.approx(1.5, abs=1e-9) and centre == pytest.approx(0.25, abs=1e-12)


def _cameras_around(n: int, rng) -> np.ndarray:
    """n world-to-camera matrices [n, 4, 4] on a noisy arc around the origin, each looking at it
    (`conftest.look_at`)."""
    from conftest import look_at

    return np.stack([look_at([2.0 * np.sin(a), -2.0 * np.cos(a), 0.5 + 0.1 * rng.normal()])
                     for a in np.linspace(-0.8, 0.8, n)])


def test_run_camera_carries_a_test_camera_by_way_of_its_training_camera():
    """`run_camera`: a test camera D T_src seen through the run's camera for T_src. When the run's cameras are the
    true ones carried by a similarity, it is the test camera carried by the same similarity (`apply_alignment`,
    tested above); when the run's camera of the source frame is off, the test camera is off by the same
    camera-side error; D = I gives the run's camera itself."""
    from fgjax import geometry
    from fgjax.method.evaluate import apply_alignment, run_camera

    rng = np.random.default_rng(1)
    true = _cameras_around(6, rng)
    rot = np.asarray(geometry.so3_exp(np.array([0.1, 0.3, -0.2])), np.float64)
    s, t = 0.8, np.array([0.1, 0.4, -0.3])
    used = apply_alignment(true, s, rot, t)
    d = np.eye(4)
    d[:3, :3] = np.asarray(geometry.so3_exp(np.array([0.05, -0.2, 0.1])), np.float64)
    d[:3, 3] = [0.3, -0.1, 0.2]
    test = d @ true[2]
    np.testing.assert_allclose(run_camera(test, true[2], used[2], s), apply_alignment(test[None], s, rot, t)[0],
                               atol=1e-12)
    np.testing.assert_allclose(run_camera(true[4], true[4], used[4], s), used[4], atol=1e-12)
    err = np.eye(4)
    err[:3, :3] = np.asarray(geometry.so3_exp(np.array([0.0, 0.003, 0.0])), np.float64)
    err[:3, 3] = [0.001, 0.0, 0.0]
    off = run_camera(test, true[2], err @ used[2], s)
    np.testing.assert_allclose(off, run_camera(test, true[2], used[2], s) @ np.linalg.inv(used[2]) @ err @ used[2],
                               atol=1e-12)
    assert not np.allclose(off, apply_alignment(test[None], s, rot, t)[0], atol=1e-4)


def test_align_cameras_recovers_a_similarity_and_keeps_every_image():
    """Cameras carried by a known similarity x = s R x_true + t: `align_cameras` finds (s, R, t) again; the carried
    cameras project every moved point where the original ones project the point; with per-camera noise the fit
    is still close; one camera gives scale 1; wrong shapes are refused."""
    from fgjax import geometry
    from fgjax.method.evaluate import align_cameras, apply_alignment, camera_errors

    rng = np.random.default_rng(0)
    true = _cameras_around(12, rng)
    rot = np.asarray(geometry.so3_exp(np.array([0.2, -0.3, 0.25])), np.float64)  # 25 degrees
    s, t = 1.3, np.array([0.5, -0.2, 0.1])
    run = apply_alignment(true, s, rot, t)
    s2, rot2, t2 = align_cameras(run, true)
    assert s2 == pytest.approx(s, abs=1e-9)
    np.testing.assert_allclose(rot2, rot, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-9)
    assert camera_errors(run, apply_alignment(true, s2, rot2, t2))[1] < 1e-9
    # the same image: a point seen by a true camera and the moved point seen by the carried one
    x = rng.normal(size=(5, 3)) * 0.3
    cam = np.einsum("tij,mj->tmi", true[:, :3, :3], x) + true[:, None, :3, 3]
    cam2 = np.einsum("tij,mj->tmi", run[:, :3, :3], s * x @ rot.T + t) + run[:, None, :3, 3]
    np.testing.assert_allclose(cam2[..., :2] / cam2[..., 2:], cam[..., :2] / cam[..., 2:], atol=1e-12)
    np.testing.assert_allclose(run[:, :3, :3] @ np.transpose(run[:, :3, :3], (0, 2, 1)), np.tile(np.eye(3), (12, 1, 1)),
                               atol=1e-12)  # still rotations
    # per-camera noise (0.2 degree, 0.005): the shift and scale are still found to about the noise
    noisy = run.copy()
    for i in range(len(noisy)):
        d = np.asarray(geometry.so3_exp(rng.normal(size=3) * np.radians(0.2)), np.float64)
        noisy[i, :3, :3] = d @ noisy[i, :3, :3]
        noisy[i, :3, 3] = d @ noisy[i, :3, 3] + rng.normal(size=3) * 0.005
    s3, rot3, t3 = align_cameras(noisy, true)
    assert abs(s3 - s) < 0.01 and np.abs(t3 - t).max() < 0.02
    assert np.degrees(np.arccos(np.clip((np.trace(rot3 @ rot.T) - 1) / 2, -1, 1))) < 0.2
    assert camera_errors(noisy, apply_alignment(true, s3, rot3, t3))[1] < camera_errors(noisy, true)[1] / 10
    one = align_cameras(run[:1], true[:1])
    assert one[0] == 1.0 and np.all(np.isfinite(one[1])) and np.all(np.isfinite(one[2]))
    with pytest.raises(ValueError, match="align_cameras"):
        align_cameras(run[:3], true[:4])
