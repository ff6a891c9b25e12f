"""``fgjax bench flow``: run time and end-point error of the flow derivatives across motion sizes.

A random Gaussian scene (float32) is rendered from camera 0; camera 1 = camera 0 moved by the twist
``s * base`` for each motion size s. Truth is ``reprojection_flow`` of the rendered expected depth. Rows:

- ``motion_field`` (first order, expected depth) and ``motion_field`` at the composited inverse depth;
- the isotropic and anisotropic dynamic Gaussian flow maps of the equivalent object motion (every
  Gaussian moved by c2w0 c2w1^-1, seen from camera 0: the same image motion as the camera moving);

EPE is the mean end-point error in pixels over fully covered pixels (alpha > 0.99) where the truth is
valid. Timings are medians over ``--repeats`` runs after compilation (``jax.jit``, ``block_until_ready``),
for the pixel paths at each ``--resolutions`` entry and for the Gaussian paths at the scene resolution.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from fgjax import flow as fl
from fgjax import geometry as g
from fgjax.render.api import rasterization

BASE_TWIST = (0.002, -0.003, 0.0015, 0.012, 0.006, 0.009)  # [omega (rad), v (scene units)] per unit s


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    jax.block_until_ready(fn())  # compile + warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def _scene(n: int, width: int, height: int, seed: int):
    """Random Gaussians 2-5 units in front of an identity-ish camera, covering the image."""
    rng = np.random.default_rng(seed)
    f = 0.9 * width
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], np.float32)
    z = rng.uniform(2.0, 5.0, n)
    x = rng.uniform(-0.65, 0.65, n) * z * width / (2 * f) * 2
    y = rng.uniform(-0.65, 0.65, n) * z * height / (2 * f) * 2
    c2w0 = np.asarray(g.se3_exp(jnp.array([0.05, -0.1, 0.02, 0.1, 0.0, -0.2])), np.float32)
    p_cam = np.stack([x, y, z], -1)
    means = p_cam @ c2w0[:3, :3].T + c2w0[:3, 3]
    quats = rng.normal(size=(n, 4))
    mean_spacing = np.sqrt((1.3 * z.mean() * width / f) * (1.3 * z.mean() * height / f) / n)
    scales = rng.uniform(0.5, 1.5, (n, 3)) * mean_spacing
    opac = rng.uniform(0.6, 0.95, n)
    cast = lambda a: jnp.asarray(a, jnp.float32)
    return cast(means), cast(quats), cast(scales), cast(opac), cast(c2w0), cast(K)


def _rotate_quats(rot, quats):
    return g.rotmat_to_quat(rot @ g.quat_to_rotmat(quats))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench flow", description=__doc__.split("\n")[0])
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--n-gaussians", type=int, default=4000)
    p.add_argument("--motions", default="1,2,4,8,16,32,64", help="comma-separated motion sizes s")
    p.add_argument("--resolutions", default="320x240,640x480,1280x960", help="pixel-path timing resolutions WxH")
    p.add_argument("--repeats", type=int, default=21)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    w, h = args.width, args.height
    means, quats, scales, opac, c2w0, K = _scene(args.n_gaussians, w, h, args.seed)
    view0 = g.se3_inverse(c2w0)
    img, alpha, info = rasterization(means, quats, scales, opac, jnp.ones((means.shape[0], 1)), view0, K, w, h)
    cap = int(info["capacity"])
    depth = info["depth"]
    covered = alpha > 0.99
    base = jnp.asarray(BASE_TWIST, jnp.float32)
    print(f"# fgjax bench flow: {w}x{h}, {means.shape[0]} Gaussians, {float(covered.mean()) * 100:.0f}% of pixels "
          f"fully covered, capacity {cap}, backend {jax.default_backend()}, float32")

    # Every array is an argument (nothing closed over), so XLA cannot constant-fold the scene: the timings
    # are those of a training step, where the Gaussians are traced values.
    scene = (means, quats, scales, opac)

    @jax.jit
    def exact(depth, K, c2w0, c2w1):
        return fl.reprojection_flow(depth, K, c2w0, c2w1)

    @jax.jit
    def first_order(depth, K, c2w0, c2w1):
        v, om = fl.camera_velocity(c2w0, c2w1)
        return fl.motion_field(fl.pixel_centers(*depth.shape, dtype=depth.dtype), depth, K, v, om)

    @jax.jit
    def first_order_rho(rho, K, c2w0, c2w1):
        v, om = fl.camera_velocity(c2w0, c2w1)
        return fl.motion_field_inv_depth(fl.pixel_centers(*rho.shape, dtype=rho.dtype), rho, K, v, om)

    def moved(means, quats, c2w0, c2w1):
        gmat = c2w0 @ g.se3_inverse(c2w1)  # world motion equivalent to the camera motion
        return means @ gmat[:3, :3].T + gmat[None, :3, 3], _rotate_quats(gmat[:3, :3], quats)

    @jax.jit
    def gs_iso(scene, K, c2w0, c2w1):
        means, quats, scales, opac = scene
        m1, _ = moved(means, quats, c2w0, c2w1)
        view0 = g.se3_inverse(c2w0)
        return fl.dynamic_gaussian_flow(means, quats, scales, opac, m1, view0, K, w, h, capacity=cap)

    @jax.jit
    def gs_aniso(scene, K, c2w0, c2w1):
        means, quats, scales, opac = scene
        m1, q1 = moved(means, quats, c2w0, c2w1)
        view0 = g.se3_inverse(c2w0)
        return fl.dynamic_gaussian_flow(
            means, quats, scales, opac, m1, view0, K, w, h, anisotropic=True, quats1=q1, capacity=cap
        )

    rows = []
    for s in (float(x) for x in args.motions.split(",")):
        xi = s * base
        c2w1 = c2w0 @ g.se3_exp(xi)
        truth, valid = exact(depth, K, c2w0, c2w1)
        mask = covered & valid
        iso = gs_iso(scene, K, c2w0, c2w1)
        aniso = gs_aniso(scene, K, c2w0, c2w1)
        if bool(iso.overflow) or bool(aniso.overflow):
            print(f"fgjax bench flow: rasterizer capacity {cap} overflowed at s = {s}", file=sys.stderr)
            return 1
        n = jnp.maximum(mask.sum(), 1)

        def epe(f, truth=truth, mask=mask, n=n):
            return float(jnp.sum(jnp.where(mask, jnp.linalg.norm(f - truth, axis=-1), 0.0)) / n)

        rows.append(
            (
                s,
                float(jnp.degrees(jnp.linalg.norm(xi[:3]))),
                float(jnp.linalg.norm(xi[3:])),
                float(jnp.sum(jnp.where(mask, jnp.linalg.norm(truth, axis=-1), 0.0)) / n),
                epe(first_order(depth, K, c2w0, c2w1)),
                epe(first_order_rho(iso.inv_depth, K, c2w0, c2w1)),
                epe(iso.flow),
                epe(aniso.flow),
            )
        )
    print("\n## End-point error against reprojection_flow (mean px over fully covered pixels)\n")
    print("| s | rotation (deg) | translation | mean flow (px) | motion_field, expected depth | "
          "motion_field, composited 1/Z | Gaussian flow, isotropic | Gaussian flow, anisotropic |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r[0]:g} | {r[1]:.3f} | {r[2]:.4f} | {r[3]:.2f} | {r[4]:.4f} | "
              f"{r[5]:.4f} | {r[6]:.4f} | {r[7]:.4f} |")

    print(f"\n## Run time (median of {args.repeats} after compile, ms)\n")
    print("| path | resolution | ms |")
    print("|---|---|---:|")
    c2w1 = c2w0 @ g.se3_exp(base)
    for res in args.resolutions.split(","):
        rw, rh = (int(x) for x in res.lower().split("x"))
        d = jax.image.resize(depth, (rh, rw), "nearest")
        kk = K.at[:2].multiply(jnp.array([rw / w, rh / h], jnp.float32)[:, None])
        t_ex = _median_ms(lambda: exact(d, kk, c2w0, c2w1), args.repeats)
        t_fo = _median_ms(lambda: first_order(d, kk, c2w0, c2w1), args.repeats)
        print(f"| reprojection_flow (exact) | {rw}x{rh} | {t_ex:.3f} |")
        print(f"| camera_velocity + motion_field (first order) | {rw}x{rh} | {t_fo:.3f} |")
    t_iso = _median_ms(lambda: gs_iso(scene, K, c2w0, c2w1), args.repeats)
    t_aniso = _median_ms(lambda: gs_aniso(scene, K, c2w0, c2w1), args.repeats)
    print(f"| dynamic Gaussian flow, isotropic (render, 3 channels) | {w}x{h} | {t_iso:.3f} |")
    print(f"| dynamic Gaussian flow, anisotropic (render, 7 channels) | {w}x{h} | {t_aniso:.3f} |")

    p_cam = means @ view0[:3, :3].T + view0[None, :3, 3]
    v, om = fl.camera_velocity(c2w0, c2w1)
    zeros = jnp.zeros_like(p_cam)
    analytic = jax.jit(lambda p, z, K, v, om: fl.gaussian_image_velocity(p, z, K, v, om))
    jvp = jax.jit(
        lambda x, K, c2w0, xi: fl.gaussian_image_velocity_jvp(lambda t: x, lambda t: c2w0 @ g.se3_exp(t * xi),
                                                              K, 0.0)[1]
    )
    n = means.shape[0]
    t_an = _median_ms(lambda: analytic(p_cam, zeros, K, v, om), args.repeats)
    t_jvp = _median_ms(lambda: jvp(means, K, c2w0, base), args.repeats)
    print(f"| per-Gaussian image velocity, analytic | N={n} | {t_an:.3f} |")
    print(f"| per-Gaussian image velocity, jax.jvp | N={n} | {t_jvp:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
