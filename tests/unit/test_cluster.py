"""fgjax.cluster: Otsu selection, DBSCAN / HDBSCAN with size filtering, auto eps, trajectories, snapping.

Synthetic data only (numpy): Gaussian blobs with uniform noise, and trajectories with known samples.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.metrics import adjusted_rand_score

from fgjax import cluster as C


def _blobs(seed=0, n=200, std=0.015, centres=((0, 0, 0), (0.5, 0, 0), (0, 0.5, 0.2)), n_noise=30):
    rng = np.random.default_rng(seed)
    pts = [rng.normal(c, std, (n, 3)) for c in centres]
    labels = np.repeat(np.arange(len(centres)), n)
    noise = rng.uniform(-0.6, 1.1, (n_noise, 3))
    return np.concatenate(pts + [noise]), np.concatenate([labels, np.full(n_noise, -1)])


# ---------------------------------------------------------------------------------------------- selection


def test_otsu_threshold_separates_two_modes():
    rng = np.random.default_rng(0)
    v = np.concatenate([rng.normal(0.02, 0.01, 900), rng.normal(0.3, 0.03, 100)])
    thr = C.otsu_threshold(v)
    assert v[:900].max() < thr < v[900:].min()  # well-separated modes: a perfect cut
    np.testing.assert_array_equal(C.select_dynamic(v), np.arange(1000) >= 900)
    # edge cases: empty, constant, non-finite
    assert C.otsu_threshold(np.array([])) == np.inf
    assert C.otsu_threshold(np.full(5, 0.3)) == 0.3
    assert not C.select_dynamic(np.full(5, 0.3)).any()
    assert C.select_dynamic(np.zeros(0)).shape == (0,)
    s = np.array([0.0, 0.0, 0.9, np.nan, np.inf])
    np.testing.assert_array_equal(C.select_dynamic(s), [False, False, True, False, False])


def test_select_dynamic_threshold_floor_and_valid():
    s = np.array([0.0, 0.01, 0.015, 0.5, 0.6])
    np.testing.assert_array_equal(C.select_dynamic(s, 0.1), [0, 0, 0, 1, 1])
    # Otsu on pure low noise still cuts; the floor keeps it empty
    noise = np.random.default_rng(1).uniform(0, 0.01, 100)
    assert C.select_dynamic(noise).any()
    assert not C.select_dynamic(noise, min_score=0.02).any()
    valid = np.array([1, 1, 1, 0, 1], bool)
    np.testing.assert_array_equal(C.select_dynamic(s, 0.1, valid=valid), [0, 0, 0, 0, 1])
    with pytest.raises(ValueError, match="scores"):
        C.select_dynamic(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="valid"):
        C.select_dynamic(s, valid=np.ones(3, bool))
    with pytest.raises(ValueError, match="threshold"):
        C.select_dynamic(s, "mean")  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------- clustering


@pytest.mark.parametrize("method", ["dbscan", "hdbscan"])
def test_cluster_blobs(method):
    pts, truth = _blobs()
    labels = C.cluster_dynamic(pts, method)
    rep = C.cluster_report(labels)
    assert rep.n_clusters == 3 and rep.n_points == len(pts)
    assert rep.sizes == tuple(sorted(rep.sizes, reverse=True))
    core = truth >= 0
    assert adjusted_rand_score(truth[core], labels[core]) > 0.98
    assert np.mean(labels[~core] == -1) > 0.5  # scattered points are mostly noise
    assert "3 cluster(s)" in str(rep)


def test_labels_ordered_by_size_and_small_clusters_dropped():
    rng = np.random.default_rng(2)
    big = rng.normal((0, 0, 0), 0.01, (300, 3))
    mid = rng.normal((1, 0, 0), 0.01, (100, 3))
    small = rng.normal((0, 1, 0), 0.01, (12, 3))  # 12 / 412 = 2.9 %
    pts = np.concatenate([small, mid, big])
    lab = C.cluster_dynamic(pts, min_fraction=0.0)
    assert C.cluster_report(lab).sizes == (300, 100, 12)
    assert np.all(lab[112:] == 0) and np.all(lab[12:112] == 1) and np.all(lab[:12] == 2)
    lab = C.cluster_dynamic(pts, min_fraction=0.05)
    assert C.cluster_report(lab).sizes == (300, 100)
    assert np.all(lab[:12] == -1)
    # the same with HDBSCAN
    lab = C.cluster_dynamic(pts, "hdbscan", min_fraction=0.05)
    assert C.cluster_report(lab).n_clusters == 2 and np.all(lab[:12] == -1)


def test_relabel_by_size_ties_keep_first_occurrence():
    np.testing.assert_array_equal(C.relabel_by_size(np.array([5, 5, 2, 2, -1, 7])), [0, 0, 1, 1, -1, 2])
    np.testing.assert_array_equal(C.relabel_by_size(np.array([5, 5, 2, 2, 2, 7]), min_size=2), [1, 1, 0, 0, 0, -1])


def test_cluster_edge_cases():
    assert C.cluster_dynamic(np.zeros((0, 3))).shape == (0,)
    np.testing.assert_array_equal(C.cluster_dynamic(np.zeros((1, 3))), [-1])  # single point
    np.testing.assert_array_equal(C.cluster_dynamic(np.zeros((1, 3)), "hdbscan"), [-1])
    np.testing.assert_array_equal(C.cluster_dynamic(np.zeros((4, 3)), min_samples=5), [-1] * 4)
    far = np.arange(30, dtype=float)[:, None] * np.array([[1.0, 0, 0]])  # all far apart: all noise
    lab = C.cluster_dynamic(far)
    assert np.all(lab == -1)
    rep = C.cluster_report(lab)
    assert rep.n_clusters == 0 and rep.sizes == () and rep.n_noise == 30
    assert C.cluster_report(np.zeros(0, int)).n_points == 0
    with pytest.raises(ValueError, match="method"):
        C.cluster_dynamic(far, "kmeans")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="non-finite"):
        C.cluster_dynamic(np.full((6, 3), np.nan))
    with pytest.raises(ValueError, match="points"):
        C.cluster_dynamic(np.zeros(6))


def test_auto_eps_on_blobs():
    pts, truth = _blobs(std=0.015, n_noise=40)
    eps = C.auto_eps(pts, 4)
    # within-blob 4-NN distances are ~0.01, noise 4-NN distances ~0.2: the knee lies between
    kd = C.k_distances(pts, 4)
    assert np.median(kd) < eps < 0.15, (eps, np.median(kd))
    lab = C.cluster_dynamic(pts, auto_eps=True)
    assert C.cluster_report(lab).n_clusters == 3
    assert adjusted_rand_score(truth[truth >= 0], lab[truth >= 0]) > 0.95
    # scale equivariance: the knee scales with the data
    np.testing.assert_allclose(C.auto_eps(10 * pts, 4), 10 * eps, rtol=1e-9)
    # duplicate points: a tiny positive eps, not 0 or a crash
    assert 0 < C.auto_eps(np.zeros((10, 3)), 3) <= 1e-12
    with pytest.raises(ValueError, match="more than k"):
        C.auto_eps(pts[:4], 4)


# ---------------------------------------------------------------------------------------------- trajectories


def test_trajectories_are_cluster_means():
    rng = np.random.default_rng(3)
    t, n = 7, 50
    centres = rng.normal(size=(t, n, 3))
    labels = rng.integers(-1, 3, n)
    traj = C.trajectories(centres, labels)
    assert traj.shape == (3, t, 3)
    for k in range(3):
        np.testing.assert_allclose(traj[k], centres[:, labels == k].mean(axis=1), rtol=1e-12)
    # T = 1, all noise, compactness
    assert C.trajectories(centres[:1], labels).shape == (3, 1, 3)
    assert C.trajectories(centres, np.full(n, -1)).shape == (0, t, 3)
    with pytest.raises(ValueError, match="compact"):
        C.trajectories(centres, np.where(labels == 1, 2, labels))
    with pytest.raises(ValueError, match="labels"):
        C.trajectories(centres, labels[:-1])


def test_snap_on_path_returns_exact_samples():
    rng = np.random.default_rng(4)
    traj = np.cumsum(rng.normal(size=(9, 3)), axis=0)
    for i in range(9):
        t, p = C.snap_to_trajectory(traj, traj[i] - traj[0])
        assert t == float(i)
        np.testing.assert_array_equal(p, traj[i])
    # time stamps instead of indices
    times = np.linspace(0, 1, 9)
    assert C.snap_to_trajectory(traj, traj[4] - traj[0], times=times).t == times[4]


def test_snap_off_path_interpolates():
    traj = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]])
    t, p = C.snap_to_trajectory(traj, np.array([0.25, 0.4, 0.0]))
    assert t == pytest.approx(0.25)
    np.testing.assert_allclose(p, [0.25, 0, 0])
    t, p = C.snap_to_trajectory(traj, np.array([1.3, 0.6, -0.2]))
    assert t == pytest.approx(1.6)
    np.testing.assert_allclose(p, [1, 0.6, 0])
    # beyond the end: the last sample
    t, p = C.snap_to_trajectory(traj, np.array([1.0, 1.0, 5.0]))
    assert t == 3.0 and np.array_equal(p, traj[-1])
    # a different origin: the vector is taken from it
    t, p = C.snap_to_trajectory(traj, np.array([0.0, 0.5, 0.0]), origin=np.array([1.0, 0.0, 0.0]))
    assert t == pytest.approx(1.5)
    # interpolated times
    t, _ = C.snap_to_trajectory(traj, np.array([0.25, 0.4, 0.0]), times=np.array([0.0, 0.2, 0.6, 1.0]))
    assert t == pytest.approx(0.05)


def test_snap_open_close_prefers_first_and_handles_rests():
    # rest, open, hold, close, rest: repeated samples (zero-length segments) and a path walked twice
    traj = np.array([[0.0, 0, 0], [0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1, 0, 0], [0.5, 0, 0], [0, 0, 0]])
    t, p = C.snap_to_trajectory(traj, np.array([0.5, 0.1, 0.0]))
    assert t == 2.0 and np.array_equal(p, traj[2])
    t, p = C.snap_to_trajectory(traj, np.array([0.75, 0.0, 0.0]))
    assert t == pytest.approx(2.5)
    t, p = C.snap_to_trajectory(traj, np.zeros(3))
    assert t == 0.0


def test_snap_edge_cases():
    t, p = C.snap_to_trajectory(np.array([[1.0, 2, 3]]), np.array([5.0, 5, 5]))  # T = 1
    assert t == 0.0 and np.array_equal(p, [1.0, 2, 3])
    with pytest.raises(ValueError, match="traj"):
        C.snap_to_trajectory(np.zeros((0, 3)), np.zeros(3))
    with pytest.raises(ValueError, match="vector"):
        C.snap_to_trajectory(np.zeros((2, 3)), np.zeros(2))
    with pytest.raises(ValueError, match="non-finite"):
        C.snap_to_trajectory(np.zeros((2, 3)), np.array([np.nan, 0, 0]))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 8))
def test_snap_is_nearest_point_of_polyline(seed, t):
    """Property: no point of the polyline (dense sampling) is nearer than the snapped point."""
    rng = np.random.default_rng(seed)
    traj = rng.normal(size=(t, 3))
    v = rng.normal(size=3) * 2
    snap = C.snap_to_trajectory(traj, v)
    p = traj[0] + v
    d = np.linalg.norm(snap.point - p)
    if t > 1:
        u = np.linspace(0, 1, 201)[:, None, None]
        dense = (traj[:-1] + u * (traj[1:] - traj[:-1])).reshape(-1, 3)
        assert d <= np.linalg.norm(dense - p, axis=1).min() + 1e-9
        i = int(np.floor(snap.t))
        frac = snap.t - i
        expect = traj[i] if frac == 0 else traj[i] + frac * (traj[i + 1] - traj[i])
        np.testing.assert_allclose(snap.point, expect, atol=1e-12)
    assert 0.0 <= snap.t <= t - 1


def test_fill_hulls_brings_in_the_static_points_inside_a_clusters_core_hull():
    from fgjax.cluster import fill_hulls

    corners = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])  # a unit cube
    box_b = corners * 0.5 + np.array([3.0, 0.0, 0.0])  # a second cluster's cube, [3, 3.5] x [0, 0.5]^2
    inside = np.array([[0.5, 0.5, 0.5], [0.1, 0.9, 0.2], [0.99, 0.01, 0.5]])
    outside = np.array([[1.01, 0.5, 0.5], [0.5, -0.02, 0.5], [2.0, 2.0, 2.0], [3.25, 0.25, 0.51], [-0.1, 0.5, 0.5]])
    faint_out = np.array([[-0.5, 0.5, 0.5]])  # a member that is not core: it does not widen the hull
    in_b = np.array([[3.2, 0.3, 0.1]])
    pts = np.concatenate([corners, box_b, inside, outside, faint_out, in_b, [[0.5, 0.5, 0.4]]])
    n_c, n_b, n_in, n_out = len(corners), len(box_b), len(inside), len(outside)
    labels = np.full(len(pts), -1)
    labels[:n_c] = 0
    labels[n_c:n_c + n_b] = 1
    i_faint = n_c + n_b + n_in + n_out
    labels[i_faint] = 0
    labels[-1] = 1  # a member of another cluster inside cube 0 keeps its label
    core = labels >= 0
    core[i_faint] = False
    cand = np.ones(len(pts), bool)
    cand[n_c + n_b + 2] = False  # a non-candidate inside stays static
    out = fill_hulls(pts, labels, core, cand)
    s = n_c + n_b
    np.testing.assert_array_equal(out[s:s + n_in], [0, 0, -1])
    np.testing.assert_array_equal(out[s + n_in:s + n_in + n_out], -1)  # just outside, far, above cube 1, or only
    # inside the hull that the faint member would widen
    assert out[i_faint] == 0 and out[i_faint + 1] == 1 and out[-1] == 1
    np.testing.assert_array_equal(out[labels >= 0], labels[labels >= 0])  # members never change
    # a point inside two overlapping hulls joins the cluster of the nearer core member
    two = np.concatenate([corners, corners + np.array([0.8, 0.0, 0.0]), [[0.85, 0.5, 0.5], [0.95, 0.02, 0.02]]])
    lab2 = np.r_[np.zeros(8, int), np.ones(8, int), -1, -1]
    out2 = fill_hulls(two, lab2, lab2 >= 0, np.ones(len(two), bool))
    assert out2[-2] == 1 and out2[-1] == 0  # nearest core points: (0.8, 0, 0) of cube 1; (1, 0, 0) of cube 0
    # a hull holding more candidates than max_growth x its cluster's size fills nothing (cube 0: 8 members + the
    # faint one, 2 candidates inside; cube 1: 8 + 1 members, 1 inside)
    capped = fill_hulls(pts, labels, core, cand, max_growth=0.2)
    np.testing.assert_array_equal(capped[s:s + n_in], [-1, -1, -1])
    assert capped[i_faint + 1] == 1
    np.testing.assert_array_equal(fill_hulls(pts, labels, core, cand, max_growth=0.25), out)  # 2 <= 0.25 x 9
    # degenerate cores fill nothing: 3 points, and 4 coplanar ones
    flat = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.5, 0.5, 0.0]])
    for m in (3, 4):
        lab3 = np.r_[np.zeros(m, int), np.full(len(flat) - m, -1)]
        np.testing.assert_array_equal(fill_hulls(flat, lab3, lab3 >= 0, np.ones(len(flat), bool)), lab3)
    np.testing.assert_array_equal(fill_hulls(pts, np.full(len(pts), -1), core, cand), -1)  # no clusters
    with pytest.raises(ValueError, match="non-finite"):  # refused, as by the other functions of this module
        fill_hulls(np.where(np.arange(len(pts))[:, None] == 3, np.nan, pts), labels, core, cand)
    with pytest.raises(ValueError, match="fill_hulls"):
        fill_hulls(pts[:, :2], labels, core, cand)
    with pytest.raises(ValueError, match="fill_hulls"):
        fill_hulls(pts, labels[:-1], core, cand)


def _activity(t, n, spans):
    """Per-frame painted weights [T, N]: total 10 everywhere; point i moving (weight 8) in frames spans[i]."""
    total = np.full((t, n), 10.0)
    moving = np.zeros((t, n))
    for i, sp in spans.items():
        moving[list(sp), i] = 8.0
    return moving, total


def test_moving_frames_and_dilation():
    labels = np.array([0, 0, 1, -1])
    moving, total = _activity(12, 4, {0: range(3, 6), 1: range(3, 6), 2: [8, 9], 3: range(12)})
    moving[4, 1] = 2.0  # a weaker frame: cluster 0's fraction (0.8 + 0.2) / 2 = 0.5 of its maximum
    f = C.moving_frames(labels, moving, total, active=0.5)
    assert f.shape == (2, 12)
    np.testing.assert_array_equal(np.flatnonzero(f[0]), [3, 4, 5])
    np.testing.assert_array_equal(np.flatnonzero(f[1]), [8, 9])
    np.testing.assert_array_equal(np.flatnonzero(C.moving_frames(labels, moving, total, active=0.9)[0]), [3, 5])
    d = C.moving_frames(labels, moving, total, active=0.5, dilate=1)
    np.testing.assert_array_equal(np.flatnonzero(d[0]), [2, 3, 4, 5, 6])
    np.testing.assert_array_equal(np.flatnonzero(d[1]), [7, 8, 9, 10])
    assert C.moving_frames(np.full(4, -1), moving, total).shape == (0, 12)  # no clusters
    np.testing.assert_array_equal(C.moving_frames(labels, np.zeros_like(moving), total), False)  # never moving
    with pytest.raises(ValueError, match="moving_t and total_t"):
        C.moving_frames(labels, moving[:, :3], total)


def test_localize_clusters_finds_a_briefly_moving_part_that_the_global_score_misses():
    # cluster 0 (points 0-4) moves in frames 40-47 of 60; near it: a point on the same part that the
    # global cut missed (moving whenever the part moves), a static neighbour, a neighbour moving only
    # outside the part's frames; far away: a point moving in the same frames (beyond the radius);
    # a member of cluster 1 (also near) keeps its label.
    t = 60
    pts = np.array([[0.0, 0, 0], [0.02, 0, 0], [0.04, 0, 0], [0.0, 0.02, 0], [0.02, 0.02, 0],  # cluster 0
                    [0.07, 0.0, 0],   # 5: the missed piece of the part
                    [0.0, -0.06, 0],  # 6: static neighbour
                    [0.0, 0.07, 0],   # 7: moves, but in other frames
                    [2.0, 0.0, 0],    # 8: moves in the same frames, far away
                    [0.06, 0.04, 0]])  # 9: cluster 1
    labels = np.array([0, 0, 0, 0, 0, -1, -1, -1, -1, 1])
    part = range(40, 48)
    moving, total = _activity(t, len(pts), {**{i: part for i in range(6)}, 7: range(0, 10), 8: part, 9: range(20, 24)})
    glob = moving.sum(0) / (total.sum(0) + 0.1)
    assert glob[5] < 0.15  # diluted by the 52 frames of rest: below any sensible global cut
    res = C.localize_clusters(pts, labels, moving, total, radius=0.1, threshold=0.4)
    np.testing.assert_array_equal(res.labels, [0, 0, 0, 0, 0, 0, -1, -1, -1, 1])
    np.testing.assert_array_equal(np.flatnonzero(res.frames[0]), list(part))
    assert res.joined == (1, 0)
    assert res.scores[5] == pytest.approx(8 * 8 / (8 * 10 + 0.1))
    assert res.scores[6] == 0.0 and np.isnan(res.scores[8])  # tested and failed; never tested (too far)
    # candidates restrict who may join; a point reaching two clusters joins the higher-scoring one
    none = C.localize_clusters(pts, labels, moving, total, radius=0.1, threshold=0.4, candidates=np.zeros(10, bool))
    np.testing.assert_array_equal(none.labels, labels)
    lab2 = labels.copy()
    lab2[7] = 1  # cluster 1 now also holds a point moving in frames 0-9; point 6 moves in frames 0-9 too
    mv2, tt2 = _activity(t, len(pts), {**{i: part for i in range(6)}, 6: range(0, 10), 7: range(0, 10),
                                       9: range(0, 10)})
    mv2[40:48, 6] = 4.0  # and half-moving in cluster 0's frames
    res2 = C.localize_clusters(pts, lab2, mv2, tt2, radius=0.15, threshold=0.4)
    assert res2.scores[6] == pytest.approx(8 * 10 / (10 * 10 + 0.1)) and res2.labels[6] == 1
    with pytest.raises(ValueError, match="threshold"):
        C.localize_clusters(pts, labels, moving, total, radius=0.1, threshold=1.5)
    with pytest.raises(ValueError, match="labels"):
        C.localize_clusters(pts, labels[:3], moving, total, radius=0.1, threshold=0.4)


def test_merge_fragments_joins_close_fragments_that_move_together():
    from sklearn.cluster import DBSCAN

    rng = np.random.default_rng(0)
    # one part: two dense blobs joined by a sparse bridge (border points, not core): DBSCAN splits it
    left = rng.normal([0.0, 0.0, 0.0], 0.01, (40, 3))
    right = rng.normal([0.12, 0.0, 0.0], 0.01, (40, 3))
    bridge = np.array([[0.04, 0, 0], [0.06, 0, 0], [0.08, 0, 0]])
    other = rng.normal([0.12, 0.09, 0.0], 0.01, (30, 3))  # another part, as close, moving at other times
    far = rng.normal([1.0, 1.0, 1.0], 0.01, (30, 3))  # same times as the first part, far away
    pts = np.concatenate([left, bridge, right, other, far])
    raw = C.relabel_by_size(DBSCAN(eps=0.03, min_samples=5).fit_predict(pts))
    first = np.r_[0:40, 43:83]
    assert len(set(raw[first])) == 2  # the fragments DBSCAN leaves
    runs = [*range(5, 9), *range(15, 19)]
    spans = {i: runs for i in range(83)}
    spans.update({i: range(25, 30) for i in range(83, 113)})
    spans.update({i: runs for i in range(113, 143)})
    moving, total = _activity(40, len(pts), spans)
    out = C.merge_fragments(pts, raw, moving, total, eps=0.03)
    assert len(set(out[first])) == 1 and out[first[0]] >= 0  # joined ...
    assert out[90] not in (out[0], -1) and out[120] not in (out[0], out[90], -1)  # ... the others are not
    assert np.all(out[raw == -1] == -1)  # noise stays noise
    assert out[0] == 0 and sorted(set(out[out >= 0])) == [0, 1, 2]  # renumbered by size
    # closer than eps is required
    np.testing.assert_array_equal(C.merge_fragments(pts, raw, moving, total, eps=0.01), C.relabel_by_size(raw))
    # fewer than two clusters: unchanged
    one = np.where(np.arange(len(pts)) < 40, 0, -1)
    np.testing.assert_array_equal(C.merge_fragments(pts, one, moving, total, eps=0.05), one)
    with pytest.raises(ValueError, match="merge_fragments"):
        C.merge_fragments(pts, raw[:5], moving, total, eps=0.03)
    with pytest.raises(ValueError, match="eps"):
        C.merge_fragments(pts, raw, moving, total, eps=0.0)


def test_split_by_motion_separates_parts_that_move_at_different_times():
    rng = np.random.default_rng(0)
    a = rng.normal([0.0, 0.0, 0.0], 0.01, (30, 3))  # part A
    b = rng.normal([0.04, 0.0, 0.0], 0.01, (20, 3))  # part B, touching A: one DBSCAN cluster
    pts = np.concatenate([a, b, [[1.0, 1.0, 1.0]]])
    labels = np.r_[np.zeros(50, int), -1]
    a_runs, b_runs = [*range(5, 9), *range(15, 19)], [*range(25, 29), *range(35, 39)]  # open, rest, close
    moving, total = _activity(45, 51, {**{i: a_runs for i in range(30)}, **{i: b_runs for i in range(30, 50)}})
    moving[:, 29] = 0.0  # an idle member of A (never on moving pixels) follows its nearest active neighbour
    out = C.split_by_motion(pts, labels, moving, total)
    assert len(set(out[:30])) == 1 and len(set(out[30:50])) == 1 and out[0] != out[30]
    assert out[0] == 0 and out[30] == 1 and out[-1] == -1  # by size; noise stays noise
    # one part opening then closing (two runs, the same members): not split
    one, _ = _activity(45, 51, {i: a_runs for i in range(50)})
    np.testing.assert_array_equal(C.split_by_motion(pts, labels, one, total), labels)
    # a part smaller than min_size stays merged
    np.testing.assert_array_equal(C.split_by_motion(pts, labels, moving, total, min_size=25), labels)
    with pytest.raises(ValueError, match="split_by_motion"):
        C.split_by_motion(pts, labels[:5], moving, total)


def _door_and_lid(seed=0):
    """A door (a 20 x 10 grid, spacing 0.01) and a small lid (6 x 5) touching it along one edge, whose seam column
    paints both: points [230, 3], truth [230] (0 door, 1 lid), moving and total [24, 230] with noise."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(20), np.arange(10), indexing="ij")
    door = np.c_[gx.ravel() * 0.01, gy.ravel() * 0.01, np.zeros(200)]
    lx, ly = np.meshgrid(np.arange(6), np.arange(5), indexing="ij")
    lid = np.c_[0.2 + lx.ravel() * 0.01, ly.ravel() * 0.01, np.zeros(30)]
    pts = np.concatenate([door, lid]) + rng.normal(0, 1e-3, (230, 3))
    truth = np.r_[np.zeros(200, int), np.ones(30, int)]
    spans = {i: range(2, 9) for i in range(200)} | {200 + i: range(15, 21) for i in range(30)}
    moving, total = _activity(24, 230, spans)
    seam = np.flatnonzero(np.isclose(pts[:, 0], 0.19, atol=3e-3))  # the door's last column paints the lid too
    moving[15:21, seam] = 4.0
    moving += rng.uniform(0.0, 1.0, moving.shape)  # false-positive pixels everywhere
    return pts, truth, moving, total


