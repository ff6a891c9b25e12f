"""File writing (`fgjax.io`): atomic writes and videos."""

from __future__ import annotations

import cv2
import imageio.v3 as iio
import numpy as np
import pytest

from fgjax import io


def test_atomic_write_replaces_whole_or_leaves_the_old_file(tmp_path):
    path = tmp_path / "a.txt"
    io.atomic_write(path, lambda f: f.write(b"old"))

    def fail(f):
        f.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        io.atomic_write(path, fail)
    assert path.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_write_video_pads_odd_sides_and_falls_back_to_a_gif(tmp_path, monkeypatch):
    """An mp4 of frames with odd sides (padded to even), nothing else left in the folder; when the ffmpeg
    writer fails, a GIF with every frame instead and the failure reported."""
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (31, 45, 3), np.uint8) for _ in range(4)]
    out = io.write_video(frames, tmp_path / "v.mp4", fps=5)
    assert out == tmp_path / "v.mp4" and out.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]  # no temporary file left
    cap = cv2.VideoCapture(str(out))
    try:
        read = [f for ok, f in iter(cap.read, (False, None)) if ok]
    finally:
        cap.release()
    assert len(read) == 4 and read[0].shape[:2] == (32, 46)
    import imageio.v2 as iio2

    def broken(*a, **k):
        raise OSError("no ffmpeg here")

    monkeypatch.setattr(iio2, "get_writer", broken)
    said = []
    gif = io.write_video(frames, tmp_path / "w.mp4", warn=said.append)
    assert gif == tmp_path / "w.gif" and "no ffmpeg here" in said[0]
    assert iio.imread(gif).shape[0] == 4
    assert not (tmp_path / "w.mp4").exists() and not any(p.name.startswith(".") for p in tmp_path.iterdir())
    with pytest.raises(ValueError, match="no frames"):
        io.write_video([], tmp_path / "x.mp4")
