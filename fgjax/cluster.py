"""Dynamic-Gaussian selection, clustering into objects, trajectories and trajectory snapping.

DESIGN.md section 1, steps 5 (selection of the dynamic set D from per-Gaussian scores), 6 (DBSCAN /
HDBSCAN on the canonical centres of D; the trajectory ς(t, k) of cluster k is the mean deformed
centre of its Gaussians) and 8 (a user's 3D vector is snapped to the nearest point of ς(·, k)).

Layering (DESIGN.md section 3): numpy + scikit-learn only; nothing here knows of JAX or of models.
Every function takes and returns plain numpy arrays. Label conventions: cluster labels are
0..K-1, ordered by decreasing cluster size (ties: by first occurrence), and -1 is noise.
"""

from __future__ import annotations

import dataclasses
from typing import Literal, NamedTuple

import numpy as np
from jaxtyping import Bool, Float, Int

__all__ = [
    "grow_clusters",
    "fill_hulls",
    "hinge_axes",
    "fill_hinges",
    "drop_isolated",
    "refine_by_colour",
    "localize_clusters",
    "split_by_motion",
    "merge_fragments",
    "true_runs",
    "moving_frames",
    "Localized",
    "otsu_threshold",
    "select_dynamic",
    "k_distances",
    "auto_eps",
    "cluster_dynamic",
    "relabel_by_size",
    "size_cut",
    "ClusterReport",
    "cluster_report",
    "trajectories",
    "Snap",
    "snap_to_trajectory",
]


# ============================================================================ selection


def otsu_threshold(values: Float[np.ndarray, ...], *, bins: int = 256) -> float:
    """Otsu's threshold: the cut that maximises the between-class variance of a 1D sample.

    For a histogram with class probabilities w0(c), w1(c) and means m0(c), m1(c) of the values
    below / above the cut c, Otsu (1979) picks argmax_c w0 w1 (m0 - m1)^2. The histogram has
    `bins` equal bins over [min, max] of the finite values; the threshold returned is the upper
    edge of the last bin of the lower class, so ``values > threshold`` is the upper class.

    Args:
        values: any shape; non-finite entries are ignored.
        bins: number of histogram bins (>= 2).

    Returns:
        The threshold. With no finite values it is +inf (nothing is above it); with a single
        distinct value it is that value (nothing is strictly above it).
    """
    if bins < 2:
        raise ValueError(f"otsu_threshold: bins must be >= 2, got {bins}")
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("inf")
    lo, hi = float(v.min()), float(v.max())
    if hi <= lo:
        return hi
    hist, edges = np.histogram(v, bins=bins, range=(lo, hi))
    centres = 0.5 * (edges[:-1] + edges[1:])
    p = hist / v.size
    w0 = np.cumsum(p)  # [bins] weight of the class at or below each cut
    mu = np.cumsum(p * centres)
    mu_t = mu[-1]
    w1 = 1.0 - w0
    ok = (w0 > 0) & (w1 > 1e-12)
    between = np.zeros_like(w0)
    den = np.where(ok, w0 * w1, 1.0)
    between[ok] = ((mu_t * w0 - mu) ** 2 / den)[ok]
    i = int(np.argmax(between))
    return float(edges[i + 1])


def select_dynamic(
    scores: Float[np.ndarray, " N"],
    threshold: float | Literal["otsu"] = "otsu",
    *,
    min_score: float = 0.0,
    valid: Bool[np.ndarray, " N"] | None = None,
) -> Bool[np.ndarray, " N"]:
    """The dynamic set D: Gaussians whose discovery score is above a threshold (step 5).

    D = valid & (score > threshold) & (score > min_score). With ``threshold="otsu"`` the cut is
    `otsu_threshold` of the valid, finite scores: the scores of a scene with moving parts are
    bimodal (near 0 for static Gaussians, a fraction of their visibility for moving ones), and
    `min_score` keeps a scene with nothing moving from being split in two by noise.

    Args:
        scores: [N] per-Gaussian scores (e.g. `fgjax.pipeline.discover.accumulate_scores`).
        threshold: a number, or ``"otsu"``.
        min_score: a floor under the threshold.
        valid: [N] Gaussians that may be selected (e.g. seen often enough); None = all.

    Returns:
        [N] bool mask D. Non-finite scores are never selected; an empty input gives an empty mask.
    """
    s = np.asarray(scores, dtype=np.float64)
    if s.ndim != 1:
        raise ValueError(f"select_dynamic: scores must have shape [N], got {s.shape}")
    ok = np.isfinite(s)
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != s.shape:
            raise ValueError(f"select_dynamic: valid must have shape {s.shape}, got {valid.shape}")
        ok &= valid
    if isinstance(threshold, str):
        if threshold != "otsu":
            raise ValueError(f"select_dynamic: threshold must be a number or 'otsu', got {threshold!r}")
        thr = otsu_threshold(s[ok]) if ok.any() else float("inf")
    else:
        thr = float(threshold)
    return ok & (s > thr) & (s > min_score)


# ============================================================================ clustering


def _points(points, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] < 1:
        raise ValueError(f"{name}: points must have shape [M, D], got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: points contain non-finite values")
    return p


