"""Re-fitting the reference Gaussians to the training images under the tracked rigid motion, with relabelling.

Stage 1's deformation field paints a part's states as a blur that its time dependence hides frame by frame; moved
rigidly by the tracked poses, that blur would be carried into every controlled state. `refit_gaussians` optimises
every Gaussian's parameters with stage 1's photometric loss on frame i rendered with each object moved by its pose
T_k(t_i) (`fgjax.models.posed.transform_gaussians`), and can first decide, for each Gaussian near a part, whether it
moves with it (`refit_gaussians`' relabelling).
"""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Float, Int

from fgjax.articulate.phototrack import mixed_copies, relabel_candidates, soft_members
from fgjax.data.scene import Scene
from fgjax.gaussians import Gaussians
from fgjax.method.result import LoadedRun, reference_scene, render_capacity
from fgjax.models.model import render_params, scene_extent
from fgjax.models.posed import transform_gaussians
from fgjax.train.losses import photometric_loss
from fgjax.train.optim import OptimSpec, guarded_step, guarded_update, make_optimizer

__all__ = ["posed_frame_loss", "posed_losses", "refit_gaussians"]


def posed_frame_loss(g: Gaussians, alive, labels, pose, viewmat, K, image, background, *, sh_degree: int,
                      width: int, height: int, capacity: int | None, tile_size: int, lam: float):
    """(stage 1's photometric loss of ``image`` [H, W, 3] against `g` (raw parameters) with each object moved by its
    pose (``pose`` [K, 4, 4]; ``labels`` [N], -1 static) seen by one camera, whether the render overflowed)."""

    m, q = transform_gaussians(g.means, g.quats, labels, pose)
    img, _, info, _ = render_params({"gaussians": Gaussians(m, g.log_scales, q, g.opacity_logits, g.sh)}, alive,
                                    viewmat, K, 0.0, spec=None, sh_degree=sh_degree, width=width, height=height,
                                    background=background, capacity=capacity, tile_size=tile_size)
    return photometric_loss(img, image, lam), info["overflow"]


@functools.partial(jax.jit, static_argnames=("sh_degree", "width", "height", "capacity", "tile_size", "lam"))
def _posed_loss(g: Gaussians, alive, labels, pose, viewmat, K, image, background, **kw):
    """`posed_frame_loss`'s loss, inf where the render overflows or the loss is not finite. Jitted once for all
    the scenes and poses of a shape."""
    loss, over = posed_frame_loss(g, alive, labels, pose, viewmat, K, image, background, **kw)
    return jnp.where(jnp.isfinite(loss) & ~over, loss, jnp.inf)


def posed_losses(run: LoadedRun, scene: Scene, order: Int[np.ndarray, " T"], gs: Gaussians,
                 labels: Int[np.ndarray, " N"], poses: Float[np.ndarray, "K T 4 4"], frames):
    """[F] stage 1's photometric loss of each training frame in ``frames`` (time order) rendered from `gs` (raw
    parameters) with each object moved by its pose (``poses`` [K, T, 4, 4]); inf where the render overflows."""
    g = jax.tree_util.tree_map(jnp.asarray, gs)
    args = (jnp.asarray(run.state.densify.alive), jnp.asarray(labels, jnp.int32))
    bg = jnp.asarray(run.cfg.model.background, jnp.float32)
    kw = dict(sh_degree=int(run.cfg.model.sh_degree), width=int(scene.width), height=int(scene.height),
              capacity=render_capacity(run), tile_size=int(run.cfg.train.tile_size),
              lam=float(run.cfg.train.lambda_dssim))
    return np.array([float(_posed_loss(g, *args, jnp.asarray(poses[:, f], jnp.float32),
                                       jnp.asarray(scene.viewmats[order[f]], jnp.float32),
                                       jnp.asarray(scene.Ks[order[f]], jnp.float32),
                                       jnp.asarray(scene.images[order[f]]), bg, **kw))
                     for f in np.asarray(frames, np.int64).reshape(-1)])


@functools.lru_cache(maxsize=16)
def _refit_optimizer(steps: int, scene_extent: float, num_sh_coeffs: int, lr_scale: float):
    """`refit_gaussians`' optimiser: stage 1's groups and rates (decaying over ``steps``) times ``lr_scale``.
    Memoised (it is a pure function of its arguments), so that the re-fits of one configuration, e.g. a hinge
    trial's candidates, share one compiled `_posed_refit_step`."""

    # Adam's update is linear in its learning rate: scaling the update scales every group's rate and schedule
    return optax.chain(make_optimizer(OptimSpec(steps=steps, scene_extent=scene_extent), num_sh_coeffs),
                       optax.scale(lr_scale))


