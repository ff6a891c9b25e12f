"""Long-range flow supervision: the rendered correspondence from a reference frame against chained optical flow.

L_uGS (`fgjax.flow.gaussian.gaussian_flow_loss`) supervises the velocity of the Gaussians between consecutive frames,
with a target u - u_cam that is right only where the model already renders frame t-1 in its true state: where a part
is rendered in the wrong place at t-1, its pixels ask the Gaussians that paint them (the part's ghost, or what lies
behind it) to stay still, and the background's pixels ask the background to move. This module supervises positions
instead. For a reference frame r (the first frame of the video: the scene that `fgjax.models.deform.DeformSpec.anchor`
fixes) and any later frame t:

- the target is the 2D track of each pixel p of frame r: D(p, t) = p(t) - p, with p(t) optical flow chained from r
  to t (`fgjax.data.opticalflow.chained_tracks`), NaN where the chain was lost (occluded, out of view);
- the rendered correspondence is C(p, t) = sum_i T_i alpha_i (pi_t(x_i(t)) - pi_r(x_i(r))) / alpha(p): the
  displacement, from their projection in frame r to their projection in frame t (each with its own camera), of the
  Gaussians that paint p in frame r, composited with frame r's weights (`fgjax.rasterization` with the 2D
  displacements as colour channels);
- `gaussian_track_loss` = mean over valid pixels (rendered alpha > ``min_alpha`` at r, finite D) of
  max(|C(p, t) - D(p, t)|_1 - tau, 0): errors under tau pixels (``threshold``, `fgjax.config.FlowConfig.threshold`)
  cost nothing (``norm = "l1"``); or, with ``norm = "charbonnier"``, the mean of
  c^2 (sqrt(1 + e^2 / c^2) - 1) with e = max(|C(p, t) - D(p, t)|_2 - tau, 0) and c = ``scale`` pixels (Charbonnier
  1994: e^2 / 2 for e << c, so a small residual pulls in proportion to its size, and linear beyond, as in
  `fgjax.flow.gaussian.gaussian_flow_loss`). C composites the displacements of the Gaussians' centres, not of the
  surface point each pixel sees (the isotropic form of L_uGS, DESIGN.md section 1, step 4), so a static pixel's
  residual grows with the camera's motion between r and t (measured on a synthetic door: median 0.04 px one frame
  apart, 0.2 px six frames, 0.47 px fifteen), and so does the chained flow's own error; without tau, L1's gradient
  sign(r) would push every static Gaussian as hard as a moving one.

Frame r's weights and centres are held fixed (stop-gradient): the loss moves the Gaussians at time t, never which
Gaussians paint frame r. The camera motion is inside both C and D, so no camera flow (and no depth) enters the
target; a static Gaussian at the right depth satisfies the loss by itself.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from fgjax.flow._common import charbonnier
from fgjax.geometry import abs0, as_float, project_points, safe_norm
from fgjax.render.api import rasterization

__all__ = ["project_centres", "rendered_correspondence", "gaussian_track_loss"]


def project_centres(means: Float[ArrayLike, "N 3"], viewmat: Float[ArrayLike, "4 4"], K: Float[ArrayLike, "3 3"],
                    near: float = 1e-2) -> Float[Array, "N 2"]:
    """Pixel coordinates (x, y) of world points under an OpenCV camera (world-to-camera ``viewmat``, pixel centres
    at +0.5 as in the rasterizer): `fgjax.geometry.project_points` with the camera depth clamped at ``near``, so
    that points behind the camera stay finite and push nothing through their depth."""
    means, viewmat = as_float(means), as_float(viewmat)
    pc = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    return project_points(jnp.concatenate([pc[:, :2], jnp.maximum(pc[:, 2:3], near)], axis=-1), K)


def rendered_correspondence(
    means_r: Float[ArrayLike, "N 3"], quats_r: Float[ArrayLike, "N 4"], scales_r: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, " N"], means_t: Float[ArrayLike, "N 3"], viewmat_r: Float[ArrayLike, "4 4"],
    K_r: Float[ArrayLike, "3 3"], viewmat_t: Float[ArrayLike, "4 4"], K_t: Float[ArrayLike, "3 3"], width: int,
    height: int, *, capacity: int | None = None, tile_size: int = 16,
) -> tuple[Float[Array, "H W 2"], Float[Array, "H W"], Bool[Array, ""]]:
    """(C [H, W, 2] on frame r's grid, alpha [H, W] of frame r, overflow flag): module docstring. Frame r's
    Gaussians (``means_r, quats_r, scales_r, opacities``, activated) and their centres at t (``means_t``), world
    frame; C is the composited displacement divided by alpha (0 where alpha is 0)."""
    d = project_centres(means_t, viewmat_t, K_t) - project_centres(means_r, viewmat_r, K_r)  # [N, 2]
    img, alpha, info = rasterization(means_r, quats_r, scales_r, opacities, d, viewmat_r, K_r, width, height,
                                     background=jnp.zeros(2, d.dtype), capacity=capacity, tile_size=tile_size)
    return img / jnp.maximum(alpha, 1e-6)[..., None], alpha, info["overflow"]


def gaussian_track_loss(
    means_r: Float[ArrayLike, "N 3"], quats_r: Float[ArrayLike, "N 4"], scales_r: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, " N"], means_t: Float[ArrayLike, "N 3"], viewmat_r: Float[ArrayLike, "4 4"],
    K_r: Float[ArrayLike, "3 3"], viewmat_t: Float[ArrayLike, "4 4"], K_t: Float[ArrayLike, "3 3"],
    track: Float[ArrayLike, "H W 2"], width: int, height: int, *, threshold: float = 0.0, min_alpha: float = 0.5,
    capacity: int | None = None, tile_size: int = 16, norm: str = "l1", scale: float = 10.0,
) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """(mean over valid pixels of max(|C - D|_1 - threshold, 0) in pixels, or of its Charbonnier form with ``norm =
    "charbonnier"`` and c = ``scale`` (a Python float, static under jit), overflow flag): module docstring.
    ``track`` is D [H, W, 2] on frame r's grid (NaN = lost). Frame r's Gaussians are held fixed; gradients reach
    ``means_t`` only. 0 when no pixel is valid."""
    if norm not in ("l1", "charbonnier"):
        raise ValueError(f"norm must be 'l1' or 'charbonnier'; got {norm!r}.")
    if not scale > 0:
        raise ValueError(f"scale must be > 0; got {scale!r}.")
    sg = jax.lax.stop_gradient
    corr, alpha, overflow = rendered_correspondence(sg(means_r), sg(quats_r), sg(scales_r), sg(opacities), means_t,
                                                    viewmat_r, K_r, viewmat_t, K_t, width, height, capacity=capacity,
                                                    tile_size=tile_size)
    track = as_float(track)
    known = jnp.all(jnp.isfinite(track), axis=-1)
    valid = (known & (sg(alpha) > min_alpha)).astype(corr.dtype)
    r = corr - jnp.where(known[..., None], track, 0.0)
    if norm == "l1":
        err = jnp.maximum(jnp.sum(abs0(r), axis=-1) - threshold, 0.0)
    else:
        e = jnp.maximum(safe_norm(r) - threshold, 0.0)
        err = charbonnier(e * e, scale)
    return jnp.sum(valid * err) / jnp.maximum(jnp.sum(valid), 1.0), overflow
