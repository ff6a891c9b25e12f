"""Rigid object tracking from flow (`fgjax.articulate.track`; the rigid camera increment of `fgjax.method.camera`)
against known motions."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import look_at

from fgjax import geometry
from fgjax.articulate.track import field_poses, track_objects
from fgjax.geometry import quat_multiply
from fgjax.method.camera import rigid_increment
from fgjax.models.posed import transform_gaussians

K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
W, H = 64, 48


def _project(vm, p):
    q = p @ vm[:3, :3].T + vm[:3, 3]
    return np.stack([K[0, 0] * q[..., 0] / q[..., 2] + K[0, 2], K[1, 1] * q[..., 1] / q[..., 2] + K[1, 2]], -1)


def _pose(omega, t):
    p = np.eye(4)
    p[:3, :3] = np.asarray(geometry.so3_exp(jnp.asarray(omega, jnp.float64)))
    p[:3, 3] = t
    return p


def test_quaternion_product_and_transform_match_rotation_matrices():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4))
    r = np.asarray(geometry.so3_exp(jnp.asarray(rng.normal(size=3))))
    qr = np.asarray(geometry.rotmat_to_quat(jnp.asarray(r)))
    prod = np.asarray(quat_multiply(qr, q))
    np.testing.assert_allclose(np.linalg.norm(prod, axis=-1), np.linalg.norm(q, axis=-1), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(geometry.quat_to_rotmat(jnp.asarray(prod))),
                               r @ np.asarray(geometry.quat_to_rotmat(jnp.asarray(q))), atol=1e-9)
    means = rng.normal(size=(5, 3))
    labels = np.array([0, -1, 1, 0, -1])
    poses = np.stack([_pose([0.1, 0.2, -0.3], [0.5, 0, 0]), np.eye(4)])
    m, qq = transform_gaussians(jnp.asarray(means), jnp.asarray(q), jnp.asarray(labels), jnp.asarray(poses))
    m, qq = np.asarray(m), np.asarray(qq)
    np.testing.assert_allclose(m[[1, 2, 4]], means[[1, 2, 4]], atol=1e-12)  # static, and the identity pose
    np.testing.assert_allclose(m[[0, 3]], means[[0, 3]] @ poses[0][:3, :3].T + poses[0][:3, 3], atol=1e-12)
    np.testing.assert_allclose(qq[1], q[1])


def test_rigid_increment_recovers_a_motion_despite_outliers():
    rng = np.random.default_rng(1)
    vm = look_at(np.array([0.0, -3.0, 0.5]))
    pts = rng.uniform(-0.3, 0.3, (400, 3))
    true = _pose([0.05, -0.1, 0.08], [0.04, -0.02, 0.06])
    target = _project(vm, pts @ true[:3, :3].T + true[:3, 3])
    target[:40] += rng.normal(0, 15.0, (40, 2))  # 10% gross outliers
    pad = 100  # padding rows (weight 0) must not matter
    pts_p = np.concatenate([pts, rng.normal(size=(pad, 3))])
    tgt_p = np.concatenate([target, rng.normal(size=(pad, 2))])
    w = np.concatenate([np.ones(400), np.zeros(pad)]).astype(np.float32)
    delta, rms = rigid_increment(pts_p, tgt_p, w, jnp.asarray(vm, jnp.float32), jnp.asarray(K, jnp.float32))
    delta = np.asarray(delta, np.float64)
    np.testing.assert_allclose(delta[:3, :3], true[:3, :3], atol=3e-3)
    np.testing.assert_allclose(delta[:3, 3], true[:3, 3], atol=3e-3)
    assert float(rms) < 0.2
    # no motion: identity
    delta, _ = rigid_increment(pts, _project(vm, pts), np.ones(400, np.float32), jnp.asarray(vm, jnp.float32),
                               jnp.asarray(K, jnp.float32))
    np.testing.assert_allclose(np.asarray(delta), np.eye(4), atol=1e-4)


def _rendered_flow(means, quats, scales, opac, labels, pose_a, pose_b, vm_a, vm_b):
    """Exact flow a -> b of the rendered scene: each pixel's expected-depth point moves with its object."""
    from fgjax.render.api import rasterization

    m_a, q_a = transform_gaussians(jnp.asarray(means), jnp.asarray(quats), jnp.asarray(labels),
                                   jnp.asarray(pose_a[None]))
    onehot = np.stack([labels < 0, labels >= 0], -1).astype(np.float64)
    feat, alpha, info = rasterization(m_a, q_a, scales, opac, onehot, jnp.asarray(vm_a), jnp.asarray(K), W, H,
                                      render_depth=True)
    feat, alpha, depth = np.asarray(feat), np.asarray(alpha), np.asarray(info["depth"])
    ys, xs = np.mgrid[0:H, 0:W]
    pix = np.stack([xs + 0.5, ys + 0.5], -1)
    ray = np.concatenate([pix, np.ones((H, W, 1))], -1) @ np.linalg.inv(K).T
    c2w = np.linalg.inv(vm_a)
    p = (ray * depth[..., None]) @ c2w[:3, :3].T + c2w[:3, 3]
    rel = pose_b @ np.linalg.inv(pose_a)
    obj = feat[..., 1] > 0.5 * alpha
    p_b = np.where(obj[..., None], p @ rel[:3, :3].T + rel[:3, 3], p)
    flow = _project(vm_b, p_b) - pix
    return np.where((alpha > 0.5)[..., None], flow, np.nan)


