"""`write_transforms`: a nerfstudio/Blender-style ``transforms_{split}.json`` with its images, depths and
masks, written atomically (the format `fgjax.data.loaders.load_scene` reads; conventions there)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
from jaxtyping import Float

from fgjax.data.loaders import imread
from fgjax.data.scene import rigid_problem
from fgjax.geometry import opencv_to_opengl_c2w, viewmat_to_c2w

__all__ = ["write_transforms"]


_RESERVED_TOP = ("frames", "camera_model", "camera_angle_x", "w", "h")


def _check_name(name: Any, i: int) -> str:
    if (
        not isinstance(name, str)
        or not name
        or name in (".", "..")
        or any(c in name for c in "/\\\0")
    ):
        raise ValueError(f"write_transforms: frame_names[{i}] = {name!r} is not a valid file stem")
    return name


def _image_array_for_png(img: np.ndarray, i: int) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[-1] not in (3, 4):
        raise ValueError(f"write_transforms: images[{i}] must be [H, W, 3|4], got shape {a.shape}")
    if a.dtype in (np.uint8, np.uint16):
        return a
    if np.issubdtype(a.dtype, np.floating):
        if not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 1:
            raise ValueError(f"write_transforms: images[{i}] float values must be finite and in [0, 1]")
        return np.round(a * 255.0).astype(np.uint8)
    raise ValueError(f"write_transforms: images[{i}] has dtype {a.dtype}; expected uint8, uint16 or float")


def write_transforms(
    out_dir: str | os.PathLike,
    split: str,
    images_or_paths: np.ndarray | Sequence[str | os.PathLike],
    Ks: Float[np.ndarray, "T 3 3"],
    viewmats: Float[np.ndarray, "T 4 4"],
    times: Float[np.ndarray, " T"],
    *,
    depths: Float[np.ndarray, "T H W"] | None = None,
    masks: np.ndarray | None = None,
    extra: dict[str, Any] | None = None,
    frame_names: Sequence[str] | None = None,
    depth_png_scale: float | None = None,
) -> Path:
    """Write a nerfstudio/Blender-style ``out_dir/transforms_{split}.json`` with its images.

    Files: ``images/<name>.png`` (float images quantised to 8 bit, uint8/uint16 kept; paths
    are copied byte for byte, keeping their extension), ``depth/<name>.npy`` (float32 z-depth,
    world units; or, with `depth_png_scale` s, ``depth/<name>.png``: 16-bit integers round(depth / s), 0 unknown,
    and the json's top-level ``depth_scale`` = s), ``mask/<name>.png`` (8-bit, or 16-bit when labels exceed 255;
    bool -> 0/1),
    and the json: per frame ``file_path``, ``transform_matrix`` (OpenGL camera-to-world,
    from ``opencv_to_opengl_c2w(inverse(viewmat))``), ``time``, ``fl_x, fl_y, cx, cy, w, h``,
    ``depth_file_path``, ``mask_path``; top level ``camera_model`` "OPENCV" (zero distortion),
    ``w``, ``h`` and, when every frame has fx = fy and the principal point at (W/2, H/2) with
    one focal length, ``camera_angle_x``; then `extra`. Names default to ``{split}_{i:05d}``.

    Atomic: every input is validated before anything is written; each file goes to a temporary
    name in its final folder and is `os.replace`d into place at the end (json last). On any
    failure, temporary files, newly created files and newly created folders are removed.

    Args:
        out_dir: dataset folder (created if absent).
        split: split name, used in the json name and default frame names.
        images_or_paths: [T, H, W, 3|4] array (float in [0, 1], uint8 or uint16) or T image paths.
        Ks: [T, 3, 3] zero-skew pinhole intrinsics (pixel centres at +0.5).
        viewmats: [T, 4, 4] OpenCV world-to-camera matrices, world units.
        times: [T] in [0, 1].
        depths: optional [T, H, W] camera z-depth in world units (>= 0, 0 = unknown).
        masks: optional [T, H, W] bool or non-negative integer labels (< 65536).
        extra: optional JSON-serialisable top-level fields (e.g. ``depth_scale``, a scene name).
        frame_names: optional T distinct file stems.
        depth_png_scale: write depths as 16-bit PNG in units of this many world units (e.g. 1e-3 for millimetres
            when the world unit is the metre); depths beyond 65535 units are written as 0 (unknown).

    Returns:
        The path of the written json.
    """
    out = Path(out_dir)
    if not isinstance(split, str) or not split or any(c in split for c in "/\\\0"):
        raise ValueError(f"write_transforms: split must be a plain name, got {split!r}")

    # ---- validate everything before touching the disk
    if isinstance(images_or_paths, np.ndarray):
        arr = images_or_paths
        if arr.ndim != 4:
            raise ValueError(f"write_transforms: images must be [T, H, W, 3|4], got shape {arr.shape}")
        pngs: list[np.ndarray] | None = [_image_array_for_png(arr[i], i) for i in range(arr.shape[0])]
        src_paths: list[Path] | None = None
        t = arr.shape[0]
        h, w = arr.shape[1:3]
    else:
        pngs = None
        src_paths = [Path(p) for p in images_or_paths]
        t = len(src_paths)
        if t == 0:
            raise ValueError("write_transforms: images_or_paths is empty")
        size0 = None
        for i, p in enumerate(src_paths):
            if not p.is_file():
                raise FileNotFoundError(f"write_transforms: images_or_paths[{i}] = {p} does not exist")
            try:
                shape = imread(p).shape
            except Exception as e:  # imageio raises many types for bad files
                raise ValueError(f"write_transforms: images_or_paths[{i}] = {p} is not a readable image: {e}") from e
            if size0 is None:
                size0 = (shape[:2], p)
            elif shape[:2] != size0[0]:
                raise ValueError(
                    f"write_transforms: image {p} is {shape[1]}x{shape[0]} but {size0[1]} is "
                    f"{size0[0][1]}x{size0[0][0]} (W x H)"
                )
        assert size0 is not None
        h, w = size0[0]
    if t == 0:
        raise ValueError("write_transforms: no frames")

    ks = np.asarray(Ks, dtype=np.float64)
    if ks.shape != (t, 3, 3) or not np.all(np.isfinite(ks)):
        raise ValueError(f"write_transforms: Ks must be finite [T, 3, 3] = [{t}, 3, 3], got shape {ks.shape}")
    for i, k in enumerate(ks):
        if k[0, 1] != 0 or k[1, 0] != 0 or np.any(k[2] != [0.0, 0.0, 1.0]) or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError(f"write_transforms: Ks[{i}] is not a zero-skew pinhole with fx, fy > 0: {k.tolist()}")
    vm = np.asarray(viewmats, dtype=np.float64)
    if vm.shape != (t, 4, 4):
        raise ValueError(f"write_transforms: viewmats must be [T, 4, 4] = [{t}, 4, 4], got shape {vm.shape}")
    problem = rigid_problem(vm)
    if problem is not None:
        raise ValueError(f"write_transforms: viewmats[{problem[0]}] {problem[1]}")
    ts = np.asarray(times, dtype=np.float64)
    if ts.shape != (t,):
        raise ValueError(f"write_transforms: times must be [T] = [{t}], got shape {ts.shape}")
    bad = np.flatnonzero(~np.isfinite(ts) | (ts < 0) | (ts > 1))
    if bad.size:
        raise ValueError(f"write_transforms: times[{bad[0]}] = {ts[bad[0]]} is outside [0, 1]")
    if depths is not None:
        dp = np.asarray(depths)
        if not np.issubdtype(dp.dtype, np.floating) or dp.shape != (t, h, w):
            raise ValueError(f"write_transforms: depths must be float [T, H, W] = [{t}, {h}, {w}], got {dp.shape}")
        if np.any(np.isnan(dp)) or np.any(dp < 0):
            raise ValueError("write_transforms: depths contain NaN or negative values")
        if depth_png_scale is not None:
            if not (isinstance(depth_png_scale, int | float) and math.isfinite(depth_png_scale)
                    and depth_png_scale > 0):
                raise ValueError(f"write_transforms: depth_png_scale must be > 0, got {depth_png_scale!r}")
            q = np.round(np.where(np.isfinite(dp), dp, 0.0) / depth_png_scale)
            dp = np.where(q <= 65535, q, 0).astype(np.uint16)
    if masks is not None:
        mk = np.asarray(masks)
        if mk.shape != (t, h, w) or not (mk.dtype == bool or np.issubdtype(mk.dtype, np.integer)):
            raise ValueError(f"write_transforms: masks must be bool/int [T, H, W] = [{t}, {h}, {w}], got {mk.shape}")
        if mk.dtype != bool and (mk.min() < 0 or mk.max() > 65535):
            raise ValueError("write_transforms: masks labels must be in [0, 65535]")
        mk = mk.astype(np.uint8 if mk.dtype == bool or mk.max() <= 255 else np.uint16)
    names = [f"{split}_{i:05d}" for i in range(t)] if frame_names is None else list(frame_names)
    if len(names) != t:
        raise ValueError(f"write_transforms: frame_names has {len(names)} items, expected {t}")
    names = [_check_name(n, i) for i, n in enumerate(names)]
    if len(set(names)) != t:
        raise ValueError("write_transforms: frame_names must be distinct")
    extra = dict(extra or {})
    if depths is not None and depth_png_scale is not None:
        extra["depth_scale"] = float(depth_png_scale)
    for key in extra:
        if not isinstance(key, str) or key in _RESERVED_TOP:
            raise ValueError(f"write_transforms: extra field {key!r} is reserved or not a string")

    c2w_gl = opencv_to_opengl_c2w(viewmat_to_c2w(vm))  # [T, 4, 4]
    img_ext = [".png"] * t if src_paths is None else [p.suffix or ".png" for p in src_paths]
    frames = []
    for i in range(t):
        fr: dict[str, Any] = {
            "file_path": f"images/{names[i]}{img_ext[i]}",
            "transform_matrix": c2w_gl[i].tolist(),
            "time": float(ts[i]),
            "fl_x": float(ks[i, 0, 0]),
            "fl_y": float(ks[i, 1, 1]),
            "cx": float(ks[i, 0, 2]),
            "cy": float(ks[i, 1, 2]),
            "w": int(w),
            "h": int(h),
        }
        if depths is not None:
            fr["depth_file_path"] = f"depth/{names[i]}.{'npy' if depth_png_scale is None else 'png'}"
        if masks is not None:
            fr["mask_path"] = f"mask/{names[i]}.png"
        frames.append(fr)
    doc: dict[str, Any] = {"camera_model": "OPENCV", "w": int(w), "h": int(h)}
    fx0 = ks[0, 0, 0]
    if np.all(ks[:, 0, 0] == fx0) and np.all(ks[:, 1, 1] == fx0) and np.all(ks[:, 0, 2] == w / 2) and np.all(
        ks[:, 1, 2] == h / 2
    ):
        doc["camera_angle_x"] = 2.0 * math.atan(w / (2.0 * fx0))
    doc.update(extra)
    doc["frames"] = frames
    try:
        text = json.dumps(doc, indent=2, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"write_transforms: extra is not JSON-serialisable: {e}") from e

    # ---- write to temporary names, then move into place
    plan: list[tuple[Path, Any]] = []  # (final path, writer(tmp_path))
    for i in range(t):
        final = out / frames[i]["file_path"]
        if pngs is not None:
            plan.append((final, lambda tmp, a=pngs[i]: iio.imwrite(tmp, a, extension=".png")))
        else:
            plan.append((final, lambda tmp, s=src_paths[i]: shutil.copyfile(s, tmp)))
        if depths is not None:
            save = _save_npy if depth_png_scale is None else (lambda tmp, a: iio.imwrite(tmp, a, extension=".png"))
            plan.append((out / frames[i]["depth_file_path"], lambda tmp, a=dp[i], save=save: save(tmp, a)))
        if masks is not None:
            plan.append((out / frames[i]["mask_path"], lambda tmp, a=mk[i]: iio.imwrite(tmp, a, extension=".png")))
    json_path = out / f"transforms_{split}.json"
    plan.append((json_path, lambda tmp: tmp.write_text(text, encoding="utf-8")))

    created_dirs: list[Path] = []
    temps: list[Path] = []
    new_files: list[Path] = []
    token = uuid.uuid4().hex[:12]
    try:
        for final, _ in plan:
            for d in reversed([final.parent, *final.parent.parents]):
                if not d.exists():
                    d.mkdir()
                    created_dirs.append(d)
        for final, write in plan:
            tmp = final.with_name(f".{final.name}.{token}.tmp")
            temps.append(tmp)
            write(tmp)
        for (final, _), tmp in zip(plan, temps, strict=True):
            existed = final.exists()
            os.replace(tmp, final)
            if not existed:
                new_files.append(final)
    except BaseException:
        for p in [*temps, *new_files]:
            with contextlib.suppress(OSError):
                p.unlink()
        for d in reversed(created_dirs):
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    return json_path


def _save_npy(path: Path, a: np.ndarray) -> None:
    with open(path, "wb") as f:
        np.save(f, np.asarray(a, dtype=np.float32))