def test_cluster_by_motion_cuts_the_seam_between_parts_that_move_at_different_times():
    pts, truth, moving, total = _door_and_lid()
    plain = C.cluster_by_motion(pts, moving, total, eps=0.015, min_samples=5, min_corr=-1.0)
    from sklearn.cluster import DBSCAN  # reference: min_corr = -1 is plain DBSCAN

    np.testing.assert_array_equal(plain, C.relabel_by_size(DBSCAN(eps=0.015, min_samples=5).fit_predict(pts)))
    assert len(set(plain)) == 1  # position alone: one cluster through the seam
    lab = C.cluster_by_motion(pts, moving, total, eps=0.015, min_samples=5, min_corr=0.8)
    ok = lab >= 0
    assert ok.mean() > 0.9 and len(set(lab[ok])) == 2
    assert adjusted_rand_score(truth[ok], lab[ok]) == 1.0
    assert np.all(lab[200:] == 1)  # the whole lid, smaller: label 1


def test_cluster_by_motion_edge_cases():
    pts, _, moving, total = _door_and_lid()
    # a constant profile (no evidence of when a point moves) correlates with nothing
    z = C.activity_correlation(np.ones((5, 3)), np.full((5, 3), 2.0))
    assert z.shape == (5, 3) and np.all(z == 0.0)
    flat = C.cluster_by_motion(pts, np.zeros_like(moving), total, eps=0.015, min_corr=0.5)
    assert np.all(flat == -1)
    assert C.cluster_by_motion(pts[:3], moving[:, :3], total[:, :3], eps=0.015, min_samples=5).tolist() == [-1] * 3
    # auto_eps and the size cut as in cluster_dynamic
    auto = C.cluster_by_motion(pts, moving, total, eps=1.0, min_corr=0.8, auto_eps=True)
    np.testing.assert_array_equal(auto, C.cluster_by_motion(pts, moving, total, eps=C.auto_eps(pts, 4), min_corr=0.8))
    cut = C.cluster_by_motion(pts, moving, total, eps=0.015, min_corr=0.8, min_fraction=0.5)
    assert set(cut) <= {-1, 0} and np.sum(cut == 0) >= 115
    for kw, msg in (({"eps": 0.0}, "eps"), ({"eps": 0.1, "min_corr": 1.5}, "min_corr"),
                    ({"eps": 0.1, "min_samples": 0}, "min_samples"),
                    ({"eps": 0.1, "min_fraction": 1.0}, "min_fraction")):
        with pytest.raises(ValueError, match=msg):
            C.cluster_by_motion(pts, moving, total, **kw)
    with pytest.raises(ValueError, match=r"\[T, 230\]"):
        C.cluster_by_motion(pts, moving[:, :10], total[:, :10], eps=0.015)
    bad = moving.copy()
    bad[3, 7] = np.nan
    with pytest.raises(ValueError, match="finite"):
        C.cluster_by_motion(pts, bad, total, eps=0.015)


