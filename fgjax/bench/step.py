"""``fgjax bench step``: one stage-1 step and one tile-restricted render, each two ways, time beside difference.

1. The stage-1 training step with the batch's cameras looped (the one-device path) and vmapped (the
   data-parallel path). Under ``jax.vmap`` the compositor's ``lax.cond`` skips of unused chunk batches
   become selects that compute every batch. Printed: median ms of each, their ratio, and the largest
   difference of loss and updated parameters between them.
2. ``fgjax.rasterization`` value and gradient with all tiles against ``active=`` a central window's
   Gaussians (the photometric tracker's case: only one part moves). Printed: median ms of each, their
   ratio, and the largest difference of the active Gaussians' gradients (exact by construction).

Both forms of each are timed alternately in one process, so the machine's load changes hit both alike.
With ``--run RUN --data DATA`` the Gaussians of a trained stage-1 run are used (at frame ``--frame``);
otherwise the default synthetic scene is generated into a temporary folder and stage 1's initial state
is drawn with ``--gaussians`` random points.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from fgjax.config import load_config
from fgjax.data.loaders import load_scene
from fgjax.gaussians import Gaussians, knn_graph
from fgjax.method import stage1
from fgjax.models.model import render_params
from fgjax.synth import SynthConfig, generate
from fgjax.train.optim import OptimSpec, make_optimizer

__all__ = ["main"]


def _copy(tree):
    return jax.tree_util.tree_map(lambda a: jnp.array(a, copy=True), tree)


def _alternate(fns: dict, repeats: int) -> dict[str, float]:
    """Median wall seconds of each fn() (compiled first), the fns interleaved repeat by repeat."""
    for f in fns.values():
        jax.block_until_ready(f())
    ts: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, f in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f())
            ts[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in ts.items()}


def _max_diff(a, b) -> float:
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    return max((float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)), initial=0.0))
                for x, y in zip(la, lb)), default=0.0)


def _load(args):
    """(cfg, state, spec, scene, capacity, tmp) from a run or a fresh initial state on the synthetic scene."""
    tmp = None
    if args.run:
        if not args.data:
            raise SystemExit("fgjax bench step: --run needs --data (the run's dataset folder)")
        cfg, state, spec, meta = stage1.load_run(args.run)
        data = Path(args.data)
    else:
        tmp = tempfile.TemporaryDirectory()
        data = Path(tmp.name) / "synth"
        generate(SynthConfig(), data)
        cfg = load_config(args.config, ["model.init=random", f"model.init_points={args.gaussians}",
                                        f"model.capacity={args.gaussians}", *args.overrides])
    scene = load_scene(data, "train", downscale=cfg.data.downscale)
    if not args.run:
        state, spec, _ = stage1.initial_state(cfg, scene, log=lambda *_: None)
    f32 = lambda x: np.asarray(x, np.float32)
    cap = stage1.compute_capacity(state.params, state.densify.alive, f32(scene.viewmats), f32(scene.Ks),
                                   scene.width, scene.height, cfg.train.tile_size, cfg.train.capacity_margin)
    return cfg, state, spec, scene, cap, tmp


def bench_step(cfg, state, spec, scene, cap, frames, repeats) -> dict:
    t = cfg.train
    ospec = OptimSpec(steps=t.steps, warmup_steps=t.warmup_steps)
    num_sh = state.params["gaussians"].sh.shape[1]
    sh_mask = stage1.active_sh_mask(cfg.model.sh_degree, cfg.model.sh_degree)
    nbr = knn_graph(state.params["gaussians"].means, state.densify.alive, t.rigid_neighbours) if t.rigid_weight > 0 \
        else None
    i = np.asarray(frames)
    f32 = lambda x: np.asarray(x, np.float32)
    batch = (sh_mask, f32(scene.images[i]), f32(scene.viewmats[i]), f32(scene.Ks[i]), f32(scene.times[i]),
             i.astype(np.int32))
    opt0 = make_optimizer(ospec, num_sh).init(state.params)
    steps, outs = {}, {}
    for name, vm in (("looped", False), ("vmapped", True)):
        ss = stage1.StepSpec(spec, cfg.model.sh_degree, scene.width, scene.height, cap, t.tile_size, t.lambda_dssim,
                             t.scale_reg, t.scale_reg_max, "pose" in state.params, rigid_weight=t.rigid_weight,
                             rigid_cap=t.rigid_cap, vmap_cameras=vm)
        fn = stage1.make_step(ss, ospec, num_sh, tuple(cfg.model.background))
        steps[name] = (lambda fn=fn: fn(_copy(state.params), _copy(opt0), _copy(state.densify), *batch, nbr=nbr))
        outs[name] = steps[name]()
    med = _alternate(steps, repeats)
    (p0, _, d0, l0, _, b0), (p1, _, d1, l1, _, b1) = outs["looped"], outs["vmapped"]
    return {"gaussians": int(jnp.sum(state.densify.alive)), "capacity": cap, "batch": len(i),
            "looped_ms": 1e3 * med["looped"], "vmapped_ms": 1e3 * med["vmapped"],
            "ratio": med["vmapped"] / med["looped"], "loss_diff": abs(float(l0) - float(l1)),
            "param_diff": _max_diff((p0, d0), (p1, d1)), "skipped": bool(b0) or bool(b1)}


def bench_active(cfg, state, spec, scene, cap, frame, window, repeats) -> dict:
    alive = state.densify.alive
    vm = jnp.asarray(scene.viewmats[frame], jnp.float32)
    K = jnp.asarray(scene.Ks[frame], jnp.float32)
    tt = jnp.float32(scene.times[frame])
    w, h = scene.width, scene.height
    bg = jnp.asarray(cfg.model.background, jnp.float32)
    target = jnp.asarray(scene.images[frame], jnp.float32)
    # active: the live Gaussians whose centre projects into a central window of `window` of the image area
    g = state.params["gaussians"]
    cam = g.means @ vm[:3, :3].T + vm[:3, 3]
    uv = cam[:, :2] / jnp.maximum(cam[:, 2:], 1e-6) @ K[:2, :2].T + K[:2, 2]
    half = 0.5 * np.sqrt(window) * np.array([w, h])
    inside = jnp.all(jnp.abs(uv - jnp.array([w / 2, h / 2])) <= half, axis=-1) & (cam[:, 2] > 0)
    active = alive & inside

    def loss(params, means, sh, act):
        p = {**params, "gaussians": Gaussians(means, g.log_scales, g.quats, g.opacity_logits, sh)}
        img, _, _, _ = render_params(p, alive, vm, K, tt, spec=spec, sh_degree=cfg.model.sh_degree, width=w, height=h,
                                     background=bg, capacity=cap, tile_size=cfg.train.tile_size, active=act)
        return jnp.mean(jnp.abs(img - target))

    # The parameters are arguments, not constants closed over: with jaxlib 0.10.2 on the CPU, a jitted
    # deform_apply that closes over the hash-grid parameters returns garbage (1e8-1e30).
    full = jax.jit(jax.value_and_grad(lambda prm, m, s: loss(prm, m, s, None), argnums=(1, 2)))
    part = jax.jit(jax.value_and_grad(lambda prm, m, s, act: loss(prm, m, s, act), argnums=(1, 2)))
    prm = state.params
    med = _alternate({"all": lambda: full(prm, g.means, g.sh), "active": lambda: part(prm, g.means, g.sh, active)},
                     repeats)
    (_, gf), (_, ga) = full(prm, g.means, g.sh), part(prm, g.means, g.sh, active)
    a = np.asarray(active)
    diff = max(float(np.abs(np.asarray(x)[a] - np.asarray(y)[a]).max(initial=0.0)) for x, y in zip(gf, ga))
    scale = max(float(np.abs(np.asarray(x)[a]).max(initial=0.0)) for x in gf)
    return {"active": int(a.sum()), "window": window, "all_ms": 1e3 * med["all"], "active_ms": 1e3 * med["active"],
            "ratio": med["all"] / med["active"], "grad_diff": diff, "grad_scale": scale}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench step", description=__doc__.splitlines()[0])
    p.add_argument("--run", default=None, help="a trained stage-1 run (default: a fresh initial state)")
    p.add_argument("--data", default=None, help="the run's dataset folder (needed with --run)")
    p.add_argument("--config", default="experiments/articulated.toml", help="config without --run")
    p.add_argument("--gaussians", type=int, default=20000, help="random initial Gaussians without --run")
    p.add_argument("--frames", default="45", help="comma list of training frames of one step's batch")
    p.add_argument("--window", type=float, default=0.25, help="image-area fraction of the active window")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--set", dest="overrides", action="append", default=[], help="config overrides without --run")
    p.add_argument("--json", default=None, help="also write the results to this file")
    args = p.parse_args(argv)
    cfg, state, spec, scene, cap, tmp = _load(args)
    frames = [int(f) % scene.num_frames for f in args.frames.split(",") if f.strip()]
    if state.static:
        spec = None
    s = bench_step(cfg, state, spec, scene, cap, frames, args.repeats)
    print(f"stage-1 step, {s['gaussians']} Gaussians, batch {s['batch']}, capacity {s['capacity']}: looped "
          f"{s['looped_ms']:.1f} ms, vmapped {s['vmapped_ms']:.1f} ms (x{s['ratio']:.2f}); |loss diff| "
          f"{s['loss_diff']:.2e}, "
          f"max param diff {s['param_diff']:.2e}" + (" (a step was skipped)" if s["skipped"] else ""),
          flush=True)
    a = bench_active(cfg, state, spec, scene, cap, frames[0], args.window, args.repeats)
    print(f"render value+grad, {a['active']} active Gaussians in {a['window']:.0%} of the image: all tiles "
          f"{a['all_ms']:.1f} ms, active tiles {a['active_ms']:.1f} ms (x{a['ratio']:.2f}); max grad diff of the "
          f"active {a['grad_diff']:.2e} (largest grad {a['grad_scale']:.2e})")
    if args.json:
        Path(args.json).write_text(json.dumps({"step": s, "active": a}, indent=1))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
