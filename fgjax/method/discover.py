"""Discovery of dynamic Gaussians from flow (DESIGN.md section 1, step 5), as pure functions on arrays.

For each training pair (t-1, t):

1. residual flow r = u - u_cam: optical flow minus the flow the camera alone would cause
   (`camera_flow_from_depth`: exact reprojection or the first-order motion field, from the rendered
   depth of frame t-1 and the two poses; with the depth trusted only within a relative tolerance, u_cam is the
   point nearest u on the image of that depth interval, `nearest_on_segment`);
2. binarise |r| per frame (`binarize`: a fixed threshold in pixels or Otsu's, with a floor, optionally raised
   to the pair's noise level, `noise_threshold`);
3. back-project the mask through the rasterizer: w_i(m) = sum_p m_p T_ip alpha_ip
   (`fgjax.render.api.gaussian_weights`) with the Gaussians deformed to time t-1 and camera t-1.

Scores are accumulated over pairs and normalised by each Gaussian's total contribution:

    score_i = sum_t w_i(mask_t) / (sum_t w_i(1) + eps)

i.e. the fraction of everything Gaussian i paints (over all frames) that lies on moving pixels. The
plain sum sum_t w_i(mask_t) would favour big, opaque splats that cover many pixels (a background
splat overlapping a moving edge collects weight from every mask pixel it touches); the ratio is in
[0, 1] whatever the Gaussian's size, and `eps` (in pixel-equivalents: one fully opaque, unoccluded
pixel contributes 1) damps Gaussians that are barely ever seen. `select_dynamic` then thresholds the
scores (Otsu by default), and `fgjax.cluster.cluster_dynamic` groups the selected canonical centres.

With a reference frame r (`Reference`: its optical-flow tracks through the video, its Gaussians and camera), each
moving pixel of frame t-1 that a track of r reaches is back-projected at frame r instead, onto the Gaussians that
paint that track's pixel there (`carry_masks`), and the others as above; both sums add the two parts:
score_i = sum_t [w_i^r(c'_t) + w_i^t(mask_t (1 - k_t))] / (sum_t [w_i^r(s_t) + w_i^t(1 - k_t)] + eps), with
c'_t, s_t the carried mask and the tracked pixels of r, and k_t the pixels of frame t-1 the tracks cover.

Optionally each pixel p of frame t carries a confidence c_tp in [0, 1] (`agreement`: how well the model's rendering
matches the image there), and both sums weight p by it:
score_i = sum_t w_i(c_t mask_t) / (sum_t w_i(c_t) + eps).

Nothing here knows of stage-1 models: `discover` takes the deformed Gaussians per pair as arrays.
"""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, Float32
from scipy import ndimage

from fgjax import cluster
from fgjax import flow as fl
from fgjax.render.api import gaussian_weights

__all__ = [
    "residual_flow",
    "binarize",
    "noise_threshold",
    "camera_flow_from_depth",
    "nearest_on_segment",
    "Scores",
    "agreement",
    "accumulate_scores",
    "carry_masks",
    "windowed_score",
    "Reference",
    "Discovery",
    "discover",
]


def residual_flow(
    flow: Float[np.ndarray, "*T H W 2"], camera_flow: Float[np.ndarray, "*T H W 2"]
) -> Float[np.ndarray, "*T H W 2"]:
    """Object-induced flow r = u - u_cam (pixels per frame interval), same shape as the inputs."""
    f = np.asarray(flow, dtype=np.float32)
    c = np.asarray(camera_flow, dtype=np.float32)
    if f.shape != c.shape or f.ndim < 3 or f.shape[-1] != 2:
        raise ValueError(f"residual_flow: flow and camera_flow must both have shape [..., H, W, 2], "
                         f"got {f.shape} and {c.shape}")
    return f - c