def _turn(axis, pivot, deg, slide=0.0):
    """x -> R (x - p) + p + slide * a, R the turn by `deg` about unit `axis` (scipy's rotation vector, not the
    module under test): [4, 4]."""
    from scipy.spatial.transform import Rotation

    a = np.asarray(axis, float) / np.linalg.norm(axis)
    R = Rotation.from_rotvec(np.radians(deg) * a).as_matrix()
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = np.asarray(pivot) - R @ np.asarray(pivot) + slide * a
    return out


def _line_distance(point, a, p):
    d = np.asarray(point) - np.asarray(p)
    return float(np.linalg.norm(d - (d @ a) * a))


def test_hinge_axes_recover_the_axis_and_a_point_of_it_from_rigid_poses():
    from fgjax.cluster import hinge_axes

    rng = np.random.default_rng(0)
    a0 = rng.normal(size=3)
    a0 /= np.linalg.norm(a0)
    p0 = np.array([0.4, -1.2, 2.0])
    t = np.linspace(0.0, 1.0, 12)
    poses = np.stack([
        [_turn(a0, p0, 80.0 * s) for s in t],  # a hinge turning to 80 degrees
        [_turn([0, 0, 1], [0, 0, 0], 0.0, slide=0.5 * s) for s in t],  # a slide: no hinge
        [_turn([1, 0, 0], [0, 1, 0], 15.0 * s) for s in t],  # turns less than min_deg: no hinge
        [_turn([0, 1, 0], [2.0, 0, 0], 60.0 * s, slide=0.3 * s) for s in t],  # a screw: the same line
        [_turn([0, 0, 1], [1.0, 1.0, 0], 180.0 * s) for s in t],  # up to a half turn
    ])
    axes, pivots, angles = hinge_axes(poses, min_deg=20.0)
    np.testing.assert_allclose(angles, [80.0, 0.0, 15.0, 60.0, 180.0], atol=1e-6)
    for k in (1, 2):
        assert np.all(np.isnan(axes[k])) and np.all(np.isnan(pivots[k]))
    for k, a, p in ((0, a0, p0), (3, np.array([0, 1.0, 0]), [2.0, 0, 0]), (4, np.array([0, 0, 1.0]), [1.0, 1.0, 0])):
        assert abs(abs(axes[k] @ a) - 1.0) < 1e-9, (k, axes[k], a)
        assert _line_distance(pivots[k], a, p) < 1e-9, (k, pivots[k])
        assert abs(pivots[k] @ axes[k]) < 1e-9  # the line's point nearest the origin
    # noisy poses (tracked ones are): the axis within a degree, the line within a hundredth
    noisy = poses[:1].copy()
    for j in range(len(t)):
        noisy[0, j] = noisy[0, j] @ _turn(rng.normal(size=3), rng.normal(size=3) * 0.1, 0.3)
    axes_n, pivots_n, _ = hinge_axes(noisy)
    assert np.degrees(np.arccos(min(1.0, abs(axes_n[0] @ a0)))) < 1.0
    assert _line_distance(pivots_n[0], a0, p0) < 0.01
    empty = hinge_axes(np.zeros((0, 5, 4, 4)))
    assert [e.shape for e in empty] == [(0, 3), (0, 3), (0,)]
    with pytest.raises(ValueError, match="non-finite"):
        hinge_axes(np.where(np.arange(4)[None, None, :, None] == 0, np.nan, poses))
    with pytest.raises(ValueError, match="hinge_axes"):
        hinge_axes(poses[..., :3, :])
    with pytest.raises(ValueError, match="min_deg"):
        hinge_axes(poses, min_deg=0.0)


