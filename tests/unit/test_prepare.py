"""`fgjax prepare`'s pieces on clips with known cameras (a ray-cast textured room, tests/_captures.py):
structure from motion recovers the poses up to a similarity, a still clip falls back to identity poses and a panning
one to rotations, a Record3D export is read with its column-major K and ARKit axes, and the written scene loads with
the normalisation it records."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from _captures import TexturedRoom, look_at_c2w, orbit_c2w, pinhole, umeyama, write_record3d

from fgjax.data.loaders import load_scene
from fgjax.data.prepare import (
    content_normalization,
    interleaved_split,
    prepare_record3d,
    prepare_video,
    write_scene,
)
from fgjax.data.record3d import read_record3d
from fgjax.data.sfm import rotation_poses
from fgjax.data.write import write_transforms
from fgjax.geometry import look_at_point, opengl_to_opencv_c2w
from fgjax.io import write_video
from fgjax.models.model import scene_extent

W, H = 320, 240


def _angle_deg(r: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def _clip(path: Path, c2w: np.ndarray, K: np.ndarray, offsets=None, supersample: int = 2) -> Path:
    room = TexturedRoom(seed=0)
    offs = offsets if offsets is not None else [(0.0, 0.0, 0.0)] * len(c2w)
    write_video([room.render(c, K, W, H, cube_offset=o, supersample=supersample) for c, o in zip(c2w, offs)],
                path, fps=10)
    return path


def _read_written(scene: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """(source frame numbers [T], OpenCV c2w [T, 4, 4] in file units, prepare.json) of a prepared scene."""
    idx, c2w = [], []
    for split in ("train", "test"):
        p = scene / f"transforms_{split}.json"
        if p.is_file():
            for f in json.loads(p.read_text())["frames"]:
                idx.append(int(Path(f["file_path"]).stem.split("_")[-1]))
                c2w.append(opengl_to_opencv_c2w(np.array(f["transform_matrix"])))
    order = np.argsort(idx)
    return np.array(idx)[order], np.stack(c2w)[order], json.loads((scene / "prepare.json").read_text())


def test_sfm_recovers_an_orbit_up_to_a_similarity(tmp_path):
    """20 frames on a 40-degree arc around a textured cube in a textured room, encoded as H.264: every frame is
    registered, and after the Umeyama similarity on the camera centres the rotations agree within 2 degrees (measured:
    ~0.4) and the centres within 5% of the path length (measured: ~0.1%); the focal length within 5% (~3%)."""
    import pycolmap  # noqa: F401  (the test extra installs it; a broken install fails here, not skips)
    K = pinhole(W, H, 0.8 * W)
    truth = orbit_c2w(20)
    clip = _clip(tmp_path / "orbit.mp4", truth, K)
    lines: list[str] = []
    cap = prepare_video(clip, max_side=W, log=lines.append)
    scene = write_scene(tmp_path / "scene", cap, log=lines.append)
    idx, est, info = _read_written(scene)
    assert info["poses"] == "sfm" and info["fallback"] is None
    assert info["sfm"]["registered"] == 20 and list(idx) == list(range(20))
    assert info["split"] == {"train": 18, "test": 2, "test_every": 8}
    assert abs(cap.K[0, 0] / K[0, 0] - 1) < 0.05
    s, r, t = umeyama(est[:, :3, 3], truth[:, :3, 3])
    path = np.sum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1))
    pos = est[:, :3, 3] @ (s * r).T + t
    assert np.max(np.linalg.norm(pos - truth[:, :3, 3], axis=1)) < 0.05 * path
    assert max(_angle_deg((r @ e[:3, :3]).T @ g[:3, :3]) for e, g in zip(est, truth)) < 2.0
    # progress for each phase, and the loaded scene is normalised by the recorded content normalisation
    assert any(ln.startswith("prepare: decoded") for ln in lines) and any("SfM registered" in ln for ln in lines)
    assert any(ln.startswith("prepare: wrote") for ln in lines)
    train = load_scene(scene, "train")
    assert np.allclose(train.normalization.centre, info["normalization"]["centre"])
    dist = np.linalg.norm(train.camtoworlds[:, :3, 3], axis=1)
    assert 0.7 < np.median(dist) < 1.3  # cameras about one unit from the content's centre
    assert train.times.min() == 0.0 and np.all(np.diff(train.times) > 0)
    test = load_scene(scene, "test", normalize=train.normalization)
    assert np.allclose(test.times, [7 / 19, 15 / 19])


def test_a_still_clip_falls_back_to_identity_poses(tmp_path):
    """A camera held still while the cube slides: the image hardly moves (its static majority), so SfM is skipped,
    the camera turns by ~0 degrees, the poses are the identity and the focal length comes from --fov; one line says
    so, and prepare.json records it."""
    K = pinhole(W, H, 0.8 * W)
    cam = look_at_c2w((0.3, -1.6, 1.0), (0.0, 0.0, 0.4))
    offs = [(0.02 * i, 0.0, 0.0) for i in range(12)]
    clip = _clip(tmp_path / "still.mp4", np.stack([cam] * 12), K, offs, supersample=1)
    lines: list[str] = []
    cap = prepare_video(clip, max_side=W, fov_deg=70.0, log=lines.append)
    assert cap.info["poses"] == "still" and sum("falling back to a still camera" in ln for ln in lines) == 1
    assert cap.info["sfm"]["registered"] == 0 and "SfM skipped" in cap.info["fallback"]
    assert np.allclose(cap.c2w[:, :3, :3], np.eye(3)) and np.allclose(cap.c2w[:, :3, 3], 0.0)
    assert np.isclose(cap.K[0, 0], W / (2 * math.tan(math.radians(35.0))))
    scene = write_scene(tmp_path / "scene", cap, log=lambda m: None)
    info = json.loads((scene / "prepare.json").read_text())
    assert info["poses"] == "still" and info["fallback"] == cap.info["fallback"]
    train = load_scene(scene, "train")  # still cameras: one unit in front of the content's centre
    assert np.allclose(train.camtoworlds[:, :3, 3], [0.0, 0.0, -1.0])


def test_a_panning_clip_falls_back_to_rotations(tmp_path):
    """A camera turning about its centre (pan 8 degrees, tilt 3) over 12 frames: no parallax, so SfM registers too
    few frames, or builds a degenerate model (measured: 9-10 frames on 0-2 points), and the clip falls back to rotations
    fitted to its optical flow; with the true focal length (--fov) they agree with the true rotations within 0.3 degrees
    (measured: 0.004 on the rendered frames, 0.01 through H.264)."""
    import pycolmap  # noqa: F401  (the test extra installs it; a broken install fails here, not skips)
    K = pinhole(W, H, 0.8 * W)
    c = np.array([0.3, -1.6, 1.0])
    truth = np.stack([look_at_c2w(c, c + [math.sin(math.radians(-4 + 8 * i / 11)),
                                          math.cos(math.radians(-4 + 8 * i / 11)),
                                          -0.3 + 0.05 * i / 11]) for i in range(12)])
    clip = _clip(tmp_path / "pan.mp4", truth, K, supersample=1)
    lines: list[str] = []
    cap = prepare_video(clip, max_side=W, fov_deg=math.degrees(2 * math.atan(0.5 / 0.8)), log=lines.append)
    assert cap.info["poses"] == "rotation" and cap.info["fallback"].startswith("SfM")  # too few frames or points
    assert cap.info["rotation"]["frames"] == 12
    assert sum("falling back to a camera turning about a fixed centre" in ln for ln in lines) == 1
    rel_true = [truth[0, :3, :3].T @ m[:3, :3] for m in truth]  # rotations relative to frame 0 (c2w)
    assert max(_angle_deg(e[:3, :3].T @ r) for e, r in zip(cap.c2w, rel_true)) < 0.3
    assert np.allclose(cap.c2w[:, :3, 3], 0.0)
    # the same fit on the rendered frames, without the video codec
    room = TexturedRoom(seed=0)
    est, fitted = rotation_poses(np.stack([room.render(m, K, W, H, supersample=1) for m in truth[::3]]), K)
    assert fitted == 3 and max(_angle_deg(e[:3, :3].T @ r) for e, r in zip(est, rel_true[::3])) < 0.3


def test_look_at_point_and_extent_for_cameras_that_share_a_centre():
    """Still or turning cameras: the box sits one unit ahead and the extent is 1.1 x a quarter of that distance,
    not the 1e-3 floor of a zero spread; an orbit keeps 3DGS's camera extent."""
    still = np.tile(np.eye(4), (5, 1, 1))
    centre, dist = look_at_point(still)
    assert np.allclose(centre, [0, 0, 1]) and dist == pytest.approx(1.0)
    assert scene_extent(still) == pytest.approx(1.1 * 0.25)
    turning = np.stack([np.linalg.inv(look_at_c2w((0, 0, 0), (math.sin(a), math.cos(a), 0.0)))
                        for a in np.linspace(-0.2, 0.2, 5)])
    centre, dist = look_at_point(turning)
    assert dist == 1.0 and np.linalg.norm(centre) == pytest.approx(1.0, rel=0.05)
    orbit = np.linalg.inv(orbit_c2w(10, sweep_deg=90))
    c = orbit_c2w(10, sweep_deg=90)[:, :3, 3]
    assert scene_extent(orbit) == pytest.approx(1.1 * np.max(np.linalg.norm(c - c.mean(0), axis=1)))


