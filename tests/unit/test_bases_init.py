"""The motion bases initialised from the flow (`fgjax.method.bases_init`).

The labels are checked on the synthetic scene of `test_discover` (64 x 48, 12 frames, a door, a drawer and a lid
moving in their own time windows) with its ground truth: the "warm-up model" is the true scene at rest (state 0,
every part closed), the flow the true optical flow. The weight fit is checked against the labels it was given, and
the stage-1 hook on a tiny scene whose blob moves.
"""

from __future__ import annotations

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import synth
from test_stage1 import _cfg, _tiny_scene

from fgjax import config as C
from fgjax.gaussians import Gaussians
from fgjax.method import bases_init as B
from fgjax.method import stage1
from fgjax.models.deform import DeformSpec, basis_logits, deform_init


@pytest.fixture(scope="module")
def scene():
    cfg = synth.SynthConfig(objects=("door", "drawer", "lid"), width=64, height=48, frames=12,
                            test_views=0, test_states=0)
    sc = synth.make_scene(cfg)
    times = np.arange(cfg.frames) / (cfg.frames - 1)
    states = synth.scene_states(sc, times)
    vm = np.linalg.inv(np.stack([synth.camera_c2w(sc, float(t)) for t in times]))
    renders = synth.render_sequence(sc, vm, states)
    f = synth.sequence_flow(sc, states, vm, renders)
    n = len(sc.means)
    g = Gaussians(jnp.asarray(sc.means, jnp.float32), jnp.asarray(np.log(sc.scales), jnp.float32),
                  jnp.asarray(sc.quats, jnp.float32),
                  jnp.asarray(np.log(sc.opacities) - np.log1p(-np.minimum(sc.opacities, 1 - 1e-6)), jnp.float32),
                  jnp.zeros((n, 1, 3), jnp.float32))
    flows = np.full((cfg.frames, cfg.height, cfg.width, 2), np.nan, np.float32)
    flows[1:] = np.where((f["flow_valid"] & ~f["flow_occluded"])[..., None], f["flow"], np.nan)
    view = types.SimpleNamespace(viewmats=vm, Ks=np.stack([sc.K] * cfg.frames), times=times, width=cfg.width,
                                 height=cfg.height, num_frames=cfg.frames)
    return {"sc": sc, "params": {"gaussians": g}, "alive": jnp.ones(n, bool), "view": view, "flows": flows}


def test_flow_part_labels_put_each_part_in_its_own_group(scene):
    sc = scene["sc"]
    prev = np.arange(len(scene["flows"])) - 1
    labels, n_dyn = B.flow_part_labels(scene["params"], scene["alive"], scene["view"], scene["flows"], prev, parts=5,
                                       capacity=None)
    truth = sc.labels
    assert labels.shape == truth.shape and n_dyn > 0
    assert np.mean(labels[truth == 0] == 0) > 0.97  # the static scene stays on basis 0
    groups = [k for k in range(1, 6) if np.any(labels == k)]
    majority = {k: int(np.bincount(truth[labels == k], minlength=4).argmax()) for k in groups}
    purity = {k: float(np.mean(truth[labels == k] == majority[k])) for k in groups}
    print("groups", {k: (int(np.sum(labels == k)), majority[k], purity[k]) for k in groups})
    assert set(majority.values()) == {1, 2, 3}  # every part has a group, no group is the static scene's
    assert min(purity.values()) > 0.9
    # fewer bases than parts: only the largest groups are kept, the rest are left out of the fit (-1)
    two, _ = B.flow_part_labels(scene["params"], scene["alive"], scene["view"], scene["flows"], prev, parts=2,
                                capacity=None)
    assert set(np.unique(two)) <= {-1, 0, 1, 2} and np.sum(two == -1) >= np.sum(labels > 2)
    # nothing moves (the flow is the camera's own): no part, the bases start as they were
    logs = []
    spec = DeformSpec(kind="bases", depth=1, width=16, bases=3, knots=4, aabb=(-2, -2, -2, 2, 2, 2))
    d0 = deform_init(jax.random.key(0), spec)
    vm, rest = scene["view"].viewmats, np.zeros_like(synth.scene_states(sc, scene["view"].times))
    still = np.full_like(scene["flows"], np.nan)
    still[1:] = synth.sequence_flow(sc, rest, vm, synth.render_sequence(sc, vm, rest))["flow"]
    out = B.init_bases_from_flow({**scene["params"], "deform": d0}, scene["alive"], spec, scene["view"], still,
                                 method="dis",
                                 capacity=None, log=logs.append)
    assert out is d0 or all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(d0)))
    assert any("no part found" in m for m in logs)


