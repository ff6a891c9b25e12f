"""Photometric tracking: the objects' rigid poses fitted to the training images by rendering them.

Flow-based tracking (`fgjax.articulate.track`) measures each part's motion through the optical flow of the
pixels it paints. Parts that turn towards or away from the camera (a door about its hinge, a lid lifting)
barely move in one pair's flow, and the estimators miss large displacements of fine, periodic textures,
so flow-tracked turns come out far too small. Here the poses are fitted by analysis by synthesis instead:

1. Frames in time order. Object k's pose in frame n starts from its pose in frame n-1, extrapolated at
   constant velocity or not, or from an earlier fit's pose when one is given (whichever renders closest
   to image n), and only objects moving in pair (n-1, n) are fitted (the others keep their pose; with
   ``rest_check``, a run of such frames is put back at rest afterwards where that renders closer).
2. A pose update is a rotation about the object's current centroid and a shift, both in world
   coordinates (``x`` [K, 6]: rotation vector, shift in units of the object's radius times
   ``translation_scale``). The loss is the mean absolute difference of the rendered and the observed
   image, both blurred by a Gaussian of ``sigmas[l]`` pixels, minimised with Adam for ``steps[l]``
   steps per level (coarse to fine: a wide blur makes a part's colour blob overlap its image even when
   the pose starts several pixels off).
3. Discovery's labels are not exact: a door's hinge side is missed and static surfaces next to a part
   join it, and a mislabelled Gaussian drags the pose towards a compromise. Each candidate (a Gaussian
   within ``radius`` of a cluster, members included) is therefore rendered twice, moved with its nearest
   cluster (opacity sigma(o) pi) and static (opacity sigma(o) (1 - pi)), as in the re-fit's relabelling
   (`fgjax.articulate.refit.refit_gaussians`). pi = sigmoid(l), l starting at +2 for members and -2 for
   the others, is trained with the poses and carried from frame to frame, so it collects the evidence of
   every frame in which its cluster is fitted. It only weights the tracking; the labels are not changed.
   A frame composites, at every step, only the tiles that its fitted objects and their candidates reach;
   the rest of the image (the objects not fitted at their poses included) is drawn once per frame.
4. `joint_poses` then replaces each object's per-frame poses by one articulation (revolute or
   prismatic, `fgjax.articulate.track.fit_joint` on its reference points' projected positions): a
   single image pins a pose poorly, all frames together pin an axis.

Conventions: OpenCV cameras (world-to-camera `viewmats` [T, 4, 4], `Ks` [T, 3, 3]); poses [K, T, 4, 4]
are world-space rigid transforms of each object from the reference scene (pose 0 = I); quaternions wxyz.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import ArrayLike, Bool, Float, Int
from sklearn.neighbors import NearestNeighbors

from fgjax import geometry
from fgjax.articulate.track import JOINT_KINDS, fit_joint
from fgjax.gaussians import Gaussians, activate
from fgjax.geometry import HIGHEST
from fgjax.method.camera import project_rows
from fgjax.metrics import filter_valid, rotation_angle_deg
from fgjax.models.model import render_params
from fgjax.models.posed import transform_gaussians
from fgjax.render.project import project_gaussians
from fgjax.render.tiles import tile_ranges

__all__ = ["blur", "blur_kernel", "blur_with", "pose_delta", "relabel_candidates", "mixed_opacity_logits",
           "mixed_copies", "soft_members", "tile_region", "rects_meeting", "subset_bucket", "rest_spans",
           "settle_at_rest", "track_photometric", "joint_poses", "hinge_offset", "largest_turn_deg", "is_far_hinge",
           "FAR_HINGE_RADII", "FAR_HINGE_TURN_DEG", "converged_joints"]


def blur_kernel(sigma: float, radius: int | None = None) -> np.ndarray:
    """The 1-D kernel [2 radius + 1] of `blur`: a normalised Gaussian of `sigma` pixels truncated at
    ceil(3 sigma) taps, zero beyond (``radius`` >= that; None: exactly that); sigma <= 0: a unit impulse."""
    r = int(np.ceil(3.0 * sigma)) if sigma > 0 else 0
    radius = r if radius is None else int(radius)
    if radius < r:
        raise ValueError(f"blur_kernel: radius {radius} is below ceil(3 sigma) = {r}")
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.where(np.abs(x) <= r, np.exp(-0.5 * (x / sigma) ** 2), 0.0) if sigma > 0 else (x == 0) * 1.0
    return k / k.sum()


def blur_with(img, k):
    """Image [H, W, C] convolved separably with the symmetric 1-D kernel `k` [2R + 1] (a jax array, traceable),
    zero padding: `fgjax.metrics.filter_valid` on the zero-padded image (products with banded matrices, faster on
    the CPU than two 1-D ``lax.conv_general_dilated``)."""
    r = (k.shape[0] - 1) // 2
    x = jnp.pad(jnp.moveaxis(img, -1, 0), ((0, 0), (r, r), (r, r)))  # [C, H + 2R, W + 2R]
    return jnp.moveaxis(filter_valid(x, k.astype(img.dtype)), 0, -1)


def blur(img, sigma: float):
    """Image [H, W, C] convolved with a normalised Gaussian of `sigma` pixels (truncated at 3 sigma; zero
    padding); sigma <= 0 returns `img`."""
    if sigma <= 0:
        return img
    return blur_with(img, jnp.asarray(blur_kernel(sigma)))


def pose_delta(x, centres, scale):
    """World transforms [K, 4, 4] of updates x [K, 6]: rotation by exp(x[:3]) about `centres` [K, 3], then a
    shift of x[3:] * `scale` [K]."""
    rot = geometry.so3_exp(x[:, :3])  # [K, 3, 3]
    t = centres - jnp.einsum("kij,kj->ki", rot, centres, precision=HIGHEST) + x[:, 3:] * scale[:, None]
    return geometry.make_pose(rot, t)


def relabel_candidates(means: np.ndarray, labels: np.ndarray, alive: np.ndarray, radius: float):
    """(candidate indices [C], their nearest cluster [C]): the alive Gaussians within `radius` of a member
    of some cluster (members included, each with its own cluster)."""
    members = np.flatnonzero(labels >= 0)
    nn = NearestNeighbors(n_neighbors=1).fit(means[members])
    d, j = nn.kneighbors(means)
    near = labels[members[j[:, 0]]]
    cand = np.flatnonzero(alive & ((d[:, 0] <= radius) | (labels >= 0)))
    return cand, np.where(labels[cand] >= 0, labels[cand], near[cand])


def mixed_opacity_logits(o, logit_w):
    """logit(sigmoid(o) * sigmoid(logit_w)), computed in log space: [M]."""
    log_p = jax.nn.log_sigmoid(o) + jax.nn.log_sigmoid(logit_w)
    log_p = jnp.minimum(log_p, float(np.log1p(-1e-6)))
    return log_p - jnp.log(-jnp.expm1(log_p))


def mixed_copies(g: Gaussians, means, quats, cand, logits) -> Gaussians:
    """The scene with candidates `cand` [C] drawn twice: at `means`/`quats` [N, ...] (where their cluster
    moved them) with opacity sigma(o) sigmoid(logits), and at their own place in `g` with opacity
    sigma(o) (1 - sigmoid(logits)); [N + C] Gaussians, the static copies last."""
    o_moved = g.opacity_logits.at[cand].set(mixed_opacity_logits(g.opacity_logits[cand], logits))
    o_static = mixed_opacity_logits(g.opacity_logits[cand], -logits)
    return Gaussians(jnp.concatenate([means, g.means[cand]]), jnp.concatenate([g.log_scales, g.log_scales[cand]]),
                     jnp.concatenate([quats, g.quats[cand]]), jnp.concatenate([o_moved, o_static]),
                     jnp.concatenate([g.sh, g.sh[cand]]))


def soft_members(labels: np.ndarray, cand: np.ndarray, nearest: np.ndarray, alive):
    """The set-up of the two-copy scene (`mixed_copies`) for candidates `cand` [C] with their nearest cluster
    `nearest` [C]: (labels [N] that move each candidate's first copy with its cluster, cand as a jax array,
    alive [N + C] of both copies, initial membership logits [C]: +2 for members, -2 for the others)."""
    mixed = np.array(labels, np.int64)
    mixed[cand] = nearest
    cj = jnp.asarray(cand)
    alive = jnp.asarray(alive)
    logits = jnp.asarray(np.where(np.asarray(labels)[cand] >= 0, 2.0, -2.0), jnp.float32)
    return jnp.asarray(mixed), cj, jnp.concatenate([alive, alive[cj]]), logits


def _radii(means: np.ndarray, labels: np.ndarray, num_objects: int) -> np.ndarray:
    """RMS distance [K] of each object's Gaussians from their centroid (floor 1e-3)."""
    out = np.full(num_objects, 1e-3)
    for k in range(num_objects):
        p = means[labels == k]
        if len(p):
            out[k] = max(float(np.sqrt(np.mean(np.sum((p - p.mean(0)) ** 2, 1)))), 1e-3)
    return out


