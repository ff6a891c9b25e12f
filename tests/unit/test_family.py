"""The scene family (`fgjax.synth.family`): reproducible per seed, varied over seeds, physically consistent."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest
from conftest import synth

from fgjax.synth import family as fam
from fgjax.synth.scene import camera_c2w, compose_transforms, deform, moving_labels, scene_states

SEEDS = range(40)


@pytest.fixture(scope="module")
def scenes():
    return {s: fam.make_family_scene(fam.family_config(s)) for s in SEEDS}


def test_same_seed_same_scene_bit_for_bit():
    a = fam.make_family_scene(fam.family_config(7))
    b = fam.make_family_scene(fam.family_config(7))
    for f in ("means", "quats", "scales", "opacities", "colors", "labels", "K"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    assert [o.to_dict() for o in a.objects] == [o.to_dict() for o in b.objects]
    for t in (0.0, 0.37, 1.0):
        assert np.array_equal(camera_c2w(a, t), camera_c2w(b, t))
    c = fam.make_family_scene(fam.family_config(8))
    assert len(c.means) != len(a.means) or not np.array_equal(c.means, a.means)


def test_a_size_override_keeps_the_seeds_scene():
    a = fam.make_family_scene(fam.family_config(5))
    b = fam.make_family_scene(fam.family_config(5, size=(96, 72), frames=9))
    assert (b.cfg.width, b.cfg.height, b.cfg.frames) == (96, 72, 9)
    assert np.array_equal(a.means, b.means) and np.array_equal(a.colors, b.colors)
    assert b.K[0, 0] == pytest.approx(a.K[0, 0] * 96 / a.cfg.width)


def test_the_family_covers_what_it_promises(scenes):
    """Over 40 seeds: every joint kind, 1 to 4 parts, attached parts, hinge axes that are vertical, horizontal
    and tilted, slides in several directions, every camera path, resolutions from 128x96 to 320x240, parts that
    stay open and parts that move twice, and parts coloured like their box."""
    kinds, counts, paths, sizes, axes_z, dirs = set(), set(), set(), set(), [], []
    attached = stay_open = twice = 0
    for sc in scenes.values():
        counts.add(sc.num_objects)
        paths.add(sc.camera["path"])
        sizes.add((sc.cfg.width, sc.cfg.height))
        for o in sc.objects:
            kinds.add(o.kind)
            attached += o.parent > 0
            if o.kind == "hinge" and not o.parent:
                axes_z.append(abs(o.axis[2]) / np.linalg.norm(o.axis))
            if o.kind == "slide":
                dirs.append(o.direction)
            stay_open += o.key_states[-1] > 0
            twice += int(np.sum(np.diff(np.sign(np.diff(o.key_states))) < 0)) >= 2
    assert kinds == set(synth.FAMILY_KINDS)
    assert counts == {1, 2, 3, 4}
    assert paths == {"orbit", "dolly", "handheld", "still"}
    assert min(sizes) >= (128, 96) and max(sizes) <= (320, 240) and len(sizes) >= 4
    assert attached >= 3 and stay_open >= 5 and twice >= 3
    axes_z = np.asarray(axes_z)
    assert np.any(axes_z > 0.99) and np.any(axes_z < 0.01) and np.any((axes_z > 0.1) & (axes_z < 0.95))
    d = np.asarray(dirs)
    assert np.any(np.abs(d[:, 2]) > 0.9) and np.any(np.abs(d[:, 0]) > 0.9) and np.any(np.abs(d[:, 1]) > 0.9)


def test_objects_stay_apart_in_the_room_and_above_the_floor(scenes):
    for seed, sc in scenes.items():
        assert sc.min_separation >= fam.MIN_SEPARATION, seed
        for s in (0.0, 0.5, 1.0):
            means, _ = deform(sc, np.full(sc.num_objects, s))
            moving = means[sc.labels > 0]
            assert moving[:, 2].min() > -1e-6, (seed, s)
            assert np.abs(moving[:, :2]).max() < synth.ROOM_HALF, (seed, s)


def test_cameras_stay_inside_the_side_walls_and_roll_at_most_five_degrees(scenes):
    for seed, sc in scenes.items():
        for t in np.linspace(0, 1, 9):
            for d_az in (0.0, math.radians(10), -math.radians(10)):  # the test views too
                c2w = camera_c2w(sc, float(t), d_azimuth=d_az, d_height=0.15, d_radius=-0.15)
                assert abs(c2w[0, 3]) < synth.ROOM_HALF - 0.1, (seed, t)
            c2w = camera_c2w(sc, float(t))
            x_cam, z_world = c2w[:3, 0], np.array([0.0, 0.0, 1.0])
            tilt = math.degrees(math.asin(abs(float(x_cam @ z_world))))  # the image x axis against the horizon
            assert tilt <= 10.0 + 1e-9, (seed, t, tilt)
        if sc.camera["path"] == "still":
            assert np.array_equal(camera_c2w(sc, 0.0), camera_c2w(sc, 1.0))


def test_schedules_are_keyframes_in_time_order_and_every_part_moves(scenes):
    for sc in scenes.values():
        states = scene_states(sc, np.linspace(0, 1, 60))
        assert states.min() >= 0.0 and states.max() <= 1.0
        for k, o in enumerate(sc.objects):
            assert np.all(np.diff(o.key_times) > 0) and o.key_times[0] == 0.0 and o.key_times[-1] == 1.0
            assert states[:, k].max() >= 0.7


def test_an_attached_part_moves_with_its_parent():
    sc = next(s for s in (fam.make_family_scene(fam.family_config(i)) for i in SEEDS)
              if any(o.parent for o in s.objects))
    child = next(o for o in sc.objects if o.parent)
    states = np.zeros(sc.num_objects)
    states[child.parent - 1] = 0.8
    tr = compose_transforms(sc.objects, states)
    np.testing.assert_allclose(tr[child.label], tr[child.parent], atol=1e-12)  # child at rest rides along
    states[child.label - 1] = 0.5
    tr2 = compose_transforms(sc.objects, states)
    assert not np.allclose(tr2[child.label], tr[child.label])
    moving = moving_labels(sc.objects, np.stack([np.zeros(sc.num_objects), np.eye(sc.num_objects)[child.parent - 1]]))
    assert moving[0, child.label - 1] and moving[0, child.parent - 1]


def _digest(folder) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.suffix in (".png", ".npy", ".npz", ".json"):
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_generated_family_scene_is_reproducible_and_records_its_seed(tmp_path):
    cfg = fam.family_config(3, size=(40, 30), frames=4)
    a = synth.generate(cfg, tmp_path / "a")
    b = synth.generate(cfg, tmp_path / "b")
    assert _digest(a) == _digest(b)
    import json

    meta = json.loads((a / "gt" / "meta.json").read_text())
    assert meta["family"] == 3 and meta["config"]["family"] == 3 and meta["camera_path"]["path"]
    assert [o["parent"] for o in meta["objects"]] == [o.parent for o in fam.make_family_scene(cfg).objects]


def test_parse_seeds():
    assert fam.parse_seeds("0-3,12") == [0, 1, 2, 3, 12]
    assert fam.parse_seeds("6") == [6]
    for bad in ("", "3-1", "a", "-2"):
        with pytest.raises(ValueError, match="seeds"):
            fam.parse_seeds(bad)


def test_family_config_rejects_a_bad_seed_and_hand_made_kinds():
    with pytest.raises(ValueError, match="seed"):
        fam.family_config(-1)
    with pytest.raises(ValueError, match="unknown kind"):
        synth.SynthConfig(objects=("door",), family=1)
    with pytest.raises(ValueError, match="make_family_scene"):
        synth.make_scene(fam.family_config(1))