def binarize(
    residual: Float[np.ndarray, "*T H W 2"],
    threshold_px: float | Float[np.ndarray, "*T H W"] | Literal["otsu"] | None = "otsu",
    *,
    valid: Bool[np.ndarray, "*T H W"] | None = None,
    min_px: float = 0.5,
    noise_sigmas: float = 0.0,
) -> Bool[np.ndarray, "*T H W"]:
    """Moving-pixel masks: |r| above a threshold, per frame.

    The threshold is `threshold_px` pixels (one number, or one per pixel), or (``"otsu"`` / None)
    Otsu's threshold of the frame's valid magnitudes, never below `min_px`: a frame where nothing
    moves has unimodal noise that Otsu would still cut in two, and the floor keeps it empty.

    With `noise_sigmas` k > 0 each frame's threshold is raised, where lower, to the noise level of its
    residual: median(|r|) + k sigma, sigma = 1.4826 MAD(|r|) (the median absolute deviation, scaled to a
    Gaussian's standard deviation), over the frame's valid pixels. Both statistics are those of the static
    pixels while these are the majority of the valid ones (the assumption the camera correction makes too,
    `fgjax.method.camera.camera_correction`), so a pair whose camera flow is off by a pixel everywhere (a
    hand-held camera, a depth error) is cut above that error instead of being marked moving, and a pair with
    sub-pixel noise keeps `threshold_px`. docs/benchmarks.md, "Discovery's threshold from the residual's
    noise".

    Args:
        residual: [H, W, 2] or [T, H, W, 2] residual flow.
        threshold_px: pixels (a number, or an array of the masks' shape), or ``"otsu"`` (None
            means ``"otsu"``).
        valid: [H, W] or [T, H, W] pixels where the residual is defined (others are False);
            non-finite residuals are invalid too.
        min_px: floor of the Otsu threshold (pixels).
        noise_sigmas: k above (>= 0; 0: the threshold is not raised).

    Returns:
        bool masks, [H, W] or [T, H, W].
    """
    if not (np.isfinite(noise_sigmas) and noise_sigmas >= 0):
        raise ValueError(f"binarize: noise_sigmas must be a finite number >= 0, got {noise_sigmas}")
    r = np.asarray(residual, dtype=np.float64)
    if r.ndim not in (3, 4) or r.shape[-1] != 2:
        raise ValueError(f"binarize: residual must have shape [H, W, 2] or [T, H, W, 2], got {r.shape}")
    single = r.ndim == 3
    r = r[None] if single else r
    mag = np.linalg.norm(r, axis=-1)  # [T, H, W]
    ok = np.isfinite(mag)
    if valid is not None:
        v = np.asarray(valid, dtype=bool)
        v = v[None] if single else v
        if v.shape != mag.shape:
            raise ValueError(f"binarize: valid must have shape {mag.shape[int(single):]}, got {np.shape(valid)}")
        ok &= v
    if threshold_px is None:
        threshold_px = "otsu"
    if not isinstance(threshold_px, str) and np.ndim(threshold_px) > 0:
        per_px = np.asarray(threshold_px, np.float64)
        if per_px.shape != mag.shape[int(single):]:
            raise ValueError(f"binarize: threshold_px must be a number or have shape {mag.shape[int(single):]}, "
                             f"got {per_px.shape}")
        threshold_px = per_px[None] if single else per_px
    out = np.zeros(mag.shape, bool)
    for t in range(len(mag)):
        if isinstance(threshold_px, str):
            if threshold_px != "otsu":
                raise ValueError(f"binarize: threshold_px must be a number, 'otsu' or None, got {threshold_px!r}")
            thr = max(cluster.otsu_threshold(mag[t][ok[t]]), float(min_px))
        else:
            thr = threshold_px[t] if np.ndim(threshold_px) else float(threshold_px)
        if noise_sigmas > 0 and ok[t].any():
            thr = np.maximum(thr, noise_threshold(mag[t][ok[t]], noise_sigmas))
        out[t] = ok[t] & (np.where(ok[t], mag[t], 0.0) > thr)
    return out[0] if single else out


def noise_threshold(magnitudes: Float[np.ndarray, "..."], sigmas: float) -> float:
    """median(m) + `sigmas` * 1.4826 * median(|m - median(m)|) of the finite values `magnitudes` (any shape):
    a robust "k standard deviations above the typical value" (the MAD's factor makes sigma a normal
    distribution's standard deviation). +inf for no finite value. See `binarize`."""
    m = np.asarray(magnitudes, np.float64).ravel()
    m = m[np.isfinite(m)]
    if m.size == 0:
        return float("inf")
    med = float(np.median(m))
    return med + float(sigmas) * 1.4826 * float(np.median(np.abs(m - med)))


