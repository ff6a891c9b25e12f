"""Dataset readers (nerfstudio, Blender/D-NeRF/LiveScene, CoNeRF/Nerfies); the writer is `fgjax.data.write`.

Every reader returns one `Scene` (see `fgjax.data.scene`): images [T, H, W, 3] float32 in
[0, 1], pinhole Ks, OpenCV world-to-camera viewmats in normalised scene units, times in
[0, 1], optional depths and masks, and the `Normalization` that maps back to world units.

Conventions of the files read and written here:

- ``transforms*.json`` (nerfstudio, Blender, D-NeRF, LiveScene): ``transform_matrix`` is an
  OpenGL/Blender camera-to-world 4x4 (camera x right, y up, z back). It is converted once, here:
  OpenCV c2w = OpenGL c2w @ diag(1, -1, -1, 1) (the same map converts back). Intrinsics
  ``fl_x, fl_y, cx, cy, w, h`` (nerfstudio, top level or per frame, per frame wins) or
  ``camera_angle_x`` [, ``camera_angle_y``] (Blender: fx = W / (2 tan(angle_x / 2)), principal
  point at the image centre (W/2, H/2)). Principal points are in the pixel-centre-at-+0.5
  convention (nerfstudio and COLMAP use it too), so no half-pixel shift is applied.
  ``file_path`` is relative to the json's folder, with or without extension, maybe './'-prefixed.
  ``time`` in [0, 1] per frame (all frames or none; none -> frame order / (T - 1)).
- Depth: per-frame ``depth_file_path`` (nerfstudio key) or, when a ``depth/`` folder sits next
  to the image folder, ``depth/<image stem>.npy|.png``. ``.npy`` holds camera z-depth in world
  units; 8/16-bit ``.png`` holds integers multiplied by the json's ``depth_scale`` (alias:
  nerfstudio's ``depth_unit_scale_factor``; default 1/1000, i.e. millimetres). 0 marks unknown
  depth, +inf is read as 0. Depths are returned in normalised units (times the scale).
- Masks: per-frame ``mask_path`` or ``mask/<image stem>.png|.npy``; integer labels kept as they
  are (channel 0 of a multi-channel PNG), returned as int32 (bool .npy stays bool).
- CoNeRF/Nerfies/HyperNeRF: ``dataset.json`` (``ids``, ``train_ids``, ``val_ids``),
  ``metadata.json`` (per id ``time_id`` or else ``warp_id`` -> time = (v - min) / (max - min)
  over all ids), ``camera/<id>.json`` (OpenCV-style: ``orientation`` is the world-to-camera
  rotation whose rows are the camera axes, ``position`` the camera centre, fx = ``focal_length``,
  fy = ``focal_length * pixel_aspect_ratio``, ``principal_point``, ``image_size`` = [W, H],
  pixel centres at +0.5 as in Nerfies' ``get_pixel_centers``), images ``rgb/<s>x/<id>.png``.
  ``scene.json`` is not used (fgjax computes its own normalisation).
- fgjax cameras are pinhole: non-zero distortion or skew is ignored with a warning (undistort
  the images beforehand for exact results); fisheye/equirectangular models are an error.

Normalisation (``normalize=True``): the one the training json records in a top-level
``normalization`` object ({"centre": [x, y, z], "scale": s}: x_normalised = (x - centre) * s; `fgjax prepare`
writes it for real captures, where the content, not the camera path, sets the scale), else
`compute_normalization` on the camera centres of the *training* split (poses only; falls back to the requested
split when there is no training split), so train/val/test loaded separately share one frame.
Pass ``normalize=False`` for world units, or a `Normalization` (e.g. ``train_scene.normalization``) to reuse one.

Errors name the file, the frame and the field: missing images -> `FileNotFoundError`
(or a warning and the frame skipped with ``skip_missing=True``); unreadable images, NaN or
non-rigid poses, inconsistent sizes, times out of [0, 1], malformed json -> `ValueError`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import imageio.v3 as iio
import numpy as np

from fgjax.data.scene import Normalization, Scene, compute_normalization, rigid_problem
from fgjax.geometry import c2w_to_viewmat, opengl_to_opencv_c2w, viewmat_to_c2w

__all__ = [
    "FrameRecord",
    "Listing",
    "detect_layout",
    "frame_intrinsics",
    "imread",
    "load_scene",
    "parse_transforms",
    "recorded_normalization",
]

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
DEPTH_EXTS = (".npy", ".png")
MASK_EXTS = (".png", ".npy")
DEFAULT_PNG_DEPTH_SCALE = 1e-3
_DISTORTION_FIELDS = ("k1", "k2", "k3", "k4", "p1", "p2")
_INTRINSIC_FIELDS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "PERSPECTIVE")


def _read_json(path: Path) -> dict[str, Any]:
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder; a transforms JSON file is expected")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: cannot parse as JSON ({e})") from e
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level, got {type(data).__name__}")
    return data


def _as_number(src: Path, where: str, field: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{src}: {where}: field `{field}` must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{src}: {where}: field `{field}` is not finite ({value!r})")
    return v


def _as_matrix(src: Path, where: str, field: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{src}: {where}: field `{field}` is not a numeric array ({e})") from e
    if arr.shape != shape:
        raise ValueError(f"{src}: {where}: field `{field}` has shape {arr.shape}, expected {shape}")
    return arr


def _check_rigid(src: Path, where: str, field: str, m: np.ndarray) -> None:
    problem = rigid_problem(m[None])
    if problem is not None:
        raise ValueError(f"{src}: {where}: `{field}` {problem[1]}")


def imread(path: Path) -> np.ndarray:
    """Decode an image file. Reads the bytes first: imageio leaks the file handle on corrupt files."""
    data = path.read_bytes()
    return np.asarray(iio.imread(data, extension=path.suffix.lower() or ".png"))


def _image_to_float(arr: np.ndarray, path: Path, background: Sequence[float] | None) -> np.ndarray:
    """Decoded image -> [H, W, 3] float32 in [0, 1]; alpha composited over `background`."""
    if arr.dtype == np.uint8:
        x = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16:
        x = arr.astype(np.float32) / 65535.0
    elif arr.dtype == bool:
        x = arr.astype(np.float32)
    elif np.issubdtype(arr.dtype, np.floating):
        x = arr.astype(np.float32)
        if not np.all(np.isfinite(x)) or x.min() < 0 or x.max() > 1:
            raise ValueError(f"{path}: float image values must be finite and in [0, 1]")
    else:
        raise ValueError(f"{path}: unsupported image dtype {arr.dtype} (expected uint8, uint16 or float)")
    if x.ndim == 2:
        x = x[..., None]
    if x.ndim != 3 or x.shape[-1] not in (1, 2, 3, 4):
        raise ValueError(f"{path}: expected an H x W image with 1-4 channels, got shape {arr.shape}")
    c = x.shape[-1]
    if c in (2, 4):
        rgb, alpha = x[..., : c - 1], x[..., c - 1 :]
        if background is not None:
            bg = np.asarray(background, dtype=np.float32).reshape(-1)
            rgb = rgb * alpha + bg * (1.0 - alpha)
        x = rgb
    if x.shape[-1] == 1:
        x = np.repeat(x, 3, axis=-1)
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def _read_depth(path: Path, png_scale: float) -> np.ndarray:
    """Depth file -> [H, W] float64 camera z-depth in world units (0 = unknown)."""
    if path.suffix.lower() == ".npy":
        d = np.load(path, allow_pickle=False)
        d = np.asarray(d, dtype=np.float64)
    else:
        raw = imread(path)
        if not np.issubdtype(raw.dtype, np.integer):
            raise ValueError(f"depth png {path} must be an integer (8/16-bit) image, got {raw.dtype}")
        d = raw.astype(np.float64) * png_scale
    if d.ndim == 3 and d.shape[-1] == 1:
        d = d[..., 0]
    if d.ndim != 2:
        raise ValueError(f"depth {path} must be [H, W], got shape {d.shape}")
    if np.any(np.isnan(d)) or np.any(d < 0):
        raise ValueError(f"depth {path} contains NaN or negative values")
    return np.where(np.isinf(d), 0.0, d)


def _read_mask(path: Path) -> np.ndarray:
    """Mask file -> [H, W] int32 labels (bool stays bool)."""
    m = np.load(path, allow_pickle=False) if path.suffix.lower() == ".npy" else imread(path)
    m = np.asarray(m)
    if m.ndim == 3:
        m = m[..., 0]
    if m.ndim != 2:
        raise ValueError(f"mask {path} must be [H, W] (or [H, W, C]), got shape {m.shape}")
    if m.dtype == bool:
        return m
    if not np.issubdtype(m.dtype, np.integer):
        raise ValueError(f"mask {path} must hold integer labels, got dtype {m.dtype}")
    return m.astype(np.int32)


def _resolve(base: Path, rel: str, exts: Sequence[str]) -> tuple[Path | None, Path]:
    """(existing file or None, the path looked for) for `rel` with or without an extension."""
    p = base / rel
    if p.is_file():
        return p, p
    if p.suffix not in exts:
        for ext in exts:
            q = p.with_name(p.name + ext)
            if q.is_file():
                return q, p
    return None, p


def _find_stem(folder: Path, stem: str, exts: Sequence[str]) -> Path | None:
    for ext in exts:
        q = folder / (stem + ext)
        if q.is_file():
            return q
    return None


def _frame_name(rel: str) -> str:
    name = rel.replace("\\", "/")
    while name.startswith("./"):
        name = name[2:]
    root, ext = os.path.splitext(name)
    return root if ext in IMAGE_EXTS else name


def _nearest_resize(a: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest-neighbour resize of [H, W] sampling at the new pixel centres."""
    rows = np.minimum(((np.arange(h) + 0.5) * a.shape[0] / h).astype(np.int64), a.shape[0] - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * a.shape[1] / w).astype(np.int64), a.shape[1] - 1)
    return a[rows][:, cols]


