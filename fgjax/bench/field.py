"""``fgjax bench field``: can stage 1's deformation field learn a local motion at all, given the motion itself?

No rendering and no images: the field of a named configuration (``[deform]``, anchored at t = 0 as with
``deform.anchor = "first"``) is fitted alone, with stage 1's Adam groups and rates (``train.lr_deform`` decaying to
``train.lr_deform_final``, hash tables x ``train.lr_hash_factor``, unless ``--hash-factors`` says otherwise), to an
exact 3D target at random points of the field's box: the points of a cube (the "part", half-size ``--part``) move by
dX = (``--shift``, 0, 0) x s(t), with s rising from 0 to 1 linearly over ``--ramp`` around t = 0.5 (0: a step at
0.5), and every other point stays (the static scene). One step takes one of ``frames`` evenly spaced training times:

- ``--target displacement``: the residual is dX(x, t) - target(x, t), the form of the photometric and track losses
  (the displacement from the canonical state);
- ``--target velocity``: the residual is [dX(x, t_k) - dX(x, t_{k-1})] - [target(x, t_k) - target(x, t_{k-1})] for
  consecutive training times, the form of L_uGS (the dynamic flow of one frame pair, DESIGN.md section 1, step 4)
  lifted to 3D.

The loss on the residual is the mean over the points of its L1 norm ("l1", the form of every stage-1 term that
reaches the displacements) or of its squared norm ("l2").

Printed per (loss, hash factor): the part's mean learned dX at t = 0.9 against the shift, the largest |dX| of a
static point then, and the fit's time. Because every parameter of the field (the MLP, the coarse hash levels) is
shared by many points, an L1 loss puts it at the weighted median of what the points ask, which is "no motion" when
the part is a few % of them (docs/benchmarks.md, "Can the field learn a local motion?").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from fgjax.config import Config, load_config
from fgjax.io import atomic_write
from fgjax.method.stage1 import deform_spec_from_config
from fgjax.models.deform import deform_apply, deform_init
from fgjax.train.optim import exp_decay

__all__ = ["fit_local_motion", "main"]

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"
BOX = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)
CENTRE = np.array([0.3, -0.2, 0.1])


def fit_local_motion(cfg: Config, *, loss: str = "l1", hash_factor: float | None = None, steps: int = 700,
                     part: float = 0.4, shift: float = 0.6, points: int = 12000, frames: int = 47,
                     target: str = "displacement", ramp: float = 0.0, seed: int = 0) -> dict:
    """The fit described in the module docstring. Returns {"part_points", "learned" (the part's mean dX_x at
    t = 0.9), "ratio" (learned / shift), "static_max" (largest |dX| of a static point at t = 0.9), "time_s"}."""
    if loss not in ("l1", "l2"):
        raise ValueError(f"fit_local_motion: loss must be 'l1' or 'l2', got {loss!r}")
    if target not in ("displacement", "velocity"):
        raise ValueError(f"fit_local_motion: target must be 'displacement' or 'velocity', got {target!r}")
    if not 0.0 <= ramp <= 0.9 or frames < 2:
        raise ValueError(f"fit_local_motion: ramp must lie in [0, 0.9] and frames >= 2; got {ramp}, {frames}")
    spec = dataclasses.replace(deform_spec_from_config(cfg, BOX), anchor=0.0)
    rng = np.random.default_rng(seed)
    x = jnp.asarray(rng.uniform(-1.2, 1.2, (points, 3)), jnp.float32)
    on = np.all(np.abs(np.asarray(x) - CENTRE) < part, axis=-1)
    times = np.linspace(0.0, 1.0, frames)
    t = cfg.train
    hf = t.lr_hash_factor if hash_factor is None else float(hash_factor)
    params = deform_init(jax.random.key(seed), spec)
    labels = {k: jax.tree_util.tree_map(lambda _, k=k: "hash" if k == "grid" else "field", v)
              for k, v in params.items()}
    tx = optax.multi_transform({
        "field": optax.adam(exp_decay(t.lr_deform, t.lr_deform_final, steps), eps=1e-15),
        "hash": optax.adam(exp_decay(t.lr_deform * hf, t.lr_deform_final * hf, steps), eps=1e-15),
    }, labels)
    state = tx.init(params)
    part_w = jnp.asarray(on, jnp.float32)[:, None]
    unit = jnp.asarray([shift, 0.0, 0.0], jnp.float32)
    dt = float(times[1] - times[0])

    def moved(tt):  # the part's share s(t) of the shift
        if ramp > 0:
            return jnp.clip((tt - 0.5 + 0.5 * ramp) / ramp, 0.0, 1.0)
        return jnp.where(tt > 0.5, 1.0, 0.0)

    def residual(p, tt):
        if target == "displacement":
            return deform_apply(spec, p, x, tt)[0] - part_w * moved(tt) * unit
        step_dx = deform_apply(spec, p, x, tt)[0] - deform_apply(spec, p, x, tt - dt)[0]
        return step_dx - part_w * (moved(tt) - moved(tt - dt)) * unit

    @jax.jit
    def step(params, state, tt):
        def objective(p):
            r = residual(p, tt)
            return jnp.mean(jnp.sum(jnp.abs(r), -1) if loss == "l1" else jnp.sum(r * r, -1))

        g = jax.grad(objective)(params)
        u, state = tx.update(g, state, params)
        return optax.apply_updates(params, u), state

    first = 0 if target == "displacement" else 1  # a velocity needs the previous training time
    t0 = time.perf_counter()
    for _ in range(int(steps)):
        params, state = step(params, state, jnp.float32(times[rng.integers(first, frames)]))
    dx = np.asarray(deform_apply(spec, params, x, jnp.float32(0.9))[0])
    learned = float(dx[on, 0].mean()) if on.any() else float("nan")
    return {"part_points": int(on.sum()), "learned": learned, "ratio": learned / shift,
            "static_max": float(np.abs(dx[~on]).max()) if (~on).any() else 0.0, "time_s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench field", description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(EXPERIMENTS / "family.toml"),
                   help="named configuration (default: %(default)s)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a setting (repeatable)")
    p.add_argument("--losses", default="l1,l2", help="residual losses to compare (default: %(default)s)")
    p.add_argument("--hash-factors", default="", help="hash-table rate factors to compare (default: the config's)")
    p.add_argument("--steps", type=int, default=700, help="Adam steps (default: %(default)s)")
    p.add_argument("--part", type=float, default=0.4, help="half-size of the moving cube (default: %(default)s)")
    p.add_argument("--target", choices=("displacement", "velocity"), default="displacement",
                   help="fit the displacement from t = 0 or the step between consecutive times (default: %(default)s)")
    p.add_argument("--ramp", type=float, default=0.0,
                   help="the part moves linearly over this time span around 0.5 (default: %(default)s, a step)")
    p.add_argument("--json", default=None, help="also write the rows to this file")
    args = p.parse_args(argv)
    cfg = load_config(args.config, args.overrides)
    factors = [float(f) for f in args.hash_factors.split(",") if f.strip()] or [None]
    rows = []
    print(f"{'loss':>5} {'hash x':>7} {'part pts':>8} {'learned':>8} {'ratio':>6} {'static max':>10} {'time s':>7}")
    for loss in [s.strip() for s in args.losses.split(",") if s.strip()]:
        for hf in factors:
            r = fit_local_motion(cfg, loss=loss, hash_factor=hf, steps=args.steps, part=args.part, target=args.target,
                                 ramp=args.ramp)
            r.update(loss=loss, hash_factor=cfg.train.lr_hash_factor if hf is None else hf, target=args.target,
                     ramp=args.ramp)
            rows.append(r)
            print(f"{loss:>5} {r['hash_factor']:7.0f} {r['part_points']:8d} {r['learned']:8.3f} {r['ratio']:6.2f} "
                  f"{r['static_max']:10.3f} {r['time_s']:7.1f}", flush=True)
    if args.json:
        atomic_write(Path(args.json), lambda f: f.write(json.dumps(
            {"rows": rows, "command": "fgjax bench field " + " ".join(argv if argv is not None else sys.argv[2:])},
            indent=1).encode()))
    return 0
