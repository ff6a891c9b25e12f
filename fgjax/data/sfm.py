"""Camera poses of a monocular clip: incremental structure from motion (pycolmap), and the fallbacks when it
cannot register the clip (a camera held still, or turned about its centre).

- `run_sfm`: COLMAP's incremental pipeline through pycolmap (an optional dependency: ``pip install 'fgjax[video]'``):
  SIFT features, sequential matching (each frame against the next ``overlap`` frames), one shared camera
  (SIMPLE_RADIAL: f, cx, cy, k1; or SIMPLE_PINHOLE), incremental mapping. The largest model is kept. Its parallax is
  the median triangulation angle of its points: for each point, the largest angle between the rays from the camera
  centres that see it.
- `rotation_poses`: camera rotations about a fixed centre, fitted between consecutive frames
  (the rays of a static point in consecutive frames differ by the relative rotation), dense optical flow (OpenCV's
  DIS) and a 3-degree-of-freedom MSAC; no pycolmap.
- `image_motion`: how far the image content moves from frame to frame, as an angle: the median optical-flow
  magnitude divided by the focal length (degrees per frame).

Conventions: OpenCV cameras, camera-to-world 4x4 matrices; COLMAP's principal point uses the pixel-centre-at-+0.5
convention, as fgjax does, so no half-pixel shift is applied.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from fgjax.data.opticalflow import estimate_flow, forward_backward_mask

try:  # optional: fgjax[video]
    import pycolmap
except ImportError:  # pragma: no cover - depends on the environment
    pycolmap = None

__all__ = ["SfmResult", "PYCOLMAP_MISSING", "have_pycolmap", "run_sfm", "rotation_poses", "image_motion",
           "focal_from_fov", "nearest_rotation", "relative_rotation"]

PYCOLMAP_MISSING = ("pycolmap is not installed; structure from motion needs it: pip install 'fgjax[video]' "
                    "(or pass --still for a still camera)")
CAMERA_MODELS = ("SIMPLE_RADIAL", "SIMPLE_PINHOLE")


def have_pycolmap() -> bool:
    """True when pycolmap can be imported."""
    return pycolmap is not None


@dataclasses.dataclass(frozen=True)
class SfmResult:
    """What incremental SfM recovered from T frames.

    Attributes:
        K: [3, 3] shared pinhole intrinsics (pixels, centre-at-+0.5 principal point).
        k1: radial distortion of SIMPLE_RADIAL (0 for SIMPLE_PINHOLE), on normalised coordinates:
            x_d = x (1 + k1 r^2), the same model as OpenCV's first coefficient.
        c2w: [T, 4, 4] OpenCV camera-to-world (SfM units); NaN for frames not registered.
        registered: [T] bool.
        points: [P, 3] sparse points (SfM units); colors [P, 3] uint8.
        parallax_deg: median triangulation angle of the points (degrees; 0 without points).
        reprojection_error: mean reprojection error in pixels.
        models: number of models COLMAP built (the largest is kept).
    """

    K: np.ndarray
    k1: float
    c2w: np.ndarray
    registered: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    parallax_deg: float
    reprojection_error: float
    models: int

    @property
    def num_registered(self) -> int:
        return int(self.registered.sum())


def focal_from_fov(width: int, fov_deg: float) -> float:
    """Focal length in pixels of a pinhole whose horizontal field of view is ``fov_deg``: W / (2 tan(fov / 2))."""
    if not 1.0 <= fov_deg <= 170.0:
        raise ValueError(f"--fov must be in [1, 170] degrees, got {fov_deg}")
    return width / (2.0 * math.tan(math.radians(fov_deg) / 2.0))


def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to the 3x3 matrix ``m``: U diag(1, 1, det(U V^T)) V^T."""
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def _triangulation_angles(rec, centres: dict[int, np.ndarray]) -> np.ndarray:
    """[P] for each point of `rec`: the largest angle (degrees) between rays from the centres that see it."""
    out = []
    for p in rec.points3D.values():
        ids = {el.image_id for el in p.track.elements}
        rays = np.array([p.xyz - centres[i] for i in ids if i in centres])
        if len(rays) < 2:
            continue
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        cos = np.clip(rays @ rays.T, -1.0, 1.0)
        out.append(math.degrees(math.acos(float(cos.min()))))
    return np.asarray(out, np.float64)