def test_track_objects_recovers_rigid_poses_from_exact_flow():
    rng = np.random.default_rng(2)
    # a static wall of Gaussians and a small box-shaped object in front of it
    wall = np.stack(np.meshgrid(np.linspace(-1.5, 1.5, 30), [1.0], np.linspace(-1.0, 1.0, 20)), -1).reshape(-1, 3)
    obj = rng.uniform([-0.3, -0.3, -0.3], [0.3, 0.0, 0.3], (300, 3))
    means = np.concatenate([wall, obj])
    n = len(means)
    labels = np.concatenate([np.full(len(wall), -1), np.zeros(len(obj), int)])
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    scales = np.concatenate([np.full((len(wall), 3), 0.07), np.full((len(obj), 3), 0.04)])
    opac = np.full(n, 0.9)
    t = 5
    vms = np.stack([look_at(np.array([0.3 * (i - 2) / 2, -3.0, 0.4])) for i in range(t)])
    # a general motion (no articulation): the turn alternates between two axes, and the object also slides
    poses = [np.eye(4)]
    for i in range(1, t):
        inc = _pose([0.0, 0.0, 0.12] if i % 2 else [0.12, 0.0, 0.0], [0.03, 0.0, 0.02])
        poses.append(inc @ poses[-1])
    poses = np.stack(poses)
    flows = np.stack([_rendered_flow(means, quats, scales, opac, labels, poses[i], poses[i + 1], vms[i], vms[i + 1])
                      for i in range(t - 1)])
    est = track_objects(means, quats, scales, opac, labels, 1, vms, np.stack([K] * t), flows, W, H,
                        log=lambda m: None)
    assert est.shape == (1, t, 4, 4)
    np.testing.assert_allclose(est[0, 0], np.eye(4))
    np.testing.assert_allclose(est[0, :, :3, :3], poses[:, :3, :3], atol=0.01)
    np.testing.assert_allclose(est[0, :, :3, 3], poses[:, :3, 3], atol=0.01)
    # the per-frame geometry (the scene as reconstructed at each frame) gives the same poses
    per = [transform_gaussians(jnp.asarray(means), jnp.asarray(quats), jnp.asarray(labels), jnp.asarray(p[None]))
           for p in poses]
    logs_f = []
    est_f = track_objects(np.stack([np.asarray(m) for m, _ in per]), np.stack([np.asarray(q) for _, q in per]),
                          np.stack([scales] * t), opac, labels, 1, vms, np.stack([K] * t), flows, W, H,
                          log=logs_f.append)
    np.testing.assert_allclose(est_f[0, :, :3, :3], poses[:, :3, :3], atol=0.01)
    np.testing.assert_allclose(est_f[0, :, :3, 3], poses[:, :3, 3], atol=0.01)
    # a hinge (turns about a fixed vertical axis at the object's edge): with the per-frame geometry the
    # articulation fit is tried, chosen, and gives the poses
    hinge = []
    for i in range(t):
        p = _pose([0.0, 0.0, 0.12 * i], [0.0, 0.0, 0.0])
        piv = np.array([-0.3, 0.0, 0.0])
        p[:3, 3] = piv - p[:3, :3] @ piv
        hinge.append(p)
    hinge = np.stack(hinge)
    flows_h = np.stack([_rendered_flow(means, quats, scales, opac, labels, hinge[i], hinge[i + 1], vms[i], vms[i + 1])
                        for i in range(t - 1)])
    per_h = [transform_gaussians(jnp.asarray(means), jnp.asarray(quats), jnp.asarray(labels), jnp.asarray(p[None]))
             for p in hinge]
    logs = []
    est_h = track_objects(np.stack([np.asarray(m) for m, _ in per_h]), np.stack([np.asarray(q) for _, q in per_h]),
                          np.stack([scales] * t), opac, labels, 1, vms, np.stack([K] * t), flows_h, W, H,
                          log=logs.append)
    assert any("-> revolute" in m for m in logs), logs
    np.testing.assert_allclose(est_h[0, :, :3, :3], hinge[:, :3, :3], atol=0.01)
    np.testing.assert_allclose(est_h[0, :, :3, 3], hinge[:, :3, 3], atol=0.01)
    # the general motion above is no articulation: the pair-by-pair poses were kept
    assert any("-> pair by pair" in m for m in logs_f), logs_f
    with pytest.raises(ValueError, match="joints"):
        track_objects(means, quats, scales, opac, labels, 1, vms, np.stack([K] * t), flows, W, H, joints="yes")
    # pairs marked as resting keep the pose: the increment of pair 1 is skipped, the others still apply
    moving = np.array([[True, False, True, True]])
    est_m = track_objects(means, quats, scales, opac, labels, 1, vms, np.stack([K] * t), flows, W, H,
                          moving=moving, log=lambda m: None)
    np.testing.assert_allclose(est_m[0, 2], est_m[0, 1])
    np.testing.assert_allclose(est_m[0, 1, :3, 3], poses[1, :3, 3], atol=0.01)
    assert not np.allclose(est_m[0, 3], est_m[0, 2], atol=1e-3)
    still = track_objects(means, quats, scales, opac, labels, 1, vms, np.stack([K] * t), flows, W, H,
                          moving=np.zeros((1, t - 1), bool), log=lambda m: None)
    np.testing.assert_array_equal(still, np.tile(np.eye(4), (1, t, 1, 1)))
    # no objects / one frame: identities, no work
    assert track_objects(means, quats, scales, opac, np.full(n, -1), 0, vms, np.stack([K] * t), flows, W, H,
                         log=lambda m: None).shape == (0, t, 4, 4)