def tile_region(rects: np.ndarray, on: np.ndarray, n_tiles_y: int, n_tiles_x: int, margin: int) -> np.ndarray:
    """[nty, ntx] bool: the tiles that the rectangles ``rects`` [M, 4] (tile indices x0, y0, x1, y1, half open;
    `fgjax.render.tiles.tile_ranges`) of the Gaussians ``on`` [M] cover, widened by ``margin`` tiles."""
    r = np.asarray(rects, np.int64)[np.asarray(on, bool)]
    r = r[(r[:, 2] > r[:, 0]) & (r[:, 3] > r[:, 1])]  # empty rects (culled Gaussians) cover nothing
    x0, x1 = np.clip(r[:, 0] - margin, 0, n_tiles_x), np.clip(r[:, 2] + margin, 0, n_tiles_x)
    y0, y1 = np.clip(r[:, 1] - margin, 0, n_tiles_y), np.clip(r[:, 3] + margin, 0, n_tiles_y)
    diff = np.zeros((n_tiles_y + 1, n_tiles_x + 1), np.int64)  # 2D difference array of the rectangles
    np.add.at(diff, (y0, x0), 1)
    np.add.at(diff, (y0, x1), -1)
    np.add.at(diff, (y1, x0), -1)
    np.add.at(diff, (y1, x1), 1)
    return np.cumsum(np.cumsum(diff, 0), 1)[:n_tiles_y, :n_tiles_x] > 0


def rects_meeting(rects: np.ndarray, region: np.ndarray) -> np.ndarray:
    """[M] bool: whether each rectangle [M, 4] (x0, y0, x1, y1 in tiles, half open) holds a tile of ``region``
    [nty, ntx] (a summed-area table, O(1) per rectangle)."""
    r = np.asarray(rects, np.int64)
    sat = np.zeros((region.shape[0] + 1, region.shape[1] + 1), np.int64)
    sat[1:, 1:] = np.cumsum(np.cumsum(np.asarray(region, np.int64), 0), 1)
    x0, y0, x1, y1 = (np.clip(r[:, j], 0, region.shape[1 - j % 2]) for j in range(4))
    inside = sat[y1, x1] - sat[y0, x1] - sat[y1, x0] + sat[y0, x0]
    return (x1 > x0) & (y1 > y0) & (inside > 0)


def subset_bucket(n_subset: int, n_all: int, fractions=(0.5, 0.75)) -> int:
    """The padded size of a subset of ``n_subset`` of ``n_all`` Gaussians: the smallest of ``fractions`` of
    ``n_all`` (rounded up) that holds it, else ``n_all``; few sizes, so few compiled programs."""
    for f in sorted(fractions):
        b = int(np.ceil(f * n_all))
        if n_subset <= b:
            return b
    return int(n_all)