def nearest_on_segment(
    flow: Float[np.ndarray, "*B 2"], near: Float[np.ndarray, "*B 2"], far: Float[np.ndarray, "*B 2"]
) -> Float[np.ndarray, "*B 2"]:
    """The point of each segment [far, near] closest to `flow` (all [..., 2]): far + clip(s, 0, 1) (near - far) with
    s = <flow - far, near - far> / |near - far|^2 (a degenerate segment gives `far`).

    A static pixel's camera flow is one point of its epipolar line per depth; with the depth known only within a
    relative tolerance delta, it is anywhere on the segment between the camera flows at depths Z / (1 + delta)
    (``near``) and Z (1 + delta) (``far``), the image of that depth interval. ``flow`` minus this point is the
    part of the observed flow that no depth in the interval explains (`fgjax.method.stage2.discover_run`,
    ``stage2.depth_tolerance``): the residual of the paper's step 4 at delta = 0, and the distance from the
    epipolar line as delta grows.
    """
    f = np.asarray(flow, np.float64)
    a = np.asarray(far, np.float64)
    b = np.asarray(near, np.float64)
    if not (f.shape == a.shape == b.shape and f.shape[-1:] == (2,)):
        raise ValueError(f"nearest_on_segment: flow, near and far must have one shape [..., 2]; got {f.shape}, "
                         f"{b.shape}, {a.shape}")
    d = b - a
    dd = np.sum(d * d, -1, keepdims=True)
    s = np.where(dd > 1e-12, np.sum((f - a) * d, -1, keepdims=True) / np.where(dd > 1e-12, dd, 1.0), 0.0)
    return a + np.clip(np.nan_to_num(s), 0.0, 1.0) * d


