"""Is the scene static? Stage 1 asks once, after its warm-up; a static scene trains without the deformation field
(a scene that does not need the dynamic branch does not pay for it)."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np

from fgjax import flow as fl
from fgjax.config import Config
from fgjax.data.opticalflow import estimate_flow
from fgjax.geometry import viewmat_to_c2w
from fgjax.models.model import render_params
from fgjax.viz import to_u8

__all__ = ["detect_static", "flow_motion_score"]


def detect_static(params, alive, scene, cfg: Config, capacity: int, cache_dir: Path | None = None
                  ) -> tuple[bool, float]:
    """Static-scene test after the warm-up (no deformation yet), on two kinds of evidence; static only when both say
    so. (1) Photometric: a static model of a dynamic scene leaves localised residual blobs; the score is the largest
    fraction over frames of pixels whose error exceeds max(0.1, 4 x the frame's median). (2) Flow
    (`flow_motion_score`): the share of pixels whose optical flow departs from the flow the camera alone causes.
    Returns (static, the larger score); static when it is below ``static.threshold``."""
    bg = jnp.asarray(cfg.model.background, jnp.float32)
    score = 0.0
    idx = np.linspace(0, scene.num_frames - 1, min(scene.num_frames, 12)).round().astype(int)
    for i in idx:
        img, _, _, _ = render_params(params, alive, jnp.asarray(scene.viewmats[i], jnp.float32),
                                     jnp.asarray(scene.Ks[i], jnp.float32), 0.0, spec=None, sh_degree=0,
                                     width=scene.width, height=scene.height, background=bg, capacity=capacity)
        err = np.abs(np.asarray(img) - scene.images[i]).max(-1)
        thr = max(0.1, 4.0 * float(np.median(err)))  # relative: an unconverged model errs everywhere
        score = max(score, float(np.mean(err > thr)))
    if score < cfg.static.threshold and scene.num_frames >= 2:  # the photometric test alone would call it static
        score = max(score, flow_motion_score(params, alive, scene, cfg, capacity, cache_dir))
    return score < cfg.static.threshold, score


def flow_motion_score(params, alive, scene, cfg: Config, capacity: int, cache_dir: Path | None = None,
                      pairs: int = 12, min_px: float = 2.0, k: float = 3.0) -> float:
    """Largest share, over up to ``pairs`` consecutive frame pairs (time order), of the pixels where the observed
    optical flow u (``flow.method``, cached in ``cache_dir``) departs from the camera flow u_cam by more than
    max(``min_px``, ``k`` x the pair's median departure): u_cam is the exact reprojection of the static model's
    rendered depth (`fgjax.flow.reprojection_flow`), over the pixels it covers (alpha >= 0.5). Parts that move make
    such pixels whatever their colours; a static scene seen by correct cameras makes few: ``min_px`` sits above the
    OpenCV estimators' end-point error on textured frames (docs/benchmarks.md, "Optical flow"), and the median
    absorbs an error common to the whole frame (of the flow, the warm-up model's depth or the poses)."""
    order = np.argsort(scene.times, kind="stable")
    sel = np.unique(np.linspace(0, len(order) - 2, min(len(order) - 1, pairs)).round().astype(int))
    c2w = viewmat_to_c2w(np.asarray(scene.viewmats, np.float64))
    bg = jnp.asarray(cfg.model.background, jnp.float32)
    score = 0.0
    for j in sel:
        a, b = int(order[j]), int(order[j + 1])
        _, alpha, info, _ = render_params(params, alive, jnp.asarray(scene.viewmats[a], jnp.float32),
                                          jnp.asarray(scene.Ks[a], jnp.float32), 0.0, spec=None, sh_degree=0,
                                          width=scene.width, height=scene.height, background=bg, capacity=capacity,
                                          render_depth=True)
        u = estimate_flow(to_u8(scene.images[a]), to_u8(scene.images[b]), cfg.flow.method, cache_dir=cache_dir)
        cam, ok = fl.reprojection_flow(np.asarray(info["depth"], np.float64), scene.Ks[a], c2w[a], c2w[b])
        r = np.linalg.norm(u - np.asarray(cam), axis=-1)  # [H, W]
        use = np.asarray(ok) & (np.asarray(alpha) >= 0.5) & np.isfinite(r)
        if use.sum() < 16:
            continue
        thr = max(min_px, k * float(np.median(r[use])))
        score = max(score, float(np.mean(r[use] > thr)))
    return score