def test_interleaved_split_and_normalisation():
    train, test = interleaved_split(17, 8)
    assert list(test) == [7, 15] and len(train) == 15
    assert len(interleaved_split(5, 0)[1]) == 0
    with pytest.raises(ValueError, match="--test-every"):
        interleaved_split(10, 1)
    c2w = orbit_c2w(8)
    pts = np.random.default_rng(0).normal(size=(100, 3)) * 0.1 + [0, 0, 0.4]
    norm, how = content_normalization(c2w, pts)
    assert "median of 100 scene points" in how
    assert np.median(np.linalg.norm(norm.points_to_scene(c2w[:, :3, 3]), axis=1)) == pytest.approx(1.0)


def test_a_malformed_recorded_normalisation_names_the_file(tmp_path):
    vm = np.linalg.inv(orbit_c2w(3))
    write_transforms(tmp_path, "train", np.zeros((3, 8, 8, 3)), np.tile(pinhole(8, 8, 8.0), (3, 1, 1)), vm,
                     np.linspace(0, 1, 3), extra={"normalization": {"centre": [0, 0], "scale": 2.0}})
    with pytest.raises(ValueError, match=r"transforms_train\.json: field `normalization` is malformed"):
        load_scene(tmp_path, "train")
    assert load_scene(tmp_path, "train", normalize=False).normalization.scale == 1.0


