"""Camera poses from optical flow (`fgjax.method.poses`): tracks, triangulation and the bundle adjustment,
against exact flows of a box room computed here independently (numpy ray casting)."""

from __future__ import annotations

import numpy as np
import pytest

from fgjax.method.poses import FlowTracks, _triangulate_inverse_depth, bundle_adjust, flow_tracks

W, H = 64, 48
K = np.array([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])


def _look_at(centre, target):
    """World-to-camera (OpenCV: x right, y down, z forward) of a camera at `centre` looking at `target`."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, -1.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    vm = np.eye(4)
    vm[:3, :3], vm[:3, 3] = r, -r @ centre
    return vm


def _cameras(n=10):
    out = []
    for i in range(n):
        a = 0.5 + 0.06 * i
        c = np.array([0.8 * np.cos(a), 0.1 * np.sin(3 * a), 0.8 * np.sin(a)])
        out.append(_look_at(c, np.array([0.2 * np.sin(i), 0.0, -0.1])))
    return np.stack(out)


def _depth(vm):
    """Camera z-depth of the inside of the box [-2, 2] x [-1.5, 1.5] x [-2.5, 2.5] (every pixel hits a wall)."""
    r, c = vm[:3, :3], -vm[:3, :3].T @ vm[:3, 3]
    ys, xs = np.mgrid[0:H, 0:W]
    cam = np.stack([(xs + 0.5 - K[0, 2]) / K[0, 0], (ys + 0.5 - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    d = cam @ r  # world direction with camera z = 1
    hi = np.array([2.0, 1.5, 2.5])
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (hi - c) / d, np.where(d < 0, (-hi - c) / d, np.inf))
    return t.min(-1)


def _flow(vm0, vm1):
    """Exact flow frame 0 -> 1 on frame 0's grid (pixel centres at +0.5)."""
    z = _depth(vm0)
    ys, xs = np.mgrid[0:H, 0:W]
    cam0 = np.stack([(xs + 0.5 - K[0, 2]) / K[0, 0] * z, (ys + 0.5 - K[1, 2]) / K[1, 1] * z, z], -1)
    world = (cam0 - vm0[:3, 3]) @ vm0[:3, :3]
    cam1 = world @ vm1[:3, :3].T + vm1[:3, 3]
    u = K[0, 0] * cam1[..., 0] / cam1[..., 2] + K[0, 2]
    v = K[1, 1] * cam1[..., 1] / cam1[..., 2] + K[1, 2]
    return np.stack([u - (xs + 0.5), v - (ys + 0.5)], -1).astype(np.float32)


def _flows(vms):
    out = np.full((len(vms), H, W, 2), np.nan, np.float32)
    for i in range(1, len(vms)):
        out[i] = _flow(vms[i - 1], vms[i])
    return out, np.arange(len(vms)) - 1


def _noisy(vms, deg, trans, seed=0):
    rng = np.random.default_rng(seed)
    out = vms.copy()
    for i in range(len(vms)):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        ang = np.radians(deg) * rng.normal()
        kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        rot = np.eye(3) + np.sin(ang) * kx + (1 - np.cos(ang)) * kx @ kx
        out[i, :3, :3] = rot @ vms[i, :3, :3]
        out[i, :3, 3] = rot @ vms[i, :3, 3] + trans * rng.normal(size=3)
    return out


def _errors(a, b):
    rel = a[:, :3, :3] @ np.transpose(b[:, :3, :3], (0, 2, 1))
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    ca = -np.einsum("tji,tj->ti", a[:, :3, :3], a[:, :3, 3])
    cb = -np.einsum("tji,tj->ti", b[:, :3, :3], b[:, :3, 3])
    return float(ang.mean()), float(np.linalg.norm(ca - cb, axis=1).mean())


