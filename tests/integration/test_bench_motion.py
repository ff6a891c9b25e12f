"""``fgjax bench motion`` on the tiny synthetic run: a known deformation gives known numbers."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from fgjax.bench import motion


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _pipeline_run import shared_base, tiny_run

    return tiny_run(shared_base(tmp_path_factory) / "pipeline", stage2=False)


def test_motion_report_measures_a_known_translation(tiny, monkeypatch, tmp_path, capsys):
    run_dir, data = tiny
    shift = np.array([0.036, -0.048, 0.0])  # |shift| = 0.06
    real = motion.deformed_gaussians

    def shifted(params, alive, t, spec):
        m, *rest = real(params, alive, t, None)  # the canonical Gaussians ...
        return (m + shift * (t > 0.5), *rest)  # ... translated in the second half of the video only

    monkeypatch.setattr(motion, "deformed_gaussians", shifted)
    r = motion.motion_report(run_dir, data, num_times=5)
    live = r["live_gaussians"]
    assert live > 0
    assert r["moving_gaussians"] == {"0.01": live, "0.05": live, "0.1": 0}
    meta = json.loads((data / "gt" / "meta.json").read_text())
    assert [o["name"] for o in r["objects"]] == [o["name"] for o in meta["objects"]]
    for o in r["objects"]:
        assert o["true_max_displacement"] > 0.06  # the synthetic parts do move
        if o["gaussians"]:
            assert o["learned_max_displacement"] == pytest.approx(0.06, rel=1e-5)
    assert np.isfinite(r["psnr_static_pixels"])
    # the CLI prints the table and writes the same report
    monkeypatch.setattr(motion, "deformed_gaussians", real)
    out = tmp_path / "m.json"
    assert motion.main(["--run", str(run_dir), "--data", str(data), "--json", str(out)]) == 0
    assert "learned" in capsys.readouterr().out and json.loads(out.read_text())["objects"]


def test_motion_report_needs_the_ground_truth(tiny, tmp_path, capsys):
    run_dir, _ = tiny
    assert motion.main(["--run", str(run_dir), "--data", str(tmp_path)]) == 2
    assert "needs a dataset written by `fgjax synth`" in capsys.readouterr().err


def test_motion_scores_ratio_and_angle():
    true = np.zeros((1, 5, 3))
    true[0, :, 0] = [0.0, 0.05, 0.2, 0.1, 0.0]  # largest displacement at t* = index 2, along x
    rot = lambda deg: np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg)), 0.0])
    for scale, deg, ok in ((1.0, 0.0, True), (0.85, 10.0, True), (0.7, 0.0, False), (1.0, 20.0, False),
                           (0.03, 0.0, False)):
        learned = np.zeros_like(true)
        learned[0, 2] = 0.2 * scale * rot(deg)
        s = motion.motion_scores(learned, true)[0]
        assert s["ratio"] == pytest.approx(scale) and s["angle_deg"] == pytest.approx(deg, abs=1e-4)
        assert s["ok"] is ok and s["true"] == pytest.approx(0.2)
    assert not motion.motion_scores(np.full_like(true, np.nan), true)[0]["ok"]  # a part without Gaussians


def test_motion_observability_measures_the_parallax_that_pins_motion_along_the_rays():
    """A part at x = 1 slides along y from t = 2 on and stays there (its t* state: frames 2-4). Seen by a still
    camera at the origin the rays of that state coincide (0 degrees); by cameras stepping along x at depth 0 they
    spread by the angle the part's position subtends between the outermost ones, computed here directly."""
    centres = np.zeros((1, 5, 3))
    centres[0, :, 0] = 1.0
    centres[0, 2:, 1] = 0.5  # [K, T, 3]: along y, toward a camera placed on the far side of y
    still = np.tile([[1.0, -2.0, 0.0]], (5, 1))  # [T, 3]: on the y axis of the part, looking along +y
    o = motion.motion_observability(centres, still)[0]
    assert o["ray_spread_deg"] == pytest.approx(0.0, abs=1e-5)
    assert o["along_ray_deg"] == pytest.approx(0.0, abs=1e-5)  # the slide goes straight away from the camera
    assert np.allclose(o["view_dir"], [0.0, 1.0, 0.0])
    moving = np.stack([[1.0 + 0.3 * i, -2.0, 0.0] for i in range(5)])
    o = motion.motion_observability(centres, moving)[0]
    ray = lambda c: (np.array([1.0, 0.5, 0.0]) - c) / np.linalg.norm(np.array([1.0, 0.5, 0.0]) - c)
    want = np.degrees(np.arccos(ray(moving[2]) @ ray(moving[4])))
    assert o["ray_spread_deg"] == pytest.approx(want, abs=1e-6) and want > 5.0
    assert o["along_ray_deg"] == pytest.approx(np.degrees(np.arccos(abs(ray(moving[2])[1]))), abs=1e-6)