def k_distances(points: Float[np.ndarray, "M D"], k: int) -> Float[np.ndarray, " M"]:
    """Sorted (ascending) distance of every point to its k-th nearest neighbour, itself excluded."""
    from sklearn.neighbors import NearestNeighbors

    p = _points(points, "k_distances")
    if k < 1:
        raise ValueError(f"k_distances: k must be >= 1, got {k}")
    if len(p) <= k:
        raise ValueError(f"k_distances: need more than k={k} points, got {len(p)}")
    d, _ = NearestNeighbors(n_neighbors=k + 1).fit(p).kneighbors(p)
    return np.sort(d[:, k])


def auto_eps(points: Float[np.ndarray, "M D"], k: int = 4) -> float:
    """DBSCAN radius from the knee of the sorted k-distance curve (Ester et al. 1996, section 4.2).

    The curve d_(1) <= ... <= d_(M) of k-th-neighbour distances is flat inside clusters and rises
    steeply for noise. Both axes are rescaled to [0, 1] (index i / (M - 1) and
    (d - d_min) / (d_max - d_min)), and the knee is the sample farthest from the chord joining the
    first and last samples (the "kneedle" construction, Satopää et al. 2011, for a convex
    increasing curve); its distance is returned. With DBSCAN's `min_samples` (which counts the
    point itself) use k = min_samples - 1, so that the knee radius makes the flat part core points.

    Args:
        points: [M, D].
        k: neighbour rank (>= 1).

    Returns:
        eps > 0 (for a flat curve, the common k-distance; if that is 0, i.e. duplicate points,
        the smallest positive pairwise scale is not defined and 1e-12 is returned).

    Raises:
        ValueError: fewer than k + 1 points.
    """
    d = k_distances(points, k)
    lo, hi = float(d[0]), float(d[-1])
    if hi - lo <= 1e-12 * max(hi, 1.0):
        return max(hi, 1e-12)
    x = np.linspace(0.0, 1.0, len(d))
    y = (d - lo) / (hi - lo)
    # distance of (x, y) to the chord y = x (first sample (0, 0), last (1, 1)): |x - y| / sqrt 2;
    # on a convex increasing curve the knee is where x - y is largest.
    i = int(np.argmax(x - y))
    return max(float(d[i]), 1e-12)


_auto_eps = auto_eps  # `cluster_dynamic` has a flag of the same name


def relabel_by_size(labels: Int[np.ndarray, " M"], *, min_size: int = 1) -> Int[np.ndarray, " M"]:
    """Clusters smaller than `min_size` become noise (-1); the rest are renumbered 0..K-1 by size.

    Largest first; equal sizes keep their order of first occurrence.
    """
    lab = np.asarray(labels).astype(np.int64).ravel()
    out = np.full(lab.shape, -1, np.int64)
    ids, first, counts = np.unique(lab[lab >= 0], return_index=True, return_counts=True)
    keep = counts >= max(min_size, 1)
    ids, first, counts = ids[keep], first[keep], counts[keep]
    order = np.lexsort((first, -counts))  # size descending, then first occurrence
    for new, old in enumerate(ids[order]):
        out[lab == old] = new
    return out


def size_cut(min_fraction: float, m: int) -> int:
    """The size cut of `cluster_dynamic`: clusters of fewer than max(1, ceil(min_fraction * m)) points drop."""
    return max(1, int(np.ceil(min_fraction * m)))


def cluster_dynamic(
    points: Float[np.ndarray, "M 3"],
    method: Literal["dbscan", "hdbscan"] = "dbscan",
    *,
    eps: float = 0.05,
    min_samples: int = 5,
    min_fraction: float = 0.01,
    auto_eps: bool = False,
    min_cluster_size: int | None = None,
) -> Int[np.ndarray, " M"]:
    """Group the dynamic Gaussians into objects (step 6): DBSCAN or HDBSCAN on canonical centres.

    DBSCAN (Euclidean, radius `eps` in scene units, `min_samples` counting the point itself) or
    HDBSCAN (scikit-learn; `min_samples` as above, `min_cluster_size` defaulting to
    max(2, min_samples); `eps` unused). Clusters with fewer than max(1, ceil(min_fraction * M))
    points are dropped to noise, then the labels are renumbered 0..K-1 by decreasing size.

    Args:
        points: [M, 3] canonical centres of the Gaussians in D.
        method: ``"dbscan"`` or ``"hdbscan"``.
        eps: DBSCAN radius (scene units).
        min_samples: neighbourhood count of a core point (itself included).
        min_fraction: smallest cluster kept, as a fraction of M.
        auto_eps: replace `eps` by `auto_eps(points, min_samples - 1)` (DBSCAN only).
        min_cluster_size: HDBSCAN's smallest cluster (None: max(2, min_samples)).

    Returns:
        [M] int64 labels, -1 = noise. M = 0 gives an empty array; fewer than `min_samples`
        points (no core point can exist) give all -1.
    """
    if np.size(points) == 0:
        return np.zeros(0, np.int64)
    p = _points(points, "cluster_dynamic")
    if method not in ("dbscan", "hdbscan"):
        raise ValueError(f"cluster_dynamic: method must be 'dbscan' or 'hdbscan', got {method!r}")
    if min_samples < 1:
        raise ValueError(f"cluster_dynamic: min_samples must be >= 1, got {min_samples}")
    if not 0.0 <= min_fraction < 1.0:
        raise ValueError(f"cluster_dynamic: min_fraction must be in [0, 1), got {min_fraction}")
    m = len(p)
    if m < max(min_samples, 2):
        return np.full(m, -1, np.int64)
    if method == "dbscan":
        from sklearn.cluster import DBSCAN

        if auto_eps:
            e = _auto_eps(p, max(min_samples - 1, 1))
        else:
            e = float(eps)
        if not e > 0:
            raise ValueError(f"cluster_dynamic: eps must be > 0, got {e}")
        raw = DBSCAN(eps=e, min_samples=min_samples).fit_predict(p)
    else:
        from sklearn.cluster import HDBSCAN

        mcs = max(2, min_samples) if min_cluster_size is None else int(min_cluster_size)
        if mcs < 2:
            raise ValueError(f"cluster_dynamic: min_cluster_size must be >= 2, got {mcs}")
        if m < mcs:
            return np.full(m, -1, np.int64)
        raw = HDBSCAN(min_cluster_size=mcs, min_samples=min_samples, copy=True).fit_predict(p)
    return relabel_by_size(raw, min_size=size_cut(min_fraction, m))


