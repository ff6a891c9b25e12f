"""Stage 1 on tiny scenes: training, resume, checkpoints, densification, static scenes, CLI, 2 devices."""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import look_at

from fgjax import config as C
from fgjax.data.scene import Scene
from fgjax.gaussians import init_random
from fgjax.method import stage1
from fgjax.models.model import refined_viewmats
from fgjax.train import checkpoint as ckpt
from fgjax.train.densify import densify_apply, densify_init, follow_parents
from fgjax.train.optim import make_optimizer

QUICK = str(pathlib.Path(__file__).resolve().parents[2] / "experiments" / "quick.toml")


def _tiny_scene(dynamic: bool, frames: int = 6, w: int = 32, h: int = 24, depth: bool = False) -> Scene:
    """Random Gaussians (one blob moves when `dynamic`) seen by cameras on an arc, rendered exactly; with `depth`,
    the rendered expected depth as the scene's measured depth (0 where the render covers less than half)."""
    from fgjax.render.api import rasterization

    rng = np.random.default_rng(0)
    n = 200
    means = rng.uniform(-0.5, 0.5, (n, 3))
    cols = rng.uniform(0, 1, (n, 3))
    scales = np.full((n, 3), 0.08)
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    opac = np.full(n, 0.8)
    K = np.array([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]])
    imgs, vms, deps = [], [], []
    times = np.linspace(0, 1, frames)
    for i, t in enumerate(times):
        a = 0.4 * (i / max(frames - 1, 1) - 0.5)
        vm = look_at(np.array([2.0 * np.sin(a), -2.0 * np.cos(a), 0.3]))
        m = means.copy()
        if dynamic:
            m[:30] += np.array([0.4 * t, 0.0, 0.0])
        img, alpha, info = rasterization(m, quats, scales, opac, cols, vm, K, w, h, background=np.ones(3),
                                         render_depth=True)
        imgs.append(np.clip(np.asarray(img), 0, 1))
        vms.append(vm)
        deps.append(np.where(np.asarray(alpha) > 0.5, np.asarray(info["depth"]), 0.0))
    return Scene(np.stack(imgs), np.stack([K] * frames), np.stack(vms), times, w, h, [f"f{i}" for i in range(frames)],
                 depths=np.stack(deps) if depth else None)


def _cfg(*extra):
    return C.load_config(QUICK, ["train.video_frames=0", *extra])


@pytest.mark.parametrize("sampling", [0.0, 0.7])
def test_training_reduces_loss_and_resume_reproduces_trajectory(tmp_path, sampling):
    scene = _tiny_scene(True)
    cfg = _cfg(f"train.error_sampling={sampling}")
    full = stage1.train_stage1(cfg, scene, tmp_path / "a", progress=False, log=lambda *_: None)
    losses = np.asarray(full["losses"])
    assert len(losses) == cfg.train.steps and np.all(np.isfinite(losses))
    assert losses[-5:].mean() < losses[:5].mean()
    part = stage1.train_stage1(cfg, scene, tmp_path / "b", stop_at=15, progress=False, log=lambda *_: None)
    assert len(part["losses"]) == 15
    rest = stage1.train_stage1(cfg, scene, tmp_path / "b", resume=True, progress=False, log=lambda *_: None)
    resumed = np.concatenate([part["losses"], rest["losses"]])
    np.testing.assert_allclose(resumed, losses, rtol=0, atol=1e-6)
    a = full["state"].params["gaussians"].means
    b = rest["state"].params["gaussians"].means
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6)
    if sampling:  # the per-frame errors that steer the sampling were checkpointed and resumed
        fe = full["state"].frame_err
        assert fe.shape == (scene.num_frames,) and np.all(np.isfinite(fe)) and np.all(fe > 0)
        np.testing.assert_allclose(rest["state"].frame_err, fe, atol=1e-6)
    else:
        assert full["state"].frame_err is None


def test_checkpoint_errors(tmp_path):
    scene = _tiny_scene(False, frames=3)
    cfg = _cfg()
    stage1.train_stage1(cfg, scene, tmp_path / "r", stop_at=2, progress=False, log=lambda *_: None)
    path = tmp_path / "r" / ckpt.CHECKPOINT_NAME
    state, spec, _ = stage1.initial_state(cfg, scene)
    loaded = ckpt.load_checkpoint(path, state)
    assert loaded.step == 2
    assert loaded.step == ckpt.read_meta(path)["step"]
    # incompatible: a different capacity
    other, _, _ = stage1.initial_state(C.apply_overrides(cfg, ["model.capacity=700"]), scene)
    with pytest.raises(ckpt.CheckpointError, match="shape"):
        ckpt.load_checkpoint(path, other)
    # corrupt: truncated file
    bad = tmp_path / "bad.npz"
    bad.write_bytes(path.read_bytes()[:100])
    with pytest.raises(ckpt.CheckpointError, match="corrupt"):
        ckpt.load_checkpoint(bad, state)
    with pytest.raises(ckpt.CheckpointError, match="does not exist"):
        ckpt.load_checkpoint(tmp_path / "nope.npz", state)
    # a run saved without the static points (deform.gauge off) loads into a state that has them: the gauge stays
    # off; and the other way round, the stored points come back
    bases = C.apply_overrides(cfg, ["deform.kind=bases", "deform.init=flow", "deform.gauge=1", "deform.hold=0"])
    b_state, _, _ = stage1.initial_state(bases, scene)
    no_gauge = dataclasses.replace(b_state, static_points=None)
    ckpt.save_checkpoint(tmp_path / "no_gauge.npz", no_gauge)
    assert ckpt.load_checkpoint(tmp_path / "no_gauge.npz", b_state).static_points is None
    pts = np.arange(4096 * 4, dtype=np.float32).reshape(4096, 4)
    ckpt.save_checkpoint(tmp_path / "gauge.npz", dataclasses.replace(b_state, static_points=pts))
    np.testing.assert_array_equal(ckpt.load_checkpoint(tmp_path / "gauge.npz", no_gauge).static_points, pts)
    for name, want in (("no_gauge.npz", None), ("gauge.npz", pts)):  # files from before the flag: by their count
        with np.load(tmp_path / name) as z:
            arrays = dict(z)
        meta = json.loads(bytes(arrays["__meta__"]).decode())
        del meta["static_points"]
        arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
        np.savez(tmp_path / "old.npz", **arrays)
        for template in (b_state, no_gauge):
            got = ckpt.load_checkpoint(tmp_path / "old.npz", template).static_points
            assert got is None if want is None else np.array_equal(got, want)


