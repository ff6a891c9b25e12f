"""Encodings, deformation fields and the Gaussian pytree."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fgjax import gaussians as G
from fgjax.models import deform, encoding


def test_frequency_encoding_layout():
    x = jnp.array([[0.25, -0.5]])
    e = encoding.frequency_encoding(x, 3)
    assert e.shape == (1, encoding.frequency_dim(2, 3)) == (1, 14)
    np.testing.assert_allclose(e[0, :2], [0.25, -0.5])
    np.testing.assert_allclose(e[0, 2:4], np.sin(np.pi * np.array([0.25, -0.5])), atol=1e-12)
    np.testing.assert_allclose(e[0, 4:6], np.cos(np.pi * np.array([0.25, -0.5])), atol=1e-12)
    np.testing.assert_allclose(e[0, 12:14], np.cos(4 * np.pi * np.array([0.25, -0.5])), atol=1e-12)


def _hash_reference(tables, x, resolutions):
    """Slow per-point loop: dense or hashed index of each of the 2^D corners, d-linear weights."""
    primes = [1, 2654435761, 805459861, 3674653429]
    L, T, F = tables.shape
    out = np.zeros((len(x), L * F))
    for n, p in enumerate(np.clip(x, 0, 1)):
        for level, res in enumerate(resolutions):
            pos = p * res
            base = np.minimum(np.floor(pos).astype(np.int64), res - 1)
            frac = pos - np.floor(pos)
            acc = np.zeros(F)
            for c in range(2 ** len(p)):
                off = np.array([(c >> k) & 1 for k in range(len(p))])
                idx = base + off
                w = np.prod(np.where(off == 1, frac, 1 - frac))
                if (res + 1) ** len(p) <= T:
                    h = sum(int(idx[k]) * (res + 1) ** k for k in range(len(p))) % T
                else:
                    h = 0
                    for k in range(len(p)):
                        h ^= (int(idx[k]) * primes[k]) & 0xFFFFFFFF
                    h %= T
                acc += w * tables[level, h]
            out[n, level * F : (level + 1) * F] = acc
    return out


@pytest.mark.parametrize("d", [2, 3])
def test_hash_grid_matches_reference(key, d):
    tables = jax.random.normal(key, (3, 2**8, 2))
    res = (4, 9, 40)  # dense, dense (d=2), hashed
    x = jax.random.uniform(jax.random.key(1), (7, d))
    got = encoding.hash_grid_encode(tables, x, res)
    np.testing.assert_allclose(got, _hash_reference(np.asarray(tables), np.asarray(x), res), atol=1e-9)


def test_hash_grid_continuous_and_differentiable(key):
    tables = jax.random.normal(key, (4, 2**10, 2))
    res = tuple(encoding.hash_grid_resolutions(4, 4, 64))
    x0 = jnp.array([[0.3, 0.6, 0.2]])
    a = encoding.hash_grid_encode(tables, x0, res)
    b = encoding.hash_grid_encode(tables, x0 + 1e-7, res)
    assert float(jnp.max(jnp.abs(a - b))) < 1e-4
    g = jax.grad(lambda t: jnp.sum(encoding.hash_grid_encode(t, x0, res) ** 2))(tables)
    assert int(jnp.sum(g != 0)) > 0


@pytest.mark.parametrize("kind", ["frequency", "hash"])
def test_deform_starts_at_identity_and_learns(key, kind):
    spec = deform.DeformSpec(kind=kind, depth=3, width=32, skip=2, hash_levels=4, hash_log2_table=10)
    params = deform.deform_init(key, spec, dtype=jnp.float64)
    x = jax.random.uniform(jax.random.key(2), (50, 3), minval=-1, maxval=1)
    dx, dq, ds = deform.deform_apply(spec, params, x, 0.3)
    assert dx.shape == (50, 3) and dq.shape == (50, 4) and ds.shape == (50, 3)
    assert float(jnp.max(jnp.abs(jnp.concatenate([dx, dq, ds], -1)))) == 0.0
    # gradients reach every leaf group (heads first; the rest after one step)
    loss = lambda p: jnp.sum((deform.deform_apply(spec, p, x, 0.3)[0] - 0.1) ** 2)
    g = jax.grad(loss)(params)
    assert float(jnp.abs(g["head"]["w"]).sum()) > 0
    # per-Gaussian times broadcast
    dx2, _, _ = deform.deform_apply(spec, params, x, jnp.full((50,), 0.3))
    np.testing.assert_allclose(dx2, dx)


def test_bases_field_is_a_blend_of_rigid_motions(key):
    """kind = "bases": identity at init (dX = 0, with a gradient into the motions); with the logits pinned by the
    head's bias, dX = sum_k w_k [R_k(t) (X - c_k) + c_k + tau_k(t) - X] against scipy's rotation vectors and numpy's
    linear interpolation between the knots (t clipped to [0, 1]); per-point times; the orientations turned by the
    bases' rotations; the anchor inside the control values; gradients against central differences in float64."""
    from jax.test_util import check_grads
    from scipy.spatial.transform import Rotation

    spec = deform.DeformSpec(kind="bases", depth=2, width=16, hash_levels=4, hash_log2_table=10, bases=3, knots=4)
    p = deform.deform_init(key, spec, dtype=jnp.float64)
    x = jax.random.uniform(jax.random.key(3), (40, 3), jnp.float64, minval=-1, maxval=1)
    dx, dq, ds = deform.deform_apply(spec, p, x, 0.3)
    assert float(jnp.max(jnp.abs(dx))) == 0.0 and float(jnp.max(jnp.abs(dq))) == 0.0 and ds.shape == (40, 3)
    g = jax.grad(lambda q: jnp.sum(deform.deform_apply(spec, q, x, 0.3)[0][:, 0]))(p)
    assert float(jnp.abs(g["motion"]).sum()) > 0

    rng = np.random.default_rng(0)
    motion, pivot, w = rng.normal(0, 0.4, (2, 4, 6)), rng.normal(0, 0.5, (2, 3)), np.array([0.2, 0.3, 0.5])
    p = {**p, "motion": jnp.asarray(motion), "pivot": jnp.asarray(pivot),
         "head": {"w": jnp.zeros_like(p["head"]["w"]), "b": jnp.asarray(np.log(w))}}
    xs = np.asarray(x)
    for t in (0.0, 0.3, 2.0 / 3.0, 0.95, 1.4):
        knots_t = np.linspace(0.0, 1.0, 4)
        want = np.zeros_like(xs)
        for k in range(2):
            m = np.array([np.interp(min(t, 1.0), knots_t, motion[k, :, j]) for j in range(6)])
            rot = Rotation.from_rotvec(m[:3]).as_matrix()
            want += w[k + 1] * ((xs - pivot[k]) @ rot.T + pivot[k] + m[3:] - xs)
        np.testing.assert_allclose(np.asarray(deform.deform_apply(spec, p, x, t)[0]), want, atol=1e-12)
    per_point = deform.deform_apply(spec, p, x, jnp.linspace(0.0, 1.0, 40))[0]
    for i in (0, 17, 39):
        np.testing.assert_allclose(per_point[i], deform.deform_apply(spec, p, x[i:i + 1], i / 39.0)[0][0], atol=1e-12)
    check_grads(lambda m, c: deform.deform_apply(spec, {**p, "motion": m, "pivot": c}, x, 0.45)[0],
                (p["motion"], p["pivot"]), order=1, modes=["rev"], atol=1e-6, rtol=1e-6)
    # orientations: one basis (weight ~1) turns each quaternion by its rotation (scipy, up to sign); a blend turns it
    # by the normalised blend of the bases' quaternions on the w >= 0 hemisphere
    quats = jax.random.normal(jax.random.key(4), (40, 4), jnp.float64)
    one = {**p, "head": {"w": p["head"]["w"], "b": jnp.asarray([0.0, 80.0, 0.0])}}
    m = np.array([np.interp(0.3, np.linspace(0.0, 1.0, 4), motion[0, :, j]) for j in range(6)])
    q1 = np.asarray(quats + deform.deform_apply(spec, one, x, 0.3, quats=quats)[1])
    qn = np.asarray(quats) / np.linalg.norm(np.asarray(quats), axis=-1, keepdims=True)
    want = (Rotation.from_rotvec(m[:3]) * Rotation.from_quat(qn[:, [1, 2, 3, 0]])).as_quat()[:, [3, 0, 1, 2]]
    got = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(got * want, -1)), 1.0, atol=1e-10)
    r = w[0] * np.array([1.0, 0, 0, 0])
    for k in range(2):
        mk = np.array([np.interp(0.3, np.linspace(0.0, 1.0, 4), motion[k, :, j]) for j in range(3)])
        rk = Rotation.from_rotvec(mk).as_quat()[[3, 0, 1, 2]]
        r = r + w[k + 1] * rk * np.sign(rk[0])
    r = r / np.linalg.norm(r)
    blend = np.asarray(quats + deform.deform_apply(spec, p, x, 0.3, quats=quats)[1])
    want = (Rotation.from_quat(r[[1, 2, 3, 0]]) * Rotation.from_quat(qn[:, [1, 2, 3, 0]])).as_quat()[:, [3, 0, 1, 2]]
    np.testing.assert_allclose(np.abs(np.sum(blend / np.linalg.norm(blend, axis=-1, keepdims=True) * want, -1)), 1.0,
                               atol=1e-10)
    check_grads(lambda m, q: deform.deform_apply(spec, {**p, "motion": m}, x, 0.45, quats=q)[1],
                (p["motion"], quats), order=1, modes=["rev"], atol=1e-6, rtol=1e-6)
    g0 = jax.grad(lambda m: jnp.sum(deform.deform_apply(spec, {**p, "motion": m}, x, 0.3, quats=quats)[1] ** 2))(
        jnp.zeros_like(p["motion"]))
    assert bool(jnp.all(jnp.isfinite(g0)))  # at omega = 0
    # an anchor: the identity at t_a (positions and orientations), rigid elsewhere (relative control values)
    anch = deform.DeformSpec(kind="bases", depth=2, width=16, hash_levels=4, hash_log2_table=10, bases=3, knots=4,
                             anchor=0.2)
    dx_a, dq_a, _ = deform.deform_apply(anch, p, x, 0.2, quats=quats)
    assert float(jnp.max(jnp.abs(dx_a))) == 0.0 and float(jnp.max(jnp.abs(dq_a))) < 1e-15
    rel = {**one, "motion": one["motion"] - jax.vmap(lambda mk: deform._knot_values(anch, mk[None], 0.2)[0])(
        one["motion"])[:, None]}
    np.testing.assert_allclose(deform.deform_apply(anch, one, x, 0.7)[0], deform.deform_apply(spec, rel, x, 0.7)[0],
                               atol=1e-12)
    with pytest.raises(ValueError, match="bases and knots must be >= 2"):
        deform.DeformSpec(kind="bases", bases=1)