@dataclasses.dataclass(frozen=True)
class ClusterReport:
    """Summary of a clustering: point count, cluster count, sizes (largest first), noise count."""

    n_points: int
    n_clusters: int
    sizes: tuple[int, ...]
    n_noise: int

    def __str__(self) -> str:
        return (f"{self.n_clusters} cluster(s) of sizes {list(self.sizes)} among {self.n_points} dynamic "
                f"Gaussians, {self.n_noise} noise")


def grow_clusters(
    points: Float[np.ndarray, "M D"], labels: Int[np.ndarray, " M"], candidates: Bool[np.ndarray, " M"], eps: float,
    *, max_rounds: int = 50,
) -> Int[np.ndarray, " M"]:
    """Hysteresis region growing: unlabelled `candidates` within `eps` of a labelled point join its cluster.

    Repeats until nothing changes (or `max_rounds`), so chains of candidates connected to a cluster join
    it; a candidate joins the cluster of its nearest labelled point. Labels -1 = none; non-candidates
    never change. Returns the new labels [M]."""
    pts = _points(points, "points")
    lab = np.asarray(labels, np.int64).copy()
    cand = np.asarray(candidates, bool)
    if lab.shape != (len(pts),) or cand.shape != (len(pts),):
        raise ValueError(f"grow_clusters: labels and candidates must have shape [{len(pts)}], got {lab.shape}, "
                         f"{cand.shape}")
    if not eps > 0:
        raise ValueError(f"grow_clusters: eps must be > 0, got {eps}")
    from scipy.spatial import cKDTree

    for _ in range(max_rounds):
        have = np.flatnonzero(lab >= 0)
        todo = np.flatnonzero(cand & (lab < 0))
        if len(have) == 0 or len(todo) == 0:
            break
        d, j = cKDTree(pts[have]).query(pts[todo], k=1, distance_upper_bound=eps)
        hit = np.isfinite(d)
        if not np.any(hit):
            break
        lab[todo[hit]] = lab[have[j[hit]]]
    return lab


def near_swept(
    points: Float[np.ndarray, "M 3"], labels: Int[np.ndarray, " M"], poses: Float[np.ndarray, "K T 4 4"],
    radius: float, *, max_frames: int = 64,
) -> Bool[np.ndarray, " M"]:
    """Unlabelled points (label < 0) within `radius` of a cluster's members at any of its poses.

    Cluster k's members, moved rigidly by each of its poses T_k(t) (x -> R x + t; up to `max_frames` of the
    T, evenly spaced), sweep the volume the part passes through. A static point near it sits where the part
    is at some time, or right behind where it is at others: a reconstruction that blurred the part's states
    leaves Gaussians there that the rest frames cannot correct, since the part hides them (`Stage2Config.
    ghost_radius`). Returns [M] bool (False for every labelled point; all False when `radius` is 0)."""
    pts = np.asarray(points, np.float64)
    lab = np.asarray(labels, np.int64)
    pz = np.asarray(poses, np.float64)
    if lab.shape != (len(pts),):
        raise ValueError(f"near_swept: labels must have shape [{len(pts)}], got {lab.shape}")
    if not (np.isfinite(radius) and radius >= 0):
        raise ValueError(f"near_swept: radius must be finite and >= 0, got {radius!r}")
    k = int(lab.max(initial=-1)) + 1
    if pz.ndim != 4 or pz.shape[0] < k or pz.shape[2:] != (4, 4):
        raise ValueError(f"near_swept: poses must have shape [>= {k}, T, 4, 4], got {list(pz.shape)}")
    out = np.zeros(len(pts), bool)
    todo = np.flatnonzero(lab < 0)
    if radius == 0 or k == 0 or len(todo) == 0:
        return out
    from scipy.spatial import cKDTree

    frames = np.unique(np.linspace(0, pz.shape[1] - 1, min(pz.shape[1], max_frames)).round().astype(int))
    swept = [np.einsum("tij,mj->tmi", pz[c, frames, :3, :3], pts[lab == c]) + pz[c, frames, None, :3, 3]
             for c in range(k) if np.any(lab == c)]  # [T', M_c, 3] each
    swept = np.concatenate([x.reshape(-1, 3) for x in swept], 0)
    swept = swept[np.all(np.isfinite(swept), axis=1)]
    if len(swept):
        d, _ = cKDTree(swept).query(pts[todo], k=1, distance_upper_bound=radius)
        out[todo] = np.isfinite(d)
    return out