@contextlib.contextmanager
def _quiet_colmap(verbose: bool):
    """COLMAP logs every step at INFO to stderr; keep only errors unless ``verbose``."""
    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = old if verbose else 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def run_sfm(images: np.ndarray, *, camera_model: str = "SIMPLE_RADIAL", overlap: int = 10,
            threads: int | None = None, seed: int = 0, max_mapping_s: float = 300.0,
            work_dir: str | os.PathLike | None = None, verbose: bool = False,
            log: Callable[[str], None] = print) -> SfmResult:
    """Incremental SfM on frames ``images`` [T, H, W, 3] uint8 RGB (one camera).

    Args:
        images: the frames, in order (sequential matching pairs frame i with i + 1 .. i + overlap, and with
            frames at quadratic offsets).
        camera_model: "SIMPLE_RADIAL" or "SIMPLE_PINHOLE" (one camera shared by all frames).
        overlap: the sequential matcher's window.
        threads: CPU threads for COLMAP (default: all, at most 4).
        seed: COLMAP's random seed (results are repeatable for a given seed and thread count).
        max_mapping_s: stop the incremental mapping after this many seconds (COLMAP's ``max_runtime_seconds``;
            what is registered by then is kept).
        work_dir: folder for COLMAP's database and images (default: a temporary folder, removed after).
        verbose: let COLMAP log at INFO level.
        log: progress lines.

    Returns:
        The `SfmResult` of the largest model; every frame unregistered when COLMAP builds none.

    Raises:
        ImportError: pycolmap is missing (`PYCOLMAP_MISSING`).
    """
    if pycolmap is None:
        raise ImportError(PYCOLMAP_MISSING)
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera model must be one of {', '.join(CAMERA_MODELS)}, got {camera_model!r}")
    t, h, w = images.shape[:3]
    threads = threads or min(os.cpu_count() or 1, 4)
    own = work_dir is None
    work = Path(tempfile.mkdtemp(prefix="fgjax-sfm-")) if own else Path(work_dir)
    try:
        img_dir = work / "images"
        img_dir.mkdir(parents=True, exist_ok=True)
        names = [f"{i:05d}.png" for i in range(t)]
        for name, img in zip(names, images, strict=True):
            cv2.imwrite(str(img_dir / name), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        db = work / "database.db"
        if db.exists():
            db.unlink()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        extract = pycolmap.FeatureExtractionOptions()
        extract.num_threads = threads
        match = pycolmap.FeatureMatchingOptions()
        match.num_threads = threads
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = overlap
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = threads
        opts.random_seed = seed
        opts.min_model_size = 3
        opts.max_runtime_seconds = int(max_mapping_s)
        (work / "sparse").mkdir(exist_ok=True)
        with _quiet_colmap(verbose):
            pycolmap.extract_features(db, img_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=extract)
            log(f"sfm: SIFT features of {t} frames")
            pycolmap.match_sequential(db, matching_options=match, pairing_options=pairing)
            log(f"sfm: sequential matching (overlap {overlap})")
            models = pycolmap.incremental_mapping(db, img_dir, work / "sparse", options=opts)
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)
    c2w = np.full((t, 4, 4), np.nan)
    registered = np.zeros(t, bool)
    fx = focal_from_fov(w, 60.0)
    K, k1 = np.array([[fx, 0, w / 2], [0, fx, h / 2], [0, 0, 1.0]]), 0.0
    if not models:
        return SfmResult(K, k1, c2w, registered, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), 0.0, float("nan"), 0)
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    index = {name: i for i, name in enumerate(names)}
    centres = {}
    for image_id, im in rec.images.items():
        if not im.has_pose:
            continue
        m = np.eye(4)
        m[:3] = im.cam_from_world().matrix()
        i = index[im.name]
        c2w[i] = np.linalg.inv(m)
        registered[i] = True
        centres[image_id] = c2w[i, :3, 3]
    cam = next(iter(rec.cameras.values()))
    K = np.asarray(cam.calibration_matrix(), np.float64)
    k1 = float(cam.params[3]) if camera_model == "SIMPLE_RADIAL" else 0.0
    pts = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    cols = np.array([p.color for p in rec.points3D.values()], np.uint8).reshape(-1, 3)
    angles = _triangulation_angles(rec, centres)
    return SfmResult(K, k1, c2w, registered, pts, cols, float(np.median(angles)) if len(angles) else 0.0,
                     float(rec.compute_mean_reprojection_error()), len(models))