# ----------------------------------------------------------------------------- Record3D


def test_record3d_reader_reprojects_a_known_point(tmp_path):
    """A point of the room seen by two Record3D frames projects to the same pixels after reading (K column-major,
    ARKit axes flipped to OpenCV), resizing and the content normalisation; the LiDAR depth (at its own 48x64 size,
    low-confidence pixels dropped) comes back in metres through the 16-bit millimetre PNGs."""
    w, h = 192, 256  # portrait, like a phone
    K = pinhole(w, h, 180.0)
    K[0, 2], K[1, 2] = 95.0, 130.0  # off-centre: catches a transposed (row-major) K
    c2w = np.stack([look_at_c2w((0.3 * i, -1.6, 1.0), (0.0, 0.0, 0.4)) for i in range(6)])
    room = TexturedRoom(seed=1)
    images = [room.render(m, K, w, h, supersample=1) for m in c2w]
    dw, dh = 48, 64
    depths = [np.full((dh, dw), 1.5 + 0.1 * i, np.float32) for i in range(6)]
    conf = [np.full((dh, dw), 2, np.uint8) for _ in range(6)]
    for c in conf:
        c[:8] = 1  # the top rows: low confidence
    folder = write_record3d(tmp_path / "r3d", c2w, K, images, depths, conf)
    rec = read_record3d(folder, max_side=128, log=lambda m: None)
    assert rec.images.shape == (6, 128, 96, 3) and np.allclose(rec.K, np.diag([0.5, 0.5, 1]) @ K)
    assert np.allclose(rec.c2w, c2w, atol=1e-6)
    assert rec.depths.shape == (6, 128, 96) and np.all(rec.depths[:, :16] == 0)
    assert np.allclose(rec.depths[3, 16:], 1.8)
    scene = write_scene(tmp_path / "scene", prepare_record3d(folder, max_side=128, log=lambda m: None),
                        test_every=0, log=lambda m: None)
    s = load_scene(scene, "train")
    x = np.array([0.1, 0.2, 0.5])  # a world point in front of every camera
    for i in (0, 5):
        p_true = K @ np.linalg.inv(c2w[i])[:3] @ np.append(x, 1.0)
        vm = s.viewmats[i]
        p = s.Ks[i] @ (vm[:3, :3] @ s.normalization.points_to_scene(x) + vm[:3, 3])
        assert np.allclose(p[:2] / p[2], 0.5 * p_true[:2] / p_true[2], atol=1e-3)
    assert np.allclose(s.normalization.lengths_to_world(s.depths[3][16:]), 1.8, atol=1e-3)
    doc = json.loads((scene / "transforms_train.json").read_text())
    assert doc["depth_scale"] == 0.001 and doc["depth_format"].startswith("16-bit PNG, millimetres")
    assert doc["frames"][0]["depth_file_path"].endswith(".png")


def test_record3d_real_export_depth_decodes_to_metres():
    """The Record3D iPhone export in ../shared/data (LiDAR 192x256, lzfse-compressed float32 metres, ARKit
    confidence): three frames decode to depths of a person and a room 1.5-4 m away, most pixels confident."""
    from conftest import shared_data

    rec = read_record3d(shared_data("real/record3d_dance"), last=3, log=lambda m: None)
    assert rec.images.shape == (3, 320, 240, 3) and rec.depths.shape == (3, 320, 240)
    known = rec.depths > 0
    assert 0.5 < known.mean() < 1.0, known.mean()  # low-confidence pixels are 0
    lo, mid, hi = np.percentile(rec.depths[known], [1, 50, 99])
    assert 1.5 < lo < mid < hi < 4.0, (lo, mid, hi)
    assert "LiDAR 192x256" in rec.depth_note


