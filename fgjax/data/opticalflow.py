"""Dense optical flow from OpenCV, Middlebury .flo I/O, forward-backward masks, an on-disk cache,
and the ``fgjax flow`` command.

Convention (docs/DESIGN.md, "Flow"): flow is forward (frame0 -> frame1), lives on frame0's pixel
grid, and is stored as float32 ``[H, W, 2]`` holding (dx, dy) in pixels, so pixel (j, i) of frame0
moves to (j + dx, i + dy) in frame1. Images are uint8 RGB ``[H, W, 3]`` (greyscale ``[H, W]`` is
accepted too).

Methods (each has a frozen parameter dataclass; every field is settable from the API as a dict or
dataclass and from the command line as ``--param key=value``):

- ``dis_deepflow`` (default): DIS patch search at full resolution (Kroeger et al. ECCV 2016), then
  DeepFlow's variational energy (Weinzaepfel et al. ICCV 2013, as in OpenCV) over the top
  ``levels`` pyramid levels. On the three shared Middlebury pairs it is more accurate than OpenCV
  DeepFlow (0.121 vs 0.126 average EPE; Sintel alley_1 non-occluded 0.138 vs 0.140) at about a
  quarter of its run time; see docs/benchmarks.md ("Optical flow") for the search behind it.
- ``deepflow``: OpenCV's DeepFlow (coarse-to-fine variational refinement from zero flow; no deep
  matching). OpenCV 5's Python bindings expose none of its parameters, so the same pyramid is
  driven here from ``cv2.VariationalRefinement``; with default parameters it reproduces
  ``cv2.optflow.createOptFlow_DeepFlow()`` to ~0.01 px (tested).
- ``dis``: ``cv2.DISOpticalFlow`` with its variational refinement; defaults are OpenCV's MEDIUM
  preset except ``finest_scale=0`` (MEDIUM stops at half resolution: 0.21 vs 0.14 EPE).
- ``tvl1``: ``cv2.optflow.DualTVL1OpticalFlow`` (Zach et al. 2007; Wedel et al. 2009).
- ``rlof``: ``cv2.optflow.DenseRLOFOpticalFlow`` (Senst et al.; Geistert et al. 2016).
- ``farneback``: ``cv2.FarnebackOpticalFlow`` (Farneback 2003).

Everything here is a plain function of its arguments (no module state); the only side effects are
the files a caller asks for, written atomically (temporary file in the same folder, then
``os.replace``).
"""

from __future__ import annotations

import argparse
import dataclasses
import glob as globlib
import hashlib
import json
import math
import os
import re
import shutil
import sys
import tempfile
import time
import typing
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from fgjax.io import atomic_write

if TYPE_CHECKING:  # annotations only: jaxtyping costs ~0.5 s to import and the CLI should start fast
    from jaxtyping import Bool, Float, Float32, UInt8

__all__ = [
    "CACHE_FORMAT_VERSION",
    "DEFAULT_METHOD",
    "METHODS",
    "DISDeepFlowParams",
    "DISParams",
    "DeepFlowParams",
    "FarnebackParams",
    "RLOFParams",
    "TVL1Params",
    "estimate_flow",
    "estimate_sequence",
    "flow_cache_key",
    "flow_valid_mask",
    "forward_backward_error",
    "forward_backward_mask",
    "frames_from_transforms",
    "import_sequence",
    "list_frames",
    "load_flow",
    "main",
    "read_flo",
    "read_image",
    "resolve_params",
    "save_flow",
    "write_flo",
]

DEFAULT_METHOD = "dis_deepflow"
CACHE_FORMAT_VERSION = 1
FLO_MAGIC = b"PIEH"  # float32 202021.25 in little-endian, the Middlebury tag
FLO_UNKNOWN = 1e9  # |value| above this marks unknown flow in .flo ground truth
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")
_FLT_MAX = 3.4028234663852886e38


# --------------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------------


def _check(cond: bool, cls: str, field: str, what: str, value: Any) -> None:
    if not cond:
        raise ValueError(f"{cls}.{field} {what}, got {value!r}")


@dataclass(frozen=True)
class DISParams:
    """``cv2.DISOpticalFlow`` settings (Kroeger et al., "Fast Optical Flow using Dense Inverse
    Search", ECCV 2016). Defaults: OpenCV's PRESET_MEDIUM except ``finest_scale=0``."""

    finest_scale: int = 0
    """Finest pyramid level processed (0 = full resolution; MEDIUM uses 1, i.e. half)."""
    coarsest_scale: int = -1
    """Coarsest level; -1 picks it from the image size."""
    patch_size: int = 8
    """Side of the square patches matched by inverse search, in pixels."""
    patch_stride: int = 3
    """Distance between neighbouring patches; smaller is denser and slower."""
    gradient_descent_iterations: int = 25
    """Inverse-search iterations per patch."""
    variational_refinement_iterations: int = 5
    """Fixed-point iterations of the variational refinement at each level (0 disables it)."""
    variational_refinement_alpha: float = 20.0
    """Smoothness weight of the refinement."""
    variational_refinement_delta: float = 5.0
    """Colour-constancy weight of the refinement."""
    variational_refinement_gamma: float = 10.0
    """Gradient-constancy weight of the refinement."""
    variational_refinement_epsilon: float = 0.01
    """Charbonnier epsilon of the refinement's robust penalty."""
    use_mean_normalization: bool = True
    """Match mean-normalised patches (robust to brightness change)."""
    use_spatial_propagation: bool = True
    """Propagate good patch displacements to neighbours."""

    def __post_init__(self):
        n = type(self).__name__
        _check(self.finest_scale >= 0, n, "finest_scale", "must be >= 0", self.finest_scale)
        _check(self.coarsest_scale == -1 or self.coarsest_scale >= self.finest_scale, n, "coarsest_scale",
               "must be -1 (automatic) or >= finest_scale", self.coarsest_scale)
        _check(self.patch_size >= 2, n, "patch_size", "must be >= 2", self.patch_size)
        _check(1 <= self.patch_stride <= self.patch_size, n, "patch_stride", "must be in [1, patch_size]",
               self.patch_stride)
        _check(self.gradient_descent_iterations >= 1, n, "gradient_descent_iterations", "must be >= 1",
               self.gradient_descent_iterations)
        _check(self.variational_refinement_iterations >= 0, n, "variational_refinement_iterations",
               "must be >= 0", self.variational_refinement_iterations)
        for f in ("alpha", "delta", "gamma", "epsilon"):
            v = getattr(self, f"variational_refinement_{f}")
            _check(math.isfinite(v) and v >= 0, n, f"variational_refinement_{f}", "must be finite and >= 0", v)


@dataclass(frozen=True)
class DeepFlowParams:
    """OpenCV DeepFlow settings (Weinzaepfel et al., ICCV 2013; OpenCV's variant without deep
    matching). Defaults are OpenCV's; ``alpha``, ``delta`` and ``gamma`` are on DeepFlow's scale
    and are handed to ``cv2.VariationalRefinement`` as (4 alpha, delta / 3, gamma / 3), as OpenCV does."""

    sigma: float = 0.6
    """Gaussian pre-smoothing of both images (pixels)."""
    min_size: int = 25
    """The pyramid stops before a level whose width or height would be <= this."""
    downscale_factor: float = 0.95
    """Size ratio between consecutive pyramid levels."""
    fixed_point_iterations: int = 5
    """Outer (warping) iterations per level."""
    sor_iterations: int = 25
    """Red-black SOR sweeps per fixed-point iteration."""
    alpha: float = 1.0
    """Smoothness weight."""
    delta: float = 0.5
    """Colour-constancy weight."""
    gamma: float = 5.0
    """Gradient-constancy weight."""
    omega: float = 1.6
    """SOR relaxation factor, in (0, 2)."""

    def __post_init__(self):
        _check_variational(self)
        n = type(self).__name__
        _check(self.min_size >= 1, n, "min_size", "must be >= 1", self.min_size)