def test_camera_correction_removes_a_pose_error_from_u_cam_despite_moving_pixels():
    from fgjax import flow as fl
    from fgjax.method.camera import camera_correction

    rng = np.random.default_rng(3)
    h, w = 48, 64
    K = np.array([[60.0, 0, w / 2], [0, 60.0, h / 2], [0, 0, 1]])
    vm0 = look_at(np.array([0.0, -3.0, 0.4]))
    vm1 = look_at(np.array([0.15, -2.95, 0.42]))
    ys, xs = np.mgrid[0:h, 0:w]
    depth = 2.5 + 0.5 * np.sin(xs / 9.0) + 0.3 * np.cos(ys / 7.0)  # a smooth surface in front of camera 0
    c2w = lambda v: np.linalg.inv(v)
    u_true, ok = fl.reprojection_flow(depth, K, c2w(vm0), c2w(vm1))
    u_obs = np.array(u_true, np.float64)
    moving = np.zeros((h, w), bool)
    moving[10:25, 30:50] = True  # a part moving 3-6 px: outliers of the camera fit
    u_obs[moving] += rng.uniform(3, 6, size=(moving.sum(), 2))
    # the written pose of camera 1 is off by 0.5 degree and 2 cm
    xi = np.concatenate([rng.normal(size=3), rng.normal(size=3)])
    xi[:3] *= np.radians(0.5) / np.linalg.norm(xi[:3])
    xi[3:] *= 0.02 / np.linalg.norm(xi[3:])
    noisy = np.asarray(geometry.se3_exp(jnp.asarray(xi))) @ vm1
    err = lambda v: np.abs(np.asarray(fl.reprojection_flow(depth, K, c2w(vm0), c2w(v))[0]) - np.asarray(u_true))
    static = np.asarray(ok) & ~moving
    assert np.median(err(noisy)[static]) > 0.2  # the pose error shows up as flow on static pixels
    fixed, rms, used = camera_correction(depth, np.asarray(ok), u_obs, vm0, noisy, K)
    assert used == int(np.asarray(ok).sum()) and rms < 1e-6
    assert np.max(err(fixed)[static]) < 1e-6  # u_cam is right again on every static pixel
    r = np.linalg.norm(u_obs - np.asarray(fl.reprojection_flow(depth, K, c2w(vm0), c2w(fixed))[0]), axis=-1)
    assert np.all(r[moving] > 2.5)  # ... and the moving part still stands out
    # a strided subset gives the same exact answer
    sub, rms3, n3 = camera_correction(depth, np.asarray(ok), u_obs, vm0, noisy, K, max_pixels=500)
    assert n3 == 500 and np.max(err(sub)[static]) < 1e-6
    # too few usable pixels: the pose is returned unchanged
    out, rms2, n = camera_correction(depth, np.zeros((h, w), bool), u_obs, vm0, noisy, K)
    np.testing.assert_array_equal(out, noisy)
    assert n == 0 and np.isnan(rms2)


