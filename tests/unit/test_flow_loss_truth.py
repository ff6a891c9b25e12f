"""L_uGS verified before it is trusted (issue 53, item 1): on a synthetic door, with the true camera poses and the
ground-truth optical flow (`fgjax.synth.ground_truth_flow`: pixels back-projected with the rendered depth, moved by the
door's rigid motion, reprojected; an independent computation in numpy), the loss of the Gaussians moved by the true
motion is near zero, the loss of the Gaussians held still is large, and the gradient at rest points the door's
Gaussians along their true motion."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fgjax.flow import (
    camera_velocity,
    dynamic_gaussian_flow,
    gaussian_flow_loss,
    lemma1_residual,
    maps_camera_flow,
    pixel_centers,
)
from fgjax.render.api import rasterization
from fgjax.synth import SynthConfig, make_scene
from fgjax.synth.parts import rigid_inv
from fgjax.synth.render import render_sequence, sequence_flow
from fgjax.synth.scene import camera_c2w, deform, scene_states

W, H = 96, 72


@pytest.fixture(scope="module")
def door_pair():
    """The frame pair of a 24-frame door sequence in which the door moves most, with its ground truth."""
    scene = make_scene(SynthConfig(objects=("door",), width=W, height=H, frames=24, seed=3))
    times = np.arange(24) / 23.0
    states = scene_states(scene, times)
    i = int(np.argmax(np.abs(np.diff(states[:, 0]))))
    vm = rigid_inv(np.stack([camera_c2w(scene, float(times[j])) for j in (i, i + 1)]))
    st = states[i:i + 2]
    gt = sequence_flow(scene, st, vm, render_sequence(scene, vm, st))
    m0, q0 = deform(scene, st[0])
    m1, q1 = deform(scene, st[1])
    flow = np.where(gt["flow_valid"][0, ..., None], gt["flow"][0], np.nan).astype(np.float32)
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    return {"m0": f32(m0), "q0": f32(q0), "s": f32(scene.scales), "o": f32(scene.opacities),
            "m1": f32(m1), "q1": f32(q1),
            "vm0": f32(vm[0]), "vm1": f32(vm[1]), "K": f32(scene.K), "flow": jnp.asarray(flow),
            "object_flow": gt["object_flow"][0], "door": (gt["object_flow"][0] != 0).any(-1),
            "labels": scene.labels}


def _loss(p, m1, threshold=None, norm="l1"):
    loss, overflow = gaussian_flow_loss(p["m0"], p["q0"], p["s"], p["o"], m1, p["vm0"], p["vm1"], p["K"], p["flow"],
                                        W, H, threshold=threshold, norm=norm)
    assert not bool(overflow)
    return loss


def test_loss_near_zero_at_true_motion_and_large_at_rest(door_pair):
    p = door_pair
    mag = np.linalg.norm(p["object_flow"][p["door"]], axis=-1)
    assert p["door"].sum() > 50 and mag.mean() > 1.0, "the chosen pair must show the door moving"
    true, rest = float(_loss(p, p["m1"])), float(_loss(p, p["m0"]))
    assert np.isfinite(true) and np.isfinite(rest)
    # the mean runs over every valid pixel: the static ones (94 % here) keep the optical flow's and the composited
    # depth's small errors at both motions, so the whole loss falls by less than the door's share of it
    assert true < 0.5 * rest, (true, rest)
    # the same under the Charbonnier penalty (flow.norm = "charbonnier"), which squares the door's residuals
    true_c, rest_c = float(_loss(p, p["m1"], norm="charbonnier")), float(_loss(p, p["m0"], norm="charbonnier"))
    assert np.isfinite(true_c) and true_c < 0.2 * rest_c, (true_c, rest_c)
    # on the door's pixels: the rendered dynamic flow is the true object flow to within a fraction of its size
    maps = dynamic_gaussian_flow(p["m0"], p["q0"], p["s"], p["o"], p["m1"], p["vm0"], p["K"], W, H)
    epe = np.linalg.norm(np.asarray(maps.flow)[p["door"]] - p["object_flow"][p["door"]], axis=-1)
    assert np.median(epe) < 0.15 * np.median(mag), (np.median(epe), np.median(mag))


def test_gradient_at_rest_points_along_the_true_motion(door_pair):
    """With the targets' sub-threshold noise set to zero (flow.threshold, 0.5 px): L1's gradient is sign(r), as
    strong for a 0.05 px error on a static pixel as for a 2 px one on the door, so without the threshold the
    static pixels' flow noise would outweigh the door in the gradient."""
    p = door_pair
    g = np.asarray(jax.grad(lambda m1: _loss(p, m1, threshold=0.5))(p["m0"]))  # [N, 3]
    door = p["labels"] == 1
    true = np.asarray(p["m1"] - p["m0"])
    moved = door & (np.linalg.norm(true, axis=-1) > 1e-4) & (np.linalg.norm(g, axis=-1) > 0)
    assert moved.sum() > 20
    cos = np.sum(-g[moved] * true[moved], -1) / (np.linalg.norm(g[moved], axis=-1)
                                                 * np.linalg.norm(true[moved], axis=-1))
    assert np.median(cos) > 0.5, np.median(cos)
    assert np.all(np.isfinite(g))
    # static Gaussians get (almost) nothing: their pixels' target is zero and so is their flow at rest
    still = ~door
    assert np.abs(g[still]).sum() < 0.1 * np.abs(g[door]).sum()