@dataclass(frozen=True)
class DISDeepFlowParams:
    """DIS at full resolution, then DeepFlow's energy over the top ``levels`` pyramid levels
    (scales ``downscale_factor**(levels-1), ..., 1``). The default method; its defaults come from
    the search recorded in docs/benchmarks.md ("Optical flow")."""

    # DIS initialisation
    finest_scale: int = 0
    """DIS: finest pyramid level (0 = full resolution)."""
    patch_size: int = 8
    """DIS: patch side in pixels."""
    patch_stride: int = 4
    """DIS: distance between patches."""
    gradient_descent_iterations: int = 12
    """DIS: inverse-search iterations per patch."""
    dis_variational_iterations: int = 0
    """DIS: its own variational refinement per level (OpenCV's weights 20/5/10); 0 = off, since the
    DeepFlow stage below refines anyway."""
    use_mean_normalization: bool = True
    """DIS: match mean-normalised patches."""
    use_spatial_propagation: bool = True
    """DIS: propagate good displacements to neighbours."""
    # DeepFlow refinement
    levels: int = 4
    """Number of pyramid levels refined with DeepFlow's energy (0 = DIS only)."""
    downscale_factor: float = 0.95
    """Size ratio between consecutive refinement levels."""
    sigma: float = 0.6
    """Gaussian pre-smoothing for the refinement (pixels)."""
    fixed_point_iterations: int = 5
    """Outer (warping) iterations per refinement level."""
    sor_iterations: int = 10
    """SOR sweeps per fixed-point iteration (DeepFlow uses 25; DIS's flow is a good start)."""
    alpha: float = 1.0
    """Smoothness weight (DeepFlow's scale)."""
    delta: float = 0.5
    """Colour-constancy weight (DeepFlow's scale)."""
    gamma: float = 5.0
    """Gradient-constancy weight (DeepFlow's scale)."""
    omega: float = 1.6
    """SOR relaxation factor, in (0, 2)."""

    def __post_init__(self):
        _check_variational(self)
        n = type(self).__name__
        _check(self.finest_scale >= 0, n, "finest_scale", "must be >= 0", self.finest_scale)
        _check(self.patch_size >= 2, n, "patch_size", "must be >= 2", self.patch_size)
        _check(1 <= self.patch_stride <= self.patch_size, n, "patch_stride", "must be in [1, patch_size]",
               self.patch_stride)
        _check(self.gradient_descent_iterations >= 1, n, "gradient_descent_iterations", "must be >= 1",
               self.gradient_descent_iterations)
        _check(self.dis_variational_iterations >= 0, n, "dis_variational_iterations", "must be >= 0",
               self.dis_variational_iterations)
        _check(self.levels >= 0, n, "levels", "must be >= 0", self.levels)


def _check_variational(p) -> None:
    n = type(p).__name__
    _check(math.isfinite(p.sigma) and p.sigma > 0, n, "sigma", "must be > 0", p.sigma)
    _check(0.0 < p.downscale_factor < 1.0, n, "downscale_factor", "must be in (0, 1)", p.downscale_factor)
    _check(p.fixed_point_iterations >= 1, n, "fixed_point_iterations", "must be >= 1", p.fixed_point_iterations)
    _check(p.sor_iterations >= 1, n, "sor_iterations", "must be >= 1", p.sor_iterations)
    for f in ("alpha", "delta", "gamma"):
        v = getattr(p, f)
        _check(math.isfinite(v) and v >= 0, n, f, "must be finite and >= 0", v)
    _check(0.0 < p.omega < 2.0, n, "omega", "must be in (0, 2)", p.omega)


@dataclass(frozen=True)
class TVL1Params:
    """``cv2.optflow.DualTVL1OpticalFlow`` settings (Zach, Pock, Bischof 2007; Wedel et al. 2009).
    Defaults are OpenCV's."""

    tau: float = 0.25
    """Time step of the numerical scheme (stable for <= 0.25)."""
    lambda_: float = 0.15
    """Data-term weight (larger: less smooth). CLI key: ``lambda_``."""
    theta: float = 0.3
    """Tightness of the coupling between the two sub-problems."""
    scales_number: int = 5
    """Pyramid levels."""
    warps_number: int = 5
    """Warpings per level."""
    epsilon: float = 0.01
    """Stopping threshold of the inner solver."""
    inner_iterations: int = 30
    """Inner iterations per warp."""
    outer_iterations: int = 10
    """Outer iterations per warp."""
    scale_step: float = 0.8
    """Size ratio between consecutive levels."""
    gamma: float = 0.0
    """Weight of the illumination-change term (0 = off)."""
    median_filtering: int = 5
    """Median filter size applied to the flow between warps (1 = off)."""

    def __post_init__(self):
        n = type(self).__name__
        for f in ("tau", "lambda_", "theta", "epsilon"):
            v = getattr(self, f)
            _check(math.isfinite(v) and v > 0, n, f, "must be > 0", v)
        _check(self.scales_number >= 1, n, "scales_number", "must be >= 1", self.scales_number)
        _check(self.warps_number >= 1, n, "warps_number", "must be >= 1", self.warps_number)
        _check(self.inner_iterations >= 1, n, "inner_iterations", "must be >= 1", self.inner_iterations)
        _check(self.outer_iterations >= 1, n, "outer_iterations", "must be >= 1", self.outer_iterations)
        _check(0.0 < self.scale_step < 1.0, n, "scale_step", "must be in (0, 1)", self.scale_step)
        _check(self.gamma >= 0, n, "gamma", "must be >= 0", self.gamma)
        _check(self.median_filtering >= 1 and self.median_filtering % 2 == 1, n, "median_filtering",
               "must be an odd number >= 1", self.median_filtering)


@dataclass(frozen=True)
class RLOFParams:
    """``cv2.optflow.DenseRLOFOpticalFlow`` settings: robust local flow on a grid, then sparse-to-dense
    interpolation (Senst et al. 2012-2016; Geistert et al. 2016). Defaults are OpenCV's."""

    grid_step: int = 6
    """Spacing of the grid of local-flow seeds (pixels)."""
    forward_backward_threshold: float = 1.0
    """Seeds whose forward-backward error exceeds this are dropped (<= 0: no check, faster)."""
    interpolation: str = "epic"
    """Sparse-to-dense interpolation: 'epic', 'geo' or 'ric'."""
    epic_k: int = 128
    """EPIC: nearest seeds used."""
    epic_sigma: float = 0.05
    """EPIC: kernel width."""
    epic_lambda: float = 999.0
    """EPIC: regularisation."""
    ric_sp_size: int = 15
    """RIC: superpixel size."""
    ric_slic_type: int = 100
    """RIC: SLIC variant (100 SLIC, 101 SLICO, 102 MSLIC)."""
    use_post_proc: bool = True
    """Fast global smoother on the result."""
    fgs_lambda: float = 500.0
    """Fast global smoother: lambda."""
    fgs_sigma: float = 1.5
    """Fast global smoother: sigma."""
    use_variational_refinement: bool = False
    """Refine the interpolated field variationally."""
    solver: str = "bilinear"
    """Local solver: 'bilinear' or 'standard'."""
    support_region: str = "cross"
    """Support region: 'cross' (colour-segmented) or 'fixed'."""
    small_win_size: int = 9
    """Smallest support window."""
    large_win_size: int = 21
    """Largest support window."""
    max_level: int = 4
    """Pyramid levels of the local solver."""
    max_iteration: int = 30
    """Iterations of the local solver."""
    min_eigen_value: float = 0.0001
    """Seeds with a weaker structure tensor are dropped."""
    norm_sigma0: float = _FLT_MAX
    """Shrinked Hampel norm parameter (FLT_MAX = least squares)."""
    norm_sigma1: float = _FLT_MAX
    """Shrinked Hampel norm parameter (FLT_MAX = least squares)."""
    cross_segmentation_threshold: int = 25
    """Colour threshold of the cross support region."""
    use_illumination_model: bool = True
    """Model linear illumination changes."""
    use_global_motion_prior: bool = True
    """Initialise from a RANSAC global motion."""
    global_motion_ransac_threshold: float = 10.0
    """RANSAC threshold of the global motion prior (pixels)."""

    def __post_init__(self):
        n = type(self).__name__
        _check(self.grid_step >= 1, n, "grid_step", "must be >= 1", self.grid_step)
        _check(self.interpolation in _RLOF_INTERP, n, "interpolation", f"must be one of {sorted(_RLOF_INTERP)}",
               self.interpolation)
        _check(self.solver in ("bilinear", "standard"), n, "solver", "must be 'bilinear' or 'standard'", self.solver)
        _check(self.support_region in ("cross", "fixed"), n, "support_region", "must be 'cross' or 'fixed'",
               self.support_region)
        _check(3 <= self.small_win_size <= self.large_win_size, n, "small_win_size",
               "must be in [3, large_win_size]", self.small_win_size)
        _check(self.max_level >= 0, n, "max_level", "must be >= 0", self.max_level)
        _check(self.max_iteration >= 1, n, "max_iteration", "must be >= 1", self.max_iteration)
        _check(self.epic_k >= 1, n, "epic_k", "must be >= 1", self.epic_k)
        _check(self.ric_slic_type in (100, 101, 102), n, "ric_slic_type", "must be 100, 101 or 102",
               self.ric_slic_type)