@functools.partial(jax.jit, static_argnames=("opt", "sh_degree", "width", "height", "capacity", "tile_size", "lam"))
def _posed_refit_step(p, st, i, labels, poses, viewmats, Ks, images, background, alive, *, opt, **kw):
    """`guarded_update` of `posed_frame_loss` on training frame i (time order) with each object moved by its
    pose (``poses`` [K, T, 4, 4]). Everything but the optimiser and the render's settings is an argument, so one
    compiled step serves every re-fit of a shape."""

    def loss_fn(p_, i_):
        return posed_frame_loss(p_["gaussians"], alive, labels, poses[:, i_], viewmats[i_], Ks[i_], images[i_],
                                 background, **kw)

    return guarded_update(loss_fn, opt, p, st, i)


def refit_gaussians(run: LoadedRun, scene: Scene, order: Int[np.ndarray, " T"], labels: Int[np.ndarray, " N"],
                    poses: Float[np.ndarray, "K T 4 4"], steps: int, *, seed: int = 0,
                    relabel_steps: int = 0, relabel_radius: float = 0.1, relabel_lr: float = 0.05,
                    init: Gaussians | None = None, lr_scale: float = 1.0, frames=None,
                    log=print) -> tuple[Gaussians, np.ndarray]:
    """Re-fit the reference Gaussians (stage 1 at t0, or ``init``: an earlier re-fit's) to the training
    images under the tracked motion.

    Stage 1's deformation field moves the parts only a little (`fgjax bench motion`), so their Gaussians are a blur
    of their states that the field's time dependence hides frame by frame; moved rigidly by the tracked poses they
    would carry that blur into every state. Here every Gaussian's parameters (centres, scales, rotations, opacities,
    SH) are optimised with the photometric loss of stage 1 on frame i rendered with each object moved by its pose
    T_k(t_i) (`fgjax.models.posed.transform_gaussians`; static Gaussians stay), with stage 1's optimiser groups and
    learning rates (decaying over `steps`), all times ``lr_scale``. No densification. A step whose render
    overflows the tile capacity or whose loss is not finite is skipped.

    Relabelling (the first ``relabel_steps`` of the steps): discovery labels a part by where its residual
    flow is large, so a door's hinge side is missed and static surfaces next to a part can join it. Each
    candidate, a Gaussian within ``relabel_radius`` (scene units, at t0) of a cluster's members, is then
    rendered twice: moved with its nearest cluster k_g with opacity sigma(o) pi_g, and static with
    opacity sigma(o) (1 - pi_g), pi_g = sigmoid(l_g) (l_g starts at +2 for members, -2 for the others,
    and is trained with Adam at ``relabel_lr``). Where k_g's pose differs from the reference the two copies
    part, and the photometric loss keeps the one that is where the image shows it. Afterwards a candidate
    joins k_g when pi_g > 0.5 and is static otherwise; the remaining steps re-fit with those labels.
    Those steps draw frames in which some object is away from its reference pose (all frames when none).

    ``frames``: the training frames (time order) the steps draw from; None: all.

    Returns:
        (`Gaussians` (numpy leaves) of the reference scene, labels [N] after relabelling (the input labels
        when ``relabel_steps`` is 0)).
    """

    t_start = time.perf_counter()
    ref = reference_scene(run, float(scene.times[order[0]])) if init is None else init
    params = {"gaussians": jax.tree_util.tree_map(jnp.asarray, ref)}
    alive = run.state.densify.alive
    pj = jnp.asarray(poses, jnp.float32)  # [K, T, 4, 4]
    images = jnp.asarray(scene.images[order])
    vms = jnp.asarray(scene.viewmats[order], jnp.float32)
    Ks = jnp.asarray(scene.Ks[order], jnp.float32)
    bg = jnp.asarray(run.cfg.model.background, jnp.float32)
    cap = render_capacity(run)
    lam = float(run.cfg.train.lambda_dssim)
    opt = _refit_optimizer(max(int(steps), 1), float(scene_extent(scene.viewmats)), int(ref.sh.shape[1]),
                           float(lr_scale))

    def photo(gs: Gaussians, alive_, i):
        """(photometric loss, overflow) of training frame i (time order) rendered from `gs` as given."""
        img, _, info, _ = render_params({"gaussians": gs}, alive_, vms[i], Ks[i], 0.0, spec=None,
                                        sh_degree=run.cfg.model.sh_degree, width=scene.width, height=scene.height,
                                        background=bg, capacity=cap, tile_size=run.cfg.train.tile_size)
        return photometric_loss(img, images[i], lam), info["overflow"]

    st = opt.init(params)
    rng = np.random.default_rng(seed + 2)
    losses, n_bad = [], 0
    n_rel = min(int(relabel_steps), int(steps))
    labels = np.asarray(labels, np.int64)
    if n_rel > 0 and labels.max(initial=-1) >= 0:
        params, st, labels, info = _relabel(params, st, opt, labels, np.asarray(poses), photo, alive, n_rel,
                                            relabel_radius, relabel_lr, rng)
        losses += info.pop("losses")
        n_bad += info.pop("skipped")
        log(f"stage 2: relabelled by motion in {n_rel} steps: {info}")
    else:
        n_rel = 0
    lab, alive_j = jnp.asarray(labels), jnp.asarray(alive)
    kw = dict(opt=opt, sh_degree=int(run.cfg.model.sh_degree), width=int(scene.width), height=int(scene.height),
              capacity=cap, tile_size=int(run.cfg.train.tile_size), lam=lam)
    step = functools.partial(_posed_refit_step, **kw)
    pool = np.arange(len(order)) if frames is None else np.asarray(frames, np.int64).reshape(-1)
    if len(pool) == 0 or pool.min() < 0 or pool.max() >= len(order):
        raise ValueError(f"refit_gaussians: frames must be indices into the {len(order)} training frames, got "
                         f"{pool.tolist()}")
    for _ in range(int(steps) - n_rel):
        params, st, loss, bad = step(params, st, jnp.asarray(pool[rng.integers(len(pool))], jnp.int32), lab, pj, vms,
                                     Ks, images, bg, alive_j)
        losses.append(loss)
        n_bad += int(bad)
    if losses:
        losses = [float(x) for x in losses]
        log(f"stage 2: re-fitted the Gaussians under the tracked motion, {steps} steps, loss "
            f"{np.mean(losses[:10]):.4f} -> {np.mean(losses[-10:]):.4f} ({n_bad} skipped, "
            f"{time.perf_counter() - t_start:.1f} s)")
    return jax.tree_util.tree_map(np.asarray, params["gaussians"]), labels


