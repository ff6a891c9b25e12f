"""fgjax: annotation-free controllable 3D Gaussian splats from flow derivatives, in JAX.

Public API (everything else is private to its module):

- ``fgjax.rasterization``: jit tile rasterizer (gsplat rules, custom VJP).
- ``fgjax.spherical_harmonics``: view-dependent colour from SH coefficients (degree 0-3).
- ``fgjax.flow``: camera velocity, motion field, reprojection flow, Gaussian flow, flow loss.
- ``fgjax.geometry``: SO(3)/SE(3), quaternions, OpenGL <-> OpenCV.
- ``fgjax.estimate_flow``: OpenCV optical flow on uint8 RGB frames.
"""

from __future__ import annotations

__version__ = "0.1.0"


def __getattr__(name):  # lazy: `import fgjax` stays cheap, and the CLI starts fast
    if name in ("rasterization", "spherical_harmonics", "gaussian_weights", "count_intersections"):
        from fgjax.render import api

        return getattr(api, name)
    if name == "estimate_flow":
        from fgjax.data.opticalflow import estimate_flow

        return estimate_flow
    if name in ("flow", "geometry"):
        import importlib

        return importlib.import_module(f"fgjax.{name}")
    raise AttributeError(f"module 'fgjax' has no attribute {name!r}")
