"""Stage 2 on a tiny synthetic run: outputs, reload, cluster maps, controlled renders, errors."""

from __future__ import annotations

import json
import re

import jax
import numpy as np
import pytest

from fgjax.apps import render as render_app
from fgjax.articulate import labels as L
from fgjax.articulate import pipeline as AP
from fgjax.articulate import refit, trial
from fgjax.articulate.pipeline import run_articulated
from fgjax.config import ArticulateConfig, Stage2Config
from fgjax.method import result
from fgjax.method.control import train_control
from fgjax.method.stage2 import discover_run


def _cfgs(**kw) -> tuple[Stage2Config, ArticulateConfig]:
    """(Stage2Config, ArticulateConfig) from one set of keyword arguments, each to the section that has it."""
    names = set(Stage2Config.__dataclass_fields__)
    return (Stage2Config(**{k: v for k, v in kw.items() if k in names}),
            ArticulateConfig(**{k: v for k, v in kw.items() if k not in names}))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    import sys

    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1]))
    from _pipeline_run import shared_base, tiny_run

    return tiny_run(shared_base(tmp_path_factory) / "pipeline")


def test_stage2_outputs(tiny):
    run_dir, data = tiny
    summary = json.loads((run_dir / "stage2.json").read_text())
    assert summary["data_dir"] == str(data.resolve())
    assert not list(run_dir.glob("*.tmp"))  # atomic writes leave no temporaries
    run = result.load_stage2(run_dir)
    s2 = run.s2
    n = run.state.params["gaussians"].means.shape[0]
    assert s2.labels.shape == (n,) and s2.dynamic.shape == (n,)
    # clustered Gaussians are dynamic and alive; labels are compact 0..K-1
    assert np.all(s2.dynamic[s2.labels >= 0])
    assert np.all(np.asarray(run.state.densify.alive)[s2.labels >= 0])
    assert set(np.unique(s2.labels[s2.labels >= 0])) == set(range(s2.num_objects))
    assert s2.traj.shape == (s2.num_objects, 8, 3) and np.all(np.diff(s2.traj_times) >= 0)
    assert summary["num_objects"] == s2.num_objects


def test_controlled_render_zero_vector_is_stage1_at_t0(tiny):
    from fgjax.method.stage1 import render_frame

    run = result.load_stage2(tiny[0])
    m = run.meta
    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization

    sc = load_scene(tiny[1], "train", normalize=Normalization.from_dict(m["normalization"]))
    k = max(run.s2.num_objects, 1)
    img = result.render_controlled(run, np.zeros((k, 3)), sc.viewmats[0], sc.Ks[0], m["width"], m["height"])
    if run.s2.refit is None:  # v = 0 gives exactly the stage-1 scene at t0 (f(0) - f(0) = 0)
        ref = render_frame(run.state, run.spec, run.cfg, sc.viewmats[0], sc.Ks[0], run.s2.t0, m["width"], m["height"])
    else:  # ... or the re-fitted reference scene
        ref = np.clip(np.asarray(run.render_geometry(*run.base(), sc.viewmats[0], sc.Ks[0], m["width"], m["height"],
                                                     params=run.control_params())[0]), 0, 1)
    np.testing.assert_allclose(img, ref, atol=1e-5)  # float32 rendering tolerance
    ids = result.render_clusters(run, sc.viewmats[0], sc.Ks[0], m["width"], m["height"])
    assert ids.shape == (m["height"], m["width"]) and ids.min() >= 0 and ids.max() <= run.s2.num_objects
    # at the reference time both sources draw the same scene (zero control vectors)
    ids_c = result.render_clusters(run, sc.viewmats[0], sc.Ks[0], m["width"], m["height"], source="control")
    assert np.mean(ids_c == ids) > 0.99
    with pytest.raises(ValueError, match="source"):
        result.render_clusters(run, sc.viewmats[0], sc.Ks[0], m["width"], m["height"], source="gt")