def test_fill_hinges_brings_in_the_static_points_along_a_turning_clusters_axis():
    from fgjax.cluster import fill_hinges

    # a door 1 wide and 2 tall in the plane y = 0, hinged on the z axis; its strip near the hinge is unlabelled
    door = np.array([[x, y, z] for x in (0.05, 0.3, 0.6, 1.0) for y in (0.0, 0.02) for z in (0.0, 1.0, 2.0)])
    strip = np.array([[0.1, 0.0, 1.0], [0.15, 0.01, 0.5], [0.0, -0.05, 1.9]])  # within 0.2 of the axis: join
    away = np.array([[0.25, 0.0, 1.0],  # beyond 0.2 x r_max (r_max = 1.0002)
                     [0.1, 0.0, 2.3], [0.1, 0.0, -0.2]])  # past the door's ends along the axis
    pts = np.concatenate([door, strip, away, [[0.1, 0.0, 0.4]]])
    labels = np.r_[np.zeros(len(door), int), np.full(len(strip) + len(away) + 1, -1)]
    core = labels >= 0
    cand = np.ones(len(pts), bool)
    cand[-1] = False  # not a candidate: stays static
    z_axis, origin = np.array([[0.0, 0.0, 1.0]]), np.zeros((1, 3))
    out = fill_hinges(pts, labels, core, cand, z_axis, origin, radius=0.2, reach=0.15)
    s = len(door)
    np.testing.assert_array_equal(out[s:s + len(strip)], 0)
    np.testing.assert_array_equal(out[s + len(strip):], -1)
    np.testing.assert_array_equal(out[:s], 0)  # members never change
    # the axis's length and sign do not matter
    np.testing.assert_array_equal(fill_hinges(pts, labels, core, cand, -3.0 * z_axis, origin, radius=0.2), out)
    # an axis that does not run along the part (nearest core member 1.05 from it, farthest 2.0): nothing joins
    far = np.array([[-1.0, 0.0, 0.0]])
    np.testing.assert_array_equal(fill_hinges(pts, labels, core, cand, z_axis, far), labels)
    # ... unless reach allows it (1.05 <= 0.6 x 2.0); then the cylinder is 0.2 x 2.0 = 0.4 wide about x = -1
    wide = fill_hinges(pts, labels, core, cand, z_axis, far, reach=0.6)
    np.testing.assert_array_equal(wide, labels)  # no candidate lies within 0.4 of x = -1
    # no hinge (NaN: a slide), or a zero axis: nothing joins
    nan3 = np.full((1, 3), np.nan)
    np.testing.assert_array_equal(fill_hinges(pts, labels, core, cand, nan3, nan3), labels)
    np.testing.assert_array_equal(fill_hinges(pts, labels, core, cand, np.zeros((1, 3)), origin), labels)
    # the core only: a faint member on the axis far below does not stretch the cylinder's ends
    low = np.concatenate([pts, [[0.02, 0.0, -1.0]]])
    lab_low, core_low = np.r_[labels, 0], np.r_[core, False]
    out_low = fill_hinges(low, lab_low, core_low, np.r_[cand, True], z_axis, origin)
    assert out_low[s + len(strip) + 2] == -1  # (0.1, 0, -0.2) stays out
    # two hinges (cylinders 0.2 wide): a candidate in both joins the nearer axis
    other = np.array([[x, 0.0, z] for x in (0.28, -0.2, -0.7) for z in (0.0, 2.0)])  # hinged at x = 0.3
    pts2 = np.concatenate([door, other, [[0.1, 0.0, 1.0], [0.17, 0.0, 1.0], [0.22, 0.0, 1.0]]])
    lab2 = np.r_[np.zeros(len(door), int), np.ones(len(other), int), -1, -1, -1]
    axes2, piv2 = np.array([[0.0, 0, 1], [0, 0, 1]]), np.array([[0.0, 0, 0], [0.3, 0, 0]])
    out2 = fill_hinges(pts2, lab2, lab2 >= 0, np.ones(len(pts2), bool), axes2, piv2, radius=0.2)
    np.testing.assert_array_equal(out2[-3:], [0, 1, 1])
    # a cylinder holding more than max_growth x the cluster's size fills nothing (24 members, 3 inside)
    np.testing.assert_array_equal(fill_hinges(pts, labels, core, cand, z_axis, origin, radius=0.2, max_growth=0.1),
                                  labels)
    np.testing.assert_array_equal(fill_hinges(pts, labels, core, cand, z_axis, origin, radius=0.2, max_growth=0.125),
                                  out)
    # the default cylinder, 0.15 x r_max: (0.15, 0.01, 0.5) lies just outside it
    np.testing.assert_array_equal(fill_hinges(pts, labels, core, cand, z_axis, origin)[s:s + len(strip)], [0, -1, 0])
    np.testing.assert_array_equal(fill_hinges(pts, np.full(len(pts), -1), core, cand, np.zeros((0, 3)),
                                              np.zeros((0, 3))), -1)  # no clusters
    with pytest.raises(ValueError, match="non-finite"):
        fill_hinges(np.where(np.arange(len(pts))[:, None] == 3, np.inf, pts), labels, core, cand, z_axis, origin)
    with pytest.raises(ValueError, match="fill_hinges"):
        fill_hinges(pts, labels, core, cand, np.zeros((2, 3)), np.zeros((2, 3)))  # one cluster, two axes
    with pytest.raises(ValueError, match="fill_hinges"):
        fill_hinges(pts, labels[:-1], core, cand, z_axis, origin)
    with pytest.raises(ValueError, match="radius"):
        fill_hinges(pts, labels, core, cand, z_axis, origin, radius=-0.1)