# ----------------------------------------------------------------------------- frame records


@dataclasses.dataclass
class FrameRecord:
    """One listed frame, before any image is read (world units, OpenCV c2w)."""

    src: Path  # the file that lists the frame (named in errors)
    where: str  # "frame 3" / "id 'abc' (frame 3)"
    field: str  # field that gave the image path
    name: str
    image: Path | None
    image_hint: Path
    c2w: np.ndarray  # [4, 4] OpenCV camera-to-world, world units
    time: float
    intr: dict[str, float | None]
    depth: Path | None = None
    depth_hint: tuple[str, Path] | None = None  # (field, path) when expected but absent
    mask: Path | None = None
    mask_hint: tuple[str, Path] | None = None


@dataclasses.dataclass
class Listing:
    frames: list[FrameRecord]
    depth_scale: float
    warn_fields: dict[str, set[str]]  # source file -> non-pinhole fields ignored


def _sibling_file(image: Path | None, hint: Path, folder: str, exts: Sequence[str]):
    """Look for `<image dir>/../<folder>/<stem>.<ext>`; (path, hint) with hint set when expected."""
    img = image if image is not None else hint
    d = img.parent.parent / folder
    if not d.is_dir():
        return None, None
    stem = _frame_name(img.name)
    found = _find_stem(d, stem, exts)
    return found, (None if found is not None else (f"{folder}/ folder", d / (stem + exts[0])))