def fill_hulls(
    points: Float[np.ndarray, "M 3"], labels: Int[np.ndarray, " M"], core: Bool[np.ndarray, " M"],
    candidates: Bool[np.ndarray, " M"], *, max_growth: float = np.inf,
) -> Int[np.ndarray, " M"]:
    """Unlabelled `candidates` inside the convex hull of a cluster's `core` members join that cluster.

    A rigid part is solid: a Gaussian inside the hull of the part's opaque members (stage 2 passes
    ``core`` = members with opacity >= ``Stage2Config.hull_opacity``) moves with it, whether or not its
    own flow or photometric evidence said so (it may be hidden in every training frame, e.g. behind a
    drawer's front, and show in a novel view). Only labels -1 change; a candidate inside several hulls
    joins the cluster of its nearest core member. A cluster whose core has fewer than 4 points, or lies
    in a plane (no 3-D hull), fills nothing, and so does one whose hull holds more than ``max_growth`` times
    its own member count of unlabelled candidates: such a core spans static surfaces (a cluster spread over
    the scene, or two parts merged), not one solid part. Returns the new labels [M]."""
    from scipy.spatial import Delaunay, QhullError, cKDTree

    pts = _points(points, "points")
    lab = np.asarray(labels, np.int64).copy()
    core, cand = np.asarray(core, bool), np.asarray(candidates, bool)
    if pts.shape[1] != 3 or lab.shape != (len(pts),) or core.shape != lab.shape or cand.shape != lab.shape:
        raise ValueError(f"fill_hulls: points must be [M, 3] and labels, core, candidates [M]; got "
                         f"{pts.shape}, {lab.shape}, {core.shape}, {cand.shape}")
    todo = np.flatnonzero(cand & (lab < 0))
    best = np.full(len(todo), np.inf)
    new = np.full(len(todo), -1, np.int64)
    for k in range(int(lab.max(initial=-1)) + 1):
        mem = pts[(lab == k) & core]
        if len(mem) < 4 or len(todo) == 0:
            continue
        try:
            inside = Delaunay(mem).find_simplex(pts[todo]) >= 0
        except QhullError:  # coplanar or otherwise degenerate core: no volume to fill
            continue
        if np.sum(inside) > max_growth * np.sum(lab == k):
            continue
        d = np.where(inside, cKDTree(mem).query(pts[todo], k=1)[0], np.inf)
        take = d < best
        best[take], new[take] = d[take], k
    lab[todo] = np.where(new >= 0, new, lab[todo])
    return lab


def drop_isolated(
    points: Float[np.ndarray, "M 3"], labels: Int[np.ndarray, " M"], factor: float,
    alive: Bool[np.ndarray, " M"] | None = None,
) -> Int[np.ndarray, " M"]:
    """Members farther from every other member of their cluster than ``factor`` times the cluster's median
    spacing made unlabelled (-1).

    A part's Gaussians lie on its surfaces, each a spacing s_k (the median over cluster k of the distance to the
    nearest other member) from the next. The passes that grow a cluster (`localize_clusters`, the fills) join
    static Gaussians within a radius of any member, several spacings away from the part: the box under a lid,
    the frame around a door. Such a member has no other member near it. Only alive members (``alive`` [M],
    default all) count as neighbours and can be dropped; a cluster with fewer than 3 of them is left as it is.

    Args:
        points: [M, 3] centres (finite).
        labels: [M] int, -1 for unlabelled.
        factor: >= 1 (below 1 it would drop a regular grid whole); ``inf`` drops nothing.
        alive: [M] bool or None.

    Returns:
        [M] int labels (the same ids; no cluster is emptied: at least half its members are within its median
        spacing of another).
    """
    pts = _points(points, "drop_isolated")
    lab = np.asarray(labels, np.int64)
    if lab.shape != (len(pts),):
        raise ValueError(f"drop_isolated: labels must have shape [{len(pts)}], got {list(lab.shape)}")
    if not factor >= 1:  # NaN too
        raise ValueError(f"drop_isolated: factor must be >= 1, got {factor!r}")
    ok = np.ones(len(pts), bool) if alive is None else np.asarray(alive, bool)
    if ok.shape != (len(pts),):
        raise ValueError(f"drop_isolated: alive must have shape [{len(pts)}], got {list(ok.shape)}")
    out = lab.copy()
    if not np.isfinite(factor):
        return out
    from scipy.spatial import cKDTree

    for k in np.unique(lab[(lab >= 0) & ok]):
        idx = np.flatnonzero((lab == k) & ok)
        if len(idx) < 3:
            continue
        d, _ = cKDTree(pts[idx]).query(pts[idx], k=2)  # [m, 2]: itself, then its nearest other member
        nearest = d[:, 1]
        out[idx[nearest > factor * np.median(nearest)]] = -1
    return out


