"""``fgjax bench raster``: tile rasterizer run time, memory and error against the dense reference.

Scenes: gsplat's garden test asset (../shared/data/garden, camera 0 at 648x420, gsplat's test
recipe: means cropped to [-2, 2]^3, random unit quats, scales U[1e-4, 0.02], opacities U[0, 1],
colours from the file) and a soft random scene. For each tile size: compile time, forward median,
forward+backward median, peak memory (process RSS high-water mark), intersections, and error
against the float64 dense reference on a crop (the dense reference is O(H W N)).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import resource
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from fgjax.render import api, tiles
from fgjax.render import composite as comp
from fgjax.render.api import count_intersections, rasterization, round_capacity
from fgjax.render.project import project_gaussians
from fgjax.render.reference import rasterize_dense

DEFAULT_GARDEN = pathlib.Path(__file__).resolve().parents[2].parent / "shared" / "data" / "garden" / "test_garden.npz"


def garden_scene(path, camera: int = 0, scale: float = 1.0, seed: int = 42):
    """gsplat's test recipe on the garden asset; returns float32 args and (width, height)."""
    d = np.load(path)
    m = d["means3d"]
    keep = np.all(np.abs(m) <= 2.0, axis=1)
    m = m[keep]
    n = len(m)
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    s = rng.uniform(1e-4, 0.02, (n, 3))
    o = rng.uniform(0.0, 1.0, n)
    c = d["colors"][keep] / 255.0
    K = np.array(d["Ks"][camera], np.float64)
    w, h = int(d["width"]), int(d["height"])
    if scale != 1.0:
        K[:2] *= scale
        w, h = int(round(w * scale)), int(round(h * scale))
    args = [jnp.asarray(x, jnp.float32) for x in (m, q, s, o, c, d["viewmats"][camera], K)]
    return args, (w, h)