_RLOF_INTERP = {"epic": 1, "geo": 0, "ric": 2}  # cv2.optflow.INTERP_EPIC / INTERP_GEO / INTERP_RIC


@dataclass(frozen=True)
class FarnebackParams:
    """``cv2.FarnebackOpticalFlow`` settings (Farneback, SCIA 2003). Defaults are OpenCV's."""

    num_levels: int = 5
    """Pyramid levels."""
    pyr_scale: float = 0.5
    """Size ratio between levels."""
    fast_pyramids: bool = False
    """Use the faster, less accurate pyramid."""
    win_size: int = 13
    """Averaging window (pixels)."""
    num_iters: int = 10
    """Iterations per level."""
    poly_n: int = 5
    """Neighbourhood of the polynomial expansion (5 or 7)."""
    poly_sigma: float = 1.1
    """Gaussian width of the polynomial expansion (1.1 for poly_n=5, 1.5 for 7)."""
    gaussian_window: bool = False
    """Gaussian instead of box averaging window."""

    def __post_init__(self):
        n = type(self).__name__
        _check(self.num_levels >= 1, n, "num_levels", "must be >= 1", self.num_levels)
        _check(0.0 < self.pyr_scale < 1.0, n, "pyr_scale", "must be in (0, 1)", self.pyr_scale)
        _check(self.win_size >= 1, n, "win_size", "must be >= 1", self.win_size)
        _check(self.num_iters >= 1, n, "num_iters", "must be >= 1", self.num_iters)
        _check(self.poly_n in (5, 7), n, "poly_n", "must be 5 or 7", self.poly_n)
        _check(self.poly_sigma > 0, n, "poly_sigma", "must be > 0", self.poly_sigma)


# --------------------------------------------------------------------------------------------------
# Backends
# --------------------------------------------------------------------------------------------------


def _gray(image: np.ndarray) -> np.ndarray:
    import cv2

    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _blurred_float(gray: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    k = int(math.floor(3 * sigma)) * 2 + 1  # OpenCV DeepFlow's kernel size
    return cv2.GaussianBlur(gray.astype(np.float32), (k, k), sigma)


def _variational(p):
    import cv2

    v = cv2.VariationalRefinement_create()
    v.setAlpha(4.0 * p.alpha)  # DeepFlow -> VariationalRefinement weights, as OpenCV's DeepFlow does
    v.setDelta(p.delta / 3.0)
    v.setGamma(p.gamma / 3.0)
    v.setFixedPointIterations(p.fixed_point_iterations)
    v.setSorIterations(p.sor_iterations)
    v.setOmega(p.omega)
    return v


def _refine_pyramid(i0: np.ndarray, i1: np.ndarray, sizes: list[tuple[int, int]], flow: np.ndarray, p):
    """Coarse-to-fine variational refinement of `flow` (any size; rescaled to each level) over
    `sizes` ((w, h), coarsest first). i0, i1: blurred float32 full-resolution images; each level
    is resized from them directly."""
    import cv2

    refine = _variational(p)
    for w, h in sizes:
        if flow.shape[:2] != (h, w):
            fh, fw = flow.shape[:2]
            flow = cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR)
            flow[..., 0] *= w / fw
            flow[..., 1] *= h / fh
        if (h, w) == i0.shape:
            a, b = i0, i1
        else:
            a = cv2.resize(i0, (w, h), interpolation=cv2.INTER_LINEAR)
            b = cv2.resize(i1, (w, h), interpolation=cv2.INTER_LINEAR)
        flow = refine.calc(a, b, flow)
    return flow


def _run_deepflow(image0, image1, p: DeepFlowParams):
    import cv2

    i0 = _blurred_float(_gray(image0), p.sigma)
    i1 = _blurred_float(_gray(image1), p.sigma)
    # OpenCV's pyramid: each level resized from the previous one, stop before a side <= min_size
    pyr0, pyr1 = [i0], [i1]
    for _ in range(200):
        h, w = pyr0[-1].shape
        nw, nh = int(w * p.downscale_factor + 0.5), int(h * p.downscale_factor + 0.5)
        if nw <= p.min_size or nh <= p.min_size:
            break
        pyr0.append(cv2.resize(pyr0[-1], (nw, nh), interpolation=cv2.INTER_LINEAR))
        pyr1.append(cv2.resize(pyr1[-1], (nw, nh), interpolation=cv2.INTER_LINEAR))
    refine = _variational(p)
    h, w = pyr0[-1].shape
    flow = np.zeros((h, w, 2), np.float32)
    for level in range(len(pyr0) - 1, -1, -1):
        flow = refine.calc(pyr0[level], pyr1[level], flow)
        if level > 0:
            h, w = pyr0[level - 1].shape
            flow = cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR) * np.float32(1.0 / p.downscale_factor)
    return flow


def _dis(finest, coarsest, patch, stride, gd, vr_iters, mean_norm, spatial_prop):
    import cv2

    d = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    d.setFinestScale(finest)
    if coarsest >= 0:
        d.setCoarsestScale(coarsest)
    d.setPatchSize(patch)
    d.setPatchStride(stride)
    d.setGradientDescentIterations(gd)
    d.setVariationalRefinementIterations(vr_iters)
    d.setUseMeanNormalization(mean_norm)
    d.setUseSpatialPropagation(spatial_prop)
    return d


def _run_dis(image0, image1, p: DISParams):
    d = _dis(p.finest_scale, p.coarsest_scale, p.patch_size, p.patch_stride, p.gradient_descent_iterations,
             p.variational_refinement_iterations, p.use_mean_normalization, p.use_spatial_propagation)
    d.setVariationalRefinementAlpha(p.variational_refinement_alpha)
    d.setVariationalRefinementDelta(p.variational_refinement_delta)
    d.setVariationalRefinementGamma(p.variational_refinement_gamma)
    d.setVariationalRefinementEpsilon(p.variational_refinement_epsilon)
    return d.calc(_gray(image0), _gray(image1), None)


def _run_dis_deepflow(image0, image1, p: DISDeepFlowParams):
    g0, g1 = _gray(image0), _gray(image1)
    d = _dis(p.finest_scale, -1, p.patch_size, p.patch_stride, p.gradient_descent_iterations,
             p.dis_variational_iterations, p.use_mean_normalization, p.use_spatial_propagation)
    flow = d.calc(g0, g1, None)
    if p.levels == 0:
        return flow
    h, w = g0.shape
    sizes = [(int(w * p.downscale_factor**k + 0.5), int(h * p.downscale_factor**k + 0.5))
             for k in range(p.levels - 1, -1, -1)]
    return _refine_pyramid(_blurred_float(g0, p.sigma), _blurred_float(g1, p.sigma), sizes, flow, p)