def _hinged_patch_pairs(kind, amounts, seed=0):
    """A planar 0.3 x 0.4 patch (a door face) seen from the front, moved pair by pair about a vertical
    hinge at its left edge (revolute) or along the viewing direction (prismatic): the exact data of
    `fit_joint` (points of the first frame of each pair, their pixels in the second)."""
    rng = np.random.default_rng(seed)
    vm = look_at(np.array([0.1, -2.0, 0.3]))
    base = np.stack([rng.uniform(0.0, 0.3, 200), np.zeros(200), rng.uniform(0.0, 0.4, 200)], -1)
    pivot, axis = np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    direction = np.array([0.0, -1.0, 0.0])
    pts, tgt, pose = [], [], np.eye(4)
    for a in amounts:
        cur = base @ pose[:3, :3].T + pose[:3, 3]
        if kind == "revolute":
            inc = _pose(axis * a, [0.0, 0.0, 0.0])
            inc[:3, 3] = pivot - inc[:3, :3] @ pivot
        else:
            inc = _pose([0.0, 0.0, 0.0], direction * a)
        nxt = cur @ inc[:3, :3].T + inc[:3, 3]
        pts.append(cur)
        tgt.append(_project(vm, nxt))
        pose = inc @ pose
    j = len(amounts)
    return np.stack(pts), np.stack(tgt), np.ones((j, 200)), np.stack([vm] * j), np.stack([K] * j), axis, direction