def refine_by_colour(
    points: Float[np.ndarray, "M 3"], colours: Float[np.ndarray, "M C"], labels: Int[np.ndarray, " M"],
    usable: Bool[np.ndarray, " M"] | None = None, *, radius: float, n_components: int = 4, smooth_k: int = 8,
    rounds: int = 2, min_separation: float = 0.65, max_change: float = 0.5, colour_floor: float = 1e-4,
    seed: int = 0,
) -> tuple[Int[np.ndarray, " M"], list[dict]]:
    """Each cluster's outline relabelled by colour, as GrabCut (Rother et al. 2004) does for an image mask.

    The passes that find a part from its motion leave its outline wrong both ways: a part barely moves near
    its hinge, so that strip stays static, and what lies around it (the box under a lid, the frame around a
    door) joins it. Where the part differs in colour from its surroundings, its colours tell them apart. For
    cluster k, over ``rounds`` rounds: the foreground is its usable members, the background the usable
    unlabelled Gaussians within ``radius`` of one of them; a Gaussian mixture of ``n_components`` full
    covariances, each at least ``colour_floor`` on its diagonal (variance: 1e-4 is 0.01 in RGB over [0, 1], so
    that no component fits a handful of odd colours), is fitted to the colours of each (scikit-learn, seeded by
    ``seed``); each of them gets
    L = log p_fg(colour) - log p_bg(colour) (clipped to [-10, 10]), averaged half-and-half with the mean L of its
    ``smooth_k`` nearest (by centre, itself included) among them (0: no smoothing); then members with
    L <= 0 become unlabelled and background Gaussians with L > 0 join k. Clusters are taken in order, so a
    Gaussian near two joins the first.

    A cluster's refinement stops before a round, which is not applied (its entry in the report says why), when
    the cluster or its background has fewer than ``max(20, 5 n_components)`` Gaussians; when the two mixtures
    do not tell its own two sets apart (balanced accuracy of L > 0 on them below ``min_separation``: a part
    coloured like its surroundings); or when the round would remove or add more than ``max_change`` times its
    member count. Stopped before its first round, the cluster is left as it was.

    Args:
        points: [M, 3] centres (finite).
        colours: [M, C] colours (finite; e.g. RGB from the SH DC term).
        labels: [M] int, -1 unlabelled.
        usable: [M] bool (default all): the Gaussians whose colour counts (alive, not faint); the others keep
            their labels and are in neither set.
        radius: > 0, same units as ``points``.

    Returns:
        (labels [M], report: per cluster {"joined", "left", "separation", "skipped"} with ``skipped`` None or
        a reason).
    """
    from scipy.spatial import cKDTree
    from sklearn.mixture import GaussianMixture

    pts = _points(points, "refine_by_colour")
    col = np.asarray(colours, np.float64)
    lab = np.asarray(labels, np.int64)
    m = len(pts)
    if col.ndim != 2 or col.shape[0] != m or not np.all(np.isfinite(col)):
        raise ValueError(f"refine_by_colour: colours must be finite with shape [{m}, C], got {list(col.shape)}")
    if lab.shape != (m,):
        raise ValueError(f"refine_by_colour: labels must have shape [{m}], got {list(lab.shape)}")
    ok = np.ones(m, bool) if usable is None else np.asarray(usable, bool)
    if ok.shape != (m,):
        raise ValueError(f"refine_by_colour: usable must have shape [{m}], got {list(ok.shape)}")
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"refine_by_colour: radius must be finite and > 0, got {radius!r}")
    if n_components < 1 or smooth_k < 0 or rounds < 1:
        raise ValueError(f"refine_by_colour: need n_components >= 1, smooth_k >= 0 and rounds >= 1, got "
                         f"{n_components!r}, {smooth_k!r}, {rounds!r}")
    if not (0 <= min_separation <= 1 and max_change > 0 and colour_floor > 0):  # NaN too
        raise ValueError(f"refine_by_colour: need 0 <= min_separation <= 1, max_change > 0 and colour_floor > 0, "
                         f"got {min_separation!r}, {max_change!r} and {colour_floor!r}")
    out = lab.copy()
    min_size = max(20, 5 * n_components)
    report = []
    for k in range(int(lab.max(initial=-1)) + 1):
        rep = {"joined": 0, "left": 0, "separation": None, "skipped": None}
        report.append(rep)
        for _ in range(rounds):
            fg = (out == k) & ok
            if fg.sum() < min_size:
                rep["skipped"] = f"{int(fg.sum())} usable members (fewer than {min_size})"
                break
            d, _ = cKDTree(pts[fg]).query(pts, k=1)  # [M]
            bg = (out == -1) & ok & (d <= radius)
            if bg.sum() < min_size:
                rep["skipped"] = (f"{int(bg.sum())} usable unlabelled Gaussians within {radius:g} "
                                  f"(fewer than {min_size})")
                break
            gm_fg = GaussianMixture(n_components, reg_covar=colour_floor, random_state=seed).fit(col[fg])
            gm_bg = GaussianMixture(n_components, reg_covar=colour_floor, random_state=seed).fit(col[bg])
            cand = np.flatnonzero(fg | bg)  # [J]
            score = np.clip(gm_fg.score_samples(col[cand]) - gm_bg.score_samples(col[cand]), -10.0, 10.0)  # [J]
            is_fg = fg[cand]
            sep = 0.5 * (np.mean(score[is_fg] > 0) + np.mean(score[~is_fg] <= 0))
            rep["separation"] = float(sep)
            if sep < min_separation:
                rep["skipped"] = f"colours apart by {sep:.2f} (below {min_separation:g})"
                break
            if smooth_k > 0:
                _, j = cKDTree(pts[cand]).query(pts[cand], k=min(smooth_k, len(cand)))
                score = 0.5 * score + 0.5 * score[j.reshape(len(cand), -1)].mean(axis=1)
            leave, join = cand[is_fg & (score <= 0)], cand[~is_fg & (score > 0)]
            if max(len(leave), len(join)) > max_change * fg.sum():
                rep["skipped"] = (f"would change {max(len(leave), len(join))} of {int(fg.sum())} members "
                                  f"(more than {max_change:g}x)")
                break
            out[leave], out[join] = -1, k
        rep["joined"] = int(np.sum((out == k) & (lab != k)))
        rep["left"] = int(np.sum((out != k) & (lab == k)))
    return out, report


