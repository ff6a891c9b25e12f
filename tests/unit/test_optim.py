"""The optimiser's pieces (`fgjax.train.optim`): the log-linear learning-rate schedule and the guarded step that
refuses an update whose loss is not finite or whose render overflowed its tile capacity."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from fgjax.train.optim import exp_decay, guarded_update


def test_exp_decay_is_log_linear_after_its_delay():
    """lr0 during the delay, lr1 from the last step on, the geometric mean half-way (log-linear)."""
    sched = exp_decay(1e-2, 1e-4, steps=110, delay=10)
    assert float(sched(0)) == pytest.approx(1e-2) and float(sched(10)) == pytest.approx(1e-2)
    assert float(sched(60)) == pytest.approx(1e-3, rel=1e-5)
    assert float(sched(110)) == pytest.approx(1e-4) and float(sched(500)) == pytest.approx(1e-4)
    got = np.array([float(sched(c)) for c in range(10, 111, 20)])
    np.testing.assert_allclose(np.diff(np.log(got)), 0.2 * np.log(1e-4 / 1e-2), rtol=1e-4)  # 20 of 100 steps


@pytest.mark.parametrize("bad", ["nan", "inf", "overflow"])
def test_guarded_update_keeps_params_and_state_on_a_bad_step(bad):
    """A finite step moves the parameters by Adam's first step (lr x sign of the gradient); a step whose loss is
    NaN or inf, or whose render overflowed, returns the parameters and the optimiser state unchanged, flagged."""
    opt = optax.adam(0.1)
    p = {"x": jnp.array([1.0, -2.0, 3.0])}
    st = opt.init(p)

    def loss_fn(params, i):
        val = jnp.sum(params["x"] ** 2)
        if i == 1:
            val = val * {"nan": jnp.nan, "inf": jnp.inf, "overflow": 1.0}[bad]
        return val, jnp.asarray(i == 1 and bad == "overflow")

    new, st1, loss, skipped = guarded_update(loss_fn, opt, p, st, 0)
    np.testing.assert_allclose(np.asarray(new["x"]), [0.9, -1.9, 2.9], rtol=1e-6)
    assert not bool(skipped) and float(loss) == pytest.approx(14.0)
    again, st2, loss, skipped = guarded_update(loss_fn, opt, new, st1, 1)
    assert bool(skipped)
    np.testing.assert_array_equal(np.asarray(again["x"]), np.asarray(new["x"]))
    for a, b in zip(jax.tree_util.tree_leaves(st2), jax.tree_util.tree_leaves(st1), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
