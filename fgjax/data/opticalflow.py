"""Dense optical flow from OpenCV between two frames, with an on-disk cache, and forward-backward masks.

Related modules: `fgjax.data.flowmethods` (parameter dataclasses, backends, `METHODS`, re-exported here),
`fgjax.data.flowio` (.flo/.npy flow files, frames), `fgjax.data.flowseq` (whole sequences); the
``fgjax flow`` command is `fgjax.apps.flow`.

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
  quarter of its run time (docs/benchmarks.md, "Optical flow").
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

import dataclasses
import hashlib
import json
import math
import os
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from fgjax.data.flowmethods import (
    DEFAULT_METHOD,
    METHODS,
    DeepFlowParams,
    DISDeepFlowParams,
    DISParams,
    FarnebackParams,
    FlowMethod,
    RLOFParams,
    TVL1Params,
    get_method,
    resolve_params,
)
from fgjax.io import atomic_write

if TYPE_CHECKING:  # annotations only: jaxtyping costs ~0.5 s to import and the CLI should start fast
    from jaxtyping import Bool, Float, Float32, UInt8

__all__ = [
    "CACHE_FORMAT_VERSION",
    "DEFAULT_METHOD",
    "METHODS",
    "DISDeepFlowParams",
    "chained_tracks",
    "DISParams",
    "DeepFlowParams",
    "FarnebackParams",
    "FlowMethod",
    "RLOFParams",
    "TVL1Params",
    "estimate_flow",
    "estimate_flow_cached",
    "flow_cache_key",
    "forward_backward_error",
    "forward_backward_mask",
    "resolve_params",
]

CACHE_FORMAT_VERSION = 1


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


def estimate_flow_cached(image0, image1, method, params, cache_dir) -> tuple[np.ndarray, bool]:
    """`estimate_flow` that also says whether the flow came from the cache: (flow [H, W, 2] float32, from_cache)."""
    _check_images(image0, image1)
    spec = get_method(method)
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
        atomic_write(path, lambda f: np.savez(f, flow=flow, key=np.array(key), meta=np.array(meta)))
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
    return estimate_flow_cached(image0, image1, method, params, cache_dir)[0]


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


def chained_tracks(
    flows: Float[np.ndarray, "S H W 2"], consistent: Bool[np.ndarray, "S H W"] | None = None
) -> Float32[np.ndarray, "S+1 H W 2"]:
    """Tracks of every pixel of the first frame of a sequence, by chaining its optical flow.

    ``flows[k]`` is the flow from frame k to frame k+1 on frame k's grid; ``consistent[k]`` (optional) the pixels of
    frame k whose flow to use (e.g. `forward_backward_mask`: occlusions and flow errors come out False). A track
    starts at each pixel centre p of frame 0, p_0 = p, and moves by the flow sampled bilinearly where it lies:
    p_{k+1} = p_k + flows[k](p_k). It is lost (NaN from then on) when p_k leaves the image, lands on a pixel that
    ``consistent[k]`` rejects (nearest pixel) or where the flow is not finite.

    Returns [S+1, H, W, 2] float32: p_k - p on frame 0's grid (row 0 all zeros), NaN where lost.
    """
    flows = np.asarray(flows, np.float32)
    if flows.ndim != 4 or flows.shape[-1] != 2:
        raise ValueError(f"chained_tracks: flows must have shape [S, H, W, 2]; got {list(flows.shape)}")
    s, h, w = flows.shape[:3]
    if consistent is not None and np.shape(consistent) != (s, h, w):
        raise ValueError(f"chained_tracks: consistent must have shape {[s, h, w]}; got {list(np.shape(consistent))}")
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)  # array indices = pixel coordinates - 0.5
    x, y = xs.copy(), ys.copy()
    alive = np.ones((h, w), bool)
    out = np.full((s + 1, h, w, 2), np.nan, np.float32)
    out[0] = 0.0
    for k in range(s):
        alive &= (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
        ix = np.clip(np.rint(x).astype(np.intp), 0, w - 1)
        iy = np.clip(np.rint(y).astype(np.intp), 0, h - 1)
        if consistent is not None:
            alive &= np.asarray(consistent[k], bool)[iy, ix]
        f = _bilinear(flows[k], x, y)
        alive &= np.isfinite(f).all(-1)
        x = np.where(alive, x + np.where(alive, f[..., 0], 0.0), x)  # a lost track stays put (finite), masked
        y = np.where(alive, y + np.where(alive, f[..., 1], 0.0), y)
        alive &= (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
        out[k + 1, ..., 0] = np.where(alive, x - xs, np.nan)
        out[k + 1, ..., 1] = np.where(alive, y - ys, np.nan)
    return out