def parse_transforms(json_path: Path, split: str | None) -> Listing:
    """Frames of a transforms json; `split` selects `{split}_filenames` (transforms.json only)."""
    meta = _read_json(json_path)
    base = json_path.parent
    frames_raw = meta.get("frames")
    if not isinstance(frames_raw, list) or not frames_raw:
        raise ValueError(f"{json_path}: field `frames` must be a non-empty list")

    model = meta.get("camera_model")
    if model is not None and str(model).upper() not in _PINHOLE_MODELS:
        raise ValueError(f"{json_path}: field `camera_model` = {model!r} is not a pinhole model")

    scale_key = "depth_scale" if "depth_scale" in meta else "depth_unit_scale_factor"
    depth_scale = DEFAULT_PNG_DEPTH_SCALE
    if scale_key in meta:
        depth_scale = _as_number(json_path, "top level", scale_key, meta[scale_key])
        if depth_scale <= 0:
            raise ValueError(f"{json_path}: field `{scale_key}` must be > 0, got {depth_scale}")

    keep: set[str] | None = None
    if split is not None:
        key = f"{split}_filenames"
        if key in meta:
            if not isinstance(meta[key], list):
                raise ValueError(f"{json_path}: field `{key}` must be a list of file paths")
            keep = {_frame_name(str(p)) for p in meta[key]}
        elif split not in ("train", "all"):
            raise ValueError(
                f"{json_path}: no field `{key}`, so split {split!r} is undefined; "
                "use split='train' or split='all' for every frame"
            )

    ignored: set[str] = set()
    frames: list[FrameRecord] = []
    raw_times: list[float | None] = []
    for i, fr in enumerate(frames_raw):
        where = f"frame {i}"
        if not isinstance(fr, dict):
            raise ValueError(f"{json_path}: {where}: expected an object, got {type(fr).__name__}")
        rel = fr.get("file_path")
        if not isinstance(rel, str) or not rel:
            raise ValueError(f"{json_path}: {where}: field `file_path` missing or not a string")
        name = _frame_name(rel)
        if keep is not None and name not in keep:
            continue
        if "transform_matrix" not in fr:
            raise ValueError(f"{json_path}: {where}: field `transform_matrix` is missing")
        tm = _as_matrix(json_path, where, "transform_matrix", fr.get("transform_matrix"), _matrix_shape(fr))
        if tm.shape == (3, 4):
            tm = np.vstack([tm, [0.0, 0.0, 0.0, 1.0]])
        _check_rigid(json_path, where, "transform_matrix", tm)
        if "time" in fr:
            t = _as_number(json_path, where, "time", fr["time"])
            if not 0.0 <= t <= 1.0:
                raise ValueError(f"{json_path}: {where}: field `time` = {t} is outside [0, 1]")
            raw_times.append(t)
        else:
            raw_times.append(None)
        intr: dict[str, float | None] = {}
        for k in _INTRINSIC_FIELDS:
            v = fr.get(k, meta.get(k))
            intr[k] = None if v is None else _as_number(json_path, where, k, v)
        for k in _DISTORTION_FIELDS:
            v = fr.get(k, meta.get(k))
            if v is not None and _as_number(json_path, where, k, v) != 0.0:
                ignored.add(k)
        image, hint = _resolve(base, rel, IMAGE_EXTS)
        f = FrameRecord(json_path, where, "file_path", name, image, hint, opengl_to_opencv_c2w(tm), 0.0, intr)
        for attr, key, folder, exts in (
            ("depth", "depth_file_path", "depth", DEPTH_EXTS),
            ("mask", "mask_path", "mask", MASK_EXTS),
        ):
            if key in fr:
                if not isinstance(fr[key], str):
                    raise ValueError(f"{json_path}: {where}: field `{key}` must be a string")
                found, want = _resolve(base, fr[key], exts)
                hint_ = None if found is not None else (f"field `{key}`", want)
            else:
                found, hint_ = _sibling_file(image, hint, folder, exts)
            setattr(f, attr, found)
            setattr(f, attr + "_hint", hint_)
        frames.append(f)
    if not frames:
        raise ValueError(f"{json_path}: no frame of `frames` is listed in `{split}_filenames`")
    have = [t is not None for t in raw_times]
    if any(have) and not all(have):
        j = have.index(False)
        raise ValueError(f"{json_path}: {frames[j].where}: field `time` is missing while other frames have it")
    n = len(frames)
    for j, f in enumerate(frames):
        f.time = raw_times[j] if all(have) else (j / (n - 1) if n > 1 else 0.0)
    return Listing(frames, depth_scale, {str(json_path): ignored} if ignored else {})


