"""Loaders: round trips (writer -> reader), OpenGL <-> OpenCV on real cameras, normalisation, bad input."""

from __future__ import annotations

import json
import math
import os

import imageio.v3 as iio
import numpy as np
import pytest
from conftest import shared_data
from hypothesis import given, settings
from hypothesis import strategies as st

from fgjax.data import write as writer
from fgjax.data.loaders import load_scene
from fgjax.data.scene import Normalization, Scene, camera_centres, compute_normalization
from fgjax.data.write import write_transforms
from fgjax.geometry import c2w_to_viewmat, opencv_to_opengl_c2w, opengl_to_opencv_c2w, viewmat_to_c2w

# ----------------------------------------------------------------------------- helpers


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _viewmats(rng: np.random.Generator, t: int, spread: float = 3.0) -> np.ndarray:
    """[T, 4, 4] random OpenCV world-to-camera matrices (world units)."""
    out = np.tile(np.eye(4), (t, 1, 1))
    for i in range(t):
        r = _rotation(rng)
        c = rng.normal(size=3) * spread + np.array([5.0, -2.0, 1.0])
        out[i, :3, :3] = r
        out[i, :3, 3] = -r @ c
    return out


def _project(k: np.ndarray, vm: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV pinhole: pixels [N, 2] and camera z [N] of world points x [N, 3]."""
    p = x @ vm[:3, :3].T + vm[:3, 3]  # [N, 3]
    uv = p[:, :2] / p[:, 2:3] * np.array([k[0, 0], k[1, 1]]) + np.array([k[0, 2], k[1, 2]])
    return uv, p[:, 2]


def _small_scene(tmp_path, t=3, h=6, w=8, seed=0, **kw):
    rng = np.random.default_rng(seed)
    images = rng.integers(0, 256, size=(t, h, w, 3), dtype=np.uint8)
    ks = np.tile(np.array([[10.0, 0, 4.0], [0, 11.0, 3.5], [0, 0, 1]]), (t, 1, 1))
    vm = _viewmats(rng, t)
    times = np.linspace(0.0, 1.0, t)
    write_transforms(tmp_path, "train", images, ks, vm, times, **kw)
    return images, ks, vm, times


def _edit_json(path, fn):
    with open(path) as f:
        doc = json.load(f)
    fn(doc)
    with open(path, "w") as f:
        json.dump(doc, f)  # NaN is written as the JSON extension literal NaN


def _listing(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


# ----------------------------------------------------------------------------- conversions


def test_opengl_opencv_conversion_is_an_involution_flipping_y_and_z():
    rng = np.random.default_rng(1)
    c2w = viewmat_to_c2w(_viewmats(rng, 4))
    gl = opencv_to_opengl_c2w(c2w)
    np.testing.assert_allclose(opengl_to_opencv_c2w(gl), c2w, atol=1e-15)
    np.testing.assert_array_equal(gl[:, :3, 3], c2w[:, :3, 3])  # same centre
    np.testing.assert_array_equal(gl[:, :3, 0], c2w[:, :3, 0])  # x axis kept
    np.testing.assert_array_equal(gl[:, :3, 1], -c2w[:, :3, 1])  # y up = -(y down)
    np.testing.assert_array_equal(gl[:, :3, 2], -c2w[:, :3, 2])  # z back = -(z forward)
    np.testing.assert_allclose(c2w_to_viewmat(c2w) @ c2w, np.tile(np.eye(4), (4, 1, 1)), atol=1e-12)


def test_garden_cameras_roundtrip_through_opengl_transforms(tmp_path):
    data = np.load(shared_data("garden") / "test_garden.npz")
    vm = data["viewmats"].astype(np.float64)  # [3, 4, 4] OpenCV world->camera
    ks = data["Ks"].astype(np.float64)
    w, h = int(data["width"]), int(data["height"])
    pts = data["means3d"][::20].astype(np.float64)  # [~6900, 3]
    images = np.broadcast_to(np.linspace(0, 255, w, dtype=np.uint8)[None, :, None], (3, h, w, 3)).copy()
    json_path = write_transforms(tmp_path, "train", images, ks, vm, np.array([0.0, 0.5, 1.0]))

    scene = load_scene(tmp_path, normalize=False)
    assert (scene.width, scene.height) == (w, h)
    np.testing.assert_allclose(scene.viewmats, vm, atol=1e-6)
    np.testing.assert_allclose(scene.Ks, ks, atol=1e-6)
    np.testing.assert_allclose(scene.times, [0.0, 0.5, 1.0])

    frames = json.loads(json_path.read_text())["frames"]
    for i in range(3):
        uv0, z0 = _project(ks[i], vm[i], pts)
        uv1, z1 = _project(scene.Ks[i], scene.viewmats[i], pts)
        front = z0 > 0.01
        visible = front & np.all((uv0 >= 0) & (uv0 <= [w, h]), axis=-1)
        assert visible.mean() > 0.3  # the garden cameras see much of the cloud
        np.testing.assert_allclose(uv1[front], uv0[front], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(z1, z0, atol=1e-9)
        # Independent OpenGL projection straight from the file: the camera looks down -z, y is up.
        c2w_gl = np.array(frames[i]["transform_matrix"])
        p_gl = pts @ np.linalg.inv(c2w_gl)[:3, :3].T + np.linalg.inv(c2w_gl)[:3, 3]  # [N, 3]
        assert np.all(p_gl[z0 > 0, 2] < 0) and np.all(p_gl[z0 < 0, 2] > 0)
        np.testing.assert_allclose(p_gl[:, 2], -z0, atol=1e-9)
        u = ks[i, 0, 2] + ks[i, 0, 0] * p_gl[:, 0] / -p_gl[:, 2]
        v = ks[i, 1, 2] - ks[i, 1, 1] * p_gl[:, 1] / -p_gl[:, 2]
        np.testing.assert_allclose(np.stack([u, v], -1)[visible], uv0[visible], atol=1e-6)


def test_normalization_maps_cameras_back_and_keeps_pixels(tmp_path):
    rng = np.random.default_rng(2)
    _, ks, vm, _ = _small_scene(tmp_path, t=5)
    scene = load_scene(tmp_path)  # normalize=True
    norm = scene.normalization
    np.testing.assert_allclose(norm.viewmats_to_world(scene.viewmats), vm, atol=1e-6)
    np.testing.assert_allclose(scene.viewmats_world(), vm, atol=1e-6)
    centres = camera_centres(scene.viewmats)
    np.testing.assert_allclose(centres.mean(0), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(centres, axis=-1).max(), 1.0, rtol=1e-12)
    pts = rng.normal(size=(50, 3)) * 2 + 5
    for i in range(5):
        uv0, z0 = _project(ks[i], vm[i], pts)
        uv1, z1 = _project(scene.Ks[i], scene.viewmats[i], norm.points_to_scene(pts))
        np.testing.assert_allclose(uv1, uv0, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(z1, norm.lengths_to_scene(z0), rtol=1e-12)
    np.testing.assert_allclose(norm.points_to_world(norm.points_to_scene(pts)), pts, atol=1e-12)
    assert Normalization.from_dict(json.loads(json.dumps(norm.to_dict()))).to_dict() == norm.to_dict()


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    scale=st.floats(1e-3, 1e3),
    centre=st.lists(st.floats(-100, 100), min_size=3, max_size=3),
)
def test_normalization_pose_roundtrip(seed, scale, centre):
    vm = _viewmats(np.random.default_rng(seed), 4)
    norm = Normalization(np.array(centre), scale)
    back = norm.viewmats_to_world(norm.viewmats_to_scene(vm))
    np.testing.assert_allclose(back, vm, atol=1e-6 * (1 + np.abs(vm).max()))
    np.testing.assert_allclose(
        camera_centres(norm.viewmats_to_scene(vm)), norm.points_to_scene(camera_centres(vm)), atol=1e-6
    )


def test_compute_normalization_degenerate_cameras_keep_scale_one():
    norm = compute_normalization(np.tile([[1.0, 2.0, 3.0]], (4, 1)))
    assert norm.scale == 1.0 and np.allclose(norm.centre, [1, 2, 3])
    with pytest.raises(ValueError, match="scale"):
        Normalization(np.zeros(3), 0.0)


# ----------------------------------------------------------------------------- layouts


def _blender_frame(i, t, c2w_cv, rel):
    fr = {"file_path": rel, "transform_matrix": opencv_to_opengl_c2w(c2w_cv).tolist()}
    if t is not None:
        fr["time"] = t
    return fr


def test_blender_rgba_no_extension_no_time(tmp_path):
    rng = np.random.default_rng(3)
    h, w = 4, 6
    (tmp_path / "train").mkdir()
    vm = _viewmats(rng, 3)
    frames = []
    for i in range(3):
        rgba = np.zeros((h, w, 4), np.uint8)
        rgba[..., 0] = 255
        rgba[0, :, 3] = 255  # opaque red row
        rgba[1, :, 3] = 0  # transparent row
        rgba[2:, :, 3] = 51  # 20 % alpha
        iio.imwrite(tmp_path / "train" / f"r_{i:03d}.png", rgba)
        frames.append(_blender_frame(i, None, viewmat_to_c2w(vm[i]), f"./train/r_{i:03d}"))
    angle = 0.7
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))

    scene = load_scene(tmp_path, normalize=False)
    fx = 0.5 * w / math.tan(0.5 * angle)
    np.testing.assert_allclose(scene.Ks[1], [[fx, 0, w / 2], [0, fx, h / 2], [0, 0, 1]])
    np.testing.assert_allclose(scene.viewmats, vm, atol=1e-12)
    np.testing.assert_allclose(scene.times, [0.0, 0.5, 1.0])
    assert scene.frame_names == ["train/r_000", "train/r_001", "train/r_002"]
    np.testing.assert_allclose(scene.images[0, 0, 0], [1, 0, 0])  # opaque red
    np.testing.assert_allclose(scene.images[0, 1, 0], [1, 1, 1])  # white background
    np.testing.assert_allclose(scene.images[0, 2, 0], [1, 0.8, 0.8], atol=1e-6)
    black = load_scene(tmp_path, normalize=False, background=(0.0, 0.0, 0.0))
    np.testing.assert_allclose(black.images[0, 1, 0], [0, 0, 0])
    np.testing.assert_allclose(black.images[0, 2, 0], [0.2, 0, 0], atol=1e-6)


def test_dnerf_splits_share_the_training_normalization(tmp_path):
    rng = np.random.default_rng(4)
    img = np.full((4, 4, 3), 128, np.uint8)
    for split, t in (("train", 4), ("val", 2)):
        (tmp_path / split).mkdir()
        vm = _viewmats(rng, t)
        frames = []
        for i in range(t):
            iio.imwrite(tmp_path / split / f"r_{i}.png", img)
            frames.append(_blender_frame(i, i / (2 * t), viewmat_to_c2w(vm[i]), f"{split}/r_{i}.png"))
        doc = {"camera_angle_x": 1.0, "frames": frames}
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps(doc))
    train, val = load_scene(tmp_path, "train"), load_scene(tmp_path, "val")
    assert val.normalization.to_dict() == train.normalization.to_dict()
    np.testing.assert_allclose(val.times, [0.0, 0.25])
    np.testing.assert_allclose(np.linalg.norm(camera_centres(train.viewmats), axis=-1).max(), 1.0)


def test_nerfstudio_transforms_json_with_filename_splits(tmp_path):
    rng = np.random.default_rng(5)
    (tmp_path / "images").mkdir()
    vm = _viewmats(rng, 4)
    frames = []
    for i in range(4):
        iio.imwrite(tmp_path / "images" / f"f{i}.jpg", np.full((6, 8, 3), 40 * i, np.uint8))
        fr = _blender_frame(i, i / 3, viewmat_to_c2w(vm[i]), f"images/f{i}.jpg")
        if i == 3:
            fr["fl_x"] = 20.0  # per-frame override
        frames.append(fr)
    doc = {"fl_x": 9.0, "fl_y": 9.5, "cx": 4.1, "cy": 2.9, "w": 8, "h": 6, "frames": frames}
    doc["train_filenames"] = ["images/f0.jpg", "images/f2.jpg", "images/f3.jpg"]
    doc["val_filenames"] = ["images/f1.jpg"]
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    train = load_scene(tmp_path, "train", normalize=False)
    val = load_scene(tmp_path, "val", normalize=False)
    assert train.frame_names == ["images/f0", "images/f2", "images/f3"]
    assert val.frame_names == ["images/f1"]
    np.testing.assert_allclose(train.Ks[0], [[9.0, 0, 4.1], [0, 9.5, 2.9], [0, 0, 1]])
    assert train.Ks[2, 0, 0] == 20.0
    np.testing.assert_allclose(val.viewmats[0], vm[1], atol=1e-12)
    np.testing.assert_allclose(train.times, [0.0, 2 / 3, 1.0])
    with pytest.raises(ValueError, match=r"transforms\.json.*`test_filenames`"):
        load_scene(tmp_path, "test")


def _write_nerfies(root, rng, *, n=3, distortion=False, scales=(1, 2)):
    ids = [f"cam_{i:02d}" for i in range(n)]
    (root / "camera").mkdir(parents=True)
    (root / "dataset.json").write_text(
        json.dumps({"count": n, "ids": ids, "train_ids": ids[:-1], "val_ids": ids[-1:]})
    )
    (root / "metadata.json").write_text(
        json.dumps({cid: {"warp_id": i, "appearance_id": i, "camera_id": 0, "time_id": 2 * i}
                    for i, cid in enumerate(ids)})
    )
    cams = {}
    for i, cid in enumerate(ids):
        cam = {
            "orientation": _rotation(rng).tolist(),
            "position": (rng.normal(size=3) * 2).tolist(),
            "focal_length": 30.0 + i,
            "pixel_aspect_ratio": 1.1,
            "principal_point": [7.9, 6.2],
            "image_size": [16, 12],
            "skew": 0.0,
            "radial_distortion": [0.01 if distortion else 0.0, 0.0, 0.0],
            "tangential_distortion": [0.0, 0.0],
        }
        cams[cid] = cam
        (root / "camera" / f"{cid}.json").write_text(json.dumps(cam))
        for s in scales:
            (root / "rgb" / f"{s}x").mkdir(parents=True, exist_ok=True)
            iio.imwrite(root / "rgb" / f"{s}x" / f"{cid}.png", np.full((12 // s, 16 // s, 3), 10 * i, np.uint8))
    return ids, cams


def test_nerfies_cameras_are_opencv_world_to_camera(tmp_path):
    ids, cams = _write_nerfies(tmp_path, np.random.default_rng(6))
    train = load_scene(tmp_path, "train", normalize=False)
    assert train.frame_names == ids[:2]
    for i, cid in enumerate(ids[:2]):
        r = np.array(cams[cid]["orientation"])
        np.testing.assert_allclose(train.viewmats[i, :3, :3], r, atol=1e-12)
        np.testing.assert_allclose(train.viewmats[i, :3, 3], -r @ np.array(cams[cid]["position"]), atol=1e-12)
        f = cams[cid]["focal_length"]
        np.testing.assert_allclose(train.Ks[i], [[f, 0, 7.9], [0, f * 1.1, 6.2], [0, 0, 1]])
        # A point on the optical axis, in front of the camera, lands on the principal point.
        p = np.array(cams[cid]["position"]) + 3.0 * r[2]
        uv, z = _project(train.Ks[i], train.viewmats[i], p[None])
        np.testing.assert_allclose(uv[0], [7.9, 6.2], atol=1e-9)
        assert z[0] > 0
    np.testing.assert_allclose(train.times, [0.0, 0.5])  # time_id 0, 2 of max 4
    val = load_scene(tmp_path, "val")
    assert val.frame_names == ids[2:] and val.times.tolist() == [1.0]
    assert val.normalization.to_dict() == load_scene(tmp_path, "train").normalization.to_dict()
    half = load_scene(tmp_path, "train", normalize=False, downscale=2)  # uses rgb/2x
    assert (half.width, half.height) == (8, 6)
    np.testing.assert_allclose(half.Ks[:, :2], train.Ks[:, :2] / 2)


def test_nerfies_downscale_without_prescaled_folder_and_distortion_warning(tmp_path):
    _write_nerfies(tmp_path, np.random.default_rng(7), distortion=True, scales=(1,))
    with pytest.warns(UserWarning, match="radial_distortion"):
        full = load_scene(tmp_path, "all", normalize=False)
    with pytest.warns(UserWarning, match="radial_distortion"):
        quarter = load_scene(tmp_path, "all", normalize=False, downscale=4)
    assert full.num_frames == 3 and quarter.images.shape == (3, 3, 4, 3)
    np.testing.assert_allclose(quarter.Ks[:, :2], full.Ks[:, :2] / 4)


def test_downscale_scales_intrinsics_and_area_averages(tmp_path):
    block = np.kron(np.arange(12, dtype=np.uint8).reshape(3, 4) * 20, np.ones((2, 2), np.uint8))  # [6, 8]
    images = np.repeat(block[None, :, :, None], 3, axis=-1).repeat(2, axis=0)  # [2, 6, 8, 3]
    ks = np.tile(np.array([[10.0, 0, 4.0], [0, 11.0, 3.5], [0, 0, 1]]), (2, 1, 1))
    masks = np.kron(np.arange(12).reshape(3, 4), np.ones((2, 2), np.int64))[None].repeat(2, 0)
    write_transforms(tmp_path, "train", images, ks, _viewmats(np.random.default_rng(0), 2), [0, 1], masks=masks)
    s = load_scene(tmp_path, normalize=False, downscale=2)
    assert s.images.shape == (2, 3, 4, 3)
    np.testing.assert_allclose(s.images[0, ..., 0], block[::2, ::2] / 255.0, atol=1e-6)
    np.testing.assert_allclose(s.Ks[0], [[5.0, 0, 2.0], [0, 5.5, 1.75], [0, 0, 1]])
    np.testing.assert_array_equal(s.masks[0], np.arange(12).reshape(3, 4))


def test_depth_and_mask_roundtrip(tmp_path):
    rng = np.random.default_rng(8)
    t, h, w = 2, 6, 8
    depths = rng.uniform(0.5, 4.0, size=(t, h, w))
    masks = rng.integers(0, 3, size=(t, h, w))
    _, _, vm, _ = _small_scene(tmp_path, t=t, h=h, w=w, depths=depths, masks=masks)
    s = load_scene(tmp_path)
    np.testing.assert_allclose(s.depths, depths * s.normalization.scale, rtol=1e-6)
    np.testing.assert_array_equal(s.masks, masks)
    np.testing.assert_allclose(s.normalization.lengths_to_world(s.depths), depths, rtol=1e-6)


def test_sibling_depth_png_uses_depth_scale(tmp_path):
    t, h, w = 2, 6, 8
    _small_scene(tmp_path, t=t, h=h, w=w, extra={"depth_scale": 0.01})
    (tmp_path / "depth").mkdir()
    raw = np.arange(h * w, dtype=np.uint16).reshape(h, w) * 7
    for i in range(t):
        iio.imwrite(tmp_path / "depth" / f"train_{i:05d}.png", raw)
    s = load_scene(tmp_path, normalize=False)
    np.testing.assert_allclose(s.depths[1], raw * 0.01, rtol=1e-6)
    os.remove(tmp_path / "depth" / "train_00001.png")
    with pytest.raises(FileNotFoundError, match=r"frame 1.*depth/.*train_00001"):
        load_scene(tmp_path, normalize=False)


# ----------------------------------------------------------------------------- bad input: loaders


def test_missing_frame_errors_or_is_skipped_with_warning(tmp_path):
    _small_scene(tmp_path)
    os.remove(tmp_path / "images" / "train_00001.png")
    with pytest.raises(FileNotFoundError, match=r"transforms_train\.json: frame 1 .*`file_path`.*train_00001"):
        load_scene(tmp_path)
    with pytest.warns(UserWarning, match=r"transforms_train\.json: frame 1 .*skipped"):
        s = load_scene(tmp_path, skip_missing=True)
    assert s.frame_names == ["images/train_00000", "images/train_00002"]
    np.testing.assert_allclose(s.times, [0.0, 1.0])  # times of the listed frames are kept


def test_unreadable_image_names_json_frame_and_path(tmp_path):
    _small_scene(tmp_path)
    (tmp_path / "images" / "train_00002.png").write_bytes(b"not a png at all")
    with pytest.raises(ValueError, match=r"transforms_train\.json: frame 2 \(field `file_path`\).*train_00002\.png"):
        load_scene(tmp_path)


def test_inconsistent_image_sizes_name_both_files(tmp_path):
    _small_scene(tmp_path)
    iio.imwrite(tmp_path / "images" / "train_00001.png", np.zeros((7, 8, 3), np.uint8))
    with pytest.raises(ValueError, match=r"frame 1: image .*train_00001\.png is 8x7 but .*train_00000\.png is 8x6"):
        load_scene(tmp_path)


def _set_matrix(value_fn, frame=2):
    def fn(doc):
        m = np.array(doc["frames"][frame]["transform_matrix"])
        doc["frames"][frame]["transform_matrix"] = value_fn(m).tolist()

    return fn


@pytest.mark.parametrize(
    "edit, message",
    [
        (_set_matrix(lambda m: m * np.where(np.eye(4)[0:1] > 0, np.nan, 1.0)), "non-finite"),
        (_set_matrix(lambda m: np.diag([1.1, 1.0, 1.0, 1.0]) @ m), "not orthonormal"),
        (_set_matrix(lambda m: m @ np.diag([1.0, 1.0, -1.0, 1.0])), "det"),
        (_set_matrix(lambda m: m + np.array([[0, 0, 0, 0]] * 3 + [[0, 0, 0.5, 0]])), "last row"),
        (_set_matrix(lambda m: m[:2]), "shape"),
    ],
    ids=["nan", "scaled", "reflection", "projective", "shape"],
)
def test_bad_pose_names_json_frame_and_field(tmp_path, edit, message):
    _small_scene(tmp_path)
    _edit_json(tmp_path / "transforms_train.json", edit)
    with pytest.raises(ValueError, match=rf"transforms_train\.json: frame 2: .*`transform_matrix`.*{message}"):
        load_scene(tmp_path)


@pytest.mark.parametrize("bad_time", [1.5, -0.1, float("nan"), "0.5"])
def test_time_out_of_range_names_json_frame_and_field(tmp_path, bad_time):
    _small_scene(tmp_path)

    def fn(doc):
        doc["frames"][1]["time"] = bad_time

    _edit_json(tmp_path / "transforms_train.json", fn)
    with pytest.raises(ValueError, match=r"transforms_train\.json: frame 1: field `time`"):
        load_scene(tmp_path)


def test_partial_times_and_size_fields_are_rejected(tmp_path):
    _small_scene(tmp_path)
    path = tmp_path / "transforms_train.json"
    _edit_json(path, lambda d: d["frames"][2].pop("time"))
    with pytest.raises(ValueError, match=r"frame 2: field `time` is missing"):
        load_scene(tmp_path)
    _edit_json(path, lambda d: d["frames"][2].update(time=1.0, w=99))
    with pytest.raises(ValueError, match=r"frame 2: field `w` = 99 but image .*train_00002\.png is 8x6"):
        load_scene(tmp_path)

    def no_intrinsics(d):
        d["frames"][2]["w"] = 8
        for k in ("fl_x", "fl_y", "cx", "cy"):
            d["frames"][0].pop(k)
        d.pop("camera_angle_x", None)

    _edit_json(path, no_intrinsics)
    with pytest.raises(ValueError, match=r"frame 0: no intrinsics.*`fl_x`.*`camera_angle_x`"):
        load_scene(tmp_path)


def test_no_layout_and_malformed_json(tmp_path):
    with pytest.raises(FileNotFoundError, match="transforms_train.json"):
        load_scene(tmp_path)
    (tmp_path / "transforms_train.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"transforms_train\.json: cannot parse"):
        load_scene(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": [{"transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(ValueError, match=r"frame 0: field `file_path`"):
        load_scene(tmp_path)


def test_nerfies_bad_camera_names_camera_file_and_field(tmp_path):
    ids, cams = _write_nerfies(tmp_path, np.random.default_rng(9))
    cam_path = tmp_path / "camera" / f"{ids[1]}.json"
    bad = dict(cams[ids[1]], orientation=(np.array(cams[ids[1]]["orientation"]) * 2).tolist())
    cam_path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=rf"{ids[1]}\.json: id '{ids[1]}'.*`orientation`.*orthonormal"):
        load_scene(tmp_path, normalize=False)
    cam_path.write_text(json.dumps({k: v for k, v in cams[ids[1]].items() if k != "focal_length"}))
    with pytest.raises(ValueError, match=rf"{ids[1]}\.json: .*field `focal_length` is missing"):
        load_scene(tmp_path, normalize=False)
    (tmp_path / "rgb" / "1x" / f"{ids[0]}.png").unlink()
    cam_path.write_text(json.dumps(cams[ids[1]]))
    with pytest.raises(FileNotFoundError, match=rf"dataset\.json: id '{ids[0]}' \(frame 0\).*{ids[0]}"):
        load_scene(tmp_path, normalize=False)


@pytest.mark.parametrize(
    "field, value",
    [
        ("images", np.zeros((2, 4, 5), np.float32)),
        ("images", np.full((2, 4, 5, 3), 2.0, np.float32)),
        ("Ks", np.zeros((2, 3, 3))),
        ("viewmats", np.tile(np.diag([1.0, 1.0, 2.0, 1.0]), (2, 1, 1))),
        ("times", np.array([0.0, 1.5])),
        ("frame_names", ["a"]),
        ("depths", np.zeros((2, 4, 4), np.float32)),
        ("masks", np.zeros((2, 4, 5), np.float32)),
        ("width", 7),
    ],
)
def test_scene_validation_names_the_field(field, value):
    good = dict(
        images=np.zeros((2, 4, 5, 3), np.float32),
        Ks=np.tile(np.array([[5.0, 0, 2.5], [0, 5.0, 2.0], [0, 0, 1]]), (2, 1, 1)),
        viewmats=np.tile(np.eye(4), (2, 1, 1)),
        times=np.array([0.0, 1.0]),
        width=5,
        height=4,
        frame_names=["a", "b"],
    )
    Scene(**good)  # the baseline is valid
    with pytest.raises(ValueError, match=rf"Scene\.{field}"):
        Scene(**dict(good, **{field: value}))


# ----------------------------------------------------------------------------- bad input: writer


def _good_args(rng, t=3, h=6, w=8):
    images = rng.integers(0, 256, size=(t, h, w, 3), dtype=np.uint8)
    ks = np.tile(np.array([[10.0, 0, 4.0], [0, 11.0, 3.5], [0, 0, 1]]), (t, 1, 1))
    return [images, ks, _viewmats(rng, t), np.linspace(0, 1, t)]


def _bad_viewmat(args, value):
    args[2] = args[2].copy()
    args[2][1, 0, 0] = value
    return args


@pytest.mark.parametrize(
    "mutate, kwargs, error, message",
    [
        (lambda a: _bad_viewmat(a, np.nan), {}, ValueError, r"viewmats\[1\] has non-finite"),
        (lambda a: _bad_viewmat(a, 3.0), {}, ValueError, r"viewmats\[1\] rotation block is not orthonormal"),
        (lambda a: a[:3] + [np.array([0.0, 1.2, 1.0])], {}, ValueError, r"times\[1\] = 1.2"),
        (lambda a: [a[0], a[1] + np.array([[0, 1.0, 0], [0, 0, 0], [0, 0, 0]]), a[2], a[3]], {},
         ValueError, r"Ks\[0\]"),
        (lambda a: [a[0].astype(np.float32) * 2, *a[1:]], {}, ValueError, r"images\[0\] float values"),
        (lambda a: a, {"extra": {"scene": object()}}, ValueError, "not JSON-serialisable"),
        (lambda a: a, {"extra": {"frames": []}}, ValueError, "reserved"),
        (lambda a: a, {"depths": np.ones((3, 5, 8))}, ValueError, "depths must be"),
        (lambda a: a, {"frame_names": ["a", "a", "b"]}, ValueError, "distinct"),
        (lambda a: a, {"frame_names": ["a", "../b", "c"]}, ValueError, r"frame_names\[1\]"),
    ],
    ids=["nan-pose", "non-rigid", "time", "skew", "image-range", "extra-json", "extra-reserved", "depth", "dup",
         "name"],
)
def test_writer_rejects_bad_input_and_writes_nothing(tmp_path, mutate, kwargs, error, message):
    out = tmp_path / "out"
    args = mutate(_good_args(np.random.default_rng(10)))
    with pytest.raises(error, match=message):
        write_transforms(out, "train", *args, **kwargs)
    assert not out.exists()


def test_writer_with_paths_rejects_missing_and_inconsistent_files(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    iio.imwrite(src / "a.png", np.zeros((6, 8, 3), np.uint8))
    iio.imwrite(src / "b.png", np.zeros((5, 8, 3), np.uint8))
    _, ks, vm, times = _good_args(np.random.default_rng(11), t=2)
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("pre-existing")
    with pytest.raises(ValueError, match=r"b\.png is 8x5 but .*a\.png is 8x6"):
        write_transforms(out, "train", [src / "a.png", src / "b.png"], ks, vm, times)
    with pytest.raises(FileNotFoundError, match=r"images_or_paths\[1\]"):
        write_transforms(out, "train", [src / "a.png", src / "c.png"], ks, vm, times)
    assert _listing(out) == ["keep.txt"]
    write_transforms(out, "train", [src / "a.png", src / "a.png"], ks, vm, times, frame_names=["x", "y"])
    s = load_scene(out, normalize=False)
    assert s.frame_names == ["images/x", "images/y"]
    np.testing.assert_allclose(s.viewmats, vm, atol=1e-12)


def test_writer_failure_midway_leaves_nothing_new(tmp_path, monkeypatch):
    rng = np.random.default_rng(12)
    out = tmp_path / "out"
    images, ks, vm, times = _good_args(rng)
    write_transforms(out, "train", images, ks, vm, times)  # an earlier, good write
    before = _listing(out)
    old_json = (out / "transforms_train.json").read_text()
    calls = []

    def failing_save(path, a):
        calls.append(path)
        if len(calls) >= 2:
            raise OSError("disk full (simulated)")
        writer._save_npy.__wrapped__(path, a)

    failing_save.__wrapped__ = writer._save_npy
    monkeypatch.setattr(writer, "_save_npy", failing_save)
    new_images, new_ks, new_vm, _ = _good_args(rng)
    with pytest.raises(OSError, match="simulated"):
        write_transforms(out, "train", new_images, new_ks, new_vm, times, depths=np.ones((3, 6, 8)))
    with pytest.raises(OSError, match="simulated"):
        write_transforms(tmp_path / "fresh", "val", new_images, new_ks, new_vm, times, depths=np.ones((3, 6, 8)))
    assert len(calls) == 3  # second write failed on its first depth file
    assert _listing(out) == before  # no temp files, no depth/ folder, no new images
    assert (out / "transforms_train.json").read_text() == old_json
    assert not (tmp_path / "fresh").exists()


def test_cli_reports_bad_input_without_traceback(tmp_path, capsys):
    from fgjax import cli

    missing = tmp_path / "nope"
    assert cli.main(["train", "--data", str(missing), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "fgjax train: error:" in err and str(missing) in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()
