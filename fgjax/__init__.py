"""fgjax: annotation-free controllable 3D Gaussian splats from flow derivatives, in JAX.

Public API (docs/architecture.md describes the layout; everything else is private to its module):

- ``fgjax.rasterization``: jit tile rasterizer (gsplat rules, custom VJP); ``fgjax.spherical_harmonics``,
  ``fgjax.gaussian_weights``, ``fgjax.count_intersections``.
- ``fgjax.flow``: camera velocity, motion field, reprojection flow, Gaussian flow, flow losses.
- ``fgjax.geometry``: SO(3)/SE(3), quaternions, OpenGL <-> OpenCV.
- ``fgjax.estimate_flow``: OpenCV optical flow on uint8 RGB frames.
- ``fgjax.load_config``, ``fgjax.Config``: named configurations (experiments/*.toml) and overrides.
- ``fgjax.load_scene``: a dataset (nerfstudio / Blender / D-NeRF / Nerfies layouts).
- ``fgjax.run_stage1``: stage 1 on a dataset into a run folder; ``fgjax.run_stage2``: the paper's stage 2;
  ``fgjax.run_articulated``: the articulated variant; ``fgjax.load_stage2``, ``fgjax.render_controlled``,
  ``fgjax.render_clusters``, ``fgjax.snap_vector``: use a finished run; ``fgjax.scene_gaussians``,
  ``fgjax.viewer_gaussians``: its scene at a time or with objects moved, as Gaussians.
- ``fgjax.write_ply``, ``fgjax.read_ply``: Gaussians as a standard 3DGS .ply file.

Attributes load on first use, so ``import fgjax`` stays cheap and the command line starts fast.
"""

from __future__ import annotations

import importlib

from fgjax.version import __version__ as __version__

_LAZY = {
    "rasterization": "fgjax.render.api",
    "spherical_harmonics": "fgjax.render.api",
    "gaussian_weights": "fgjax.render.api",
    "count_intersections": "fgjax.render.api",
    "estimate_flow": "fgjax.data.opticalflow",
    "load_scene": "fgjax.data.loaders",
    "load_config": "fgjax.config",
    "Config": "fgjax.config",
    "Stage2Config": "fgjax.config",
    "ArticulateConfig": "fgjax.config",
    "run_stage1": "fgjax.method",
    "run_stage2": "fgjax.method",
    "load_stage2": "fgjax.method",
    "render_controlled": "fgjax.method",
    "render_clusters": "fgjax.method",
    "snap_vector": "fgjax.method",
    "scene_gaussians": "fgjax.method",
    "viewer_gaussians": "fgjax.method",
    "write_ply": "fgjax.ply",
    "read_ply": "fgjax.ply",
    "run_articulated": "fgjax.articulate",
}
_MODULES = ("flow", "geometry", "method", "articulate", "cluster", "metrics")

__all__ = ["__version__", *_LAZY, *_MODULES]


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name in _MODULES:
        return importlib.import_module(f"fgjax.{name}")
    raise AttributeError(f"module 'fgjax' has no attribute {name!r}")


def __dir__():
    return sorted(__all__)