def _matrix_shape(fr: dict[str, Any]) -> tuple[int, int]:
    m = fr.get("transform_matrix")
    return (3, 4) if isinstance(m, list) and len(m) == 3 else (4, 4)


def _split_ids(ds_path: Path, ds: dict[str, Any], split: str) -> list[str]:
    key = "ids" if split == "all" else f"{split}_ids"
    ids = ds.get(key)
    if ids is None and split == "all":
        ids = list(ds.get("train_ids", [])) + list(ds.get("val_ids", []))
    if not isinstance(ids, list) or not ids or not all(isinstance(i, str) for i in ids):
        raise ValueError(f"{ds_path}: field `{key}` missing, empty or not a list of strings (split {split!r})")
    return ids


def _nerfies_camera(cam_path: Path, where: str) -> tuple[np.ndarray, dict[str, float | None], set[str]]:
    """camera/<id>.json -> (OpenCV c2w [4, 4], intrinsics at scale 1, ignored fields)."""
    cam = _read_json(cam_path)
    for k in ("orientation", "position", "focal_length", "principal_point", "image_size"):
        if k not in cam:
            raise ValueError(f"{cam_path}: {where}: field `{k}` is missing")
    rot = _as_matrix(cam_path, where, "orientation", cam["orientation"], (3, 3))
    pos = _as_matrix(cam_path, where, "position", cam["position"], (3,))
    if not np.all(np.isfinite(pos)):
        raise ValueError(f"{cam_path}: {where}: `position` has non-finite entries")
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ pos
    _check_rigid(cam_path, where, "orientation", w2c)
    f = _as_number(cam_path, where, "focal_length", cam["focal_length"])
    par = _as_number(cam_path, where, "pixel_aspect_ratio", cam.get("pixel_aspect_ratio", 1.0))
    pp = _as_matrix(cam_path, where, "principal_point", cam["principal_point"], (2,))
    size = _as_matrix(cam_path, where, "image_size", cam["image_size"], (2,))
    if not (np.all(np.isfinite(pp)) and np.all(size > 0)):
        raise ValueError(f"{cam_path}: {where}: `principal_point`/`image_size` invalid: {pp}, {size}")
    ignored = set()
    skew = _as_number(cam_path, where, "skew", cam.get("skew", 0.0))
    if skew != 0.0:
        ignored.add("skew")
    for k in ("radial_distortion", "tangential_distortion", "tangential"):
        v = cam.get(k)
        if v is not None and np.any(np.asarray(v, dtype=np.float64) != 0):
            ignored.add(k)
    intr = {
        "fl_x": f,
        "fl_y": f * par,
        "cx": float(pp[0]),
        "cy": float(pp[1]),
        "w": float(size[0]),
        "h": float(size[1]),
        "camera_angle_x": None,
        "camera_angle_y": None,
    }
    return viewmat_to_c2w(w2c), intr, ignored


