"""The stage-1 model as a function: canonical Gaussians + deformation field -> Gaussians and an image at time t.

The parameters are a dict pytree {"gaussians": `fgjax.gaussians.Gaussians` (raw: log-scales, unnormalised wxyz
quaternions, opacity logits, SH), "deform": the deformation field's parameters (`fgjax.models.deform`), and, when
stage 1 refined the cameras, "pose": [T, 6] se(3) deltas}. Cameras are OpenCV: ``viewmat`` world-to-camera 4x4,
``K`` 3x3 (DESIGN.md section 2).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from fgjax.gaussians import Gaussians, activate
from fgjax.geometry import look_at_point, matmul, se3_exp
from fgjax.models.deform import DeformSpec, deform_apply
from fgjax.render.api import rasterization, spherical_harmonics

__all__ = ["scene_extent", "deformed_gaussians", "render_params", "refined_viewmats"]


def scene_extent(viewmats: np.ndarray) -> float:
    """3DGS's camera extent: 1.1 x the largest distance of a camera centre from their mean, but at least 1.1 x a
    quarter of the cameras' distance to the point they look at (`fgjax.geometry.look_at_point`). The floor only acts
    for cameras that barely move against the distance to what they see (a still camera, a camera that only turns,
    a short hand-held baseline), whose spread says nothing of the scene's size; an orbit is unaffected."""
    c = -np.einsum("tji,tj->ti", viewmats[:, :3, :3], viewmats[:, :3, 3])
    spread = float(np.max(np.linalg.norm(c - c.mean(0), axis=-1)))
    return 1.1 * max(spread, 0.25 * look_at_point(viewmats)[1], 1e-3)


def scale_gradient(x, factor: float):
    """x in the forward pass; ``factor`` times its gradient in the backward pass (0: stop-gradient)."""
    if factor == 1.0:
        return x
    sg = jax.lax.stop_gradient(x)
    return sg if factor == 0.0 else sg + factor * (x - sg)


def deformed_gaussians(params, alive, t, spec: DeformSpec | None, motion_grad: float = 1.0):
    """(means [N, 3], activated quats [N, 4], scales [N, 3], opacities [N], log-scales [N, 3]) of the model at time
    t: x + dx, q + dq, log s + ds with (dx, dq, ds) = f(sg(x), t) (the deformation field reads stop-gradient
    canonical centres, as in Deformable-3DGS); ``spec`` None: the canonical Gaussians. ``motion_grad`` (a Python
    float) scales the gradient that reaches the field through dx (0: the loss that renders these Gaussians does not
    train the motion: `fgjax.config.FlowConfig.photo_motion`)."""
    g: Gaussians = params["gaussians"]
    means, quats, log_scales = g.means, g.quats, g.log_scales
    if spec is not None:
        dx, dq, ds = deform_apply(spec, params["deform"], jax.lax.stop_gradient(means), t, quats=quats)
        dx = scale_gradient(dx, motion_grad)
        means, quats, log_scales = means + dx, quats + dq, log_scales + ds
    g2 = Gaussians(means, log_scales, quats, g.opacity_logits, g.sh)
    q, s, o = activate(g2, alive)
    return means, q, s, o, log_scales


def render_params(
    params, alive, viewmat, K, t, *, spec: DeformSpec | None, sh_degree: int, width: int, height: int,
    background, capacity: int | None, tile_size: int = 8, delta2d=None, render_depth: bool = False, sh_mask=None,
    active=None, motion_grad: float = 1.0,
):
    """Render the model at time t from one camera: (image [H, W, 3], alpha, info, geometry) with geometry =
    {"means": deformed centres [N, 3], "log_scales": deformed log-scales [N, 3]}.

    ``delta2d`` [N, 2] (zeros) shifts each Gaussian by that many pixels on screen (a camera-space
    offset proportional to depth); its gradient is the screen-space gradient densification needs.
    ``active`` [N] bool: composite only the tiles these Gaussians reach (`fgjax.rasterization`'s ``active``).
    ``motion_grad``: `deformed_gaussians`'s.
    """

    means, q, s, o, log_scales = deformed_gaussians(params, alive, t, spec, motion_grad)
    geometry = {"means": means, "log_scales": log_scales}
    rot = viewmat[:3, :3]
    if delta2d is not None:
        z = matmul(means, rot[2]) + viewmat[2, 3]  # [N]
        off_cam = jnp.stack([delta2d[:, 0] * z / K[0, 0], delta2d[:, 1] * z / K[1, 1], jnp.zeros_like(z)], -1)
        means = means + matmul(off_cam, rot)  # R^T off
    campos = -matmul(rot.T, viewmat[:3, 3])
    sh = params["gaussians"].sh
    if sh_mask is not None:  # SH-degree schedule without recompiling: zero the inactive coefficients
        sh = sh * sh_mask[:, None]
    colors = jnp.maximum(spherical_harmonics(sh_degree, means - campos, sh) + 0.5, 0.0)
    img, alpha, info = rasterization(
        means, q, s, o, colors, viewmat, K, width, height, background=background, capacity=capacity,
        tile_size=tile_size, render_depth=render_depth, active=active,
    )
    return img, alpha, info, geometry


def refined_viewmats(params, viewmats: np.ndarray) -> np.ndarray:
    """The training cameras as stage 1 last saw them: se3_exp(delta_i) @ viewmat_i [T, 4, 4] (OpenCV
    world-to-camera) when the run refined poses (``pose.enabled``), else ``viewmats`` unchanged."""
    if "pose" not in params:
        return np.asarray(viewmats)

    deltas = np.asarray(params["pose"], np.float64)  # [T, 6]
    vm = np.asarray(viewmats, np.float64)
    if deltas.shape[0] != vm.shape[0]:
        raise ValueError(f"the run refined {deltas.shape[0]} camera poses but the scene has {vm.shape[0]} frames")
    return (np.asarray(se3_exp(deltas)) @ vm).astype(vm.dtype)  # se3_exp is batched: [T, 4, 4]
