"""The articulation search (`fgjax.pipeline.articulation`): its hypotheses, joints read back from poses, and the
search recovering a hinge from rendered images where the given joint is wrong, never leaving better poses."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_phototrack import _coloured_hinge, _images
from test_track import K

from fgjax import geometry
from fgjax.gaussians import Gaussians
from fgjax.pipeline.articulation import (
    articulated_pose,
    articulation_hypotheses,
    displaced_frames,
    joint_from_poses,
    search_articulations,
)


def _box(n=400, seed=0):
    rng = np.random.default_rng(seed)
    rot = np.asarray(geometry.so3_exp(jnp.asarray([0.3, -0.5, 0.8])), np.float64)
    local = rng.uniform([-1.0, -0.4, -0.1], [1.0, 0.4, 0.1], (n, 3))  # a lid-like slab
    return local @ rot.T + np.array([0.5, -0.2, 2.0]), rot


def test_articulation_hypotheses_are_hinges_on_the_box_edges_and_slides_along_its_axes():
    pts, rot = _box()
    hyps = articulation_hypotheses(pts)
    assert len(hyps) == 15 and [h[0] for h in hyps] == ["revolute"] * 12 + ["prismatic"] * 3
    for _, axis, pivot in hyps:
        assert abs(np.linalg.norm(axis) - 1.0) < 1e-9 and np.all(np.isfinite(pivot))
    # the first axis is the slab's long side; its four hinges lie on the edges of the 0.8 x 0.2 cross-section
    assert abs(abs(hyps[0][1] @ rot[:, 0]) - 1.0) < 1e-3
    local = np.stack([(h[2] - np.array([0.5, -0.2, 2.0])) @ rot for h in hyps[:4]])  # [4, 3] in the slab's frame
    np.testing.assert_allclose(np.sort(np.abs(local[:, 1])), [0.36] * 4, atol=0.03)  # 5th-95th pct of +-0.4
    np.testing.assert_allclose(np.sort(np.abs(local[:, 2])), [0.09] * 4, atol=0.01)
    assert len({tuple(np.sign(x[1:]).astype(int)) for x in local}) == 4  # the four edges, not one twice
    with pytest.raises(ValueError, match="at least 3 points"):
        articulation_hypotheses(pts[:2])
    with pytest.raises(ValueError, match="finite"):
        articulation_hypotheses(np.where(np.arange(len(pts))[:, None] == 5, np.nan, pts))
    # degenerate parts (every point the same; a line) still give 15 finite hypotheses with unit axes
    for degenerate in (np.ones((5, 3)), np.outer(np.linspace(0, 1, 7), [1.0, 2.0, 3.0])):
        hyps = articulation_hypotheses(degenerate)
        assert len(hyps) == 15
        assert all(np.all(np.isfinite(a)) and np.all(np.isfinite(p)) and abs(np.linalg.norm(a) - 1) < 1e-9
                   for _, a, p in hyps)


@pytest.mark.parametrize("kind", ["revolute", "prismatic"])
def test_joint_from_poses_reads_back_the_joint_that_made_them(kind):
    axis = np.array([0.6, 0.0, 0.8])
    pivot = np.array([1.0, -2.0, 0.5])
    amounts = np.array([0.0, 0.2, -0.7, 0.4])
    poses = np.stack([np.asarray(articulated_pose(kind == "revolute", axis, pivot, a), np.float64) for a in amounts])
    got = joint_from_poses(poses, kind)
    assert got is not None
    a, p = got
    assert abs(abs(a @ axis) - 1.0) < 1e-5, a
    if kind == "revolute":  # the pivot lies on the hinge's line, and the poses turn about it
        d = (p - pivot) - axis * ((p - pivot) @ axis)
        assert np.linalg.norm(d) < 1e-4, d
        np.testing.assert_allclose(poses[2, :3, :3] @ pivot + poses[2, :3, 3], pivot, atol=1e-5)
    else:
        np.testing.assert_allclose(poses[2, :3, 3], -0.7 * axis, atol=1e-6)
        np.testing.assert_allclose(poses[2, :3, :3], np.eye(3), atol=1e-7)
    assert joint_from_poses(np.tile(np.eye(4), (3, 1, 1)), kind) is None
    with pytest.raises(ValueError, match="kind must be"):
        joint_from_poses(poses, "ball")


def test_articulated_pose_is_finite_with_finite_gradients_at_zero_and_large_turns():
    for a in (0.0, 1e-9, 3.0, 40.0):
        for rev in (True, False):
            p = articulated_pose(rev, jnp.array([0.0, 0.0, 1.0]), jnp.array([1.0, 2.0, 3.0]), a)
            g = jax.grad(lambda x, rev=rev: jnp.sum(articulated_pose(rev, jnp.array([0.0, 0.0, 1.0]),
                                                                     jnp.array([1.0, 2.0, 3.0]), x)))(jnp.asarray(a))
            assert np.all(np.isfinite(np.asarray(p))) and np.isfinite(float(g))


def test_displaced_frames():
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[1, 0, 3] = 0.01
    poses[2, 0, 3] = 1e-4
    np.testing.assert_array_equal(displaced_frames(pts, poses, 1e-3), [False, True, False])


def _point_error(poses, true, pts):
    a = np.einsum("tij,mj->tmi", poses[:, :3, :3], pts) + poses[:, None, :3, 3]
    b = np.einsum("tij,mj->tmi", true[:, :3, :3], pts) + true[:, None, :3, 3]
    return np.linalg.norm(a - b, axis=-1).mean(1)  # [T]


def test_search_articulations_finds_the_hinge_from_the_images_when_the_fitted_joint_is_wrong():
    """A box turning 0.12 rad a frame about a vertical hinge at its edge (`test_track._hinge_scene`, the box
    flattened so that its principal axes are its sides), imaged; the
    given poses turn it by the same angles about a horizontal axis through its centre (a wrong joint, fitted as a
    hinge). The search replaces them with a vertical hinge near the true one, whose poses put the part's points
    within a few hundredths of the truth (the box is 0.6 wide; the wrong poses are 0.1 off and more). From the true
    poses, it keeps poses as close (it never leaves poses that render closer than what it finds)."""
    t = 6
    g, labels, vms, true = _coloured_hinge(t, 0.12)
    # the box 0.6 x 0.3 x 0.4 (x, y, z) instead of 0.6 x 0.3 x 0.6: a square cross-section has no principal axes
    g = Gaussians(g.means.at[:, 2].multiply(jnp.where(jnp.asarray(labels) == 0, 2.0 / 3.0, 1.0)), g.log_scales,
                  g.quats, g.opacity_logits, g.sh)
    imgs = _images(g, labels, vms, true[None])
    Ks = np.stack([K] * t)
    pts = np.asarray(g.means)[labels == 0]
    centre = pts.mean(0)
    wrong = np.stack([np.asarray(articulated_pose(True, np.array([1.0, 0.0, 0.0]), centre, 0.12 * i), np.float64)
                      for i in range(t)])
    alive = np.ones(len(labels), bool)
    kw = dict(kinds=["revolute"], sh_degree=0, background=np.zeros(3), tile_size=8)
    logs = []
    est, info = search_articulations(g, alive, labels, 1, imgs, vms, Ks, wrong[None], log=logs.append, **kw)
    assert info[0] is not None and info[0]["replaced"] and info[0]["kind"] == "revolute", (info, logs)
    assert abs(info[0]["axis"][2]) > 0.99, info  # vertical
    assert info[0]["frames"] == t - 1  # frame 0 is at rest
    assert info[0]["score"] < info[0]["score_given"]
    e_wrong, e_est = _point_error(wrong, true, pts), _point_error(est[0], true, pts)
    assert e_wrong.max() > 0.1 and e_est.max() < 0.03, (e_wrong, e_est)
    np.testing.assert_array_equal(est[0, 0], np.eye(4))
    assert any("replaced" in m for m in logs), logs
    # from the true poses: kept, or replaced by poses that render at least as close and stay as near the truth
    est_t, info_t = search_articulations(g, alive, labels, 1, imgs, vms, Ks, true[None], **kw, log=logs.append)
    # the fitted joint is searched from its own amounts, so the best found renders at least as close as the given
    assert info_t[0]["score"] <= info_t[0]["score_given"] + 1e-6, info_t  # both ~1e-7: the images are exact
    assert _point_error(est_t[0], true, pts).max() < 0.03
    # an object not searched, or never displaced, keeps its poses and has no info
    same, none = search_articulations(g, alive, labels, 1, imgs, vms, Ks, wrong[None], objects=[False], **kw)
    np.testing.assert_array_equal(same, wrong[None].astype(np.float32)) and none == [None]
    still = np.tile(np.eye(4), (1, t, 1, 1))
    same, none = search_articulations(g, alive, labels, 1, imgs, vms, Ks, still, **kw)
    np.testing.assert_array_equal(same, still) and none == [None]
    assert none == [None]
