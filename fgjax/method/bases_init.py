"""The motion bases' weights initialised from the flow (``deform.bases_init = "flow"``; issue 53, item 2).

Shape of Motion (Wang et al. 2024) starts its motion bases from tracks clustered by their motion; here the parts are
found the way stage 2 finds them (DESIGN.md section 1, steps 5 and 6), once, on the static model of the warm-up:

1. for each consecutive training pair (a, b) in time order, the camera flow u_cam of frame a is the exact
   reprojection of the warm-up model's rendered depth from camera a to camera b (`fgjax.flow.reprojection_flow`),
   and the moving pixels are those where the optical flow u departs from it (`fgjax.method.discover.discover`:
   |u - u_cam| above Otsu's threshold with a floor, pixels where the model's alpha >= 0.5);
2. each Gaussian's score is the share of what it paints that lies on moving pixels, thresholded (Otsu);
3. the selected centres are grouped by DBSCAN (`fgjax.cluster.cluster_dynamic`) with its radius read from their
   k-distance curve (`fgjax.cluster.auto_eps`: the warm-up's Gaussians are sparser and noisier than a trained
   model's, and the radius must not depend on the scene's units); the K-1 largest groups become parts 1..K-1,
   everything not selected part 0 (the static basis). A group that does not move costs nothing: its basis stays
   at the identity;
4. the weight network w(X) = softmax(logits(X)) (hash grid + MLP, `fgjax.models.deform`) is fitted to these labels
   by class-balanced cross-entropy against smoothed one-hot targets (each class weighs the same, whatever its size;
   the target is 1 - s on the label and s / (K - 1) on each other basis, so the logits stay finite and training can
   still move a point between bases); selected Gaussians outside the kept groups (DBSCAN noise, smaller groups) do
   not enter the fit. Each part's basis pivot c_k goes to its group's centroid, so that its rotation turns the part
   about a point of the part rather than the scene's origin. Motions stay at the identity: the flow losses learn
   them.

The options are those of stage 2's discovery and clustering (`fgjax.config.Stage2Config`'s defaults, with
``auto_eps``). The warm-up must leave a model whose depth is good enough for u_cam (``train.warmup_steps``).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Float, Int

from fgjax import cluster
from fgjax import flow as fl
from fgjax.config import Stage2Config
from fgjax.gaussians import activate
from fgjax.geometry import viewmat_to_c2w
from fgjax.method.discover import discover
from fgjax.method.flows import estimate_training_flows, previous_frames
from fgjax.models.deform import DeformSpec, basis_logits
from fgjax.models.model import render_params

__all__ = ["flow_part_labels", "fit_basis_weights", "init_bases_from_flow"]


def flow_part_labels(
    params, alive, scene, flows: Float[np.ndarray, "T H W 2"], prev: Int[np.ndarray, " T"], *, parts: int,
    capacity: int | None, background=(0.0, 0.0, 0.0), opts: Stage2Config | None = None,
) -> tuple[Int[np.ndarray, " N"], int]:
    """Labels of the warm-up model's Gaussians (steps 1-3 of the module docstring): 0 static, 1..``parts`` the moving
    groups by decreasing size, -1 selected as moving but in no kept group (or not alive). Returns (labels, the number
    of moving Gaussians selected).

    Args:
        params: stage-1 parameters ({"gaussians", ...}); the deformation field is not applied (the warm-up model).
        alive: [N] bool.
        scene: the training `Scene`.
        flows: [T, H, W, 2] optical flow into each frame from ``prev`` of it, on the predecessor's grid (NaN where
            unknown; `fgjax.method.flows.estimate_training_flows`).
        prev: [T] index of each frame's predecessor in time (-1 for the first).
        parts: the most groups kept (the bases besides the static one).
        capacity: the rasterizer's intersection capacity.
        opts: discovery and clustering options (None: `Stage2Config(auto_eps=True)`).
    """
    o = Stage2Config(auto_eps=True) if opts is None else opts
    alive_np = np.asarray(alive, bool)
    n = alive_np.shape[0]
    pairs = [(int(a), i) for i, a in enumerate(np.asarray(prev)) if a >= 0]
    labels = np.zeros(n, np.int64)
    if not pairs:
        return np.where(alive_np, 0, -1), 0
    c2w = viewmat_to_c2w(np.asarray(scene.viewmats, np.float64))
    bg = jnp.asarray(background, jnp.float32)
    cams, valid = [], []
    for a, b in pairs:
        _, alpha, info, _ = render_params(params, alive, jnp.asarray(scene.viewmats[a], jnp.float32),
                                          jnp.asarray(scene.Ks[a], jnp.float32), 0.0, spec=None, sh_degree=0,
                                          width=scene.width, height=scene.height, background=bg, capacity=capacity,
                                          render_depth=True)
        cam, ok = fl.reprojection_flow(np.asarray(info["depth"], np.float64), scene.Ks[a], c2w[a], c2w[b])
        cams.append(np.asarray(cam, np.float32))
        valid.append(np.asarray(ok) & (np.asarray(alpha) >= o.min_alpha) & np.all(np.isfinite(flows[b]), -1))
    q, s, op = activate(params["gaussians"], alive)
    idx_a = np.array([a for a, _ in pairs])
    thr = o.threshold_px if o.threshold_px == "otsu" else float(o.threshold_px)
    disc = discover(np.asarray(params["gaussians"].means), np.asarray(q), np.asarray(s), np.asarray(op),
                    np.asarray(scene.viewmats)[idx_a], np.asarray(scene.Ks)[idx_a],
                    np.nan_to_num(np.stack([flows[b] for _, b in pairs])), np.stack(cams), valid=np.stack(valid),
                    threshold_px=thr, min_px=o.min_px, score_threshold=o.score_threshold, min_score=o.min_score,
                    capacity=capacity)
    dyn = disc.dynamic & alive_np
    groups = cluster.cluster_dynamic(np.asarray(params["gaussians"].means)[dyn], o.cluster_method, eps=o.eps,
                                     min_samples=o.min_samples, min_fraction=o.min_fraction, auto_eps=o.auto_eps)
    labels[dyn] = np.where((groups >= 0) & (groups < parts), groups + 1, -1)
    labels[~alive_np] = -1
    return labels, int(dyn.sum())


@functools.partial(jax.jit, static_argnames=("spec", "steps", "lr", "smooth"))
def fit_basis_weights(spec: DeformSpec, dparams, means: Float[jax.Array, "N 3"], labels: Int[jax.Array, " N"], *,
                      steps: int = 300, lr: float = 1e-2, smooth: float = 0.1) -> tuple[Any, jax.Array]:
    """Fit the "bases" field's weight network (hash grid, MLP and head) so that softmax(logits(X_i)) matches each
    labelled point's smoothed one-hot target (module docstring, step 4; labels -1 are left out), by Adam on the
    class-balanced cross-entropy. The motions and pivots are returned unchanged. Returns (params, final loss)."""
    k = spec.bases
    use = labels >= 0
    lab = jnp.where(use, labels, 0)
    target = jax.nn.one_hot(lab, k) * (1.0 - smooth - smooth / (k - 1)) + smooth / (k - 1)
    counts = jnp.zeros(k).at[lab].add(use.astype(jnp.float32))
    present = jnp.sum(counts > 0)
    wts = jnp.where(use, 1.0 / jnp.maximum(counts[lab], 1.0), 0.0) / jnp.maximum(present, 1)  # sums to 1
    net_keys = ("layers", "head", "grid")
    net = {key: dparams[key] for key in net_keys}

    def loss_fn(p):
        logp = jax.nn.log_softmax(basis_logits(spec, {**dparams, **p}, means), axis=-1)
        return -jnp.sum(wts * jnp.sum(target * logp, axis=-1))

    opt = optax.adam(lr)

    def body(carry, _):
        p, st = carry
        loss, g = jax.value_and_grad(loss_fn)(p)
        upd, st = opt.update(g, st, p)
        return (optax.apply_updates(p, upd), st), loss

    (net, _), losses = jax.lax.scan(body, (net, opt.init(net)), None, length=steps)
    return {**dparams, **net}, losses[-1]


def init_bases_from_flow(params, alive, spec: DeformSpec, scene, flows: Float[np.ndarray, "T H W 2"] | None, *,
                         method: str, capacity: int | None, background=(0.0, 0.0, 0.0),
                         cache_dir: str | Path | None = None, log=print) -> dict[str, Any]:
    """The "bases" field's parameters initialised from the flow (module docstring): returns params["deform"] with
    the weight network fitted to the parts found and each part's pivot at its centroid. ``flows``: optical flow
    into each frame from its predecessor in time (`fgjax.method.flows.estimate_training_flows`; None: estimated
    here with ``method``, cached in ``cache_dir``). With no part found the field is returned unchanged (the log
    says so)."""
    if spec.kind != "bases":
        raise ValueError(f"deform.bases_init = 'flow' needs deform.kind = 'bases'; got {spec.kind!r}")
    if flows is None:
        flows = estimate_training_flows(scene, method, cache_dir, log=log)
    labels, n_dyn = flow_part_labels(params, alive, scene, flows, previous_frames(scene.times), parts=spec.bases - 1,
                                     capacity=capacity, background=background)
    sizes = [int(np.sum(labels == j)) for j in range(1, spec.bases)]
    found = [z for z in sizes if z > 0]
    if not found:
        log(f"motion bases from the flow: {n_dyn} moving Gaussians, no part found; the bases start as they were")
        return params["deform"]
    means = np.asarray(params["gaussians"].means, np.float32)
    pivot = np.asarray(params["deform"]["pivot"]).copy()
    for j, z in enumerate(sizes):
        if z:
            pivot[j] = means[labels == j + 1].mean(axis=0)
    dparams = {**params["deform"], "pivot": jnp.asarray(pivot, params["deform"]["pivot"].dtype)}
    dparams, loss = fit_basis_weights(spec, dparams, jnp.asarray(means), jnp.asarray(labels))
    log(f"motion bases from the flow: {n_dyn} moving Gaussians, parts of {found} Gaussians on bases "
        f"1-{len(found)}; weights fitted (cross-entropy {float(loss):.3f})")
    return dparams