def test_near_swept_marks_the_static_points_the_parts_pass_by_at_any_pose():
    """A one-point cluster at the origin slides to x = 1 over 5 poses (0, 0.25, ..., 1): static points within the
    radius of any of its 5 positions are near; between two positions farther than the radius from both, or beyond
    the last one, they are not; members never are. A second cluster turned 90 degrees about z puts its member
    (1, 0, 5) at (0, 1, 5)."""
    from fgjax.cluster import near_swept

    t = 5
    poses = np.tile(np.eye(4), (2, t, 1, 1))
    poses[0, :, 0, 3] = np.linspace(0.0, 1.0, t)
    poses[1, -1, :3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    pts = np.array([[0.0, 0.0, 0.0],  # cluster 0's member
                    [1.0, 0.0, 5.0],  # cluster 1's member
                    [0.5, 0.05, 0.0],  # 0.05 from the middle position: near
                    [0.125, 0.09, 0.0],  # between two positions, sqrt(0.125^2 + 0.09^2) = 0.154 from both: not
                    [1.09, 0.0, 0.0],  # 0.09 beyond the last position: near
                    [1.2, 0.0, 0.0],  # 0.2 beyond: not
                    [0.0, 1.05, 5.0],  # by cluster 1's turned member: near
                    [0.7, 0.7, 5.0]])  # on the arc it did not sample: not
    lab = np.array([0, 1, -1, -1, -1, -1, -1, -1])
    np.testing.assert_array_equal(near_swept(pts, lab, poses, 0.1), [0, 0, 1, 0, 1, 0, 1, 0])
    np.testing.assert_array_equal(near_swept(pts, lab, poses, 0.0), 0)  # off
    np.testing.assert_array_equal(near_swept(pts, np.full(len(pts), -1), poses, 0.1), 0)  # no clusters
    # a dropped (non-finite) pose is left out, not spread
    bad = poses.copy()
    bad[0, 2] = np.nan
    np.testing.assert_array_equal(near_swept(pts, lab, bad, 0.1), [0, 0, 0, 0, 1, 0, 1, 0])
    with pytest.raises(ValueError, match="near_swept: radius"):
        near_swept(pts, lab, poses, -1.0)
    with pytest.raises(ValueError, match="near_swept: poses"):
        near_swept(pts, lab, poses[:1], 0.1)
    with pytest.raises(ValueError, match="near_swept: labels"):
        near_swept(pts, lab[:-1], poses, 0.1)


def test_drop_isolated_drops_the_members_far_from_the_rest_of_their_cluster():
    """`drop_isolated`: two clusters on grids of spacings 0.01 and 0.05 (the cut is each cluster's own median
    spacing times the factor), three members of the dense one 0.04 off its face are dropped, the sparse one keeps
    every member; a member whose only close neighbour is dead is dropped too; unlabelled points and dead members keep
    their labels; a cluster of two is left alone; inf drops nothing; bad inputs raise."""
    from fgjax.cluster import drop_isolated

    g = np.stack(np.meshgrid(np.arange(10), np.arange(10), indexing="ij"), -1).reshape(-1, 2) * 1.0
    dense = np.c_[g * 0.01, np.zeros(100)]  # a 0.09 x 0.09 face, spacing 0.01
    sparse = np.c_[g * 0.05 + [2.0, 0.0], np.zeros(100)]  # spacing 0.05, far away
    off = np.array([[0.02, 0.02, 0.04], [0.05, 0.05, -0.04], [0.09, 0.0, 0.04]])  # 0.04 from the face
    lonely = np.array([[-0.2, 0.0, 0.0], [-0.205, 0.0, 0.0]])  # a member and its only neighbour (dead)
    static = np.array([[0.5, 0.5, 0.5]])
    pair = np.array([[5.0, 0.0, 0.0], [6.0, 0.0, 0.0]])
    pts = np.concatenate([dense, sparse, off, lonely, static, pair])
    lab = np.r_[np.zeros(100), np.ones(100), np.zeros(3), [0, 0], [-1], [2, 2]].astype(int)
    alive = np.ones(len(pts), bool)
    alive[204] = False  # the lonely member's neighbour
    out = drop_isolated(pts, lab, 2.5, alive)
    dropped = np.flatnonzero(out != lab)
    np.testing.assert_array_equal(dropped, [200, 201, 202, 203])  # the three off the face, the lonely one
    assert np.all(out[dropped] == -1)
    assert out[204] == 0 and out[205] == -1 and list(out[206:208]) == [2, 2]
    # without the alive mask the lonely pair keeps each other
    assert drop_isolated(pts, lab, 2.5)[203] == 0
    np.testing.assert_array_equal(drop_isolated(pts, lab, np.inf, alive), lab)
    for bad, msg in ((dict(factor=0.0), "factor"), (dict(factor=0.9), "factor"), (dict(factor=float("nan")), "factor"),
                     (dict(labels=lab[:-1]), "labels"), (dict(alive=alive[:-1]), "alive"),
                     (dict(points=np.where(np.arange(len(pts))[:, None] == 3, np.nan, pts)), "non-finite")):
        kw = {"points": pts, "labels": lab, "factor": 2.5, "alive": alive, **bad}
        with pytest.raises(ValueError, match=msg):
            drop_isolated(**kw)


def _lid_scene(seed=0, lid_rgb=(0.9, 0.75, 0.15), box_rgb=(0.3, 0.38, 0.25)):
    """A lid-like part (a 0.36 x 0.26 plate, spacing 0.01) on a box whose walls' tops lie under its edges, with
    the labels that motion cues leave: the plate's strip along its hinge (y > 0.09) unlabelled, the walls' top
    rows (within 0.02 below the plate) labelled with it. Colours: each set's own, with a checker and noise."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(-0.18, 0.1801, 0.01), np.arange(-0.13, 0.1301, 0.01), indexing="ij")
    plate = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 0.22)]
    walls = []
    for z in np.arange(0.0, 0.2101, 0.01):
        for x in np.arange(-0.18, 0.1801, 0.01):
            walls += [[x, -0.13, z], [x, 0.13, z]]
        for y in np.arange(-0.12, 0.1201, 0.01):
            walls += [[-0.18, y, z], [0.18, y, z]]
    walls = np.array(walls)
    pts = np.concatenate([plate, walls])
    truth = np.r_[np.zeros(len(plate), int), np.full(len(walls), -1)]
    checker = ((np.floor(pts[:, 0] / 0.05) + np.floor(pts[:, 1] / 0.05) + np.floor(pts[:, 2] / 0.05)) % 2)[:, None]
    base = np.where(truth[:, None] == 0, lid_rgb, box_rgb)
    col = np.clip(base * (0.85 + 0.3 * checker) + rng.normal(0, 0.03, pts.shape), 0, 1)
    lab = truth.copy()
    lab[(truth == 0) & (pts[:, 1] > 0.09)] = -1  # the hinge strip
    lab[(truth == -1) & (pts[:, 2] >= 0.19)] = 0  # the walls' tops
    return pts, col, lab, truth


def test_refine_by_colour_mends_a_lids_outline_and_leaves_an_alike_part_alone():
    """`refine_by_colour` on `_lid_scene`: the hinge strip (148 Gaussians) joins and the walls' tops (372) leave,
    every one, and nothing else changes; the report counts them (without ``colour_floor`` a few odd colours of the
    plate leave too). A part coloured like its box is left as it was
    (its separation is reported below the cut); so is a part with too few members, or one whose round would change
    more than ``max_change`` of it. Gaussians that are not usable keep their labels. Bad inputs raise."""
    pts, col, lab, truth = _lid_scene()
    assert np.sum((truth == 0) & (lab == -1)) == 148 and np.sum((truth == -1) & (lab == 0)) == 372
    out, rep = C.refine_by_colour(pts, col, lab, radius=0.08)
    np.testing.assert_array_equal(out, truth)
    assert rep[0]["joined"] == 148 and rep[0]["left"] == 372 and rep[0]["skipped"] is None
    # without the colour floor, mixture components fit a few of the plate's brightest colours, which then leave
    out_nf, _ = C.refine_by_colour(pts, col, lab, radius=0.08, colour_floor=1e-6)
    assert np.sum(out_nf != truth) >= 1
    assert 0.65 <= rep[0]["separation"] <= 1.0
    # not usable: keeps its label (one strip Gaussian, one wall top)
    usable = np.ones(len(pts), bool)
    strip, top = np.flatnonzero((truth == 0) & (lab == -1))[0], np.flatnonzero((truth == -1) & (lab == 0))[0]
    usable[[strip, top]] = False
    out_u, _ = C.refine_by_colour(pts, col, lab, usable, radius=0.08)
    assert out_u[strip] == -1 and out_u[top] == 0 and out[top] == -1
    # a part coloured like its box: nothing changes, and the report says why
    pts2, col2, lab2, _ = _lid_scene(lid_rgb=(0.3, 0.38, 0.25))
    out2, rep2 = C.refine_by_colour(pts2, col2, lab2, radius=0.08)
    np.testing.assert_array_equal(out2, lab2)
    assert rep2[0]["separation"] < 0.65 and "colours apart" in rep2[0]["skipped"]
    assert rep2[0]["joined"] == rep2[0]["left"] == 0
    # too few members; too large a change
    few = np.where(np.arange(len(lab)) < 10, lab, -1)
    out3, rep3 = C.refine_by_colour(pts, col, few, radius=0.08)
    np.testing.assert_array_equal(out3, few)
    assert "usable members" in rep3[0]["skipped"]
    out4, rep4 = C.refine_by_colour(pts, col, lab, radius=0.08, max_change=0.1)
    np.testing.assert_array_equal(out4, lab)
    assert "would change" in rep4[0]["skipped"]
    # no clusters: nothing to do
    out5, rep5 = C.refine_by_colour(pts, col, np.full(len(lab), -1), radius=0.08)
    assert rep5 == [] and np.all(out5 == -1)
    for bad, msg in ((dict(colours=col[:-1]), "colours"),
                     (dict(colours=np.where(pts == pts[3], np.nan, col)), "colours"),
                     (dict(labels=lab[:-1]), "labels"), (dict(usable=usable[:-1]), "usable"),
                     (dict(radius=0.0), "radius"), (dict(radius=float("nan")), "radius"),
                     (dict(n_components=0), "n_components"), (dict(min_separation=1.5), "min_separation"),
                     (dict(colour_floor=0.0), "colour_floor"),
                     (dict(points=np.where(np.arange(len(pts))[:, None] == 3, np.inf, pts)), "non-finite")):
        kw = {"points": pts, "colours": col, "labels": lab, "usable": usable, "radius": 0.08, **bad}
        with pytest.raises(ValueError, match=msg):
            C.refine_by_colour(**kw)