def test_init_bases_from_flow_fits_the_weights_and_moves_the_pivots(scene):
    sc = scene["sc"]
    spec = DeformSpec(kind="bases", depth=2, width=32, bases=4, knots=4, aabb=(-2, -2, -2, 2, 2, 2))
    d0 = deform_init(jax.random.key(1), spec)
    logs = []
    d = B.init_bases_from_flow({**scene["params"], "deform": d0}, scene["alive"], spec, scene["view"],
                               scene["flows"], method="dis", capacity=None, log=logs.append)
    prev = np.arange(len(scene["flows"])) - 1
    labels, _ = B.flow_part_labels(scene["params"], scene["alive"], scene["view"], scene["flows"], prev, parts=3,
                                   capacity=None)
    w = np.asarray(jax.nn.softmax(basis_logits(spec, d, sc.means), axis=-1))
    use = labels >= 0
    assert np.mean(w.argmax(1)[use] == labels[use]) > 0.97
    for k in range(1, 4):  # every class is learned, the small ones too (class-balanced), and the pivot is its centroid
        assert np.mean(w[labels == k, k]) > 0.6
        np.testing.assert_allclose(np.asarray(d["pivot"][k - 1]), sc.means[labels == k].mean(0), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(d["motion"]), np.asarray(d0["motion"]))  # motions stay at the identity
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(d))
    assert any("weights fitted" in m for m in logs)
    with pytest.raises(ValueError, match="deform.kind = 'bases'"):
        B.init_bases_from_flow(scene["params"], scene["alive"], DeformSpec(kind="hash"), scene["view"],
                               scene["flows"], method="dis", capacity=None)


def test_fit_basis_weights_leaves_out_unlabelled_points_and_keeps_finite_logits():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (600, 3)).astype(np.float32)
    labels = np.where(x[:, 0] > 0.5, 1, 0)
    labels[np.linalg.norm(x - [-0.5, -0.5, 0.0], axis=1) < 0.3] = 2  # a small class
    labels[x[:, 2] > 0.8] = -1  # left out: any weights there
    spec = DeformSpec(kind="bases", depth=2, width=32, bases=3, knots=2, aabb=(-1, -1, -1, 1, 1, 1))
    d0 = deform_init(jax.random.key(2), spec)
    d, loss = B.fit_basis_weights(spec, d0, jnp.asarray(x), jnp.asarray(labels))
    logits = np.asarray(basis_logits(spec, d, x))
    assert np.all(np.isfinite(logits)) and np.isfinite(float(loss))
    use = labels >= 0
    assert np.mean(logits.argmax(1)[use] == labels[use]) > 0.95
    assert np.mean(logits.argmax(1)[labels == 2] == 2) > 0.9
    # the smoothed targets (s = 0.1) bound the fitted weights away from 0 and 1
    w = np.asarray(jax.nn.softmax(logits, axis=-1))
    assert w.max() < 0.999
    np.testing.assert_array_equal(np.asarray(d["pivot"]), np.asarray(d0["pivot"]))


def test_stage1_initialises_the_bases_after_the_warm_up(tmp_path):
    """``deform.bases_init = "flow"``: once, at the end of the warm-up, with the log line; refused for other fields."""
    scene = _tiny_scene(True, frames=4, w=48, h=32)
    cfg = _cfg("deform.kind=bases", "deform.bases=3", "deform.knots=4", "deform.bases_init=flow", "flow.method=dis",
               "train.warmup_steps=2", "static.force=dynamic", "densify.enabled=false")
    logs = []
    res = stage1.train_stage1(cfg, scene, tmp_path / "run", stop_at=4, progress=False, log=logs.append)
    assert sum("motion bases from the flow" in m for m in logs) == 1, logs
    assert np.all(np.isfinite(res["losses"]))
    with pytest.raises(C.ConfigError, match="deform.bases_init"):
        stage1.train_stage1(_cfg("deform.bases_init=flow"), scene, None, stop_at=1, progress=False,
                            log=lambda *_: None)
    with pytest.raises(C.ConfigError, match="deform.bases_init"):
        C.load_config(None, ["deform.kind=bases", "deform.bases_init=yes"])
