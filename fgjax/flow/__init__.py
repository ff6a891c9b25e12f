"""Flow derivatives: camera velocity, motion field, reprojection flow, Gaussian flow maps, Lemma 1, flow loss.

The maths is ../shared/DESIGN.md section 1, steps 3 and 4 (FreeGaussian, Lemma 1; GaussianFlow for the
anisotropic form). Conventions, shared by every function here:

- Cameras are OpenCV (x right, y down, z forward). ``c2w`` is a 4x4 camera-to-world pose, ``viewmat`` a 4x4
  world-to-camera matrix. ``K`` is 3x3; the motion-field formulas assume zero skew (``K[0, 1]`` ignored
  there), ``reprojection_flow`` and ``geometry.project_points`` honour it.
- Pixel (j, i) (column j, row i) has its centre at m = (j + 0.5, i + 0.5); ``xy`` arguments are in that
  continuous system, as are K's cx, cy (gsplat's convention). Datasets whose K assumes integer pixel
  centres (OpenCV/ROS calibrations such as TUM's cx = 319.5) need cx + 0.5, cy + 0.5.
- Flow is forward, frame t-1 -> t, on frame t-1's pixel grid, in pixels per frame interval, stored
  [H, W, 2] as (dx, dy): the content at m in frame t-1 is at m + flow(m) in frame t.
- Camera velocity (v, omega) is expressed in camera-(t-1) coordinates: v is the camera centre's velocity,
  omega the angular velocity, so that a static point P (camera coordinates) moves as P' = -v - omega x P.
- Quaternions are wxyz, any norm; scales and opacities are activated (as the rasterizer takes them).

Every function is pure, differentiable, vmap-able and NaN-free (double-``where`` on every division and
square root). The array functions are wrapped in ``jax.jit`` (static: image sizes, norms, thresholds), so
eager calls run as one compiled program and calls inside other jitted code are inlined. The Gaussian flow
maps render through ``fgjax.render.api.rasterization`` and are not jitted themselves, so that outside jit
the rasterizer can size its intersection buffer exactly; they are jit-able with a ``capacity``.

Modules: `fgjax.flow.motion` (camera velocity, motion field, reprojection flow, Gaussian image velocity) and
`fgjax.flow.gaussian` (2D covariances, affine flow, rendered Gaussian flow, Lemma 1, losses, warping) and
`fgjax.flow.track` (the rendered correspondence from a reference frame and the long-range track loss).
"""

from __future__ import annotations

from fgjax.flow.gaussian import GaussianFlowMaps as GaussianFlowMaps
from fgjax.flow.gaussian import composited_inverse_depth as composited_inverse_depth
from fgjax.flow.gaussian import dynamic_gaussian_flow as dynamic_gaussian_flow
from fgjax.flow.gaussian import flow_loss as flow_loss
from fgjax.flow.gaussian import gaussian_flow_affine as gaussian_flow_affine
from fgjax.flow.gaussian import gaussian_flow_loss as gaussian_flow_loss
from fgjax.flow.gaussian import lemma1_residual as lemma1_residual
from fgjax.flow.gaussian import maps_camera_flow as maps_camera_flow
from fgjax.flow.gaussian import project_covariances as project_covariances
from fgjax.flow.gaussian import sqrtm_2x2 as sqrtm_2x2
from fgjax.flow.gaussian import warp_backward as warp_backward
from fgjax.flow.motion import camera_velocity as camera_velocity
from fgjax.flow.motion import gaussian_image_velocity as gaussian_image_velocity
from fgjax.flow.motion import gaussian_image_velocity_jvp as gaussian_image_velocity_jvp
from fgjax.flow.motion import motion_field as motion_field
from fgjax.flow.motion import motion_field_inv_depth as motion_field_inv_depth
from fgjax.flow.motion import motion_field_matrices as motion_field_matrices
from fgjax.flow.motion import pixel_centers as pixel_centers
from fgjax.flow.motion import reprojection_flow as reprojection_flow
from fgjax.flow.track import gaussian_track_loss as gaussian_track_loss
from fgjax.flow.track import rendered_correspondence as rendered_correspondence

__all__ = [
    "pixel_centers",
    "camera_velocity",
    "motion_field_matrices",
    "motion_field",
    "motion_field_inv_depth",
    "reprojection_flow",
    "gaussian_image_velocity",
    "gaussian_image_velocity_jvp",
    "project_covariances",
    "sqrtm_2x2",
    "gaussian_flow_affine",
    "GaussianFlowMaps",
    "dynamic_gaussian_flow",
    "composited_inverse_depth",
    "lemma1_residual",
    "flow_loss",
    "gaussian_flow_loss",
    "maps_camera_flow",
    "warp_backward",
    "rendered_correspondence",
    "gaussian_track_loss",
]