def test_densify_clone_split_prune_and_capacity_flag(key):
    g, alive = init_random(key, 6, [-1, -1, -1], [1, 1, 1], capacity=8, sh_degree=0)
    g = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), g)
    ls = g.log_scales.at[0].set(jnp.log(0.5)).at[1].set(jnp.log(0.001))  # 0 large (split), 1 small (clone)
    logit = g.opacity_logits.at[5].set(-10.0)  # 5 transparent -> pruned
    g = type(g)(g.means, ls, g.quats, logit, g.sh)
    st = densify_init(alive)
    st = type(st)(st.alive, jnp.zeros(8).at[0].set(1.0).at[1].set(0.5), jnp.ones(8, jnp.int32), st.full, st.parent)
    rows = jnp.arange(8.0)[:, None] * jnp.ones((1, 3))  # per-slot data beside the Gaussians (row i = i)
    opt = {"gaussians": g, "slots": {"logits": rows + 1.0}}  # any pytree of rows works for the moments' reset
    g2, opt2, st2, n_alive = densify_apply(g, opt, st, key, grad_threshold=0.1, clone_max_scale=0.01,
                                           prune_opacity=0.005, prune_max_scale=10.0)
    assert int(n_alive) == 6 + 2 - 1 and not bool(st2.full)
    new = np.flatnonzero(np.asarray(st2.alive) & ~np.asarray(alive))
    assert len(new) == 2
    assert float(jnp.exp(g2.log_scales[0, 0])) == pytest.approx(0.5 / 1.6, rel=1e-5)
    clone = [i for i in new if np.allclose(g2.means[i], g.means[1])]
    assert len(clone) == 1
    # the per-slot rows follow: the clone's slot takes slot 1's row, the split's new slot slot 0's, the rest stay;
    # the moments of the new slots and of the split source are zeroed under "slots" as under "gaussians"
    split_new = [i for i in new if i != clone[0]][0]
    want = np.arange(8.0)
    want[clone[0]], want[split_new] = 1.0, 0.0
    followed = follow_parents({"slots": {"logits": rows}, "motion": jnp.ones(2)}, st2)
    np.testing.assert_array_equal(followed["slots"]["logits"][:, 0], want)
    np.testing.assert_array_equal(follow_parents(followed, st2)["slots"]["logits"][:, 0], want)  # idempotent
    assert followed["motion"].shape == (2,)
    zeroed = np.flatnonzero(np.asarray(opt2["slots"]["logits"][:, 0]) == 0.0)
    assert sorted(zeroed.tolist()) == sorted([0, clone[0], split_new])
    assert float(st2.grad_sum.sum()) == 0.0
    # no free slots left: candidates exceed them -> flag
    st3 = type(st2)(st2.alive, jnp.ones(8), jnp.ones(8, jnp.int32), st2.full, st2.parent)
    _, _, st4, _ = densify_apply(g2, opt, st3, key, grad_threshold=0.1, clone_max_scale=0.01,
                                 prune_opacity=0.005, prune_max_scale=10.0)
    assert bool(st4.full)


def test_static_scene_skips_deformation():
    scene = _tiny_scene(False)
    cfg = _cfg("densify.enabled=false")
    res = stage1.train_stage1(cfg, scene, None, progress=False, log=lambda *_: None)
    assert res["static"] is True
    dyn = stage1.train_stage1(_cfg("densify.enabled=false", "static.force=dynamic"), _tiny_scene(True), None,
                              stop_at=12, progress=False, log=lambda *_: None)
    assert dyn["static"] is False


def test_config_overrides_and_errors(tmp_path):
    cfg = C.load_config(QUICK, ["train.steps=7", "model.background=0,0,0"])
    assert cfg.train.steps == 7 and cfg.model.background == (0.0, 0.0, 0.0)
    import tomllib

    assert C.from_dict(tomllib.loads(C.to_toml(cfg))) == cfg
    with pytest.raises(C.ConfigError, match="train.stepz"):
        C.apply_overrides(cfg, ["train.stepz=3"])
    with pytest.raises(C.ConfigError, match="train.steps"):
        C.apply_overrides(cfg, ["train.steps=many"])
    with pytest.raises(C.ConfigError, match="densify.enabled"):
        C.apply_overrides(cfg, ["densify.enabled=maybe"])
    C.load_config(str(pathlib.Path(QUICK).parent / "articulated.toml"))
    C.load_config(str(pathlib.Path(QUICK).parent / "paper.toml"))


