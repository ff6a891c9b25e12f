"""The long-range flow loss (`fgjax.flow.track`, ``flow.loss = "track"``) verified before it is trusted: optical
flow chained into tracks (`fgjax.data.opticalflow.chained_tracks`) on fields with known answers; on a synthetic door
with the true poses and the true optical flow (`fgjax.synth.render.sequence_flow`, an independent numpy
computation) chained from the first frame, the loss of the Gaussians moved by the true motion is near zero, the
loss with the door held still is large, the gradient at rest points the door along its motion, and the gradient
matches central finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fgjax.data.opticalflow import chained_tracks
from fgjax.flow.track import gaussian_track_loss, project_centres, rendered_correspondence
from fgjax.synth import SynthConfig, make_scene
from fgjax.synth.parts import rigid_inv
from fgjax.synth.render import render_sequence, sequence_flow
from fgjax.synth.scene import camera_c2w, deform, scene_states

W, H = 96, 72


def test_chained_tracks_of_a_constant_flow():
    flows = np.zeros((3, 6, 8, 2), np.float32)
    flows[..., 0] = 1.25  # 1.25 px to the right per frame
    tr = chained_tracks(flows)
    assert tr.shape == (4, 6, 8, 2) and np.all(tr[0] == 0)
    for k in range(1, 4):
        x_end = np.arange(8) + 1.25 * k  # array index of the track after k frames
        inside = x_end <= 8 - 0.5
        row = tr[k, 2]
        assert np.allclose(row[inside, 0], 1.25 * k) and np.allclose(row[inside, 1], 0.0)
        assert np.all(np.isnan(row[~inside]))  # left the image: lost
    # a rejected pixel of frame 1 ends the track that lands on it, and only that one
    ok = np.ones((3, 6, 8), bool)
    ok[1, 4, 3] = False  # frame 1, row 4, column 3: where the track from column 1.75 -> rounds to 3
    tr2 = chained_tracks(flows, ok)
    lost = np.isnan(tr2[2, ..., 0]) & ~np.isnan(tr[2, ..., 0])
    assert lost.sum() == 1 and lost[4, 2]  # the track that started at column 2 (at 3.25 in frame 1)
    with pytest.raises(ValueError, match="consistent must have shape"):
        chained_tracks(flows, ok[:2])


def test_chained_tracks_follow_a_rotation_field():
    """A flow that turns the image by 2 degrees per frame about its centre, chained 5 times, is a 10-degree turn
    (bilinear sampling of a linear field is exact)."""
    h, w = 40, 50
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    c = np.array([w / 2, h / 2])
    a = np.radians(2.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    p = np.stack([xs, ys], -1) - c
    flow = (p @ rot.T - p).astype(np.float32)
    tr = chained_tracks(np.repeat(flow[None], 5, 0))
    b = np.radians(10.0)
    rot5 = np.array([[np.cos(b), -np.sin(b)], [np.sin(b), np.cos(b)]])
    want = p @ rot5.T - p
    ok = np.isfinite(tr[5, ..., 0])
    assert ok.mean() > 0.7
    # a linear field is sampled exactly (the chain samples it at the moved point, so the turn composes), except
    # within half a pixel of the border, where the sampler holds the edge's value
    inner = ok & (np.linalg.norm(p, axis=-1) < 0.5 * h - 2)
    assert inner.sum() > 800
    assert np.abs(tr[5][inner] - want[inner]).max() < 1e-3


@pytest.fixture(scope="module")
def door_track():
    """A 24-frame door sequence; the tracks of frame 0 chained with the true flow to the frame where the door is
    furthest from its state at frame 0."""
    scene = make_scene(SynthConfig(objects=("door",), width=W, height=H, frames=24, seed=3))
    times = np.arange(24) / 23.0
    states = scene_states(scene, times)
    vm = rigid_inv(np.stack([camera_c2w(scene, float(t)) for t in times]))
    gt = sequence_flow(scene, states, vm, render_sequence(scene, vm, states))
    t = int(np.argmax(np.abs(states[:, 0] - states[0, 0])))
    flows = np.where(gt["flow_valid"][:t, ..., None], gt["flow"][:t], np.nan).astype(np.float32)
    tracks = chained_tracks(flows, ~gt["flow_occluded"][:t])
    m0, q0 = deform(scene, states[0])
    m1, _ = deform(scene, states[t])
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    return {"m0": f32(m0), "q0": f32(q0), "s": f32(scene.scales), "o": f32(scene.opacities), "m1": f32(m1),
            "vm0": f32(vm[0]), "vm1": f32(vm[t]), "K": f32(scene.K), "track": jnp.asarray(tracks[t]),
            "labels": scene.labels, "turn": float(abs(states[t, 0] - states[0, 0]))}


def _loss(p, m1, threshold=1.0, **kw):
    loss, overflow = gaussian_track_loss(p["m0"], p["q0"], p["s"], p["o"], m1, p["vm0"], p["K"], p["vm1"], p["K"],
                                         p["track"], W, H, threshold=threshold, **kw)
    assert not bool(overflow)
    return loss


def _residual(p, m1):
    corr, alpha, _ = rendered_correspondence(p["m0"], p["q0"], p["s"], p["o"], m1, p["vm0"], p["K"], p["vm1"], p["K"],
                                             W, H)
    r = np.abs(np.asarray(corr) - np.asarray(p["track"])).sum(-1)
    return np.where(np.asarray(alpha) > 0.5, r, np.nan), np.asarray(corr)


def test_track_loss_near_zero_at_true_motion_and_large_at_rest(door_track):
    p = door_track
    assert p["turn"] > 0.5, "the chosen frame must show the door well open"
    assert np.isfinite(np.asarray(p["track"])).mean() > 0.5
    r_true, c_true = _residual(p, p["m1"])
    r_rest, c_rest = _residual(p, p["m0"])
    door = np.linalg.norm(c_true - c_rest, axis=-1) > 2.0  # the pixels that the door's motion moves by > 2 px
    assert door.sum() > 50
    ok = door & np.isfinite(r_true)
    assert ok.sum() > 30
    # on the door's pixels the tracks match the true motion to a fraction of what holding the door still leaves
    # (measured 2.2 against 10.6 px: at the door's edges a pixel composites door and background Gaussians, whose
    # displacements 12 frames apart differ by tens of pixels)
    assert np.median(r_true[ok]) < 0.3 * np.median(r_rest[ok]), (np.median(r_true[ok]), np.median(r_rest[ok]))
    # the whole loss (errors under a pixel free; 94 % of the pixels static) falls too
    true, rest = float(_loss(p, p["m1"])), float(_loss(p, p["m0"]))
    assert np.isfinite(true) and np.isfinite(rest)
    assert true < 0.75 * rest, (true, rest)


def test_track_loss_gradient_at_rest_points_along_the_motion(door_track):
    p = door_track
    g = np.asarray(jax.grad(lambda m1: _loss(p, m1))(p["m0"]))
    assert np.all(np.isfinite(g))
    door = p["labels"] == 1
    true = np.asarray(p["m1"] - p["m0"])
    moved = door & (np.linalg.norm(true, axis=-1) > 1e-3) & (np.linalg.norm(g, axis=-1) > 0)
    assert moved.sum() > 20
    # the loss sees the motion across the view: compare the image-plane components (the ray's is free)
    cos = np.sum(-g[moved] * true[moved], -1) / (np.linalg.norm(g[moved], axis=-1)
                                                 * np.linalg.norm(true[moved], axis=-1))
    assert np.median(cos) > 0.5, np.median(cos)
    assert np.abs(g[~door]).sum() < 0.75 * np.abs(g[door]).sum()  # measured 0.58: the door's edge pixels
    # without the dead zone, L1's sign gradient from the static pixels' sub-pixel residuals outweighs the door
    g0 = np.asarray(jax.grad(lambda m1: _loss(p, m1, threshold=0.0))(p["m0"]))
    assert np.abs(g0[~door]).sum() > np.abs(g0[door]).sum()


def test_track_loss_gradient_matches_finite_differences(door_track):
    p = door_track
    rng = np.random.default_rng(0)
    x = p["m0"] + 0.5 * (p["m1"] - p["m0"])  # halfway: residuals away from the L1 kinks
    v = jnp.asarray(rng.normal(size=x.shape) * (p["labels"] == 1)[:, None], jnp.float32)
    v = v / jnp.linalg.norm(v)
    g = jax.grad(lambda m: _loss(p, m))(x)
    eps = 1e-3
    fd = (float(_loss(p, x + eps * v)) - float(_loss(p, x - eps * v))) / (2 * eps)
    assert float(jnp.sum(g * v)) == pytest.approx(fd, rel=0.05, abs=1e-3)


def test_charbonnier_track_loss_against_numpy_and_central_differences(door_track):
    """norm = "charbonnier": the mean over valid pixels of c^2 (sqrt(1 + e^2 / c^2) - 1), e = max(|C - D|_2 - tau, 0),
    against numpy on the rendered correspondence; its gradient against central differences; at rest, without a dead
    zone, the static Gaussians' share of the gradient is a tenth of L1's (the squared form weighs the static pixels'
    sub-pixel residuals by their size, where L1 gives each the same push)."""
    p = door_track
    x = p["m0"] + 0.5 * (p["m1"] - p["m0"])
    corr, alpha, _ = rendered_correspondence(p["m0"], p["q0"], p["s"], p["o"], x, p["vm0"], p["K"], p["vm1"], p["K"],
                                             W, H)
    tr = np.asarray(p["track"], np.float64)
    valid = np.isfinite(tr).all(-1) & (np.asarray(alpha) > 0.5)
    e = np.maximum(np.linalg.norm(np.asarray(corr, np.float64) - np.nan_to_num(tr), axis=-1) - 1.0, 0.0)
    for c in (3.0, 10.0):
        want = np.sum(np.where(valid, c * c * (np.sqrt(1 + e * e / (c * c)) - 1), 0.0)) / valid.sum()
        got = float(_loss(p, x, norm="charbonnier", scale=c))
        assert got == pytest.approx(want, rel=1e-4), (c, got, want)
    rng = np.random.default_rng(1)
    v = jnp.asarray(rng.normal(size=x.shape) * (p["labels"] == 1)[:, None], jnp.float32)
    v = v / jnp.linalg.norm(v)
    f = lambda m: _loss(p, m, norm="charbonnier", scale=3.0)
    fd = (float(f(x + 1e-3 * v)) - float(f(x - 1e-3 * v))) / 2e-3
    assert float(jnp.sum(jax.grad(f)(x) * v)) == pytest.approx(fd, rel=0.05, abs=1e-3)
    door = p["labels"] == 1

    def static_share(**kw):  # |gradient| on the static Gaussians over that on the door's, at rest
        g = np.asarray(jax.grad(lambda m1: _loss(p, m1, **kw))(p["m0"]))
        assert np.all(np.isfinite(g))
        return np.abs(g[~door]).sum() / np.abs(g[door]).sum()

    # measured: 20.1 (L1) against 2.0 without the dead zone, 0.59 against 0.49 with it
    assert static_share(threshold=0.0, norm="charbonnier", scale=10.0) < 0.2 * static_share(threshold=0.0)
    assert static_share(threshold=1.0, norm="charbonnier", scale=10.0) < 0.6
    with pytest.raises(ValueError, match="norm must be"):
        _loss(p, x, norm="l2")


def test_project_centres_matches_the_pinhole_model_and_stays_finite_behind_the_camera():
    K = jnp.asarray([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
    vm = jnp.eye(4).at[2, 3].set(2.0)  # camera 2 units behind the origin, looking along +z
    pts = jnp.asarray([[0.0, 0.0, 0.0], [0.2, -0.1, 2.0], [0.0, 0.0, -2.0]])  # the last one on the camera centre
    uv = np.asarray(project_centres(pts, vm, K))
    assert np.allclose(uv[0], [40, 30]) and np.allclose(uv[1], [40 + 100 * 0.2 / 4, 30 - 100 * 0.1 / 4])
    assert np.all(np.isfinite(uv))
    g = jax.grad(lambda m: jnp.sum(project_centres(m, vm, K)))(pts)
    assert np.all(np.isfinite(np.asarray(g)))


def test_track_loss_is_finite_on_degenerate_input():
    """Nothing visible (all behind the camera, or transparent), NaN tracks everywhere, coincident centres: the loss
    is 0 or finite and so is its gradient."""
    K = jnp.asarray([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]])
    vm = jnp.eye(4)
    n = 5
    q = jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (n, 1))
    s = jnp.full((n, 3), 0.05)
    track = jnp.zeros((24, 32, 2))
    cases = [
        (jnp.tile(jnp.asarray([0.0, 0.0, -1.0]), (n, 1)), jnp.full((n,), 0.9), track),  # behind the camera
        (jnp.tile(jnp.asarray([0.0, 0.0, 2.0]), (n, 1)), jnp.zeros((n,)), track),  # transparent
        (jnp.tile(jnp.asarray([0.0, 0.0, 2.0]), (n, 1)), jnp.full((n,), 0.9), jnp.full((24, 32, 2), jnp.nan)),  # lost
        (jnp.tile(jnp.asarray([0.0, 0.0, 2.0]), (n, 1)), jnp.full((n,), 0.9), track),  # all at one point
    ]
    for means, o, tr in cases:
        for norm, thr in (("l1", 0.5), ("charbonnier", 0.5), ("charbonnier", 0.0)):
            f = lambda m1, means=means, o=o, tr=tr, norm=norm, thr=thr: gaussian_track_loss(
                means, q, s, o, m1, vm, K, vm, K, tr, 32, 24, threshold=thr, norm=norm)[0]
            for at in (means + 0.01, means):  # the second: every residual exactly zero
                val, g = jax.value_and_grad(f)(at)
                assert np.isfinite(float(val)) and np.all(np.isfinite(np.asarray(g))), (norm, thr)
