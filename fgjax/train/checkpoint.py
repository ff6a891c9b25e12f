"""Atomic checkpoints of the whole stage-1 state: parameters, optimiser state, densify state, step, RNG key,
tile capacity, static flag and the effective config (TOML text).

Format: one ``.npz`` (no pickle) with the flattened leaves ``leaf_00000 ...`` and a JSON header ``__meta__``
(format version, step, leaf count, shapes and dtypes). Loading needs a template state of the same
structure (built from the config); any mismatch (version, leaf count, shape, dtype) raises
``CheckpointError`` naming what differs. Writes go to a temporary file in the same folder, are fsynced
and renamed over the target, so a crash never leaves a half-written checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import zipfile
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from fgjax.io import atomic_write

__all__ = ["CheckpointError", "save_checkpoint", "load_checkpoint", "CHECKPOINT_NAME", "FORMAT_VERSION"]

CHECKPOINT_NAME = "checkpoint.npz"
FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint that cannot be read or does not fit the current configuration."""


def _state_tree(state) -> dict[str, Any]:
    tree = {"params": state.params, "opt_state": state.opt_state, "densify": state.densify,
            "key": jax.random.key_data(state.key)}
    if getattr(state, "frame_err", None) is not None:  # only with train.error_sampling (older runs load as before)
        tree["frame_err"] = state.frame_err
    if getattr(state, "static_points", None) is not None:  # only with deform.gauge > 0
        tree["static_points"] = state.static_points
    return tree


def save_checkpoint(path: str | Path, state, *, config_toml: str = "") -> Path:
    """Write `state` (a ``stage1.TrainState``) atomically to `path`."""
    path = Path(path)
    leaves, _ = jax.tree_util.tree_flatten(_state_tree(state))
    arrays = {f"leaf_{i:05d}": np.asarray(x) for i, x in enumerate(leaves)}
    meta = {
        "format_version": FORMAT_VERSION, "step": int(state.step), "capacity": int(state.capacity),
        "static": None if state.static is None else bool(state.static), "num_leaves": len(leaves),
        "shapes": [list(a.shape) for a in arrays.values()], "dtypes": [str(a.dtype) for a in arrays.values()],
        "config_toml": config_toml, "static_points": getattr(state, "static_points", None) is not None,
    }
    arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda f: np.savez(f, **arrays))
    return path


def read_meta(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        with open(path, "rb") as f, np.load(f, allow_pickle=False) as z:
            return json.loads(bytes(z["__meta__"]).decode())
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {path} does not exist") from None
    except (zipfile.BadZipFile, ValueError, KeyError, OSError, EOFError, json.JSONDecodeError) as e:
        raise CheckpointError(f"checkpoint {path} is corrupt or not an fgjax checkpoint "
                              f"({type(e).__name__}: {e})") from None


def load_checkpoint(path: str | Path, template):
    """Load into a copy of `template` (a ``TrainState`` built from the same config); returns the new state."""
    path = Path(path)
    meta = read_meta(path)
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path} has format version {meta.get('format_version')}; "
                              f"this fgjax reads version {FORMAT_VERSION}")
    n_template = len(jax.tree_util.tree_leaves(_state_tree(template)))
    has_points = getattr(template, "static_points", None) is not None
    saved_points = meta.get("static_points",  # files written before the flag: by their number of arrays
                            meta["num_leaves"] == n_template + (0 if has_points else 1))
    if has_points and not saved_points:
        template = dataclasses.replace(template, static_points=None)  # saved without deform.gauge: it stays off
    elif not has_points and saved_points:  # the points are the tree's last leaf (its keys are flattened sorted)
        template = dataclasses.replace(template, static_points=np.zeros(meta["shapes"][-1], np.float32))
    t_leaves, treedef = jax.tree_util.tree_flatten(_state_tree(template))
    if meta["num_leaves"] != len(t_leaves):
        raise CheckpointError(
            f"checkpoint {path} holds {meta['num_leaves']} arrays but the current config builds a state with "
            f"{len(t_leaves)} (different model, deformation field, pose refinement or optimiser settings?)")
    leaves = []
    try:
        with open(path, "rb") as f, np.load(f, allow_pickle=False) as z:
            for i, t in enumerate(t_leaves):
                a = z[f"leaf_{i:05d}"]
                if tuple(a.shape) != tuple(np.shape(t)) or a.dtype != np.asarray(t).dtype:
                    raise CheckpointError(
                        f"checkpoint {path}: array {i} has shape {list(a.shape)} {a.dtype}, the current config "
                        f"expects {list(np.shape(t))} {np.asarray(t).dtype} (incompatible model settings, "
                        "e.g. model.capacity, model.sh_degree or deform.*)")
                leaves.append(jnp.asarray(a))
    except CheckpointError:
        raise
    except (zipfile.BadZipFile, ValueError, KeyError, OSError, EOFError) as e:
        raise CheckpointError(f"checkpoint {path} is corrupt ({type(e).__name__}: {e})") from None
    tree = jax.tree_util.tree_unflatten(treedef, leaves)
    return dataclasses.replace(
        template, params=tree["params"], opt_state=tree["opt_state"], densify=tree["densify"],
        key=jax.random.wrap_key_data(tree["key"]), step=int(meta["step"]), capacity=int(meta["capacity"]),
        static=meta["static"],
        frame_err=np.array(tree["frame_err"], np.float32) if "frame_err" in tree else None,
        static_points=np.array(tree["static_points"], np.float32) if "static_points" in tree else None,
    )