def soft_scene(n: int = 20000, width: int = 320, height: int = 240, seed: int = 0):
    """Large, soft, overlapping Gaussians: many intersections per tile, deep compositing."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-1.5, 1.5, (n, 3)) + [0, 0, 4.0]
    q = rng.normal(size=(n, 4))
    s = np.exp(rng.uniform(-3.5, -1.5, (n, 3)))
    o = rng.uniform(0.05, 0.6, n)
    c = rng.uniform(0, 1, (n, 3))
    K = np.array([[300.0, 0, width / 2], [0, 300.0, height / 2], [0, 0, 1]])
    args = [jnp.asarray(x, jnp.float32) for x in (means, q, s, o, c, np.eye(4), K)]
    return args, (width, height)


def _median_time(fn, repeats, cpu=False):
    """Median wall time of fn() (or process CPU time, all threads, with cpu=True: steadier than
    wall time on a shared, loaded machine)."""
    clock = time.process_time if cpu else time.perf_counter
    ts = []
    for _ in range(repeats):
        t = clock()
        jax.block_until_ready(fn())
        ts.append(clock() - t)
    return statistics.median(ts)


def _peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def crop_scene(args, w, h, x0, y0, cw, ch):
    """Same scene, camera cropped to a cw x ch window at (x0, y0)."""
    K = np.array(args[6])
    K[0, 2] -= x0
    K[1, 2] -= y0
    return list(args[:6]) + [jnp.asarray(K, jnp.float32)], (cw, ch)


def dense_error(args, w, h, tile_size, crop):
    """Max/mean abs error of the tile rasterizer against the float64 dense reference on a crop.

    Only Gaussians whose tile rectangle touches the crop are passed to the (O(H W N)) reference.
    """
    cargs, (cw, ch) = crop_scene(args, w, h, *crop)
    img, _, info = rasterization(*cargs, cw, ch, tile_size=tile_size)
    rect = np.asarray(info["tile_rect"])
    sel = (rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])
    with jax.enable_x64(True):
        a64 = [jnp.asarray(np.asarray(a)[sel], jnp.float64) for a in cargs[:5]]
        a64 += [jnp.asarray(np.asarray(a), jnp.float64) for a in cargs[5:]]
        ref = np.asarray(rasterize_dense(*a64, cw, ch)[0])
    err = np.abs(np.asarray(img, np.float64) - ref)
    return float(err.max()), float(err.mean()), int(sel.sum())


def bench_scene(name, args, w, h, tile_sizes, repeats, crop, check_error=True):
    rows = []
    for ts in tile_sizes:
        need = int(count_intersections(*args[:4], args[5], args[6], width=w, height=h, tile_size=ts))
        cap = round_capacity(need)
        fwd = jax.jit(lambda *a, ts=ts, cap=cap: rasterization(*a, w, h, tile_size=ts, capacity=cap)[0])

        def loss(means, quats, scales, opac, colors, ts=ts, cap=cap):
            img, alpha, _ = rasterization(
                means, quats, scales, opac, colors, args[5], args[6], w, h, tile_size=ts, capacity=cap
            )
            return jnp.sum(img) + jnp.sum(alpha)

        grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3, 4)))
        t = time.perf_counter()
        jax.block_until_ready(fwd(*args))
        compile_fwd = time.perf_counter() - t
        t = time.perf_counter()
        jax.block_until_ready(grad(*args[:5]))
        compile_bwd = time.perf_counter() - t
        t_fwd = _median_time(lambda: fwd(*args), repeats)
        t_bwd = _median_time(lambda: grad(*args[:5]), repeats)
        c_fwd = _median_time(lambda: fwd(*args), repeats, cpu=True)
        c_bwd = _median_time(lambda: grad(*args[:5]), repeats, cpu=True)
        emax, emean, nsel = dense_error(args, w, h, ts, crop) if check_error else (float("nan"),) * 2 + (0,)
        row = dict(scene=name, tile=ts, n=int(args[0].shape[0]), isect=need, compile_s=compile_fwd + compile_bwd,
                   compile_fwd_s=compile_fwd, fwd_s=t_fwd, fwdbwd_s=t_bwd, fwd_cpu_s=c_fwd, fwdbwd_cpu_s=c_bwd,
                   peak_rss_mb=_peak_rss_mb(),
                   err_max=emax, err_mean=emean)
        rows.append(row)
        print(
            f"{name:<8} tile {ts:>2}  N {row['n']:>6}  isect {need:>8}  compile {row['compile_s']:6.1f}s "
            f"(fwd {compile_fwd:5.1f}s)  fwd {t_fwd:6.3f}s [cpu {c_fwd:6.3f}s]  "
            f"fwd+bwd {t_bwd:6.3f}s [cpu {c_bwd:6.3f}s]  peakRSS {row['peak_rss_mb']:7.0f}MB  "
            f"err max {emax:.1e} mean {emean:.1e} (crop {crop[2]}x{crop[3]}, {nsel} Gaussians)",
            flush=True,
        )
    return rows


def breakdown(name, args, w, h, tile_size, repeats, chunk=None, batch=None):
    """Median time of each stage: projection, binning (sort), chunking, compositing fwd / fwd+bwd.

    Also reports the (Gaussian, pixel) pairs evaluated, i.e. chunk slots x tile pixels, the
    quantity the compositor's run time scales with.
    """
    chunk = chunk or api.DEFAULT_CHUNK
    batch = batch or api.DEFAULT_BATCH
    n = int(args[0].shape[0])
    need = int(api.count_intersections(*args[:4], args[5], args[6], width=w, height=h, tile_size=tile_size))
    cap = api.round_capacity(need)
    ntx, nty = -(-w // tile_size), -(-h // tile_size)
    proj_f = jax.jit(lambda m, q, s, o, vm, K: project_gaussians(m, q, s, o, vm, K, w, h))
    rect_f = jax.jit(lambda p: tiles.tile_ranges(p.means2d, p.extent, p.valid, tile_size, w, h))
    bin_f = jax.jit(lambda rect, dep: tiles.bin_gaussians(rect, dep, ntx, nty, cap))
    chunk_f = jax.jit(lambda ids, st: comp.make_chunks(ids, st, n, chunk))
    kw = dict(width=w, height=h, tile_size=tile_size, chunk=chunk, batch=batch)
    comp_f = jax.jit(lambda m2, cn, op, ft, ch: comp.composite(m2, cn, op, ft, ch, **kw))
    grad_f = jax.jit(jax.grad(lambda m2, cn, op, ft, ch: jnp.sum(comp.composite(m2, cn, op, ft, ch, **kw)),
                              argnums=(0, 1, 2, 3)))
    p = proj_f(*args[:4], args[5], args[6])
    rect = rect_f(p)
    b = bin_f(rect, p.depths)
    ch = chunk_f(b.isect_ids, b.tile_start)
    feats = jnp.concatenate([args[4], jnp.ones((n, 1), jnp.float32)], -1)
    opac = jnp.where(p.valid, args[3], 0.0)
    stages = {
        "project": lambda: proj_f(*args[:4], args[5], args[6]),
        "tile ranges": lambda: rect_f(p),
        "bin+sort": lambda: bin_f(rect, p.depths),
        "chunks": lambda: chunk_f(b.isect_ids, b.tile_start),
        "composite fwd": lambda: comp_f(p.means2d, p.conics, opac, feats, ch),
        "composite fwd+bwd": lambda: grad_f(p.means2d, p.conics, opac, feats, ch),
    }
    for f in stages.values():
        jax.block_until_ready(f())
    times = {k: _median_time(f, repeats, cpu=True) for k, f in stages.items()}
    pairs = int(ch.n_used) * chunk * tile_size * tile_size
    print(f"{name} breakdown (tile {tile_size}, chunk {chunk}, batch {batch}): isect {need}, "
          f"chunks used {int(ch.n_used)}/{ch.ids.shape[0]}, (Gaussian, pixel) pairs evaluated {pairs / 1e6:.1f}M")
    for k, t in times.items():
        extra = f"   {t / pairs * 1e9:5.2f} ns/pair" if k.startswith("composite") else ""
        print(f"  {k:<18} {t * 1e3:8.1f} ms cpu{extra}")
    return times, pairs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench raster", description=__doc__.split("\n\n")[0])
    p.add_argument("--garden", type=pathlib.Path, default=DEFAULT_GARDEN, help="path of test_garden.npz")
    p.add_argument("--tiles", default="8,16,32", help="comma-separated tile sizes")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats (median reported)")
    p.add_argument("--scale", type=float, default=1.0, help="image scale for the garden scene")
    p.add_argument("--scenes", default="garden,soft", help="comma-separated: garden, soft")
    p.add_argument("--no-error", action="store_true", help="skip the dense-reference error (slow part)")
    p.add_argument("--breakdown", action="store_true", help="also time each stage of the garden render")
    a = p.parse_args(argv)
    tiles = [int(t) for t in a.tiles.split(",")]
    print(f"# fgjax bench raster  jax {jax.__version__}  backend {jax.default_backend()}  "
          f"devices {jax.devices()}  cpu {platform.processor() or platform.machine()}  cores {_cores()}", flush=True)
    scenes = a.scenes.split(",")
    if "garden" in scenes:
        if not a.garden.exists():
            print(f"fgjax bench raster: garden scene not found at {a.garden}; pass --garden PATH", file=sys.stderr)
            return 2
        args, (w, h) = garden_scene(a.garden, 0, a.scale)
        bench_scene("garden", args, w, h, tiles, a.repeats, (w // 2 - 40, h // 2 - 30, 80, 60), not a.no_error)
        if a.breakdown:
            for ts in tiles:
                breakdown("garden", args, w, h, ts, a.repeats)
    if "soft" in scenes:
        args, (w, h) = soft_scene()
        bench_scene("soft", args, w, h, tiles, a.repeats, (120, 90, 80, 60), not a.no_error)
    return 0


def _cores():
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
