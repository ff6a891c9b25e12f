"""fgjax.data: dataset loaders and writer, optical flow (OpenCV backends, .flo I/O, sequences).

Public names (imported lazily, so that ``import fgjax.data`` stays cheap):
``Scene``, ``Normalization``, ``load_scene`` (loaders), ``write_transforms`` (writer),
``estimate_flow`` (optical flow), ``read_flo``, ``write_flo``, ``load_flow`` (flow files).
The synthetic scene generator is `fgjax.synth`.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Scene": "fgjax.data.scene",
    "Normalization": "fgjax.data.scene",
    "load_scene": "fgjax.data.loaders",
    "write_transforms": "fgjax.data.write",
    "estimate_flow": "fgjax.data.opticalflow",
    "read_flo": "fgjax.data.flowio",
    "write_flo": "fgjax.data.flowio",
    "load_flow": "fgjax.data.flowio",
}

__all__ = list(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'fgjax.data' has no attribute {name!r}")
