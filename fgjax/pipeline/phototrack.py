"""Photometric tracking: the objects' rigid poses fitted to the training images by rendering them.

Flow-based tracking (`fgjax.pipeline.track`) measures each part's motion through the optical flow of the
pixels it paints. Parts that turn towards or away from the camera (a door about its hinge, a lid lifting)
barely move in one pair's flow, and the estimators miss large displacements of fine, periodic textures,
so the tracked turns come out far too small (docs/benchmarks.md, session 6: 9 against 76 degrees). Here
the poses are fitted by analysis by synthesis instead:

1. Frames in time order. Object k's pose in frame n starts from its pose in frame n-1, extrapolated at
   constant velocity or not, or from an earlier fit's pose when one is given (whichever renders closest
   to image n), and only objects moving in pair (n-1, n) are fitted (the others keep their pose).
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
   (`fgjax.pipeline.stage2.refit_gaussians`). pi = sigmoid(l), l starting at +2 for members and -2 for
   the others, is trained with the poses and carried from frame to frame, so it collects the evidence of
   every frame in which its cluster is fitted. It only weights the tracking; the labels are not changed.
   A frame composites, at every step, only the tiles that its fitted objects and their candidates reach;
   the rest of the image (the objects not fitted at their poses included) is drawn once per frame.
4. `joint_poses` then replaces each object's per-frame poses by one articulation (revolute or
   prismatic, `fgjax.pipeline.track.fit_joint` on its reference points' projected positions): a
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

from fgjax import geometry
from fgjax.gaussians import Gaussians
from fgjax.metrics import filter_valid
from fgjax.pipeline.track import JOINT_KINDS, _project_rows, fit_joint, transform_gaussians

__all__ = ["blur", "blur_kernel", "blur_with", "pose_delta", "relabel_candidates", "mixed_opacity_logits", "mixed_copies", "soft_members",
           "track_photometric", "joint_poses"]


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
    zero padding: `fgjax.metrics.filter_valid` on the zero-padded image (products with banded matrices; two
    1-D ``lax.conv_general_dilated`` took 32 ms instead of 2 ms for value and gradient at 160x120, R = 12,
    docs/benchmarks.md, session 13)."""
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
    t = centres - jnp.einsum("kij,kj->ki", rot, centres) + x[:, 3:] * scale[:, None]
    return geometry.make_pose(rot, t)


def relabel_candidates(means: np.ndarray, labels: np.ndarray, alive: np.ndarray, radius: float):
    """(candidate indices [C], their nearest cluster [C]): the alive Gaussians within `radius` of a member
    of some cluster (members included, each with its own cluster)."""
    from sklearn.neighbors import NearestNeighbors

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


