"""Motion bases placed from the flow before they move (``deform.init = "flow"``; DESIGN.md section 1, steps 3-6).

The "bases" field (`fgjax.models.deform`) blends K rigid motions with weights w(X) = softmax(logits(X)); basis 0
is the static scene. Started from random logits, the flow loss drives every weight onto basis 0 within its first
steps (a moving basis's early, random motion only costs on the static pixels, which are most of them), and a
softmax at w_0 ~ 1 passes almost no gradient to a part's other weights: the parts then stay still (docs/benchmarks.md,
"Where the bases' weights sit"). Shape of Motion (Wang et al. 2024) starts its bases from clustered 3D tracks
instead; this is the same idea with the evidence stage 1 already has, at the end of its warm-up:

1. the warm-up model's depth gives each training pair's camera flow u_cam (exact reprojection), and the observed
   flow u minus u_cam marks the moving pixels (`fgjax.method.discover.discover`, |u - u_cam| > 1 px), for the pairs
   of frames each span of ``deform.spans`` apart in time (a part that moves 0.3 px a frame is under the 1 px floor
   between consecutive frames, above it over four: docs/benchmarks.md, "The placement's frame spans");
2. the moving pixels are back-projected onto the canonical Gaussians through the rasterizer's weights and the
   Gaussians that paint mostly moving pixels are selected, span by span (each with its own score threshold), and
   the selections united (with ``deform.place_agree_sigma`` > 0 each pixel weighs by the agreement of the warm-up
   model's render with the image, `fgjax.method.discover.agreement`: the warm-up model does not move the parts, so a
   part's moved pixels are painted by what it covered or uncovered, which renders wrongly there); DBSCAN
   (`fgjax.cluster.cluster_dynamic`, automatic radius) groups them;
3. the logits network is fitted, by class-balanced cross-entropy with label smoothing, to put cluster j
   (largest first, j < K - 1) on basis j + 1 and every unselected Gaussian on basis 0; selected Gaussians that
   DBSCAN calls noise, and clusters beyond K - 1, are left to the training. With per-slot weights
   (``deform.weights = "slot"``) the same targets are written into the slots' logits instead (log of the target),
   every selected Gaussian is freed and every other is held on the static basis (`fgjax.models.deform`), but for
   those near a cluster with ``deform.place_free_eps`` > 0 (`free_near_clusters`), which start static, free.

The bases' motions stay at the identity; the flow loss then fits each basis's motion to the pixels of the part
that sits on it. For ``deform.hold`` steps after the placement only the motions (and pivots, axes) train
(`fgjax.method.stage1`): a basis at the identity passes no gradient to the weights, and from its first non-zero one
Adam moves the logits network by about a full step per iteration (the hash grid's rate is ten times the field's)
in the direction that a motion not yet fitted to its cluster sets; unheld, the placed weights are back on the
static basis 100 steps later (docs/benchmarks.md, "The placed weights held"). The Gaussians labelled static also
give the points whose rigid drift ``deform.gauge`` prices (`static_points`). Nothing here encodes a part's shape
or motion kind.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
from scipy.spatial import cKDTree

from fgjax import cluster
from fgjax.config import Config
from fgjax.gaussians import activate
from fgjax.geometry import viewmat_to_c2w
from fgjax.method.discover import agreement, camera_flow_from_depth, discover
from fgjax.method.flows import estimate_training_flows, previous_frames
from fgjax.models.deform import MOTION_KEYS, DeformSpec, basis_logits
from fgjax.models.model import render_params

__all__ = ["moving_clusters", "free_near_clusters", "basis_targets", "fit_basis_logits", "place_bases", "static_points"]


def moving_clusters(
    params, alive, viewmats, Ks, flows, prev, *, width: int, height: int, capacity: int,
    background=(0.0, 0.0, 0.0), threshold_px: float = 1.0, camera_share: float = 0.0, min_fraction: float = 0.02,
    window: int = 0, times=None, images=None, agree_sigma: float = 0.0, sh_degree: int = 0, noise_sigmas: float = 0.0,
) -> np.ndarray:
    """Label every Gaussian slot: -2 static, -1 dead or moving but DBSCAN noise, j >= 0 moving cluster j (the
    largest first), from the canonical Gaussians (``params["gaussians"]``, no deformation) and the training flows.

    Args:
        params, alive: stage-1 parameters and the live-slot mask [N].
        viewmats [T, 4, 4] (OpenCV world-to-camera), Ks [T, 3, 3]: the training cameras.
        flows: [T, H, W, 2] optical flow into frame i from frame ``prev[i]``, on that frame's grid (NaN: unknown);
            or a sequence of such arrays, one per frame span, whose selections are united.
        prev: [T] the earlier frame of each frame's pair (-1: none; `fgjax.method.flows.previous_frames`); or a
            sequence, one per array of ``flows``.
        width, height, capacity, background: rendering of the canonical model's depth.
        threshold_px: a pixel moves where |u - u_cam| exceeds this many pixels. A fixed floor rather than each pair's
            Otsu threshold: a fast part's large residual puts Otsu's cut above a slow part's (`fgjax.method.discover`).
        camera_share: the floor grows with the pair's camera flow, threshold_px + camera_share |u_cam| per pixel:
            u_cam's error is the canonical depth's relative error times its parallax, and the optical flow's own
            error grows with the displacement, so a moving camera needs more evidence than a still one.
        min_fraction: clusters smaller than this share of the moving Gaussians are noise.
        window: > 0: a Gaussian's score is the best run of this many consecutive pairs of a span, in the order of
            ``times`` (`fgjax.method.discover.windowed_score`), so that a part that moves in a few pairs is not
            diluted by the pairs in which it rests; 0: the score over all pairs.
        times: [T] the frames' times (None: the frames are in time order).
        images, agree_sigma, sh_degree: with ``agree_sigma`` > 0, the training images [T, H, W, 3] in [0, 1]: each
            pixel's back-projection is weighted by the agreement of the canonical model's render (SH up to
            ``sh_degree``) with image ``prev[i]`` (`fgjax.method.discover.agreement`).
        noise_sigmas: > 0: each pair's floor is raised, where lower, to median + noise_sigmas * 1.4826 MAD of the
            pair's |u - u_cam| (`fgjax.method.discover.binarize`): the warm-up depth's camera-flow error on a moving
            camera is a noise level of its own pair, not a share of |u_cam| fixed in advance.
    """
    if agree_sigma > 0 and images is None:
        raise ValueError("moving_clusters: agree_sigma > 0 needs the training images")
    sets = list(zip(flows, prev)) if isinstance(flows, list | tuple) else [(flows, prev)]
    alive_np = np.asarray(alive, bool)
    labels = np.where(alive_np, -2, -1).astype(np.int64)
    dyn = np.zeros_like(alive_np)
    for f, p in sets:
        dyn |= _moving_gaussians(params, alive, viewmats, Ks, f, p, width, height, capacity, background, threshold_px,
                                 camera_share, window, times, images, agree_sigma, sh_degree, noise_sigmas)
    dyn &= alive_np
    if dyn.sum() >= 2:
        labels[dyn] = cluster.cluster_dynamic(np.asarray(params["gaussians"].means)[dyn], auto_eps=True,
                                              min_fraction=min_fraction)
    return labels


def _moving_gaussians(params, alive, viewmats, Ks, flows, prev, width, height, capacity, background, threshold_px,
                      camera_share=0.0, window=0, times=None, images=None, agree_sigma=0.0, sh_degree=0,
                      noise_sigmas=0.0):
    """[N] bool: `discover`'s dynamic Gaussians of one set of pairs (`moving_clusters`)."""
    pairs = [i for i in range(len(prev)) if prev[i] >= 0]
    if times is not None:  # in the time order of their first frames
        pairs = sorted(pairs, key=lambda i: (float(times[prev[i]]), int(prev[i])))
    if not pairs or not np.asarray(alive, bool).any():
        return np.zeros(np.shape(alive), bool)
    g = params["gaussians"]
    quats, scales, opac = activate(g, alive)
    c2w = viewmat_to_c2w(np.asarray(viewmats, np.float64))
    bg = jnp.asarray(background, jnp.float32)
    cam_flows, valid, agree = [], [], []
    gate = agree_sigma > 0
    for i in pairs:
        a = int(prev[i])
        img, alpha, info, _ = render_params(params, alive, jnp.asarray(viewmats[a], jnp.float32),
                                            jnp.asarray(Ks[a], jnp.float32), 0.0, spec=None,
                                            sh_degree=sh_degree if gate else 0, width=width, height=height,
                                            background=bg, capacity=capacity, render_depth=True)
        if gate:
            agree.append(agreement(np.asarray(img), np.asarray(images[a], np.float32), agree_sigma))
        cam, ok = camera_flow_from_depth(np.asarray(info["depth"]), Ks[a], c2w[a], c2w[i])
        cam_flows.append(cam)
        valid.append(ok & (np.asarray(alpha) >= 0.5) & np.all(np.isfinite(flows[i]), axis=-1))
    src = [int(prev[i]) for i in pairs]
    u = np.nan_to_num(np.asarray(flows, np.float32)[pairs])
    cams = np.stack(cam_flows)
    found = discover(np.asarray(g.means), np.asarray(quats), np.asarray(scales), np.asarray(opac),
                     np.asarray(viewmats, np.float32)[src], np.asarray(Ks, np.float32)[src], u, cams,
                     valid=np.stack(valid), capacity=capacity,
                     threshold_px=threshold_px + camera_share * np.linalg.norm(cams, axis=-1)
                     if camera_share > 0 else threshold_px, window=window, noise_sigmas=noise_sigmas,
                     confidence=np.stack(agree) if gate else None)
    return np.asarray(found.dynamic, bool)