def _flow_pairs(images: np.ndarray, pairs: list[tuple[int, int]], grid: int = 6):
    """For each frame pair (i, j): pixel positions in i and where the forward DIS flow takes them in j ([M, 2] each),
    on a grid every ``grid`` pixels, kept where the backward flow confirms the forward one."""
    for i, j in pairs:
        fw = estimate_flow(images[i], images[j], "dis")
        bw = estimate_flow(images[j], images[i], "dis")
        ok = forward_backward_mask(fw, bw)
        ys, xs = np.mgrid[grid // 2:fw.shape[0]:grid, grid // 2:fw.shape[1]:grid]
        keep = ok[ys, xs]
        a = np.stack([xs[keep] + 0.5, ys[keep] + 0.5], axis=-1).astype(np.float64)  # pixel centres
        yield a, a + fw[ys[keep], xs[keep]].astype(np.float64)


def image_motion(images: np.ndarray, focal: float, *, pairs: int = 16) -> float:
    """How far the image content moves from one frame to the next, as an angle: the median over up to ``pairs``
    evenly spaced consecutive pairs of the median optical-flow magnitude (DIS, forward-backward consistent pixels)
    divided by ``focal``, in degrees per frame (0 for fewer than 2 frames). Camera and objects both move it; the
    median follows the larger share of the image."""
    t = len(images)
    if t < 2:
        return 0.0
    starts = np.unique(np.linspace(0, t - 2, min(pairs, t - 1)).round().astype(int))
    meds = [float(np.median(np.linalg.norm(b - a, axis=1)))
            for a, b in _flow_pairs(images, [(i, i + 1) for i in starts]) if len(a)]
    return math.degrees(math.atan(float(np.median(meds)) / focal)) if meds else 0.0


def _kabsch_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation R minimising sum |b_k - R a_k|^2 over unit rays a, b [M, 3]."""
    return nearest_rotation(b.T @ a)


def relative_rotation(rays_a: np.ndarray, rays_b: np.ndarray, *, threshold: float, iters: int = 200,
                      seed: int = 0) -> tuple[np.ndarray, int]:
    """(R, inliers): the rotation with rays_b ~ R rays_a ([M, 3] unit rays of matched features) by MSAC over 3-ray
    Kabsch fits (each fit scored by sum_k min(e_k^2, threshold^2), e_k the angle between R a_k and b_k in radians, so
    that a fit is not pulled towards a second, moving group by a loose threshold), refitted twice on its inliers
    (e_k < threshold); the identity and 0 for M < 3."""
    m = len(rays_a)
    if m < 3:
        return np.eye(3), 0
    rng = np.random.default_rng(seed)

    def err2(r):  # [M] squared angles (small-angle: |R a - b|^2)
        return np.sum((rays_a @ r.T - rays_b) ** 2, axis=1)

    t2 = threshold**2
    best, best_cost = np.eye(3), np.inf
    for _ in range(iters):
        s = rng.choice(m, 3, replace=False)
        r = _kabsch_rotation(rays_a[s], rays_b[s])
        cost = float(np.minimum(err2(r), t2).sum())
        if cost < best_cost:
            best, best_cost = r, cost
    for _ in range(2):
        inl = err2(best) < t2
        if inl.sum() < 3:
            break
        best = _kabsch_rotation(rays_a[inl], rays_b[inl])
    return best, int(np.sum(err2(best) < t2))


def rotation_poses(images: np.ndarray, K: np.ndarray, *, min_share: float = 0.5,
                   log: Callable[[str], None] | None = None) -> tuple[np.ndarray, int]:
    """Rotation-only camera-to-world poses [T, 4, 4] (OpenCV; centres at the origin, frame 0 the identity) of a
    camera that turns about a fixed centre, and how many of the T - 1 frames were fitted against their key frame
    (the others against the frame before).

    For a camera that only turns, the rays r = K^-1 x~ (normalised) of a static point in frames k and i satisfy
    r_i = R_i R_k^T r_k (R: world-to-camera rotations). Each frame's rotation relative to a key frame k (frame 0 at
    first) is fitted to their optical flow on a 6-pixel grid (DIS, forward-backward consistent pixels;
    `relative_rotation`: 3-degree-of-freedom MSAC, inliers within 0.5 pixel), so the static majority of the pixels
    decides even where the background has little texture and moving hands and objects carry most of the corners.
    Fitting against a key frame rather than chaining consecutive frames keeps a nearly still camera from drifting:
    the key frame moves to the frame before only when fewer than ``min_share`` of the grid points are inliers
    (the view has turned away, or the flow broke down), and that frame is then fitted against the frame before."""
    t = len(images)
    kinv = np.linalg.inv(K)
    thr = 0.5 / K[0, 0]

    def rays(px):
        r = np.concatenate([px, np.ones((len(px), 1))], axis=1) @ kinv.T
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    def fit(k: int, i: int) -> tuple[np.ndarray, float]:
        (a, b), = _flow_pairs(images, [(k, i)])
        grid = (images.shape[1] // 6) * (images.shape[2] // 6)
        rel, n = relative_rotation(rays(a), rays(b), threshold=thr, seed=i)
        return rel, n / max(grid, 1)

    rots = [np.eye(3)]  # world-to-camera rotations
    key, on_key = 0, 0
    for i in range(1, t):
        rel, share = fit(key, i)
        if share >= min_share:
            on_key += 1
        elif key != i - 1:
            key = i - 1
            rel, share = fit(key, i)
        if share < 0.1:  # no usable flow: keep the previous rotation
            rel = np.eye(3)
        rots.append(rel @ rots[key])
    c2w = np.tile(np.eye(4), (t, 1, 1))
    c2w[:, :3, :3] = np.transpose(np.stack(rots), (0, 2, 1))
    if log is not None:
        log(f"rotation: {on_key} of {t - 1} frames fitted against their key frame")
    return c2w, on_key