def test_cli_train_and_render(tmp_path):
    from conftest import synth

    from fgjax.apps import render, train

    SynthConfig, generate = synth.SynthConfig, synth.generate

    data = tmp_path / "data"
    generate(SynthConfig(objects=("drawer",), width=32, height=24, frames=6, test_views=2, test_states=1), data)
    run = tmp_path / "run"
    rc = train.main(["--data", str(data), "--out", str(run), "--config", QUICK])
    assert rc == 0
    m = json.loads((run / "metrics.json").read_text())
    assert m["num_views"] == 2 and np.isfinite(m["psnr"]) and 0 < m["ssim"] <= 1
    assert len(list((run / "test").glob("*.png"))) == 2
    assert any(run.glob("sweep.*"))
    assert C.load_config(run / "config.toml") == C.load_config(QUICK)
    out = tmp_path / "renders"
    assert render.main(["--run", str(run), "--cameras", str(data / "transforms_test.json"), "--out", str(out)]) == 0
    assert len(list(out.glob("*.png"))) == 3
    assert train.main(["--data", str(data), "--out", str(run), "--set", "train.nope=1"]) == 2


_TWO_DEVICES = textwrap.dedent(
    """
    import json, sys
    import jax
    sys.path[:0] = [{tests!r}, {root!r}]
    from test_stage1 import _tiny_scene, _cfg
    from fgjax.method import stage1
    assert len(jax.devices()) == 2, jax.devices()
    cfg = _cfg("train.batch_size=2", "densify.enabled=false", "train.warmup_steps=0", "static.force=dynamic")
    scene = _tiny_scene(True)
    out = {{}}
    for name, devs in (("two", jax.devices()), ("one", jax.devices()[:1])):
        res = stage1.train_stage1(cfg, scene, None, stop_at=4, progress=False, log=lambda *_: None, devices=devs)
        out[name] = res["losses"]
    print(json.dumps(out))
    """
)