def test_flow_tracks_follow_chained_flow_and_stop_outside():
    flows = np.full((4, 10, 12, 2), np.nan, np.float32)
    flows[1:] = [1.5, 0.25]  # every frame shifts by (1.5, 0.25)
    flows[2, :, 8:] = np.nan  # unknown on the right of frame 1's grid
    tr = flow_tracks(flows, np.array([-1, 0, 1, 2]), length=3, stride=4)
    assert isinstance(tr, FlowTracks) and set(tr.host.tolist()) == {0, 1, 2}  # frame 3 has no successor
    for o in range(len(tr.obs_track)):
        m = tr.obs_track[o]
        hops = tr.obs_frame[o] - tr.host[m]
        np.testing.assert_allclose(tr.obs_xy[o], tr.xy[m] + hops * np.array([1.5, 0.25]), atol=1e-9)
        assert np.all(tr.obs_xy[o] >= 0) and tr.obs_xy[o][0] <= 12 and tr.obs_xy[o][1] <= 10
    # a track of frame 0 whose position in frame 1 falls where frame 1's flow is unknown stops there
    right = (tr.host == 0) & (tr.xy[:, 0] + 1.5 > 8.5)
    for m in np.flatnonzero(right):
        assert set(tr.obs_frame[tr.obs_track == m].tolist()) == {1}


def test_triangulation_is_exact_on_exact_flow():
    vms = _cameras(4)
    flows, prev = _flows(vms)
    tr = flow_tracks(flows, prev, length=1, stride=8)  # one hop: flow read at grid points, no interpolation
    rho = _triangulate_inverse_depth(vms, np.tile(K, (4, 1, 1)), tr)
    z = np.stack([_depth(v) for v in vms])  # [T, H, W]
    ij = np.floor(tr.xy).astype(int)
    seen = np.bincount(tr.obs_track, minlength=len(tr.host)) > 0
    assert seen.mean() > 0.8 and np.all(rho[~seen] == 0.0)  # a track seen nowhere else: no depth (0)
    np.testing.assert_allclose(rho[seen] * z[tr.host, ij[:, 1], ij[:, 0]][seen], 1.0, rtol=1e-4)  # float32 flow


def _relative_errors(a, b):
    """Gauge-free errors of consecutive relative poses: rotation (degrees) and translation direction
    (degrees); a global rotation, translation or scale of all cameras changes neither."""
    ra, rb = a[1:] @ np.linalg.inv(a[:-1]), b[1:] @ np.linalg.inv(b[:-1])
    ta, tb = ra[:, :3, 3], rb[:, :3, 3]
    cos = np.sum(ta * tb, 1) / np.linalg.norm(ta, axis=1) / np.linalg.norm(tb, axis=1)
    return _errors(ra, rb)[0], float(np.degrees(np.arccos(np.clip(cos, -1, 1))).mean())


@pytest.mark.parametrize("moving_block", [False, True])
def test_bundle_adjustment_removes_pose_noise(moving_block):
    """Exact flow of a box room, written poses 0.5 degree and 0.02 off. The absolute errors can only fall to
    the gauge the prior leaves (the mean of 10 noisy poses), so the relative poses are checked too. With a
    moving block (2 px off in three frames, carried along every track through it) the fit must still
    improve; on exact flow it must fit to 0.05 px."""
    true = _cameras(10)
    flows, prev = _flows(true)
    if moving_block:
        flows[3:6, 10:22, 20:34] += np.array([2.0, -1.0], np.float32)
    noisy = _noisy(true, 0.5, 0.02)
    ks = np.tile(K, (10, 1, 1))
    res = bundle_adjust(noisy, ks, flows, prev, prior_rot_deg=1.0, prior_trans=0.05, stride=4, log=lambda *a: None)
    (rot0, c0), (rot1, c1) = _errors(noisy, true), _errors(res.viewmats, true)
    (rr0, dir0), (rr1, dir1) = _relative_errors(noisy, true), _relative_errors(res.viewmats, true)
    assert rot1 < 0.9 * rot0 and c1 < 0.6 * c0, (rot0, rot1, c0, c1)
    assert rr1 < 0.5 * rr0 and dir1 < 0.2 * dir0, (rr0, rr1, dir0, dir1)
    if not moving_block:
        assert rot1 < 0.3 * rot0 and rr1 < 0.25 * rr0 and res.rms_after < 0.05, (rot1, rr1, res.rms_after)
    assert res.rms_after < 0.3 * res.rms_before
    from fgjax.geometry import se3_exp

    np.testing.assert_allclose(np.asarray(se3_exp(res.deltas)) @ noisy, res.viewmats, atol=1e-5)