def _run_tvl1(image0, image1, p: TVL1Params):
    import cv2

    t = cv2.optflow.DualTVL1OpticalFlow_create()
    t.setTau(p.tau)
    t.setLambda(p.lambda_)
    t.setTheta(p.theta)
    t.setScalesNumber(p.scales_number)
    t.setWarpingsNumber(p.warps_number)
    t.setEpsilon(p.epsilon)
    t.setInnerIterations(p.inner_iterations)
    t.setOuterIterations(p.outer_iterations)
    t.setScaleStep(p.scale_step)
    t.setGamma(p.gamma)
    t.setMedianFiltering(p.median_filtering)
    return t.calc(_gray(image0), _gray(image1), None)


def _run_rlof(image0, image1, p: RLOFParams):
    import cv2

    rp = cv2.optflow.RLOFOpticalFlowParameter_create()
    rp.setSolverType(cv2.optflow.ST_BILINEAR if p.solver == "bilinear" else cv2.optflow.ST_STANDART)
    rp.setSupportRegionType(cv2.optflow.SR_CROSS if p.support_region == "cross" else cv2.optflow.SR_FIXED)
    rp.setSmallWinSize(p.small_win_size)
    rp.setLargeWinSize(p.large_win_size)
    rp.setMaxLevel(p.max_level)
    rp.setMaxIteration(p.max_iteration)
    rp.setMinEigenValue(p.min_eigen_value)
    rp.setNormSigma0(p.norm_sigma0)
    rp.setNormSigma1(p.norm_sigma1)
    rp.setCrossSegmentationThreshold(p.cross_segmentation_threshold)
    rp.setUseIlluminationModel(p.use_illumination_model)
    rp.setUseGlobalMotionPrior(p.use_global_motion_prior)
    rp.setGlobalMotionRansacThreshold(p.global_motion_ransac_threshold)
    r = cv2.optflow.DenseRLOFOpticalFlow_create(
        rp, p.forward_backward_threshold, (p.grid_step, p.grid_step), _RLOF_INTERP[p.interpolation],
        p.epic_k, p.epic_sigma, p.epic_lambda, p.ric_sp_size, p.ric_slic_type, p.use_post_proc,
        p.fgs_lambda, p.fgs_sigma, p.use_variational_refinement)

    def bgr(im):  # RLOF wants 8-bit 3-channel images (cross support region segments by colour)
        return cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) if im.ndim == 2 else cv2.cvtColor(im, cv2.COLOR_RGB2BGR)

    return r.calc(bgr(image0), bgr(image1), None)


def _run_farneback(image0, image1, p: FarnebackParams):
    import cv2

    f = cv2.FarnebackOpticalFlow_create(p.num_levels, p.pyr_scale, p.fast_pyramids, p.win_size, p.num_iters,
                                        p.poly_n, p.poly_sigma, cv2.OPTFLOW_FARNEBACK_GAUSSIAN if p.gaussian_window else 0)
    return f.calc(_gray(image0), _gray(image1), None)


@dataclass(frozen=True)
class _Method:
    params: type
    run: Callable[[np.ndarray, np.ndarray, Any], np.ndarray]
    summary: str


METHODS: Mapping[str, _Method] = {
    "dis_deepflow": _Method(DISDeepFlowParams, _run_dis_deepflow,
                            "DIS at full resolution + DeepFlow energy on the top pyramid levels (default)"),
    "deepflow": _Method(DeepFlowParams, _run_deepflow, "OpenCV DeepFlow (variational, coarse-to-fine)"),
    "dis": _Method(DISParams, _run_dis, "OpenCV DIS with variational refinement"),
    "tvl1": _Method(TVL1Params, _run_tvl1, "OpenCV Dual TV-L1"),
    "rlof": _Method(RLOFParams, _run_rlof, "OpenCV dense RLOF (robust local flow + EPIC interpolation)"),
    "farneback": _Method(FarnebackParams, _run_farneback, "OpenCV Farneback polynomial expansion"),
}
"""Registry of methods: name -> (parameter dataclass, backend, one-line summary). Read-only."""


def _method(name: str) -> _Method:
    if not isinstance(name, str) or name not in METHODS:
        raise ValueError(f"unknown optical-flow method {name!r}; choose from {', '.join(METHODS)}")
    return METHODS[name]


def _parse_value(text: str, typ, where: str):
    if typ is bool:
        t = text.strip().lower()
        if t in ("1", "true", "yes", "on"):
            return True
        if t in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"{where}: expected a boolean (true/false), got {text!r}")
    try:
        if typ is int:
            return int(text)
        if typ is float:
            return float(text)
    except ValueError:
        raise ValueError(f"{where}: expected {'an int' if typ is int else 'a float'}, got {text!r}") from None
    return text