def test_rigid_control_moves_each_cluster_by_the_rigid_motion_nearest_the_network(tiny):
    """`controlled_gaussians(rigid=True)` (`Stage2Config.control_rigid`): each cluster's members are their base
    centres moved by one rotation and shift (distances between them kept), the one nearest the network's centres
    (checked against an independent float64 Kabsch fit); their orientations turn with it, their scales are the
    base's, and the static Gaussians are untouched; a zero vector gives the base scene; results of a stage 2
    without the option render as the network gives them."""
    import jax.numpy as jnp

    from fgjax.geometry import quat_to_rotmat

    run = result.load_stage2(tiny[0])
    s2 = run.s2
    assert s2.rigid  # the tiny run sets control_rigid (the articulated configuration does)
    k = s2.num_objects
    assert k > 0, "the tiny run found no object"
    base, can, lab = run.base(), run.state.params["gaussians"].means, jnp.asarray(s2.labels)
    vec = jnp.asarray(s2.traj[:, -1] - s2.traj[:, 0] + 0.05, jnp.float32)  # [K, 3]
    free = result.controlled_gaussians(s2.control, base, can, lab, vec)
    rig = result.controlled_gaussians(s2.control, base, can, lab, vec, rigid=True)
    m0, mf, mr = (np.asarray(x, np.float64) for x in (base[0], free[0], rig[0]))
    static = s2.labels < 0
    np.testing.assert_array_equal(mr[static], m0[static])
    np.testing.assert_array_equal(np.asarray(rig[2]), np.asarray(base[2]))
    for c in range(k):
        sel = s2.labels == c
        a, b = m0[sel], mf[sel]
        u, _, vt = np.linalg.svd((a - a.mean(0)).T @ (b - b.mean(0)))
        rot = vt.T @ np.diag([1, 1, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
        expect = (a - a.mean(0)) @ rot.T + b.mean(0)
        np.testing.assert_allclose(mr[sel], expect, atol=2e-5)
        # the orientations turn by the same rotation
        r0 = np.asarray(quat_to_rotmat(jnp.asarray(base[1])[sel]), np.float64)
        r1 = np.asarray(quat_to_rotmat(rig[1][sel]), np.float64)
        np.testing.assert_allclose(r1, np.einsum("ij,njk->nik", rot, r0), atol=1e-4)
    zero = result.controlled_gaussians(s2.control, base, can, lab, jnp.zeros((k, 3)), rigid=True)
    np.testing.assert_allclose(np.asarray(zero[0]), m0, atol=1e-5)
    # an older stage 2 (no control_rigid in its config): the network as it is
    old = result.Stage2Result(s2.labels, s2.dynamic, s2.scores, s2.traj, s2.traj_times, s2.control,
                              {**s2.meta, "config": {key: v for key, v in s2.meta["config"].items()
                                                     if key != "control_rigid"}}, s2.refit)
    assert not old.rigid


def test_fit_group_poses_recovers_each_groups_motion_and_degrades_safely():
    """`fgjax.geometry.fit_group_poses`: exact poses of moved groups; a group of one or two points gets its shift only;
    an empty group the identity; coincident points a finite pose; gradients 0, never NaN."""
    import jax
    import jax.numpy as jnp

    from fgjax import geometry
    from fgjax.geometry import fit_group_poses
    from fgjax.models.posed import transform_gaussians

    rng = np.random.default_rng(0)
    src = rng.normal(size=(300, 3))
    lab = rng.integers(-1, 3, 300)  # groups 0-2 and the ungrouped
    lab[:2] = 3  # group 3: two points; group 4: none
    poses = np.stack([np.asarray(geometry.make_pose(geometry.so3_exp(rng.normal(size=3) * 1.5), rng.normal(size=3)))
                      for _ in range(5)])
    dst = np.asarray(transform_gaussians(jnp.asarray(src, jnp.float32), jnp.ones((300, 4)), lab, poses)[0])
    got = np.asarray(fit_group_poses(src, dst, lab, 5))
    np.testing.assert_allclose(got[:3], poses[:3], atol=1e-5)
    np.testing.assert_allclose(got[3, :3, :3], np.eye(3), atol=1e-6)  # two points: no turn ...
    np.testing.assert_allclose(got[3, :3, 3], (dst[:2] - src[:2]).mean(0), atol=1e-5)  # ... their shift
    np.testing.assert_array_equal(got[4], np.eye(4))  # no points
    same = np.zeros((10, 3))
    assert np.isfinite(np.asarray(fit_group_poses(same, same + 1.0, np.zeros(10, int), 1))).all()
    grad = jax.grad(lambda d: jnp.sum(fit_group_poses(src, d, lab, 5)))(jnp.asarray(dst, jnp.float32))
    assert np.all(np.asarray(grad) == 0)


def test_cluster_map_of_the_stage1_source_is_the_stage1_model_at_t(tiny):
    """source="stage1": the one-hot ids composited over the stage-1 model at time t (what `fgjax render`
    draws in colour), checked against an independent composite of the same geometry."""
    import jax.numpy as jnp

    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization
    from fgjax.gaussians import activate
    from fgjax.render.api import rasterization

    run = result.load_stage2(tiny[0])
    m = run.meta
    sc = load_scene(tiny[1], "train", normalize=Normalization.from_dict(m["normalization"]))
    t = float(sc.times[-1])
    labels = run.s2.labels.copy()
    labels[: len(labels) // 3] = 0  # make sure some Gaussians carry an object id
    run.s2.labels = labels
    ids = result.render_clusters(run, sc.viewmats[-1], sc.Ks[-1], m["width"], m["height"], t=t)
    mt, qt, st = run.deformed(t)
    g = run.state.params["gaussians"]
    q, s, o = activate(type(g)(mt, st, qt, g.opacity_logits, g.sh), run.state.densify.alive)
    obj = (labels >= 0).astype(np.float32)[:, None]
    feat, alpha, _ = rasterization(mt, q, s, o, jnp.asarray(obj), jnp.asarray(sc.viewmats[-1], jnp.float32),
                                   jnp.asarray(sc.Ks[-1], jnp.float32), m["width"], m["height"])
    feat, alpha = np.asarray(feat)[..., 0], np.asarray(alpha)
    expect = (alpha >= 0.5) & (feat > 0.5 * alpha)  # an object channel dominates
    decided = np.abs(feat - 0.5 * alpha) > 1e-3  # away from ties
    np.testing.assert_array_equal((ids > 0)[decided], expect[decided])
    assert expect.any()


def test_deformed_compiles_once_per_field(tiny):
    """A run loaded again (or a second run of the same field and size) reuses the jitted deformation: stage 2,
    the evaluation and the viewer each load runs, and a program per load was a compile per load."""
    first = result.load_stage2(tiny[0]).deformed(0.5)
    size = result._deformed._cache_size()
    again = result.load_stage2(tiny[0]).deformed(0.25)
    assert result._deformed._cache_size() == size
    assert all(np.isfinite(np.asarray(a)).all() for a in (*first, *again))


def test_write_cluster_maps(tiny, tmp_path):
    from fgjax.data.cameras import read_cameras
    from fgjax.data.scene import Normalization

    run_dir, data = tiny
    meta = json.loads((run_dir / "model.json").read_text())
    cams = read_cameras(data / "transforms_test.json", Normalization.from_dict(meta["normalization"]),
                        meta["width"], meta["height"])[:1]
    assert render_app.write_cluster_maps(run_dir, cams, tmp_path / "ids", log=lambda m: None) == 0
    ids = np.load(tmp_path / "ids" / f"{cams[0][0]}_ids.npy")
    assert ids.shape == (meta["height"], meta["width"]) and (tmp_path / "ids" / f"{cams[0][0]}_ids.png").is_file()
    # the default draws the controlled scene at the camera's time (what eval's ari_controlled scores); "stage1" the
    # stage-1 model
    run = result.load_stage2(run_dir)
    name, vm, K, t, w, h = cams[0]
    want = {src: result.render_clusters(run, vm, K, w, h, t=t, source=src) for src in ("control", "stage1")}
    np.testing.assert_array_equal(ids, want["control"])
    assert render_app.write_cluster_maps(run_dir, cams, tmp_path / "ids1", log=lambda m: None, source="stage1") == 0
    np.testing.assert_array_equal(np.load(tmp_path / "ids1" / f"{name}_ids.npy"), want["stage1"])
    assert np.any(want["control"] != want["stage1"])  # the two scenes differ here, so the checks above can fail
    assert render_app.write_cluster_maps(tmp_path / "nope", cams, tmp_path / "ids") == 2


def test_snap_and_vectors(tiny):
    run = result.load_stage2(tiny[0])
    s2 = run.s2
    assert s2.num_objects > 0, "no clusters in the tiny run"
    v_end = s2.traj[0, -1] - s2.traj[0, 0]
    v, t = result.snap_vector(s2, 0, v_end)  # a point on the trajectory snaps to itself
    np.testing.assert_allclose(v, v_end, atol=1e-9)
    np.testing.assert_allclose(result.cluster_vectors_at(s2, s2.t0), 0.0, atol=1e-12)
    with pytest.raises(ValueError, match="out of range"):
        result.snap_vector(s2, s2.num_objects, np.zeros(3))


def test_missing_stage2_is_a_clear_error(tiny, tmp_path):
    import shutil

    run_dir = tmp_path / "run"
    shutil.copytree(tiny[0], run_dir)
    (run_dir / result.STAGE2_NAME).unlink()
    with pytest.raises(result.Stage2Error, match="no stage-2 results"):
        result.load_stage2(run_dir)
    (run_dir / result.STAGE2_NAME).write_bytes(b"not a zip")
    with pytest.raises(result.Stage2Error, match="not a readable"):
        result.load_stage2(run_dir)


def test_control_training_uses_the_flow_loss(tiny):
    """The photometric phase adds beta L_uGS: with a non-zero observed object flow the trained network
    differs from the photometric-only one, stays finite, and the run records the flow loss as used."""
    import jax

    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization

    run = result.load_stage2(tiny[0])
    sc = load_scene(tiny[1], "train", normalize=Normalization.from_dict(run.meta["normalization"]))
    order = np.argsort(sc.times, kind="stable")
    alive = np.flatnonzero(np.asarray(run.state.densify.alive))
    labels = np.full(len(run.s2.labels), -1)
    labels[alive[:40]] = 0
    t = len(order)
    traj = np.zeros((1, t, 3))
    traj[0, :, 0] = np.linspace(0.0, 0.2, t)
    geo = [run.deformed(float(sc.times[i])) for i in order]
    teacher = tuple(np.stack([np.asarray(g[c]) for g in geo]) for c in range(3))
    flows = np.full((t - 1, sc.height, sc.width, 2), 2.0, np.float32)
    flows[:, :4] = np.nan
    out = {}
    for beta in (0.0, 1.0):
        cfg = Stage2Config(distill_steps=2, photo_steps=3, flow_weight=beta)
        ctrl, stats = train_control(run, sc, order, labels, traj, cfg, teacher, flows, log=lambda m: None)
        out[beta] = jax.tree_util.tree_leaves(ctrl)
        assert stats["photometric"]["flow_weight"] == beta
        assert all(np.all(np.isfinite(np.asarray(a))) for a in out[beta])
    diff = max(float(np.max(np.abs(np.asarray(a) - np.asarray(b)))) for a, b in zip(out[0.0], out[1.0]))
    assert diff > 0


def test_camera_correction_config_is_checked_and_wired_into_discovery(tiny, monkeypatch, tmp_path):
    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization
    from fgjax.method import stage2 as paper

    with pytest.raises(ValueError, match="articulate.track_joints"):
        run_articulated(tiny[0], tiny[1], *_cfgs(track_joints="on"), log=lambda m: None)
    for run_ in (paper.run_stage2, lambda *a, **k: run_articulated(*a, ArticulateConfig(), **k)):
        with pytest.raises(ValueError, match="stage2.camera_correction"):
            run_(tiny[0], tiny[1], Stage2Config(camera_correction="yes"), log=lambda m: None)
    run = result.load_stage2(tiny[0], require_stage2=False)
    scene = load_scene(tiny[1], "train", normalize=Normalization.from_dict(run.meta["normalization"]))
    calls = []
    real = paper.camera_correction

    def spy(*a, **k):
        out = real(*a, **k)
        calls.append(out)
        return out

    monkeypatch.setattr(paper, "camera_correction", spy)
    base = discover_run(run, scene, Stage2Config(), tmp_path, log=lambda m: None)
    assert calls == []  # "auto" and a run without pose refinement: no correction
    logs = []
    on = discover_run(run, scene, Stage2Config(camera_correction="on"), tmp_path, log=logs.append)
    assert len(calls) == scene.num_frames - 1 and any("corrected" in m for m in logs)
    # the correction fits the camera to the observed flow of the (mostly static) frame: the residual
    # |u - u_cam| that discovery thresholds shrinks (this 8-step run's depth is poor, so it is large)
    flows = on[3][1]
    res = lambda cams: np.nanmedian(np.linalg.norm(flows - cams, axis=-1))
    assert res(on[3][2]) < 0.8 * res(base[3][2])


def test_agree_sigma_weights_discovery_by_the_stage1_renders_agreement_with_the_images(tiny, tmp_path):
    """With ``stage2.agree_sigma`` > 0 each pixel's back-projection is weighted by the agreement of the stage-1
    render with the image: a frame whose image is that render keeps every weight, the others lose some."""
    import dataclasses

    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization

    run = result.load_stage2(tiny[0], require_stage2=False)
    scene = load_scene(tiny[1], "train", normalize=Normalization.from_dict(run.meta["normalization"]))
    first = int(np.argsort(scene.times, kind="stable")[0])
    m, q, ls = run.deformed(float(scene.times[first]))
    img, _, _ = run.render_geometry(m, q, ls, scene.viewmats[first], scene.Ks[first], scene.width, scene.height,
                                    capacity=result.render_capacity(run))
    images = np.array(scene.images)
    images[first] = np.asarray(img)
    scene = dataclasses.replace(scene, images=images)
    base = discover_run(run, scene, Stage2Config(), tmp_path, per_frame=True, log=lambda m: None)[0].scores
    gated = discover_run(run, scene, Stage2Config(agree_sigma=0.05), tmp_path, per_frame=True,
                         log=lambda m: None)[0].scores
    np.testing.assert_allclose(gated.total_t[0], base.total_t[0], rtol=1e-3, atol=1e-3)
    assert np.all(gated.total_t <= base.total_t + 1e-3)
    assert gated.total_t[1:].sum() < 0.99 * base.total_t[1:].sum()
    assert np.all(gated.moving_t <= gated.total_t + 1e-3) and np.all(np.isfinite(gated.score))


def test_threshold_sigmas_raises_each_pairs_threshold_to_its_residuals_noise(tiny, tmp_path):
    """``stage2.threshold_sigmas`` reaches the binarisation: each pair's masks shrink to a subset of the fixed
    threshold's (`fgjax.method.discover.binarize` is tested for the values), and far above the noise none is left."""
    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization

    run = result.load_stage2(tiny[0], require_stage2=False)
    scene = load_scene(tiny[1], "train", normalize=Normalization.from_dict(run.meta["normalization"]))
    masks = {k: discover_run(run, scene, Stage2Config(threshold_px=0.5, threshold_sigmas=k), tmp_path,
                             log=lambda m: None)[0].masks for k in (0.0, 3.0, 1e4)}
    assert masks[0.0].any() and not masks[1e4].any()
    assert np.all(masks[3.0] <= masks[0.0]) and masks[3.0].sum() < masks[0.0].sum()


def test_backproject_track_scores_every_pair_on_the_first_frames_gaussians(tiny, tmp_path):
    """``stage2.backproject = "track"`` reaches discovery: the masks are the pairs' own, and each pair's terms are
    back-projected at the first frame through its tracks (`fgjax.method.discover.carry_masks`, tested for the
    values): the first pair, whose tracks start at zero, gives the pair-by-pair terms over the pixels whose flow
    passes the round trip (most of them), the later ones other terms."""
    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization

    run = result.load_stage2(tiny[0], require_stage2=False)
    scene = load_scene(tiny[1], "train", normalize=Normalization.from_dict(run.meta["normalization"]))
    logs: list[str] = []
    by_pair = discover_run(run, scene, Stage2Config(), tmp_path, per_frame=True, log=lambda m: None)[0]
    track = discover_run(run, scene, Stage2Config(backproject="track"), tmp_path, per_frame=True, log=logs.append)[0]
    np.testing.assert_array_equal(track.masks, by_pair.masks)
    sc, pair = track.scores, by_pair.scores
    assert np.all(sc.total_t[0] <= pair.total_t[0] + 1e-3) and np.all(sc.moving_t[0] <= pair.moving_t[0] + 1e-3)
    assert sc.total_t[0].sum() > 0.8 * pair.total_t[0].sum()
    assert not np.allclose(sc.total_t[1:], pair.total_t[1:], rtol=1e-3, atol=1e-3)
    assert np.all(sc.moving_t <= sc.total_t + 1e-3) and np.all(np.isfinite(sc.score))
    assert any("flow tracks from frame" in m for m in logs)


def test_depth_tolerance_reaches_the_camera_flow(tiny, tmp_path):
    """``stage2.depth_tolerance`` reaches discovery: the camera flow returned is the point of the depth interval's
    segment nearest the optical flow, so each pair's masks shrink to a subset of the exact camera flow's (the
    tiny scene's camera moves), and the residual never grows (`fgjax.method.discover.nearest_on_segment` is
    tested for the values)."""
    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization

    run = result.load_stage2(tiny[0], require_stage2=False)
    scene = load_scene(tiny[1], "train", normalize=Normalization.from_dict(run.meta["normalization"]))
    out = {d: discover_run(run, scene, Stage2Config(threshold_px=0.5, depth_tolerance=d), tmp_path,
                           log=lambda m: None) for d in (0.0, 0.5)}
    m0, m5 = out[0.0][0].masks, out[0.5][0].masks
    assert m0.any() and np.all(m5 <= m0) and m5.sum() < m0.sum()
    flows, cam0, cam5 = out[0.0][3][1], out[0.0][3][2], out[0.5][3][2]
    np.testing.assert_array_equal(out[0.5][3][1], flows)
    r0, r5 = np.linalg.norm(flows - cam0, axis=-1), np.linalg.norm(flows - cam5, axis=-1)
    assert np.all(r5 <= r0 + 1e-4) and np.all(np.isfinite(cam5))


def test_fb_px_leaves_out_the_pixels_whose_flow_fails_the_round_trip(tiny, tmp_path):
    """``stage2.fb_px`` reaches discovery: with a fixed cut and no pose correction, each pair's mask is the mask
    without the check, less the pixels whose flow t-1 -> t the flow t -> t-1 does not bring back within fb_px
    (`fgjax.data.opticalflow.forward_backward_mask` with alpha 0, computed here from the images); a cut of a
    thousandth of a pixel leaves out nearly every pixel, and the optical and camera flows are those without it."""
    from fgjax.data.loaders import load_scene
    from fgjax.data.opticalflow import estimate_flow, forward_backward_mask
    from fgjax.data.scene import Normalization
    from fgjax.viz import to_u8

    run = result.load_stage2(tiny[0], require_stage2=False)
    scene = load_scene(tiny[1], "train", normalize=Normalization.from_dict(run.meta["normalization"]))
    base = dict(threshold_px=0.5, camera_correction="off")
    out = {fb: discover_run(run, scene, Stage2Config(fb_px=fb, **base), tmp_path, log=lambda m: None)
           for fb in (0.0, 1.0, 1e-3)}
    m0, m1, m3 = (out[fb][0].masks for fb in (0.0, 1.0, 1e-3))
    order, flows, cams = out[0.0][3]
    ok = np.stack([forward_backward_mask(flows[j], estimate_flow(to_u8(scene.images[order[j + 1]]),
                                                                 to_u8(scene.images[order[j]]), "dis_deepflow",
                                                                 cache_dir=tmp_path), alpha=0.0, beta=1.0)
                   for j in range(len(flows))])
    assert 0 < ok.sum() < ok.size
    np.testing.assert_array_equal(m1, m0 & ok)
    assert m1.sum() < m0.sum() and m3.sum() < 0.05 * m0.sum()
    for fb in (1.0, 1e-3):
        np.testing.assert_array_equal(out[fb][3][1], flows)
        np.testing.assert_array_equal(out[fb][3][2], cams)


def _moved_scene(run, sc, labels, poses):
    """The training scene with its images replaced by renders of the stage-1 model at t0 whose labelled
    Gaussians move by `poses` [1, T, 4, 4] (frames in time order)."""
    import dataclasses

    import jax.numpy as jnp

    from fgjax.models.posed import transform_gaussians

    order = np.argsort(sc.times, kind="stable")
    m0, q0, ls0 = run.deformed(float(sc.times[order[0]]))
    images = np.array(sc.images)
    for j, i in enumerate(order):
        m, q = transform_gaussians(m0, q0, jnp.asarray(labels), jnp.asarray(poses[:, j], jnp.float32))
        img, _, _ = run.render_geometry(m, q, ls0, sc.viewmats[i], sc.Ks[i], sc.width, sc.height)
        images[i] = np.asarray(img)
    return dataclasses.replace(sc, images=images), order


def _sliding_part(tiny, dx: float):
    """The tiny run with the alive Gaussians beyond the median x as part 0, sliding along x by up to `dx`:
    (run, labels [N], poses [1, T, 4, 4], training scene rendered that way, time order)."""
    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization

    run = result.load_stage2(tiny[0], require_stage2=False)
    sc = load_scene(tiny[1], "train", normalize=Normalization.from_dict(run.meta["normalization"]))
    alive = np.asarray(run.state.densify.alive)
    m0 = np.asarray(run.state.params["gaussians"].means)
    labels = np.where(alive & (m0[:, 0] > np.median(m0[alive, 0])), 0, -1)
    poses = np.tile(np.eye(4), (1, sc.num_frames, 1, 1))
    poses[0, :, 0, 3] = np.linspace(0.0, dx, sc.num_frames)
    moved, order = _moved_scene(run, sc, labels, poses)
    return run, labels, poses, moved, order


def test_refit_moves_the_objects_by_their_poses_and_repairs_damaged_colours(tiny):
    """`refit_gaussians` renders each frame with the objects moved by their poses: on images made that
    way from the stage-1 scene at t0 its first loss is zero (and not without the poses); with the moving
    part's colours damaged it lowers the loss and brings them back towards the originals."""
    import jax.numpy as jnp

    run, labels, poses, moved, order = _sliding_part(tiny, 0.1)
    t = poses.shape[1]
    def losses(poses_, steps):
        logs = []
        g, _ = refit.refit_gaussians(run, moved, order, labels, poses_, steps, log=logs.append)
        first, last = (float(x) for x in logs[0].split("loss ")[1].split(" (")[0].split(" -> "))
        return g, first, last

    # with the poses the images were made with, the first loss is ~0 (then Adam takes lr-sized
    # steps on round-off gradients, so the parameters are not bit-identical); without them it is not
    _, first_posed, _ = losses(poses, 1)
    _, first_still, _ = losses(np.tile(np.eye(4), (1, t, 1, 1)), 1)
    assert first_posed < 1e-3 < first_still
    # damage the part's colours (SH DC): the re-fit lowers the loss and moves them back
    sh = np.array(run.state.params["gaussians"].sh)
    part = labels == 0
    sh[part, 0] += 0.3
    run.state.params = {**run.state.params, "gaussians": type(run.state.params["gaussians"])(
        *[jnp.asarray(sh) if f == "sh" else getattr(run.state.params["gaussians"], f)
          for f in ("means", "log_scales", "quats", "opacity_logits", "sh")])}
    g2, first, last = losses(poses, 40)
    assert last < 0.7 * first, (first, last)
    assert np.abs(g2.sh[part, 0] - (sh[part, 0] - 0.3)).mean() < 0.3  # closer to the undamaged colours


def test_refit_lr_scale_scales_every_group_of_the_first_step(tiny):
    """Adam's first step is lr g / (|g| + eps) per entry, so with ``lr_scale`` 2 every parameter group of the
    re-fit moves twice as far as with 1 (the means' schedule included), and the same direction."""
    run, labels, poses, moved, order = _sliding_part(tiny, 0.1)
    still = np.tile(np.eye(4), (1, poses.shape[1], 1, 1))  # the images disagree: real gradients
    g0 = result.reference_scene(run, float(moved.times[order[0]]))
    steps = {f: refit.refit_gaussians(run, moved, order, labels, still, 1, lr_scale=f, log=lambda *_: None)[0]
             for f in (1.0, 2.0)}
    for field in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        d1 = np.asarray(getattr(steps[1.0], field), np.float64) - np.asarray(getattr(g0, field), np.float64)
        d2 = np.asarray(getattr(steps[2.0], field), np.float64) - np.asarray(getattr(g0, field), np.float64)
        big = np.abs(d1) > 0.5 * np.abs(d1).max()
        assert big.any(), field
        np.testing.assert_allclose(d2[big], 2.0 * d1[big], rtol=0.05, err_msg=field)


def test_refit_draws_only_the_given_frames(tiny):
    """``frames`` restricts the frames the re-fit's steps draw: with the last frame's pose wrong (the part left at
    rest where the images show it slid), a step drawn from the other frames starts at ~0 loss and one drawn from
    the last frame does not; indices outside the frames are refused."""
    run, labels, poses, moved, order = _sliding_part(tiny, 0.1)
    t = poses.shape[1]
    wrong = poses.copy()
    wrong[0, -1] = np.eye(4)

    def first_loss(frames, seed):
        logs = []
        refit.refit_gaussians(run, moved, order, labels, wrong, 1, frames=frames, seed=seed, log=logs.append)
        return float(logs[0].split("loss ")[1].split(" -> ")[0])

    # three draws each (drawn from all 8 frames, the last would be hit by all three with probability 1/512)
    assert max(first_loss(np.arange(t - 1), s) for s in range(3)) < 1e-3 < min(first_loss([t - 1], s) for s in range(3))
    for bad in ([t], [-1], []):
        with pytest.raises(ValueError, match="frames must be indices"):
            refit.refit_gaussians(run, moved, order, labels, wrong, 1, frames=bad, log=lambda m: None)


def test_refits_of_one_configuration_share_one_compiled_step(tiny):
    """Re-fits with the same step count, rate and scene (a hinge trial's candidates) under other poses and labels
    reuse `_posed_refit_step`'s compiled program: the poses, labels and images are its arguments, not constants.
    Another step count (another optimiser schedule) compiles once more. The poses still count: the re-fit under
    the wrong poses ends elsewhere."""
    run, labels, poses, moved, order = _sliding_part(tiny, 0.1)
    wrong = poses.copy()
    wrong[0, -1] = np.eye(4)
    quiet = lambda m: None
    refit.refit_gaussians(run, moved, order, labels, poses, 2, seed=5, log=quiet)
    n = refit._posed_refit_step._cache_size()
    a, _ = refit.refit_gaussians(run, moved, order, labels, poses, 2, seed=5, log=quiet)
    b, _ = refit.refit_gaussians(run, moved, order, np.where(labels == 0, 0, -1), wrong, 2, seed=5, log=quiet)
    assert refit._posed_refit_step._cache_size() == n
    assert not np.array_equal(np.asarray(a.means), np.asarray(b.means))
    refit.refit_gaussians(run, moved, order, labels, poses, 3, seed=5, log=quiet)
    assert refit._posed_refit_step._cache_size() == n + 1


def test_posed_losses_are_the_refits_loss_of_each_frame(tiny):
    """`posed_losses` renders each frame with the objects at their poses: ~0 on images made that way, and in a
    frame whose pose is wrong (the part left at rest) the same as the re-fit's first loss on that frame alone."""
    run, labels, poses, moved, order = _sliding_part(tiny, 0.1)
    t = poses.shape[1]
    ref = result.reference_scene(run, float(moved.times[order[0]]))
    assert refit.posed_losses(run, moved, order, ref, labels, poses, np.arange(t)).max() < 1e-3
    wrong = poses.copy()
    wrong[0, -1] = np.eye(4)
    got = refit.posed_losses(run, moved, order, ref, labels, wrong, [0, t - 1])
    logs = []
    refit.refit_gaussians(run, moved, order, labels, wrong, 1, frames=[t - 1], log=logs.append)
    assert got[0] < 1e-3 < got[1] and abs(got[1] - float(logs[0].split("loss ")[1].split(" -> ")[0])) < 1e-4


def _trial_setup(tiny):
    """(run, scene, order, reference, labels, given poses [1, T, 4, 4], candidates for a faked search) for
    `hinge_trial`: part 0 of `_sliding_part` turning 20 degrees about an axis 4 radii off it."""
    from fgjax.articulate.articulation import articulated_pose
    from fgjax.articulate.phototrack import hinge_offset

    run, labels, _, moved, order = _sliding_part(tiny, 0.1)
    ref = result.reference_scene(run, float(moved.times[order[0]]))
    pts = np.asarray(ref.means)[(labels == 0) & np.asarray(run.state.densify.alive)]
    c = pts.mean(0)
    r95 = np.percentile(np.linalg.norm(pts - c, axis=1), 95)
    t = len(order)
    far = c + np.array([0.0, 0.0, 4.0 * r95])

    def hinge(axis, pivot, top):
        return np.stack([np.asarray(articulated_pose(True, np.asarray(axis, float), pivot, a), np.float32)
                         for a in np.radians(np.linspace(0.0, top, t))])

    given = hinge([1.0, 0.0, 0.0], far, 20.0)[None]
    assert abs(hinge_offset(pts, [1.0, 0.0, 0.0], far)[1] - 4.0) < 1e-6
    edges = [([0.0, 1.0, 0.0], c + [0.05, 0, 0], 60.0), ([0.0, 1.0, 0.0], c - [0.05, 0, 0], 50.0),
             ([0.0, 0.0, 1.0], c + [0.05, 0, 0], 30.0), ([0.0, 0.0, 1.0], c - [0.05, 0, 0], 40.0)]
    cands = {h: ("revolute", np.array(a), p, hinge(a, p, top)) for h, (a, p, top) in enumerate(edges)}
    return run, moved, order, ref, labels, given, cands, pts


def test_hinge_trial_replaces_a_far_hinge_by_the_candidate_whose_refit_renders_closest(tiny, monkeypatch):
    """`hinge_trial` with the search and the re-fits faked: it searches the four `rect_hinges` of the part's alive
    members (no fitted joint, no screening, no replacing), re-fits from the reference under each candidate (the
    given poses first) for ``hinge_trial`` steps on the frames some candidate displaces the part in, and takes the
    lowest re-fitted loss when it beats the given poses' by the margin; within the margin, or for a near hinge, a
    small turn, a slide or an object left out, the poses stay (no search for the last four)."""
    from fgjax.articulate import articulation
    from fgjax.articulate.phototrack import hinge_offset

    run, scene, order, ref, labels, given, cands, pts = _trial_setup(tiny)
    t = given.shape[1]
    seen = {}

    searched = {}  # the searched slides' poses (hinge_trial_search_slides): -4 the chord's, -5 the snapped one's
    edge_scores = [0.5, 0.5, 0.5, 0.5]

    def fake_search(gaussians, alive, labels_, k_, images, vms, Ks, poses, **kw):
        seen["search"] = kw
        seen["labels"] = labels_
        seen["poses"] = kw["fitted_poses"]
        assert np.asarray(gaussians.means).shape == np.asarray(ref.means).shape
        np.testing.assert_array_equal(poses, given)  # the displaced frames and the edges' searches: the given poses'
        if kw["kinds"] == ["none"]:
            assert kw["fitted_poses"] is None
            return poses, [dict(candidates=cands, frames=t - 1, score_given=1.0, fitted_hypothesis=False,
                                scores=dict(enumerate(edge_scores)))]
        # the chord's slide as the fitted joint, first; the edges; the snapped slide last
        assert kw["kinds"] == ["prismatic"] and len(kw["hypotheses"][0]) == 5
        ax5 = kw["hypotheses"][0][4][1]
        found = {0: ("prismatic", slide_axis, np.zeros(3), searched[-4]),
                 **{h + 1: c for h, c in cands.items()}, 5: ("prismatic", ax5, np.zeros(3), searched[-5])}
        return poses, [dict(candidates=found, frames=t - 1, score_given=1.0, fitted_hypothesis=True,
                            scores={0: 0.4, **{h + 1: v for h, v in enumerate(edge_scores)}, 5: 0.4})]

    refits = []

    def fake_refit(run_, scene_, order_, labels_, poses, steps, *, init=None, frames=None, **kw):
        refits.append((poses[0].copy(), steps, None if frames is None else list(frames)))
        assert init is ref
        return init, labels_

    loss_of = {-1: 1.0, -2: 1.1, -3: 1.15, 0: 0.9, 1: 0.5, 2: 0.7, 3: 0.8}
    slide_axis, _ = articulation.slide_from_poses(pts.astype(np.float64), given[0])
    snap_axis, _ = articulation.slide_from_poses(pts.astype(np.float64), given[0], snap=True)
    # the setup's chord runs well off the part's principal axes, so the snapped slide is tried too
    assert abs(slide_axis @ snap_axis) < np.cos(np.radians(2.0))

    def fake_losses(run_, scene_, order_, gs, labels_, poses, frames):
        for h, pk in [(-1, given[0])] + [(h, c[3]) for h, c in cands.items()] + list(searched.items()):
            if np.array_equal(poses[0], pk):
                return np.full(len(frames), loss_of[h])
        # a slide: no turn; the given poses' chord, or along the part's principal axis nearest it
        np.testing.assert_array_equal(poses[0][:, :3, :3], np.broadcast_to(np.eye(3), (t, 3, 3)))
        members = np.asarray(ref.means, np.float64)[(labels_ == 0) & np.asarray(run.state.densify.alive)]
        for h, snap in ((-2, False), (-3, True)):
            ax, am = articulation.slide_from_poses(members, given[0], snap=snap)  # of the trial's labels
            if np.allclose(poses[0][:, :3, 3], am[:, None] * ax, atol=1e-6):
                return np.full(len(frames), loss_of[h])
        raise AssertionError("unknown poses")

    monkeypatch.setattr(trial, "search_articulations", fake_search)
    monkeypatch.setattr(trial, "refit_gaussians", fake_refit)
    monkeypatch.setattr(trial, "posed_losses", fake_losses)
    cfg = ArticulateConfig(hinge_trial=7, hinge_trial_race=1.0, colour_radius=0.0, hinge_trial_search_slides=False,
                           hinge_trial_edges=4)
    far = np.array([hinge_offset(pts, [1.0, 0.0, 0.0], pts.mean(0) + [0.0, 0.0, 1.0])[1]])
    far[0] = 4.0
    logs = []
    out, rec = trial.hinge_trial(run, scene, order, ref, labels, 1, given, ["revolute"], far, cfg, np.ones(1, bool),
                                   log=logs.append)
    np.testing.assert_array_equal(out[0], cands[1][3])
    kw = seen["search"]
    assert not kw["replace"] and kw["keep"] >= 4 and list(kw["objects"]) == [True] and kw["kinds"] == ["none"]
    hyps = kw["hypotheses"][0]
    assert len(hyps) == 4 and all(h[0] == "revolute" for h in hyps)  # rect_hinges of the part's alive members
    assert len(refits) == 7 and all(s == 7 for _, s, _ in refits)
    np.testing.assert_array_equal(refits[0][0], given[0])
    assert all(f == list(range(1, t)) for *_, f in refits)  # frame 0 is at rest under every candidate
    r = rec[0]
    assert r["replaced"] and r["given_loss"] == 1.0 and r["kind"] == "revolute"
    assert [c["hypothesis"] for c in r["candidates"]] == [-1, -2, -3, 0, 1, 2, 3]
    assert [c["kind"] for c in r["candidates"]] == ["revolute", "prismatic", "prismatic"] + ["revolute"] * 4
    assert [c["loss"] for c in r["candidates"]] == pytest.approx([1.0, 1.1, 1.15, 0.9, 0.5, 0.7, 0.8])
    assert r["frames"] == t - 1
    assert r["axis"] == [0.0, 1.0, 0.0] and abs(r["offset"] - hinge_offset(pts, [0, 1, 0], cands[1][2])[1]) < 1e-9
    json.dumps(r)  # written to stage2.json as it is
    assert any("replaced by the edge 1" in m for m in logs), logs
    # within the margin: kept
    loss_of.update({-2: 1.05, -3: 1.03, 0: 0.99, 1: 0.985, 2: 0.995, 3: 1.2})
    refits.clear()
    out, rec = trial.hinge_trial(run, scene, order, ref, labels, 1, given, ["revolute"], far, cfg, np.ones(1, bool),
                                   log=logs.append)
    np.testing.assert_array_equal(out, given)
    assert not rec[0]["replaced"] and rec[0]["axis"] is None and rec[0]["offset"] is None and rec[0]["kind"] is None
    # the best slide within the margin of the given poses, or an edge that beats them but not that slide: the slide
    for update, axis in (({-2: 1.01}, slide_axis), ({-2: 0.4, 1: 0.5}, slide_axis), ({-3: 0.3}, snap_axis)):
        loss_of.update(update)
        out, rec = trial.hinge_trial(run, scene, order, ref, labels, 1, given, ["revolute"], far, cfg,
                                       np.ones(1, bool), log=logs.append)
        r = rec[0]
        assert r["replaced"] and r["kind"] == "prismatic" and r["offset"] is None
        np.testing.assert_allclose(r["axis"], axis, atol=1e-12)
        np.testing.assert_array_equal(out[0][:, :3, :3], np.broadcast_to(np.eye(3), (t, 3, 3)))
        json.dumps(r)
    assert any("replaced by the slide, axis" in m for m in logs), logs
    assert any("replaced by the slide along a principal axis" in m for m in logs), logs
    # without ``hinge_trial_slide``: no slide is tried
    refits.clear()
    out, rec = trial.hinge_trial(run, scene, order, ref, labels, 1, given, ["revolute"], far,
                                   ArticulateConfig(hinge_trial=7, hinge_trial_race=1.0, colour_radius=0.0,
                                                       hinge_trial_slide=False, hinge_trial_edges=4),
                                   np.ones(1, bool), log=logs.append)
    assert len(refits) == 5 and [c["hypothesis"] for c in rec[0]["candidates"]] == [-1, 0, 1, 2, 3]
    np.testing.assert_array_equal(out[0], cands[1][3])
    loss_of.update({-2: 1.1, -3: 1.15, 1: 0.985})
    # ``hinge_trial_edges``: only the edges the search scores best are re-fitted; ``hinge_trial_search_slides``: the
    # search also takes the chord's slide as its fitted joint (its poses, first) and the snapped slide as a
    # hypothesis after the edges, and their searched poses are two more candidates (-4, -5)
    for h, ax in ((-4, slide_axis), (-5, snap_axis)):
        searched[h] = np.tile(np.eye(4, dtype=np.float32), (t, 1, 1))
        searched[h][:, :3, 3] = np.linspace(0.0, 0.3 if h == -4 else 0.2, t)[:, None] * ax
    edge_scores[:] = [0.6, 0.3, 0.7, 0.2]
    loss_of.update({-4: 0.45, -5: 0.6, 1: 0.5})
    refits.clear()
    out, rec = trial.hinge_trial(run, scene, order, ref, labels, 1, given, ["revolute"], far,
                                   ArticulateConfig(hinge_trial=7, hinge_trial_race=1.0, colour_radius=0.0,
                                                       hinge_trial_edges=2, hinge_trial_search_slides=True),
                                   np.ones(1, bool), log=logs.append)
    assert [c["hypothesis"] for c in rec[0]["candidates"]] == [-1, -2, -3, -4, -5, 1, 3] and len(refits) == 7
    np.testing.assert_array_equal(seen["poses"][0][:, :3, :3], np.broadcast_to(np.eye(3), (t, 3, 3)))  # the chord's
    np.testing.assert_allclose(seen["poses"][0][:, :3, 3], np.asarray(
        articulation.slide_from_poses(pts.astype(np.float64), given[0])[1])[:, None] * slide_axis, atol=1e-6)
    np.testing.assert_allclose(seen["search"]["hypotheses"][0][4][1], snap_axis, atol=1e-12)
    assert rec[0]["replaced"] and rec[0]["kind"] == "prismatic"
    np.testing.assert_array_equal(out[0], searched[-4])
    assert any("its amounts searched" in m for m in logs) and any("re-fitting edges [1, 3]" in m for m in logs)
    # a searched slide with the poses of another candidate (its search kept every amount) is not re-fitted again
    chord = np.tile(np.eye(4, dtype=np.float32), (t, 1, 1))
    chord[:, :3, 3] = np.asarray(articulation.slide_from_poses(
        pts.astype(np.float64), given[0])[1])[:, None] * slide_axis + 4e-7
    searched[-4] = chord
    refits.clear()
    out, rec = trial.hinge_trial(run, scene, order, ref, labels, 1, given, ["revolute"], far,
                                   ArticulateConfig(hinge_trial=7, hinge_trial_race=1.0, colour_radius=0.0,
                                                       hinge_trial_edges=2, hinge_trial_search_slides=True),
                                   np.ones(1, bool), log=logs.append)
    assert len(refits) == 6 and rec[0]["candidates"][3]["loss"] == rec[0]["candidates"][1]["loss"]
    assert any("the poses of the slide, axis" in m for m in logs)
    edge_scores[:] = [0.5, 0.5, 0.5, 0.5]
    # a near hinge, no turn, a slide, no offset, an object left out: no trial
    still = given.copy()
    still[0, :, :3, :3] = np.eye(3)
    for poses, kinds, off, objects in ((given, ["revolute"], np.array([1.5]), np.ones(1, bool)),
                                       (still, ["revolute"], far, np.ones(1, bool)),
                                       (given, ["prismatic"], far, np.ones(1, bool)),
                                       (given, ["revolute"], np.array([np.nan]), np.ones(1, bool)),
                                       (given, ["revolute"], far, np.zeros(1, bool))):
        seen.clear()
        out, rec = trial.hinge_trial(run, scene, order, ref, labels, 1, poses, kinds, off, cfg, objects,
                                       log=logs.append)
        assert rec == {} and "search" not in seen
        np.testing.assert_array_equal(out, poses)
    # with ``colour_radius`` on, the search and every re-fit see the labels relabelled by colour on the reference
    # (once for all the objects tried); the labels the pipeline goes on with are not changed
    recoloured = np.where(labels == 0, -1, labels)
    recoloured[np.flatnonzero(labels == 0)[::2]] = 0  # half the part
    coloured = []
    monkeypatch.setattr(trial, "refine_by_colour", lambda lab, gs, alive, cfg_, seed, log=print: coloured.append(gs)
                        or (recoloured, []))
    labels_seen = []
    monkeypatch.setattr(trial, "refit_gaussians", lambda run_, sc_, o_, lab, *a, init=None, **k: labels_seen.append(lab)
                        or (init, lab))
    loss_of.update({1: 0.5})
    trial.hinge_trial(run, scene, order, ref, labels, 1, given, ["revolute"], far,
                        ArticulateConfig(hinge_trial=7, hinge_trial_race=1.0, hinge_trial_search_slides=False,
                                         hinge_trial_edges=4, colour_radius=0.08),
                        np.ones(1, bool), log=logs.append)
    assert len(coloured) == 1 and coloured[0] is ref and len(labels_seen) in (6, 7)  # the snapped slide may run
    assert all(lab is recoloured for lab in labels_seen)
    hyps = seen["search"]["hypotheses"][0]
    np.testing.assert_allclose(hyps[0][1], articulation.rect_hinges(
        np.asarray(ref.means)[(recoloured == 0) & np.asarray(run.state.densify.alive)])[0][1])


def test_hinge_trial_races_its_candidates_and_chooses_by_the_finalists_full_refits(tiny, monkeypatch):
    """``hinge_trial_race``: every candidate is re-fitted from the reference for that share of the steps; the given
    poses, the best slide and the best edge then go on from their own re-fits for the rest, and the choice is made
    on those finalists' losses (here the given poses overtake the edge that led the first round)."""
    from fgjax.articulate import articulation

    run, scene, order, ref, labels, given, cands, pts = _trial_setup(tiny)
    t = given.shape[1]

    def fake_search(gaussians, alive, labels_, k_, images, vms, Ks, poses, **kw):
        return poses, [dict(candidates=cands, frames=t - 1, score_given=1.0, fitted_hypothesis=False,
                            scores=dict(enumerate([0.5] * 4)))]

    def which(poses):
        for h, pk in [(-1, given[0])] + [(h, c[3]) for h, c in cands.items()]:
            if np.array_equal(poses[0], pk):
                return h
        members = np.asarray(ref.means, np.float64)[(labels == 0) & np.asarray(run.state.densify.alive)]
        for h, snap in ((-2, False), (-3, True)):
            ax, am = articulation.slide_from_poses(members, given[0], snap=snap)
            if np.allclose(poses[0][:, :3, 3], am[:, None] * ax, atol=1e-6):
                return h
        raise AssertionError("unknown poses")

    refits = []

    def fake_refit(run_, scene_, order_, labels_, poses, steps, *, init=None, frames=None, **kw):
        h = which(poses)
        before = 0 if init is ref else init["steps"]
        assert init is ref or init["h"] == h  # round 2 goes on from the candidate's own re-fit
        refits.append((h, steps, before))
        return {"h": h, "steps": before + steps}, labels_

    first = {-1: 1.0, -2: 1.1, -3: 1.15, 0: 0.9, 1: 0.5, 2: 0.7, 3: 0.8}  # after 3 steps
    full = {-1: 0.3, -2: 0.9, 1: 0.45}  # after all 7: the given poses now render closest

    def fake_losses(run_, scene_, order_, gs, labels_, poses, frames):
        return np.full(len(frames), (first if gs["steps"] == 3 else full)[gs["h"]])

    monkeypatch.setattr(trial, "search_articulations", fake_search)
    monkeypatch.setattr(trial, "refit_gaussians", fake_refit)
    monkeypatch.setattr(trial, "posed_losses", fake_losses)
    cfg = ArticulateConfig(hinge_trial=7, hinge_trial_race=3 / 7, colour_radius=0.0, hinge_trial_search_slides=False,
                           hinge_trial_edges=4)
    out, rec = trial.hinge_trial(run, scene, order, ref, labels, 1, given, ["revolute"],
                                 np.array([4.0]), cfg, np.ones(1, bool), log=lambda *a: None)
    assert sorted(refits[:7]) == sorted((h, 3, 0) for h in (-1, -2, -3, 0, 1, 2, 3))
    assert sorted(refits[7:]) == [(-2, 4, 3), (-1, 4, 3), (1, 4, 3)]  # the finalists, from their own re-fits
    np.testing.assert_array_equal(out, given)  # kept: the full re-fits decide, not the first round
    r = rec[0]
    assert not r["replaced"] and r["given_loss"] == 0.3
    steps = {c["hypothesis"]: c["steps"] for c in r["candidates"]}
    assert steps == {-1: 7, -2: 7, -3: 3, 0: 3, 1: 7, 2: 3, 3: 3}
    assert {c["hypothesis"]: c["loss"] for c in r["candidates"]} == pytest.approx(
        {-1: 0.3, -2: 0.9, -3: 1.15, 0: 0.9, 1: 0.45, 2: 0.7, 3: 0.8})
    # with the edge still ahead after all the steps, it replaces the far hinge
    full[1], refits[:] = 0.1, []
    out, rec = trial.hinge_trial(run, scene, order, ref, labels, 1, given, ["revolute"], np.array([4.0]), cfg,
                                 np.ones(1, bool), log=lambda *a: None)
    np.testing.assert_array_equal(out[0], cands[1][3])
    assert rec[0]["replaced"] and len(refits) == 10


def test_trial_choice_takes_an_edge_by_the_margin_and_the_slide_within_it():
    """`trial_choice`: an edge must beat the given poses by the margin and be no worse than the slide; the slide
    wins when within (1 + margin) of the given poses; else the given poses (0). Infinite losses (an overflowing
    render) never win; NaN or a list without the given poses first is refused."""
    m = 0.02
    assert trial.trial_choice([-1, -2, 0, 1], [1.0, 1.1, 0.9, 0.97], m) == 2
    assert trial.trial_choice([-1, -2, 0, 1], [1.0, 1.1, 0.99, 0.985], m) == 0
    assert trial.trial_choice([-1, -2, 0, 1], [1.0, 1.019, 0.99, 0.985], m) == 1
    assert trial.trial_choice([-1, -2, 0, 1], [1.0, 0.85, 0.9, 0.95], m) == 1  # the slide beats the best edge
    assert trial.trial_choice([-1, -2, -3, 0], [1.0, 0.86, 0.85, 0.9], m) == 2  # the better of two slides
    assert trial.trial_choice([-1, -2, -3, 0], [1.0, 1.5, 0.88, 0.87], m) == 3  # the best slide is what counts
    assert trial.trial_choice([-1, -2, 0], [1.0, 0.9, 0.9], m) == 2  # a tie with the slide goes to the edge
    assert trial.trial_choice([-1, 0, 1], [1.0, 0.99, 0.5], m) == 2
    assert trial.trial_choice([-1, 0, 1], [1.0, 0.99, 0.985], m) == 0
    assert trial.trial_choice([-1, -2], [1.0, 1.0], 0.0) == 1
    assert trial.trial_choice([-1, -2, 0], [1.0, np.inf, np.inf], m) == 0
    assert trial.trial_choice([-1, -2, 0], [np.inf, 2.0, np.inf], m) == 1  # an overflowing given render loses
    for hyps, losses in (([-1, 0], [1.0, np.nan]), ([0, -1], [1.0, 0.5])):
        with pytest.raises(ValueError, match="trial_choice"):
            trial.trial_choice(hyps, losses, m)


def test_trial_slides_offer_the_chord_and_the_principal_axis_unless_they_agree():
    """`trial_slides`: poses that slide a slab along its longest side give the chord alone (the principal axis
    agrees with it); a turn about a far line gives the chord and the slab's nearest principal axis as well, each
    with no turn and the chord's shifts along its axis; poses that never move it give none."""
    from fgjax.articulate.articulation import articulated_pose

    g = np.meshgrid(np.linspace(-1.0, 1.0, 11), np.linspace(-0.4, 0.4, 5), np.linspace(-0.1, 0.1, 3), indexing="ij")
    pts = np.stack([x.ravel() for x in g], 1)  # a slab on a grid: its principal axes are x (longest), y, z exactly
    amounts = np.linspace(0.0, 0.6, 7)
    slide = np.stack([np.asarray(articulated_pose(False, np.array([1.0, 0.0, 0.0]), np.zeros(3), a), np.float64)
                      for a in amounts])
    got = trial.trial_slides(pts, slide)
    assert [c[0] for c in got] == [-2] and got[0][1] == "prismatic"
    np.testing.assert_allclose(got[0][2], [1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(got[0][4][:, :3, 3], slide[:, :3, 3], atol=1e-6)
    turn = np.stack([np.asarray(articulated_pose(True, np.array([0.0, 0.0, 1.0]), np.array([0.0, -6.0, 0.0]), a),
                                np.float64) for a in np.radians(np.linspace(0.0, 25.0, 7))])
    got = trial.trial_slides(pts, turn)
    assert [c[0] for c in got] == [-2, -3]
    assert abs(got[1][2][0]) > 0.999  # the slab's longest side; the chord of a 25-degree arc is 12.5 degrees off it
    for _, kind, axis, pivot, pk in got:
        assert kind == "prismatic" and np.array_equal(pivot, np.zeros(3))
        np.testing.assert_array_equal(pk[:, :3, :3], np.broadcast_to(np.eye(3), (7, 3, 3)))
        np.testing.assert_allclose(pk[:, :3, 3] @ axis, np.linalg.norm(pk[:, :3, 3], axis=1), rtol=1e-5, atol=1e-7)
    assert trial.trial_slides(pts, np.tile(np.eye(4), (4, 1, 1))) == []


def test_trial_held_objects_are_those_a_trial_replaced_in_any_round():
    hist = [{"joint_kinds": ["revolute"] * 3}, {"hinge_trials": [None, {"replaced": False}, {"replaced": True}]},
            {"hinge_trials": [{"replaced": True}, None, None]}]
    np.testing.assert_array_equal(trial.trial_held(hist, 3), [True, False, True])
    np.testing.assert_array_equal(trial.trial_held(hist[:1], 3), [False, False, False])


def test_photometric_poses_runs_the_hinge_trial_and_records_it(tiny, monkeypatch):
    """With ``hinge_trial`` > 0 (the default), `photometric_poses` hands the joint fit's kinds and offsets and the
    scene it tracked to `hinge_trial` and takes its poses; a replaced joint's kind, axis and offset follow the trial
    and its record is kept; off, no trial runs and the record is None."""
    from fgjax.articulate import phototrack

    run, scene, order, ref, labels, given, cands, pts = _trial_setup(tiny)
    monkeypatch.setattr(AP, "track_photometric", lambda *a, **k: (given.copy(), None))
    monkeypatch.setattr(AP, "joint_poses", lambda pts_, poses, *a, **k: (
        poses, ["revolute"], np.array([0.5]), np.array([[1.0, 0.0, 0.0]]), np.array([4.0])))
    calls, refs = [], []
    chosen = {"replaced": True, "kind": "revolute", "axis": [0.0, 1.0, 0.0], "offset": 0.3}

    def fake_trial(run_, scene_, order_, ref_, labels_, k_, poses, kinds, offsets, cfg, objects, seed, log):
        calls.append((list(kinds), list(offsets), list(objects)))
        refs.append(ref_)
        out = poses.copy()
        out[0] = cands[1][3]
        return out, {0: dict(chosen)}

    monkeypatch.setattr(AP, "hinge_trial", fake_trial)
    poses, joints = AP.photometric_poses(run, scene, order, ref, labels, 1, ArticulateConfig(hinge_trial=5),
                                              None, log=lambda m: None)
    assert calls == [(["revolute"], [4.0], [True])] and refs == [ref]  # the scene the round tracked
    np.testing.assert_array_equal(poses[0], cands[1][3])
    assert joints["joint_axes"] == [[0.0, 1.0, 0.0]] and joints["joint_hinge_offsets"] == [0.3]
    assert joints["hinge_trials"][0]["replaced"] and joints["joint_kinds"] == ["revolute"]
    chosen.update(kind="prismatic", axis=[0.0, 0.0, 1.0], offset=None)  # the slide: no hinge offset
    poses, joints = AP.photometric_poses(run, scene, order, ref, labels, 1, ArticulateConfig(hinge_trial=5),
                                              None, log=lambda m: None)
    assert joints["joint_kinds"] == ["prismatic"] and joints["joint_axes"] == [[0.0, 0.0, 1.0]]
    assert joints["joint_hinge_offsets"] == [None]
    calls.clear()
    refs.clear()
    poses, joints = AP.photometric_poses(run, scene, order, ref, labels, 1, ArticulateConfig(hinge_trial=0),
                                              None, log=lambda m: None)
    defaults = ArticulateConfig()
    assert defaults.hinge_trial == 150 and defaults.hinge_trial_search_slides and defaults.hinge_trial_edges == 2
    assert defaults.hinge_up_deg == 25.0
    assert calls == [] and joints["hinge_trials"] == [None] and joints["joint_hinge_offsets"] == [4.0]
    np.testing.assert_array_equal(poses, given)
    assert refs == []
    # ``hinge_up_deg``: each round's revolute joint goes through `hinge_made_vertical` with the cameras' up
    from fgjax.articulate import articulation

    seen = {}

    def fake_vertical(points, poses_k, up, max_deg):
        seen.update(n=len(points), up=np.asarray(up), max_deg=max_deg)
        return cands[1][3], np.array([0.0, 0.0, 1.0]), 7.0

    monkeypatch.setattr(AP, "hinge_made_vertical", fake_vertical)
    far = AP.joint_poses  # the fake above: a hinge 4 radii off its part
    monkeypatch.setattr(AP, "joint_poses", lambda pts_, poses, *a, **k: (
        poses, ["revolute"], np.array([0.5]), np.array([[1.0, 0.0, 0.0]]), np.array([0.5])))
    logs = []
    poses, joints = AP.photometric_poses(run, scene, order, ref, labels, 1,
                                              ArticulateConfig(hinge_trial=0, hinge_up_deg=25.0), None,
                                              log=logs.append)
    np.testing.assert_array_equal(poses[0], cands[1][3])
    assert joints["joint_axes"] == [[0.0, 0.0, 1.0]] and seen["max_deg"] == 25.0
    assert seen["n"] == int(np.sum((labels == 0) & np.asarray(run.state.densify.alive)))
    np.testing.assert_allclose(seen["up"], articulation.camera_up(scene.viewmats[order]), atol=1e-12)
    assert any("made vertical" in m for m in logs)
    # cameras not held level (or an up they do not fix): hinges kept as tracked, and the log says why
    monkeypatch.setattr(AP, "camera_tilt", lambda vms: (articulation.LEVEL_TILT_DEG + 0.5, 0.01))
    seen.clear()
    logs = []
    poses, joints = AP.photometric_poses(run, scene, order, ref, labels, 1,
                                              ArticulateConfig(hinge_trial=0, hinge_up_deg=25.0), None,
                                              log=logs.append)
    np.testing.assert_array_equal(poses, given)
    assert seen == {} and any("not trusted" in m and "tilt 2.50" in m for m in logs)
    # a far hinge (4 radii off its part while it turns 5 degrees or more): kept as tracked, for the hinge trial
    monkeypatch.undo()
    monkeypatch.setattr(AP, "track_photometric", lambda *a, **k: (given.copy(), None))
    monkeypatch.setattr(AP, "joint_poses", far)
    monkeypatch.setattr(AP, "hinge_made_vertical", fake_vertical)
    assert phototrack.is_far_hinge(4.0, phototrack.largest_turn_deg(given[0]))
    poses, joints = AP.photometric_poses(run, scene, order, ref, labels, 1,
                                              ArticulateConfig(hinge_trial=0, hinge_up_deg=25.0), None,
                                              log=lambda m: None)
    np.testing.assert_array_equal(poses, given)
    assert seen == {} and joints["joint_axes"] == [[1.0, 0.0, 0.0]]


def test_refit_is_saved_and_the_controlled_scene_starts_from_it(tiny, tmp_path):
    import shutil

    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization
    from fgjax.gaussians import Gaussians

    dst = tmp_path / "run"
    shutil.copytree(tiny[0], dst)
    run = result.load_stage2(dst)
    g = run.state.params["gaussians"]
    m0, q0, ls0 = run.deformed(run.s2.t0)
    refit = Gaussians(np.asarray(m0) + 0.01, np.asarray(ls0), np.asarray(q0), np.asarray(g.opacity_logits) - 0.5,
                      np.asarray(g.sh) * 0.9)
    s2 = run.s2
    result.save_stage2(dst, result.Stage2Result(s2.labels, s2.dynamic, s2.scores, s2.traj, s2.traj_times, s2.control,
                                                s2.meta, refit))
    back = result.load_stage2(dst)
    for f in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_allclose(getattr(back.s2.refit, f), getattr(refit, f), rtol=1e-6)
    sc = load_scene(tiny[1], "train", normalize=Normalization.from_dict(run.meta["normalization"]))
    k = max(back.s2.num_objects, 1)
    img = result.render_controlled(back, np.zeros((k, 3)), sc.viewmats[0], sc.Ks[0], sc.width, sc.height)
    ref = np.asarray(back.render_geometry(*(np.asarray(x) for x in (refit.means, refit.quats, refit.log_scales)),
                                          sc.viewmats[0], sc.Ks[0], sc.width, sc.height,
                                          params=back.control_params())[0])
    np.testing.assert_allclose(img, np.clip(ref, 0, 1), atol=1e-5)
    stage1 = result.render_controlled(run, np.zeros((k, 3)), sc.viewmats[0], sc.Ks[0], sc.width, sc.height)
    assert np.abs(img - stage1).max() > 1e-3  # it is not the stage-1 scene


def test_refit_relabelling_returns_mislabelled_gaussians_to_their_part(tiny):
    """Images made with a part moved by known poses; the labels given to the re-fit have part Gaussians
    marked static and static Gaussians marked as the part. The relabelling phase (both copies rendered,
    the photometric loss keeps one) moves most of them back; without it the labels come back unchanged."""
    run, labels, poses, moved, order = _sliding_part(tiny, 0.15)
    alive = np.asarray(run.state.densify.alive)
    m0 = np.asarray(run.state.params["gaussians"].means)
    rng = np.random.default_rng(0)
    seen = alive
    flip = seen & (rng.random(len(labels)) < 0.25)
    wrong = np.where(flip, np.where(labels == 0, -1, 0), labels)
    radius = float(np.ptp(m0[alive], 0).max())  # every Gaussian is a candidate
    kept, same = refit.refit_gaussians(run, moved, order, wrong, poses, 2, log=lambda m: None)
    np.testing.assert_array_equal(same, wrong)
    logs = []
    _, new = refit.refit_gaussians(run, moved, order, wrong, poses, 80, relabel_steps=80, relabel_radius=radius,
                                    relabel_lr=0.3, log=logs.append)
    assert any("relabelled by motion" in m for m in logs), logs
    before = np.mean(wrong[flip] == labels[flip])  # 0
    after = np.mean(new[flip] == labels[flip])
    kept_right = np.mean(new[seen & ~flip] == labels[seen & ~flip])
    assert before == 0.0 and after > 0.6 and kept_right > 0.9, (after, kept_right)


@pytest.mark.optimized  # run-time-bound: photometric tracking
def test_stage2_with_photometric_tracking_writes_joint_poses(tiny, tmp_path, monkeypatch):
    """`track_photo` replaces the flow-based tracking: the log shows the photometric fit, one articulation
    per object and the re-fit, and the result is written; `track_only_moving`, `track_subset_margin` and the steps
    per blur level reach the tracker, and `track_photo_next` only a later round's; negative step counts and zero
    rounds are refused. (Rounds: `test_track_rounds_track_again_from_the_last_refit`.)"""
    import shutil

    from fgjax.articulate import phototrack

    dst = tmp_path / "run"
    shutil.copytree(tiny[0], dst)
    logs, seen = [], []
    real = phototrack.track_photometric
    monkeypatch.setattr(AP, "track_photometric",
                        lambda *a, **k: seen.append((k["only_moving"], k["subset_margin"], k["steps"], k["rest_check"]))
                        or real(*a, **k))
    from fgjax.config import Config, apply_overrides

    cfg = apply_overrides(Config(), ["stage2.auto_eps=true", "stage2.distill_steps=5", "stage2.photo_steps=2",
                                     "articulate.refit_steps=4", "articulate.track_photo=5",
                                     "articulate.track_only_moving=false", "articulate.track_subset_margin=3",
                                     "articulate.track_photo_next=3", "articulate.track_rounds=1",
                                     "articulate.track_rest=true", "articulate.hull_fill=true",
                                     "articulate.hinge_fill=true"])
    res = run_articulated(dst, tiny[1], cfg.stage2, cfg.articulate, log=logs.append)
    defaults = ArticulateConfig()
    assert seen == [(False, 3, (2, 2, 1), True)] and defaults.track_only_moving
    assert defaults.track_rest and defaults.track_subset_margin == 2
    assert res.num_objects > 0, logs
    assert sum(m.startswith("photometric tracking:") and "frames fitted" in m for m in logs) == 1, logs
    assert sum("-> revolute" in m or "-> prismatic" in m for m in logs) == res.num_objects, logs
    # one round's re-fit, then the hull fill's (`hull_fill`, turned on above) with its own step count
    assert sum(m.startswith("stage 2: re-fitted the Gaussians") for m in logs) == 2, logs
    assert any("inside the hulls" in m for m in logs) and any("re-fitted" in m and "100 steps" in m for m in logs), logs
    assert sum("along the hinges" in m for m in logs) == 1, logs  # `hinge_fill` shares that re-fit
    assert not any("round 2" in m for m in logs), logs
    # `ghost_radius` (0.03 by default): the round's re-fit, not the hull fill's, starts with the static
    # Gaussians by the parts' swept volume faded
    assert defaults.ghost_radius == 0.03
    assert sum("swept volume faded" in m and "(within" not in m and "within 0.03)" in m for m in logs) == 1, logs
    # numbers in the log are rounded for reading (the distillation's first loss was once printed to 17 digits)
    assert not [m for m in logs if m.startswith("stage 2:") and re.search(r"\d\.\d{7,}", m)], logs
    assert np.all(np.isfinite(res.traj)) and res.refit is not None
    meta = result.load_stage2(dst).s2.meta
    assert meta["variant"] == "articulated" and meta["articulate"]["track_photo"] == 5
    assert len(meta["joint_kinds"]) == len(meta["joint_costs"]) == len(meta["joint_axes"]) == res.num_objects, meta
    assert all(a is None or abs(np.linalg.norm(a) - 1.0) < 1e-6 for a in meta["joint_axes"]), meta["joint_axes"]
    # a hinge's axis offset from its part's centre (radii) is recorded, and only for hinges
    assert len(meta["joint_hinge_offsets"]) == res.num_objects and all(
        (r is None) == (k != "revolute") and (r is None or r >= 0)
        for k, r in zip(meta["joint_kinds"], meta["joint_hinge_offsets"])), meta
    assert all(k in ("revolute", "prismatic") and c >= 0 for k, c in zip(meta["joint_kinds"], meta["joint_costs"]))
    assert len(meta["hull_joined"]) == len(meta["hinge_joined"]) == len(meta["hinges"]) == res.num_objects, meta
    assert all(h is None or (h["angle_deg"] >= 20 and abs(np.linalg.norm(h["axis"]) - 1) < 1e-6)
               for h in meta["hinges"])
    for bad, field in (({"track_photo": -1}, "track_photo"), ({"track_photo_next": -1}, "track_photo_next"),
                       ({"track_rounds": 0}, "track_rounds"), ({"track_converged_deg": -1.0}, "track_converged_deg"),
                       ({"track_converged_deg": float("nan")}, "track_converged_deg"),
                       ({"hull_opacity": 1.5}, "hull_opacity"), ({"hull_refit_steps": -1}, "hull_refit_steps"),
                       ({"hull_max_growth": float("nan")}, "hull_max_growth"),
                       ({"hinge_radius": -0.1}, "hinge_radius"), ({"hinge_reach": float("inf")}, "hinge_reach"),
                       ({"hinge_min_deg": 0.0}, "hinge_min_deg"), ({"hinge_min_deg": 200.0}, "hinge_min_deg")):
        with pytest.raises(ValueError, match=field):
            run_articulated(dst, tiny[1], Stage2Config(), ArticulateConfig(**bad), log=logs.append)
    # rounds without photometric tracking: said, not silently ignored (stopped before any work by a missing run)
    with pytest.raises(FileNotFoundError):
        run_articulated(tmp_path / "none", tiny[1], Stage2Config(), ArticulateConfig(track_rounds=2, track_photo=0),
                        log=logs.append)
    assert any("track_rounds=2 has no effect" in m for m in logs), logs


def test_track_rounds_track_again_from_the_last_refit(tiny, tmp_path, monkeypatch):
    """``track_rounds=2``: round 2 tracks again rendering round 1's re-fit and starting from round 1's poses,
    and its re-fit continues from round 1's (with the next seed); the last re-fit is the one kept. The
    tracking and the re-fit are replaced by recorders (the real ones: the test above and
    tests/test_phototrack.py), so this checks the wiring in seconds."""
    import shutil

    import jax

    dst = tmp_path / "run"
    shutil.copytree(tiny[0], dst)
    calls = []

    def fake_track(run, scene, order, ref, labels, k, cfg, moving, log=print, init_poses=None, fixed=None,
                   prev_joints=None, seed=0):
        assert fixed is None  # two rounds: no convergence test (`test_later_rounds_track_only_...`)
        poses = np.tile(np.eye(4, dtype=np.float32), (k, len(order), 1, 1))
        poses[:, :, 0, 3] = 0.01 * (len(calls) + 1)  # each call's poses told apart by their shift
        calls.append(("track", ref, init_poses, poses))
        return poses, {"joint_kinds": ["revolute"] * k, "joint_costs": [float(len(calls))] * k}

    def fake_refit(run, scene, order, labels, poses, steps, *, seed=0, relabel_steps=0, relabel_radius=0.1,
                   init=None, lr_scale=1.0, log=print):
        out = jax.tree_util.tree_map(lambda a: a + 0, init)  # a new object, told apart from `init`
        calls.append(("refit", init, poses, seed, out))
        return out, labels

    monkeypatch.setattr(AP, "photometric_poses", fake_track)
    monkeypatch.setattr(AP, "refit_gaussians", fake_refit)
    logs = []
    cfg = _cfgs(auto_eps=True, distill_steps=2, photo_steps=0, refit_steps=4, track_photo=5,
                              track_rounds=2, seed=3, hull_fill=False,
                              hinge_fill=False, isolated_factor=0.0,  # (their re-fit: test_hull_and_hinge_...)
                              through_prune=0.0, colour_radius=0.0,
                              ghost_radius=0.0)  # (its fade makes a new start: test_stage2_with_photometric_...)
    res = run_articulated(dst, tiny[1], *cfg, log=logs.append)
    assert [c[0] for c in calls] == ["track", "refit", "track", "refit"], [c[0] for c in calls]
    (_, ref1, init1, poses1), (_, rinit1, rposes1, seed1, refit1) = calls[0], calls[1]
    (_, ref2, init2, poses2), (_, rinit2, rposes2, seed2, refit2) = calls[2], calls[3]
    assert init1 is None and rinit1 is ref1 and rposes1 is poses1 and seed1 == 3
    assert ref2 is refit1 and init2 is poses1  # round 2 renders round 1's re-fit, starts from its poses
    assert rinit2 is refit1 and rposes2 is poses2 and seed2 == 4
    np.testing.assert_allclose(np.asarray(res.refit.means), np.asarray(refit2.means))
    assert any("round 2 of 2" in m for m in logs), logs
    assert res.meta["joint_costs"] == [3.0] * res.num_objects  # the last round's joints are the ones kept


def _recording_refit(calls: list):
    """A stand-in for `refit.refit_gaussians` that records ("refit",) in ``calls`` and returns its start unchanged."""
    import jax

    def fake_refit(run, scene, order, labels, poses, steps, *, init=None, **kw):
        calls.append(("refit",))
        return jax.tree_util.tree_map(lambda a: a + 0, init), labels

    return fake_refit


def test_later_rounds_track_only_the_objects_whose_joint_has_not_converged(tiny, tmp_path, monkeypatch):
    """``track_rounds=4``: rounds 1 and 2 track every object; object 1's axis then turns by 40 degrees and the
    others' by 5, so round 3 tracks object 1 only (the others fixed, at round 2's poses); after round 3 no axis
    moved, so there is no round 4. With ``track_converged_deg=0`` every round tracks every object. Recorders
    replace the tracking and the re-fit (the real ones: tests/test_phototrack.py)."""
    import shutil

    def turned(deg):
        r = np.radians(deg)
        return [float(np.cos(r)), float(np.sin(r)), 0.0]

    for limit, want in ((20.0, 3), (0.0, 4)):
        dst = tmp_path / f"run{limit}"
        shutil.copytree(tiny[0], dst)
        calls = []

        def fake_track(run, scene, order, ref, labels, k, cfg, moving, log=print, init_poses=None, fixed=None,
                       prev_joints=None, seed=0):
            n = sum(c[0] == "track" for c in calls)
            poses = np.tile(np.eye(4, dtype=np.float32), (k, len(order), 1, 1))
            axes = [turned(0.0)] * k if n == 0 else [turned(40.0)] + [turned(5.0)] * (k - 1)
            calls.append(("track", None if fixed is None else np.asarray(fixed).copy(), init_poses))
            return poses, {"joint_kinds": ["revolute"] * k, "joint_costs": [1.0] * k, "joint_axes": axes}

        monkeypatch.setattr(AP, "photometric_poses", fake_track)
        monkeypatch.setattr(AP, "refit_gaussians", _recording_refit(calls))
        logs = []
        cfg = _cfgs(auto_eps=True, distill_steps=2, photo_steps=0, refit_steps=4, track_photo=5,
                                  track_rounds=4, track_converged_deg=limit, hull_fill=False,
                                  hinge_fill=False, isolated_factor=0.0, through_prune=0.0, colour_radius=0.0)
        res = run_articulated(dst, tiny[1], *cfg, log=logs.append)
        tracks = [c for c in calls if c[0] == "track"]
        assert [c[0] for c in calls] == ["track", "refit"] * want, [c[0] for c in calls]
        assert res.num_objects > 0, "no clusters in the tiny run"
        assert tracks[0][1] is None and tracks[1][1] is None  # rounds 1 and 2: every object
        if limit > 0:
            np.testing.assert_array_equal(tracks[2][1], [False] + [True] * (res.num_objects - 1))
            assert any("objects [1] only" in m for m in logs) or res.num_objects == 1, logs
            assert any("every joint converged" in m and "no round 4" in m for m in logs), logs
        else:
            assert all(c[1] is None or not np.any(c[1]) for c in tracks)


def test_later_rounds_keep_the_joints_a_hinge_trial_chose(tiny, tmp_path, monkeypatch):
    """With ``hinge_trial`` on, an object whose poses round 1's trial replaced is fixed in the later rounds (tracked
    neither again nor tried): the tiny run's one object, so there is no round 2 and the log says why. A trial that
    kept the poses holds nothing: all three rounds track it. stage2.json keeps each round's trial records (which
    objects are held, for several: `test_trial_held_objects_are_those_a_trial_replaced_in_any_round`). Recorders
    replace the tracking and the re-fit."""
    import shutil

    for replaced in (True, False):
        dst = tmp_path / f"run{replaced}"
        shutil.copytree(tiny[0], dst)
        calls = []

        def fake_track(run, scene, order, ref, labels, k, cfg, moving, log=print, init_poses=None, fixed=None,
                       prev_joints=None, seed=0):
            calls.append(("track", None if fixed is None else np.asarray(fixed).copy()))
            poses = np.tile(np.eye(4, dtype=np.float32), (k, len(order), 1, 1))
            trials = [{"replaced": replaced, "axis": [1.0, 0.0, 0.0] if replaced else None, "offset": None}] * k
            return poses, {"joint_kinds": ["revolute"] * k, "joint_costs": [1.0] * k,
                           "joint_axes": [[1.0, 0.0, 0.0]] * k, "joint_hinge_offsets": [0.5] * k,
                           "hinge_trials": trials}

        monkeypatch.setattr(AP, "photometric_poses", fake_track)
        monkeypatch.setattr(AP, "refit_gaussians", _recording_refit(calls))
        logs = []
        cfg = _cfgs(auto_eps=True, distill_steps=2, photo_steps=0, refit_steps=4, track_photo=5,
                                  track_rounds=3, track_converged_deg=0.0, hull_fill=False, hinge_fill=False,
                                  isolated_factor=0.0, through_prune=0.0, colour_radius=0.0, hinge_trial=3)
        res = run_articulated(dst, tiny[1], *cfg, log=logs.append)
        assert res.num_objects > 0, "no clusters in the tiny run"
        meta = result.load_stage2(dst).s2.meta
        if replaced:
            assert [c[0] for c in calls] == ["track", "refit"], calls
            assert any("chosen by a hinge trial; no round 2" in m for m in logs), logs
            assert len(meta["hinge_trials"]) == 1 and all(r["replaced"] for r in meta["hinge_trials"][0])
        else:
            assert [c[0] for c in calls] == ["track", "refit"] * 3, calls
            assert all(c[1] is None or not c[1].any() for c in calls if c[0] == "track")
            assert len(meta["hinge_trials"]) == 3 and not any(r["replaced"] for x in meta["hinge_trials"] for r in x)


def test_fill_hulls_core_is_the_alive_opaque_members_and_extreme_logits_are_quiet():
    """`labels.fill_hulls`: the hull's core is the cluster's alive members with opacity >= the cut; a faint member
    (logit -800, which overflowed exp() in a hand-written sigmoid) and a dead one do not widen it, without warnings."""
    import warnings

    from fgjax.gaussians import Gaussians

    cube = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    means = np.concatenate([cube, [[-1.0, 0.5, 0.5], [2.0, 0.5, 0.5], [0.5, 0.5, 0.5], [-0.5, 0.5, 0.5],
                                   [1.5, 0.5, 0.5]]])
    n = len(means)
    logits = np.r_[np.full(8, 5.0), -800.0, 5.0, -800.0, 5.0, 5.0]  # faint member, dead member, 3 static
    g = Gaussians(means, np.zeros((n, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), logits, np.zeros((n, 1, 3)))
    labels = np.r_[np.zeros(10, int), -1, -1, -1]
    alive = np.ones(n, bool)
    alive[9] = False  # the member at x = 2 is dead
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = L.fill_hulls(labels, g, alive, 0.7, log=lambda m: None)
    np.testing.assert_array_equal(out, np.r_[np.zeros(10, int), 0, -1, -1])  # only the point inside the cube joins


def test_refine_by_colour_takes_the_dc_colours_of_the_alive_visible_gaussians(monkeypatch):
    """`labels.refine_by_colour` hands `fgjax.cluster.refine_by_colour` the centres, the RGB of the SH DC term
    (C0 sh0 + 0.5), the alive Gaussians with opacity >= 0.1 as usable (a faint one, logit -800, and a dead one
    are not), and the config's radius, components, separation and seed; it returns the labels and report and
    logs what joined and left and why a part was left alone."""
    import warnings

    from fgjax import cluster
    from fgjax.gaussians import SH_C0, Gaussians

    n = 5
    means = np.arange(3 * n, dtype=np.float64).reshape(n, 3)
    sh = np.zeros((n, 4, 3))
    sh[:, 0] = np.linspace(-1.0, 1.0, 3 * n).reshape(n, 3)
    sh[:, 1:] = 9.0  # higher orders play no part
    logits = np.array([5.0, -800.0, 0.0, -2.0, 5.0])  # opacities ~1, 0, 0.5, 0.12, ~1 (the last one dead)
    g = Gaussians(means, np.zeros((n, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), logits, sh)
    alive = np.array([True, True, True, True, False])
    labels = np.array([0, 0, -1, 1, -1])
    seen = {}

    def fake(points, colours, lab, usable, **kw):
        seen.update(points=points, colours=colours, labels=lab, usable=usable, **kw)
        return np.array([0, -1, 0, 1, -1]), [{"joined": 1, "left": 1, "separation": 0.9, "skipped": None},
                                              {"joined": 0, "left": 0, "separation": 0.5, "skipped": "colours apart"}]

    monkeypatch.setattr(cluster, "refine_by_colour", fake)
    logs = []
    cfg = ArticulateConfig(colour_radius=0.07, colour_components=3, colour_separation=0.6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out, rep = L.refine_by_colour(labels, g, alive, cfg, 5, log=logs.append)
    np.testing.assert_array_equal(out, [0, -1, 0, 1, -1])
    assert rep[1]["skipped"] == "colours apart"
    np.testing.assert_allclose(seen["points"], means)
    np.testing.assert_allclose(seen["colours"], sh[:, 0] * SH_C0 + 0.5)
    np.testing.assert_array_equal(seen["usable"], [True, False, True, True, False])
    np.testing.assert_array_equal(seen["labels"], labels)
    assert (seen["radius"], seen["n_components"], seen["min_separation"], seen["seed"]) == (0.07, 3, 0.6, 5)
    assert len(logs) == 1 and "joined [1, 0], left [1, 0]" in logs[0] and "object 2 stopped: colours apart" in logs[0]


def test_fill_hinges_takes_the_hinge_from_the_poses_and_the_core_from_the_alive_opaque_members():
    """`labels.fill_hinges`: the hinge is the poses' axis (a door turning about the z axis through (0, 0, 0));
    its cylinder is sized and bounded by the cluster's alive members with opacity >= ``hull_opacity``: a faint
    member (logit -800) and a dead one far out along the axis do not stretch it. An object that turns by less
    than ``hinge_min_deg`` has no hinge. What joined and the hinges are logged and returned."""
    import warnings

    from scipy.spatial.transform import Rotation

    from fgjax.gaussians import Gaussians

    def about_z(deg):  # a turn about the z axis through the origin
        out = np.eye(4)
        out[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(deg)]).as_matrix()
        return out

    door = np.array([[x, 0.0, z] for x in (0.02, 0.5, 1.0) for z in (0.0, 1.0)])
    means = np.concatenate([door, [[0.0, 0.0, 3.0], [0.0, 0.0, -2.0], [0.1, 0.0, 0.5], [0.1, 0.0, 2.5],
                                   [0.1, 0.0, -1.5]]])
    n = len(means)
    logits = np.r_[np.full(6, 5.0), -800.0, 5.0, 5.0, 5.0, 5.0]  # faint member, dead member, 3 static
    g = Gaussians(means, np.zeros((n, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), logits, np.zeros((n, 1, 3)))
    labels = np.r_[np.zeros(8, int), -1, -1, -1]
    alive = np.ones(n, bool)
    alive[7] = False  # the member at z = -2 is dead
    poses = np.stack([[about_z(d) for d in (0.0, 30.0, 70.0)]])
    cfg = ArticulateConfig()
    logs = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out, hinges = L.fill_hinges(labels, g, alive, poses, cfg, log=logs.append)
    np.testing.assert_array_equal(out, np.r_[np.zeros(8, int), 0, -1, -1])  # only the point beside the door joins
    assert abs(abs(hinges[0]["axis"][2]) - 1.0) < 1e-9 and np.allclose(hinges[0]["pivot"], 0.0, atol=1e-9)
    assert hinges[0]["angle_deg"] == pytest.approx(70.0)
    assert logs == ["stage 2: [1] static Gaussians (objects 1, 2, ...) along the hinges of the objects that turn by "
                    ">= 20 degrees [1] joined them"], logs
    small = np.stack([[about_z(d) for d in (0.0, 10.0, 19.0)]])
    out_small, hinges_small = L.fill_hinges(labels, g, alive, small, cfg, log=lambda m: None)
    np.testing.assert_array_equal(out_small, labels)
    assert hinges_small == [None]


def test_track_photo_next_sets_the_steps_of_the_later_rounds_only(monkeypatch):
    """`photometric_poses` gives the tracker ``track_photo`` steps per frame (2:2:1 over its blur levels) in the
    first round and ``track_photo_next`` in a round started from earlier poses; ``track_photo_next=0`` keeps
    ``track_photo``. The tracker and the joint fit are recorders (the real ones: tests/test_phototrack.py)."""
    from types import SimpleNamespace

    seen = []
    monkeypatch.setattr(AP, "track_photometric",
                        lambda g, alive, labels, k, imgs, vms, Ks, **kw: seen.append(kw["steps"])
                        or (np.tile(np.eye(4, dtype=np.float32), (k, len(vms), 1, 1)), None))
    monkeypatch.setattr(AP, "joint_poses", lambda pts, poses, vms, Ks, log=print, return_axes=False,
                        return_offsets=False: (poses, ["revolute"], [1.0])
                        + ((np.array([[1.0, 0.0, 0.0]]),) if return_axes else ())
                        + ((np.array([0.5]),) if return_offsets else ()))
    run = SimpleNamespace(state=SimpleNamespace(densify=SimpleNamespace(alive=np.ones(4, bool))), meta={},
                          cfg=SimpleNamespace(model=SimpleNamespace(sh_degree=0, background=(0.0, 0.0, 0.0)),
                                              train=SimpleNamespace(tile_size=8)))
    scene = SimpleNamespace(viewmats=np.tile(np.eye(4), (3, 1, 1)), Ks=np.tile(np.eye(3), (3, 1, 1)),
                            images=np.zeros((3, 2, 2, 3)))
    ref = SimpleNamespace(means=np.zeros((4, 3)))
    labels, order = np.array([0, 0, -1, -1]), np.arange(3)
    earlier = np.tile(np.eye(4, dtype=np.float32), (1, 3, 1, 1))
    for cfg, init, want in ((ArticulateConfig(track_photo=40, track_photo_next=20), None, (16, 16, 8)),
                            (ArticulateConfig(track_photo=40, track_photo_next=20), earlier, (8, 8, 4)),
                            (ArticulateConfig(track_photo=40), earlier, (16, 16, 8))):
        AP.photometric_poses(run, scene, order, ref, labels, 1, cfg, None, log=lambda m: None, init_poses=init)
        assert seen[-1] == want, (cfg.track_photo_next, init is None, seen)
    # a fixed object: no joint fit (no points reach it) and the earlier round's joint is kept
    pts_seen = []
    monkeypatch.setattr(AP, "joint_poses", lambda pts, poses, vms, Ks, log=print, return_axes=False,
                        return_offsets=False: pts_seen.append(pts)
                        or (poses, ["kept"], [np.nan], np.full((1, 3), np.nan), np.full(1, np.nan)))
    prev = {"joint_kinds": ["prismatic"], "joint_costs": [0.5], "joint_axes": [[0.0, 1.0, 0.0]],
            "joint_hinge_offsets": [None]}
    _, joints = AP.photometric_poses(run, scene, order, ref, labels, 1, ArticulateConfig(track_photo=40), None,
                                          log=lambda m: None, init_poses=earlier, fixed=np.array([True]),
                                          prev_joints=prev)
    assert joints == {**prev, "hinge_trials": [None]} and len(pts_seen[-1][0]) == 0  # an older record lacks trials
    # a joint fitted afresh reports its hinge offset
    monkeypatch.setattr(AP, "joint_poses", lambda pts, poses, vms, Ks, log=print, return_axes=False,
                        return_offsets=False: (poses, ["revolute"], [1.0])
                        + ((np.array([[1.0, 0.0, 0.0]]),) if return_axes else ())
                        + ((np.array([0.5]),) if return_offsets else ()))
    _, joints = AP.photometric_poses(run, scene, order, ref, labels, 1, ArticulateConfig(track_photo=40),
                                          None, log=lambda m: None)
    assert joints["joint_hinge_offsets"] == [0.5] and joints["joint_kinds"] == ["revolute"]


def _selection_case(seed=0, c_missed=0):
    """Discovery's output on a made-up scene: a large part A (600 dynamic Gaussians, moving in frames 0-9), a small
    part B that moves in frames 20-24 (30 dynamic Gaussians, its 200 others missed by discovery but on moving pixels
    in B's frames) and a false fragment C (30 dynamic Gaussians moving in B's frames, ``c_missed`` others around it
    on moving pixels in those frames, like the static Gaussians a lid uncovers)."""
    from fgjax.method.discover import Discovery, Scores

    rng = np.random.default_rng(seed)
    blob = lambda c, n: np.asarray(c) + rng.uniform(-0.04, 0.04, (n, 3))  # noqa: E731
    pts = np.concatenate([blob([0, 0, 0], 600), blob([1, 0, 0], 30), blob([1, 0, 0], 200), blob([2, 0, 0], 30),
                          blob([2, 0, 0], c_missed)])
    n, t = len(pts), 30
    moving_t = np.zeros((t, n), np.float32)
    moving_t[:10, :600] = 1.0
    moving_t[20:25, 600:] = 1.0  # B's members, B's missed Gaussians and C
    total_t = np.ones((t, n), np.float32)
    dynamic = np.zeros(n, bool)
    dynamic[:630] = True
    dynamic[830:860] = True
    score = moving_t.sum(0) / total_t.sum(0)
    scores = Scores(score, moving_t.sum(0), total_t.sum(0), moving_t, total_t)
    return pts, Discovery(dynamic, scores, np.zeros((t, 2, 2), bool), 0.3)


def test_size_cut_after_the_second_pass_keeps_a_part_that_moves_in_few_frames():
    """B's first cluster (30) is under 5% of D (660: 33), like the default scene's lid after a long stage 1; the
    second pass in B's own frames grows it to 230, so the cut after that pass keeps it and drops C. A false
    fragment that the second pass grows to 6.7% of the clustered Gaussians (as the close pair's and the pose-noise
    scene's did) passes a 5% cut and not the default 10%."""
    pts, disc = _selection_case()
    quiet = lambda *_: None  # noqa: E731
    early = ArticulateConfig(cut_after_local=False)
    labels, _, report = AP.select_parts(pts, disc, Stage2Config(), early, np.ones(len(pts), bool), log=quiet)
    assert report.n_clusters == 1 and np.all(labels[:600] == 0) and np.all(labels[600:] == -1)
    late = ArticulateConfig()
    assert late.cut_after_local
    labels, disc2, report = AP.select_parts(pts, disc, Stage2Config(), late, np.ones(len(pts), bool), log=quiet)
    assert report.n_clusters == 2, list(report.sizes)
    assert np.all(labels[:600] == 0) and np.all(labels[600:830] == 1) and np.all(labels[830:] == -1)
    assert np.all(disc2.dynamic[600:830]) and np.array_equal(disc2.dynamic[830:], disc.dynamic[830:])
    # without candidates B cannot grow and the late cut drops it as well
    _, _, report = AP.select_parts(pts, disc, Stage2Config(), late, np.zeros(len(pts), bool), log=quiet)
    assert report.n_clusters == 1
    # C grown to 60 by the Gaussians around it (6.7% of the 890 clustered): over a 5% cut, under the default 10%
    pts, disc = _selection_case(c_missed=30)
    for frac, kept in ((0.05, 3), (late.local_min_fraction, 2)):
        labels, _, report = AP.select_parts(pts, disc, Stage2Config(), ArticulateConfig(local_min_fraction=frac),
                                                  np.ones(len(pts), bool), log=quiet)
        assert report.n_clusters == kept and np.sum(labels >= 0) == 830 + 60 * (kept == 3), (frac, list(report.sizes))
    with pytest.raises(ValueError, match="local_min_fraction"):
        run_articulated("nowhere", "nowhere", Stage2Config(), ArticulateConfig(local_min_fraction=-0.1))
    with pytest.raises(ValueError, match="local_floor"):
        run_articulated("nowhere", "nowhere", Stage2Config(), ArticulateConfig(local_floor=1.0))


def test_select_parts_links_only_gaussians_that_move_together_with_link_min_corr():
    """A door (200 Gaussians on a grid) opening in frames 2-8 and a lid (30) touching it, opening right after (9-14):
    position alone (the default, -1) makes one cluster, and with no resting frame between the two the split by
    moving times cannot cut it; ``link_min_corr`` = 0.8 gives DBSCAN only the links between Gaussians that move
    together, and the door and the lid come out as two objects."""
    from fgjax.method.discover import Discovery, Scores

    rng = np.random.default_rng(0)
    gx, gy = np.meshgrid(np.arange(20), np.arange(10), indexing="ij")
    lx, ly = np.meshgrid(np.arange(6), np.arange(5), indexing="ij")
    pts = np.concatenate([np.c_[gx.ravel() * 0.01, gy.ravel() * 0.01, np.zeros(200)],
                          np.c_[0.2 + lx.ravel() * 0.01, ly.ravel() * 0.01, np.zeros(30)]])
    pts += rng.normal(0, 1e-3, pts.shape)
    t, n = 24, len(pts)
    total_t = np.full((t, n), 10.0)
    moving_t = rng.uniform(0.0, 1.0, (t, n))  # false-positive pixels everywhere
    moving_t[2:9, :200] += 8.0
    moving_t[9:15, 200:] += 8.0
    seam = np.flatnonzero(np.isclose(pts[:, 0], 0.19, atol=3e-3))
    moving_t[9:15, seam] += 4.0  # the door's last column paints the lid too
    scores = Scores(moving_t.sum(0) / total_t.sum(0), moving_t.sum(0), total_t.sum(0), moving_t, total_t)
    disc = Discovery(np.ones(n, bool), scores, np.zeros((t, 2, 2), bool), 0.1)
    cfg = Stage2Config(eps=0.015, min_samples=5)
    quiet = lambda *_: None  # noqa: E731
    none = np.zeros(n, bool)
    labels, _, report = AP.select_parts(pts, disc, cfg, ArticulateConfig(), none, log=quiet)
    assert report.n_clusters == 1
    labels, _, report = AP.select_parts(pts, disc, cfg, ArticulateConfig(link_min_corr=0.8), none, log=quiet)
    assert report.n_clusters == 2, list(report.sizes)
    assert np.all(labels[200:] == 1) and np.mean(labels[:200] == 0) > 0.9 and not np.any(labels[:200] == 1)
    said = []  # HDBSCAN has no gated neighbourhood graph: the option says it has no effect
    AP.select_parts(pts, disc, Stage2Config(eps=0.015, min_samples=5, cluster_method="hdbscan"),
                    ArticulateConfig(link_min_corr=0.8), none, log=said.append)
    assert any("link_min_corr=0.8 has no effect with cluster_method='hdbscan'" in m for m in said), said


def test_fade_ghosts_caps_the_opacity_of_the_alive_static_gaussians_near_the_swept_volume():
    """`labels.fade_ghosts`: a part (one member at the origin) slides to x = 1; of the static Gaussians by its
    path, the opaque alive ones are capped at ``ghost_opacity``, a fainter one keeps its logit, a dead one is
    left; far ones and the member keep theirs, and nothing but the opacities changes."""
    from scipy.special import expit

    from fgjax.gaussians import Gaussians

    means = np.array([[0.0, 0.0, 0.0], [0.5, 0.02, 0.0], [1.0, 0.0, 0.03], [0.5, 0.0, 0.01], [0.3, 0.0, 0.0],
                      [0.5, 2.0, 0.0]])
    n = len(means)
    logits = np.array([4.0, 3.0, 0.5, -6.0, 2.0, 3.0], np.float32)  # member, near, near, near faint, near dead, far
    g = Gaussians(means, np.zeros((n, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), logits, np.ones((n, 1, 3)))
    poses = np.tile(np.eye(4), (1, 5, 1, 1))
    poses[0, :, 0, 3] = np.linspace(0.0, 1.0, 5)
    alive = np.array([1, 1, 1, 1, 0, 1], bool)
    msgs = []
    cfg = ArticulateConfig(ghost_radius=0.1, ghost_opacity=0.05)
    out = L.fade_ghosts(g, np.array([0, -1, -1, -1, -1, -1]), poses, alive, cfg, log=msgs.append)
    np.testing.assert_allclose(expit(out.opacity_logits[1:3]), 0.05, rtol=1e-5)
    np.testing.assert_array_equal(out.opacity_logits[[0, 3, 4, 5]], logits[[0, 3, 4, 5]])
    for f in ("means", "log_scales", "quats", "sh"):
        np.testing.assert_array_equal(getattr(out, f), getattr(g, f))
    assert "2 static Gaussians" in msgs[0] and "(3 within 0.1)" in msgs[0]


def test_seen_through_matches_the_dense_reference_weights():
    """`labels.seen_through` against an independent float64 reference: the dense rasterizer
    (`fgjax.render.reference`) with one colour channel per Gaussian gives every Gaussian's T alpha at every
    pixel, so the members' coverage is the sum of their channels and each Gaussian's share follows by sums.
    A member plane at z = 3 that slides sideways between two frames (a translation, so its isotropic
    Gaussians need no rotation) half hides a static Gaussian behind it; a static Gaussian beside it and a
    semi-transparent one in front complete the scene; a dead Gaussian (any position) gets 0."""
    import jax.numpy as jnp

    from fgjax.gaussians import Gaussians
    from fgjax.render.reference import rasterize_dense

    w, h = 24, 20
    K = np.array([[20.0, 0, 12.0], [0, 20.0, 10.0], [0, 0, 1]])
    vm = np.eye(4)
    gx, gy = np.meshgrid(np.linspace(-0.5, 0.1, 4), np.linspace(-0.3, 0.3, 4))
    plane = np.stack([gx.ravel(), gy.ravel(), np.full(16, 3.0)], -1)  # members
    static = np.array([[0.0, 0.0, 4.0], [1.4, 0.0, 3.5], [-0.3, 0.1, 2.0],
                       [0.0, 0.0, 3.0]])  # behind, beside, front, dead
    means = np.concatenate([plane, static])
    n = len(means)
    labels = np.r_[np.zeros(16, int), -np.ones(4, int)]
    alive = np.r_[np.ones(19, bool), False]
    log_scales = np.log(np.r_[np.full(16, 0.12), 0.15, 0.15, 0.1, 0.1])[:, None] * np.ones((1, 3))
    logits = np.r_[np.full(16, 0.5), 3.0, 3.0, -1.0, 3.0]
    g = Gaussians(means, log_scales, np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), logits, np.zeros((n, 1, 3)))
    poses = np.tile(np.eye(4), (1, 2, 1, 1))
    poses[0, 1, 0, 3] = 0.35  # frame 1: the plane slides right, over the static Gaussian behind it
    got = L.seen_through(g, alive, labels, poses, np.stack([vm, vm]), np.stack([K, K]), w, h)

    inside, total = np.zeros(n), np.zeros(n)
    op = 1.0 / (1.0 + np.exp(-logits)) * alive
    for i in range(2):
        m = means + (labels >= 0)[:, None] * poses[0, i, :3, 3]
        img, _, _ = rasterize_dense(jnp.asarray(m), jnp.asarray(g.quats), jnp.exp(jnp.asarray(log_scales)),
                                    jnp.asarray(op), jnp.eye(n, dtype=jnp.float64), jnp.asarray(vm),
                                    jnp.asarray(K), w, h)
        wts = np.asarray(img)  # [H, W, N]: T alpha of each Gaussian at each pixel
        cov = wts[..., labels >= 0].sum(-1)
        inside += np.einsum("hwn,hw->n", wts, cov)
        total += wts.sum((0, 1))
    want = np.where(total > 0, inside / np.maximum(total, 1e-30), 0.0)
    np.testing.assert_allclose(got, want, atol=2e-4)
    print("seen_through: behind, beside, in front:", np.round(got[16:19], 3))
    assert got[19] == 0.0 and got[17] < 0.05  # dead; beside the plane
    assert got[16] > 0.5 and 0.05 < got[18] < got[16]  # behind: seen through the plane; the one in front less so
    assert np.all(np.isfinite(got)) and got.min() >= 0 and got.max() <= 1
    with pytest.raises(ValueError, match="poses must be"):
        L.seen_through(g, alive, labels, poses[:, :1], np.stack([vm, vm]), np.stack([K, K]), w, h)
    with pytest.raises(ValueError, match="labels and alive"):
        L.seen_through(g, alive[:-1], labels, poses, np.stack([vm, vm]), np.stack([K, K]), w, h)
    with pytest.raises(L.TileOverflow, match="overflowed the tile capacity"):
        L.seen_through(g, alive, labels, poses, np.stack([vm, vm]), np.stack([K, K]), w, h, capacity=4)


def test_prune_seen_through_prunes_nothing_on_an_overflow_and_lets_other_errors_through(monkeypatch):
    """`labels.prune_seen_through`: a `TileOverflow` from `seen_through` leaves the scene as it is and says so;
    any other error (a shape mismatch: a bug) is raised; otherwise the alive static Gaussians above the cut get
    `_PRUNED_OPACITY` and nothing else changes."""
    from types import SimpleNamespace

    from scipy.special import expit

    from fgjax.gaussians import Gaussians

    n = 4
    g = Gaussians(np.zeros((n, 3)), np.zeros((n, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
                  np.full(n, 2.0, np.float32), np.zeros((n, 1, 3)))
    run = SimpleNamespace(state=SimpleNamespace(densify=SimpleNamespace(alive=np.array([1, 1, 1, 0], bool))),
                          meta={}, cfg=SimpleNamespace(train=SimpleNamespace(tile_size=16)))
    scene = SimpleNamespace(viewmats=np.tile(np.eye(4), (2, 1, 1)), Ks=np.tile(np.eye(3), (2, 1, 1)), width=8, height=8)
    labels = np.array([0, -1, -1, -1])

    def raises(exc):
        def f(*a, **k):
            raise exc
        return f

    msgs = []
    monkeypatch.setattr(L, "seen_through", raises(L.TileOverflow("frame 0 overflowed")))
    out, k = L.prune_seen_through(g, labels, None, run, scene, np.arange(2), 0.5, log=msgs.append)
    assert k == 0 and out is g and "no static Gaussians pruned" in msgs[0] and "overflowed" in msgs[0]
    monkeypatch.setattr(L, "seen_through", raises(ValueError("seen_through: poses must be ...")))
    with pytest.raises(ValueError, match="poses must be"):
        L.prune_seen_through(g, labels, None, run, scene, np.arange(2), 0.5, log=msgs.append)
    monkeypatch.setattr(L, "seen_through", lambda *a, **k: np.array([0.9, 0.9, 0.3, 0.9]))
    out, k = L.prune_seen_through(g, labels, None, run, scene, np.arange(2), 0.5, log=msgs.append)
    assert k == 1  # the member, the one below the cut and the dead one are kept
    np.testing.assert_allclose(expit(np.asarray(out.opacity_logits, np.float64)),
                               [expit(2.0), 1e-6, expit(2.0), expit(2.0)], rtol=1e-4)


def test_label_passes_apply_the_enabled_passes_in_order_and_refit_only_after_a_change(tiny):
    """`fgjax.articulate.pipeline.label_passes` on the sliding part of the tiny run (real passes, nothing faked):
    with every pass off it returns its inputs and an empty record and does not re-fit; with the hull fill alone its
    labels are `labels.fill_hulls`'s and the record lists who joined; with the isolated-member drop as well, that
    drop runs on the filled labels; ``hull_refit_steps`` > 0 re-fits the scene (new parameters), 0 keeps it."""
    run, labels, poses, moved, order = _sliding_part(tiny, 0.1)
    ref = result.reference_scene(run, float(moved.times[order[0]]))
    alive = run.state.densify.alive
    quiet = lambda *_: None  # noqa: E731
    off = ArticulateConfig(hull_fill=False, hinge_fill=False, isolated_factor=0.0, colour_radius=0.0,
                           settle_rest=False, through_prune=0.0, hull_refit_steps=3)
    # a few part members made static, so that the hull fill has something to take back
    lab = labels.copy()
    inside = np.flatnonzero(labels == 0)[::7]
    lab[inside] = -1
    g, out, p, fills = AP.label_passes(run, moved, order, ref, ref, lab, poses, None, off, 0, 1, quiet)
    assert g is ref and out is lab and p is poses and fills == {}
    import dataclasses

    # every alive member spans the hull (this 8-step run's opacities are low)
    hull = dataclasses.replace(off, hull_fill=True, hull_opacity=0.0, hull_refit_steps=0)
    g, out, _, fills = AP.label_passes(run, moved, order, ref, ref, lab, poses, None, hull, 0, 1, quiet)
    want = L.fill_hulls(lab, ref, alive, hull.hull_opacity, hull.hull_max_growth, quiet)
    np.testing.assert_array_equal(out, want)
    assert fills["hull_joined"] == L.joined(lab, want) and fills["hull_joined"][0] > 0, fills
    assert g is ref  # no re-fit steps: the scene as it was
    both = dataclasses.replace(hull, isolated_factor=1.0)  # the tightest drop: some members always go
    _, out2, _, fills2 = AP.label_passes(run, moved, order, ref, ref, lab, poses, None, both, 0, 1, quiet)
    want2, dropped = L.drop_isolated(want, ref, alive, 1.0, quiet)
    np.testing.assert_array_equal(out2, want2)
    assert fills2["isolated_dropped"] == dropped and fills2["hull_joined"] == fills["hull_joined"]
    refitted = dataclasses.replace(hull, hull_refit_steps=2)
    g, out3, _, _ = AP.label_passes(run, moved, order, ref, ref, lab, poses, None, refitted, 0, 1, quiet)
    np.testing.assert_array_equal(out3, want)
    assert not np.array_equal(np.asarray(g.sh), np.asarray(ref.sh))  # re-fitted under the filled labels


@pytest.mark.parametrize("encoding", ["frequency", "hashgrid"])
def test_paper_chain_writes_a_stage2_result_that_loads_back(tiny, tmp_path, encoding):
    """`fgjax.method.run_stage2` (the paper's chain: discovery, DBSCAN, trajectories from the deformation field, the
    control network with either encoding of X) on the tiny run writes stage2.npz and stage2.json; `load_stage2` reads
    them back with ``variant`` "paper", the labels and trajectories of the returned result, the same control network,
    and no re-fitted scene."""
    import shutil

    from fgjax.method import run_stage2

    dst = tmp_path / "run"
    shutil.copytree(tiny[0], dst, ignore=shutil.ignore_patterns(result.STAGE2_NAME, "stage2.json"))
    res = run_stage2(dst, tiny[1], Stage2Config(auto_eps=True, distill_steps=5, photo_steps=2,
                                                control_encoding=encoding),
                     log=lambda m: None)
    back = result.load_stage2(dst)
    assert back.s2.control.encoding == encoding
    for a, b in zip(jax.tree_util.tree_leaves(back.s2.control), jax.tree_util.tree_leaves(res.control), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert back.s2.meta["variant"] == "paper" and json.loads((dst / "stage2.json").read_text())["variant"] == "paper"
    np.testing.assert_array_equal(back.s2.labels, res.labels)
    np.testing.assert_allclose(back.s2.traj, res.traj)
    assert back.s2.refit is None and back.s2.traj.shape == (back.s2.num_objects, 8, 3)
    assert np.all(back.s2.dynamic[back.s2.labels >= 0])
