"""The held-out test views of a scene folder, as stage 1's evaluation reads them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fgjax.config import Config
from fgjax.data.loaders import load_scene

__all__ = ["load_test_views"]


def load_test_views(data_dir: Path, cfg: Config, normalization):
    """Held-out test views evaluated by time (the synthetic scenes' "state" frames are skipped), plus
    dynamic-region masks where the dataset has them (scene masks, or the synthetic gt object ids). (None, None,
    None) where the dataset has no test split; a test split that exists but cannot be read raises, naming its file."""
    try:
        test = load_scene(data_dir, "test", normalize=normalization, downscale=cfg.data.downscale)
    except (FileNotFoundError, ValueError):
        if (Path(data_dir) / "transforms_test.json").exists():
            raise
        return None, None, None
    keep = list(range(test.num_frames))
    masks = None if test.masks is None else (np.asarray(test.masks) > 0)
    meta_p = data_dir / "gt" / "meta.json"
    if meta_p.exists():
        meta = json.loads(meta_p.read_text())
        kinds = [f.get("kind", "view") for f in meta.get("test_frames", [])]
        if len(kinds) == test.num_frames:
            keep = [i for i, k in enumerate(kinds) if k == "view"]
        oid = data_dir / "gt" / "test" / "object_id.npy"
        if masks is None and oid.exists():
            ids = np.load(oid)
            if ids.shape[:1] == (test.num_frames,) and ids.shape[1:3] == (test.height, test.width):
                masks = ids > 0
    test = test.subset(keep)
    names = test.frame_names
    if masks is not None:
        masks = masks[keep]
    return test, masks, names
