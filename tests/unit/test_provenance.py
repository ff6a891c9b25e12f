"""`fgjax.provenance`: the data fingerprint sees every training file and nothing else; records round-trip."""

from __future__ import annotations

import json

import pytest

from fgjax.provenance import file_sha256, read_provenance, scene_fingerprint, write_provenance


def _scene(root):
    (root / "images").mkdir(parents=True)
    (root / "gt").mkdir()
    (root / "transforms_train.json").write_text('{"frames": []}')
    (root / "images" / "a.png").write_bytes(b"\x00\x01")
    (root / "gt" / "depth.npy").write_bytes(b"gt")
    return root


def test_fingerprint_follows_training_files_only(tmp_path):
    root = _scene(tmp_path / "s")
    f0 = scene_fingerprint(root)
    assert len(f0) == 64 and f0 == scene_fingerprint(root)
    (root / "gt" / "depth.npy").write_bytes(b"other ground truth")  # never read by training
    (root / ".cache").write_text("hidden")
    assert scene_fingerprint(root) == f0
    (root / "images" / "a.png").write_bytes(b"\x00\x02")  # one byte of one image
    f1 = scene_fingerprint(root)
    assert f1 != f0
    (root / "images" / "a.png").rename(root / "images" / "b.png")  # same bytes, another name
    assert scene_fingerprint(root) != f1
    with pytest.raises(FileNotFoundError, match="does not exist"):
        scene_fingerprint(tmp_path / "none")


def test_provenance_round_trip_and_corrupt_record(tmp_path):
    root = _scene(tmp_path / "s")
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.toml").write_text("[train]\nsteps = 3\n")
    (run / "checkpoint.npz").write_bytes(b"ckpt")
    rec = write_provenance(run, root, run / "checkpoint.npz", 3, "9.9")
    assert read_provenance(run) == rec == json.loads((run / "provenance.json").read_text())
    assert rec["checkpoint"] == {"step": 3, "sha256": file_sha256(run / "checkpoint.npz")}
    assert rec["data_fingerprint"] == scene_fingerprint(root) and rec["fgjax_version"] == "9.9"
    assert read_provenance(tmp_path) is None
    (run / "provenance.json").write_text("{not json")
    with pytest.raises(ValueError, match="provenance.json is corrupt"):
        read_provenance(run)