def hinge_axes(
    poses: Float[np.ndarray, "K T 4 4"], *, min_deg: float = 20.0
) -> tuple[Float[np.ndarray, "K 3"], Float[np.ndarray, "K 3"], Float[np.ndarray, " K"]]:
    """The hinge of each object's rigid motion: (axes [K, 3] unit, pivots [K, 3], angles [K] degrees).

    ``poses`` [K, T, 4, 4] map the reference to each frame, x -> R x + t. An object's largest rotation
    angle over the frames is ``angles[k]``; when it is below ``min_deg`` (a slide, or no motion) its axis
    and pivot are NaN. Otherwise, over the frames that turn by at least ``min_deg``: the axis is the top
    eigenvector of sum_j (R_j + R_j^T - (tr R_j - 1) I) = sum_j 2 (1 - cos theta_j) a_j a_j^T (each frame's
    axis, weighted by how far it turns; no sign to pick), and the pivot is the least-squares point p with
    (I - R_j) p = t_j - (t_j . a) a (a turn about the line through p, plus any slide along it: a screw),
    the one nearest the origin (the line's points differ along a only). Non-finite poses are refused."""
    P = np.asarray(poses, np.float64)
    if P.ndim != 4 or P.shape[2:] != (4, 4):
        raise ValueError(f"hinge_axes: poses must be [K, T, 4, 4], got {list(P.shape)}")
    if not np.all(np.isfinite(P)):
        raise ValueError("hinge_axes: poses contain non-finite values")
    if not np.isfinite(min_deg) or min_deg <= 0:
        raise ValueError(f"hinge_axes: min_deg must be finite and > 0, got {min_deg!r}")
    k_num = P.shape[0]
    axes, pivots = np.full((k_num, 3), np.nan), np.full((k_num, 3), np.nan)
    rot, tr = P[..., :3, :3], P[..., :3, 3]  # [K, T, 3, 3], [K, T, 3]
    cos = np.clip((np.trace(rot, axis1=2, axis2=3) - 1.0) / 2.0, -1.0, 1.0)  # [K, T]
    deg = np.degrees(np.arccos(cos))
    angles = deg.max(axis=1, initial=0.0)
    eye = np.eye(3)
    for k in range(k_num):
        use = deg[k] >= min_deg
        if not use.any():
            continue
        R, t = rot[k, use], tr[k, use]  # [J, 3, 3], [J, 3]
        m = (R + np.swapaxes(R, 1, 2) - (np.trace(R, axis1=1, axis2=2) - 1.0)[:, None, None] * eye).sum(0)
        a = np.linalg.eigh(m)[1][:, -1]  # [3] unit
        rhs = t - (t @ a)[:, None] * a  # [J, 3]
        p = np.linalg.lstsq((eye - R).reshape(-1, 3), rhs.reshape(-1), rcond=None)[0]
        axes[k], pivots[k] = a, p - (p @ a) * a
    return axes, pivots, angles