def test_screw_bases_turn_about_and_slide_along_one_axis_for_the_whole_clip(key):
    """joint = "screw": identity at init with unit axes; dX = sum_k w_k [R_k(t) (X - c_k) + c_k + h_k(t) a_k - X] with
    R_k(t) = exp(theta_k(t) a_k) against scipy (the axes given unnormalised); the same field as the "free" joint
    whose control values are (theta a, h a), orientations included; a point on a basis's axis line moves only along
    the axis and every point keeps its distance to that line, at every time; gradients against central differences
    (float64) and finite at the identity and at a zero axis; the anchor; a screw without bases fails."""
    from jax.test_util import check_grads
    from scipy.spatial.transform import Rotation

    kw = dict(kind="bases", depth=2, width=16, hash_levels=4, hash_log2_table=10, bases=3, knots=4)
    spec = deform.DeformSpec(**kw, joint="screw")
    p = deform.deform_init(key, spec, dtype=jnp.float64)
    assert p["motion"].shape == (2, 4, 2) and p["axis"].shape == (2, 3)
    np.testing.assert_allclose(np.linalg.norm(p["axis"], axis=-1), 1.0, atol=1e-12)
    x = jax.random.uniform(jax.random.key(3), (40, 3), jnp.float64, minval=-1, maxval=1)
    assert float(jnp.max(jnp.abs(deform.deform_apply(spec, p, x, 0.3)[0]))) == 0.0
    g = jax.grad(lambda q: jnp.sum(deform.deform_apply(spec, q, x, 0.3)[0][:, 0]))(p)
    assert float(jnp.abs(g["motion"]).sum()) > 0 and bool(jnp.all(jnp.isfinite(g["axis"])))

    rng = np.random.default_rng(2)
    motion, axis, pivot = rng.normal(0, 0.6, (2, 4, 2)), rng.normal(0, 2.0, (2, 3)), rng.normal(0, 0.5, (2, 3))
    w = np.array([0.2, 0.3, 0.5])
    p = {**p, "motion": jnp.asarray(motion), "axis": jnp.asarray(axis), "pivot": jnp.asarray(pivot),
         "head": {"w": jnp.zeros_like(p["head"]["w"]), "b": jnp.asarray(np.log(w))}}
    unit = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    xs = np.asarray(x)
    quats = jax.random.normal(jax.random.key(4), (40, 4), jnp.float64)
    free = deform.DeformSpec(**kw)
    as_free = {k: v for k, v in p.items() if k != "axis"}
    as_free["motion"] = jnp.asarray(np.concatenate([motion[..., :1] * unit[:, None], motion[..., 1:] * unit[:, None]],
                                                   axis=-1))
    for t in (0.0, 0.3, 0.95, 1.4):
        want = np.zeros_like(xs)
        for k in range(2):
            theta, h = (np.interp(min(t, 1.0), np.linspace(0.0, 1.0, 4), motion[k, :, j]) for j in range(2))
            rot = Rotation.from_rotvec(theta * unit[k]).as_matrix()
            want += w[k + 1] * ((xs - pivot[k]) @ rot.T + pivot[k] + h * unit[k] - xs)
        got = deform.deform_apply(spec, p, x, t, quats=quats)
        np.testing.assert_allclose(np.asarray(got[0]), want, atol=1e-12)
        ref = deform.deform_apply(free, as_free, x, t, quats=quats)
        np.testing.assert_allclose(np.asarray(got[1]), np.asarray(ref[1]), atol=1e-12)
    # one basis (weight ~1): the axis line slides along itself, every point keeps its distance to it
    one = {**p, "head": {"w": p["head"]["w"], "b": jnp.asarray([0.0, 80.0, 0.0])}}
    on_line = pivot[0] + np.linspace(-1.0, 1.0, 5)[:, None] * unit[0]
    def line_dist(pts):
        d = pts - pivot[0]
        return np.linalg.norm(d - (d @ unit[0])[:, None] * unit[0], axis=-1)
    for t in (0.1, 0.5, 0.9):
        d_line = np.asarray(deform.deform_apply(spec, one, jnp.asarray(on_line), t)[0])
        np.testing.assert_allclose(np.cross(d_line, unit[0]), 0.0, atol=1e-12)
        moved = xs + np.asarray(deform.deform_apply(spec, one, x, t)[0])
        np.testing.assert_allclose(line_dist(moved), line_dist(xs), atol=1e-12)
    check_grads(lambda m, a, c: deform.deform_apply(spec, {**p, "motion": m, "axis": a, "pivot": c}, x, 0.45)[0],
                (p["motion"], p["axis"], p["pivot"]), order=1, modes=["rev"], atol=1e-6, rtol=1e-6)
    for q in ({**p, "motion": jnp.zeros_like(p["motion"])}, {**p, "axis": jnp.zeros_like(p["axis"])}):
        out = lambda q: deform.deform_apply(spec, q, x, 0.3, quats=quats)
        val, grad = jax.value_and_grad(lambda q: jnp.sum(out(q)[0] ** 2) + jnp.sum(out(q)[1] ** 2))(q)
        assert bool(jnp.isfinite(val)) and all(bool(jnp.all(jnp.isfinite(v))) for v in jax.tree_util.tree_leaves(grad))
    anch = deform.DeformSpec(**kw, joint="screw", anchor=0.2)
    dx_a, dq_a, _ = deform.deform_apply(anch, p, x, 0.2, quats=quats)
    assert float(jnp.max(jnp.abs(dx_a))) == 0.0 and float(jnp.max(jnp.abs(dq_a))) < 1e-15
    with pytest.raises(ValueError, match="joint must be 'free' or, with kind 'bases', 'screw'"):
        deform.DeformSpec(kind="hash", joint="screw")
    slot = deform.deform_init(key, deform.DeformSpec(kind="bases", bases=3, knots=4, weights="slot", joint="screw"),
                              slots=5)
    assert set(slot) == {"motion", "pivot", "axis", "slots"}