def rest_spans(moving, poses, fixed=None, *, tol_deg: float = 0.1,
               tol_shift: float = 1e-4) -> list[tuple[int, int, int]]:
    """The still spans of `track_photometric`'s ``rest_check``: (k, a, b) for each object k and maximal run of
    frames a..b-1 (a >= 2) in which k is not fitted (``moving`` [K, T-1] false for pairs a-1..b-2) right after a
    frame in which it was, and in which its pose (``poses`` [K, T, 4, 4], the same in the whole run) is off the
    identity by more than ``tol_deg`` degrees or ``tol_shift`` (scene units). ``fixed`` [K] bool: objects skipped."""
    mov = np.asarray(moving, bool)
    poses = np.asarray(poses, np.float64)
    n_obj, t_all = poses.shape[:2]
    if mov.shape != (n_obj, t_all - 1):
        raise ValueError(f"rest_spans: moving must be [K, T-1] = [{n_obj}, {t_all - 1}], got {list(mov.shape)}")
    fixed = np.zeros(n_obj, bool) if fixed is None else np.asarray(fixed, bool)
    out = []
    for k in np.flatnonzero(~fixed):
        n = 1
        while n < t_all:
            if mov[k, n - 1] or n < 2 or not mov[k, n - 2]:
                n += 1
                continue
            b = n
            while b < t_all and not mov[k, b - 1]:
                b += 1
            angle = rotation_angle_deg(poses[k, n, :3, :3])
            if not (angle <= tol_deg and np.linalg.norm(poses[k, n, :3, 3]) <= tol_shift):  # non-finite: off too
                out.append((int(k), n, b))
            n = b
    return out


def _spans_to_rest(poses: np.ndarray, spans, loss, *, extend: bool = False) -> tuple[np.ndarray, list]:
    """Each still span (k, a, b) of `rest_spans`, in turn, put at rest (the identity) where that renders closer over
    it: the sum of ``loss(P, n)`` (frame n's loss with the poses P [K, 4, 4] of that frame; nan never wins) over
    frames a..b-1. ``extend``: first the frames just before the span join it one by one going back, as long as the
    object's pose there is off the identity and at rest renders closer to that frame. Each frame is rendered once
    as posed and once at rest. Returns (poses, [(k, a, b, kept, rest)] for each span, a its first frame after
    extending; it went to rest where rest < kept)."""
    eye = np.eye(4, dtype=poses.dtype)
    tried = []
    for k, a, b in spans:
        def both(n):  # (frame n's loss as posed, with object k at rest)
            at_rest = poses[:, n].copy()
            at_rest[k] = eye
            return loss(poses[:, n], n), loss(at_rest, n)

        pairs = {}
        while extend and a > 1 and not np.allclose(poses[k, a - 1], eye, atol=1e-6):
            pairs[a - 1] = both(a - 1)
            if not pairs[a - 1][1] < pairs[a - 1][0]:
                break
            a -= 1
        for n in range(a, b):
            if n not in pairs:
                pairs[n] = both(n)
        kept = sum(pairs[n][0] for n in range(a, b))
        rest = sum(pairs[n][1] for n in range(a, b))
        if rest < kept:
            poses = poses.copy()
            poses[k, a:b] = eye
        tried.append((int(k), int(a), int(b), kept, rest))
    return poses, tried