def test_motion_scores_image_angle_ignores_the_error_along_the_ray():
    """A learned displacement off the true one only along the viewing ray is right in the image (0 degrees) and
    wrong in 3D; one turned within the image plane is wrong in both."""
    true = np.zeros((1, 3, 3))
    true[0, 2] = [0.2, 0.0, 0.0]
    view = np.array([[0.0, 0.0, 1.0]])  # the ray at t*: along z
    learned = true.copy()
    learned[0, 2] = [0.2, 0.0, 0.15]  # extra motion along the ray
    s = motion.motion_scores(learned, true, view)[0]
    assert s["image_angle_deg"] == pytest.approx(0.0, abs=1e-5) and s["image_ratio"] == pytest.approx(1.0)
    assert s["angle_deg"] == pytest.approx(np.degrees(np.arctan2(0.15, 0.2)), abs=1e-4) and not s["ok"]
    learned[0, 2] = [0.0, 0.2, 0.0]  # turned by 90 degrees in the image plane
    assert motion.motion_scores(learned, true, view)[0]["image_angle_deg"] == pytest.approx(90.0, abs=1e-5)
    assert "image_angle_deg" not in motion.motion_scores(learned, true)[0]
    learned[0, 2] = [0.0, 0.0, 0.3]  # all along the ray: nothing in the image to compare
    assert np.isnan(motion.motion_scores(learned, true, view)[0]["image_angle_deg"])
    along = np.zeros((1, 3, 3))
    along[0, 2] = [0.0, 0.0, 0.2]  # a true motion along the ray has no image-plane part to scale against
    s = motion.motion_scores(learned, along, view)[0]
    assert np.isnan(s["image_ratio"]) and np.isnan(s["image_angle_deg"]) and s["ratio"] == pytest.approx(1.5)


def test_basis_weights_read_the_bases_weights_that_the_field_applies():
    """Every moving basis a unit translation along x: the field moves X by 1 - w_0(X) along x (`deform_apply`), an
    independent read of the static basis's weight; the hash kind has no bases."""
    import jax
    import jax.numpy as jnp

    from fgjax.gaussians import Gaussians
    from fgjax.models.deform import DeformSpec, deform_apply, deform_init

    spec = DeformSpec(kind="bases", depth=2, width=16, hash_levels=2, hash_log2_table=8, bases=4, knots=3)
    d = deform_init(jax.random.PRNGKey(3), spec)
    d["head"]["w"] = d["head"]["w"] * 40.0  # weights that differ from point to point
    d["motion"] = d["motion"].at[:, :, 3].set(1.0)
    x = jax.random.uniform(jax.random.PRNGKey(4), (50, 3), minval=-0.9, maxval=0.9)
    n = x.shape[0]
    g = Gaussians(x, jnp.zeros((n, 3)), jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (n, 1)), jnp.zeros(n),
                  jnp.zeros((n, 1, 3)))
    alive = np.arange(n) < 40  # the last ten are dead slots
    parts = [np.arange(0, 10), np.arange(25, 40), np.zeros(0, int)]
    r = motion.basis_weights({"gaussians": g, "deform": d}, alive, spec, parts)
    moved = np.asarray(deform_apply(spec, d, x, 0.5)[0])[:, 0]  # 1 - w_0
    assert moved[:40].std() > 0.05  # the check below is not of a constant
    assert r["static_all"] == pytest.approx(1.0 - moved[:40].mean(), abs=1e-5)
    for idx, w in zip(parts[:2], r["parts"][:2]):
        assert len(w) == 4 and sum(w) == pytest.approx(1.0, abs=1e-5)
        assert w[0] == pytest.approx(1.0 - moved[idx].mean(), abs=1e-5)
    assert np.all(np.isnan(r["parts"][2]))
    assert motion.basis_weights({"gaussians": g, "deform": d}, alive, DeformSpec(kind="hash"), parts) is None
    assert motion.basis_weights({"gaussians": g}, alive, None, parts) is None