def test_fit_joint_recovers_a_hinge_and_a_slide_over_all_pairs():
    from fgjax.articulate.track import fit_joint

    amounts = np.array([0.06, 0.17, 0.24, 0.26, 0.0, -0.2, -0.25])  # radians per pair (a door opening 42 deg)
    pts, tgt, w, vms, Ks, axis, _ = _hinged_patch_pairs("revolute", amounts)
    inc, rms, frac, ax, piv, cost = fit_joint(pts, tgt, w, vms, Ks, "revolute")
    assert rms < 1e-3 and frac == 1.0 and 0.0 <= cost < 1e-6
    assert abs(abs(np.dot(ax, axis)) - 1.0) < 1e-6
    angles = np.arccos(np.clip((np.trace(inc[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    np.testing.assert_allclose(angles, np.abs(amounts), atol=1e-4)
    for jj in range(len(amounts)):  # each increment moves the points onto their targets
        moved = pts[jj] @ inc[jj, :3, :3].T + inc[jj, :3, 3]
        np.testing.assert_allclose(_project(vms[jj], moved), tgt[jj], atol=1e-3)
    # a slide: the prismatic fit is exact, the revolute one is not
    pts, tgt, w, vms, Ks, _, direction = _hinged_patch_pairs("prismatic", np.array([0.02, 0.05, 0.05, -0.04]))
    inc_p, rms_p, _, d, _, _ = fit_joint(pts, tgt, w, vms, Ks, "prismatic")
    assert rms_p < 1e-3 and abs(abs(np.dot(d, direction)) - 1.0) < 1e-6
    np.testing.assert_allclose(inc_p[:, :3, :3], np.tile(np.eye(3), (4, 1, 1)), atol=1e-12)
    # padding rows and a pair without data: no effect, and that pair's increment is the identity
    w2 = w.copy()
    w2[2] = 0.0
    inc_z, rms_z, _, _, _, _ = fit_joint(pts, tgt, w2, vms, Ks, "prismatic")
    assert rms_z < 1e-3
    np.testing.assert_allclose(inc_z[2], np.eye(4), atol=1e-6)
    with pytest.raises(ValueError, match="kind"):
        fit_joint(pts, tgt, w, vms, Ks, "ball")


def _hinge_scene(t: int, step: float):
    """A wall, a box-shaped part in front of it turning about a vertical hinge at its edge by `step` per
    frame, cameras sliding sideways: (means, quats, scales, opac, labels, vms, true poses [t, 4, 4])."""
    rng = np.random.default_rng(5)
    wall = np.stack(np.meshgrid(np.linspace(-1.5, 1.5, 30), [1.0], np.linspace(-1.0, 1.0, 20)), -1).reshape(-1, 3)
    obj = rng.uniform([-0.3, -0.3, -0.3], [0.3, 0.0, 0.3], (300, 3))
    means = np.concatenate([wall, obj])
    labels = np.concatenate([np.full(len(wall), -1), np.zeros(len(obj), int)])
    quats = np.tile([1.0, 0, 0, 0], (len(means), 1))
    scales = np.concatenate([np.full((len(wall), 3), 0.07), np.full((len(obj), 3), 0.04)])
    vms = np.stack([look_at(np.array([0.3 * (i - t / 2) / t, -3.0, 0.4])) for i in range(t)])
    piv = np.array([-0.3, 0.0, 0.0])
    true = []
    for i in range(t):
        p = _pose([0.0, 0.0, step * i], [0.0, 0.0, 0.0])
        p[:3, 3] = piv - p[:3, :3] @ piv
        true.append(p)
    return means, quats, scales, np.full(len(means), 0.9), labels, vms, np.stack(true)


def test_field_poses_recover_each_objects_rigid_motion_from_the_deformed_centres():
    """`field_poses`: two objects moved rigidly (a turn with a shift, a slide) and static Gaussians left alone over
    four frames; the poses fitted from the reference centres to the deformed ones are the true ones, frame 0 the
    identity; a field that moves nothing gives the identity; no objects, an empty [0, T, 4, 4]."""
    rng = np.random.default_rng(0)
    ref = rng.normal(size=(60, 3))
    labels = np.repeat([0, 1, -1], 20)
    true = np.tile(np.eye(4), (2, 4, 1, 1))
    for t in range(1, 4):
        true[0, t] = _pose([0.0, 0.2 * t, 0.05 * t], [0.1 * t, 0.0, -0.05 * t])
        true[1, t] = _pose([0.0, 0.0, 0.0], [0.0, 0.08 * t, 0.0])
    means = np.stack([np.where((labels >= 0)[:, None],
                               np.einsum("nij,nj->ni", true[np.clip(labels, 0, 1), t, :3, :3], ref)
                               + true[np.clip(labels, 0, 1), t, :3, 3], ref) for t in range(4)])
    est = field_poses(ref, means, labels, 2)
    assert est.shape == (2, 4, 4, 4)
    np.testing.assert_allclose(est, true, atol=2e-5)
    np.testing.assert_allclose(field_poses(ref, np.stack([ref] * 4), labels, 2), np.tile(np.eye(4), (2, 4, 1, 1)),
                               atol=1e-6)
    assert field_poses(ref, means, np.full(60, -1), 0).shape == (0, 4, 4, 4)


def test_tracked_poses_read_off_the_field_when_asked():
    """`fgjax.articulate.pipeline.tracked_poses` with ``track_from = "field"``: the poses of a run whose field turns
    object 0 and leaves the rest, at the training times in time order (the frames stored out of order), without
    the flow (None here: a tracker that reads it would fail)."""
    import dataclasses
    import types

    from fgjax.articulate.pipeline import tracked_poses
    from fgjax.config import ArticulateConfig

    rng = np.random.default_rng(1)
    ref = rng.normal(size=(30, 3))
    labels = np.repeat([0, -1], 15)
    times = np.array([0.0, 1.0, 0.5])
    order = np.argsort(times)

    def deformed(t):
        pose = _pose([0.0, 0.0, 0.4 * t], [0.2 * t, 0.0, 0.0])
        moved = ref @ pose[:3, :3].T + pose[:3, 3]
        return jnp.asarray(np.where((labels == 0)[:, None], moved, ref)), None, None

    run = types.SimpleNamespace(deformed=deformed)
    scene = types.SimpleNamespace(times=times)
    cfg = dataclasses.replace(ArticulateConfig(), track_from="field", track_photo=0)
    poses, joints = tracked_poses(run, scene, order, types.SimpleNamespace(means=ref), labels, 1, None, cfg,
                                  log=lambda *a: None)
    assert joints == {}
    np.testing.assert_allclose(poses[0], np.stack([_pose([0.0, 0.0, 0.4 * t], [0.2 * t, 0.0, 0.0])
                                                   for t in times[order]]), atol=2e-5)

    # the caller's centres (`discover_run`'s), read as given: the field is not deformed again
    centres = np.stack([np.asarray(deformed(t)[0]) for t in times[order]])

    def no_deform(t):
        raise AssertionError("deformed again")

    given, _ = tracked_poses(types.SimpleNamespace(deformed=no_deform), scene, order, types.SimpleNamespace(means=ref),
                             labels, 1, None, cfg, log=lambda *a: None, centres=centres)
    np.testing.assert_allclose(given, poses, atol=1e-6)
