"""Camera lists from a transforms json (nerfstudio / Blender / D-NeRF layout) for rendering a trained run."""

from __future__ import annotations

from pathlib import Path

from fgjax.data.loaders import frame_intrinsics, parse_transforms
from fgjax.geometry import c2w_to_viewmat

__all__ = ["read_cameras"]


def read_cameras(path: str | Path, normalization, width: int, height: int):
    """[(name, viewmat [4, 4] normalised OpenCV w2c, K [3, 3], time, w, h)] from a transforms json."""
    listing = parse_transforms(Path(path), None)
    out = []
    for i, f in enumerate(listing.frames):
        w = int(round(f.intr["w"])) if f.intr.get("w") is not None else width
        h = int(round(f.intr["h"])) if f.intr.get("h") is not None else height
        K = frame_intrinsics(f, w, h)
        vm = normalization.viewmats_to_scene(c2w_to_viewmat(f.c2w))
        name = (f.name or f"{i:05d}").replace("/", "_")
        out.append((name, vm, K, float(f.time), w, h))
    return out
