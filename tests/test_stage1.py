"""Stage 1 on tiny scenes: training, resume, checkpoints, densification, static scenes, CLI, 2 devices."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fgjax import config as C
from fgjax.data.scene import Scene
from fgjax.gaussians import init_random
from fgjax.pipeline import stage1
from fgjax.train import checkpoint as ckpt
from fgjax.train.densify import densify_apply, densify_init

QUICK = str(stage1.Path(__file__).resolve().parents[1] / "experiments" / "quick.toml")


def _look_at(c, target=(0.0, 0.0, 0.0)):
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])  # world -> camera rows
    vm = np.eye(4)
    vm[:3, :3] = r
    vm[:3, 3] = -r @ c
    return vm


def _tiny_scene(dynamic: bool, frames: int = 6, w: int = 32, h: int = 24) -> Scene:
    """Random Gaussians (one blob moves when `dynamic`) seen by cameras on an arc, rendered exactly."""
    from fgjax.render.api import rasterization

    rng = np.random.default_rng(0)
    n = 200
    means = rng.uniform(-0.5, 0.5, (n, 3))
    cols = rng.uniform(0, 1, (n, 3))
    scales = np.full((n, 3), 0.08)
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    opac = np.full(n, 0.8)
    K = np.array([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]])
    imgs, vms = [], []
    times = np.linspace(0, 1, frames)
    for i, t in enumerate(times):
        a = 0.4 * (i / max(frames - 1, 1) - 0.5)
        vm = _look_at(np.array([2.0 * np.sin(a), -2.0 * np.cos(a), 0.3]))
        m = means.copy()
        if dynamic:
            m[:30] += np.array([0.4 * t, 0.0, 0.0])
        img, _, _ = rasterization(m, quats, scales, opac, cols, vm, K, w, h, background=np.ones(3))
        imgs.append(np.clip(np.asarray(img), 0, 1))
        vms.append(vm)
    return Scene(np.stack(imgs), np.stack([K] * frames), np.stack(vms), times, w, h, [f"f{i}" for i in range(frames)])


def _cfg(*extra):
    return C.load_config(QUICK, ["train.video_frames=0", *extra])


def test_training_reduces_loss_and_resume_reproduces_trajectory(tmp_path):
    scene = _tiny_scene(True)
    cfg = _cfg()
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


def test_densify_clone_split_prune_and_capacity_flag(key):
    g, alive = init_random(key, 6, [-1, -1, -1], [1, 1, 1], capacity=8, sh_degree=0)
    g = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), g)
    ls = g.log_scales.at[0].set(jnp.log(0.5)).at[1].set(jnp.log(0.001))  # 0 large (split), 1 small (clone)
    logit = g.opacity_logits.at[5].set(-10.0)  # 5 transparent -> pruned
    g = type(g)(g.means, ls, g.quats, logit, g.sh)
    st = densify_init(alive)
    st = type(st)(st.alive, jnp.zeros(8).at[0].set(1.0).at[1].set(0.5), jnp.ones(8, jnp.int32), st.full)
    opt = {"gaussians": g}  # any pytree of rows works for the optimiser-state reset
    g2, _, st2, n_alive = densify_apply(g, opt, st, key, grad_threshold=0.1, clone_max_scale=0.01,
                                        prune_opacity=0.005, prune_max_scale=10.0)
    assert int(n_alive) == 6 + 2 - 1 and not bool(st2.full)
    new = np.flatnonzero(np.asarray(st2.alive) & ~np.asarray(alive))
    assert len(new) == 2
    assert float(jnp.exp(g2.log_scales[0, 0])) == pytest.approx(0.5 / 1.6, rel=1e-5)
    clone = [i for i in new if np.allclose(g2.means[i], g.means[1])]
    assert len(clone) == 1
    assert float(st2.grad_sum.sum()) == 0.0
    # no free slots left: candidates exceed them -> flag
    st3 = type(st2)(st2.alive, jnp.ones(8), jnp.ones(8, jnp.int32), st2.full)
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
    C.load_config(str(stage1.Path(QUICK).parent / "default.toml"))


def test_cli_train_and_render(tmp_path):
    from fgjax.data.synth import SynthConfig, generate
    from fgjax.pipeline import render

    data = tmp_path / "data"
    generate(SynthConfig(objects=("drawer",), width=32, height=24, frames=6, test_views=2, test_states=1), data)
    run = tmp_path / "run"
    rc = stage1.main(["--data", str(data), "--out", str(run), "--config", QUICK])
    assert rc == 0
    m = json.loads((run / "metrics.json").read_text())
    assert m["num_views"] == 2 and np.isfinite(m["psnr"]) and 0 < m["ssim"] <= 1
    assert len(list((run / "test").glob("*.png"))) == 2
    assert any(run.glob("sweep.*"))
    assert C.load_config(run / "config.toml") == C.load_config(QUICK)
    out = tmp_path / "renders"
    assert render.main(["--run", str(run), "--cameras", str(data / "transforms_test.json"), "--out", str(out)]) == 0
    assert len(list(out.glob("*.png"))) == 3
    assert stage1.main(["--data", str(data), "--out", str(run), "--set", "train.nope=1"]) == 2


_TWO_DEVICES = textwrap.dedent(
    """
    import json, sys
    import jax
    sys.path.insert(0, {tests!r})
    from test_stage1 import _tiny_scene, _cfg
    from fgjax.pipeline import stage1
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
    env["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    env["JAX_PLATFORMS"] = "cpu"
    code = _TWO_DEVICES.format(tests=str(stage1.Path(__file__).parent))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(res["two"]) == 4
    # float32; the cross-device mean may sum in a different order
    np.testing.assert_allclose(res["two"], res["one"], rtol=1e-5, atol=1e-6)