@pytest.mark.parametrize("anisotropic,camera_depth", [(True, "composited"), (False, "expected"), (True, "expected")])
def test_ablation_variants_are_verified_too(door_pair, anisotropic, camera_depth):
    """The ablation's variants of L_uGS (GaussianFlow's anisotropic u~_GS; u_cam from the expected depth) pass the
    same check: near zero at the true motion, large at rest."""
    p = door_pair

    def loss(m1, q1):
        out, overflow = gaussian_flow_loss(p["m0"], p["q0"], p["s"], p["o"], m1, p["vm0"], p["vm1"], p["K"],
                                           p["flow"], W, H, anisotropic=anisotropic, quats1=q1, scales1=p["s"],
                                           camera_depth=camera_depth)
        assert not bool(overflow)
        return float(out)

    true, rest = loss(p["m1"], p["q1"]), loss(p["m0"], p["q0"])
    assert np.isfinite(true) and np.isfinite(rest)
    assert true < 0.5 * rest, (true, rest)


def test_expected_depth_leaves_lemma1_residual(door_pair):
    """u_cam from the expected depth minus u_cam from the composited depth is Lemma 1's residual Delta (to first
    order in the camera motion: ``lemma1_residual`` is the linear motion field, the camera flows exact
    reprojections), and the pass's expected depth is the rasterizer's own (an independent render)."""
    p = door_pair
    maps = dynamic_gaussian_flow(p["m0"], p["q0"], p["s"], p["o"], p["m0"], p["vm0"], p["K"], W, H)
    _, _, info = rasterization(p["m0"], p["q0"], p["s"], p["o"], jnp.zeros((p["m0"].shape[0], 1)), p["vm0"],
                               p["K"], W, H, render_depth=True)
    np.testing.assert_allclose(np.asarray(maps.depth), np.asarray(info["depth"]), rtol=1e-3, atol=1e-4)
    u_c, ok_c = maps_camera_flow(maps, p["vm0"], p["vm1"], p["K"], "composited")
    u_e, ok_e = maps_camera_flow(maps, p["vm0"], p["vm1"], p["K"], "expected")
    c2w0, c2w1 = np.linalg.inv(np.asarray(p["vm0"], np.float64)), np.linalg.inv(np.asarray(p["vm1"], np.float64))
    v, _ = camera_velocity(c2w0, c2w1)
    delta = np.asarray(lemma1_residual(pixel_centers(H, W), p["K"], v, maps.inv_depth, maps.depth))
    ok = np.asarray(ok_c & ok_e) & (np.asarray(maps.alpha) > 0.99)
    diff = np.asarray(u_c - u_e)[ok]
    big = np.linalg.norm(delta[ok], axis=-1) > 0.05  # pixels whose Gaussians lie at different depths
    assert big.sum() > 20, big.sum()
    err = np.linalg.norm(diff[big] - delta[ok][big], axis=-1) / np.linalg.norm(delta[ok][big], axis=-1)
    assert np.median(err) < 0.2, np.median(err)
    with pytest.raises(ValueError, match="camera_depth"):
        maps_camera_flow(maps, p["vm0"], p["vm1"], p["K"], "median")