def track_photometric(gaussians: Gaussians, alive, labels, num_objects: int, images, viewmats, Ks, *, moving=None,
                      sh_degree: int, background, capacity: int | None = None, tile_size: int = 8,
                      steps=(20, 20, 10), sigmas=(4.0, 2.0, 0.7), lr: float = 0.02, member_lr: float = 0.1,
                      radius: float = 0.1, translation_scale: float = 3.0, init_poses=None, only_moving: bool = True,
                      progress_every: int = 10, log=print):
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
        progress_every: a progress line every this many fitted frames (0: none).

    Returns:
        (poses [K, T, 4, 4], pi [N]: each candidate's final membership of its nearest cluster; 1 for the
        other members and 0 for the other Gaussians).
    """
    from fgjax.pipeline.stage1 import render_params

    labels = np.asarray(labels, np.int64)
    t_all = len(viewmats)
    poses = np.tile(np.eye(4, dtype=np.float32), (num_objects, t_all, 1, 1))
    alive_np = np.asarray(alive, bool)
    if num_objects == 0 or t_all < 2:
        return poses, (labels >= 0).astype(np.float64)
    if len(steps) != len(sigmas):
        raise ValueError(f"track_photometric: {len(steps)} step counts for {len(sigmas)} blur levels")
    if init_poses is not None:
        init_poses = np.asarray(init_poses, np.float32)
        if init_poses.shape != poses.shape:
            raise ValueError(f"track_photometric: init_poses must be [K, T, 4, 4] = {list(poses.shape)}, got "
                             f"{list(init_poses.shape)}")
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

    def render(P, lg, i, rest, changing):
        """(image [H, W, 3], overflow) of frame i, objects moved by P [K, 4, 4], candidates mixed by lg [C];
        rest [H, W, 3]: frame i without the changing Gaussians (`render_rest`), for the tiles they miss."""
        img, _, info, _ = render_params({"gaussians": posed(P, lg)}, alive2, vms[i], Kj[i], 0.0, spec=None,
                                        sh_degree=sh_degree, width=width, height=height, background=bg,
                                        capacity=capacity, tile_size=tile_size, active=changing)
        on = jnp.repeat(jnp.repeat(info["tile_on"], tile_size, 0), tile_size, 1)[:height, :width]  # [H, W]
        return jnp.where(on[..., None], img, rest), info["overflow"]

    @jax.jit
    def render_rest(P, lg, i, changing):
        """Frame i without the changing Gaussians, the others at the poses P and memberships lg: [H, W, 3]."""
        img, _, _, _ = render_params({"gaussians": posed(P, lg)}, alive2 & ~changing, vms[i], Kj[i], 0.0, spec=None,
                                     sh_degree=sh_degree, width=width, height=height, background=bg,
                                     capacity=capacity, tile_size=tile_size)
        return img

    @jax.jit
    def first_loss(P, lg, i, rest, changing):
        img, _ = render(P, lg, i, rest, changing)
        return jnp.mean(jnp.abs(img - images[i]))

    opt_x, opt_l = optax.adam(lr), optax.adam(member_lr)
    learn_members = radius > 0

    # every level in one compiled step: the level's kernel (zero-padded to the widest) and target are inputs
    radius = max(len(blur_kernel(float(sg))) for sg in sigmas) // 2
    kernels = jnp.asarray(np.stack([blur_kernel(float(sg), radius) for sg in sigmas]), jnp.float32)  # [L, 2R+1]
    targets = jnp.stack([jax.vmap(lambda im, kk=kk: blur_with(im, kk))(images) for kk in kernels])  # [L, T, H, W, 3]

    @jax.jit
    def step(x, lg, st, i, rest, p_init, centres, mask, changing, learn, level):
        def loss_fn(x_, lg_):
            P = jnp.einsum("kij,kjl->kil", pose_delta(x_ * mask[:, None], centres, scale), p_init)
            img, over = render(P, lg_, i, rest, changing)
            return jnp.mean(jnp.abs(blur_with(img, kernels[level]) - targets[level, i])), over

        (loss, over), (gx, gl) = jax.value_and_grad(loss_fn, argnums=(0, 1), has_aux=True)(x, lg)
        ux, sx = opt_x.update(gx, st[0], x)
        ul, sl = opt_l.update(gl, st[1], lg)
        x2 = optax.apply_updates(x, ux)
        lg2 = optax.apply_updates(lg, jnp.where(learn, ul, 0.0)) if learn_members else lg
        bad = over | ~jnp.isfinite(loss)
        keep = lambda a, b: jax.tree_util.tree_map(lambda u, v: jnp.where(bad, v, u), a, b)
        return keep(x2, x), keep(lg2, lg), keep((sx, sl), st), loss, bad

    levels = [(jnp.asarray(lv, jnp.int32), int(n)) for lv, n in enumerate(steps)]
    mov = np.ones((num_objects, t_all - 1), bool) if moving is None else np.asarray(moving, bool)
    eye = np.eye(4, dtype=np.float32)
    n_fit, n_bad = 0, 0
    for n in range(1, t_all):
        mk = mov[:, n - 1]
        poses[:, n] = poses[:, n - 1]
        if not mk.any():
            continue
        prev = poses[:, n - 1]
        vel = np.einsum("kij,kjl->kil", prev, np.linalg.inv(poses[:, n - 2])) if n >= 2 else np.tile(eye, (num_objects, 1, 1))
        vel[~mk] = eye
        starts = [np.einsum("kij,kjl->kil", vel, prev).astype(np.float32), prev]
        if init_poses is not None:  # the earlier fit's pose for the moving objects
            starts.append(np.where(mk[:, None, None], init_poses[:, n], prev).astype(np.float32))
        i = jnp.asarray(n, jnp.int32)
        changing, learn = changing_set(jnp.asarray(mk if only_moving else np.ones_like(mk)))
        # the objects not fitted keep their pose (the same in every start), so one `rest` serves all starts
        rest = render_rest(jnp.asarray(prev), lg, i, changing)
        l0 = [float(first_loss(jnp.asarray(s), lg, i, rest, changing)) for s in starts]
        p_init = starts[int(np.argmin(np.where(np.isfinite(l0), l0, np.inf)))] if np.any(np.isfinite(l0)) else prev
        centres = np.stack([(m_ref[labels == k] @ p_init[k, :3, :3].T + p_init[k, :3, 3]).mean(0)
                            if np.any(labels == k) else p_init[k, :3, 3] for k in range(num_objects)])
        x = jnp.zeros((num_objects, 6), jnp.float32)
        pj, cen, mask = jnp.asarray(p_init), jnp.asarray(centres, jnp.float32), jnp.asarray(mk, jnp.float32)
        for level, count in levels:
            st = (opt_x.init(x), opt_l.init(lg))
            for _ in range(count):
                x, lg, st, _, bad = step(x, lg, st, i, rest, pj, cen, mask, changing, learn, level)
                n_bad += int(bad)
        new = np.asarray(jnp.einsum("kij,kjl->kil", pose_delta(x * mask[:, None], cen, scale), pj))
        poses[:, n] = np.where(np.all(np.isfinite(new), (1, 2))[:, None, None], new, p_init)
        n_fit += 1
        if progress_every > 0 and n_fit % progress_every == 0:
            log(f"photometric tracking: frame {n + 1}/{t_all}, {n_fit} fitted ({time.perf_counter() - t_start:.0f} s)")
    pi = (labels >= 0).astype(np.float64)
    pi[cand] = np.asarray(jax.nn.sigmoid(lg))
    log(f"photometric tracking: {n_fit} of {t_all - 1} frames fitted, {sum(n for _, n in levels)} steps each "
        f"({n_bad} skipped), {time.perf_counter() - t_start:.1f} s")
    return poses, pi


def joint_poses(points, poses, viewmats, Ks, *, huber_px: float = 2.0, revolute_margin: float = 0.95, log=print):
    """Each object's poses replaced by the one articulation that best explains them.

    Args:
        points: list of K arrays [M_k, 3], each object's reference points (M_k >= 3; fewer: kept as is).
        poses: [K, T, 4, 4] per-frame poses (e.g. `track_photometric`'s).
        viewmats, Ks: [T, 4, 4], [T, 3, 3].

    The reference points moved by each frame's pose and projected into that frame's camera are the
    targets of `fit_joint` (revolute and prismatic, amounts per frame from the reference; the initial
    axes: the largest pose's rotation axis or the centroid's largest shift, and the coordinate axes);
    the revolute joint wins when its inlier RMS (pixels) per inlier fraction is below ``revolute_margin``
    times the prismatic one's (a turn about a far pivot mimics a slide), else the prismatic one. Returns (poses [K, T, 4, 4], kinds [K]).
    """
    poses = np.asarray(poses, np.float64)
    out, kinds = poses.copy(), []
    t_all = poses.shape[1]
    vms = np.asarray(viewmats, np.float64)
    Kn = np.asarray(Ks, np.float64)
    for k, pts in enumerate(points):
        pts = np.asarray(pts, np.float64)
        if len(pts) < 3 or t_all < 2:
            kinds.append("kept")
            continue
        moved = np.einsum("tij,mj->tmi", poses[k, :, :3, :3], pts) + poses[k, :, None, :3, 3]  # [T, M, 3]
        uv, ok = _project_rows(jnp.asarray(moved), jnp.asarray(vms), jnp.asarray(Kn))
        tgt = np.asarray(uv)
        w = np.asarray(ok, np.float64)
        rv = np.asarray(geometry.so3_log(jnp.asarray(poses[k, :, :3, :3])))  # [T, 3]
        shift = moved.mean(1) - pts.mean(0)  # [T, 3]
        seed = {"revolute": rv[np.argmax(np.linalg.norm(rv, axis=1))], "prismatic": shift[np.argmax(np.linalg.norm(shift, axis=1))]}
        fits = {}
        for kind in JOINT_KINDS:
            axes = np.eye(3) if np.linalg.norm(seed[kind]) < 1e-9 else np.vstack([seed[kind], np.eye(3)])
            fits[kind] = fit_joint(np.repeat(pts[None], t_all, 0), tgt, w, vms, Kn, kind, axes=axes,
                                   huber_px=huber_px)
        score = {c: fits[c][1] / max(fits[c][2], 1e-3) for c in fits}
        # a turn about a far pivot mimics a slide: the revolute joint has to be clearly better
        kind = "revolute" if score["revolute"] < revolute_margin * score["prismatic"] else "prismatic"
        out[k] = fits[kind][0]
        kinds.append(kind)
        log(f"photometric tracking: object {k + 1}: revolute {fits['revolute'][1]:.2f} px, prismatic "
            f"{fits['prismatic'][1]:.2f} px -> {kind} (axis {np.round(fits[kind][3], 3).tolist()})")
    return out, kinds
