"""Atomic file writes: the one mechanism every module uses so that no half-written file is seen."""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import Any


def atomic_write(path: str | Path, write: Callable[[Any], None]) -> Path:
    """Write ``path`` through ``write(binary_file)`` into a hidden temporary file in the same folder,
    fsync it, then ``os.replace`` it into place. Readers see the old file or the new one, never a
    partial one; on any failure the temporary file is removed and the old file is untouched. The
    folder must exist (callers decide whether to create it). Permissions follow the umask.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "xb") as f:  # 'x': never clobber another writer's temporary file
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path