def test_slot_weights_hold_the_static_slots_and_give_each_free_slot_its_own(key):
    """weights = "slot": a held slot sits on the static basis exactly (dX = 0, dq = 0, no gradient into its logits);
    a free slot's weights are the softmax of its own logits, so its dX equals the "field" kind's with the same
    logits (the head's bias), and its logits' gradient matches central differences (float64); a changed logit moves
    only its own slot; bad shapes and kinds fail."""
    from jax.test_util import check_grads

    spec = deform.DeformSpec(kind="bases", bases=3, knots=4, weights="slot")
    field = deform.DeformSpec(kind="bases", depth=2, width=16, hash_levels=4, hash_log2_table=10, bases=3, knots=4)
    p = deform.deform_init(key, spec, dtype=jnp.float64, slots=6)
    assert set(p) == {"motion", "pivot", "slots"} and p["slots"]["logits"].shape == (6, 3)
    rng = np.random.default_rng(1)
    logits = rng.normal(0, 1.0, 3)
    p = {**p, "motion": jnp.asarray(rng.normal(0, 0.4, (2, 4, 6))), "pivot": jnp.asarray(rng.normal(0, 0.5, (2, 3))),
         "slots": {"logits": jnp.asarray(np.tile(logits, (6, 1))), "free": jnp.asarray([0.0, 1, 1, 0, 1, 0])}}
    x = jax.random.uniform(jax.random.key(3), (6, 3), jnp.float64, minval=-1, maxval=1)
    quats = jax.random.normal(jax.random.key(4), (6, 4), jnp.float64)
    dx, dq, _ = deform.deform_apply(spec, p, x, 0.7, quats=quats)
    held, free = np.array([0, 3, 5]), np.array([1, 2, 4])
    assert float(jnp.max(jnp.abs(dx[held]))) == 0.0 and float(jnp.max(jnp.abs(dq[held]))) == 0.0
    f = deform.deform_init(key, field, dtype=jnp.float64)
    f = {**f, "motion": p["motion"], "pivot": p["pivot"],
         "head": {"w": jnp.zeros_like(f["head"]["w"]), "b": jnp.asarray(logits)}}
    want_dx, want_dq, _ = deform.deform_apply(field, f, x, 0.7, quats=quats)
    np.testing.assert_allclose(dx[free], want_dx[free], atol=1e-12)
    np.testing.assert_allclose(dq[free], want_dq[free], atol=1e-12)
    w = deform.basis_weights(spec, p, x)
    np.testing.assert_array_equal(w[held], np.tile([1.0, 0.0, 0.0], (3, 1)))
    g = jax.grad(lambda lg: jnp.sum(deform.deform_apply(spec, {**p, "slots": {**p["slots"], "logits": lg}}, x,
                                                        0.7)[0] ** 2))(p["slots"]["logits"])
    assert float(jnp.max(jnp.abs(g[held]))) == 0.0 and float(jnp.min(jnp.abs(g[free]).sum(1))) > 0
    check_grads(lambda lg: deform.deform_apply(spec, {**p, "slots": {**p["slots"], "logits": lg}}, x, 0.7)[0],
                (p["slots"]["logits"],), order=1, modes=["rev"], atol=1e-6, rtol=1e-6)
    moved = {**p, "slots": {**p["slots"], "logits": p["slots"]["logits"].at[2].add(jnp.asarray([0.0, 3.0, 0.0]))}}
    changed = np.flatnonzero(np.any(np.asarray(deform.deform_apply(spec, moved, x, 0.7)[0] != dx), axis=1))
    assert changed.tolist() == [2]
    with pytest.raises(ValueError, match="cover 6 Gaussian slots"):
        deform.deform_apply(spec, p, x[:4], 0.7)
    with pytest.raises(ValueError, match="number of Gaussian slots"):
        deform.deform_init(key, spec)
    with pytest.raises(ValueError, match="weights must be"):
        deform.DeformSpec(kind="hash", weights="slot")


