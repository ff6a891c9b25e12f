"""What made a run folder: the data it was trained on, its configuration, its stage-1 checkpoint and fgjax's version.

RUN/provenance.json is written when stage 1 finishes:

    {"fgjax_version": "...", "data_dir": "/abs/SCENE", "data_fingerprint": "<sha256>",
     "config_sha256": "<sha256 of RUN/config.toml>", "checkpoint": {"step": N, "sha256": "<sha256>"}}

Stage 2 records the checkpoint and the data fingerprint it was built on in its own metadata, so that a stage 2 left
behind by a later stage 1, or run on another scene, is refused by name instead of served silently.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from fgjax.io import atomic_write

__all__ = ["PROVENANCE_NAME", "file_sha256", "scene_fingerprint", "write_provenance", "read_provenance"]

PROVENANCE_NAME = "provenance.json"
_SKIP_DIRS = {"gt"}  # ground truth: evaluation only, never read by training


def file_sha256(path: str | Path, *, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def scene_fingerprint(data_dir: str | Path) -> str:
    """Hex SHA-256 over every file of a data set folder that training can read: each file's path relative to the
    folder and its bytes, in sorted order; hidden files and the ground truth (``gt/``) are left out. Two folders
    with the same fingerprint hold the same training data."""
    root = Path(data_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"data folder {root} does not exist")
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if not p.is_file() or rel.parts[0] in _SKIP_DIRS or any(part.startswith(".") for part in rel.parts):
            continue
        h.update(str(rel).encode() + b"\0" + file_sha256(p).encode() + b"\n")
    return h.hexdigest()


def write_provenance(run_dir: str | Path, data_dir: str | Path, checkpoint: str | Path, step: int,
                     version: str) -> dict[str, Any]:
    """Write RUN/provenance.json (atomically) for a run whose stage 1 has just finished; returns what it wrote."""
    run_dir = Path(run_dir)
    rec = {
        "fgjax_version": version,
        "data_dir": str(Path(data_dir).resolve()),
        "data_fingerprint": scene_fingerprint(data_dir),
        "config_sha256": file_sha256(run_dir / "config.toml") if (run_dir / "config.toml").is_file() else None,
        "checkpoint": {"step": int(step), "sha256": file_sha256(checkpoint)},
    }
    atomic_write(run_dir / PROVENANCE_NAME, lambda f: f.write(json.dumps(rec, indent=1).encode()))
    return rec


def read_provenance(run_dir: str | Path) -> dict[str, Any] | None:
    """RUN/provenance.json, or None where the run has none. Raises ValueError naming the file when it is corrupt."""
    p = Path(run_dir) / PROVENANCE_NAME
    if not p.is_file():
        return None
    try:
        rec = json.loads(p.read_text())
        if not isinstance(rec, dict) or not isinstance(rec.get("checkpoint"), dict):
            raise ValueError("not a provenance record")
        return rec
    except (json.JSONDecodeError, ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{p} is corrupt ({e}); train the run again") from None