def _paired(a: optax.GradientTransformation, b: optax.GradientTransformation) -> optax.GradientTransformation:
    """`a` on the first element of a (params, params) pair, `b` on the second."""

    def init(p):
        return a.init(p[0]), b.init(p[1])

    def update(u, s, p=None):
        ua, sa = a.update(u[0], s[0], None if p is None else p[0])
        ub, sb = b.update(u[1], s[1], None if p is None else p[1])
        return (ua, ub), (sa, sb)

    return optax.GradientTransformation(init, update)


def _relabel(params, st, opt, labels, poses, photo, alive, steps, radius, lr, rng):
    """The relabelling phase of `refit_gaussians` (``photo(gaussians, alive, i)``: its render and loss of
    frame i): (params, opt state, new labels [N], info)."""

    g0 = params["gaussians"]
    cand, k_c = relabel_candidates(np.asarray(g0.means), labels, np.asarray(alive), float(radius))
    lab_m, cj, alive2, logits0 = soft_members(labels, cand, k_c, alive)  # the first copy moves with k_c
    pj = jnp.asarray(poses, jnp.float32)

    def loss_mixed(p_lg, i):
        p, lg = p_lg
        g = p["gaussians"]
        m, q = transform_gaussians(g.means, g.quats, lab_m, pj[:, i])
        both = mixed_copies(g, m, q, cj, lg)
        return photo(both, alive2, i)

    opt_l = optax.adam(lr)
    step = guarded_step(loss_mixed, _paired(opt, opt_l))
    # frames where some object is away from its reference pose: only there do the two copies part
    away = np.any(np.abs(poses - np.eye(4)).reshape(poses.shape[0], poses.shape[1], -1).max(-1) > 1e-4, axis=0)
    frames = np.flatnonzero(away) if away.any() else np.arange(poses.shape[1])
    p_lg, st_pair = (params, logits0), (st, opt_l.init(logits0))
    losses, n_bad = [], 0
    for _ in range(int(steps)):
        p_lg, st_pair, loss, bad = step(p_lg, st_pair, jnp.asarray(rng.choice(frames), jnp.int32))
        losses.append(loss)
        n_bad += int(bad)
    (params, lg), st = p_lg, st_pair[0]
    pi = np.asarray(jax.nn.sigmoid(lg))
    new = labels.copy()
    new[cand] = np.where(pi > 0.5, k_c, -1)
    for k in range(int(labels.max()) + 1):  # a cluster is never emptied: it keeps its members then
        if not np.any(new == k):
            new[labels == k] = k
    info = {"candidates": int(len(cand)), "joined": int(np.sum((labels[cand] < 0) & (new[cand] >= 0))),
            "left": int(np.sum((labels[cand] >= 0) & (new[cand] < 0))), "frames": int(len(frames)),
            "losses": losses, "skipped": n_bad}
    return params, st, new, info