def _parse_nerfies(root: Path, split: str, downscale: int) -> tuple[Listing, int]:
    """Frames of a Nerfies/CoNeRF/HyperNeRF folder; also returns the downscale still to apply."""
    ds_path = root / "dataset.json"
    ds = _read_json(ds_path)
    ids = _split_ids(ds_path, ds, split)
    all_ids = ds.get("ids") if isinstance(ds.get("ids"), list) else ids

    depth_scale = DEFAULT_PNG_DEPTH_SCALE
    if "depth_scale" in ds:
        depth_scale = _as_number(ds_path, "top level", "depth_scale", ds["depth_scale"])

    meta_path = root / "metadata.json"
    times: dict[str, float] = {}
    if meta_path.is_file():
        meta = _read_json(meta_path)
        entries = [e for e in meta.values() if isinstance(e, dict)]
        key = "time_id" if entries and all("time_id" in e for e in entries) else "warp_id"
        vals = {}
        for i in ids:
            if i not in meta or not isinstance(meta[i], dict) or key not in meta[i]:
                raise ValueError(f"{meta_path}: id {i!r}: field `{key}` is missing")
        for k, e in meta.items():
            if isinstance(e, dict) and key in e:
                vals[k] = _as_number(meta_path, f"id {k!r}", key, e[key])
        lo, hi = min(vals.values()), max(vals.values())
        times = {k: ((v - lo) / (hi - lo) if hi > lo else 0.0) for k, v in vals.items()}
    else:
        order = {k: j for j, k in enumerate(all_ids)}
        for i in ids:
            order.setdefault(i, len(order))
        n = len(order)
        times = {k: (j / (n - 1) if n > 1 else 0.0) for k, j in order.items()}

    rgb = root / "rgb"
    scaled = rgb / f"{downscale}x"
    if scaled.is_dir():
        img_dir, pre, remaining = scaled, downscale, 1
    elif (rgb / "1x").is_dir():
        img_dir, pre, remaining = rgb / "1x", 1, downscale
    else:
        have = sorted(p.name for p in rgb.iterdir()) if rgb.is_dir() else []
        raise FileNotFoundError(
            f"{root}: neither {scaled} nor {rgb / '1x'} exists (found rgb/ subfolders: {have})"
        )
    sub = f"{pre}x"

    frames: list[FrameRecord] = []
    ignored: dict[str, set[str]] = {}
    for j, cid in enumerate(ids):
        where = f"id {cid!r} (frame {j})"
        cam_path = root / "camera" / f"{cid}.json"
        c2w, intr, ign = _nerfies_camera(cam_path, where)
        if ign:
            ignored[str(cam_path)] = ign
        if pre != 1:  # Nerfies' Camera.scale(1 / pre)
            s = 1.0 / pre
            intr = dict(intr, fl_x=intr["fl_x"] * s, fl_y=intr["fl_y"] * s, cx=intr["cx"] * s, cy=intr["cy"] * s)
            intr["w"], intr["h"] = float(round(intr["w"] * s)), float(round(intr["h"] * s))
        image, hint = _resolve(img_dir, cid, IMAGE_EXTS)
        f = FrameRecord(ds_path, where, f"{split}_ids", cid, image, hint, c2w, times[cid], intr)
        for attr, folder, exts in (("depth", "depth", DEPTH_EXTS), ("mask", "mask", MASK_EXTS)):
            d = root / folder / sub if (root / folder / sub).is_dir() else root / folder
            if d.is_dir():
                found = _find_stem(d, cid, exts)
                setattr(f, attr, found)
                setattr(f, attr + "_hint", None if found else (f"{folder}/ folder", d / (cid + exts[0])))
        frames.append(f)
    return Listing(frames, depth_scale, ignored), remaining


