"""Selection of the dynamic set, DBSCAN/HDBSCAN clustering, cluster reports, trajectories and snapping
(DESIGN.md section 1, steps 5, 6 and 8; label conventions in `fgjax.cluster`)."""

from __future__ import annotations

import dataclasses
from typing import Literal, NamedTuple

import numpy as np
from jaxtyping import Bool, Float, Int
from sklearn.cluster import DBSCAN, HDBSCAN
from sklearn.neighbors import NearestNeighbors

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
        scores: [N] per-Gaussian scores (e.g. `fgjax.method.discover.accumulate_scores`).
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


def as_points(points, name: str) -> np.ndarray:
    """`points` as float64 [M, D], checked finite (ValueError naming `name` otherwise)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] < 1:
        raise ValueError(f"{name}: points must have shape [M, D], got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: points contain non-finite values")
    return p


def k_distances(points: Float[np.ndarray, "M D"], k: int) -> Float[np.ndarray, " M"]:
    """Sorted (ascending) distance of every point to its k-th nearest neighbour, itself excluded."""
    p = as_points(points, "k_distances")
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
    p = as_points(points, "cluster_dynamic")
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
        if auto_eps:
            e = _auto_eps(p, max(min_samples - 1, 1))
        else:
            e = float(eps)
        if not e > 0:
            raise ValueError(f"cluster_dynamic: eps must be > 0, got {e}")
        raw = DBSCAN(eps=e, min_samples=min_samples).fit_predict(p)
    else:
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
