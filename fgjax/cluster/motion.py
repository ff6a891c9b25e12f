"""Per-frame motion of clusters: clustering by position and motion together, moving frames, splitting clusters
that move at different times, merging fragments that move together, and the second selection pass in each
cluster's own moving frames."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from jaxtyping import Bool, Float, Int
from scipy import sparse
from scipy.spatial import cKDTree
from sklearn.cluster import DBSCAN
from sklearn.neighbors import NearestNeighbors

from fgjax.cluster.dbscan import as_points, relabel_by_size, size_cut
from fgjax.cluster.dbscan import auto_eps as _auto_eps


def _motion_profile(mv: np.ndarray, tt: np.ndarray, mem: np.ndarray) -> np.ndarray:
    """A cluster's moving fraction per frame, m(t) = sum_{i in mem} moving_it / sum_{i in mem} total_it:
    [T] (`moving_t`, `total_t` [T, M]; `mem` [M] bool)."""
    return mv[:, mem].sum(1) / np.maximum(tt[:, mem].sum(1), 1e-12)


def moving_frames(
    labels: Int[np.ndarray, " M"],
    moving_t: Float[np.ndarray, "T M"],
    total_t: Float[np.ndarray, "T M"],
    *,
    active: float = 0.5,
    dilate: int = 0,
) -> Bool[np.ndarray, "K T"]:
    """The frames in which each cluster moves: [K, T] bool (K = max label + 1).

    Cluster k's moving fraction m_k(t) = sum_{i in k} moving_it / sum_{i in k} total_it (the share of its
    painted weight that lies on moving pixels in frame t); frame t is a moving frame when
    m_k(t) >= ``active`` x max_t m_k(t) > 0, then the set is widened by ``dilate`` frames on each side."""
    lab = np.asarray(labels, np.int64)
    mv = np.asarray(moving_t, np.float64)
    tt = np.asarray(total_t, np.float64)
    if mv.ndim != 2 or mv.shape[1] != len(lab) or tt.shape != mv.shape:
        raise ValueError(f"moving_frames: moving_t and total_t must both have shape [T, {len(lab)}], got "
                         f"{list(mv.shape)} and {list(tt.shape)}")
    k_num = int(lab.max()) + 1 if np.any(lab >= 0) else 0
    out = np.zeros((k_num, mv.shape[0]), bool)
    for k in range(k_num):
        mem = lab == k
        if not np.any(mem):
            continue
        prof = _motion_profile(mv, tt, mem)
        if prof.max() > 0:
            out[k] = prof >= active * prof.max()
    for _ in range(max(int(dilate), 0)):
        prev = out.copy()
        out[:, 1:] |= prev[:, :-1]
        out[:, :-1] |= prev[:, 1:]
    return out


def true_runs(mask: np.ndarray, min_gap: int = 1) -> list[np.ndarray]:
    """Index arrays of the runs of True in `mask` [T]; runs separated by fewer than `min_gap` False frames merge
    (1: every maximal run on its own)."""
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return []
    cuts = np.flatnonzero(np.diff(idx) > min_gap) + 1
    return np.split(idx, cuts)


def _activity_inputs(name: str, points, labels, moving_t, total_t):
    """(points [M, D], a copy of labels [M] int64, moving_t and total_t [T, M] float64), shapes checked."""
    pts = as_points(points, "points")
    lab = np.asarray(labels, np.int64).copy()
    mv = np.asarray(moving_t, np.float64)
    tt = np.asarray(total_t, np.float64)
    if lab.shape != (len(pts),) or mv.ndim != 2 or mv.shape[1] != len(pts) or tt.shape != mv.shape:
        raise ValueError(f"{name}: labels [{len(pts)}] and moving_t, total_t [T, {len(pts)}] expected, got "
                         f"{list(lab.shape)}, {list(mv.shape)}, {list(tt.shape)}")
    return pts, lab, mv, tt


def activity_correlation(
    moving_t: Float[np.ndarray, "T M"], total_t: Float[np.ndarray, "T M"], *, eps: float = 0.1
) -> Float[np.ndarray, "T M"]:
    """Each point's activity profile, centred and scaled to unit norm: [T, M].

    a_it = moving_it / (total_it + eps) is the share of what point i paints in frame t that lies on moving pixels
    (``eps`` in pixel-equivalents damps frames where it is barely seen); z_i = (a_i - mean_t a_i) / ||a_i -
    mean_t a_i||, so that z_i . z_j is the Pearson correlation of the two profiles. A constant profile (no evidence
    of when the point moves) gives z_i = 0, i.e. correlation 0 with every other point.
    """
    mv = np.asarray(moving_t, np.float64)
    tt = np.asarray(total_t, np.float64)
    if mv.ndim != 2 or tt.shape != mv.shape:
        raise ValueError(f"activity_correlation: moving_t and total_t must both have shape [T, M], got "
                         f"{list(mv.shape)} and {list(tt.shape)}")
    if not (np.all(np.isfinite(mv)) and np.all(np.isfinite(tt))):
        raise ValueError("activity_correlation: moving_t and total_t must be finite")
    a = mv / (tt + eps)
    z = a - a.mean(0)
    norm = np.linalg.norm(z, axis=0)
    return np.where(norm > 1e-12, z / np.maximum(norm, 1e-12), 0.0)


def cluster_by_motion(
    points: Float[np.ndarray, "M D"],
    moving_t: Float[np.ndarray, "T M"],
    total_t: Float[np.ndarray, "T M"],
    *,
    eps: float,
    min_samples: int = 5,
    min_corr: float = 0.8,
    min_fraction: float = 0.0,
    auto_eps: bool = False,
) -> Int[np.ndarray, " M"]:
    """DBSCAN whose neighbours must also move together: points i, j are neighbours when ||x_i - x_j|| <= eps and
    the Pearson correlation of their activity profiles (`activity_correlation`) is at least ``min_corr``.

    Position alone chains parts that touch (a lid on a cabinet whose door swings) into one cluster through the
    Gaussians along their seams; parts that move at different times have uncorrelated or anti-correlated
    profiles, so the gated neighbourhood graph cuts those chains where the motion changes. With ``min_corr`` <= -1
    every pair within eps is linked: plain DBSCAN. A part whose members are cut into pieces (its seam Gaussians
    are partly occluded) is joined again by `merge_fragments`, whose cluster profiles are averages and much less
    noisy than single points'.

    Args:
        points: [M, D] canonical centres.
        moving_t, total_t: [T, M] per-frame discovery terms of the points (`fgjax.method.discover.Scores`).
        eps: neighbourhood radius (> 0).
        min_samples: neighbours of a core point, itself included.
        min_corr: the smallest profile correlation of two neighbours, in [-1, 1].
        min_fraction, auto_eps: as in `fgjax.cluster.cluster_dynamic` (the size cut; eps from the k-distance knee).

    Returns:
        [M] int64 labels, -1 = noise, 0..K-1 by decreasing size.
    """
    pts = as_points(points, "cluster_by_motion")
    m = len(pts)
    if not eps > 0:
        raise ValueError(f"cluster_by_motion: eps must be > 0, got {eps}")
    if min_samples < 1:
        raise ValueError(f"cluster_by_motion: min_samples must be >= 1, got {min_samples}")
    if not -1.0 <= min_corr <= 1.0:
        raise ValueError(f"cluster_by_motion: min_corr must be in [-1, 1], got {min_corr}")
    mv = np.asarray(moving_t, np.float64)
    tt = np.asarray(total_t, np.float64)
    if mv.ndim != 2 or mv.shape[1] != m or tt.shape != mv.shape:
        raise ValueError(f"cluster_by_motion: moving_t and total_t must have shape [T, {m}], got "
                         f"{list(mv.shape)} and {list(tt.shape)}")
    if not 0.0 <= min_fraction < 1.0:
        raise ValueError(f"cluster_by_motion: min_fraction must be in [0, 1), got {min_fraction}")
    if m < max(min_samples, 2):
        return np.full(m, -1, np.int64)
    if auto_eps:
        eps = _auto_eps(pts, max(min_samples - 1, 1))
    z = activity_correlation(mv, tt)
    g = NearestNeighbors(radius=eps).fit(pts).radius_neighbors_graph(pts, mode="distance").tocoo()
    keep = (g.row == g.col) | (np.einsum("tk,tk->k", z[:, g.row], z[:, g.col]) >= min_corr - 1e-12)
    # stored entries are the neighbours of a precomputed sparse graph (a zero distance is kept as an entry)
    graph = sparse.csr_matrix((np.maximum(g.data[keep], 0.0), (g.row[keep], g.col[keep])), shape=(m, m))
    raw = DBSCAN(eps=eps, min_samples=min_samples, metric="precomputed").fit_predict(graph)
    return relabel_by_size(raw, min_size=size_cut(min_fraction, m))


def split_by_motion(
    points: Float[np.ndarray, "M D"],
    labels: Int[np.ndarray, " M"],
    moving_t: Float[np.ndarray, "T M"],
    total_t: Float[np.ndarray, "T M"],
    *,
    active: float = 0.5,
    min_gap: int = 2,
    min_size: int = 5,
    eps: float = 0.1,
) -> Int[np.ndarray, " M"]:
    """Split clusters that hold parts moving at different times.

    Two parts closer than DBSCAN's eps merge into one cluster, although they usually move at different
    times. A cluster's moving frames (`moving_frames`) fall into runs (separated by at least
    ``min_gap`` resting frames). Each member's activity in run r is a_ir = sum_{t in r} moving_it /
    (sum_{t in r} total_it + eps). Runs whose activities are positively correlated over the members (one
    part opening, then closing: the same members move in both) form one group; a cluster with several
    groups is split, each member going to the group where its mean activity is largest (members with
    no activity in any run: to the group of their nearest active member). Parts smaller than
    ``min_size`` stay merged (with the largest part). Returns new labels [M], 0..K'-1 by decreasing size.
    """
    pts, lab, mv, tt = _activity_inputs("split_by_motion", points, labels, moving_t, total_t)
    frames = moving_frames(lab, mv, tt, active=active)
    out = lab.copy()
    next_label = int(lab.max()) + 1 if np.any(lab >= 0) else 0
    for k in range(len(frames)):
        runs = true_runs(frames[k], min_gap)
        mem = np.flatnonzero(lab == k)
        if len(runs) < 2 or len(mem) < 2 * min_size:
            continue
        act = np.stack([mv[r][:, mem].sum(0) / (tt[r][:, mem].sum(0) + eps) for r in runs], 1)  # [members, runs]
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = np.nan_to_num(np.corrcoef(act.T), nan=1.0)  # [runs, runs]; a constant column: no evidence
        group = np.arange(len(runs))  # union-find over positively correlated runs
        for a in range(len(runs)):
            for b in range(a + 1, len(runs)):
                if corr[a, b] > 0:
                    group[group == group[b]] = group[a]
        gids = np.unique(group)
        if len(gids) < 2:
            continue
        score = np.stack([act[:, group == g].mean(1) for g in gids], 1)  # [members, groups]
        pick = np.argmax(score, 1)
        idle = score.max(1) <= 0
        if np.any(idle) and np.any(~idle):
            _, nn = cKDTree(pts[mem[~idle]]).query(pts[mem[idle]], k=1)
            pick[idle] = pick[~idle][nn]
        sizes = np.bincount(pick, minlength=len(gids))
        big = int(np.argmax(sizes))
        for g in range(len(gids)):
            if g != big and sizes[g] < min_size:
                pick[pick == g] = big
        for g in np.unique(pick):
            if g != big:
                out[mem[pick == g]] = next_label
                next_label += 1
    return relabel_by_size(out)


def merge_fragments(
    points: Float[np.ndarray, "M D"],
    labels: Int[np.ndarray, " M"],
    moving_t: Float[np.ndarray, "T M"],
    total_t: Float[np.ndarray, "T M"],
    *,
    eps: float,
    min_corr: float = 0.0,
) -> Int[np.ndarray, " M"]:
    """Join clusters that are fragments of one part: their closest members lie within ``eps`` and their
    motion profiles are positively correlated (> ``min_corr``).

    DBSCAN links two groups only through core points, so a part whose dynamic set has a thin gap (a
    Gaussian there scored below the cut) comes out as fragments even when members on both sides are
    closer than eps; each fragment may then fall below the size cut on its own. A cluster's motion
    profile is m_k(t) = sum_{i in k} moving_it / sum_{i in k} total_it (as in `moving_frames`); parts that
    move at different times are not joined. Joins are transitive. Returns labels [M] renumbered 0..K'-1 by
    decreasing size (noise stays -1).
    """
    pts, lab, mv, tt = _activity_inputs("merge_fragments", points, labels, moving_t, total_t)
    if not eps > 0:
        raise ValueError(f"merge_fragments: eps must be > 0, got {eps}")
    ks = np.unique(lab[lab >= 0])
    if len(ks) < 2:
        return relabel_by_size(lab)
    prof = np.stack([_motion_profile(mv, tt, lab == k) for k in ks])  # [K, T]
    parent = {int(k): int(k) for k in ks}

    def root(k):
        while parent[k] != k:
            k = parent[k]
        return k

    trees = {int(k): cKDTree(pts[lab == k]) for k in ks}
    for a in range(len(ks)):
        for b in range(a + 1, len(ks)):
            ka, kb = int(ks[a]), int(ks[b])
            if root(ka) == root(kb):
                continue
            d = trees[ka].query(pts[lab == kb], k=1, distance_upper_bound=eps * (1 + 1e-9))[0]
            if not np.any(np.isfinite(d)):
                continue
            with np.errstate(invalid="ignore", divide="ignore"):
                c = np.corrcoef(prof[a], prof[b])[0, 1]
            if np.isfinite(c) and c > min_corr:
                parent[root(kb)] = root(ka)
    out = lab.copy()
    for k in ks:
        out[lab == k] = root(int(k))
    return relabel_by_size(out)


class Localized(NamedTuple):
    """Result of `localize_clusters`.

    labels: [M] new labels (-1 = none).
    frames: [K, T] bool, the frames in which each cluster moves.
    scores: [M] the score each point got for the cluster it was tested against (NaN: not tested).
    joined: [K] points that joined each cluster.
    """

    labels: Int[np.ndarray, " M"]
    frames: Bool[np.ndarray, "K T"]
    scores: Float[np.ndarray, " M"]
    joined: tuple[int, ...]


def localize_clusters(
    points: Float[np.ndarray, "M D"],
    labels: Int[np.ndarray, " M"],
    moving_t: Float[np.ndarray, "T M"],
    total_t: Float[np.ndarray, "T M"],
    *,
    radius: float,
    threshold: float,
    candidates: Bool[np.ndarray, " M"] | None = None,
    active: float = 0.5,
    eps: float = 0.1,
) -> Localized:
    """Second pass of the selection, in each cluster's own moving frames: unlabelled points near a
    cluster join it when they lie on moving pixels in most of the frames where that cluster moves.

    The global score sum_t moving_t / sum_t total_t of `fgjax.method.discover` is diluted by every
    frame in which a part rests: a lid that moves in 8 of 60 frames scores ~0.1 even where it is painted
    on moving pixels whenever it moves, below the global cut that the parts moving longer set. Here,
    cluster k's moving frames F_k are those where its members' moving fraction
    m_k(t) = sum_{i in k} moving_it / sum_{i in k} total_it is at least ``active`` x max_t m_k(t); every
    candidate within ``radius`` of a member (unlabelled, and a ``candidates`` point when given) gets
    s_ik = sum_{t in F_k} moving_it / (sum_{t in F_k} total_it + eps) and joins k when s_ik >= ``threshold``
    (the largest s_ik wins when several clusters reach it). Members keep their labels.

    Args:
        points: [M, D] positions (canonical centres).
        labels: [M] cluster ids 0..K-1, -1 none.
        moving_t, total_t: [T, M] per-frame painted weight on moving pixels and in all
            (`fgjax.method.discover.Scores.moving_t` / ``total_t``).
        radius: search radius around a cluster's members (same units as `points`).
        threshold: the cut of s_ik in [0, 1].
        candidates: [M] bool, the points allowed to join (None: all).
        active: a frame is in F_k when m_k(t) >= active * max_t m_k(t).
        eps: pixel-equivalents added to the denominator (points hardly seen in F_k score low).

    Returns:
        `Localized`.
    """
    pts = as_points(points, "points")
    m = len(pts)
    lab = np.asarray(labels, np.int64).copy()
    mv = np.asarray(moving_t, np.float64)
    tt = np.asarray(total_t, np.float64)
    if lab.shape != (m,):
        raise ValueError(f"localize_clusters: labels must have shape [{m}], got {list(lab.shape)}")
    if mv.ndim != 2 or mv.shape[1] != m or tt.shape != mv.shape:
        raise ValueError(f"localize_clusters: moving_t and total_t must both have shape [T, {m}], got "
                         f"{list(mv.shape)} and {list(tt.shape)}")
    if not radius > 0 or not 0.0 <= threshold <= 1.0 or not 0.0 < active <= 1.0:
        raise ValueError(f"localize_clusters: need radius > 0, threshold in [0, 1] and active in (0, 1]; got "
                         f"{radius}, {threshold}, {active}")
    cand = np.ones(m, bool) if candidates is None else np.asarray(candidates, bool)
    if cand.shape != (m,):
        raise ValueError(f"localize_clusters: candidates must have shape [{m}], got {list(cand.shape)}")
    frames = moving_frames(lab, mv, tt, active=active)
    k_num = len(frames)
    best = np.full(m, -np.inf)
    best_k = np.full(m, -1, np.int64)
    scores = np.full(m, np.nan)
    free = cand & (lab < 0)
    for k in range(k_num):
        mem = lab == k
        if not np.any(mem) or not np.any(frames[k]):
            continue
        near = np.isfinite(cKDTree(pts[mem]).query(pts, k=1, distance_upper_bound=radius)[0]) & free
        idx = np.flatnonzero(near)
        if len(idx) == 0:
            continue
        f = frames[k]
        s = mv[f][:, idx].sum(0) / (tt[f][:, idx].sum(0) + eps)  # [len(idx)]
        scores[idx] = np.where(np.isnan(scores[idx]), s, np.fmax(scores[idx], s))
        win = (s >= threshold) & (s > best[idx])
        best[idx[win]] = s[win]
        best_k[idx[win]] = k
    join = best_k >= 0
    lab[join] = best_k[join]
    joined = tuple(int(np.sum(join & (best_k == k))) for k in range(k_num))
    return Localized(labels=lab, frames=frames, scores=scores, joined=joined)
