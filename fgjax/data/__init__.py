"""fgjax.data: dataset loaders, the synthetic scene generator and optical flow.

Public names (imported lazily, so that ``import fgjax.data`` stays cheap):
``Scene``, ``Normalization``, ``load_scene``, ``write_transforms`` (loaders),
``SynthConfig``, ``generate`` (synthetic articulated scenes),
``estimate_flow``, ``read_flo``, ``write_flo``, ``load_flow`` (optical flow).
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Scene": "fgjax.data.scene",
    "Normalization": "fgjax.data.scene",
    "load_scene": "fgjax.data.loaders",
    "write_transforms": "fgjax.data.loaders",
    "SynthConfig": "fgjax.data.synth",
    "generate": "fgjax.data.synth",
    "estimate_flow": "fgjax.data.opticalflow",
    "read_flo": "fgjax.data.opticalflow",
    "write_flo": "fgjax.data.opticalflow",
    "load_flow": "fgjax.data.opticalflow",
}

__all__ = list(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'fgjax.data' has no attribute {name!r}")
