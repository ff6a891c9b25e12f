"""Optical-flow methods: one frozen parameter dataclass per OpenCV backend, the backends, the registry
`METHODS` and `resolve_params` (see `fgjax.data.opticalflow` for the methods and the flow convention)."""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

DEFAULT_METHOD = "dis_deepflow"
__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "DISDeepFlowParams",
    "DISParams",
    "DeepFlowParams",
    "FarnebackParams",
    "FlowMethod",
    "RLOFParams",
    "TVL1Params",
    "get_method",
    "resolve_params",
]

_FLT_MAX = 3.4028234663852886e38  # largest float32 (OpenCV's FLT_MAX: RLOF's least-squares norm)


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
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _blurred_float(gray: np.ndarray, sigma: float) -> np.ndarray:
    k = int(math.floor(3 * sigma)) * 2 + 1  # OpenCV DeepFlow's kernel size
    return cv2.GaussianBlur(gray.astype(np.float32), (k, k), sigma)


def _variational(p):
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


RLOF_ATTEMPTS = 6
RLOF_MIN_SIDE = 96
"""Shortest image side dense RLOF accepts. On smaller images OpenCV's dense RLOF (default settings, one
thread) gave run-to-run different fields for the same pair: all zeros, NaN, or a wrong translation
(64x80 and 48x64 textures, at every pyramid depth 1-4); at 96x120, 128x160 and 192x240 every one of
80 repeated calls was bitwise the same."""


def _run_rlof(image0, image1, p: RLOFParams):
    """OpenCV's dense RLOF on one OpenCV thread (the caller's thread count is restored): with several
    threads it returned an all-zero field on 6-25 of 60 repeated calls. Images with a side under
    `RLOF_MIN_SIDE` are refused (ValueError). An all-zero field for two images that differ, or a
    non-finite one, is computed again, up to `RLOF_ATTEMPTS` times; then it raises instead of passing
    for "no motion"."""
    if min(image0.shape[:2]) < RLOF_MIN_SIDE:
        raise ValueError(f"flow method rlof needs images at least {RLOF_MIN_SIDE} px on each side (these are "
                         f"{image0.shape[1]}x{image0.shape[0]}): OpenCV's dense RLOF is not repeatable on smaller "
                         "images; use another flow method (flow.method)")
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for _ in range(RLOF_ATTEMPTS):
            flow = _rlof_once(image0, image1, p)
            if np.all(np.isfinite(flow)) and (np.any(flow) or np.array_equal(image0, image1)):
                return flow
    finally:
        cv2.setNumThreads(threads)
    raise RuntimeError(f"OpenCV's dense RLOF returned an all-zero or non-finite flow {RLOF_ATTEMPTS} times for "
                       "two different images; use another flow method (flow.method)")


def _rlof_once(image0, image1, p: RLOFParams):
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
    f = cv2.FarnebackOpticalFlow_create(p.num_levels, p.pyr_scale, p.fast_pyramids, p.win_size, p.num_iters,
                                        p.poly_n, p.poly_sigma,
                                        cv2.OPTFLOW_FARNEBACK_GAUSSIAN if p.gaussian_window else 0)
    return f.calc(_gray(image0), _gray(image1), None)


@dataclass(frozen=True)
class FlowMethod:
    """A registered method: its parameter dataclass, its backend run(image0, image1, params) -> [H, W, 2]
    flow, and a one-line summary."""

    params: type
    run: Callable[[np.ndarray, np.ndarray, Any], np.ndarray]
    summary: str


METHODS: Mapping[str, FlowMethod] = {
    "dis_deepflow": FlowMethod(DISDeepFlowParams, _run_dis_deepflow,
                            "DIS at full resolution + DeepFlow energy on the top pyramid levels (default)"),
    "deepflow": FlowMethod(DeepFlowParams, _run_deepflow, "OpenCV DeepFlow (variational, coarse-to-fine)"),
    "dis": FlowMethod(DISParams, _run_dis, "OpenCV DIS with variational refinement"),
    "tvl1": FlowMethod(TVL1Params, _run_tvl1, "OpenCV Dual TV-L1"),
    "rlof": FlowMethod(RLOFParams, _run_rlof, "OpenCV dense RLOF (robust local flow + EPIC interpolation)"),
    "farneback": FlowMethod(FarnebackParams, _run_farneback, "OpenCV Farneback polynomial expansion"),
}
"""Registry of methods: name -> (parameter dataclass, backend, one-line summary). Read-only."""


def get_method(name: str) -> FlowMethod:
    """The `METHODS` entry of `name` (ValueError naming the known methods otherwise)."""
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
    spec = get_method(method)
    cls = spec.params
    if params is None:
        return cls()
    if isinstance(params, cls):
        return params
    if dataclasses.is_dataclass(params):
        raise ValueError(f"method {method!r} takes {cls.__name__}, not {type(params).__name__}")
    if not isinstance(params, Mapping):
        raise ValueError(f"params for {method!r} must be None, a {cls.__name__} or a mapping, "
                         f"not {type(params).__name__}")
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