def test_record3d_without_the_lzfse_decoder_reads_the_frames_and_says_why_no_depth(tmp_path, monkeypatch):
    from fgjax.data import record3d

    K = pinhole(32, 32, 30.0)
    c2w = np.stack([look_at_c2w((0.1 * i, -1.6, 1.0), (0.0, 0.0, 0.4)) for i in range(3)])
    folder = write_record3d(tmp_path / "r3d", c2w, K, [np.full((32, 32, 3), 128, np.uint8)] * 3,
                            [np.ones((16, 16), np.float32)] * 3)
    monkeypatch.setattr(record3d, "_lzfse", None)
    said = []
    rec = read_record3d(folder, log=said.append)
    assert rec.depths is None and rec.images.shape == (3, 32, 32, 3)
    assert "lzfse is not installed" in rec.depth_note and record3d.LZFSE_MISSING in " ".join(said)


def test_record3d_missing_field_and_missing_frame_name_the_file(tmp_path):
    K = pinhole(32, 32, 30.0)
    c2w = np.tile(np.eye(4), (4, 1, 1))
    imgs = [np.full((32, 32, 3), 128, np.uint8)] * 4
    folder = write_record3d(tmp_path / "nok", c2w, K, imgs, drop="K")
    with pytest.raises(ValueError, match=r"metadata: field `K` is missing"):
        read_record3d(folder)
    folder = write_record3d(tmp_path / "nojpg", c2w, K, imgs)
    (folder / "rgbd" / "2.jpg").unlink()
    with pytest.raises(FileNotFoundError, match=r"2\.jpg"):
        read_record3d(folder)


def test_focal_from_fov_and_nearest_rotation_against_independent_forms():
    """The pinhole focal of a field of view (90 degrees: half the width), and the nearest rotation against the polar
    factor (scipy) where det > 0 and, for a matrix with det < 0, against a brute-force search over 20,000 random
    rotations (none nearer in the Frobenius norm)."""
    from scipy.linalg import polar
    from scipy.spatial.transform import Rotation

    from fgjax.data.sfm import focal_from_fov, nearest_rotation

    assert focal_from_fov(320, 90.0) == pytest.approx(160.0)
    assert focal_from_fov(320, 60.0) == pytest.approx(160.0 / math.tan(math.radians(30.0)))
    with pytest.raises(ValueError, match="--fov"):
        focal_from_fov(320, 0.5)
    rng = np.random.default_rng(2)
    r = Rotation.random(random_state=3).as_matrix()
    m = r + 0.1 * rng.normal(size=(3, 3))
    assert np.linalg.det(m) > 0
    np.testing.assert_allclose(nearest_rotation(m), polar(m)[0], atol=1e-12)
    np.testing.assert_allclose(nearest_rotation(r), r, atol=1e-12)
    bad = np.diag([1.0, 0.8, -0.3]) @ r  # det < 0: the polar factor is a reflection, not a rotation
    got = nearest_rotation(bad)
    np.testing.assert_allclose(got @ got.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(got) == pytest.approx(1.0)
    others = Rotation.random(20000, random_state=5).as_matrix()
    assert np.linalg.norm(got - bad) <= np.linalg.norm(others - bad, axis=(1, 2)).min() + 1e-12


def test_relative_rotation_recovers_a_turn_despite_a_moving_group():
    """Unit rays turned by a known rotation, 30 % of them turned by another (a moving object): MSAC plus the inlier
    refits return the first rotation to float precision and count its rays as the inliers."""
    from scipy.spatial.transform import Rotation

    from fgjax.data.sfm import relative_rotation

    rng = np.random.default_rng(7)
    a = rng.normal(size=(200, 3)) + [0.0, 0.0, 3.0]
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    r = Rotation.from_rotvec([0.02, -0.05, 0.01]).as_matrix()
    other = Rotation.from_rotvec([0.0, 0.08, 0.0]).as_matrix()
    b = a @ r.T
    b[140:] = a[140:] @ other.T
    got, inliers = relative_rotation(a, b, threshold=math.radians(0.2))
    np.testing.assert_allclose(got, r, atol=1e-9)
    assert inliers == 140
    few, count = relative_rotation(a[:2], b[:2], threshold=0.01)  # under 3 rays: no fit
    np.testing.assert_array_equal(few, np.eye(3))
    assert count == 0