def test_bundle_adjustment_degenerate_inputs_stay_finite():
    vms = np.tile(_cameras(1), (5, 1, 1))  # a camera that never moves: zero flow, depth unobservable
    flows = np.zeros((5, H, W, 2), np.float32)
    flows[0] = np.nan
    prev = np.arange(5) - 1
    ks = np.tile(K, (5, 1, 1))
    res = bundle_adjust(vms, ks, flows, prev, log=lambda *a: None)
    assert np.all(np.isfinite(res.viewmats)) and np.all(np.isfinite(res.inv_depth))
    assert _errors(res.viewmats, vms)[0] < 1e-3
    none = np.full((5, H, W, 2), np.nan, np.float32)  # no flow at all: the written poses come back
    res = bundle_adjust(vms, ks, none, prev, log=lambda *a: None)
    np.testing.assert_array_equal(res.viewmats, vms)
    with pytest.raises(ValueError, match="flows and 4 predecessors"):
        bundle_adjust(vms, ks, flows, prev[:4])
    with pytest.raises(ValueError, match="prior"):
        bundle_adjust(vms, ks, flows, prev, prior_trans=0.0)


def test_bundle_adjustment_with_backward_flows_drops_an_inconsistent_block():
    """As the moving-block case above, but with the backward flows, which do not carry the block's 2 px: the
    round trip drops the block's pixels, and the fit reaches the exact-flow case's accuracy, which it does
    not without them."""
    true = _cameras(10)
    flows, prev = _flows(true)
    back = np.full_like(flows, np.nan)
    for i in range(1, 10):
        back[i] = _flow(true[i], true[i - 1])
    flows[3:6, 10:22, 20:34] += np.array([2.0, -1.0], np.float32)
    noisy = _noisy(true, 0.5, 0.02)
    ks = np.tile(K, (10, 1, 1))
    kw = dict(prior_rot_deg=1.0, prior_trans=0.05, stride=4, log=lambda *a: None)
    plain = bundle_adjust(noisy, ks, flows, prev, **kw)
    res = bundle_adjust(noisy, ks, flows, prev, backward=back, fb_px=0.1, **kw)
    rot0 = _errors(noisy, true)[0]
    (rr0, _), (rr1, _), (rrp, _) = (_relative_errors(v, true) for v in (noisy, res.viewmats, plain.viewmats))
    assert _errors(res.viewmats, true)[0] < 0.3 * rot0 and rr1 < 0.25 * rr0 and res.rms_after < 0.05
    assert rr1 < rrp, (rr1, rrp)  # the block bent the cameras without the round trip
    with pytest.raises(ValueError, match="backward flows"):
        bundle_adjust(noisy, ks, flows, prev, backward=back[:, :5], **kw)
    with pytest.raises(ValueError, match="fb_px"):
        bundle_adjust(noisy, ks, flows, prev, backward=back, fb_px=0.0, **kw)


def test_sample_bilinear_matches_scipy_and_is_nan_outside():
    """`sample_bilinear` against scipy's order-1 `map_coordinates` (row = y - 0.5, column = x - 0.5: pixel centres
    at +0.5), exact at the pixel centres, NaN beyond the outermost centres."""
    from scipy.ndimage import map_coordinates

    from fgjax.method.poses import sample_bilinear

    rng = np.random.default_rng(4)
    field = rng.normal(size=(7, 9, 2))
    xy = np.stack([rng.uniform(0.5, 8.5, 200), rng.uniform(0.5, 6.5, 200)], axis=1)
    got = sample_bilinear(field, xy)
    want = np.stack([map_coordinates(field[..., c], [xy[:, 1] - 0.5, xy[:, 0] - 0.5], order=1) for c in range(2)], 1)
    np.testing.assert_allclose(got, want, atol=1e-12)
    centres = np.array([[0.5, 0.5], [8.5, 6.5], [3.5, 2.5]])
    np.testing.assert_array_equal(sample_bilinear(field, centres), field[[0, 6, 2], [0, 8, 3]])
    out = sample_bilinear(field, np.array([[0.4, 3.0], [8.6, 3.0], [3.0, 0.4], [3.0, 6.6]]))
    assert np.isnan(out).all()
