"""Control network training (DESIGN.md section 1, step 7): f_Θ(E(v_c, X)) -> (ΔX, Δq, Δs).

Θ is fitted in two phases:

(a) distillation: ||ΔG_i(v(t)) - (G_i(t) - G_i(t0))||² over the training times, with the geometry of the
    trajectories as teacher (the stage-1 deformation field in the paper's chain; the tracked rigid poses in the
    articulated variant); no rendering;
(b) photometric: 0.8 L1 + 0.2 (1 - SSIM) of controlled renders with v = v_c(t, ·) against the training images,
    plus beta L_uGS (`fgjax.flow.gaussian_flow_loss`) of consecutive frames: the controlled scene at v_c(t-1, ·) and
    v_c(t, ·), both seen by camera t-1, against the observed flow.

Opacities and colours are the reference scene's and are not trained.
"""

from __future__ import annotations

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from fgjax.config import Stage2Config
from fgjax.flow import gaussian_flow_loss
from fgjax.gaussians import Gaussians, activate
from fgjax.method.result import LoadedRun, controlled_gaussians, render_capacity, with_geometry, with_refit
from fgjax.models.control_net import ControlNet, control_apply, control_init
from fgjax.models.model import render_params
from fgjax.train.losses import photometric_loss
from fgjax.train.optim import guarded_step

__all__ = ["train_control"]


def _control_hparams(cfg: Stage2Config, x_scale: float, v_scale: float) -> dict[str, Any]:
    """The control network's hyper-parameters (`fgjax.models.control_net.control_init`'s keywords)."""
    return {"encoding": cfg.control_encoding, "hidden": cfg.hidden, "depth": cfg.depth, "n_freqs_x": cfg.n_freqs_x,
            "n_freqs_v": cfg.n_freqs_v, "x_scale": float(x_scale), "v_scale": float(v_scale)}