def free_near_clusters(means, labels: np.ndarray, factor: float, min_samples: int = 5) -> np.ndarray:
    """`moving_clusters`' labels with every static Gaussian (-2) whose canonical centre lies within ``factor`` times
    the moving Gaussians' automatic DBSCAN radius (`fgjax.cluster.auto_eps` of the clustered centres, k =
    min_samples - 1, as `fgjax.cluster.cluster_dynamic` chooses it) of a clustered Gaussian (label >= 0) relabelled
    -1: started on the static basis, free to leave it. The flow's cut selects about 0.6 of a part's Gaussians
    (docs/benchmarks.md, "Which parts share a cluster"); the rest sit among them, and held static they keep that
    share of the part still. Returns a new array; ``factor`` <= 0 or no cluster returns a copy."""
    out = np.array(labels, copy=True)
    moving = out >= 0
    if factor <= 0 or moving.sum() < max(min_samples, 2) or not (out == -2).any():
        return out
    pts = np.asarray(means, np.float64)
    radius = factor * cluster.auto_eps(pts[moving], max(min_samples - 1, 1))
    static = np.flatnonzero(out == -2)
    dist, _ = cKDTree(pts[moving]).query(pts[static], k=1)
    out[static[dist <= radius]] = -1
    return out


def basis_targets(labels: np.ndarray, num_bases: int, smoothing: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Soft targets [N, K] and class-balanced sample weights [N] for `fit_basis_logits` from `moving_clusters`'
    labels: -2 -> basis 0, cluster j < K - 1 -> basis j + 1 (probability 1 - smoothing, the rest spread evenly),
    anything else weight 0. Each target basis's samples share a total weight of 1."""
    labels = np.asarray(labels)
    basis = np.where(labels == -2, 0, np.where((labels >= 0) & (labels < num_bases - 1), labels + 1, -1))
    target = np.full((len(labels), num_bases), smoothing / max(num_bases - 1, 1), np.float32)
    target[np.arange(len(labels)), np.maximum(basis, 0)] = 1.0 - smoothing
    weight = np.zeros(len(labels), np.float32)
    for k in np.unique(basis[basis >= 0]):
        sel = basis == k
        weight[sel] = 1.0 / sel.sum()
    return target, weight


@functools.partial(jax.jit, static_argnames=("spec", "steps"))
def fit_basis_logits(spec: DeformSpec, deform_params, x, target, weight, *, steps: int = 300, lr: float = 1e-2):
    """Fit the logits network (hash grid and MLP; the bases' motions, MOTION_KEYS, untouched) so that
    softmax(logits(x)) matches ``target`` [N, K] at the canonical centres ``x`` [N, 3]: Adam on the weighted
    cross-entropy sum_i weight_i H(target_i, softmax(logits(x_i))). Returns (the new deform params, the final
    loss)."""
    net = {k: v for k, v in deform_params.items() if k not in MOTION_KEYS}
    fixed = {k: v for k, v in deform_params.items() if k in MOTION_KEYS}
    opt = optax.adam(lr)

    def loss_fn(p):
        logp = jax.nn.log_softmax(basis_logits(spec, {**p, **fixed}, x), axis=-1)
        return -jnp.sum(weight * jnp.sum(target * logp, axis=-1)) / jnp.maximum(jnp.sum(weight), 1e-12)

    def body(carry, _):
        p, s = carry
        loss, g = jax.value_and_grad(loss_fn)(p)
        upd, s = opt.update(g, s, p)
        return (optax.apply_updates(p, upd), s), loss

    (net, _), losses = jax.lax.scan(body, (net, opt.init(net)), None, length=steps)
    return {**net, **fixed}, losses[-1]


def place_bases(cfg: Config, params, alive, spec: DeformSpec, scene, flows=None, *, capacity: int, cache_dir=None,
                log=print):
    """Steps 1-3 of the module docstring on a stage-1 model at the end of its warm-up; returns the new params.
    ``flows``: the pair flows of `fgjax.method.flows.estimate_training_flows` (None: estimated, cached in
    ``cache_dir``). Where the flow shows no moving cluster every live Gaussian goes to the static basis, which is
    what that evidence says. Returns (params, labels) with the labels of `moving_clusters`."""
    spans = cfg.deform.spans  # span 1 can use the given flows
    sets = [flows if s == 1 and flows is not None else
            estimate_training_flows(scene, cfg.flow.method, cache_dir, log=log, span=s) for s in spans]
    labels = moving_clusters(params, alive, scene.viewmats, scene.Ks, sets,
                             [previous_frames(scene.times, s) for s in spans], width=scene.width, height=scene.height,
                             capacity=capacity, background=tuple(cfg.model.background),
                             camera_share=cfg.deform.camera_share, window=cfg.deform.place_window,
                             times=scene.times, images=scene.images, agree_sigma=cfg.deform.place_agree_sigma,
                             sh_degree=cfg.model.sh_degree, noise_sigmas=cfg.deform.place_noise_sigmas)
    if spec.weights == "slot" and cfg.deform.place_free_eps > 0:
        labels = free_near_clusters(params["gaussians"].means, labels, cfg.deform.place_free_eps)
    sizes = np.bincount(labels[labels >= 0]) if (labels >= 0).any() else np.zeros(0, int)
    target, weight = basis_targets(labels, spec.bases)
    free = (labels >= 0) | ((labels == -1) & np.asarray(alive, bool))
    moving = int(np.sum(free))
    if spec.weights == "slot":  # noise and clusters beyond K - 1 start on the static basis, free to leave it
        slots = params["deform"]["slots"]
        deform = {**params["deform"], "slots": {"logits": jnp.asarray(np.log(target), slots["logits"].dtype),
                                                "free": jnp.asarray(free, slots["free"].dtype)}}
        loss = -np.sum(weight * np.sum(target * np.log(target), axis=-1)) / max(float(np.sum(weight)), 1e-12)
    else:
        deform, loss = fit_basis_logits(spec, params["deform"], params["gaussians"].means, jnp.asarray(target),
                                        jnp.asarray(weight))
    placed = sizes.tolist()[:spec.bases - 1]
    log(f"bases placed from the flow: {moving} moving Gaussians, clusters of {placed} on bases 1..{len(placed)}"
        f" (cross-entropy {float(loss):.3f})")
    return {**params, "deform": deform}, labels


def static_points(means, labels: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Up to ``count`` canonical centres of the Gaussians that `moving_clusters` labelled static (-2), drawn without
    replacement (seeded); returns [count, 4]: xyz and 1, rows past the static Gaussians' number zero (fixed shape
    for the jitted step). The points `fgjax.train.losses.rigid_drift_loss` keeps still (``deform.gauge``)."""
    idx = np.flatnonzero(np.asarray(labels) == -2)
    if idx.size > count:
        idx = np.sort(np.random.default_rng(seed).choice(idx, count, replace=False))
    out = np.zeros((count, 4), np.float32)
    out[:idx.size, :3] = np.asarray(means, np.float32)[idx]
    out[:idx.size, 3] = 1.0
    return out
