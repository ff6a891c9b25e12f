"""Atomic file writes (the one mechanism every module uses so that no half-written file is seen) and videos."""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import imageio.v2 as iio2
import imageio.v3 as iio
import numpy as np


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
        with contextlib.suppress(OSError):  # the first error is the one to report, never the clean-up's
            os.unlink(tmp)
        raise
    return path


def replace_folder(tmp: str | Path, out: str | Path) -> Path:
    """Move the finished folder ``tmp`` to ``out`` (a sibling), replacing whatever folder is there: the old one is
    renamed aside first and removed only after the swap, so ``out`` is either the old folder or the new one, never
    half of each; if the swap fails the old folder is put back."""
    tmp, out = Path(tmp), Path(out)
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{secrets.token_hex(4)}")
        os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        if old is not None:
            os.replace(old, out)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return out


def _temp_name(path: Path) -> Path:
    """A hidden temporary file beside ``path`` that keeps its suffix (writers pick the format from it)."""
    return path.with_name(f".{path.stem}.{os.getpid()}-{secrets.token_hex(4)}.tmp{path.suffix}")


def write_video(frames, path: str | Path, fps: int = 10, *, warn=None) -> Path:
    """Write RGB frames (a sequence of [H, W, 3] uint8, all the same size) as an H.264 mp4 with imageio's
    ffmpeg writer; where that fails (no ffmpeg, codec missing), an animated GIF beside it instead.
    Odd sides are padded by one edge row or column (yuv420p needs even sides). Written to a temporary
    file and renamed, so no half-written video is left. Returns the file written; ``warn(str)`` hears
    about a fallback (default: stderr)."""
    path = Path(path)
    frames = [np.asarray(f, np.uint8) for f in frames]
    if not frames:
        raise ValueError(f"write_video: no frames for {path}")
    h, w = frames[0].shape[:2]
    pad = ((0, h % 2), (0, w % 2), (0, 0))
    frames = [np.pad(f, pad, mode="edge") for f in frames]
    tmp = _temp_name(path)
    try:
        with warnings.catch_warnings():
            # JAX warns on any fork; the writer's fork is followed by exec (ffmpeg), which is safe.
            warnings.filterwarnings("ignore", message=".*os.fork.*", category=RuntimeWarning)
            with iio2.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=8,
                                 macro_block_size=2, pixelformat="yuv420p", ffmpeg_log_level="error") as wr:
                for f in frames:
                    wr.append_data(f)
        if tmp.stat().st_size == 0:
            raise OSError("empty mp4")
        os.replace(tmp, path)
        with contextlib.suppress(OSError):
            path.with_suffix(".gif").unlink()  # a fallback left by an earlier run
        return path
    except Exception as e:  # no ffmpeg, codec missing ...
        with contextlib.suppress(OSError):
            tmp.unlink()
        gif = path.with_suffix(".gif")
        (warn or (lambda s: print(s, file=sys.stderr)))(f"mp4 writing failed ({e}); writing {gif.name} instead")
        atomic_write(gif, lambda f: f.write(iio.imwrite("<bytes>", np.stack(frames), extension=".gif",
                                                        duration=1000 // fps, loop=0)))
        return gif
