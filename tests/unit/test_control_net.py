"""Control network (fgjax.models.control_net): zero at init, masked rows exactly zero, row independence,
finite gradients, jit / vmap, and the hash-grid path's error while fgjax.models.encoding lacks it."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

from fgjax.models import control_net as cn

N = 40
apply = jax.jit(cn.control_apply)  # eager op-by-op dispatch is slow on a shared CPU; one compile per shape


def _inputs(seed=0):
    rng = np.random.default_rng(seed)  # numpy: eager jax.random calls each compile on a busy CPU
    X = jnp.asarray(rng.uniform(-1.5, 1.5, (N, 3)))
    labels = jnp.asarray(rng.integers(-1, 3, N))  # -1 static, clusters 0..2
    vecs = jnp.asarray(rng.normal(size=(3, 3)) * 0.3)
    return X, labels, vecs


def _perturbed(params, seed, scale=0.5):
    """Random non-zero parameters everywhere (incl. the zero-initialised head)."""
    rng = np.random.default_rng(seed)
    leaves, tree = jax.tree_util.tree_flatten(params)
    return jax.tree_util.tree_unflatten(
        tree, [jnp.asarray(np.asarray(x) + scale * rng.normal(size=x.shape).astype(x.dtype)) for x in leaves])


@pytest.mark.parametrize("depth,hidden", [(1, 16), (3, 64)])
def test_zero_output_at_init(key, depth, hidden):
    params = cn.control_init(key, depth=depth, hidden=hidden)
    X, labels, vecs = _inputs()
    v, mask = cn.per_gaussian_vectors(vecs, labels)
    for out in apply(params, v, X, mask) + apply(params, v, X):
        assert np.all(np.asarray(out) == 0.0)
    dX, dq, ds = apply(params, v, X)
    assert dX.shape == (N, 3) and dq.shape == (N, 4) and ds.shape == (N, 3)


@pytest.mark.parametrize("seed", range(3))
def test_static_gaussians_never_move(seed):
    params = _perturbed(cn.control_init(jr.key(seed)), 100 + seed)
    X, labels, vecs = _inputs(seed)
    v, mask = cn.per_gaussian_vectors(vecs, labels)
    # even a non-zero vector on a masked row must not move it
    v = v + jnp.where(mask[:, None], 0.0, 1.0)
    outs = apply(params, v, X, mask)
    static = ~np.asarray(mask)
    assert static.any() and (~static).any()
    for o in outs:
        assert np.all(np.asarray(o)[static] == 0.0)
    assert np.abs(np.asarray(outs[0])[~static]).max() > 1e-3  # the others do move
    # and no gradient reaches parameters through static rows
    g = jax.jit(jax.grad(lambda p: sum(jnp.sum(o[static] ** 2) for o in cn.control_apply(p, v, X, mask))))(params)
    assert all(np.all(np.asarray(x) == 0) for x in jax.tree_util.tree_leaves(g))


def test_output_depends_only_on_own_cluster_vector():
    params = _perturbed(cn.control_init(jr.key(1)), 2)
    X, labels, vecs = _inputs(1)
    labels = jnp.asarray(np.arange(N) % 4 - 1)  # every cluster present
    v, mask = cn.per_gaussian_vectors(vecs, labels)
    base = apply(params, v, X, mask)
    vecs2 = vecs.at[1].add(jnp.array([0.2, -0.1, 0.3]))
    v2, _ = cn.per_gaussian_vectors(vecs2, labels)
    moved = apply(params, v2, X, mask)
    own = np.asarray(labels) == 1
    for a, b in zip(base, moved, strict=True):
        diff = np.abs(np.asarray(a) - np.asarray(b)).max(axis=1)
        assert np.all(diff[~own] == 0.0)  # other clusters and static rows: bit-identical
        assert np.all(diff[own] > 0.0)  # cluster 1: changed


def test_per_gaussian_vectors():
    vecs = jnp.array([[1.0, 0, 0], [0, 2.0, 0]])
    v, m = cn.per_gaussian_vectors(vecs, jnp.array([-1, 0, 1, 1, -1]))
    np.testing.assert_array_equal(np.asarray(m), [False, True, True, True, False])
    np.testing.assert_array_equal(np.asarray(v), [[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 2, 0], [0, 0, 0]])
    v, m = cn.per_gaussian_vectors(jnp.zeros((0, 3)), jnp.array([-1, -1]))
    assert v.shape == (2, 3) and not np.asarray(m).any()


def test_gradients_finite_jit_vmap(key):
    params = cn.control_init(key, hidden=32, depth=2, dtype=jnp.float64)
    X, labels, vecs = _inputs(3)
    v, mask = cn.per_gaussian_vectors(vecs, labels)

    def loss(p, vecs_):
        v_, m_ = cn.per_gaussian_vectors(vecs_, labels)
        dX, dq, ds = cn.control_apply(p, v_, X, m_)
        return jnp.sum((X + dX - 0.1) ** 2) + jnp.sum(dq ** 2) + jnp.sum(ds ** 2)

    g_p, g_v = jax.jit(jax.grad(loss, argnums=(0, 1)))(params, vecs)
    leaves = jax.tree_util.tree_leaves(g_p)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    assert np.abs(np.asarray(g_p.weights[-1])).max() > 0  # head learns
    assert np.all(np.isfinite(np.asarray(g_v)))
    # a step on the zero head makes the controlled rows move
    p2 = jax.tree_util.tree_map(lambda a, b: a - 0.01 * b, params, g_p)
    assert np.abs(np.asarray(apply(p2, v, X, mask)[0])[np.asarray(mask)]).max() > 0

    p = _perturbed(params, 5)
    eager = cn.control_apply(p, v, X, mask)
    jitted = jax.jit(cn.control_apply)(p, v, X, mask)
    for a, b in zip(eager, jitted, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-10)
    # vmap over a batch of control settings (e.g. several time steps): same as a loop
    vb = jnp.stack([v, 2 * v, -v])
    batched = jax.jit(jax.vmap(cn.control_apply, in_axes=(None, 0, None, None)))(p, vb, X, mask)
    for i in range(3):
        for a, b in zip(jitted if i == 0 else apply(p, vb[i], X, mask), batched, strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b[i]), rtol=1e-10, atol=1e-10)
    # and vmap over rows (one Gaussian at a time) agrees with the batched call: rows are independent
    rows = jax.jit(jax.vmap(lambda vi, xi, mi: cn.control_apply(p, vi[None], xi[None], mi[None])))(v, X, mask)
    for a, b in zip(eager, rows, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b)[:, 0], rtol=1e-10, atol=1e-10)


def test_frequency_encoding():
    x = jnp.array([[0.25, -0.5, 1.0]])
    e = cn.frequency_encoding(x, 2)
    assert e.shape == (1, 3 * 5)
    np.testing.assert_allclose(np.asarray(e[0, :3]), np.asarray(x[0]))
    np.testing.assert_allclose(np.asarray(e[0, 3:6]), np.sin(np.pi * np.asarray(x[0])), atol=1e-12)
    np.testing.assert_allclose(np.asarray(e[0, 9:12]), np.sin(2 * np.pi * np.asarray(x[0])), atol=1e-12)
    assert cn.frequency_encoding(x, 0).shape == (1, 3)


def test_bad_arguments(key):
    p = cn.control_init(key, hidden=8, depth=1)
    with pytest.raises(ValueError, match="X must have shape"):
        cn.control_apply(p, jnp.zeros((4, 3)), jnp.zeros((4, 2)))
    with pytest.raises(ValueError, match="v_c must have shape"):
        cn.control_apply(p, jnp.zeros((5, 3)), jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match="mask must have shape"):
        cn.control_apply(p, jnp.zeros((4, 3)), jnp.zeros((4, 3)), jnp.ones(5, bool))
    with pytest.raises(ValueError, match="encoding"):
        cn.control_init(key, encoding="nope")  # type: ignore[arg-type]


def test_hashgrid_path(key):
    """With the multiresolution hash grid over X the zero-at-init contract holds too, and the grid's features
    reach the output once the last layer is non-zero (gradients flow into the tables)."""
    p = cn.control_init(key, encoding="hashgrid", hidden=16, depth=1)
    assert p.grid.shape == (cn.HASH_LEVELS, 2**cn.HASH_LOG2_TABLE, cn.HASH_FEATURES)
    X, labels, vecs = _inputs()
    v, mask = cn.per_gaussian_vectors(vecs, labels)
    for o in apply(p, v, X, mask):
        assert np.all(np.asarray(o) == 0.0)
    q = eqx.tree_at(lambda m: m.weights[-1], p, jnp.ones_like(p.weights[-1]))
    g = jax.grad(lambda m: sum(jnp.sum(o ** 2) for o in apply(m, v, X, mask)))(q)
    assert np.isfinite(np.asarray(g.grid)).all() and float(jnp.abs(g.grid).sum()) > 0