def test_data_parallel_two_devices_matches_one():
    """The step sharded over a 2-device CPU mesh (cameras split) gives the single-device losses."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    env["JAX_PLATFORMS"] = "cpu"
    here = pathlib.Path(__file__).resolve()
    code = _TWO_DEVICES.format(tests=str(here.parent), root=str(here.parents[1]))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(res["two"]) == 4
    # float32; the cross-device mean may sum in a different order
    np.testing.assert_allclose(res["two"], res["one"], rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# flow loss (beta L_uGS) and pose refinement
# ---------------------------------------------------------------------------------------------


def _flow_inputs(scene, cfg, frame=3):
    state, spec, _ = stage1.initial_state(cfg, scene)
    prev = stage1.previous_frames(scene.times)
    flows = np.full((scene.num_frames, scene.height, scene.width, 2), np.nan, np.float32)
    flows[1:] = np.array([1.5, -0.5], np.float32)  # a constant observed flow: the target is not zero
    f32 = lambda x: np.asarray(x, np.float32)
    fb = stage1._flow_batch(np.array([frame]), prev, flows, f32(scene.viewmats), f32(scene.times), f32(scene.Ks))
    fb = stage1.FlowBatch(*(jnp.asarray(x)[0] for x in fb))
    return state, spec, fb


@pytest.mark.parametrize("gaussian_flow,camera_depth", [("isotropic", "composited"), ("anisotropic", "expected")])
def test_flow_loss_is_finite_and_reaches_the_deformation(gaussian_flow, camera_depth):
    """The paper's L_uGS and the ablation's other end (GaussianFlow's anisotropic u~_GS, u_cam from the expected
    depth) inside the stage-1 step."""
    scene = _tiny_scene(True)
    cfg = _cfg("flow.enabled=true", "flow.weight=0.5")
    state, spec, fb = _flow_inputs(scene, cfg)
    ss = stage1.StepSpec(spec, 1, scene.width, scene.height, 16384, 8, 0.2, 0.0, 0.05, False, 0.5, 0.0,
                         gaussian_flow=gaussian_flow, camera_depth=camera_depth)
    params = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), state.params)
    vm = jnp.asarray(scene.viewmats[3], jnp.float32)
    K = jnp.asarray(scene.Ks[3], jnp.float32)
    t = jnp.float32(scene.times[3])

    def f(p):
        return stage1.flow_term(ss, p, state.densify.alive, vm, K, t, fb)[0]

    loss, g = jax.jit(jax.value_and_grad(f))(params)
    assert np.isfinite(float(loss)) and float(loss) > 0.1  # the constant target is not explained at init
    head = np.asarray(g["deform"]["head"]["w"])
    assert np.all(np.isfinite(head)) and np.abs(head).max() > 0  # the gradient reaches the field
    # no previous frame: weight 0, loss 0
    fb0 = fb._replace(weight=jnp.float32(0.0))
    assert float(stage1.flow_term(ss, params, state.densify.alive, vm, K, t, fb0)[0]) == 0.0
    # flow.norm = "charbonnier" reaches the loss: the residuals (about 1.6 px) squared, not summed
    ssc = dataclasses.replace(ss, flow_norm="charbonnier", flow_scale=10.0)
    lc, gc = jax.value_and_grad(lambda p: stage1.flow_term(ssc, p, state.densify.alive, vm, K, t, fb)[0])(params)
    assert np.isfinite(float(lc)) and 0 < float(lc) < float(loss)
    assert np.all(np.isfinite(np.asarray(gc["deform"]["head"]["w"]))) and np.abs(gc["deform"]["head"]["w"]).max() > 0


def test_training_step_with_flow_loss_runs(monkeypatch):
    scene = _tiny_scene(True)
    flows = np.full((scene.num_frames, scene.height, scene.width, 2), np.nan, np.float32)
    flows[1:] = 0.5
    cfg = _cfg("flow.enabled=true", "flow.weight=0.1", "flow.start=0", "train.warmup_steps=0",
               "static.force=dynamic", "densify.enabled=false")
    res = stage1.train_stage1(cfg, scene, None, stop_at=3, progress=False, log=lambda *_: None, flows=flows)
    assert len(res["losses"]) == 3 and np.all(np.isfinite(res["losses"]))
    charb = stage1.train_stage1(dataclasses.replace(cfg, flow=dataclasses.replace(cfg.flow, norm="charbonnier")), scene,
                                None, stop_at=3, progress=False, log=lambda *_: None, flows=flows)
    assert np.all(np.isfinite(charb["losses"])) and charb["losses"] != res["losses"]  # the option reaches the step
    g = res["state"].params["gaussians"]
    assert np.all(np.isfinite(np.asarray(g.means)))
    assert np.abs(np.asarray(res["state"].params["deform"]["head"]["w"])).max() > 0  # the field was updated
    with pytest.raises(ValueError, match="flows must have shape"):
        stage1.train_stage1(cfg, scene, None, stop_at=1, progress=False, log=lambda *_: None, flows=flows[1:])
    # flow.photo_motion_start: the photometric share of the motion is 0 before that step, flow.photo_motion from it
    shares, make = [], stage1.make_step

    def recording(ss, *a, **k):
        fn = make(ss, *a, **k)
        return lambda *b, **kw: shares.append(ss.photo_motion) or fn(*b, **kw)

    monkeypatch.setattr(stage1, "make_step", recording)
    late = dataclasses.replace(cfg, flow=dataclasses.replace(cfg.flow, photo_motion=0.5, photo_motion_start=2))
    stage1.train_stage1(late, scene, None, stop_at=4, progress=False, log=lambda *_: None, flows=flows)
    assert shares == [0.0, 0.0, 0.5, 0.5], shares


def test_training_with_the_track_loss_runs_and_tracks_from_the_first_frame(tmp_path):
    """flow.loss = "track": the first frame's tracks from OpenCV flow (both directions, cached), the reference of
    every other frame, and a few steps that update the field (also in the Charbonnier form, with the motion bases)."""
    scene = _tiny_scene(True, frames=4, w=48, h=32)
    ref, tracks = stage1.training_tracks(scene, "dis", tmp_path / "c", log=lambda *_: None)
    first = int(np.argmin(scene.times))
    assert ref[first] == -1 and np.all(np.delete(ref, first) == first)
    assert tracks.shape == (4, 32, 48, 2) and np.all(tracks[first] == 0)
    assert np.isfinite(tracks).mean() > 0.3  # most of the first frame is tracked
    cfg = _cfg("flow.enabled=true", "flow.loss=track", "flow.weight=0.1", "flow.start=0", "flow.method=dis",
               "train.warmup_steps=0", "static.force=dynamic", "densify.enabled=false")
    res = stage1.train_stage1(cfg, scene, tmp_path / "run", stop_at=3, progress=False, log=lambda *_: None)
    assert len(res["losses"]) == 3 and np.all(np.isfinite(res["losses"]))
    assert np.abs(np.asarray(res["state"].params["deform"]["head"]["w"])).max() > 0
    # the Charbonnier form with the motion bases: the bases' motions leave the identity
    bases = C.apply_overrides(cfg, ["flow.norm=charbonnier", "deform.kind=bases", "deform.bases=3", "deform.knots=4"])
    res = stage1.train_stage1(bases, scene, tmp_path / "run_bases", stop_at=3, progress=False, log=lambda *_: None)
    assert np.all(np.isfinite(res["losses"]))
    motion = np.asarray(res["state"].params["deform"]["motion"])
    assert motion.shape == (2, 4, 6) and np.all(np.isfinite(motion)) and np.abs(motion).max() > 0
    with pytest.raises(ValueError, match="makes its own tracks"):
        stage1.train_stage1(cfg, scene, None, stop_at=1, progress=False, log=lambda *_: None,
                            flows=np.zeros((4, 32, 48, 2), np.float32))


def test_training_flows_from_opencv_are_cached(tmp_path):
    scene = _tiny_scene(True, frames=3, w=48, h=32)
    f = stage1.estimate_training_flows(scene, "dis", tmp_path / "c", log=lambda *_: None)
    assert f.shape == (3, 32, 48, 2) and np.all(np.isnan(f[0])) and np.all(np.isfinite(f[1:]))
    assert any((tmp_path / "c").rglob("*"))


def test_pose_refinement_off_by_default_and_moves_noisy_poses_towards_truth():
    from fgjax.geometry import se3_exp
    from fgjax.train.optim import OptimSpec

    assert C.Config().pose.enabled is False
    scene = _tiny_scene(False, frames=4)
    state, _, _ = stage1.initial_state(_cfg(), scene)
    assert "pose" not in state.params
    # the true Gaussians of the scene, noisy poses; only the pose deltas learn (other rates ~0)
    rng = np.random.default_rng(0)  # the draws of _tiny_scene
    n = 200
    means = rng.uniform(-0.5, 0.5, (n, 3))
    cols = rng.uniform(0, 1, (n, 3))
    rng = np.random.default_rng(1)
    from fgjax.gaussians import init_from_points

    g, alive = init_from_points(means, cols, capacity=n, sh_degree=1, init_opacity=0.8)
    g = type(g)(g.means, jnp.full((n, 3), np.log(0.08), jnp.float32), g.quats, g.opacity_logits, g.sh)
    noise = np.concatenate([rng.normal(0, 0.02, (4, 3)), rng.normal(0, 0.03, (4, 3))], -1).astype(np.float32)
    true_vm = np.asarray(scene.viewmats, np.float32)
    noisy_vm = np.asarray(se3_exp(jnp.asarray(noise)), np.float32) @ true_vm
    tiny = 1e-12
    ospec = OptimSpec(steps=60, lr_means=tiny, lr_means_final=tiny, lr_deform=tiny, lr_deform_final=tiny,
                      lr_opacity=tiny, lr_scales=tiny, lr_quats=tiny, lr_sh=tiny, lr_pose=3e-3, lr_pose_final=1e-3)
    ss = stage1.StepSpec(None, 1, scene.width, scene.height, 16384, 8, 0.0, 0.0, 0.05, True)
    step = stage1.make_step(ss, ospec, 4, (1.0, 1.0, 1.0))
    params = {"gaussians": g, "deform": state.params["deform"], "pose": jnp.zeros((4, 6), jnp.float32)}
    params = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), params)

    opt_state = make_optimizer(ospec, 4).init(params)
    ds = densify_init(alive)
    sh_mask = jnp.ones(4, jnp.float32)
    imgs = np.asarray(scene.images, np.float32)
    Ks = np.asarray(scene.Ks, np.float32)
    times = np.asarray(scene.times, np.float32)

    def err(p):
        vm = np.asarray(se3_exp(p["pose"])) @ noisy_vm
        return float(np.abs(vm[:, :3, :] - true_vm[:, :3, :]).mean())

    e0 = err(params)
    losses = []
    for s in range(60):
        i = np.array([s % 4])
        params, opt_state, ds, loss, _, bad = step(params, opt_state, ds, sh_mask, imgs[i], noisy_vm[i], Ks[i],
                                                   times[i], i.astype(np.int32))
        assert not bool(bad)
        losses.append(float(loss))
    assert np.all(np.isfinite(np.asarray(params["pose"])))
    assert np.mean(losses[-4:]) < 0.7 * np.mean(losses[:4])
    assert err(params) < 0.6 * e0


def test_cameras_looped_or_vmapped_give_the_same_step():
    """The one-device step loops over the batch's cameras (vmap would turn the compositor's skips into
    selects); the mesh path vmaps them. Both must give the same loss, update and densification statistics.
    Batch 2 (`lax.map`); batch 1 calls the same per-camera loss directly (`fgjax bench step` compares it;
    one case to keep `make test` under 15 minutes). The measured-depth term rides along, per camera, in both."""
    batch = 2
    from fgjax.train.optim import OptimSpec

    scene = _tiny_scene(True, depth=True)
    state, spec, _ = stage1.initial_state(_cfg(), scene)
    ospec = OptimSpec(steps=10)
    i = np.arange(1, 1 + batch)
    f32 = lambda x: np.asarray(x, np.float32)
    args = (jnp.ones(4, jnp.float32), f32(scene.images[i]), f32(scene.viewmats[i]), f32(scene.Ks[i]),
            f32(scene.times[i]), i.astype(np.int32))
    outs = []
    for vm, dw in ((False, 0.5), (True, 0.5), (False, 0.0)):
        ss = stage1.StepSpec(spec, 1, scene.width, scene.height, 16384, 8, 0.2, 0.0, 0.05, False, vmap_cameras=vm,
                             depth_weight=dw)
        step = stage1.make_step(ss, ospec, 4, (0.0, 0.0, 0.0))
        copy = lambda x: jax.tree_util.tree_map(lambda a: jnp.array(a, copy=True), x)
        opt_state = make_optimizer(ospec, 4).init(state.params)
        outs.append(step(copy(state.params), opt_state, copy(state.densify), *args, depths=f32(scene.depths[i])))
    (p0, _, d0, l0, m0, b0), (p1, _, d1, l1, m1, b1), (_, _, _, l2, m2, _) = outs
    assert float(l0) > float(l2) + 1e-3  # the depth term entered the loss ...
    np.testing.assert_allclose(np.asarray(m0), np.asarray(m2), rtol=1e-6)  # ... and the images are the same
    assert not bool(b0) and not bool(b1) and np.asarray(m0).shape == (batch,)
    np.testing.assert_allclose(float(l0), float(l1), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(m0), np.asarray(m1), rtol=1e-6)
    for a, b in zip(jax.tree_util.tree_leaves((p0, d0)), jax.tree_util.tree_leaves((p1, d1))):
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), rtol=1e-5, atol=1e-7)
    assert float(jnp.abs(p0["gaussians"].means - state.params["gaussians"].means).max()) > 0  # it did update


def test_coarse_to_fine_and_no_recompilation_as_the_count_changes(monkeypatch):
    """The first `coarse_to_fine` steps run a half-resolution step; with a fixed tile capacity each step
    function compiles exactly once although densification changes the number of live Gaussians."""
    made = []
    orig = stage1.make_step

    def recording(ss, *a):
        fn = orig(ss, *a)
        made.append((ss, fn))
        return fn

    monkeypatch.setattr(stage1, "make_step", recording)
    scene = _tiny_scene(True)
    logs = []
    cfg = _cfg("train.steps=24", "train.coarse_to_fine=6", "train.warmup_steps=4", "densify.start=2",
               "densify.stop=22", "densify.every=2", "densify.grad_threshold=0", "static.force=dynamic",
               "train.tile_capacity=32768", "train.log_every=4")
    res = stage1.train_stage1(cfg, scene, None, progress=False, log=logs.append)
    assert np.all(np.isfinite(res["losses"]))
    sizes = {(ss.width, ss.height) for ss, _ in made}
    assert sizes == {(16, 12), (32, 24)}, sizes
    n0 = cfg.model.init_points
    assert int(jnp.sum(res["state"].densify.alive)) != n0  # densification changed the count...
    assert res["capacity"] == 32768
    for ss, fn in made:  # ...and no step function was traced twice
        assert fn._cache_size() == 1, (ss.width, ss.spec is None)
    # tiny images are not halved: one clear line, then full-resolution steps only
    made.clear()
    small = _tiny_scene(True, w=20, h=14)
    logs = []
    stage1.train_stage1(_cfg("train.steps=4", "train.coarse_to_fine=2", "densify.enabled=false"), small, None,
                        progress=False, log=logs.append)
    assert any("coarse-to-fine skipped" in m for m in logs)
    assert {(ss.width, ss.height) for ss, _ in made} == {(20, 14)}


def test_isometry_regulariser_enters_the_deformation_steps():
    """train.rigid_weight > 0 adds the isometry loss once the deformation is on (not in the warm-up)."""
    scene = _tiny_scene(True)
    common = ["train.steps=10", "train.warmup_steps=4", "densify.enabled=false", "static.force=dynamic"]
    a = stage1.train_stage1(_cfg(*common), scene, None, progress=False, log=lambda *_: None)
    b = stage1.train_stage1(_cfg(*common, "train.rigid_weight=10", "train.rigid_scale_weight=1"), scene, None,
                            progress=False, log=lambda *_: None)
    la, lb = np.asarray(a["losses"]), np.asarray(b["losses"])
    assert np.all(np.isfinite(lb))
    np.testing.assert_array_equal(la[:4], lb[:4])  # warm-up: identical
    assert np.any(la[5:] != lb[5:])


def test_time_curriculum_window_opens_from_the_earliest_frames():
    times = np.array([0.5, 0.0, 1.0, 0.25, 0.75, 0.1, 0.9, 0.6, 0.3, 0.4])  # not in time order
    order = np.argsort(times)
    # off: every frame
    np.testing.assert_array_equal(np.sort(stage1.time_window(0, times, 10, 0, 0.1)), np.arange(10))
    # warm-up: the earliest 20%; then linear opening over 100 steps; then all
    np.testing.assert_array_equal(stage1.time_window(5, times, 10, 100, 0.2), order[:2])
    np.testing.assert_array_equal(stage1.time_window(10, times, 10, 100, 0.2), order[:2])
    np.testing.assert_array_equal(stage1.time_window(60, times, 10, 100, 0.2), order[:6])
    np.testing.assert_array_equal(stage1.time_window(500, times, 10, 100, 0.2), order)
    assert len(stage1.time_window(0, times, 10, 100, 0.0)) == 1  # never empty
    for bad in (["train.time_window_start=0"], ["train.time_curriculum=-1"], ["train.rigid_cap=-0.5"]):
        with pytest.raises(C.ConfigError, match=bad[0].split("=")[0]):
            stage1.train_stage1(_cfg(*bad), _tiny_scene(False))
    with pytest.raises(C.ConfigError, match="error_sampling"):
        stage1.train_stage1(_cfg("train.error_sampling=1.5"), _tiny_scene(False))
    # the batch is drawn from the window only, and depends on (seed, step) alone
    win = stage1.time_window(30, times, 10, 100, 0.2)
    for s in range(20):
        idx = stage1.batch_indices(0, s, 10, 3, win)
        assert set(idx.tolist()) <= set(win.tolist())
        np.testing.assert_array_equal(idx, stage1.batch_indices(0, s, 10, 3, win))


def test_refined_viewmats_apply_the_learned_pose_deltas():
    vms = np.stack([look_at(np.array([2.0, -1.0, 0.5])), look_at(np.array([0.0, -2.0, 0.3]))])
    np.testing.assert_array_equal(refined_viewmats({"gaussians": None}, vms), vms)  # no refinement
    deltas = np.zeros((2, 6))
    deltas[1, 3:] = [0.01, -0.02, 0.03]  # twist [omega, v]: a pure translation of camera 1
    out = refined_viewmats({"pose": jnp.asarray(deltas)}, vms)
    np.testing.assert_allclose(out[0], vms[0], atol=1e-12)
    shift = np.eye(4)
    shift[:3, 3] = deltas[1, 3:]
    np.testing.assert_allclose(out[1], shift @ vms[1], atol=1e-12)
    with pytest.raises(ValueError, match="refined 2 camera poses but the scene has 1"):
        refined_viewmats({"pose": jnp.asarray(deltas)}, vms[:1])


def test_error_sampling_draws_the_worst_frames_more_often():
    err = np.array([0.01, 0.01, 0.01, 0.1, np.nan, 0.01])  # frame 3 is 10x worse; frame 4 not measured yet
    draws = np.concatenate([stage1.batch_indices(0, s, 6, 1, None, err, 1.0) for s in range(3000)])
    freq = np.bincount(draws, minlength=6) / len(draws)
    # p ~ e^2, unmeasured = the worst measured: frames 3 and 4 get 100 / 205 each, the others 1 / 205
    np.testing.assert_allclose(freq, np.array([1, 1, 1, 100, 100, 1]) / 205, atol=0.02)
    # mix 0.5: half the steps uniform
    draws = np.concatenate([stage1.batch_indices(0, s, 6, 1, None, err, 0.5) for s in range(3000)])
    freq = np.bincount(draws, minlength=6) / len(draws)
    np.testing.assert_allclose(freq, 0.5 / 6 + 0.5 * np.array([1, 1, 1, 100, 100, 1]) / 205, atol=0.02)
    # within a time window; nothing measured yet or mix 0: uniform, as without error sampling
    win = np.array([0, 1, 3])
    assert set(np.concatenate([stage1.batch_indices(0, s, 6, 1, win, err, 1.0) for s in range(50)])) <= {0, 1, 3}
    none = np.full(6, np.nan)
    draws = np.concatenate([stage1.batch_indices(0, s, 6, 1, None, none, 1.0) for s in range(3000)])
    np.testing.assert_allclose(np.bincount(draws, minlength=6) / len(draws), np.full(6, 1 / 6), atol=0.02)
    for s in range(5):
        np.testing.assert_array_equal(stage1.batch_indices(0, s, 6, 2, None, err, 0.0),
                                      stage1.batch_indices(0, s, 6, 2))


def test_field_only_phase_freezes_the_canonical_gaussians():
    scene = _tiny_scene(True)
    cfg = _cfg("train.steps=10", "train.warmup_steps=3", "train.field_only_steps=4", "static.detect=false",
               "train.checkpoint_every=0")
    at = lambda n: stage1.train_stage1(cfg, scene, None, stop_at=n, progress=False, log=lambda *_: None)["state"]
    a, b, c = at(3), at(7), at(9)
    leaves = lambda st, k: jax.tree_util.tree_leaves(st.params[k])
    for x, y in zip(leaves(a, "gaussians"), leaves(b, "gaussians"), strict=True):  # frozen in steps 3-6
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert any(not np.array_equal(np.asarray(x), np.asarray(y))  # ... while the field trains
               for x, y in zip(leaves(a, "deform"), leaves(b, "deform"), strict=True))
    assert any(not np.array_equal(np.asarray(x), np.asarray(y))  # and after the phase they train again
               for x, y in zip(leaves(b, "gaussians"), leaves(c, "gaussians"), strict=True))


def test_pose_bundle_needs_refinement_and_seeds_the_pose_deltas(monkeypatch):
    """``pose.bundle``: without ``pose.enabled`` a ConfigError; with it, the bundle adjustment's corrections
    (stubbed here; `tests/test_poses.py` tests the solver) become the initial pose deltas and the initial
    Gaussians are placed with the corrected cameras."""
    from fgjax.method import poses

    scene = _tiny_scene(False, frames=4)
    with pytest.raises(C.ConfigError, match="pose.bundle"):
        C.validate_stage1(_cfg("pose.bundle=true"))
    deltas = np.arange(24, dtype=np.float64).reshape(4, 6) * 1e-3
    seen = {}

    def fake(viewmats, Ks, flows, prev, **kw):
        seen.update(kw, flows=flows.shape)
        from fgjax.geometry import se3_exp

        vm = np.asarray(se3_exp(jnp.asarray(deltas, jnp.float32)), np.float64) @ viewmats
        return poses.BundleResult(vm, deltas, np.zeros(0), 1.0, 0.1, 1.0, 3, 0.0)

    monkeypatch.setattr(stage1, "bundle_adjust", fake)
    placed = {}
    real_init = stage1.init_gaussians

    def spy(cfg, sc, key, **kw):
        placed["viewmats"] = np.asarray(sc.viewmats)
        return real_init(cfg, sc, key, **kw)

    monkeypatch.setattr(stage1, "init_gaussians", spy)
    cfg = _cfg("pose.enabled=true", "pose.bundle=true", "pose.bundle_cauchy_px=0.5", "pose.bundle_fb_px=0.1",
               "model.init=random")
    state, _, _ = stage1.initial_state(cfg, scene)
    np.testing.assert_allclose(np.asarray(state.params["pose"]), deltas, atol=1e-7)
    assert seen["cauchy_px"] == 0.5 and seen["flows"] == (4, scene.height, scene.width, 2)
    np.testing.assert_allclose(placed["viewmats"], refined_viewmats(state.params, scene.viewmats), atol=1e-5)
    # the round-trip check's backward flows (frame i -> i - 1 on frame i's grid; none into the first frame)
    assert seen["fb_px"] == 0.1 and seen["backward"].shape == (4, scene.height, scene.width, 2)
    assert np.isnan(seen["backward"][0]).all() and np.isfinite(seen["backward"][1:]).all()
    stage1.initial_state(_cfg("pose.enabled=true", "pose.bundle=true", "model.init=random"), scene)  # off by default
    assert seen["backward"] is None
    with pytest.raises(C.ConfigError, match="pose.bundle_fb_px"):
        C.validate_stage1(_cfg("pose.enabled=true", "pose.bundle=true", "pose.bundle_fb_px=-1"))


@pytest.mark.optimized  # a trained run's static-scene score near its threshold
def test_a_scene_whose_flow_shows_moving_parts_is_not_called_static(tmp_path):
    """A 64x48, 8-frame synthetic scene whose three parts are small on screen: after the warm-up the photometric test
    alone scores it under the threshold (1.6% of the pixels), but the parts' optical flow departs from the camera
    flow, so stage 1 keeps the deformation field."""
    from conftest import synth

    from fgjax.data.loaders import load_scene

    synth.generate(synth.SynthConfig(width=64, height=48, frames=8), tmp_path / "scene", overwrite=True,
                   progress=None)
    scene = load_scene(tmp_path / "scene", "train")
    cfg = C.load_config(pathlib.Path(QUICK).parent / "demo_quick.toml", ["train.steps=101", "densify.enabled=false",
                                                                         "train.video_frames=0"])
    said = []
    res = stage1.train_stage1(cfg, scene, None, progress=False, log=said.append)
    assert res["static"] is False, said


def test_flow_init_says_when_a_still_camera_gives_no_point():
    """A still camera has no baseline: flow triangulation yields nothing, and stage 1 says it starts from random
    points instead of silently doing so (family seeds 0 and 1)."""
    scene = _tiny_scene(True)
    still = dataclasses.replace(scene, viewmats=np.stack([scene.viewmats[0]] * scene.num_frames))
    logs = []
    g, alive = stage1.init_gaussians(_cfg("model.init=flow", "model.init_flow_gap=1"), still, jax.random.key(0),
                                     log=logs.append)
    assert any("no point could be triangulated" in m for m in logs), logs
    assert int(np.sum(np.asarray(alive))) == _cfg().model.init_points
    logs.clear()
    stage1.init_gaussians(_cfg("model.init=flow", "model.init_flow_gap=1"), scene, jax.random.key(0), log=logs.append)
    assert not any("no point could be triangulated" in m for m in logs)


def _depth_error(res, cfg, scene) -> float:
    """Median relative error of the trained model's expected depth against the scene's depth, on its pixels."""
    from fgjax.models.model import render_params

    st, errs = res["state"], []
    for i in range(scene.num_frames):
        _, alpha, info, _ = render_params(st.params, st.densify.alive, jnp.asarray(scene.viewmats[i], jnp.float32),
                                          jnp.asarray(scene.Ks[i], jnp.float32), float(scene.times[i]),
                                          spec=None if res["static"] else res["spec"], sh_degree=cfg.model.sh_degree,
                                          width=scene.width, height=scene.height,
                                          background=jnp.asarray(cfg.model.background, jnp.float32), capacity=None,
                                          render_depth=True)
        d = scene.depths[i]
        ok = d > 0
        errs.append(np.abs(np.asarray(info["depth"])[ok] - d[ok]) / d[ok])
    return float(np.median(np.concatenate(errs)))


def test_depth_term_and_depth_init_pull_the_geometry_onto_the_measured_depth():
    """An RGB-D scene: with ``model.init = "depth"`` and ``train.depth_weight`` the rendered depth lands on the
    measured one; from random points with the photometric loss alone it does not (measured: median relative depth
    error 31% with neither, 4.9% with the depth term alone, 3.6% with both)."""
    scene = _tiny_scene(False, depth=True)
    said = []
    runs = {}
    for name, extra in {"none": ["model.init=random"], "term": ["model.init=random", "train.depth_weight=1"],
                        "both": ["model.init=depth", "train.depth_weight=1"]}.items():
        cfg = _cfg("densify.enabled=false", *extra)
        res = stage1.train_stage1(cfg, scene, None, progress=False, log=said.append)
        assert np.all(np.isfinite(res["losses"]))
        runs[name] = _depth_error(res, cfg, scene)
        # the test-view metrics report the same error where the views have depth (on the pixels the model covers)
        m = stage1.evaluate(res["state"], res["spec"], cfg, scene)["depth_error"]
        assert m["median_relative"] == pytest.approx(runs[name], rel=0.3, abs=0.005) and m["pixels"] > 0
    assert any(m.startswith("depth point cloud:") for m in said), said
    assert runs["both"] < 0.5 * runs["none"] and runs["term"] < 0.5 * runs["none"], runs
    assert "depth_error" not in stage1.evaluate(res["state"], res["spec"], cfg, dataclasses.replace(scene, depths=None))


def test_depth_options_on_a_scene_without_depth_say_so_and_train_without():
    scene = _tiny_scene(False)
    said = []
    cfg = _cfg("densify.enabled=false", "model.init=depth", "train.depth_weight=1", "train.steps=12")
    res = stage1.train_stage1(cfg, scene, None, progress=False, log=said.append)
    assert np.all(np.isfinite(res["losses"]))
    assert any("model.init = depth: the scene has no depth maps" in m for m in said), said
    assert any("train.depth_weight = 1.0: the scene has no depth maps" in m for m in said), said
    with pytest.raises(C.ConfigError, match="train.depth_weight"):
        _cfg("train.depth_weight=-1")
    with pytest.raises(C.ConfigError, match="model.init"):
        _cfg("model.init=lidar")