# ----------------------------------------------------------------------------- assembly


def frame_intrinsics(f: FrameRecord, w: int, h: int) -> np.ndarray:
    """[3, 3] pinhole K of frame `f` at image size (w, h) (fl_x/fl_y/cx/cy or camera_angle_x/y)."""
    it = f.intr
    for key, actual in (("w", w), ("h", h)):
        if it.get(key) is not None and int(round(it[key])) != actual:
            raise ValueError(
                f"{f.src}: {f.where}: field `{key}` = {it[key]:g} but image {f.image} is {w}x{h} (W x H)"
            )
    if it.get("fl_x") is not None:
        fx = it["fl_x"]
        fy = it["fl_y"] if it.get("fl_y") is not None else fx
        cx = it["cx"] if it.get("cx") is not None else w / 2.0
        cy = it["cy"] if it.get("cy") is not None else h / 2.0
    elif it.get("camera_angle_x") is not None:
        ax = it["camera_angle_x"]
        if not 0.0 < ax < math.pi:
            raise ValueError(f"{f.src}: {f.where}: field `camera_angle_x` = {ax} is not in (0, pi)")
        fx = 0.5 * w / math.tan(0.5 * ax)
        ay = it.get("camera_angle_y")
        if ay is not None and not 0.0 < ay < math.pi:
            raise ValueError(f"{f.src}: {f.where}: field `camera_angle_y` = {ay} is not in (0, pi)")
        fy = 0.5 * h / math.tan(0.5 * ay) if ay is not None else fx
        cx, cy = w / 2.0, h / 2.0
    else:
        raise ValueError(
            f"{f.src}: {f.where}: no intrinsics: need `fl_x` (nerfstudio) or `camera_angle_x` (Blender)"
        )
    if fx <= 0 or fy <= 0:
        raise ValueError(f"{f.src}: {f.where}: focal lengths `fl_x`/`fl_y` must be > 0, got {fx}, {fy}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _drop_missing(frames: list[FrameRecord], skip_missing: bool) -> list[FrameRecord]:
    kept = []
    for f in frames:
        missing = []
        if f.image is None:
            missing.append((f"field `{f.field}`", f.image_hint, "image"))
        for kind in ("depth", "mask"):
            hint = getattr(f, kind + "_hint")
            if hint is not None:
                missing.append((hint[0], hint[1], kind))
        if not missing:
            kept.append(f)
            continue
        what, path, kind = missing[0]
        msg = f"{f.src}: {f.where} ({what}): {kind} file {path} not found"
        if not skip_missing:
            raise FileNotFoundError(msg)
        warnings.warn(msg + "; frame skipped (skip_missing=True)", stacklevel=4)
    if not kept:
        raise ValueError(f"{frames[0].src}: every listed frame is missing its files; nothing to load")
    return kept


def _assemble(
    listing: Listing,
    *,
    normalization: Normalization,
    skip_missing: bool,
    downscale: int,
    background: Sequence[float] | None,
) -> Scene:
    frames = _drop_missing(listing.frames, skip_missing)
    if listing.warn_fields:
        srcs = sorted(listing.warn_fields)
        fields = sorted(set().union(*listing.warn_fields.values()))
        more = f" (and {len(srcs) - 1} more files)" if len(srcs) > 1 else ""
        warnings.warn(
            f"{srcs[0]}{more}: fields {fields} are non-zero; fgjax cameras are pinhole, so they are "
            "ignored (undistort the images first for exact results)",
            stacklevel=3,
        )
    has_depth = any(f.depth is not None for f in frames)
    has_mask = any(f.mask is not None for f in frames)
    for kind, has in (("depth", has_depth), ("mask", has_mask)):
        if has:
            for f in frames:
                if getattr(f, kind) is None:
                    raise FileNotFoundError(f"{f.src}: {f.where}: no {kind} file while other frames have one")

    images, ks, c2ws, depths, masks = [], [], [], [], []
    first: tuple[Path, int, int] | None = None
    for f in frames:
        assert f.image is not None  # _drop_missing guarantees it
        try:
            img = _image_to_float(imread(f.image), f.image, background)
        except Exception as e:  # imageio raises many exception types for corrupt files
            raise ValueError(f"{f.src}: {f.where} (field `{f.field}`): cannot read image {f.image}: {e}") from e
        h, w = img.shape[:2]
        if first is None:
            first = (f.image, w, h)
        elif (w, h) != first[1:]:
            raise ValueError(
                f"{f.src}: {f.where}: image {f.image} is {w}x{h} but {first[0]} is "
                f"{first[1]}x{first[2]} (W x H); all frames must have the same size"
            )
        k = frame_intrinsics(f, w, h)
        for kind, out, reader in (
            ("depth", depths, lambda p: _read_depth(p, listing.depth_scale)),
            ("mask", masks, _read_mask),
        ):
            p = getattr(f, kind)
            if p is None:
                continue
            try:
                a = reader(p)
            except Exception as e:  # imageio / np.load raise many exception types
                raise ValueError(f"{f.src}: {f.where}: cannot read {kind} {p}: {e}") from e
            if a.shape != (h, w):
                raise ValueError(f"{f.src}: {f.where}: {kind} {p} is {a.shape[1]}x{a.shape[0]}, image is {w}x{h}")
            out.append(a)
        if downscale > 1:
            w2, h2 = max(w // downscale, 1), max(h // downscale, 1)
            img = cv2.resize(img, (w2, h2), interpolation=cv2.INTER_AREA)
            k = np.diag([w2 / w, h2 / h, 1.0]) @ k
            if f.depth is not None:
                depths[-1] = _nearest_resize(depths[-1], h2, w2)
            if f.mask is not None:
                masks[-1] = _nearest_resize(masks[-1], h2, w2)
        images.append(img)
        ks.append(k)
        c2ws.append(f.c2w)

    imgs = np.stack(images)  # [T, H, W, 3]
    viewmats = normalization.viewmats_to_scene(c2w_to_viewmat(np.stack(c2ws)))  # [T, 4, 4]
    return Scene(
        images=imgs,
        Ks=np.stack(ks),
        viewmats=viewmats,
        times=np.array([f.time for f in frames]),
        width=imgs.shape[2],
        height=imgs.shape[1],
        frame_names=[f.name for f in frames],
        normalization=normalization,
        depths=normalization.lengths_to_scene(np.stack(depths)).astype(np.float32) if has_depth else None,
        masks=np.stack(masks) if has_mask else None,
    )


# ----------------------------------------------------------------------------- public readers


def detect_layout(path: str | os.PathLike, split: str = "train") -> tuple[str, Path]:
    """Which reader `load_scene` uses for `path`, and the file it starts from.

    Returns ("blender", transforms_{split}.json), ("nerfstudio", transforms.json) or
    ("nerfies", dataset.json). A path to a json file is taken as that file (dataset.json ->
    nerfies, transforms.json -> nerfstudio, any other *.json -> a per-split Blender file).
    """
    p = Path(path)
    if p.is_file():
        if p.name == "dataset.json":
            return "nerfies", p
        if p.name == "transforms.json":
            return "nerfstudio", p
        if p.suffix == ".json":
            return "blender", p
        raise ValueError(f"{p}: not a json file; pass a dataset folder or its transforms/dataset json")
    if not p.is_dir():
        raise FileNotFoundError(f"{p}: no such file or directory")
    if (p / f"transforms_{split}.json").is_file():
        return "blender", p / f"transforms_{split}.json"
    if (p / "transforms.json").is_file():
        return "nerfstudio", p / "transforms.json"
    if (p / "dataset.json").is_file():
        return "nerfies", p / "dataset.json"
    raise FileNotFoundError(
        f"{p}: no transforms_{split}.json (Blender/D-NeRF/LiveScene), transforms.json (nerfstudio) "
        "or dataset.json (Nerfies/CoNeRF) found"
    )


def _training_centres(kind: str, start: Path, split: str) -> np.ndarray:
    """[T, 3] world camera centres of the training split (or of `split` when there is none)."""
    if kind == "blender":
        train = start.parent / "transforms_train.json"
        src = train if (start.name == f"transforms_{split}.json" and train.is_file()) else start
        frames = parse_transforms(src, None).frames
    elif kind == "nerfstudio":
        frames = parse_transforms(start, "train").frames
    else:
        ds = _read_json(start)
        has_train = isinstance(ds.get("train_ids"), list) and bool(ds["train_ids"])
        ids = _split_ids(start, ds, "train" if has_train else split)
        frames_c2w = [_nerfies_camera(start.parent / "camera" / f"{i}.json", f"id {i!r}")[0] for i in ids]
        return np.stack([c[:3, 3] for c in frames_c2w])
    return np.stack([f.c2w[:3, 3] for f in frames])


def recorded_normalization(kind: str, start: Path, split: str) -> Normalization | None:
    """The ``normalization`` {centre, scale} that the training json of a Blender/nerfstudio layout records at its
    top level, or None (no such field, or a Nerfies layout); ValueError naming the file when it is malformed."""
    if kind == "blender":
        train = start.parent / "transforms_train.json"
        src = train if (start.name == f"transforms_{split}.json" and train.is_file()) else start
    elif kind == "nerfstudio":
        src = start
    else:
        return None
    rec = _read_json(src).get("normalization")
    if rec is None:
        return None
    try:
        if not isinstance(rec, dict) or set(rec) != {"centre", "scale"}:
            raise ValueError("expected {\"centre\": [x, y, z], \"scale\": s}")
        return Normalization.from_dict(rec)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{src}: field `normalization` is malformed ({e}): {rec!r}") from None


def load_scene(
    path: str | os.PathLike,
    split: str = "train",
    *,
    normalize: bool | Normalization = True,
    skip_missing: bool = False,
    downscale: int = 1,
    background: Sequence[float] | None = (1.0, 1.0, 1.0),
) -> Scene:
    """Load one split of a dataset folder into a `Scene` (OpenCV cameras, normalised units).

    Dispatches on what the folder holds (see `detect_layout`): ``transforms_{split}.json``
    (Blender, D-NeRF, LiveScene OmniSim/InterReal), ``transforms.json`` (nerfstudio; the split
    comes from ``{split}_filenames``, or is every frame for split "train"/"all" when there is
    no list), or ``dataset.json`` (Nerfies, CoNeRF, HyperNeRF; ``{split}_ids``, "all" = ``ids``).
    File conventions are in the module docstring.

    Args:
        path: dataset folder (or its transforms/dataset json).
        split: "train", "val", "test" or "all" (where the layout defines it).
        normalize: True: the normalisation the training json records, else `compute_normalization` of the
            training cameras;
            False: world units (identity); a `Normalization`: use it.
        skip_missing: skip (with a warning) frames whose image/depth/mask file is absent,
            instead of raising `FileNotFoundError`.
        downscale: integer factor; images are area-resampled to (W // d, H // d), K rows
            scaled by the exact size ratios, depths/masks resampled nearest. Nerfies folders
            use ``rgb/<d>x`` when it exists.
        background: RGB in [0, 1] that RGBA images are composited over (white by default, the
            Blender convention); None drops the alpha channel.

    Returns:
        The `Scene`; ``scene.normalization`` maps its geometry back to world units.

    Raises:
        FileNotFoundError: no recognised layout, or a listed file is absent (naming the json,
            the frame and the path).
        ValueError: unreadable images, non-finite or non-rigid poses, inconsistent image sizes,
            times outside [0, 1], malformed fields (naming the file, frame and field).
    """
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise ValueError(f"load_scene: downscale must be an integer >= 1, got {downscale!r}")
    if background is not None:
        bg = np.asarray(background, dtype=np.float64)
        if bg.shape != (3,) or not np.all((bg >= 0) & (bg <= 1)):
            raise ValueError(f"load_scene: background must be 3 values in [0, 1] or None, got {background!r}")
    kind, start = detect_layout(path, split)
    if kind == "nerfies":
        listing, remaining = _parse_nerfies(start.parent, split, downscale)
    else:
        listing, remaining = parse_transforms(start, split if kind == "nerfstudio" else None), downscale

    if isinstance(normalize, Normalization):
        norm = normalize
    elif normalize is True:
        norm = recorded_normalization(kind, start, split) or compute_normalization(
            _training_centres(kind, start, split))
    elif normalize is False:
        norm = Normalization.identity()
    else:
        raise ValueError(f"load_scene: normalize must be a bool or a Normalization, got {normalize!r}")
    return _assemble(
        listing, normalization=norm, skip_missing=skip_missing, downscale=remaining, background=background
    )