@pytest.mark.parametrize("kind", ["hash", "bases"])
def test_bench_motion_trains_traces_and_diagnoses_the_flow(tiny, tmp_path, capsys, kind):
    """--train records the learned motion over training (with the bases, where their weights sit); --flow measures
    the dynamic flow on each part's pixels."""
    _, data = tiny
    run = tmp_path / "run"
    quick = Path(__file__).resolve().parents[2] / "experiments" / "quick.toml"
    sets = ["train.steps=8", "train.warmup_steps=2", "densify.enabled=false", "train.video_frames=0",
            "train.log_every=4", "train.checkpoint_every=0", "static.force=dynamic", "flow.enabled=true",
            "flow.start=0", "flow.method=dis", f"deform.kind={kind}"]
    args = ["--run", str(run), "--data", str(data), "--train", str(quick), "--flow", "--json", str(tmp_path / "r.json")]
    assert motion.main(args + [a for s in sets for a in ("--set", s)]) == 0
    out = capsys.readouterr().out
    assert "over training" in out and "EPE GS-target" in out
    r = json.loads((tmp_path / "r.json").read_text())
    assert [t["step"] for t in r["trace"]] == [4, 8]
    assert all(len(t["ratios"]) == len(r["objects"]) for t in r["trace"])
    if kind == "bases":
        assert "bases' weights" in out and 0.0 < r["static_weight"] < 1.0
        for t in r["trace"]:
            assert 0.0 < t["static_weight"] < 1.0 and len(t["part_static_weights"]) == len(r["objects"])
        for o in r["objects"]:
            assert len(o["basis_weights"]) == 6 and (o["gaussians"] == 0
                                                     or sum(o["basis_weights"]) == pytest.approx(1.0))
    else:
        assert r["static_weight"] is None and all(t["static_weight"] is None for t in r["trace"])
    for o in r["objects"]:
        f = o["flow"]
        if f["frames"]:
            assert f["grad_flow"] > 0 and np.isfinite(f["epe_gs_target"]) and np.isfinite(f["grad_photo"])
    assert any(o["flow"]["frames"] for o in r["objects"])  # the tiny scene's parts move


def test_true_gaussians_render_the_first_frame(tiny):
    """The oracle's canonical Gaussians, converted to model parameters in the run's normalisation, render the
    first training frame as `fgjax synth` rendered it (every part is in its canonical state at t0)."""
    import jax.numpy as jnp

    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization
    from fgjax.method.stage1 import load_run
    from fgjax.models.model import render_params

    run_dir, data = tiny
    cfg, _, _, meta = load_run(run_dir)
    norm = Normalization.from_dict(meta["normalization"])
    sc = load_scene(data, "train", normalize=norm)
    g = motion.true_gaussians(data / "gt", norm, cfg.model.sh_degree)
    i = int(np.argmin(sc.times))
    img = render_params({"gaussians": g}, jnp.ones(g.means.shape[0], bool), jnp.asarray(sc.viewmats[i], jnp.float32),
                        jnp.asarray(sc.Ks[i], jnp.float32), 0.0, spec=None, sh_degree=cfg.model.sh_degree,
                        width=sc.width, height=sc.height, background=jnp.asarray(cfg.model.background, jnp.float32),
                        capacity=None)[0]
    mse = float(np.mean((np.asarray(img) - sc.images[i]) ** 2))
    assert -10 * np.log10(mse) > 35.0  # 8-bit rounding of the written image, nothing more


def test_oracle_fits_a_fresh_field_on_the_true_canonical(tiny, tmp_path, capsys):
    run_dir, data = tiny
    r = motion.oracle_fit(run_dir, data, 4, flow="true", photo=1.0, log_every=2, log=lambda *a: None)
    assert [row["step"] for row in r["trace"]] == [2, 4] and r["dropped_steps"] == 0
    assert all(np.isfinite(row["loss"]) for row in r["trace"])
    meta = json.loads((data / "gt" / "meta.json").read_text())
    assert [o["name"] for o in r["objects"]] == [o["name"] for o in meta["objects"]]
    assert all(o["gaussians"] > 0 and o["true"] > 0 for o in r["objects"])  # every part's own true Gaussians
    out = tmp_path / "o.json"
    assert motion.main(["--run", str(run_dir), "--data", str(data), "--oracle", "2", "--oracle-flow", "none",
                        "--oracle-photo", "1", "--json", str(out)]) == 0
    assert "parts learned from the true canonical Gaussians" in capsys.readouterr().out
    assert json.loads(out.read_text())["trace"]
    assert motion.main(["--run", str(run_dir), "--data", str(data), "--oracle", "2", "--oracle-loss", "track"]) == 0
    assert motion.main(["--run", str(run_dir), "--data", str(data), "--oracle", "2", "--oracle-loss", "track",
                        "--oracle-flow", "true"]) == 0
    capsys.readouterr()
    for bad in (["--oracle", "-3"], ["--oracle", "2", "--oracle-flow", "none"],
                ["--oracle", "2", "--oracle-photo", "-1"]):
        assert motion.main(["--run", str(run_dir), "--data", str(data)] + bad) == 2
        assert "fgjax bench motion: --oracle" in capsys.readouterr().err