def fill_hinges(
    points: Float[np.ndarray, "M 3"], labels: Int[np.ndarray, " M"], core: Bool[np.ndarray, " M"],
    candidates: Bool[np.ndarray, " M"], axes: Float[np.ndarray, "K 3"], pivots: Float[np.ndarray, "K 3"], *,
    radius: float = 0.15, reach: float = 0.15, max_growth: float = np.inf,
) -> Int[np.ndarray, " M"]:
    """Unlabelled `candidates` along a turning cluster's hinge join that cluster.

    A part that turns about an axis barely moves near it: neither its flow nor its photometric evidence
    separates its hinge side from the static frame it hangs on (on the default synthetic scene the
    door's strip within 0.03 scene units of its hinge was two-thirds unlabelled), and in a novel state that
    strip stays behind, drawn static. For cluster k with a finite axis (unit ``axes[k]`` through
    ``pivots[k]``, e.g. from `hinge_axes`), let r_min and r_max be its ``core`` members' smallest and largest
    distances from the axis. When r_min <= ``reach`` * r_max (the axis runs along the part, as a hinge
    does; a fit whose axis passes away from the part is left alone), the candidates within ``radius`` *
    r_max of the axis and between the core's two ends along it join k. A candidate in several such
    cylinders joins the cluster whose axis is nearest; a cluster whose cylinder holds more than
    ``max_growth`` times its member count of candidates fills nothing (as `fill_hulls`). Only labels -1
    change. Returns the new labels [M]."""
    pts = _points(points, "points")
    lab = np.asarray(labels, np.int64).copy()
    core, cand = np.asarray(core, bool), np.asarray(candidates, bool)
    ax, pv = np.asarray(axes, np.float64), np.asarray(pivots, np.float64)
    k_num = int(lab.max(initial=-1)) + 1
    if pts.shape[1] != 3 or lab.shape != (len(pts),) or core.shape != lab.shape or cand.shape != lab.shape:
        raise ValueError(f"fill_hinges: points must be [M, 3] and labels, core, candidates [M]; got "
                         f"{pts.shape}, {lab.shape}, {core.shape}, {cand.shape}")
    if ax.shape != (k_num, 3) or pv.shape != (k_num, 3):
        raise ValueError(f"fill_hinges: axes and pivots must be [K, 3] = [{k_num}, 3] (K clusters in labels), got "
                         f"{list(ax.shape)} and {list(pv.shape)}")
    if not (np.isfinite(radius) and radius >= 0 and np.isfinite(reach) and reach >= 0):
        raise ValueError(f"fill_hinges: radius and reach must be finite and >= 0, got {radius!r} and {reach!r}")
    todo = np.flatnonzero(cand & (lab < 0))
    best = np.full(len(todo), np.inf)
    new = np.full(len(todo), -1, np.int64)
    for k in range(k_num):
        mem = pts[(lab == k) & core]
        if len(mem) == 0 or len(todo) == 0 or not (np.all(np.isfinite(ax[k])) and np.all(np.isfinite(pv[k]))):
            continue
        norm = np.linalg.norm(ax[k])
        if not norm > 0:
            continue
        a = ax[k] / norm

        def along_and_off(x):
            d = x - pv[k]
            s = d @ a
            return s, np.linalg.norm(d - s[:, None] * a, axis=1)

        s_mem, r_mem = along_and_off(mem)
        if r_mem.min() > reach * r_mem.max():  # the axis does not run along the part
            continue
        s, r = along_and_off(pts[todo])
        inside = (r <= radius * r_mem.max()) & (s >= s_mem.min()) & (s <= s_mem.max())
        if np.sum(inside) > max_growth * np.sum(lab == k):
            continue
        d = np.where(inside, r, np.inf)
        take = d < best
        best[take], new[take] = d[take], k
    lab[todo] = np.where(new >= 0, new, lab[todo])
    return lab


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
    pts = _points(points, "points")
    lab = np.asarray(labels, np.int64).copy()
    mv = np.asarray(moving_t, np.float64)
    tt = np.asarray(total_t, np.float64)
    if lab.shape != (len(pts),) or mv.ndim != 2 or mv.shape[1] != len(pts) or tt.shape != mv.shape:
        raise ValueError(f"{name}: labels [{len(pts)}] and moving_t, total_t [T, {len(pts)}] expected, got "
                         f"{list(lab.shape)}, {list(mv.shape)}, {list(tt.shape)}")
    return pts, lab, mv, tt


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
    from scipy.spatial import cKDTree

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
    from scipy.spatial import cKDTree

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

    The global score sum_t moving_t / sum_t total_t of `fgjax.pipeline.discover` is diluted by every
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
            (`fgjax.pipeline.discover.Scores.moving_t` / ``total_t``).
        radius: search radius around a cluster's members (same units as `points`).
        threshold: the cut of s_ik in [0, 1].
        candidates: [M] bool, the points allowed to join (None: all).
        active: a frame is in F_k when m_k(t) >= active * max_t m_k(t).
        eps: pixel-equivalents added to the denominator (points hardly seen in F_k score low).

    Returns:
        `Localized`.
    """
    pts = _points(points, "points")
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
    from scipy.spatial import cKDTree

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


def cluster_report(labels: Int[np.ndarray, " M"]) -> ClusterReport:
    """Counts of a label array (-1 = noise)."""
    lab = np.asarray(labels).astype(np.int64).ravel()
    sizes = np.bincount(lab[lab >= 0]) if np.any(lab >= 0) else np.zeros(0, np.int64)
    sizes = sizes[sizes > 0]
    return ClusterReport(n_points=int(lab.size), n_clusters=int(len(sizes)),
                         sizes=tuple(int(s) for s in sorted(sizes, reverse=True)), n_noise=int(np.sum(lab < 0)))


# ============================================================================ trajectories


def trajectories(
    centres_over_time: Float[np.ndarray, "T N 3"], labels: Int[np.ndarray, " N"]
) -> Float[np.ndarray, "K T 3"]:
    """ς(t, k): the mean deformed centre of each cluster's Gaussians per frame (step 6).

    Args:
        centres_over_time: [T, N, 3] deformed centres of the N clustered Gaussians per frame.
        labels: [N] cluster labels 0..K-1, -1 = noise (ignored).

    Returns:
        [K, T, 3] with K = max(labels) + 1 (0 when every label is -1).

    Raises:
        ValueError: bad shapes, or a label in 0..K-1 with no member (labels must be compact, as
            `cluster_dynamic` returns them).
    """
    c = np.asarray(centres_over_time, dtype=np.float64)
    lab = np.asarray(labels).astype(np.int64)
    if c.ndim != 3 or c.shape[2] != 3:
        raise ValueError(f"trajectories: centres_over_time must have shape [T, N, 3], got {c.shape}")
    if lab.shape != (c.shape[1],):
        raise ValueError(f"trajectories: labels must have shape [N]=[{c.shape[1]}], got {lab.shape}")
    k = int(lab.max()) + 1 if lab.size and lab.max() >= 0 else 0
    counts = np.bincount(lab[lab >= 0], minlength=k)
    if np.any(counts == 0):
        raise ValueError(f"trajectories: labels are not compact, no member for cluster(s) "
                         f"{np.flatnonzero(counts == 0).tolist()}")
    out = np.zeros((k, c.shape[0], 3))
    for j in range(k):
        out[j] = c[:, lab == j].mean(axis=1)
    return out


class Snap(NamedTuple):
    """Result of `snap_to_trajectory`.

    t: continuous sample index in [0, T-1] (i + u between samples i and i + 1), or the time
        interpolated the same way when ``times`` was given.
    point: [3] the snapped point on the polyline ς(·, k); the control vector to feed the network is
        ``point - traj[0]``.
    """

    t: float
    point: Float[np.ndarray, 3]


def snap_to_trajectory(
    traj: Float[np.ndarray, "T 3"],
    vector: Float[np.ndarray, 3],
    origin: Float[np.ndarray, 3] | None = None,
    *,
    times: Float[np.ndarray, " T"] | None = None,
) -> Snap:
    """Snap a user's displacement to the nearest point of a stored trajectory (step 8).

    The user's vector is a displacement from the start, v = ς(t, k) - ς(0, k), so the target
    point is p = origin + vector (origin defaults to traj[0]). The result is the point of the
    polyline traj[0] - traj[1] - ... - traj[T-1] closest to p: for each segment the projection
    u = clip(<p - a, b - a> / |b - a|^2, 0, 1); samples themselves are candidates too and win
    ties, so a vector that lands on a sample returns that sample exactly (and its integer
    index). Among equally near candidates the earliest wins (an object that opens and then
    closes passes each point twice; the opening is returned).

    Args:
        traj: [T, 3] trajectory samples (T >= 1).
        vector: [3] displacement from `origin`.
        origin: [3] the reference point (default traj[0]).
        times: [T] optional non-decreasing sample times; t is then interpolated in them.

    Returns:
        `Snap(t, point)`.
    """
    tr = np.asarray(traj, dtype=np.float64)
    if tr.ndim != 2 or tr.shape[0] < 1 or tr.shape[1] != 3:
        raise ValueError(f"snap_to_trajectory: traj must have shape [T, 3] with T >= 1, got {tr.shape}")
    v = np.asarray(vector, dtype=np.float64)
    if v.shape != (3,):
        raise ValueError(f"snap_to_trajectory: vector must have shape [3], got {v.shape}")
    o = tr[0] if origin is None else np.asarray(origin, dtype=np.float64)
    if o.shape != (3,):
        raise ValueError(f"snap_to_trajectory: origin must have shape [3], got {o.shape}")
    if times is not None:
        times = np.asarray(times, dtype=np.float64)
        if times.shape != (len(tr),):
            raise ValueError(f"snap_to_trajectory: times must have shape [T]=[{len(tr)}], got {times.shape}")
    if not (np.all(np.isfinite(tr)) and np.all(np.isfinite(v)) and np.all(np.isfinite(o))):
        raise ValueError("snap_to_trajectory: non-finite input")
    p = o + v
    dv = np.linalg.norm(tr - p, axis=1)  # [T] distances to the samples
    iv = int(np.argmin(dv))
    best_t, best_pt, best_d = float(iv), tr[iv].copy(), float(dv[iv])
    if len(tr) > 1:
        a, b = tr[:-1], tr[1:]
        ab = b - a  # [T-1, 3]
        len2 = np.sum(ab * ab, axis=1)
        u = np.where(len2 > 0, np.sum((p - a) * ab, axis=1) / np.where(len2 > 0, len2, 1.0), 0.0)
        u = np.clip(u, 0.0, 1.0)
        q = a + u[:, None] * ab  # [T-1, 3]
        ds = np.linalg.norm(q - p, axis=1)
        js = int(np.argmin(ds))
        # a segment wins only if strictly nearer (beyond rounding), and only inside it
        tol = 1e-12 * max(1.0, float(np.abs(tr).max()), float(np.abs(p).max()))
        if ds[js] < best_d - tol and 0.0 < u[js] < 1.0:
            best_t, best_pt = js + float(u[js]), q[js]
    if times is not None:
        i = int(np.floor(best_t))
        frac = best_t - i
        best_t = float(times[i]) if frac == 0.0 else float(times[i] + frac * (times[i + 1] - times[i]))
    return Snap(t=float(best_t), point=best_pt)