def resolve_params(method: str, params: Any = None):
    """The full, validated parameter dataclass of `method`.

    Args:
        method: one of ``METHODS``.
        params: None (defaults), an instance of the method's dataclass, or a mapping of overrides;
            mapping values may be typed or strings (as from ``--param key=value``).

    Returns:
        A frozen dataclass instance holding every parameter (the cache key uses all of them).

    Raises:
        ValueError: unknown method or key, a value of the wrong type, or one out of range; the
            message names the method and the field.
    """
    spec = _method(method)
    cls = spec.params
    if params is None:
        return cls()
    if isinstance(params, cls):
        return params
    if dataclasses.is_dataclass(params):
        raise ValueError(f"method {method!r} takes {cls.__name__}, not {type(params).__name__}")
    if not isinstance(params, Mapping):
        raise ValueError(f"params for {method!r} must be None, a {cls.__name__} or a mapping, not {type(params).__name__}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    values = {}
    for key, value in params.items():
        if key not in hints:
            raise ValueError(f"{method}: unknown parameter {key!r} (known: {', '.join(names)})")
        typ = hints[key]
        where = f"{method} parameter {key}={value!r} ({cls.__name__}.{key})"
        if isinstance(value, str) and typ is not str:
            value = _parse_value(value, typ, where)
        elif typ is float and isinstance(value, int | np.integer | np.floating) and not isinstance(value, bool):
            value = float(value)
        elif typ is int and isinstance(value, np.integer):
            value = int(value)
        if not isinstance(value, typ) or (typ is int and isinstance(value, bool)):
            raise ValueError(f"{where}: expected {typ.__name__}, got {type(value).__name__}")
        values[key] = value
    return cls(**values)


# --------------------------------------------------------------------------------------------------
# Estimation and cache
# --------------------------------------------------------------------------------------------------


def _check_images(image0, image1) -> None:
    for name, im in (("image0", image0), ("image1", image1)):
        if not isinstance(im, np.ndarray):
            raise ValueError(f"{name} must be a numpy array, got {type(im).__name__}")
        if im.dtype != np.uint8:
            raise ValueError(f"{name} has dtype {im.dtype}; expected uint8 RGB [H, W, 3]")
        if not (im.ndim == 2 or (im.ndim == 3 and im.shape[2] == 3)):
            raise ValueError(f"{name} has shape {im.shape}; expected uint8 RGB [H, W, 3] (or grey [H, W])")
        if min(im.shape[:2]) < 16:
            raise ValueError(f"{name} has shape {im.shape}; optical flow needs at least 16x16 pixels")
    if image0.shape != image1.shape:
        raise ValueError(f"image1 has shape {image1.shape} but image0 has shape {image0.shape}; they must match")


def _params_json(params) -> str:
    return json.dumps(dataclasses.asdict(params), sort_keys=True, allow_nan=True)


def flow_cache_key(image0: np.ndarray, image1: np.ndarray, method: str = DEFAULT_METHOD, params: Any = None) -> str:
    """Hex SHA-256 naming the flow of (image0 -> image1) under `method` and its resolved `params`.

    Covers the cache format version, the OpenCV version, the method, every parameter (defaults
    included, so a changed default also invalidates), and both images' shape, dtype and bytes.
    """
    import cv2

    p = resolve_params(method, params)
    h = hashlib.sha256()
    for part in (f"fgjax-flow-cache-v{CACHE_FORMAT_VERSION}", f"opencv-{cv2.__version__}", method, _params_json(p)):
        h.update(part.encode())
        h.update(b"\0")
    for im in (image0, image1):
        a = np.ascontiguousarray(im)
        h.update(f"{a.shape}{a.dtype.str}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


_atomic_write = atomic_write  # the shared mechanism (fgjax/io.py)


def _cache_path(cache_dir: Path, method: str, key: str) -> Path:
    return Path(cache_dir) / f"{method}-{key[:40]}.npz"


def _cache_load(path: Path, key: str, shape: tuple[int, int]) -> np.ndarray | None:
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:  # we own (and close) the handle
            if str(z["key"]) != key:
                return None
            flow = z["flow"]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None  # absent, truncated or foreign: recompute and overwrite
    if flow.shape != (*shape, 2) or flow.dtype != np.float32:
        return None
    return flow


def _estimate(image0, image1, method, params, cache_dir) -> tuple[np.ndarray, bool]:
    """(flow, from_cache)."""
    import cv2

    _check_images(image0, image1)
    spec = _method(method)
    p = resolve_params(method, params)
    key = path = None
    if cache_dir is not None:
        cache_dir = Path(cache_dir)
        if cache_dir.exists() and not cache_dir.is_dir():
            raise ValueError(f"cache folder {cache_dir} exists and is not a folder")
        key = flow_cache_key(image0, image1, method, p)
        path = _cache_path(cache_dir, method, key)
        hit = _cache_load(path, key, image0.shape[:2])
        if hit is not None:
            return hit, True
    try:
        flow = np.ascontiguousarray(spec.run(image0, image1, p), dtype=np.float32)
    except cv2.error as e:  # OpenCV's own message is terse and names no parameters
        raise RuntimeError(f"{method} failed on images of shape {image0.shape} with {p}: {e}") from e
    if flow.shape != (*image0.shape[:2], 2):  # a backend contract violation, not user error
        raise RuntimeError(f"{method} returned flow of shape {flow.shape} for images of shape {image0.shape}")
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = json.dumps({"method": method, "params": dataclasses.asdict(p), "format": CACHE_FORMAT_VERSION})
        _atomic_write(path, lambda f: np.savez(f, flow=flow, key=np.array(key), meta=np.array(meta)))
    return flow, False


def estimate_flow(
    image0: UInt8[np.ndarray, "H W 3"],
    image1: UInt8[np.ndarray, "H W 3"],
    method: str = DEFAULT_METHOD,
    params: Any = None,
    *,
    cache_dir: str | os.PathLike | None = None,
) -> Float32[np.ndarray, "H W 2"]:
    """Dense forward optical flow from `image0` to `image1`.

    u(j, i) = (dx, dy) such that image0 at pixel (j, i) matches image1 at (j + dx, i + dy).

    Args:
        image0: uint8 RGB ``[H, W, 3]`` (or grey ``[H, W]``), the frame the flow lives on.
        image1: same shape and dtype, the next frame.
        method: one of ``METHODS`` (default ``"dis_deepflow"``).
        params: None, the method's parameter dataclass, or a mapping of overrides
            (see `resolve_params`).
        cache_dir: if given, the flow is read from / written to ``cache_dir`` under a key of both
            images, the method and all resolved parameters (`flow_cache_key`); writes are atomic.

    Returns:
        float32 ``[H, W, 2]`` flow in pixels.

    Raises:
        ValueError: bad images (naming which and why), unknown method or parameter.

    Example:
        >>> flow = estimate_flow(frame0, frame1, "dis", {"finest_scale": 1})
    """
    return _estimate(image0, image1, method, params, cache_dir)[0]


# --------------------------------------------------------------------------------------------------
# Forward-backward consistency
# --------------------------------------------------------------------------------------------------


def _bilinear(field: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Sample `field` [H, W, C] at float pixel coordinates (x, y) (clamped to the image)."""
    h, w = field.shape[:2]
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.intp), w - 2 if w > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.intp), h - 2 if h > 1 else 0)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    top = field[y0, x0] * (1 - fx) + field[y0, x1] * fx
    bottom = field[y1, x0] * (1 - fx) + field[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _check_flow_pair(flow_fw, flow_bw) -> None:
    for name, f in (("flow_fw", flow_fw), ("flow_bw", flow_bw)):
        if not isinstance(f, np.ndarray) or f.ndim != 3 or f.shape[2] != 2:
            raise ValueError(f"{name} must be a [H, W, 2] array, got {getattr(f, 'shape', type(f).__name__)}")
    if flow_fw.shape != flow_bw.shape:
        raise ValueError(f"flow_bw has shape {flow_bw.shape} but flow_fw has shape {flow_fw.shape}")


def forward_backward_error(
    flow_fw: Float[np.ndarray, "H W 2"], flow_bw: Float[np.ndarray, "H W 2"]
) -> tuple[Float32[np.ndarray, "H W"], Float32[np.ndarray, "H W"], Bool[np.ndarray, "H W"]]:
    """Forward-backward residual of a flow pair.

    With w_f the forward flow at x and w_b the backward flow sampled bilinearly at x + w_f,
    returns (|w_f + w_b|^2, |w_f|^2 + |w_b|^2, inside) where `inside` says x + w_f lands in frame1
    (pixel centres, [0, W-1] x [0, H-1]) and both flows are finite there.
    """
    _check_flow_pair(flow_fw, flow_bw)
    h, w = flow_fw.shape[:2]
    fw = flow_fw.astype(np.float32)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    x1 = xs + fw[..., 0]
    y1 = ys + fw[..., 1]
    finite_fw = np.isfinite(fw).all(-1)
    inside = finite_fw & (x1 >= 0) & (x1 <= w - 1) & (y1 >= 0) & (y1 <= h - 1)
    bw = _bilinear(flow_bw.astype(np.float32), np.where(inside, x1, 0), np.where(inside, y1, 0))
    inside &= np.isfinite(bw).all(-1)
    with np.errstate(invalid="ignore", over="ignore"):
        residual = np.sum((fw + bw) ** 2, -1)
        magnitude = np.sum(fw**2, -1) + np.sum(bw**2, -1)
    return residual.astype(np.float32), magnitude.astype(np.float32), inside


def forward_backward_mask(
    flow_fw: Float[np.ndarray, "H W 2"],
    flow_bw: Float[np.ndarray, "H W 2"],
    *,
    alpha: float = 0.01,
    beta: float = 0.5,
) -> Bool[np.ndarray, "H W"]:
    """Pixels of frame0 whose forward flow is confirmed by the backward flow.

    Consistent when |w_f + w_b|^2 < alpha (|w_f|^2 + |w_b|^2) + beta (Sundaram, Brox, Keutzer,
    ECCV 2010, eq. 5; the defaults are theirs), w_b sampled at x + w_f, and x + w_f inside frame1.
    Occluded and out-of-view pixels come out False.
    """
    if not (alpha >= 0 and beta >= 0 and math.isfinite(alpha) and math.isfinite(beta)):
        raise ValueError(f"forward_backward_mask needs finite alpha >= 0 and beta >= 0, got alpha={alpha}, beta={beta}")
    residual, magnitude, inside = forward_backward_error(flow_fw, flow_bw)
    with np.errstate(invalid="ignore"):
        return inside & (residual < alpha * magnitude + beta)


# --------------------------------------------------------------------------------------------------
# Files: .flo, .npy, images
# --------------------------------------------------------------------------------------------------


def read_flo(path: str | os.PathLike) -> Float32[np.ndarray, "H W 2"]:
    """Read a Middlebury .flo file ('PIEH', int32 width, int32 height, float32 (u, v) row-major).

    Values are returned exactly as stored; unknown flow (|value| > 1e9) is kept as is (see
    `flow_valid_mask`).

    Raises:
        FileNotFoundError: no such file.
        ValueError: bad magic, implausible size, or a body of the wrong length (names the file).
    """
    path = Path(path)
    data = path.read_bytes()
    if len(data) < 12:
        raise ValueError(f"{path}: too short for a .flo header ({len(data)} bytes; need 12)")
    if data[:4] != FLO_MAGIC:
        raise ValueError(f"{path}: bad .flo magic {data[:4]!r} (expected {FLO_MAGIC!r})")
    w, h = (int(v) for v in np.frombuffer(data, "<i4", 2, 4))
    if not (0 < w < 1 << 16 and 0 < h < 1 << 16):
        raise ValueError(f"{path}: implausible .flo size width={w} height={h}")
    need = 12 + 8 * w * h
    if len(data) != need:
        raise ValueError(f"{path}: .flo header says {w}x{h} ({need} bytes) but the file has {len(data)} bytes")
    return np.frombuffer(data, "<f4", 2 * w * h, 12).reshape(h, w, 2).astype(np.float32)


def _check_flow_array(flow, where: str) -> np.ndarray:
    if not isinstance(flow, np.ndarray):
        raise ValueError(f"{where}: flow must be a numpy array, got {type(flow).__name__}")
    if flow.ndim != 3 or flow.shape[2] != 2 or flow.shape[0] < 1 or flow.shape[1] < 1:
        raise ValueError(f"{where}: flow has shape {flow.shape}; expected [H, W, 2]")
    if not np.issubdtype(flow.dtype, np.floating):
        raise ValueError(f"{where}: flow has dtype {flow.dtype}; expected a float type")
    return flow


def write_flo(path: str | os.PathLike, flow: Float[np.ndarray, "H W 2"]) -> None:
    """Write `flow` as a Middlebury .flo file, atomically. Nothing is written when `flow` is invalid."""
    path = Path(path)
    flow = _check_flow_array(flow, str(path))
    h, w = flow.shape[:2]
    body = np.ascontiguousarray(flow, dtype="<f4").tobytes()
    header = FLO_MAGIC + np.array([w, h], "<i4").tobytes()
    _atomic_write(path, lambda f: f.write(header + body))


def save_flow(path: str | os.PathLike, flow: Float[np.ndarray, "H W 2"]) -> None:
    """Write `flow` to `path` (.npy float32 or .flo by suffix), atomically."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".flo":
        return write_flo(path, flow)
    if suffix != ".npy":
        raise ValueError(f"{path}: flow files must end in .npy or .flo")
    arr = np.ascontiguousarray(_check_flow_array(flow, str(path)), dtype=np.float32)
    _atomic_write(path, lambda f: np.save(f, arr))


def flow_valid_mask(flow: Float[np.ndarray, "H W 2"]) -> Bool[np.ndarray, "H W"]:
    """Pixels with known flow: finite and |u|, |v| <= 1e9 (the .flo 'unknown' convention)."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(flow).all(-1) & (np.abs(flow) <= FLO_UNKNOWN).all(-1)


def load_flow(path: str | os.PathLike, *, shape: tuple[int, int] | None = None) -> Float32[np.ndarray, "H W 2"]:
    """Import a precomputed flow (from RAFT or any estimator) from .flo or .npy.

    Accepts ``[H, W, 2]``, or ``[2, H, W]`` (PyTorch layout; transposed here), in any float dtype.
    Unknown values (|value| > 1e9, the .flo convention) and non-finite ones become NaN.

    Args:
        path: a .flo or .npy file.
        shape: expected (H, W), e.g. of the images the flow belongs to.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unsupported suffix, pickled or non-float data, wrong shape (names the file).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".flo":
        flow = read_flo(path)
    elif suffix == ".npy":
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file")
        with open(path, "rb") as fh:  # our handle, closed even when numpy gives up half-way
            try:
                flow = np.load(fh, allow_pickle=False)
            except (ValueError, EOFError, OSError, zipfile.BadZipFile) as e:
                raise ValueError(f"{path}: not a plain .npy array ({e})") from None
            if not isinstance(flow, np.ndarray):
                flow.close()
                raise ValueError(f"{path}: holds an .npz archive, not a .npy array")
        if flow.ndim == 3 and flow.shape[0] == 2 and flow.shape[2] != 2:
            flow = flow.transpose(1, 2, 0)  # [2, H, W] -> [H, W, 2]
    else:
        raise ValueError(f"{path}: cannot import flow from {suffix or 'a file without suffix'!r}; use .flo or .npy")
    _check_flow_array(flow, str(path))
    if shape is not None and flow.shape[:2] != tuple(shape):
        raise ValueError(f"{path}: flow has shape {flow.shape[:2]} (H, W) but the images are {tuple(shape)}")
    flow = flow.astype(np.float32)
    flow[~flow_valid_mask(flow)] = np.nan
    return flow


def read_image(path: str | os.PathLike, *, background: int = 255) -> UInt8[np.ndarray, "H W 3"]:
    """Read an image file as uint8 RGB ``[H, W, 3]``.

    Grey images are replicated to RGB; 16-bit images are scaled to 8 bits; RGBA images are
    composited over a grey level `background` (255 = white, as D-NeRF's white background).
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such image file")
    im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if im is None:
        raise ValueError(f"{path}: cannot decode image (not an image, or truncated)")
    if im.dtype == np.uint16:
        im = (im // 257).astype(np.uint8)
    elif im.dtype != np.uint8:
        raise ValueError(f"{path}: unsupported pixel type {im.dtype}; expected 8- or 16-bit")
    if im.ndim == 2:
        return cv2.cvtColor(im, cv2.COLOR_GRAY2RGB)
    if im.shape[2] == 4:
        rgb = cv2.cvtColor(im, cv2.COLOR_BGRA2RGBA).astype(np.float32)
        a = rgb[..., 3:] / 255.0
        return np.round(rgb[..., :3] * a + background * (1.0 - a)).astype(np.uint8)
    if im.shape[2] == 3:
        return cv2.cvtColor(im, cv2.COLOR_BGR2RGB)
    raise ValueError(f"{path}: unsupported channel count {im.shape[2]}")


# --------------------------------------------------------------------------------------------------
# Sequences
# --------------------------------------------------------------------------------------------------


def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def list_frames(images: str | os.PathLike) -> list[Path]:
    """Image files of a folder or a glob pattern, sorted by file name (digit runs compared as
    numbers, so frame_2 < frame_10)."""
    s = str(images)
    p = Path(s)
    if p.is_dir():
        files = [q for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_SUFFIXES]
        where = f"folder {p}"
    elif globlib.has_magic(s):
        files = [Path(q) for q in globlib.glob(s) if Path(q).is_file()]
        where = f"pattern {s!r}"
    elif p.exists():
        raise ValueError(f"--images {p}: expected a folder or a glob pattern, not a single file")
    else:
        raise FileNotFoundError(f"--images {p}: no such folder")
    if not files:
        raise ValueError(f"{where} holds no image files ({', '.join(IMAGE_SUFFIXES)})")
    return sorted(files, key=_natural_key)


def frames_from_transforms(scene_dir: str | os.PathLike, split: str = "train") -> tuple[list[Path], list[float]]:
    """Frames of a nerfstudio / D-NeRF scene ordered by time: reads ``transforms_{split}.json``.

    ``frames[*].file_path`` is relative to `scene_dir` and may lack the extension (D-NeRF writes
    './train/r_000'); ``frames[*].time`` orders them (ties keep file order).

    Returns:
        (paths, times), both in time order.

    Raises:
        FileNotFoundError: no transforms file, or a frame's image is missing (names the frame index).
        ValueError: malformed JSON or a missing/wrong field (names the file and the field).
    """
    scene = Path(scene_dir)
    tf = scene / f"transforms_{split}.json"
    if not tf.is_file():
        raise FileNotFoundError(f"{tf}: no such file (expected a nerfstudio/D-NeRF scene folder)")
    try:
        meta = json.loads(tf.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{tf}: not valid JSON ({e})") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{tf}: field 'frames' is missing or empty")
    items = []
    for k, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise ValueError(f"{tf}: frames[{k}] is not an object")
        fp = fr.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise ValueError(f"{tf}: frames[{k}].file_path is missing or not a string")
        t = fr.get("time")
        if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
            raise ValueError(f"{tf}: frames[{k}].time is missing or not a number (got {t!r})")
        path = scene / fp
        if not path.is_file():
            cands = [path.with_name(path.name + s) for s in (".png", ".jpg", ".jpeg", ".PNG", ".JPG")]
            found = [c for c in cands if c.is_file()]
            if not found:
                raise FileNotFoundError(f"{tf}: frames[{k}].file_path {fp!r}: no such image (tried {path} and "
                                        f"{', '.join(c.suffix for c in cands)})")
            path = found[0]
        items.append((float(t), k, path))
    items.sort(key=lambda it: (it[0], it[1]))
    return [it[2] for it in items], [it[0] for it in items]


def _fmt_seconds(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


_OUTPUT_NAME = re.compile(r"^(flow_\d{5}\.(npy|flo)|flow_bw_\d{5}\.(npy|flo)|fbmask_\d{5}\.png)$")


class _Staging:
    """Output folder whose files appear only on success: files are written to a hidden staging
    folder inside it and moved into place at the end; on failure the staging folder (and any
    folder this created) is removed, so nothing is left behind. On success, outputs of an earlier
    run that this run did not produce (same naming scheme) are removed, so that the folder matches
    its manifest."""

    def __init__(self, out_dir: Path):
        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise ValueError(f"--out {self.out_dir}: exists and is not a folder")
        self.created: list[Path] = []
        for d in reversed([self.out_dir, *self.out_dir.parents]):
            if not d.exists():
                d.mkdir()
                self.created.append(d)
        self.tmp = Path(tempfile.mkdtemp(dir=self.out_dir, prefix=".fgjax-flow-staging-"))
        self.names: list[str] = []

    def path(self, name: str) -> Path:
        self.names.append(name)
        return self.tmp / name

    def commit(self) -> None:
        for name in self.names:
            os.replace(self.tmp / name, self.out_dir / name)
        self.tmp.rmdir()
        keep = set(self.names)
        for q in self.out_dir.iterdir():
            if q.name not in keep and _OUTPUT_NAME.match(q.name) and q.is_file():
                q.unlink()

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)
        for d in reversed(self.created):
            try:
                d.rmdir()
            except OSError:
                break


def _save_mask(path: Path, mask: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255)
    if not ok:
        raise RuntimeError(f"{path}: PNG encoding failed")
    _atomic_write(path, lambda f: f.write(buf.tobytes()))


def _check_frames(frames: Sequence[Path], background: int) -> tuple[int, int]:
    if len(frames) < 2:
        raise ValueError(f"need at least 2 frames for optical flow, got {len(frames)}")
    shape = first = None
    for p in frames:
        im = read_image(p, background=background)
        if shape is None:
            shape, first = im.shape, p
        elif im.shape != shape:
            raise ValueError(f"{p}: image is {im.shape[1]}x{im.shape[0]} but {first} is {shape[1]}x{shape[0]}; "
                             "all frames must have the same size")
    if min(shape[:2]) < 16:
        raise ValueError(f"{frames[0]}: images are {shape[1]}x{shape[0]}; optical flow needs at least 16x16 pixels")
    return shape[:2]


def _check_common(fmt: str, fb_alpha: float, fb_beta: float) -> None:
    if fmt not in ("npy", "flo"):
        raise ValueError(f"--format {fmt!r}: choose 'npy' or 'flo'")
    if not (math.isfinite(fb_alpha) and math.isfinite(fb_beta) and fb_alpha >= 0 and fb_beta >= 0):
        raise ValueError(f"forward-backward thresholds must be finite and >= 0, got alpha={fb_alpha}, beta={fb_beta}")


def _write_sequence(out_dir, n, produce, *, fmt, method, params, shape, backward, fb_alpha, fb_beta, progress) -> dict:
    """Shared writer of `estimate_sequence` / `import_sequence`. produce(k) -> (entry, fw, bw|None,
    note) for pair k; entry already names the frames/sources."""
    if progress is True:
        progress = sys.stderr  # looked up now, not at import (tests and callers may swap it)
    elif progress is False:
        progress = None
    stage = _Staging(Path(out_dir))
    try:
        pairs = []
        t_start = time.perf_counter()
        for k in range(n):
            t0 = time.perf_counter()
            entry, fw, bw, note = produce(k)
            entry = {"index": k, **entry, "forward": f"flow_{k:05d}.{fmt}"}
            save_flow(stage.path(entry["forward"]), fw)
            if bw is not None:
                mask = forward_backward_mask(fw, bw, alpha=fb_alpha, beta=fb_beta)
                entry.update(backward=f"flow_bw_{k:05d}.{fmt}", mask=f"fbmask_{k:05d}.png",
                             consistent_fraction=round(float(mask.mean()), 6))
                save_flow(stage.path(entry["backward"]), bw)
                _save_mask(stage.path(entry["mask"]), mask)
            pairs.append(entry)
            if progress is not None:
                now = time.perf_counter()
                avg = (now - t_start) / (k + 1)
                print(f"[flow] pair {k + 1}/{n} {note}: {now - t0:.2f} s, {avg:.2f} s/pair, "
                      f"ETA {_fmt_seconds(avg * (n - k - 1))}", file=progress, flush=True)
        manifest = {
            "format": 1,
            "convention": "forward flow frame0 -> frame1 on frame0's pixel grid, float32 [H, W, 2] (dx, dy) pixels",
            "method": method,
            "params": params,
            "height": int(shape[0]),
            "width": int(shape[1]),
            "backward": backward,
            "fb_alpha": fb_alpha if backward else None,
            "fb_beta": fb_beta if backward else None,
            "pairs": pairs,
        }
        text = json.dumps(manifest, indent=1).encode()
        _atomic_write(stage.path("flows.json"), lambda f: f.write(text))
        stage.commit()
    except BaseException:
        stage.abort()
        raise
    return manifest


def estimate_sequence(
    frames: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    method: str = DEFAULT_METHOD,
    params: Any = None,
    backward: bool = False,
    cache_dir: str | os.PathLike | None = None,
    fmt: str = "npy",
    times: Sequence[float] | None = None,
    fb_alpha: float = 0.01,
    fb_beta: float = 0.5,
    background: int = 255,
    progress: TextIO | bool | None = True,
) -> dict:
    """Flow between consecutive frames, written to `out_dir`.

    Pair k (frames[k] -> frames[k+1]) gives ``flow_{k:05d}.{fmt}``; with `backward` also
    ``flow_bw_{k:05d}.{fmt}`` (frames[k+1] -> frames[k]) and ``fbmask_{k:05d}.png`` (255 where
    `forward_backward_mask` holds), plus ``flows.json``, a manifest of frames, pairs and parameters.
    All inputs are checked before any flow is computed; outputs appear only when every pair
    succeeded (the cache, if any, keeps finished pairs, so a rerun resumes).

    Args:
        frames: image files, in order.
        out_dir: output folder (created if needed).
        method, params: as in `estimate_flow`.
        backward: also compute backward flow and forward-backward masks.
        cache_dir: flow cache folder (see `estimate_flow`).
        fmt: "npy" or "flo".
        times: optional time stamp per frame, recorded in the manifest.
        fb_alpha, fb_beta: `forward_backward_mask` thresholds.
        background: grey level RGBA frames are composited over.
        progress: True (stderr, the default), a stream, or False/None (silent): per-pair lines
            with seconds per pair and ETA.

    Returns:
        The manifest written to ``flows.json``.
    """
    frames = [Path(f) for f in frames]
    _check_common(fmt, fb_alpha, fb_beta)
    if times is not None and len(times) != len(frames):
        raise ValueError(f"got {len(times)} times for {len(frames)} frames")
    p = resolve_params(method, params)
    shape = _check_frames(frames, background)
    images = {}

    def produce(k):
        im0 = images.pop(k, None)
        im0 = read_image(frames[k], background=background) if im0 is None else im0
        im1 = images[k + 1] = read_image(frames[k + 1], background=background)
        fw, hit = _estimate(im0, im1, method, p, cache_dir)
        bw = None
        if backward:
            bw, hit_bw = _estimate(im1, im0, method, p, cache_dir)
            hit = hit and hit_bw
        entry = {"frame0": str(frames[k]), "frame1": str(frames[k + 1])}
        if times is not None:
            entry.update(time0=float(times[k]), time1=float(times[k + 1]))
        return entry, fw, bw, f"{frames[k].name} -> {frames[k + 1].name}{' (cached)' if hit else ''}"

    return _write_sequence(out_dir, len(frames) - 1, produce, fmt=fmt, method=method, params=dataclasses.asdict(p),
                           shape=shape, backward=backward, fb_alpha=fb_alpha, fb_beta=fb_beta, progress=progress)


def import_sequence(
    flow_files: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    frames: Sequence[str | os.PathLike] | None = None,
    backward_files: Sequence[str | os.PathLike] | None = None,
    fmt: str = "npy",
    times: Sequence[float] | None = None,
    fb_alpha: float = 0.01,
    fb_beta: float = 0.5,
    background: int = 255,
    progress: TextIO | bool | None = True,
) -> dict:
    """Bring precomputed flows (RAFT or any estimator; .flo or .npy, see `load_flow`) into the
    layout of `estimate_sequence`: same file names, manifest and (with `backward_files`)
    forward-backward masks. With `frames`, the counts (pairs = frames - 1) and sizes are checked.
    Every file is validated before anything is written."""
    fws = [Path(f) for f in flow_files]
    bws = None if backward_files is None else [Path(f) for f in backward_files]
    _check_common(fmt, fb_alpha, fb_beta)
    if not fws:
        raise ValueError("no flow files to import")
    if bws is not None and len(bws) != len(fws):
        raise ValueError(f"got {len(bws)} backward flow files for {len(fws)} forward ones")
    shape = None
    if frames is not None:
        frames = [Path(f) for f in frames]
        if len(frames) != len(fws) + 1:
            raise ValueError(f"{len(fws)} flow files need {len(fws) + 1} frames, got {len(frames)}")
        if times is not None and len(times) != len(frames):
            raise ValueError(f"got {len(times)} times for {len(frames)} frames")
        shape = _check_frames(frames, background)
    for f in fws + (bws or []):  # validate every file before writing anything
        shape = load_flow(f, shape=shape).shape[:2]

    def produce(k):
        entry = {"source": str(fws[k])}
        if frames is not None:
            entry.update(frame0=str(frames[k]), frame1=str(frames[k + 1]))
            if times is not None:
                entry.update(time0=float(times[k]), time1=float(times[k + 1]))
        bw = None
        if bws is not None:
            entry["source_backward"] = str(bws[k])
            bw = load_flow(bws[k], shape=shape)
        return entry, load_flow(fws[k], shape=shape), bw, f"imported {fws[k].name}"

    return _write_sequence(out_dir, len(fws), produce, fmt=fmt, method="imported", params={}, shape=shape,
                           backward=bws is not None, fb_alpha=fb_alpha, fb_beta=fb_beta, progress=progress)


# --------------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------------


def _parse_param_args(items: Sequence[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--param {item!r}: expected key=value")
        out[key.strip()] = value.strip()
    return out


def _methods_help() -> str:
    lines = []
    for name, spec in METHODS.items():
        lines.append(f"{name}{' (default)' if name == DEFAULT_METHOD else ''}: {spec.summary}")
        for f in dataclasses.fields(spec.params):
            lines.append(f"    {f.name} = {f.default!r}")
    return "\n".join(lines)


def _build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="fgjax flow",
        description="Dense optical flow between consecutive frames (forward, frame k -> k+1), cached on disk.",
        epilog="Methods and their parameters: fgjax flow --list-methods",
    )
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--images", metavar="DIR_OR_GLOB", help="frames: a folder or a glob, sorted by file name")
    src.add_argument("--data", metavar="SCENE_DIR", help="scene with transforms_SPLIT.json; frames ordered by time")
    ap.add_argument("--split", default="train", help="with --data: read transforms_SPLIT.json (default: train)")
    ap.add_argument("--out", metavar="DIR", help="output folder")
    ap.add_argument("--method", default=DEFAULT_METHOD, help=f"one of {', '.join(METHODS)} (default: {DEFAULT_METHOD})")
    ap.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="method parameter (repeatable)")
    ap.add_argument("--backward", action="store_true", help="also backward flow and forward-backward masks")
    ap.add_argument("--cache", metavar="DIR", help="flow cache folder (keyed by frames, method and parameters)")
    ap.add_argument("--format", default="npy", choices=("npy", "flo"), help="flow file format (default: npy)")
    ap.add_argument("--fb-alpha", type=float, default=0.01, help="forward-backward test: alpha (default 0.01)")
    ap.add_argument("--fb-beta", type=float, default=0.5, help="forward-backward test: beta in px^2 (default 0.5)")
    ap.add_argument("--background", default="white", choices=("white", "black"),
                    help="RGBA frames are composited over this (default: white)")
    ap.add_argument("--import", dest="import_flow", metavar="GLOB",
                    help="import precomputed forward flows (.flo/.npy, sorted by name) instead of estimating")
    ap.add_argument("--import-backward", metavar="GLOB", help="with --import: backward flows, for masks")
    ap.add_argument("--quiet", action="store_true", help="no progress output")
    ap.add_argument("--list-methods", action="store_true", help="print methods and parameter defaults, then exit")
    return ap


def _glob_files(pattern: str, what: str) -> list[Path]:
    p = Path(pattern)
    if p.is_dir():
        files = [q for q in p.iterdir() if q.is_file() and q.suffix.lower() in (".flo", ".npy")]
    else:
        files = [Path(q) for q in globlib.glob(pattern) if Path(q).is_file()]
    if not files:
        raise FileNotFoundError(f"{what} {pattern!r}: no .flo/.npy files match")
    return sorted(files, key=_natural_key)


def _run_cli(args) -> int:
    if args.list_methods:
        print(_methods_help())
        return 0
    if args.out is None:
        raise ValueError("--out DIR is required")
    background = 255 if args.background == "white" else 0
    progress = None if args.quiet else sys.stderr
    frames = times = None
    if args.data is not None:
        frames, times = frames_from_transforms(args.data, args.split)
    elif args.images is not None:
        frames = list_frames(args.images)
    if args.import_flow is not None:
        if args.param or args.backward or args.cache:
            raise ValueError("--import takes no --param, --backward or --cache (use --import-backward for masks)")
        fws = _glob_files(args.import_flow, "--import")
        bws = _glob_files(args.import_backward, "--import-backward") if args.import_backward else None
        manifest = import_sequence(fws, args.out, frames=frames, backward_files=bws, fmt=args.format, times=times,
                                   fb_alpha=args.fb_alpha, fb_beta=args.fb_beta, background=background,
                                   progress=progress)
    else:
        if args.import_backward:
            raise ValueError("--import-backward needs --import")
        if frames is None:
            raise ValueError("give the frames with --images DIR_OR_GLOB or --data SCENE_DIR")
        params = _parse_param_args(args.param)
        manifest = estimate_sequence(frames, args.out, method=args.method, params=params, backward=args.backward,
                                     cache_dir=args.cache, fmt=args.format, times=times, fb_alpha=args.fb_alpha,
                                     fb_beta=args.fb_beta, background=background, progress=progress)
    print(f"wrote {len(manifest['pairs'])} flow pair(s) to {args.out} (manifest: flows.json)")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``fgjax flow``: parse `argv`, run, and return the exit status (2 on bad input, no traceback)."""
    args = _build_parser().parse_args(argv)
    try:
        return _run_cli(args)
    except (ValueError, FileNotFoundError, NotADirectoryError, PermissionError) as e:
        print(f"fgjax flow: error: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:  # a backend failed on valid input
        print(f"fgjax flow: failed: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