def train_control(run: LoadedRun, scene, order, labels: np.ndarray, traj: np.ndarray, cfg: Stage2Config,
                   centres_q_s, flows=None, log=print,
                   refit: Gaussians | None = None) -> tuple[ControlNet, dict[str, Any]]:
    """Fit Θ (module docstring): distillation, then ``cfg.photo_steps`` of the photometric loss plus beta L_uGS.

    Args:
        run: the loaded stage-1 run.
        scene: the training scene; ``order`` [T]: its frames in time order.
        labels: [N] cluster ids (-1: not controlled).
        traj: [K, T, 3] trajectories ς(t, k) at the training times.
        cfg: `Stage2Config` (network size, steps, rates, beta).
        centres_q_s: the teacher geometry over time (means [T, N, 3], raw quats [T, N, 4], log-scales [T, N, 3]).
        flows: [T-1, H, W, 2] observed flow between consecutive frames in time order (None: no flow term).
        refit: the re-fitted reference Gaussians whose opacities and colours the renders use (None: stage 1's).

    Returns:
        (`ControlNet`, statistics of both phases).
    """
    k = traj.shape[0]
    canonical = run.state.params["gaussians"].means  # the control network's input X
    params = with_refit(run.state.params, refit)  # whose opacities and colours the renders use
    sel = np.flatnonzero(labels >= 0)
    ext = float(np.max(np.abs(np.asarray(canonical)[sel] - np.asarray(canonical)[sel].mean(0)))) if len(sel) else 1.0
    v_all = traj - traj[:, :1]  # [K, T, 3]
    v_scale = float(max(np.max(np.linalg.norm(v_all, axis=-1), initial=0.0), 1e-3))
    hp = _control_hparams(cfg, x_scale=max(2.0 * ext, 1e-3), v_scale=v_scale)
    control = control_init(jax.random.key(cfg.seed), **hp)
    stats: dict[str, Any] = {"control": hp}
    if len(sel) == 0 or k == 0:
        return control, stats
    means_t, quats_t, ls_t = centres_q_s  # [T, N, ...] in time order
    lab_sel = jnp.asarray(labels[sel])
    x_sel = canonical[sel]
    tgt = (jnp.asarray(means_t[:, sel] - means_t[:1, sel]), jnp.asarray(quats_t[:, sel] - quats_t[:1, sel]),
           jnp.asarray(ls_t[:, sel] - ls_t[:1, sel]))  # [T, M, ...]
    v_t = jnp.asarray(v_all.transpose(1, 0, 2), jnp.float32)  # [T, K, 3]
    opt = optax.adam(cfg.lr)

    def offsets(ctrl, vecs):  # vecs [K, 3] -> offsets of the selected Gaussians
        z = jnp.zeros((len(sel), 3), jnp.float32)
        v = vecs[lab_sel]
        a = control_apply(ctrl, v, x_sel)
        b = control_apply(ctrl, z, x_sel)
        return tuple(u - w for u, w in zip(a, b, strict=True))

    def distill_loss(ctrl, ti):  # ti [B]: a minibatch of training times
        d = jax.vmap(lambda vv: offsets(ctrl, vv))(v_t[ti])
        scale2 = v_scale ** 2
        return (jnp.mean(jnp.sum((d[0] - tgt[0][ti]) ** 2, -1)) / scale2
                + jnp.mean(jnp.sum((d[1] - tgt[1][ti]) ** 2, -1)) + jnp.mean(jnp.sum((d[2] - tgt[2][ti]) ** 2, -1)))

    @jax.jit
    def distill_step(ctrl, st, ti):
        loss, gr = jax.value_and_grad(distill_loss)(ctrl, ti)
        up, st = opt.update(gr, st, ctrl)
        return optax.apply_updates(ctrl, up), st, loss

    t0 = time.perf_counter()
    st = opt.init(control)
    loss = jnp.nan
    first = None
    n_t = int(v_t.shape[0])
    bsz = min(cfg.distill_batch, n_t)
    rng_d = np.random.default_rng(cfg.seed + 1)
    for i in range(cfg.distill_steps):
        ti = jnp.asarray(rng_d.choice(n_t, size=bsz, replace=False), jnp.int32)
        control, st, loss = distill_step(control, st, ti)
        if i == 0:
            first = float(loss)
    stats["distill"] = {"steps": cfg.distill_steps, "loss_first": first, "loss_last": float(loss),
                        "time_s": time.perf_counter() - t0}
    log(f"stage 2: distillation {cfg.distill_steps} steps, loss "
        f"{'-' if first is None else format(first, '.3g')} -> {float(loss):.3g} "
        f"({time.perf_counter() - t0:.1f} s)")
    if cfg.photo_steps <= 0:
        return control, stats
    # photometric fine-tuning of Θ only

    base = (jnp.asarray(means_t[0]), jnp.asarray(quats_t[0]), jnp.asarray(ls_t[0]))
    labels_j = jnp.asarray(labels)
    bg = jnp.asarray(run.cfg.model.background, jnp.float32)
    cap = render_capacity(run)
    images = jnp.asarray(scene.images[order])
    vms = jnp.asarray(scene.viewmats[order], jnp.float32)
    Ks = jnp.asarray(scene.Ks[order], jnp.float32)
    lam = float(run.cfg.train.lambda_dssim)
    opt2 = optax.adam(cfg.lr * 0.25)

    beta = float(cfg.flow_weight) if flows is not None and len(order) > 1 else 0.0
    if beta > 0:
        flows_j = jnp.asarray(np.asarray(flows, np.float32))  # [T-1, H, W, 2]: order[j] -> order[j + 1]
    alive = run.state.densify.alive

    def photo_loss(ctrl, i):
        geo = controlled_gaussians(ctrl, base, canonical, labels_j, v_t[i])
        p = with_geometry(params, *geo)
        img, _, info, _ = render_params(p, alive, vms[i], Ks[i], 0.0, spec=None,
                                        sh_degree=run.cfg.model.sh_degree, width=scene.width, height=scene.height,
                                        background=bg, capacity=cap, tile_size=run.cfg.train.tile_size)
        loss, over = photometric_loss(img, images[i], lam), info["overflow"]
        if beta > 0:  # L_uGS of the pair (i - 1, i) in time order: the controlled scene at both vectors

            j = jnp.maximum(i - 1, 0)
            geo0 = controlled_gaussians(ctrl, base, canonical, labels_j, v_t[j])
            q0, s0, o0 = activate(with_geometry(params, *geo0)["gaussians"], alive)
            lf, of = gaussian_flow_loss(geo0[0], q0, s0, o0, geo[0], vms[j], vms[i], Ks[j], flows_j[j],
                                        scene.width, scene.height, capacity=cap,
                                        threshold=cfg.flow_threshold if cfg.flow_threshold > 0 else None,
                                        tile_size=run.cfg.train.tile_size)
            loss = loss + beta * jnp.where(i > 0, lf, 0.0)
            over = over | of
        return loss, over

    photo_step = guarded_step(photo_loss, opt2)

    t1 = time.perf_counter()
    st = opt2.init(control)
    rng = np.random.default_rng(cfg.seed)
    losses, n_bad = [], 0
    for _ in range(cfg.photo_steps):
        control, st, loss, bad = photo_step(control, st, jnp.asarray(rng.integers(len(order)), jnp.int32))
        losses.append(loss)
        n_bad += int(bad)
    losses = [float(x) for x in losses]
    stats["photometric"] = {"steps": cfg.photo_steps, "loss_first": losses[0],
                            "loss_last_10": float(np.mean(losses[-10:])),
                            "skipped_steps": n_bad, "time_s": time.perf_counter() - t1, "flow_weight": beta}
    log(f"stage 2: photometric {cfg.photo_steps} steps, loss {losses[0]:.4f} -> {np.mean(losses[-10:]):.4f} "
        f"({n_bad} skipped, {time.perf_counter() - t1:.1f} s)")
    return control, stats