def test_deform_default_sizes_match_deformable_3dgs(key):
    spec = deform.DeformSpec()
    assert spec.in_dim == 63 + 13
    params = deform.deform_init(key, spec)
    assert len(params["layers"]) == 8
    assert params["layers"][4]["w"].shape == (256 + 76, 256)


def test_gaussians_init_and_activate(key):
    g, alive = G.init_random(key, 20, [-1, -1, -1], [1, 1, 1], capacity=32, sh_degree=2)
    assert g.means.shape == (32, 3) and g.sh.shape == (32, 9, 3) and g.sh_degree == 2
    assert int(alive.sum()) == 20
    q, s, o = G.activate(g, alive)
    np.testing.assert_allclose(jnp.linalg.norm(q, axis=-1), 1.0, rtol=1e-6)
    assert float(o[20:].max()) == 0.0 and float(o[:20].min()) == pytest.approx(0.1, rel=1e-5)
    assert bool(jnp.all(s > 0))
    with pytest.raises(ValueError, match="opacity_logits"):
        G.Gaussians(g.means, g.log_scales, g.quats, g.opacity_logits[:3], g.sh)


@pytest.mark.parametrize("kind", ["hash", "frequency"])
def test_anchored_field_is_zero_at_its_anchor_and_holds_no_constant_offset(key, kind):
    """DeformSpec.anchor: f(X, t) = g(X, t) - g(X, t_a): exactly zero at t_a for any parameters, and the network's
    output elsewhere minus its output at t_a (DESIGN section 1, step 1; config deform.anchor)."""
    kw = {"kind": kind, "depth": 2, "width": 16}
    free, anch = deform.DeformSpec(**kw), deform.DeformSpec(**kw, anchor=0.25)
    p = deform.deform_init(key, free)
    p = jax.tree_util.tree_map(lambda a: a + 0.1 * jax.random.normal(jax.random.fold_in(key, a.size), a.shape), p)
    x = jax.random.uniform(jax.random.fold_in(key, 7), (50, 3), minval=-0.9, maxval=0.9)
    for out in deform.deform_apply(anch, p, x, 0.25):
        assert float(jnp.max(jnp.abs(out))) == 0.0
    a = deform.deform_apply(anch, p, x, 0.8)
    g8, g25 = deform.deform_apply(free, p, x, 0.8), deform.deform_apply(free, p, x, 0.25)
    assert float(jnp.max(jnp.abs(g8[0] - g25[0]))) > 1e-3  # the network does vary with t
    for o, u, v in zip(a, g8, g25):
        np.testing.assert_allclose(np.asarray(o), np.asarray(u - v), atol=1e-6)
    grads = jax.grad(lambda q: jnp.sum(deform.deform_apply(anch, q, x, 0.8)[0] ** 2))(p)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grads))
    assert hash(anch) != hash(free)  # a static jit argument: the anchor is part of the compiled function
