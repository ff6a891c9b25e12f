"""The articulation search (`fgjax.articulate.articulation`): its hypotheses, joints read back from poses, and the
search recovering a hinge from rendered images where the given joint is wrong, never leaving better poses."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import look_at
from test_phototrack import _coloured_hinge, _images
from test_track import K

from fgjax import geometry
from fgjax.articulate.articulation import (
    LEVEL_AMBIGUITY,
    LEVEL_TILT_DEG,
    articulated_pose,
    articulation_hypotheses,
    camera_tilt,
    camera_up,
    displaced_frames,
    hinge_made_vertical,
    joint_from_poses,
    rect_hinges,
    search_articulations,
    slide_from_poses,
)
from fgjax.gaussians import Gaussians


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


def test_slide_from_poses_reads_a_slide_back_and_keeps_a_far_turns_chord():
    """`slide_from_poses`: the poses of a slide give back its axis and amounts (to round-off, the sign such that the
    largest amount is positive); a turn about a line far off the part gives its centroid's chord, whose poses
    (`articulated_pose`) move the centroid exactly as the turn does; all-identity poses give None; bad shapes and
    non-finite input are refused."""
    pts, _ = _box()
    axis = np.array([0.3, -0.8, 0.52])
    axis /= np.linalg.norm(axis)
    amounts = np.concatenate([np.zeros(3), np.linspace(0.0, -0.7, 9), np.linspace(-0.7, 0.0, 5)])  # [T]
    poses = np.stack([np.asarray(articulated_pose(False, axis, np.zeros(3), a)) for a in amounts])
    got_axis, got = slide_from_poses(pts, poses)
    np.testing.assert_allclose(got_axis, -axis, atol=1e-12)  # its largest amount is -0.7 along ``axis``
    np.testing.assert_allclose(got, -amounts, atol=1e-7)
    c = pts.mean(0)
    far = c + 6.0 * np.cross(axis, [0.0, 0.0, 1.0]) / np.linalg.norm(np.cross(axis, [0.0, 0.0, 1.0]))
    turn = np.stack([np.asarray(articulated_pose(True, axis, far, a), np.float64)
                     for a in np.radians(np.linspace(0.0, 20.0, 7))])
    s_axis, s_am = slide_from_poses(pts, turn)
    moved = np.einsum("tij,j->ti", turn[:, :3, :3], c) + turn[:, :3, 3]  # [T, 3] the centroid under the turn
    slid = np.stack([np.asarray(articulated_pose(False, s_axis, np.zeros(3), a), np.float64) for a in s_am])
    chord = slid[:, :3, 3] + c
    assert abs(np.linalg.norm(s_axis) - 1.0) < 1e-12 and s_am[-1] > 0
    # the chords of one arc are not parallel: the slide holds their main direction, within a small fraction
    assert np.max(np.linalg.norm(chord - moved, axis=1)) < 0.1 * np.max(np.linalg.norm(moved - c, axis=1))
    np.testing.assert_allclose(np.linalg.norm(chord[-1] - c), np.linalg.norm(moved[-1] - c), rtol=0.01)
    np.testing.assert_allclose(slid[:, :3, :3], np.broadcast_to(np.eye(3), (7, 3, 3)), atol=1e-6)
    # snapped: the part's principal axis nearest the chord, the amounts the shifts along it
    _, rot = _box()  # the slab's sides run along rot's columns (the longest first)
    off_axis = np.asarray(geometry.so3_exp(jnp.asarray(0.26 * rot[:, 2])), np.float64) @ rot[:, 0]  # 15 deg off
    drift = np.stack([np.asarray(articulated_pose(False, off_axis, np.zeros(3), a)) for a in amounts])
    chord_axis, _ = slide_from_poses(pts, drift)
    s_axis, s_am = slide_from_poses(pts, drift, snap=True)
    first = np.linalg.svd(pts - pts.mean(0), full_matrices=False)[2][0]  # the sample's longest principal axis
    assert abs(chord_axis @ off_axis) > 1 - 1e-9 and abs(s_axis @ first) > 1 - 1e-9
    assert abs(first @ rot[:, 0]) > np.cos(np.radians(4.0))
    np.testing.assert_allclose(s_am, (drift[:, :3, 3] @ s_axis), atol=1e-12)
    assert s_am[np.argmax(np.abs(s_am))] > 0
    assert slide_from_poses(pts, np.tile(np.eye(4), (5, 1, 1))) is None
    for bad_pts, bad_poses in ((pts[:0], poses), (pts, poses[0]), (np.where(pts == pts[3], np.nan, pts), poses),
                               (pts, np.where(poses == poses[4], np.inf, poses))):
        with pytest.raises(ValueError, match="slide_from_poses"):
            slide_from_poses(bad_pts, bad_poses)


def test_rect_hinges_run_along_the_four_edges_of_a_flat_part_turned_in_its_plane():
    """A slab 2 x 0.8 x 0.2 turned 40 degrees in its own plane and then tilted (`_box`'s rotation): its principal
    axes follow the turn, and so the rectangle must be found by its area, which is least with its sides along the
    slab's: two hinges along the long side through +-0.36 across it (the 5th/95th percentiles of +-0.4), two along
    the short side through +-0.9, every axis in the plane and every pivot at mid-thickness. A square plate (whose
    principal axes in the plane are arbitrary) gets its own sides too, and so do both with 5% of stray points."""
    rng = np.random.default_rng(3)
    _, rot = _box()
    centre = np.array([0.5, -0.2, 2.0])
    for (size, turn), stray in itertools.product((((1.0, 0.4), 40.0), ((0.6, 0.6), 25.0)), (False, True)):
        local = rng.uniform([-size[0], -size[1], -0.1], [size[0], size[1], 0.1], (3000, 3))
        if stray:
            local = np.concatenate([local, rng.uniform(-1.5, 1.5, (150, 3)) * [max(size), max(size), 0.3]])
        spin = np.asarray(geometry.so3_exp(jnp.asarray([0.0, 0.0, np.radians(turn)])), np.float64)
        frame = rot @ spin  # the slab's sides in the world
        pts = local @ frame.T + centre
        hyps = rect_hinges(pts)
        assert len(hyps) == 4 and {h[0] for h in hyps} == {"revolute"}
        axes = np.stack([h[1] for h in hyps])
        piv = np.stack([(h[2] - centre) @ frame for h in hyps])  # [4, 3] pivots in the slab's frame
        np.testing.assert_allclose(np.linalg.norm(axes, axis=1), 1.0, atol=1e-9)
        assert np.abs(axes @ frame[:, 2]).max() < 0.02  # in the plane
        np.testing.assert_allclose(piv[:, 2], 0.0, atol=0.02)  # mid-thickness
        along = np.abs(axes @ frame[:, :2])  # [4, 2]: |cos| with the slab's two sides
        assert np.all(along.max(1) > np.cos(np.radians(4.0))), along  # each along a side, within 4 degrees
        for n in range(4):
            side = int(np.argmax(along[n]))  # the hinge runs along this side: it lies across the other
            assert abs(abs(piv[n, 1 - side]) - 0.9 * size[1 - side]) < 0.05 * size[1 - side], (n, piv)
        assert len({tuple(np.sign(np.round(p[:2], 6))) for p in piv}) >= 3  # four distinct edges, not one twice
    with pytest.raises(ValueError, match="at least 3 points"):
        rect_hinges(pts[:2])
    with pytest.raises(ValueError, match="finite"):
        rect_hinges(np.where(np.arange(len(pts))[:, None] == 5, np.inf, pts))
    for bad in (0.0, -1.0, 46.0, float("nan")):
        with pytest.raises(ValueError, match="step_deg"):
            rect_hinges(pts, bad)
    for degenerate in (np.ones((5, 3)), np.outer(np.linspace(0, 1, 7), [1.0, 2.0, 3.0])):
        assert all(np.all(np.isfinite(a)) and np.all(np.isfinite(p)) and abs(np.linalg.norm(a) - 1) < 1e-9
                   for _, a, p in rect_hinges(degenerate))


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


@pytest.mark.optimized  # run-time-bound: the image search of the hinge
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
    np.testing.assert_array_equal(same, wrong[None].astype(np.float32))
    assert none == [None]
    still = np.tile(np.eye(4), (1, t, 1, 1))
    same, none = search_articulations(g, alive, labels, 1, imgs, vms, Ks, still, **kw)
    np.testing.assert_array_equal(same, still)
    assert none == [None]


def test_search_articulations_with_given_hypotheses_returns_candidates_and_can_leave_the_poses():
    """The hinge scene of the test above with the part a thin door (0.6 x 0.06 x 0.4, hinged at its back edge):
    with `rect_hinges` as its hypotheses, no fitted joint and ``keep`` 4 (no screening) and ``replace=False`` the
    poses come back as given, and every hypothesis is a candidate carrying its poses: the best-scoring one is the
    vertical hinge at the door's back edge, whose poses put its points within a few hundredths of the truth."""
    t = 6
    g, labels, vms, true = _coloured_hinge(t, 0.12)
    door = jnp.asarray(labels) == 0
    # the box's y from [-0.3, 0] to [-0.06, 0]: a door hinged at (-0.3, 0, z)
    g = Gaussians(g.means.at[:, 1].multiply(jnp.where(door, 0.2, 1.0)).at[:, 2].multiply(jnp.where(door, 2 / 3, 1.0)),
                  g.log_scales.at[:, 1].add(jnp.where(door, np.log(0.5), 0.0)), g.quats, g.opacity_logits, g.sh)
    imgs = _images(g, labels, vms, true[None])
    Ks = np.stack([K] * t)
    pts = np.asarray(g.means)[labels == 0]
    centre = pts.mean(0)
    wrong = np.stack([np.asarray(articulated_pose(True, np.array([1.0, 0.0, 0.0]), centre + [0, 0, 0.8], 0.06 * i),
                                 np.float64) for i in range(t)])
    alive = np.ones(len(labels), bool)
    hyps = rect_hinges(pts)
    est, info = search_articulations(g, alive, labels, 1, imgs, vms, Ks, wrong[None], kinds=["none"], sh_degree=0,
                                     background=np.zeros(3), tile_size=8, hypotheses={0: hyps}, replace=False, keep=4,
                                     log=lambda m: None)
    np.testing.assert_array_equal(est[0], wrong.astype(np.float32))
    cands = info[0]["candidates"]
    assert not info[0]["replaced"] and not info[0]["fitted_hypothesis"] and sorted(cands) == [0, 1, 2, 3]
    assert np.all(np.isnan(info[0]["screen"])) and set(cands) == set(info[0]["scores"])
    best = min(cands, key=lambda h: info[0]["scores"][h])
    kind, axis, pivot, pk = cands[best]
    assert kind == "revolute" and abs(axis[2]) > 0.99 and pivot[0] < -0.2, (best, axis, pivot)
    assert _point_error(pk, true, pts).max() < 0.03 < _point_error(wrong, true, pts).max()
    np.testing.assert_array_equal(pk[0], np.eye(4))  # frame 0: not displaced, kept as given
    for h, (kd, ax, pv, p) in cands.items():
        np.testing.assert_array_equal(ax, hyps[h][1])
        assert p.shape == (t, 4, 4) and kd == "revolute" and np.all(np.isfinite(p))
    # ``fitted_poses``: the fitted joint (first) read from other poses, here the truth, and searched from their
    # amounts; the hypotheses after it searched exactly as without it (the same frames, the given poses elsewhere)
    _, info_f = search_articulations(g, alive, labels, 1, imgs, vms, Ks, wrong[None], kinds=["revolute"], sh_degree=0,
                                     background=np.zeros(3), tile_size=8, hypotheses={0: hyps}, replace=False,
                                     keep=5, fitted_poses={0: true}, log=lambda m: None)
    cf = info_f[0]["candidates"]
    assert info_f[0]["fitted_hypothesis"] and sorted(cf) == [0, 1, 2, 3, 4]
    assert abs(cf[0][1][2]) > 0.99 and _point_error(cf[0][3], true, pts).max() < 0.03
    for h in range(4):
        np.testing.assert_array_equal(cf[h + 1][3], cands[h][3])
        assert info_f[0]["scores"][h + 1] == info[0]["scores"][h]


def test_camera_up_is_the_vertical_of_level_cameras_looking_down():
    """Level cameras on an orbit looking down 20-40 degrees at the origin: up is +z to round-off (the mean of their
    up axes is 20-40 degrees off it), for any rotation of the whole rig, and its sign follows the cameras' up."""
    rng = np.random.default_rng(0)
    ang = np.linspace(0.0, 1.5, 12)  # a quarter orbit
    h = rng.uniform(0.7, 1.7, 12)
    vms = np.stack([look_at([2 * np.cos(a), 2 * np.sin(a), z]) for a, z in zip(ang, h)])  # level: world z up
    up = camera_up(vms)
    np.testing.assert_allclose(up, [0.0, 0.0, 1.0], atol=1e-9)
    assert np.degrees(np.arccos(-vms[:, 1, :3].mean(0) @ up / np.linalg.norm(vms[:, 1, :3].mean(0)))) > 15
    rot = np.asarray(geometry.so3_exp(jnp.asarray([0.3, -1.2, 0.4])), np.float64)
    w = np.eye(4)
    w[:3, :3] = rot  # the world turned: x_new = rot x
    turned = vms @ np.linalg.inv(w)
    np.testing.assert_allclose(camera_up(turned), rot @ [0.0, 0.0, 1.0], atol=1e-9)
    flipped = vms.copy()
    flipped[:, :2] *= -1  # each camera rolled by 180 degrees: upside down
    np.testing.assert_allclose(camera_up(flipped), [0.0, 0.0, -1.0], atol=1e-9)
    one = camera_up(vms[:1])  # one camera: some unit direction orthogonal to its right axis, not that axis
    assert abs(np.linalg.norm(one) - 1.0) < 1e-12 and abs(one @ vms[0, 0, :3]) < 1e-12


def _rolled(vm, deg):
    """World-to-camera ``vm`` [4, 4] rolled by ``deg`` degrees about its own view axis."""
    roll = np.asarray(geometry.so3_exp(jnp.asarray([0.0, 0.0, np.radians(deg)])), np.float64)
    out = vm.copy()
    out[:3] = roll @ vm[:3]
    return out


def test_camera_tilt_measures_roll_and_an_up_the_cameras_do_not_fix():
    """Level orbit cameras: tilt and ambiguity 0. Each rolled by +-3 degrees: an RMS tilt of about 2.7 degrees (the
    roll seen from cameras looking 20-33 degrees down), over `LEVEL_TILT_DEG`, while up itself stays within a degree.
    A dolly whose cameras turn by only +-2 degrees and roll by +-1: a small tilt, but an ambiguity of about 0.4, over
    `LEVEL_AMBIGUITY`, and an up 6 degrees off. Fewer than three cameras: infinite ambiguity. (The synthetic scenes'
    cameras: tilt 0.4-0.6 degrees, ambiguity 0.02-0.04.)"""
    ang = np.linspace(0.0, 1.5, 12)
    vms = np.stack([look_at([2 * np.cos(a), 2 * np.sin(a), 1.0 + 0.3 * np.sin(5 * a)]) for a in ang])
    assert camera_tilt(vms) == pytest.approx((0.0, 0.0), abs=1e-6)
    rolled = np.stack([_rolled(vm, 3.0 * (-1) ** t) for t, vm in enumerate(vms)])
    tilt, _ = camera_tilt(rolled)
    assert LEVEL_TILT_DEG < tilt < 3.0
    assert camera_up(rolled)[2] > np.cos(np.radians(1.0))
    dolly = np.stack([_rolled(look_at([2.0, 0.1 * t, 1.0], target=[0.0, 0.1 * t + 0.07 * (-1) ** t, 0.0]),
                              (-1) ** (t // 2)) for t in range(6)])
    tilt, amb = camera_tilt(dolly)
    assert tilt < LEVEL_TILT_DEG and 0.3 < amb and amb > LEVEL_AMBIGUITY
    assert camera_up(dolly)[2] < np.cos(np.radians(4.0))  # the up that the ambiguity warns of
    assert camera_tilt(vms[:2]) == (0.0, float("inf"))


def test_hinge_made_vertical_keeps_the_turns_and_the_hinge_at_the_part():
    """A door (points about (0.3, 0, 0.5)) turning 0..1.2 rad about a hinge through (0, 0, 0.5) tilted 12 degrees off
    +z: made vertical, its poses turn by the same angles about +z through the old hinge's point nearest the door's
    centroid; a hinge 40 degrees off, poses that do not turn, or a turn the other way keep to the rules."""
    rng = np.random.default_rng(1)
    pts = rng.uniform([0.05, -0.02, 0.1], [0.55, 0.02, 0.9], (200, 3))
    tilt = np.asarray(geometry.so3_exp(jnp.asarray([np.radians(12.0), 0.0, 0.0])), np.float64)
    axis = tilt @ [0.0, 0.0, 1.0]
    pivot = np.array([0.0, 0.0, 0.5])
    turns = np.linspace(0.0, 1.2, 7)
    poses = np.stack([np.asarray(articulated_pose(True, axis, pivot, a), np.float64) for a in turns])
    out, new_axis, off = hinge_made_vertical(pts, poses, [0.0, 0.0, 2.0], 25.0)
    assert abs(off - 12.0) < 1e-4 and out.dtype == poses.dtype
    np.testing.assert_allclose(new_axis, [0.0, 0.0, 1.0], atol=1e-12)
    got_axis, got_pivot = joint_from_poses(out, "revolute")
    np.testing.assert_allclose(got_axis, [0.0, 0.0, 1.0], atol=1e-5)
    c = pts.mean(0)
    at = pivot + axis * ((c - pivot) @ axis)  # the old hinge's point nearest the centroid
    np.testing.assert_allclose(got_pivot[:2], at[:2], atol=1e-5)
    rv = np.asarray(geometry.so3_log(jnp.asarray(out[:, :3, :3])), np.float64)
    np.testing.assert_allclose(rv[:, 2], turns, atol=1e-5)
    np.testing.assert_allclose(out[:, :3, :3] @ at + out[:, :3, 3], np.broadcast_to(at, (7, 3)), atol=1e-5)
    assert hinge_made_vertical(pts, poses, [0.0, 0.0, 1.0], 10.0) is None  # 12 degrees off: kept
    assert hinge_made_vertical(pts, np.tile(np.eye(4), (3, 1, 1)), [0.0, 0.0, 1.0], 25.0) is None
    back, ax_b, _ = hinge_made_vertical(pts, poses, [0.0, 0.0, -1.0], 25.0)  # up given the other way round
    np.testing.assert_allclose(ax_b, [0.0, 0.0, 1.0], atol=1e-12)  # the hinge keeps its own sense
    np.testing.assert_allclose(back, out, atol=1e-9)
    bare, _, _ = hinge_made_vertical(np.zeros((0, 3)), poses, [0.0, 0.0, 1.0], 25.0)  # no members: finite poses
    assert np.all(np.isfinite(bare))