def camera_flow_from_depth(
    depth: Float[np.ndarray, "H W"],
    K: Float[np.ndarray, "3 3"],
    c2w0: Float[np.ndarray, "4 4"],
    c2w1: Float[np.ndarray, "4 4"],
    method: Literal["reprojection", "motion_field"] = "reprojection",
) -> tuple[Float[np.ndarray, "H W 2"], Bool[np.ndarray, "H W"]]:
    """Camera flow u_cam of frame t-1 (step 3) from its depth and the two OpenCV camera-to-world poses.

    ``"reprojection"``: exact, `fgjax.flow.reprojection_flow`. ``"motion_field"``: the first-order
    u = A v / Z + B ω with (v, ω) = `fgjax.flow.camera_velocity` (dt = 1 frame). Returns (flow,
    valid) as numpy; valid is False where the depth is not positive (and, for reprojection, where
    the point falls behind camera t).
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"camera_flow_from_depth: depth must have shape [H, W], got {depth.shape}")
    if method == "reprojection":
        f, v = fl.reprojection_flow(depth, K, c2w0, c2w1)
        return np.asarray(f, np.float32), np.asarray(v)
    if method == "motion_field":
        vel, omega = fl.camera_velocity(c2w0, c2w1)
        xy = fl.pixel_centers(*depth.shape)
        f = fl.motion_field(xy, depth, K, vel, omega)
        valid = np.isfinite(depth) & (depth > 0)
        return np.where(valid[..., None], np.asarray(f, np.float32), 0.0).astype(np.float32), valid
    raise ValueError(f"camera_flow_from_depth: method must be 'reprojection' or 'motion_field', got {method!r}")


@functools.partial(jax.jit, static_argnames=("width", "height", "capacity"))
def _pair_weights(means, quats, scales, opacities, viewmat, K, mask, confidence, *, width, height, capacity):
    """(w_i(mask * confidence), w_i(confidence)) for one frame: two backward passes of the rasterizer."""
    kw = {} if capacity is None else {"capacity": capacity}
    moving = gaussian_weights(means, quats, scales, opacities, viewmat, K, width, height, mask * confidence, **kw)
    total = gaussian_weights(means, quats, scales, opacities, viewmat, K, width, height, confidence, **kw)
    return moving, total


class Scores(NamedTuple):
    """Per-Gaussian discovery scores.

    score: [N] sum_t w_i(mask_t) / (sum_t w_i(1) + eps), in [0, 1).
    moving: [N] sum_t w_i(mask_t) (pixel-equivalents on moving pixels).
    total: [N] sum_t w_i(1) (pixel-equivalents painted in all frames): a visibility measure.
    moving_t, total_t: [T, N] float32 per-frame terms (only with ``per_frame=True``, else None).
    """

    score: Float[np.ndarray, " N"]
    moving: Float[np.ndarray, " N"]
    total: Float[np.ndarray, " N"]
    moving_t: Float[np.ndarray, "T N"] | None = None
    total_t: Float[np.ndarray, "T N"] | None = None


def agreement(
    rendered: Float[np.ndarray, "*T H W C"], observed: Float[np.ndarray, "*T H W C"], sigma: float
) -> Float[np.ndarray, "*T H W"]:
    """Per-pixel agreement of a rendering with the image, c = exp(-e^2 / (2 sigma^2)) in (0, 1], where e is the
    root-mean-square colour difference over the C channels (colours in [0, 1]).

    Discovery back-projects a moving pixel onto the Gaussians the model paints there. Where the model does not yet
    move a part, the part's moved pixels are painted by what it covered or uncovered (the static scene, or the part
    at rest), and those Gaussians would collect the part's motion; the model then renders those pixels wrongly, so
    weighting each pixel by c gives the motion to the Gaussians that paint it correctly (`accumulate_scores`).
    ``sigma`` is the colour error (same units) at which a pixel keeps exp(-1/2) = 0.61 of its weight.
    """
    r = np.asarray(rendered, np.float32)
    o = np.asarray(observed, np.float32)
    if r.shape != o.shape or r.ndim < 3:
        raise ValueError(f"agreement: rendered and observed must both have shape [..., H, W, C], got {r.shape} and "
                         f"{o.shape}")
    if not sigma > 0:
        raise ValueError(f"agreement: sigma must be > 0, got {sigma}")
    e2 = np.mean(np.square(np.nan_to_num(r - o, nan=np.inf, posinf=np.inf, neginf=np.inf)), axis=-1)
    return np.exp(-0.5 * e2 / float(sigma) ** 2).astype(np.float32)


def _per_frame(x, t: int, tail: tuple[int, ...], name: str) -> np.ndarray:
    """Broadcast a per-frame array [T, *tail] or a shared one [*tail] to [T, *tail]."""
    a = np.asarray(x)
    if a.shape == tail:
        return np.broadcast_to(a, (t, *tail))
    if a.shape != (t, *tail):
        raise ValueError(f"{name} must have shape {list(tail)} or [T={t}, {', '.join(map(str, tail))}], "
                         f"got {list(a.shape)}")
    return a


def accumulate_scores(
    means: Float[np.ndarray, "T N 3"],
    quats: Float[np.ndarray, "T N 4"],
    scales: Float[np.ndarray, "T N 3"],
    opacities: Float[np.ndarray, "T N"],
    viewmats: Float[np.ndarray, "T 4 4"],
    K: Float[np.ndarray, "T 3 3"],
    masks: Bool[np.ndarray, "T H W"],
    *,
    eps: float = 0.1,
    capacity: int | None = None,
    per_frame: bool = False,
    confidence: Float[np.ndarray, "T H W"] | None = None,
) -> Scores:
    """Back-project moving-pixel masks onto Gaussians and accumulate over frames (step 5).

    score_i = sum_t w_i(c_t mask_t) / (sum_t w_i(c_t) + eps), w_i(m) = sum_p m_p T_ip alpha_ip
    (`fgjax.render.api.gaussian_weights`, the rasterizer's own compositing weights); see the module
    docstring for why the ratio. Frame t here is the first frame of pair t: the Gaussians are those
    deformed to time t-1 and the camera that of frame t-1. The per-pixel confidence c_t in [0, 1]
    (default 1) says how far the Gaussians that paint a pixel are the ones the image shows there
    (`agreement`): a pixel the model renders wrongly gives its weight to no Gaussian.

    Args:
        means, quats, scales, opacities: activated Gaussians per frame, [T, N, ...] (or shared
            across frames without the T axis: scales [N, 3] and opacities [N] usually are).
        viewmats: [T, 4, 4] OpenCV world-to-camera.
        K: [3, 3] or [T, 3, 3].
        masks: [T, H, W] moving pixels (bool or soft weights in [0, 1]).
        eps: pixel-equivalents added to the denominator.
        capacity: the rasterizer's intersection capacity (static; None: its default). One
            compile serves every frame when it is fixed.
        per_frame: also return the per-frame terms (memory T x N).
        confidence: [T, H, W] per-pixel weights in [0, 1] (None: all 1).

    Returns:
        `Scores` (numpy float64).
    """
    m = np.asarray(masks)
    if m.ndim != 3:
        raise ValueError(f"accumulate_scores: masks must have shape [T, H, W], got {list(m.shape)}")
    t, h, w = m.shape
    if confidence is None:
        conf = np.ones((t, h, w), np.float32)
    else:
        conf = np.asarray(confidence, np.float32)
        if conf.shape != m.shape:
            raise ValueError(f"accumulate_scores: confidence must have the masks' shape {list(m.shape)}, "
                             f"got {list(conf.shape)}")
        if not np.all((conf >= 0) & (conf <= 1)):
            raise ValueError("accumulate_scores: confidence must lie in [0, 1] (NaN is not allowed)")
    means_a = np.asarray(means)
    n = means_a.shape[-2] if means_a.ndim >= 2 else -1
    means_a = _per_frame(means_a, t, (n, 3), "accumulate_scores: means")
    quats_a = _per_frame(quats, t, (n, 4), "accumulate_scores: quats")
    scales_a = _per_frame(scales, t, (n, 3), "accumulate_scores: scales")
    opac_a = _per_frame(opacities, t, (n,), "accumulate_scores: opacities")
    vm_a = _per_frame(viewmats, t, (4, 4), "accumulate_scores: viewmats")
    k_a = _per_frame(K, t, (3, 3), "accumulate_scores: K")
    moving = np.zeros(n)
    total = np.zeros(n)
    mt = np.zeros((t, n), np.float32) if per_frame else None
    tt = np.zeros((t, n), np.float32) if per_frame else None
    f32 = lambda x: jnp.asarray(np.asarray(x, dtype=np.float32))
    for i in range(t):
        mv, tot = _pair_weights(f32(means_a[i]), f32(quats_a[i]), f32(scales_a[i]), f32(opac_a[i]),
                                f32(vm_a[i]), f32(k_a[i]), f32(m[i]), jnp.asarray(conf[i]), width=w, height=h,
                                capacity=capacity)
        moving += np.asarray(mv, np.float64)
        total += np.asarray(tot, np.float64)
        if per_frame:
            mt[i], tt[i] = np.asarray(mv), np.asarray(tot)
    return Scores(score=moving / (total + eps), moving=moving, total=total, moving_t=mt, total_t=tt)


def carry_masks(
    masks: Bool[np.ndarray, "T H W"], tracks: Float[np.ndarray, "T+1 H W 2"]
) -> tuple[Float32[np.ndarray, "T H W"], Float32[np.ndarray, "T H W"], Bool[np.ndarray, "T H W"]]:
    """Each pair's moving-pixel mask read along the tracks of a reference frame r: (carried, seen) [T, H, W] float32
    on frame r's grid, and covered [T, H, W] bool on each pair's own grid.

    The pairs are consecutive in time: pair k maps frame k to frame k+1 of the sequence, and ``masks[k]`` lies on
    frame k's grid; ``tracks[k]`` is the displacement of each pixel p of frame r into frame k (NaN where the track is
    lost: `fgjax.data.opticalflow.chained_tracks`, whose output this is). Then seen[k, p] = 1 where p's track is
    alive in both frames of pair k (in frame k+1 too: the pair's flow there passed the round-trip check, so a point
    about to be hidden by what moves over it is not counted), and carried[k, p] = seen[k, p] *
    masks[k](p + tracks[k, p]) (nearest pixel); covered[k] marks the pixels of frame k within one pixel (3 x 3) of
    where a track seen in pair k lies, the part of frame k that frame r accounts for.

    Why: `accumulate_scores` credits a moving pixel of frame k to the Gaussians the model paints there at k, and
    where stage 1 draws a part in the wrong place (it has not learned the part's motion, issue 53), what the part
    moved over, or its blurred states, collect the motion. Carried back to frame r, the pixel is credited to the
    Gaussians that paint the same surface point in frame r, before it moved (r is the first frame; with
    ``deform.anchor = "first"`` the model's canonical scene). `discover` with a `Reference` back-projects the
    covered pixels of each pair there and the others at their own frame, so that a point hidden in frame r, or
    whose track is lost, still counts. docs/benchmarks.md, "Discovery along the tracks".
    """
    m = np.asarray(masks)
    d = np.asarray(tracks, np.float32)
    if m.ndim != 3 or d.shape != (len(m) + 1, *m.shape[1:], 2):
        raise ValueError(f"carry_masks: masks must have shape [T, H, W] and tracks [T+1, H, W, 2]; got "
                         f"{list(m.shape)} and {list(d.shape)}")
    t, h, w = m.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)  # array indices = pixel coordinates - 0.5, as chained_tracks
    x, y = xs + d[..., 0], ys + d[..., 1]
    alive = np.isfinite(x) & np.isfinite(y) & (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
    seen = alive[:-1] & alive[1:]
    ix = np.clip(np.rint(np.where(alive, x, 0.0)).astype(np.intp), 0, w - 1)[:-1]
    iy = np.clip(np.rint(np.where(alive, y, 0.0)).astype(np.intp), 0, h - 1)[:-1]
    flat = (iy * w + ix).reshape(t, -1)
    carried = np.take_along_axis(m.reshape(t, -1), flat, axis=1).reshape(t, h, w)
    covered = np.zeros((t, h * w), bool)
    k, j = np.nonzero(seen.reshape(t, -1))
    covered[k, flat[k, j]] = True
    covered = ndimage.binary_dilation(covered.reshape(t, h, w), np.ones((1, 3, 3), bool))
    return np.where(seen, carried, 0).astype(np.float32), seen.astype(np.float32), covered


def windowed_score(
    moving_t: Float[np.ndarray, "T N"], total_t: Float[np.ndarray, "T N"], window: int, *, eps: float = 0.1
) -> Float[np.ndarray, " N"]:
    """The discovery score over the best run of ``window`` consecutive pairs (pairs in time order):

        score_i = max_s sum_{t=s}^{s+window-1} moving_it / (sum_{t=s}^{s+window-1} total_it + eps).

    The score of `accumulate_scores` divides by everything a Gaussian paints over the whole clip, so a part that
    moves in a fifth of the pairs scores at most a fifth however clearly those pairs show it; over a window the
    pairs in which it rests do not dilute it. ``window`` >= T is that score (one window of every pair). Returns
    [N] float64 in [0, 1); all zero for T = 0.
    """
    mv = np.asarray(moving_t, np.float64)
    tt = np.asarray(total_t, np.float64)
    if mv.ndim != 2 or tt.shape != mv.shape:
        raise ValueError(f"windowed_score: moving_t and total_t must both have shape [T, N], got {list(mv.shape)} "
                         f"and {list(tt.shape)}")
    if window < 1:
        raise ValueError(f"windowed_score: window must be >= 1, got {window}")
    if len(mv) == 0:
        return np.zeros(mv.shape[1])
    w = min(int(window), len(mv))
    cm = np.concatenate([np.zeros((1, mv.shape[1])), np.cumsum(mv, 0)])
    ct = np.concatenate([np.zeros((1, tt.shape[1])), np.cumsum(tt, 0)])
    return ((cm[w:] - cm[:-w]) / (ct[w:] - ct[:-w] + eps)).max(0)


class Reference(NamedTuple):
    """A reference frame r for `discover`: the tracks of its pixels into every frame of the pairs (``tracks``
    [T+1, H, W, 2], time order, NaN where lost; `carry_masks`), and its Gaussians (activated ``means`` [N, 3],
    ``quats`` [N, 4]) and camera (``viewmat`` [4, 4] world-to-camera, ``K`` [3, 3])."""

    tracks: Float[np.ndarray, "T+1 H W 2"]
    means: Float[np.ndarray, "N 3"]
    quats: Float[np.ndarray, "N 4"]
    viewmat: Float[np.ndarray, "4 4"]
    K: Float[np.ndarray, "3 3"]


class Discovery(NamedTuple):
    """Result of `discover`.

    dynamic: [N] bool, the selected set D.
    scores: `Scores`.
    masks: [T, H, W] bool moving-pixel masks, one per pair.
    threshold: the score threshold used (Otsu's or the one given).
    """

    dynamic: Bool[np.ndarray, " N"]
    scores: Scores
    masks: Bool[np.ndarray, "T H W"]
    threshold: float


def discover(
    means: Float[np.ndarray, "T N 3"],
    quats: Float[np.ndarray, "T N 4"],
    scales: Float[np.ndarray, "T N 3"],
    opacities: Float[np.ndarray, "T N"],
    viewmats: Float[np.ndarray, "T 4 4"],
    K: Float[np.ndarray, "T 3 3"],
    flows: Float[np.ndarray, "T H W 2"],
    camera_flows: Float[np.ndarray, "T H W 2"],
    *,
    valid: Bool[np.ndarray, "T H W"] | None = None,
    threshold_px: float | Float[np.ndarray, "T H W"] | Literal["otsu"] | None = "otsu",
    min_px: float = 0.5,
    score_threshold: float | Literal["otsu"] = "otsu",
    min_score: float = 0.02,
    min_total: float = 0.0,
    eps: float = 0.1,
    capacity: int | None = None,
    per_frame: bool = False,
    window: int = 0,
    confidence: Float[np.ndarray, "T H W"] | None = None,
    noise_sigmas: float = 0.0,
    reference: Reference | None = None,
) -> Discovery:
    """Select the dynamic Gaussians D from optical flow and camera flow (step 5), over T pairs.

    Pair t maps frame t-1 to frame t; every array with a T axis is indexed by pair and describes
    frame t-1 (Gaussians deformed to time t-1, camera t-1, flow on frame t-1's grid).

    Args:
        means, quats, scales, opacities: activated Gaussians per pair ([T, N, ...], or shared).
        viewmats: [T, 4, 4] world-to-camera of frame t-1.
        K: [3, 3] or [T, 3, 3].
        flows: [T, H, W, 2] optical flow t-1 -> t.
        camera_flows: [T, H, W, 2] camera flow of frame t-1 (`camera_flow_from_depth`).
        valid: [T, H, W] pixels where both flows are trusted (None: all finite ones).
        threshold_px, min_px, noise_sigmas: see `binarize`.
        score_threshold, min_score: see `fgjax.cluster.select_dynamic`.
        min_total: Gaussians painting fewer pixel-equivalents than this over all frames are not
            selected (never seen, nothing to say about them).
        eps: see `accumulate_scores`.
        capacity: rasterizer capacity (static).
        per_frame: keep the per-frame terms in ``scores`` (see `Scores`).
        window: > 0: each Gaussian's score is its best run of this many consecutive pairs (`windowed_score`; the
            pairs must then be in time order); 0: the score over all pairs.
        confidence: [T, H, W] per-pixel weights in [0, 1] of the back-projection (`accumulate_scores`,
            `agreement`; None: all 1).
        reference: a reference frame r (`Reference`; the pairs must then be consecutive in time), or None. Given,
            each moving pixel is back-projected once: at frame r where one of r's tracks reaches it
            (`carry_masks`: the carried masks on r's Gaussians from r's camera, each pair weighted over the
            pixels of r tracked through it), at its own frame elsewhere (``confidence`` applies there).

    Returns:
        `Discovery` (``masks`` as binarised, on each pair's own grid).
    """
    masks = binarize(residual_flow(flows, camera_flows), threshold_px, valid=valid, min_px=min_px,
                     noise_sigmas=noise_sigmas)
    if masks.ndim != 3:
        raise ValueError(f"discover: flows must have shape [T, H, W, 2], got {np.shape(flows)}")
    if window < 0:
        raise ValueError(f"discover: window must be >= 0, got {window}")
    keep = per_frame or window > 0
    if reference is None:
        sc = accumulate_scores(means, quats, scales, opacities, viewmats, K, masks, eps=eps, capacity=capacity,
                               per_frame=keep, confidence=confidence)
    else:
        carried, seen, covered = carry_masks(masks, reference.tracks)
        own = (~covered).astype(np.float32)
        own = own if confidence is None else own * np.asarray(confidence, np.float32)
        a = accumulate_scores(means, quats, scales, opacities, viewmats, K, masks, eps=eps, capacity=capacity,
                              per_frame=keep, confidence=own)
        b = accumulate_scores(reference.means, reference.quats, scales, opacities, reference.viewmat, reference.K,
                              carried, eps=eps, capacity=capacity, per_frame=keep, confidence=seen)
        moving, total = a.moving + b.moving, a.total + b.total
        sc = Scores(score=moving / (total + eps), moving=moving, total=total,
                    moving_t=a.moving_t + b.moving_t if keep else None, total_t=a.total_t + b.total_t if keep else None)
    if window > 0:
        sc = sc._replace(score=windowed_score(sc.moving_t, sc.total_t, window, eps=eps))
        if not per_frame:
            sc = sc._replace(moving_t=None, total_t=None)
    ok = sc.total > min_total
    if isinstance(score_threshold, str):
        thr = cluster.otsu_threshold(sc.score[ok]) if ok.any() else float("inf")
    else:
        thr = float(score_threshold)
    dyn = cluster.select_dynamic(sc.score, thr, min_score=min_score, valid=ok)
    return Discovery(dynamic=dyn, scores=sc, masks=masks, threshold=float(thr))