def settle_at_rest(gaussians: Gaussians, alive: Bool[ArrayLike, " N"], labels: Int[ArrayLike, " N"], num_objects: int,
                   images: Float[ArrayLike, "T H W 3"], viewmats: Float[ArrayLike, "T 4 4"],
                   Ks: Float[ArrayLike, "T 3 3"], poses: Float[ArrayLike, "K T 4 4"],
                   moving: Bool[ArrayLike, "K T-1"], *,
                   sh_degree: int, background, capacity: int | None = None, tile_size: int = 8, sigma: float = 0.7,
                   log=print) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Each object's still spans put back at rest where the images say so, judged with hard labels on a given scene.

    `track_photometric`'s ``rest_check`` decides with the labels and the scene it tracks with. Its first
    round has discovery's labels, whose false members (the static surfaces around a part) can make a pose
    inside the part's cabinet render closer than rest; the later rounds render a scene re-fitted under that
    pose. Here, with labels cleaned since (hull fill, colour) and a scene fitted without the poses (stage 1's),
    for each still span (k, a, b) of `rest_spans`:

    1. the frames just before it, which were fitted, join it one by one going back, as long as the object at
       rest renders closer to that frame than at its pose there and its pose is off the identity (a part
       that closes is often fitted past rest in its last frames);
    2. the whole span goes to rest where that renders closer over it.

    The loss is the mean absolute difference of the render and the image, both blurred by ``sigma`` pixels,
    over the whole frame, with every other object at its pose. Poses stay on each object's joint: the identity
    is amount 0.

    Args:
        gaussians: the scene (raw parameters) the poses move; alive [N] bool; labels [N] in -1..K-1.
        images: [T, H, W, 3]; viewmats, Ks: [T, 4, 4], [T, 3, 3] (time order, as ``poses`` [K, T, 4, 4]).
        moving: [K, T-1] bool, the pairs in which each object was fitted.

    Returns:
        (poses [K, T, 4, 4], the spans (k, a, b) put at rest: frames a..b-1 of object k).
    """
    poses = np.asarray(poses, np.float32).copy()
    labels = np.asarray(labels, np.int64)
    t_all = poses.shape[1] if poses.ndim == 4 else 0
    if poses.shape != (num_objects, t_all, 4, 4) or len(images) != t_all:
        raise ValueError(f"settle_at_rest: poses must be [K, T, 4, 4] with K = {num_objects} and T = {len(images)} "
                         f"frames, got {list(poses.shape)}")
    if num_objects == 0 or t_all < 3:
        return poses, []
    g = jax.tree_util.tree_map(jnp.asarray, gaussians)
    lab_j, alive_j = jnp.asarray(labels, jnp.int32), jnp.asarray(alive, bool)
    vms, Kj = jnp.asarray(viewmats, jnp.float32), jnp.asarray(Ks, jnp.float32)
    bg = jnp.asarray(background, jnp.float32)
    width, height = int(images.shape[2]), int(images.shape[1])
    kern = jnp.asarray(blur_kernel(float(sigma)), jnp.float32)
    images = jnp.asarray(images, jnp.float32)

    @jax.jit
    def frame_loss(P, i):  # P [K, 4, 4]
        m, q = transform_gaussians(g.means, g.quats, lab_j, P)
        img, _, info, _ = render_params({"gaussians": Gaussians(m, g.log_scales, q, g.opacity_logits, g.sh)}, alive_j,
                                        vms[i], Kj[i], 0.0, spec=None, sh_degree=sh_degree, width=width,
                                        height=height, background=bg, capacity=capacity, tile_size=tile_size)
        loss = jnp.mean(jnp.abs(blur_with(img, kern) - blur_with(images[i], kern)))
        return jnp.where(jnp.isfinite(loss) & ~info["overflow"], loss, jnp.inf)

    def loss(P, n) -> float:  # P [K, 4, 4]: frame n's poses
        return float(frame_loss(jnp.asarray(P), jnp.asarray(n, jnp.int32)))

    t_start = time.perf_counter()
    spans = rest_spans(moving, poses)
    poses, tried = _spans_to_rest(poses, spans, loss, extend=True)
    settled = [(k, a, b) for k, a, b, kept, rest in tried if rest < kept]
    for k, a, b, kept, rest in tried:
        if rest < kept:
            log(f"stage 2: object {k + 1} settled at rest in frames {a + 1}-{b} (loss {kept / (b - a):.5f} -> "
                f"{rest / (b - a):.5f} a frame)")
    if spans:
        log(f"stage 2: {len(settled)} of {len(spans)} still span(s) settled at rest "
            f"({time.perf_counter() - t_start:.1f} s)")
    return poses, settled


def track_photometric(gaussians: Gaussians, alive: Bool[ArrayLike, " N"], labels: Int[ArrayLike, " N"],
                      num_objects: int, images: Float[ArrayLike, "T H W 3"], viewmats: Float[ArrayLike, "T 4 4"],
                      Ks: Float[ArrayLike, "T 3 3"], *, moving: Bool[ArrayLike, "K T-1"] | None = None,
                      sh_degree: int, background, capacity: int | None = None, tile_size: int = 8,
                      steps=(20, 20, 10), sigmas=(4.0, 2.0, 0.7), lr: float = 0.02, member_lr: float = 0.1,
                      radius: float = 0.1, translation_scale: float = 3.0, init_poses=None, only_moving: bool = True,
                      subset_margin: int | None = None, fixed=None, rest_check: bool = False, progress_every: int = 10,
                      return_stats: bool = False, log=print):
    """Poses [K, T, 4, 4] of each object fitted to the images frame by frame (module docstring, 1-3).

    Args:
        gaussians: the reference scene (raw parameters, numpy or jax leaves), which the poses move.
        alive: [N] bool.
        labels: [N] object of each Gaussian (-1: static).
        images: [T, H, W, 3] in time order; viewmats, Ks: [T, 4, 4], [T, 3, 3].
        moving: [K, T-1] bool, the pairs in which each object moves (None: all).
        sh_degree, background, capacity, tile_size: the renderer's (as stage 1's).
        steps, sigmas: Adam steps and blur (pixels) per level, coarse to fine.
        lr, member_lr: Adam learning rates of the pose updates and of the membership logits.
        radius: candidates of the soft membership (scene units; 0: members only, no soft membership).
        translation_scale: a shift's unit, in object radii.
        init_poses: [K, T, 4, 4] poses of an earlier fit (e.g. a previous round's), a third start of each
            frame besides the extrapolated and the previous pose (None: two starts).
        only_moving: a frame renders only the objects it fits (and their candidates) at every step; the
            other objects are drawn once per frame at their poses, and their candidates' memberships do not
            learn from that frame. False: every object and candidate is redrawn and learns in every frame.
            With ``radius=0`` (no memberships) both give the same poses.
        subset_margin: a frame's steps render only the changing Gaussians and the others whose tile
            rectangle meets the tiles the changing ones reach at the frame's start pose, widened by this
            many tiles (the room a part has to move within one frame's fit); the tiles outside show the
            once-per-frame render. That is the image of rendering every Gaussian while the changing ones
            stay within the margin; when one leaves it (Adam's first steps can throw a part tens of pixels),
            the frame is fitted again from its start with every Gaussian, so the poses are those of
            ``None`` (every Gaussian at every step) up to round-off.
        fixed: [K] bool, objects not fitted: their poses are ``init_poses`` (required then) in every frame,
            and the fitted objects are tracked with them drawn there (e.g. the objects whose joint has
            converged over earlier rounds; None: none).
        rest_check: after the frames are fitted, each object's still spans (the runs of frames after a fitted one
            in which it is not fitted: it keeps that frame's pose) are also rendered with the object at rest (the
            identity, the reference pose); where that renders closer to the images over the whole span (the mean
            absolute difference at the finest blur), the span takes it (`rest_spans`). A part that closes again
            is otherwise left wherever its last fitted frame put it.
        progress_every: a progress line every this many fitted frames (0: none).
        return_stats: also return what the run did (the summary line's numbers, for benchmarks).

    Returns:
        (poses [K, T, 4, 4], pi [N]: each candidate's final membership of its nearest cluster; 1 for the
        other members and 0 for the other Gaussians), and with ``return_stats`` a dict: "frames_fitted",
        "steps_per_frame", "skipped_steps", "drawn_per_step" (Gaussians drawn per step, mean over the fitted
        frames), "gaussians" (of the two-copy scene), "fitted_again" (frames fitted again with every Gaussian),
        "spans_at_rest" (``rest_check``'s spans put at rest), "frame_seconds" (list, each fitted frame's wall time; the
        first compiles) and "seconds".
    """
    labels = np.asarray(labels, np.int64)
    t_all = len(viewmats)
    poses = np.tile(np.eye(4, dtype=np.float32), (num_objects, t_all, 1, 1))
    alive_np = np.asarray(alive, bool)
    if num_objects == 0 or t_all < 2:
        pi = (labels >= 0).astype(np.float64)
        stats = dict(frames_fitted=0, steps_per_frame=int(sum(steps)), skipped_steps=0, drawn_per_step=0.0,
                     gaussians=0, fitted_again=0, frame_seconds=[], seconds=0.0)
        return (poses, pi, stats) if return_stats else (poses, pi)
    if len(steps) != len(sigmas):
        raise ValueError(f"track_photometric: {len(steps)} step counts for {len(sigmas)} blur levels")
    if init_poses is not None:
        init_poses = np.asarray(init_poses, np.float32)
        if init_poses.shape != poses.shape:
            raise ValueError(f"track_photometric: init_poses must be [K, T, 4, 4] = {list(poses.shape)}, got "
                             f"{list(init_poses.shape)}")
    fixed = np.zeros(num_objects, bool) if fixed is None else np.asarray(fixed, bool)
    if fixed.shape != (num_objects,):
        raise ValueError(f"track_photometric: fixed must be [K] = [{num_objects}], got {list(fixed.shape)}")
    if fixed.any():
        if init_poses is None:
            raise ValueError("track_photometric: fixed objects take their poses from init_poses, which is None")
        poses[fixed] = init_poses[fixed]
    t_start = time.perf_counter()
    g = jax.tree_util.tree_map(jnp.asarray, gaussians)
    m_ref = np.asarray(g.means, np.float64)
    if radius > 0:
        cand, k_c = relabel_candidates(m_ref, labels, alive_np, float(radius))
    else:  # no soft membership: the labels as they are
        cand = k_c = np.zeros(0, np.int64)
    lab_m, cj, alive2, lg = soft_members(labels, cand, k_c, alive_np)
    scale = jnp.asarray(_radii(m_ref, labels, num_objects) * translation_scale, jnp.float32)
    images = jnp.asarray(images, jnp.float32)
    vms, Kj = jnp.asarray(viewmats, jnp.float32), jnp.asarray(Ks, jnp.float32)
    bg = jnp.asarray(background, jnp.float32)
    width, height = int(images.shape[2]), int(images.shape[1])
    nty, ntx = -(-height // tile_size), -(-width // tile_size)
    n_all = int(alive2.shape[0])  # N + C: the two-copy scene
    alive2_np = np.asarray(alive2, bool)
    every = (jnp.arange(n_all, dtype=jnp.int32), jnp.asarray(alive2), jnp.ones((nty, ntx), bool))

    # Within a frame the poses move the fitted objects' Gaussians and the logits mix their candidates' copies;
    # every other Gaussian stays where it is, so the tiles none of the changing ones reaches are composited
    # once per frame (`render_rest`) and pasted.
    k_cj = jnp.asarray(k_c, jnp.int32)  # [C] each candidate's nearest cluster

    def changing_set(on):
        """(changing [N + C], learning [C]) for the objects `on` [K] bool: their Gaussians (both copies of
        their candidates) and their candidates' logits."""
        learn = on[k_cj]  # [C]
        return jnp.concatenate([(lab_m >= 0) & on[jnp.maximum(lab_m, 0)], learn]), learn

    def posed(P, lg):
        """The two-copy scene (`mixed_copies`) with the objects moved by P [K, 4, 4] and the candidates mixed
        by lg [C]: [N + C] Gaussians."""
        m, q = transform_gaussians(g.means, g.quats, lab_m, P)
        return mixed_copies(g, m, q, cj, lg)

    def render(P, lg, i, rest, changing, subset):
        """(image [H, W, 3], overflow, escaped) of frame i, objects moved by P [K, 4, 4], candidates mixed by
        lg [C]; rest [H, W, 3]: frame i without the changing Gaussians (`render_rest`), for the tiles they
        miss; subset = (ids [B], live [B], region [nty, ntx]): the Gaussians drawn and the tiles they may paint
        (`every`: all of them). escaped: a changing Gaussian reaches a tile outside the region (the image is
        then not the full render's)."""
        ids, live, region = subset
        drawn = jax.tree_util.tree_map(lambda a: a[ids], posed(P, lg))
        img, _, info, _ = render_params({"gaussians": drawn}, live, vms[i], Kj[i], 0.0, spec=None,
                                        sh_degree=sh_degree, width=width, height=height, background=bg,
                                        capacity=capacity, tile_size=tile_size, active=changing[ids] & live)
        on = info["tile_on"] & region  # [nty, ntx]
        escaped = jnp.any(info["tile_on"] & ~region)
        on = jnp.repeat(jnp.repeat(on, tile_size, 0), tile_size, 1)[:height, :width]  # [H, W]
        return jnp.where(on[..., None], img, rest), info["overflow"], escaped

    @jax.jit
    def frame_rects(P, lg, i):
        """Tile rectangles [N + C, 4] of the two-copy scene in frame i (`fgjax.render.tiles.tile_ranges`)."""
        s = posed(P, lg)
        q, sc, o = activate(s, alive2)
        proj = project_gaussians(s.means, q, sc, o, vms[i], Kj[i], width, height)
        return tile_ranges(proj.means2d, proj.extent, proj.valid, tile_size, width, height)

    def frame_subset(P, lg, i, changing):
        """(ids [B], live [B], region [nty, ntx]) for a frame fitted from the poses P (`render`'s subset):
        the changing Gaussians and every other live one whose rectangle meets the tiles the changing ones
        reach, widened by `subset_margin`; B is a `subset_bucket` size (padding: id 0, not live)."""
        if subset_margin is None:
            return every
        rects = np.asarray(frame_rects(P, lg, i))
        ch = np.asarray(changing)
        region = tile_region(rects, ch & alive2_np, nty, ntx, int(subset_margin))
        idx = np.flatnonzero(alive2_np & (ch | rects_meeting(rects, region)))
        ids = np.zeros(subset_bucket(len(idx), n_all), np.int32)
        ids[:len(idx)] = idx
        return jnp.asarray(ids), jnp.asarray(np.arange(len(ids)) < len(idx)), jnp.asarray(region)

    @jax.jit
    def render_rest(P, lg, i, changing):
        """Frame i without the changing Gaussians, the others at the poses P and memberships lg: [H, W, 3]."""
        img, _, _, _ = render_params({"gaussians": posed(P, lg)}, alive2 & ~changing, vms[i], Kj[i], 0.0, spec=None,
                                     sh_degree=sh_degree, width=width, height=height, background=bg,
                                     capacity=capacity, tile_size=tile_size)
        return img

    @jax.jit
    def first_loss(P, lg, i, rest, changing):
        img, _, _ = render(P, lg, i, rest, changing, every)
        return jnp.mean(jnp.abs(img - images[i]))

    opt_x, opt_l = optax.adam(lr), optax.adam(member_lr)
    learn_members = radius > 0

    # every level in one compiled step: the level's kernel (zero-padded to the widest) and target are inputs
    radius = max(len(blur_kernel(float(sg))) for sg in sigmas) // 2
    kernels = jnp.asarray(np.stack([blur_kernel(float(sg), radius) for sg in sigmas]), jnp.float32)  # [L, 2R+1]
    targets = jnp.stack([jax.vmap(lambda im, kk=kk: blur_with(im, kk))(images) for kk in kernels])  # [L, T, H, W, 3]

    @jax.jit
    def step(x, lg, st, i, rest, p_init, centres, mask, changing, learn, subset, level):
        def loss_fn(x_, lg_):
            P = jnp.einsum("kij,kjl->kil", pose_delta(x_ * mask[:, None], centres, scale), p_init, precision=HIGHEST)
            img, over, escaped = render(P, lg_, i, rest, changing, subset)
            return jnp.mean(jnp.abs(blur_with(img, kernels[level]) - targets[level, i])), (over, escaped)

        (loss, (over, escaped)), (gx, gl) = jax.value_and_grad(loss_fn, argnums=(0, 1), has_aux=True)(x, lg)
        ux, sx = opt_x.update(gx, st[0], x)
        ul, sl = opt_l.update(gl, st[1], lg)
        x2 = optax.apply_updates(x, ux)
        lg2 = optax.apply_updates(lg, jnp.where(learn, ul, 0.0)) if learn_members else lg
        bad = over | ~jnp.isfinite(loss)
        keep = lambda a, b: jax.tree_util.tree_map(lambda u, v: jnp.where(bad, v, u), a, b)
        return keep(x2, x), keep(lg2, lg), keep((sx, sl), st), loss, bad, escaped

    levels = [(jnp.asarray(lv, jnp.int32), int(n)) for lv, n in enumerate(steps)]
    mov = np.ones((num_objects, t_all - 1), bool) if moving is None else np.asarray(moving, bool)
    eye = np.eye(4, dtype=np.float32)
    n_fit, n_bad, n_drawn, n_redone, frame_s = 0, 0, 0, 0, []
    for n in range(1, t_all):
        mk = mov[:, n - 1] & ~fixed
        prev = poses[:, n - 1].copy()  # the start of frame n: as frame n - 1, the fixed objects at their frame-n pose
        prev[fixed] = poses[fixed, n]
        poses[:, n] = prev
        if not mk.any():
            continue
        vel = np.tile(eye, (num_objects, 1, 1))
        if n >= 2:
            vel = np.einsum("kij,kjl->kil", prev, np.linalg.inv(poses[:, n - 2]))
        vel[~mk] = eye
        starts = [np.einsum("kij,kjl->kil", vel, prev).astype(np.float32), prev]
        if init_poses is not None:  # the earlier fit's pose for the moving objects
            starts.append(np.where(mk[:, None, None], init_poses[:, n], prev).astype(np.float32))
        t_frame = time.perf_counter()
        i = jnp.asarray(n, jnp.int32)
        changing, learn = changing_set(jnp.asarray(mk if only_moving else np.ones_like(mk)))
        # the objects not fitted keep their pose (the same in every start), so one `rest` serves all starts
        rest = render_rest(jnp.asarray(prev), lg, i, changing)
        l0 = [float(first_loss(jnp.asarray(s), lg, i, rest, changing)) for s in starts]
        p_init = starts[int(np.argmin(np.where(np.isfinite(l0), l0, np.inf)))] if np.any(np.isfinite(l0)) else prev
        centres = np.stack([(m_ref[labels == k] @ p_init[k, :3, :3].T + p_init[k, :3, 3]).mean(0)
                            if np.any(labels == k) else p_init[k, :3, 3] for k in range(num_objects)])
        pj, cen, mask = jnp.asarray(p_init), jnp.asarray(centres, jnp.float32), jnp.asarray(mk, jnp.float32)

        def fit(subset, lg):
            """(x [K, 6], lg [C], skipped steps, escaped): the frame's steps drawing `subset`, stopped at the
            first step on which a changing Gaussian leaves its region."""
            x, skipped = jnp.zeros((num_objects, 6), jnp.float32), 0
            for level, count in levels:
                st = (opt_x.init(x), opt_l.init(lg))
                for _ in range(count):
                    x, lg, st, _, bad, esc = step(x, lg, st, i, rest, pj, cen, mask, changing, learn, subset, level)
                    skipped += int(bad)
                    if bool(esc):
                        return x, lg, skipped, True
            return x, lg, skipped, False

        # the subset first; if a part leaves its margin, the frame again from its start with every Gaussian
        subset = frame_subset(pj, lg, i, changing)
        x, lg_new, skipped, escaped = fit(subset, lg)
        if escaped:
            n_redone += 1
            subset = every
            x, lg_new, skipped, _ = fit(subset, lg)
        lg = lg_new
        n_bad += skipped
        n_drawn += int(np.sum(subset[1]))
        new = np.asarray(jnp.einsum("kij,kjl->kil", pose_delta(x * mask[:, None], cen, scale), pj, precision=HIGHEST))
        poses[:, n] = np.where(np.all(np.isfinite(new), (1, 2))[:, None, None], new, p_init)
        n_fit += 1
        frame_s.append(time.perf_counter() - t_frame)
        if progress_every > 0 and n_fit % progress_every == 0:
            log(f"photometric tracking: frame {n + 1}/{t_all}, {n_fit} fitted ({time.perf_counter() - t_start:.0f} s)")
    n_rest = 0
    if rest_check:
        @jax.jit
        def frame_loss(P, lg, i):
            img, _, _, _ = render_params({"gaussians": posed(P, lg)}, alive2, vms[i], Kj[i], 0.0, spec=None,
                                         sh_degree=sh_degree, width=width, height=height, background=bg,
                                         capacity=capacity, tile_size=tile_size)
            return jnp.mean(jnp.abs(blur_with(img, kernels[-1]) - targets[-1, i]))

        poses, tried = _spans_to_rest(poses, rest_spans(mov, poses, fixed), lambda P, n: float(
            frame_loss(jnp.asarray(P), lg, jnp.asarray(n, jnp.int32))))
        for k, a, b, kept, rest in tried:
            if rest < kept:
                n_rest += 1
                log(f"photometric tracking: object {k + 1} back at rest in frames {a + 1}-{b} "
                    f"(loss {kept / (b - a):.5f} "
                    f"-> {rest / (b - a):.5f} a frame)")
            else:
                log(f"photometric tracking: object {k + 1} keeps its last fitted pose in frames {a + 1}-{b} (loss "
                    f"{kept / (b - a):.5f} a frame; {rest / (b - a):.5f} at rest)")
    pi = (labels >= 0).astype(np.float64)
    pi[cand] = np.asarray(jax.nn.sigmoid(lg))
    stats = dict(frames_fitted=n_fit, spans_at_rest=n_rest, steps_per_frame=sum(n for _, n in levels),
                 skipped_steps=n_bad, drawn_per_step=n_drawn / max(n_fit, 1), gaussians=n_all, fitted_again=n_redone,
                 frame_seconds=frame_s, seconds=time.perf_counter() - t_start)
    log(f"photometric tracking: {n_fit} of {t_all - 1} frames fitted, {stats['steps_per_frame']} steps each "
        f"({n_bad} skipped), {stats['drawn_per_step']:.0f} of {n_all} Gaussians drawn per step on average "
        f"({n_redone} frame(s) fitted again with all of them: a part left its margin), {stats['seconds']:.1f} s"
        + (f" (median {np.median(frame_s[1:]):.2f} s a frame after the first)" if n_fit > 1 else ""))
    return (poses, pi, stats) if return_stats else (poses, pi)


# A far hinge lies more than FAR_HINGE_RADII of its part's radii off it (`hinge_offset`) while the part turns
# FAR_HINGE_TURN_DEG degrees or more: likely a shift fitted as a turn (`joint_poses`' warning;
# `fgjax.articulate.trial.hinge_trial`).
FAR_HINGE_RADII = 2.0
FAR_HINGE_TURN_DEG = 5.0


def largest_turn_deg(poses: Float[ArrayLike, "*batch 4 4"]) -> float:
    """The largest rotation angle, in degrees, of the poses [T, 4, 4] (0 for none; `rotation_angle_deg`)."""
    P = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    return float(np.max(rotation_angle_deg(P[:, :3, :3]), initial=0.0))


def is_far_hinge(ratio: float, turn_deg: float, *, radii: float = FAR_HINGE_RADII,
                 turn: float = FAR_HINGE_TURN_DEG) -> bool:
    """Whether a hinge ``ratio`` radii off its part (`hinge_offset`) turning up to ``turn_deg`` is a far hinge (over
    ``radii`` radii while turning ``turn`` degrees or more; a NaN ratio is not)."""
    return bool(np.isfinite(ratio) and ratio > radii and turn_deg >= turn)


def hinge_offset(points: Float[ArrayLike, "M 3"], axis: Float[ArrayLike, "3"], pivot: Float[ArrayLike, "3"]
                 ) -> tuple[float, float]:
    """How far a hinge lies from its part: (the distance of the axis line (unit ``axis`` [3] through ``pivot``
    [3]) from the centroid of ``points`` [M, 3], that distance over the 95th percentile of the points' distances
    from their centroid). A door or a lid turns about one of its own edges (a ratio up to about 1); a turn about a
    line several radii away moves the part mostly sideways, as a shift does."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    a = np.asarray(axis, np.float64) / max(float(np.linalg.norm(axis)), 1e-12)
    c = pts.mean(0)
    d = c - np.asarray(pivot, np.float64)
    off = float(np.linalg.norm(d - (d @ a) * a))
    radius = float(np.percentile(np.linalg.norm(pts - c, axis=1), 95))
    return off, off / max(radius, 1e-12)


def joint_poses(points: list, poses: Float[ArrayLike, "K T 4 4"], viewmats: Float[ArrayLike, "T 4 4"],
                Ks: Float[ArrayLike, "T 3 3"], *, huber_px: float = 2.0, revolute_margin: float = 0.95,
                warn_cost: float = 4.0, warn_offset: float = FAR_HINGE_RADII,
                warn_turn_deg: float = FAR_HINGE_TURN_DEG,
                return_axes: bool = False, return_offsets: bool = False, log=print):
    """Each object's poses replaced by the one articulation that best explains them.

    Args:
        points: list of K arrays [M_k, 3], each object's reference points (M_k >= 3; fewer: kept as is).
        poses: [K, T, 4, 4] per-frame poses (e.g. `track_photometric`'s).
        viewmats, Ks: [T, 4, 4], [T, 3, 3].

    The reference points moved by each frame's pose and projected into that frame's camera are the
    targets of `fit_joint` (revolute and prismatic, amounts per frame from the reference; the initial
    axes: the largest pose's rotation axis or the centroid's largest shift, and the coordinate axes).
    Each fit is scored by its robust cost: the mean Huber loss (width ``huber_px``, the loss the fit
    minimises) of every point's reprojection residual. The revolute joint wins when its cost
    is below ``revolute_margin`` times the prismatic one's (a turn about a far pivot mimics a slide), else
    the prismatic one. (An inlier RMS would not do: a part moves far in only a few frames, and a wrong
    joint's large residuals there count as outliers, which that RMS leaves out.)

    The chosen joint's cost also tells whether the tracking worked: a joint explains well tracked poses to
    about 1 px^2, while a lost part (poses turning about a wrong axis, or staying open after it closed) costs
    several. Over ``warn_cost`` (px^2) a warning is logged.

    A revolute joint whose turn reaches ``warn_turn_deg`` about an axis more than ``warn_offset`` times the part's
    radius from its centre (`hinge_offset`) is also warned of: doors and lids turn about their own edges, and a
    turn about a far line is a shift in disguise (a lift and a tilt fitted as a small turn about a distant axis).
    Returns (poses [K, T, 4, 4], kinds [K], costs [K]: the chosen joint's robust cost, nan where kept), and with
    ``return_axes`` also axes [K, 3]: the chosen joint's unit axis (revolute) or direction (prismatic), nan where kept;
    with ``return_offsets`` then offsets [K]: a revolute joint's `hinge_offset` ratio (the axis' distance from the
    part's centre in its radii), nan for the others.
    """
    poses = np.asarray(poses, np.float64)
    out, kinds, costs = poses.copy(), [], np.full(len(points), np.nan)
    axes_out = np.full((len(points), 3), np.nan)
    offsets = np.full(len(points), np.nan)
    t_all = poses.shape[1]
    vms = np.asarray(viewmats, np.float64)
    Kn = np.asarray(Ks, np.float64)
    for k, pts in enumerate(points):
        t_obj = time.perf_counter()
        pts = np.asarray(pts, np.float64)
        if len(pts) < 3 or t_all < 2:
            kinds.append("kept")
            continue
        moved = np.einsum("tij,mj->tmi", poses[k, :, :3, :3], pts) + poses[k, :, None, :3, 3]  # [T, M, 3]
        uv, ok = project_rows(jnp.asarray(moved), jnp.asarray(vms), jnp.asarray(Kn))
        tgt = np.asarray(uv)
        w = np.asarray(ok, np.float64)
        rv = np.asarray(geometry.so3_log(jnp.asarray(poses[k, :, :3, :3])))  # [T, 3]
        shift = moved.mean(1) - pts.mean(0)  # [T, 3]
        seed = {"revolute": rv[np.argmax(np.linalg.norm(rv, axis=1))],
                "prismatic": shift[np.argmax(np.linalg.norm(shift, axis=1))]}
        fits = {}
        for kind in JOINT_KINDS:
            axes = np.eye(3) if np.linalg.norm(seed[kind]) < 1e-9 else np.vstack([seed[kind], np.eye(3)])
            fits[kind] = fit_joint(np.repeat(pts[None], t_all, 0), tgt, w, vms, Kn, kind, axes=axes,
                                   huber_px=huber_px)
        cost = {c: fits[c][5] for c in fits}
        # a turn about a far pivot mimics a slide: the revolute joint has to be clearly better
        kind = "revolute" if cost["revolute"] < revolute_margin * cost["prismatic"] else "prismatic"
        out[k] = fits[kind][0]
        kinds.append(kind)
        costs[k] = cost[kind]
        axes_out[k] = fits[kind][3]
        where, far = "", None
        if kind == "revolute":
            off, ratio = hinge_offset(pts, fits[kind][3], fits[kind][4])
            turn = largest_turn_deg(out[k])
            where = f", {off:.3f} from the part's centre ({ratio:.1f} radii), turning up to {turn:.1f} degrees"
            offsets[k] = ratio
            if is_far_hinge(ratio, turn, radii=warn_offset, turn=warn_turn_deg):
                far = (f"photometric tracking: warning: object {k + 1}'s hinge lies {ratio:.1f} times its radius from "
                       f"its centre (more than {warn_offset:g}) while it turns {turn:.1f} degrees: "
                       "a turn about an axis "
                       f"off the part is mostly a shift, so its tracking has likely mistaken a turn about its edge for "
                       f"a lift or a slide, and controlled states far from the tracked ones will be wrong")
        log(f"photometric tracking: object {k + 1}: revolute cost {cost['revolute']:.3f} (inlier RMS "
            f"{fits['revolute'][1]:.2f} px), prismatic {cost['prismatic']:.3f} ({fits['prismatic'][1]:.2f} px) -> "
            f"{kind} (axis {np.round(fits[kind][3], 3).tolist()}{where}; {time.perf_counter() - t_obj:.1f} s)")
        if far is not None:  # after the object's line, which it refers to
            log(far)
        if not cost[kind] <= warn_cost:
            log(f"photometric tracking: warning: object {k + 1}'s {kind} joint explains its tracked poses poorly "
                f"(robust cost {cost[kind]:.2f} px^2 > {warn_cost:g}): its tracking has likely failed, and its "
                f"trajectory and controlled renders will be wrong")
    return (out, kinds, costs) + ((axes_out,) if return_axes else ()) + ((offsets,) if return_offsets else ())


def converged_joints(kinds_a, axes_a, kinds_b, axes_b, max_deg: float) -> np.ndarray:
    """[K] bool: the objects whose joint did not change between two rounds' fits (a, then b; `joint_poses`' kinds
    [K] and axes [K, 3]): the same kind, and axes within ``max_deg`` degrees of each other, either sign (a hinge's
    turn and a slide's amount change sign with their axis). An object kept by either fit ("kept", a nan axis) has
    not converged; ``max_deg <= 0``: none has."""
    a, b = np.asarray(axes_a, np.float64).reshape(-1, 3), np.asarray(axes_b, np.float64).reshape(-1, 3)
    if not len(kinds_a) == len(kinds_b) == len(a) == len(b):
        raise ValueError(f"converged_joints: {len(kinds_a)} and {len(kinds_b)} kinds for {len(a)} and {len(b)} axes")
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    ok = np.isfinite(na) & np.isfinite(nb) & (na > 0) & (nb > 0)
    cos = np.abs(np.sum(a * b, 1)) / np.where(ok, na * nb, 1.0)
    ang = np.degrees(np.arccos(np.clip(np.where(ok, cos, -1.0), -1.0, 1.0)))
    same = np.array([ka == kb and ka in JOINT_KINDS for ka, kb in zip(kinds_a, kinds_b)], bool)
    return ok & same & (ang < max_deg) if max_deg > 0 else np.zeros(len(a), bool)
