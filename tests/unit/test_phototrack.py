"""Photometric tracking (`fgjax.articulate.phototrack`): blur against OpenCV, pose updates, poses recovered from
rendered images, and the articulation fitted to per-frame poses."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_track import H, K, W, _hinge_scene, _pose

from fgjax import geometry
from fgjax.articulate.phototrack import (
    blur,
    blur_kernel,
    blur_with,
    converged_joints,
    hinge_offset,
    is_far_hinge,
    joint_poses,
    largest_turn_deg,
    mixed_copies,
    pose_delta,
    rects_meeting,
    rest_spans,
    settle_at_rest,
    subset_bucket,
    tile_region,
    track_photometric,
)
from fgjax.gaussians import Gaussians
from fgjax.models.posed import transform_gaussians


@pytest.mark.parametrize("sigma", [0.7, 2.0, 4.0])
def test_blur_matches_opencv_with_zero_border(sigma):
    import cv2

    img = np.random.default_rng(0).random((23, 31, 3))
    r = int(np.ceil(3 * sigma))
    ref = cv2.GaussianBlur(img, (2 * r + 1, 2 * r + 1), sigma, borderType=cv2.BORDER_CONSTANT)
    np.testing.assert_allclose(np.asarray(blur(jnp.asarray(img), sigma)), ref, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(blur(jnp.asarray(img), 0.0)), img)
    # the tracker's form: every level's kernel zero-padded to the widest (12 taps a side), the same blur
    for sg in (sigma, 0.0):
        wide = blur_with(jnp.asarray(img), jnp.asarray(blur_kernel(sg, 12)))
        np.testing.assert_allclose(np.asarray(wide), ref if sg else img, atol=1e-6)
    with pytest.raises(ValueError, match="radius 1 is below"):
        blur_kernel(sigma, 1)


def test_pose_delta_turns_about_the_centre_and_is_finite_on_extreme_updates():
    cen = jnp.asarray([[0.3, -0.2, 1.0], [0.0, 0.0, 0.0]])
    scale = jnp.asarray([0.5, 2.0])
    np.testing.assert_allclose(np.asarray(pose_delta(jnp.zeros((2, 6)), cen, scale)), np.tile(np.eye(4), (2, 1, 1)),
                               atol=1e-12)
    x = jnp.asarray([[0.4, -0.1, 0.2, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0, -2.0, 0.5]])
    d = np.asarray(pose_delta(x, cen, scale))
    np.testing.assert_allclose(d[0, :3, :3] @ np.asarray(cen[0]) + d[0, :3, 3], cen[0], atol=1e-12)  # centre fixed
    np.testing.assert_allclose(d[1, :3, 3], [2.0, -4.0, 1.0], atol=1e-12)  # shift in units of `scale`
    np.testing.assert_allclose(d[:, :3, :3] @ np.swapaxes(d[:, :3, :3], 1, 2), np.tile(np.eye(3), (2, 1, 1)),
                               atol=1e-12)
    huge = jnp.asarray([[1e6, -1e6, 3e5, 1e8, 0.0, 0.0], [0.0] * 6])
    assert np.all(np.isfinite(np.asarray(pose_delta(huge, cen, scale))))
    g = jax.grad(lambda v: jnp.sum(pose_delta(v, cen, scale)))(jnp.zeros((2, 6)))
    assert np.all(np.isfinite(np.asarray(g)))


def _coloured_hinge(t: int, step: float):
    """`test_track._hinge_scene` as raw Gaussians with a random colour each (a texture the images show):
    (Gaussians, labels, viewmats [t], true poses [t, 4, 4])."""
    means, quats, scales, opac, labels, vms, true = _hinge_scene(t, step)
    rng = np.random.default_rng(1)
    sh = ((rng.random((len(means), 1, 3)) - 0.5) / 0.2820948).astype(np.float64)
    g = Gaussians(jnp.asarray(means), jnp.asarray(np.log(scales)), jnp.asarray(quats),
                  jnp.asarray(np.log(opac / (1 - opac))), jnp.asarray(sh))
    return g, labels, vms, true


def _images(g, labels, vms, poses, k=K, width=W, height=H):
    from fgjax.models.model import render_params

    out = []
    for i in range(len(vms)):
        m, q = transform_gaussians(g.means, g.quats, jnp.asarray(labels), jnp.asarray(poses[:, i]))
        img, _, _, _ = render_params({"gaussians": Gaussians(m, g.log_scales, q, g.opacity_logits, g.sh)},
                                     jnp.ones(len(labels), bool), jnp.asarray(vms[i]), jnp.asarray(k), 0.0, spec=None,
                                     sh_degree=0, width=width, height=height, background=jnp.zeros(3), capacity=None)
        out.append(np.asarray(img))
    return np.stack(out)


def test_track_photometric_recovers_a_turning_part_from_its_images_and_joint_poses_make_it_a_hinge():
    """Images rendered with a part turning 0.12 rad per frame about a hinge: from identity, frame by frame
    (each start extrapolated from the last two poses), the fitted poses follow the turn; the articulation
    fitted to them is revolute about the hinge and as close to the truth. (Whether it is closer than the
    per-frame poses is not stable on this toy: perturbing the images by 1e-6 moves the per-frame errors
    by up to 50% and flips that order; so the bound is absolute.) A part that
    rests (no moving pair) keeps the identity."""
    t = 6
    g, labels, vms, true = _coloured_hinge(t, 0.12)
    imgs = _images(g, labels, vms, true[None])
    Ks = np.stack([K] * t)
    logs = []
    est, pi = track_photometric(g, np.ones(len(labels), bool), labels, 1, imgs, vms, Ks, sh_degree=0,
                                background=np.zeros(3), steps=(15, 15, 10), radius=0.0, progress_every=2,
                                log=logs.append)
    assert any("5 of 5 frames fitted" in m for m in logs), logs
    assert [m.split(",")[0] for m in logs if "fitted (" in m] == ["photometric tracking: frame 3/6",
                                                                  "photometric tracking: frame 5/6"], logs
    assert pi.shape == labels.shape and np.all(pi[labels == 0] == 1.0) and np.all(pi[labels < 0] == 0.0)
    ang = lambda r: float(np.degrees(np.linalg.norm(np.asarray(geometry.so3_log(jnp.asarray(r))))))
    pts = np.asarray(g.means)[labels == 0]

    def err(p):  # mean distance of the part's points from where the true poses put them, per frame
        a = np.einsum("tij,mj->tmi", p[:, :3, :3], pts) + p[:, None, :3, 3]
        b = np.einsum("tij,mj->tmi", true[:, :3, :3], pts) + true[:, None, :3, 3]
        return np.linalg.norm(a - b, axis=-1).mean(1)

    assert abs(ang(est[0, -1, :3, :3]) - ang(true[-1, :3, :3])) < 4.0, (ang(est[0, -1, :3, :3]), ang(true[-1, :3, :3]))
    assert err(est[0]).max() < 0.04, err(est[0])  # the part is ~0.6 wide; it turns 0.6 rad in all
    still = np.tile(np.eye(4), (1, t, 1, 1))
    assert err(still[0]).max() > 0.2  # not a test of doing nothing
    joint, kinds, costs = joint_poses([pts], est, vms, Ks, log=logs.append)
    assert kinds == ["revolute"] and costs[0] < 1.0, (logs, costs)
    assert not any("warning" in m for m in logs), logs
    # per-frame poses that no one joint explains (each frame turned by 2 rad about its own random axis and shifted
    # by 0.5, as a lost tracking gives) cost more than 4 px^2 (9.0) and are warned of
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(t, 3))
    rot = np.asarray(geometry.so3_exp(jnp.asarray(2.0 * axes / np.linalg.norm(axes, axis=1, keepdims=True))))
    wild = np.tile(np.eye(4), (t, 1, 1))
    wild[1:, :3, :3] = rot[1:]
    wild[1:, :3, 3] = pts.mean(0) - rot[1:] @ pts.mean(0) + 0.5 * rng.normal(size=(t - 1, 3))
    _, _, wild_costs = joint_poses([pts], wild[None], vms, Ks, log=logs.append)
    assert wild_costs[0] > 4.0 and any("warning: object 1's" in m for m in logs), (wild_costs, logs[-2:])
    axis = np.asarray(geometry.so3_log(jnp.asarray(joint[0, -1, :3, :3])))
    assert abs(abs(axis[2]) / np.linalg.norm(axis) - 1.0) < 0.01, axis  # the hinge is vertical (z)
    assert err(joint[0]).mean() < 0.02 and err(joint[0]).max() < 0.04, (err(joint[0]), err(est[0]))
    with pytest.raises(ValueError, match="2 step counts for 3 blur levels"):
        track_photometric(g, np.ones(len(labels), bool), labels, 1, imgs, vms, Ks, sh_degree=0,
                          background=np.zeros(3), steps=(5, 5), sigmas=(4.0, 2.0, 0.7))
    # a part that never moves keeps the identity (and nothing is fitted)
    rest, _ = track_photometric(g, np.ones(len(labels), bool), labels, 1, imgs, vms, Ks, sh_degree=0,
                                background=np.zeros(3), moving=np.zeros((1, t - 1), bool), log=logs.append)
    np.testing.assert_array_equal(rest, still)


def test_hinge_offset_measures_the_axis_from_the_centroid():
    pts = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 5.0], [0.0, -1.0, -5.0]])  # centroid 0
    radius = float(np.percentile(np.linalg.norm(pts, axis=1), 95))
    off, ratio = hinge_offset(pts, [0.0, 0.0, 2.0], [3.0, 4.0, 7.0])  # a vertical line 5 away; the axis unnormalised
    assert off == pytest.approx(5.0) and ratio == pytest.approx(5.0 / radius)
    off, _ = hinge_offset(pts, [1.0, 0.0, 0.0], [9.0, 0.0, 0.0])  # the line through the centroid
    assert off == pytest.approx(0.0, abs=1e-12)


def test_largest_turn_and_the_far_hinge_rule():
    """`largest_turn_deg` is the largest rotation angle of a pose sequence (0 for none or the identity, 180 for a
    half turn); `is_far_hinge` needs both more than 2 radii and a turn of 5 degrees or more, and a NaN ratio is
    never far."""
    turns = [np.radians(a) * np.array([0.6, 0.0, 0.8]) for a in (0.0, 12.5, 37.0, 3.0)]
    poses = np.stack([_pose(r, np.array([1.0, -2.0, 0.5])) for r in turns])
    assert largest_turn_deg(poses) == pytest.approx(37.0, abs=1e-4)
    assert largest_turn_deg(np.tile(np.eye(4), (3, 1, 1))) == 0.0 and largest_turn_deg(np.zeros((0, 4, 4))) == 0.0
    assert largest_turn_deg(_pose(np.array([np.pi, 0.0, 0.0]), np.zeros(3))) == pytest.approx(180.0, abs=1e-3)
    assert is_far_hinge(2.1, 5.0) and not is_far_hinge(2.0, 40.0) and not is_far_hinge(9.0, 4.99)
    assert not is_far_hinge(np.nan, 40.0) and is_far_hinge(1.5, 1.0, radii=1.0, turn=1.0)


@pytest.mark.parametrize("far", [False, True])
def test_joint_poses_warns_of_a_hinge_far_off_its_part(far):
    """Poses that turn a box 0.06 rad a frame about a vertical line: through its edge (0.8 radii from its
    centre, a door) they are fitted as a hinge there without a warning; about a line 4 radii away (a turn that
    mostly shifts the part, as the synthetic lid's failed tracking gives) also as a hinge, which is
    then warned of."""
    t = 6
    means, _, _, _, labels, vms, _ = _hinge_scene(t, 0.0)
    pts = means[labels == 0]
    cen = pts.mean(0)
    radius = float(np.percentile(np.linalg.norm(pts - cen, axis=1), 95))
    piv = cen + np.array([4.0 * radius, 0.0, 0.0]) if far else np.array([-0.3, 0.0, 0.0])
    poses = []
    for i in range(t):
        p = _pose([0.0, 0.0, 0.06 * i], [0.0, 0.0, 0.0])
        p[:3, 3] = piv - p[:3, :3] @ piv
        poses.append(p)
    poses = np.stack(poses)[None]
    logs = []
    joint, kinds, costs = joint_poses([pts], poses, vms, np.stack([K] * t), log=logs.append)
    assert kinds == ["revolute"] and costs[0] < 0.1, (kinds, costs, logs)
    np.testing.assert_allclose(joint, poses, atol=1e-4)
    ratio = float(logs[0].split("(")[-1].split(" radii")[0]) if "radii" in logs[0] else None
    assert ratio == pytest.approx(hinge_offset(pts, [0, 0, 1], piv)[1], abs=0.05), logs
    assert "turning up to 17.2 degrees" in logs[0], logs
    warned = [m for m in logs if "warning: object 1's hinge lies" in m]
    assert len(warned) == int(far), logs
    assert not any("explains its tracked poses poorly" in m for m in logs), logs


@pytest.mark.optimized  # run-time-bound: joint fits
def test_joint_poses_on_the_default_scenes_tracked_drawer_and_door():
    """The per-frame poses the photometric tracker gave the default scene's drawer and door in a full demo
    (tests/data/SOURCE.txt). The door turns 70 degrees in 4 of 60 frames: fitted as a hinge about the vertical,
    and the drawer as a slide. An inlier RMS per inlier fraction would put the door's two fits within 5% of each
    other and make the door a slide: a slide's large residuals in those 4 frames count as outliers, which that
    RMS leaves out. The robust cost keeps them. Both fit with
    costs under 4 px^2, so no warning."""
    from pathlib import Path

    from fgjax.articulate.track import fit_joint

    z = np.load(Path(__file__).resolve().parents[1] / "data" / "tracked_drawer_and_door.npz")
    poses, vms, Ks = (z[k].astype(np.float64) for k in ("poses", "viewmats", "Ks"))
    pts = [z["pts0"].astype(np.float64), z["pts1"].astype(np.float64)]
    logs = []
    joint, kinds, costs = joint_poses(pts, poses, vms, Ks, log=logs.append)
    assert kinds == ["prismatic", "revolute"], logs
    assert np.all(costs < 4.0) and not any("warning" in m for m in logs), (costs, logs)
    turn = np.asarray(geometry.so3_log(jnp.asarray(joint[1, :, :3, :3])))  # [T, 3]
    big = turn[np.argmax(np.linalg.norm(turn, axis=1))]
    assert np.degrees(np.linalg.norm(big)) > 50.0, turn
    assert abs(big[2]) / np.linalg.norm(big) > 0.95, big  # the scene's z is the world's vertical
    # what the old rule saw: the door's two fits within 5%
    t = poses.shape[1]
    moved = np.einsum("tij,mj->tmi", poses[1, :, :3, :3], pts[1]) + poses[1, :, None, :3, 3]
    cam = np.einsum("tij,tmj->tmi", vms[:, :3, :3], moved) + vms[:, None, :3, 3]
    tgt = np.einsum("tij,tmj->tmi", Ks[:, :2, :], cam / cam[..., 2:])  # [T, M, 2]
    fits = {c: fit_joint(np.repeat(pts[1][None], t, 0), tgt, np.ones(tgt.shape[:2]), vms, Ks, c, huber_px=2.0)
            for c in ("revolute", "prismatic")}
    old = {c: f[1] / f[2] for c, f in fits.items()}
    assert old["revolute"] > 0.95 * old["prismatic"], old
    assert fits["revolute"][5] < 0.9 * fits["prismatic"][5], {c: f[5] for c, f in fits.items()}


def test_track_photometric_starts_from_earlier_poses_when_they_render_closer():
    """`init_poses` (a previous round's fit) is a third start of each frame: given the true poses, one step
    per frame stays near them; without, one step per frame from the identity falls far behind the turn.
    A wrong shape is refused."""
    t = 6
    g, labels, vms, true = _coloured_hinge(t, 0.12)
    imgs = _images(g, labels, vms, true[None])
    Ks = np.stack([K] * t)
    pts = np.asarray(g.means)[labels == 0]
    kw = dict(sh_degree=0, background=np.zeros(3), steps=(1,), sigmas=(0.7,), radius=0.0, log=lambda s: None)
    errs = {}
    for name, init in (("given", true[None]), ("none", None)):
        est, _ = track_photometric(g, np.ones(len(labels), bool), labels, 1, imgs, vms, Ks, init_poses=init, **kw)
        a = np.einsum("tij,mj->tmi", est[0, :, :3, :3], pts) + est[0, :, None, :3, 3]
        b = np.einsum("tij,mj->tmi", true[:, :3, :3], pts) + true[:, None, :3, 3]
        errs[name] = float(np.linalg.norm(a - b, axis=-1).mean(1).max())
    # one Adam step moves each of the six coordinates by ~lr (0.02): ~0.03 off the truth at most
    assert errs["given"] < 0.05 and errs["none"] > 0.2, errs
    with pytest.raises(ValueError, match="init_poses"):
        track_photometric(g, np.ones(len(labels), bool), labels, 1, imgs, vms, Ks, init_poses=true, **kw)


@pytest.mark.optimized  # run-time-bound: photometric tracking
def test_track_photometric_soft_membership_tolerates_mislabelled_gaussians():
    """A fifth of the part marked static and a patch of the wall behind it marked as the part: with the labels
    as they are (radius 0) the fitted turn falls short; with the soft membership (candidates within 0.3)
    it is followed, and the membership learnt sides with the truth for most of the lost part Gaussians."""
    t = 6
    g, labels, vms, true = _coloured_hinge(t, 0.12)
    imgs = _images(g, labels, vms, true[None])
    rng = np.random.default_rng(3)
    part = np.flatnonzero(labels == 0)
    lost = rng.choice(part, len(part) // 5, replace=False)
    m = np.asarray(g.means)
    wall_near = np.flatnonzero((labels < 0) & (np.abs(m[:, 0]) < 0.2) & (np.abs(m[:, 2]) < 0.2))
    wrong = labels.copy()
    wrong[lost] = -1
    wrong[wall_near] = 0
    ang = lambda r: float(np.degrees(np.linalg.norm(np.asarray(geometry.so3_log(jnp.asarray(r))))))
    turn = ang(true[-1, :3, :3])
    fitted = {}
    for radius in (0.0, 0.3):
        est, pi = track_photometric(g, np.ones(len(labels), bool), wrong, 1, imgs, vms, np.stack([K] * t), sh_degree=0,
                                    background=np.zeros(3), steps=(15, 15, 10), radius=radius, log=lambda s: None)
        fitted[radius] = ang(est[0, -1, :3, :3])
    assert abs(fitted[0.3] - turn) < 3.0 < abs(fitted[0.0] - turn), (fitted, turn)
    assert np.mean(pi[lost] > 0.5) > 0.6, np.mean(pi[lost] > 0.5)


def test_mixed_copies_splits_each_candidates_opacity_between_its_two_copies():
    rng = np.random.default_rng(0)
    n = 7
    g = Gaussians(jnp.asarray(rng.normal(size=(n, 3))), jnp.zeros((n, 3)),
                  jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (n, 1)), jnp.asarray(rng.normal(size=n)), jnp.zeros((n, 1, 3)))
    cand = jnp.asarray([1, 4])
    moved = g.means + 1.0
    both = mixed_copies(g, moved, g.quats, cand, jnp.asarray([0.3, -1.0]))
    assert both.means.shape == (n + 2, 3)
    s = jax.nn.sigmoid
    o = np.asarray(s(g.opacity_logits))
    ob = np.asarray(s(both.opacity_logits))
    np.testing.assert_allclose(ob[[1, 4]] + ob[[n, n + 1]], o[[1, 4]], rtol=1e-6)  # shares add up
    np.testing.assert_allclose(ob[[0, 2, 3, 5, 6]], o[[0, 2, 3, 5, 6]], rtol=1e-12)  # others untouched
    np.testing.assert_allclose(np.asarray(both.means[n:]), np.asarray(g.means[cand]))  # static copies stay
    np.testing.assert_allclose(np.asarray(both.means[:n]), np.asarray(moved))
    extreme = mixed_copies(g, moved, g.quats, cand, jnp.asarray([80.0, -80.0]))
    assert np.all(np.isfinite(np.asarray(extreme.opacity_logits)))


def test_track_photometric_fitting_only_the_moving_objects_gives_the_same_poses():
    """Two objects that move in turn (the hinged part in pairs 0-1, then a patch of the wall sliding up in
    pairs 2-3). A frame redraws only the object it fits and pastes the rest, drawn once with the other
    object at its pose: without memberships (radius 0) that gives the poses of redrawing both at every
    step. Both objects are followed, and the one not fitted in a pair keeps its pose."""
    t = 5
    g, labels, vms, hinge = _coloured_hinge(t, 0.12)
    m = np.asarray(g.means)
    labels = labels.copy()
    labels[(labels < 0) & (m[:, 0] > 0.45) & (np.abs(m[:, 2]) < 0.5)] = 1  # the patch: next to the part in the images
    true = np.tile(np.eye(4), (2, t, 1, 1))
    true[0, :3] = hinge[:3]
    true[0, 3:] = hinge[2]  # the part turns in pairs 0-1, then rests
    true[1, 3, 2, 3], true[1, 4, 2, 3] = 0.06, 0.12  # the patch rests, then slides up in pairs 2-3
    imgs = _images(g, labels, vms, true)
    moving = np.array([[True, True, False, False], [False, False, True, True]])
    kw = dict(moving=moving, sh_degree=0, background=np.zeros(3), steps=(6, 4), sigmas=(2.0, 0.7), radius=0.0,
              log=lambda s: None)
    est = {flag: track_photometric(g, np.ones(len(labels), bool), labels, 2, imgs, vms, np.stack([K] * t),
                                   only_moving=flag, **kw)[0] for flag in (True, False)}
    np.testing.assert_allclose(est[True], est[False], atol=1e-9)
    e = est[True]
    np.testing.assert_array_equal(e[1, :3], np.tile(np.eye(4), (3, 1, 1)))  # not fitted before it moves
    np.testing.assert_array_equal(e[0, 3:], np.stack([e[0, 2]] * 2))  # nor after
    # followed: the part's turn (0.24) and the patch's rise (0.12; ten steps a frame reach about half of it)
    turn = float(np.linalg.norm(np.asarray(geometry.so3_log(jnp.asarray(e[0, 2, :3, :3])))))
    assert abs(turn - 0.24) < 0.05 and e[1, 4, 2, 3] > 0.04, (turn, e[1, 4, :3, 3])


def test_track_photometric_keeps_the_fixed_objects_poses_and_tracks_the_others():
    """The two objects of the test above, the patch ``fixed`` at given poses (its true ones, shifted by 0.01 so
    that they cannot be mistaken for a fit): its poses are those, exactly, in every frame; the part is still
    followed. With both fixed nothing is fitted. ``fixed`` without ``init_poses``, or of a wrong shape, is refused."""
    t = 5
    g, labels, vms, hinge = _coloured_hinge(t, 0.12)
    m = np.asarray(g.means)
    labels = labels.copy()
    labels[(labels < 0) & (m[:, 0] > 0.45) & (np.abs(m[:, 2]) < 0.5)] = 1
    true = np.tile(np.eye(4), (2, t, 1, 1))
    true[0, :3] = hinge[:3]
    true[0, 3:] = hinge[2]
    true[1, 3, 2, 3], true[1, 4, 2, 3] = 0.06, 0.12
    imgs = _images(g, labels, vms, true)
    given = true.astype(np.float32).copy()
    given[1, :, 0, 3] += 0.01
    kw = dict(moving=np.array([[True, True, False, False], [False, False, True, True]]), sh_degree=0,
              background=np.zeros(3), steps=(6, 4), sigmas=(2.0, 0.7), radius=0.0, log=lambda s: None)
    a = np.ones(len(labels), bool)
    e, _ = track_photometric(g, a, labels, 2, imgs, vms, np.stack([K] * t), init_poses=given, fixed=[False, True], **kw)
    np.testing.assert_array_equal(e[1], given[1])
    turn = float(np.linalg.norm(np.asarray(geometry.so3_log(jnp.asarray(e[0, 2, :3, :3])))))
    assert abs(turn - 0.24) < 0.05, turn
    e2, _, st = track_photometric(g, a, labels, 2, imgs, vms, np.stack([K] * t), init_poses=given, fixed=[True, True],
                                  return_stats=True, **kw)
    np.testing.assert_array_equal(e2, given)
    assert st["frames_fitted"] == 0
    with pytest.raises(ValueError, match="init_poses"):
        track_photometric(g, a, labels, 2, imgs, vms, np.stack([K] * t), fixed=[False, True], **kw)
    with pytest.raises(ValueError, match="fixed must be"):
        track_photometric(g, a, labels, 2, imgs, vms, np.stack([K] * t), init_poses=given, fixed=[True], **kw)


def test_converged_joints():
    """Converged: the same kind and an axis within the limit, either sign; a changed kind, a larger turn of the
    axis, a kept object (nan axis) or a limit of 0 are not. Mismatched lengths are refused."""
    c = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
    a = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    b = np.array([[c[0], c[1], 0], [0, -2.0, 0], [0, c[1], c[0]], [c[0], c[1], 0], [np.nan] * 3, [0, 1.0, 0]])
    ka = ["revolute", "prismatic", "revolute", "revolute", "revolute", "prismatic"]
    kb = ["revolute", "prismatic", "revolute", "prismatic", "kept", "prismatic"]
    np.testing.assert_array_equal(converged_joints(ka, a, kb, b, 20.0), [True, True, True, False, False, False])
    np.testing.assert_array_equal(converged_joints(ka, a, kb, b, 5.0), [False, True, False, False, False, False])
    assert not converged_joints(ka, a, kb, b, 0.0).any()
    with pytest.raises(ValueError, match="converged_joints"):
        converged_joints(ka[:2], a, kb, b, 20.0)


def test_tile_region_and_rects_meeting_match_a_brute_force_loop():
    rng = np.random.default_rng(3)
    nty, ntx = 7, 11
    x0, y0 = rng.integers(-2, ntx + 1, 200), rng.integers(-2, nty + 1, 200)
    rects = np.stack([x0, y0, x0 + rng.integers(0, 4, 200), y0 + rng.integers(0, 4, 200)], 1)  # some empty
    on = rng.random(200) < 0.1
    for margin in (0, 1, 3):
        ref = np.zeros((nty, ntx), bool)
        for (a, b, c, d), o in zip(rects, on, strict=True):
            if o and c > a and d > b:
                ref[max(b - margin, 0):max(d + margin, 0), max(a - margin, 0):max(c + margin, 0)] = True
        region = tile_region(rects, on, nty, ntx, margin)
        np.testing.assert_array_equal(region, ref)
        meet = [c > a and d > b and region[max(b, 0):max(d, 0), max(a, 0):max(c, 0)].any() for a, b, c, d in rects]
        np.testing.assert_array_equal(rects_meeting(rects, region), meet)
        assert 0 < np.sum(meet) < len(rects)
    assert not tile_region(rects, np.zeros(200, bool), nty, ntx, 2).any()
    assert [subset_bucket(n, 100) for n in (0, 50, 51, 75, 76, 100)] == [50, 50, 75, 75, 100, 100]


def test_track_photometric_drawing_only_the_gaussians_near_the_moving_parts_gives_the_same_poses(monkeypatch):
    """A frame's steps draw the changing Gaussians and only the others whose rectangles meet the tiles they
    reach (`subset_margin`): the same poses and memberships as drawing every Gaussian, with fewer drawn. The
    check is sensitive: leaving out the static Gaussians in front of and behind the part (`rects_meeting`
    always false) moved the poses by more than 1e-3 (not repeated here, for time)."""
    from fgjax.articulate import phototrack

    t = 3
    g, labels, vms, hinge = _coloured_hinge(t, 0.12)
    # static posters at both sides, far from the part, seen in a wide image (256x96)
    rng = np.random.default_rng(2)
    side = rng.uniform([2.2, 0.9, -0.9], [3.0, 0.9, 0.9], (600, 3))
    side[::2, 0] *= -1  # half on the left
    n = len(side)
    g = Gaussians(jnp.concatenate([g.means, jnp.asarray(side)]),
                  jnp.concatenate([g.log_scales, jnp.full((n, 3), np.log(0.05))]),
                  jnp.concatenate([g.quats, jnp.tile(jnp.asarray([[1.0, 0, 0, 0]]), (n, 1))]),
                  jnp.concatenate([g.opacity_logits, jnp.full(n, 2.0)]),
                  jnp.concatenate([g.sh, jnp.asarray(rng.random((n, 1, 3)) - 0.5)]))
    labels = np.concatenate([labels, np.full(n, -1)])
    k2 = K * np.array([[2.0], [2.0], [1.0]]) + np.array([[0, 0, 2.0 * W], [0, 0, 0], [0, 0, 0]])
    imgs = _images(g, labels, vms, hinge[None], k2, 4 * W, 2 * H)
    kw = dict(sh_degree=0, background=np.zeros(3), steps=(4, 2), sigmas=(2.0, 0.7), radius=0.1, log=lambda m: None)
    run = lambda: track_photometric(g, np.ones(len(labels), bool), labels, 1, imgs, vms, np.stack([k2] * t),
                                    subset_margin=2, return_stats=True, **kw)
    # the reference: a part that leaves its region (here: the region cut to one tile) has its frame fitted
    # again from its start with every Gaussian, so with one tile every frame is the full render's fit
    # (`subset_margin=None` gives these poses; one run fewer, for time)
    real_region = phototrack.tile_region

    def one_tile(*a):
        r = real_region(*a)
        out = np.zeros_like(r)
        out[tuple(np.argwhere(r)[0])] = True
        return out

    monkeypatch.setattr(phototrack, "tile_region", one_tile)
    p_all, pi_all, st_all = run()
    monkeypatch.setattr(phototrack, "tile_region", real_region)
    p_sub, pi_sub, st_sub = run()
    assert st_all["fitted_again"] == t - 1 and st_all["drawn_per_step"] == st_all["gaussians"], st_all
    assert st_sub["fitted_again"] == 0, st_sub
    assert st_sub["drawn_per_step"] < 0.8 * st_all["drawn_per_step"], st_sub  # the subset is smaller than the scene
    np.testing.assert_allclose(p_sub, p_all, atol=1e-5)
    np.testing.assert_allclose(pi_sub, pi_all, atol=1e-5)
    assert np.abs(p_all[0, -1] - np.eye(4)).max() > 0.05  # the part was followed, not left at rest


def test_rest_spans_are_the_still_runs_after_a_fitted_frame_with_the_pose_off_rest():
    """(k, a, b): object k not fitted in frames a..b-1, fitted in frame a-1 (frame n is fitted when pair
    (n-1, n) moves), and its pose there off the identity; the runs before any fitted frame, the fixed objects
    and the poses at rest are left out; a non-finite pose counts as off; a wrong shape is refused."""
    t = 8
    poses = np.tile(np.eye(4), (3, t, 1, 1))
    poses[0, 3:, 0, 3] = 0.1  # object 1 off rest from frame 3 on
    poses[1, :, :3, :3] = np.asarray(geometry.so3_exp(jnp.asarray([0.0, 0.0, 0.01])))  # 0.57 degrees
    poses[2, 5:] = np.nan
    moving = np.zeros((3, t - 1), bool)
    moving[0, [1, 2, 5]] = True  # frames 2, 3 and 6 fitted: still runs 4-5 and 7
    moving[1, 0] = True  # frame 1 fitted: still run 2-7
    moving[2, 3] = True  # frame 4 fitted: still run 5-7, nan there
    assert rest_spans(moving, poses) == [(0, 4, 6), (0, 7, 8), (1, 2, 8), (2, 5, 8)]
    assert rest_spans(moving, poses, fixed=[False, True, True]) == [(0, 4, 6), (0, 7, 8)]
    assert rest_spans(moving, poses, tol_deg=1.0) == [(0, 4, 6), (0, 7, 8), (2, 5, 8)]
    assert rest_spans(np.zeros((3, t - 1), bool), poses) == []  # nothing fitted: nothing to undo
    with pytest.raises(ValueError, match="moving must be"):
        rest_spans(moving[:, 1:], poses)


def test_track_photometric_puts_a_part_back_at_rest_where_its_images_show_it_there():
    """A part turns 0.12 rad a frame in frames 1-2 (the moving pairs) and the images show it back at rest in
    frames 3-5, which are not fitted: without ``rest_check`` it keeps frame 2's turn there; with it, the span
    is rendered at rest as well and takes the identity, which is the truth. Where the images show the part
    still open, the fitted pose stays."""
    t = 6
    g, labels, vms, hinge = _coloured_hinge(t, 0.12)
    back = hinge.copy()
    back[3:] = np.eye(4)
    kept = hinge.copy()
    kept[3:] = hinge[2]
    Ks = np.stack([K] * t)
    moving = np.array([[True, True, False, False, False]])
    kw = dict(moving=moving, sh_degree=0, background=np.zeros(3), steps=(15, 15, 10), radius=0.0)
    a = np.ones(len(labels), bool)
    ang = lambda r: float(np.degrees(np.linalg.norm(np.asarray(geometry.so3_log(jnp.asarray(r))))))
    imgs = _images(g, labels, vms, back[None])
    off, _ = track_photometric(g, a, labels, 1, imgs, vms, Ks, log=lambda s: None, **kw)
    assert all(ang(off[0, n, :3, :3]) > 10.0 for n in range(3, t))  # frame 2's turn (13.8 degrees) kept
    logs = []
    on, _, st = track_photometric(g, a, labels, 1, imgs, vms, Ks, rest_check=True, return_stats=True,
                                  log=logs.append, **kw)
    np.testing.assert_array_equal(on[0, 3:], np.tile(np.eye(4), (3, 1, 1)))
    np.testing.assert_array_equal(on[0, :3], off[0, :3])  # the fitted frames are untouched
    assert st["spans_at_rest"] == 1 and any("object 1 back at rest in frames 4-6" in m for m in logs), logs
    imgs_open = _images(g, labels, vms, kept[None])
    logs = []
    op, _, st_open = track_photometric(g, a, labels, 1, imgs_open, vms, Ks, rest_check=True, return_stats=True,
                                       log=logs.append, **kw)
    assert any("object 1 keeps its last fitted pose in frames 4-6" in m for m in logs), logs
    assert st_open["spans_at_rest"] == 0 and all(ang(op[0, n, :3, :3]) > 10.0 for n in range(3, t))


def _hinge_at(angle: float) -> np.ndarray:
    """[4, 4]: `_hinge_scene`'s part turned by ``angle`` (rad) about its hinge."""
    piv = np.array([-0.3, 0.0, 0.0])
    p = _pose([0.0, 0.0, angle], [0.0, 0.0, 0.0])
    p[:3, 3] = piv - p[:3, :3] @ piv
    return p


def test_settle_at_rest_puts_a_part_fitted_past_rest_back_and_keeps_what_the_images_show():
    """A part opens in frames 1-2, closes in frame 3 and rests after. The poses given were fitted past rest in frame 3
    (turned the other way, -0.12 rad) and kept there in frames 4-6, which were not fitted: the span and frame 3 go
    to rest, frames 1-2 (open in the images) keep their poses. Where the images show the part staying at frame 3's
    pose, nothing changes; where they show it at rest only from frame 4, frame 3 keeps its pose and the span
    settles."""
    t = 7
    g, labels, vms, _ = _coloured_hinge(t, 0.12)
    Ks = np.stack([K] * t)
    alive = np.ones(len(labels), bool)
    moving = np.array([[True, True, True, False, False, False]])
    given = np.stack([_hinge_at(a) for a in (0.0, 0.12, 0.24, -0.12, -0.12, -0.12, -0.12)])[None]
    kw = dict(sh_degree=0, background=np.zeros(3))

    def settle(truth_angles):
        truth = np.stack([_hinge_at(a) for a in truth_angles])[None]
        logs = []
        out, spans = settle_at_rest(g, alive, labels, 1, _images(g, labels, vms, truth), vms, Ks, given, moving,
                                    log=logs.append, **kw)
        return out, spans, logs

    out, spans, logs = settle((0.0, 0.12, 0.24, 0.0, 0.0, 0.0, 0.0))
    assert spans == [(0, 3, 7)] and any("object 1 settled at rest in frames 4-7" in m for m in logs), logs
    np.testing.assert_array_equal(out[0, 3:], np.tile(np.eye(4, dtype=np.float32), (4, 1, 1)))
    np.testing.assert_array_equal(out[0, :3], given[0, :3].astype(np.float32))
    out, spans, logs = settle((0.0, 0.12, 0.24, -0.12, -0.12, -0.12, -0.12))
    assert spans == [] and len(logs) == 1 and "0 of 1 still span(s) settled" in logs[0], logs
    np.testing.assert_array_equal(out, given.astype(np.float32))
    out, spans, _ = settle((0.0, 0.12, 0.24, -0.12, 0.0, 0.0, 0.0))
    assert spans == [(0, 4, 7)]
    np.testing.assert_array_equal(out[0, :4], given[0, :4].astype(np.float32))
    np.testing.assert_array_equal(out[0, 4:], np.tile(np.eye(4, dtype=np.float32), (3, 1, 1)))


def test_settle_at_rest_checks_its_shapes_and_passes_empty_inputs_through():
    t = 4
    g, labels, vms, _ = _coloured_hinge(t, 0.12)
    imgs = np.zeros((t, H, W, 3), np.float32)
    Ks = np.stack([K] * t)
    alive = np.ones(len(labels), bool)
    kw = dict(sh_degree=0, background=np.zeros(3), log=lambda m: None)
    with pytest.raises(ValueError, match="poses must be"):
        settle_at_rest(g, alive, labels, 1, imgs, vms, Ks, np.tile(np.eye(4), (1, t - 1, 1, 1)),
                       np.ones((1, t - 2), bool), **kw)
    with pytest.raises(ValueError, match="moving must be"):
        settle_at_rest(g, alive, labels, 1, imgs, vms, Ks, np.tile(np.eye(4), (1, t, 1, 1)),
                       np.ones((1, t - 2), bool), **kw)
    none = np.zeros((0, t, 4, 4))
    out, spans = settle_at_rest(g, alive, -np.ones_like(labels), 0, imgs, vms, Ks, none, np.zeros((0, t - 1), bool),
                                **kw)
    assert out.shape == (0, t, 4, 4) and spans == []
