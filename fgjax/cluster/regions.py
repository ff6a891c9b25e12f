"""Spatial label passes: points near a cluster's swept volume, convex-hull fill, isolated-member removal,
colour refinement, hinge axes and hinge fill."""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int
from scipy.spatial import Delaunay, QhullError, cKDTree
from sklearn.mixture import GaussianMixture

from fgjax.cluster.dbscan import as_points


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
    pts = as_points(points, "points")
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
    pts = as_points(points, "drop_isolated")
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
    pts = as_points(points, "refine_by_colour")
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
    pts = as_points(points, "points")
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
