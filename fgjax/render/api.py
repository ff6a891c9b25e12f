"""Public rendering API: ``rasterization`` (tile rasterizer) and ``spherical_harmonics``.

Conventions (DESIGN.md section 2): OpenCV camera (x right, y down, z forward); ``viewmat`` is
world-to-camera 4x4; ``K`` 3x3 with pixel (j, i) centred at (j + 0.5, i + 0.5); quaternions wxyz of
any norm; scales > 0 and opacities in [0, 1] are activated values.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from fgjax.render.composite import composite, make_chunks, restrict_tiles
from fgjax.render.project import project_gaussians
from fgjax.render.sh import spherical_harmonics as spherical_harmonics  # re-export
from fgjax.render.tiles import bin_gaussians, tile_ranges

__all__ = ["rasterization", "spherical_harmonics", "count_intersections", "gaussian_weights", "round_capacity"]

# Speed-only knobs, tuned with `fgjax bench raster` on the garden scene (docs/benchmarks.md):
# 8-pixel tiles evaluate far fewer (Gaussian, pixel) pairs than 16 for small splats.
DEFAULT_TILE = 8
DEFAULT_CHUNK = 64
DEFAULT_BATCH = 64


def _is_traced(*xs) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


def _check_shapes(means, quats, scales, opacities, colors, viewmat, K, width, height, background, tile_size):
    """Static contract checks: raise ValueError naming the argument and its shape (trace time)."""
    if means.ndim != 2 or means.shape[-1] != 3:
        raise ValueError(f"rasterization: means must have shape [N, 3], got {means.shape}")
    n = means.shape[0]
    expect = {"quats": (quats, (n, 4)), "scales": (scales, (n, 3)), "opacities": (opacities, (n,))}
    for name, (x, shape) in expect.items():
        if x.shape != shape:
            raise ValueError(f"rasterization: {name} must have shape {list(shape)} (N={n}), got {list(x.shape)}")
    if colors.ndim != 2 or colors.shape[0] != n or colors.shape[1] < 1:
        raise ValueError(f"rasterization: colors must have shape [N, C] with N={n}, C>=1, got {list(colors.shape)}")
    if viewmat.shape != (4, 4):
        raise ValueError(f"rasterization: viewmat must be a 4x4 world-to-camera matrix, got {list(viewmat.shape)}")
    if K.shape != (3, 3):
        raise ValueError(f"rasterization: K must be 3x3, got {list(K.shape)}")
    for name, v in (("width", width), ("height", height), ("tile_size", tile_size)):
        if not isinstance(v, (int, np.integer)) or v <= 0:
            raise ValueError(f"rasterization: {name} must be a positive int (static), got {v!r}")
    if background is not None and background.shape != (colors.shape[1],):
        raise ValueError(
            f"rasterization: background must have shape [C]=[{colors.shape[1]}], got {list(background.shape)}"
        )


def _as_float(x, dtype):
    return jnp.asarray(x).astype(dtype)


def _project_and_rect(means, quats, scales, opacities, viewmat, K, width, height, near_plane, tile_size):
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height, near_plane)
    rect = tile_ranges(proj.means2d, proj.extent, proj.valid, tile_size, width, height)
    return proj, rect


@functools.partial(jax.jit, static_argnames=("width", "height", "near_plane", "tile_size"))
def count_intersections(
    means, quats, scales, opacities, viewmat, K, *, width, height, near_plane=0.01, tile_size=DEFAULT_TILE
):
    """Number of (Gaussian, tile) intersections a render needs: the minimal ``capacity``."""
    _, rect = _project_and_rect(means, quats, scales, opacities, viewmat, K, width, height, near_plane, tile_size)
    return jnp.sum((rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1]))


def default_capacity(n: int, width: int, height: int, tile_size: int) -> int:
    """Static capacity used when none is given under jit/vmap (a heuristic: check info["overflow"]).

    16 tiles per Gaussian at tile size 8 (scaled by the tile area), plus one per tile. Training
    loops should size it from ``count_intersections`` over their cameras instead.
    """
    n_tiles = -(-width // tile_size) * -(-height // tile_size)
    per = max(2, math.ceil(16 * (8 / tile_size) ** 2))
    return per * max(n, 1) + n_tiles


def round_capacity(x: int) -> int:
    """Round up to 1.25x-spaced buckets so that nearby counts share a compiled program."""
    x = max(int(x), 1024)
    b = 2 ** math.floor(math.log2(x))
    for f in (1.0, 1.25, 1.5, 1.75, 2.0):
        if x <= b * f:
            return int(b * f)
    return 2 * b




def _empty_render(means, colors, background, width, height, render_depth):
    dtype, C = colors.dtype, colors.shape[1]
    image = jnp.zeros((height, width, C), dtype)
    if background is not None:
        image = image + background
    z = jnp.zeros((0,), dtype)
    info: dict[str, Any] = {
        "means2d": jnp.zeros((0, 2), dtype), "depths": z, "conics": jnp.zeros((0, 3), dtype),
        "cov2d": jnp.zeros((0, 3), dtype), "extent": jnp.zeros((0, 2), dtype),
        "radii": jnp.zeros((0, 2), jnp.int32), "valid": jnp.zeros((0,), bool),
        "tile_rect": jnp.zeros((0, 4), jnp.int32), "n_isect": jnp.zeros((), jnp.int32),
        "n_composited": jnp.zeros((), jnp.int32),
        "overflow": jnp.zeros((), bool),
    }
    if render_depth:
        info["depth"] = jnp.zeros((height, width), dtype)
        info["depth_acc"] = jnp.zeros((height, width), dtype)
    return image, jnp.zeros((height, width), dtype), info


@functools.partial(
    jax.jit,
    static_argnames=("width", "height", "near_plane", "tile_size", "capacity", "chunk", "batch", "render_depth"),
)
def _rasterize(
    means, quats, scales, opacities, colors, viewmat, K, background, active, *,
    width, height, near_plane, tile_size, capacity, chunk, batch, render_depth,
):
    n, C = colors.shape
    dtype = colors.dtype
    if n == 0:  # static: an empty scene is the background (and costs nothing)
        image, alpha, info = _empty_render(means, colors, background, width, height, render_depth)
        if active is not None:
            info["tile_on"] = jnp.zeros((-(-height // tile_size), -(-width // tile_size)), bool)
        return image, alpha, info
    proj, rect = _project_and_rect(means, quats, scales, opacities, viewmat, K, width, height, near_plane, tile_size)
    ntx = -(-width // tile_size)
    nty = -(-height // tile_size)
    r2 = 2.0 * jnp.log(jnp.maximum(jnp.where(proj.valid, opacities, 0.0) * 255.0, 1.0))  # alpha >= 1/255 <=> q <= r2
    ellipse = jax.lax.stop_gradient((proj.means2d, proj.conics, r2))
    bins = bin_gaussians(rect, proj.depths, ntx, nty, capacity, ellipse=ellipse, tile_size=tile_size)
    chunks = make_chunks(bins.isect_ids, bins.tile_start, n, chunk)
    if active is not None:
        chunks = restrict_tiles(chunks, active, ntx * nty)
    extra = [jnp.ones((n, 1), dtype)]  # alpha channel
    if render_depth:
        extra.append(jnp.where(proj.valid, proj.depths, 0.0)[:, None])
    feats = jnp.concatenate([colors] + extra, axis=-1)  # [N, C + 1 (+1)]
    opac = jnp.where(proj.valid, opacities, 0.0)
    acc = composite(
        proj.means2d, proj.conics, opac, feats, chunks,
        width=width, height=height, tile_size=tile_size, chunk=chunk, batch=batch,
    )  # [H, W, C + extras]
    alpha = acc[..., C]
    image = acc[..., :C]
    if background is not None:
        image = image + (1.0 - alpha)[..., None] * background
    info: dict[str, Any] = {
        "means2d": proj.means2d,
        "depths": proj.depths,
        "conics": proj.conics,
        "cov2d": proj.cov2d,
        "extent": proj.extent,
        "radii": jnp.where(proj.valid[:, None], jnp.ceil(proj.extent), 0).astype(jnp.int32),
        "valid": proj.valid,
        "tile_rect": rect,
        "n_isect": bins.n_isect,
        "n_composited": bins.n_composited,
        "overflow": bins.overflow,
    }
    if active is not None:
        info["tile_on"] = chunks.tile_on.reshape(nty, ntx)
    if render_depth:
        has = alpha > 1e-6
        info["depth"] = jnp.where(has, acc[..., C + 1] / jnp.where(has, alpha, 1.0), 0.0)  # expected depth
        info["depth_acc"] = acc[..., C + 1]  # sum_i T_i alpha_i z_i
    return image, alpha, info


def rasterization(
    means: Float[ArrayLike, "N 3"],
    quats: Float[ArrayLike, "N 4"],
    scales: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, " N"],
    colors: Float[ArrayLike, "N C"],
    viewmat: Float[ArrayLike, "4 4"],
    K: Float[ArrayLike, "3 3"],
    width: int,
    height: int,
    *,
    background: Float[ArrayLike, " C"] | None = None,
    near_plane: float = 0.01,
    tile_size: int = DEFAULT_TILE,
    capacity: int | None = None,
    chunk: int = DEFAULT_CHUNK,
    batch: int = DEFAULT_BATCH,
    render_depth: bool = True,
    active: Bool[ArrayLike, " N"] | None = None,
) -> tuple[Float[Array, "H W C"], Float[Array, "H W"], dict[str, Any]]:
    """Render N Gaussians with the tile rasterizer (gsplat rules; exact, differentiable).

    Image formation (DESIGN.md section 2): EWA projection with a 0.3 px^2 low-pass;
    alpha_i = min(0.99, o_i exp(-q_i / 2)), counted where alpha_i >= 1/255; front-to-back by camera
    depth; compositing stops before transmittance would reach 1e-4;
    image = sum_i T_i alpha_i c_i + T_final * background. The result does not depend on
    ``tile_size``, ``chunk`` or ``batch`` (they only change speed).

    Args:
      means: [N, 3] world-space centres.
      quats: [N, 4] wxyz rotations, any norm.
      scales: [N, 3] activated scales (> 0).
      opacities: [N] activated opacities in [0, 1].
      colors: [N, C] per-Gaussian features, any C >= 1 (RGB, depth, flow vectors, ids ...).
      viewmat: [4, 4] world-to-camera (OpenCV).
      K: [3, 3] intrinsics.
      width, height: image size in pixels (static).
      background: [C] or None (zeros).
      All float inputs are cast to the dtype of ``means``/``colors`` (float32 at least).
      near_plane: Gaussians with camera depth <= near_plane are culled.
      tile_size: tile edge in pixels (static).
      capacity: number of (Gaussian, tile) intersection slots (static). None: outside jit, the
        exact count rounded up to a bucket; under jit/vmap, ``default_capacity``. If a render
        needs more, outside jit a ValueError is raised; under jit ``info["overflow"]`` is True and
        the image must not be used.
      chunk, batch: compositor work sizes (speed only). The compositor skips chunk batches past the
        last intersection with ``lax.cond``; under ``jax.vmap`` (a batch of cameras) that becomes a
        select that computes every batch, so loop over cameras (``lax.map``) where speed matters.
      render_depth: also composite camera depth (``info["depth"]`` expected depth).
      active: [N] bool or None (all tiles). Only the tiles that an active Gaussian reaches are
        composited (``info["tile_on"]`` [ceil(H / tile), ceil(W / tile)]); the others are left empty
        (background, alpha 0) and pass no gradient. For fits in which only the active Gaussians
        change (a part's pose): the gradients of the active ones are exact, and the pixels of the
        tiles off equal a render without the active Gaussians, which can be made once and pasted.

    Returns:
      image [H, W, C], alpha [H, W] (= 1 - T_final), and ``info`` with means2d [N, 2], depths [N],
      conics [N, 3], cov2d [N, 3], extent [N, 2] (screen half-size in px), radii [N, 2] int,
      valid [N], tile_rect [N, 4], n_isect (bbox intersections: the capacity needed),
      n_composited (those the exact ellipse-tile test keeps), overflow, capacity, depth [H, W],
      depth_acc [H, W].
    """
    xs = (means, quats, scales, opacities, colors, viewmat, K) + (() if background is None else (background,))
    # The compute dtype follows the Gaussians (means, colours); cameras and background are cast to it.
    dtype = jnp.result_type(jnp.asarray(means).dtype, jnp.asarray(colors).dtype, jnp.float32)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.float32
    means, quats, scales, opacities, colors, viewmat, K = (_as_float(x, dtype) for x in xs[:7])
    background = None if background is None else _as_float(background, dtype)
    _check_shapes(means, quats, scales, opacities, colors, viewmat, K, width, height, background, tile_size)
    width, height = int(width), int(height)
    traced = _is_traced(means, quats, scales, opacities, colors, viewmat, K, background)
    needed = None
    if capacity is None:
        if traced:
            capacity = default_capacity(means.shape[0], width, height, tile_size)
        else:
            needed = int(count_intersections(
                means, quats, scales, opacities, viewmat, K,
                width=width, height=height, near_plane=near_plane, tile_size=tile_size,
            ))
            capacity = round_capacity(needed)
    elif not isinstance(capacity, (int, np.integer)) or capacity <= 0:
        raise ValueError(f"rasterization: capacity must be a positive int, got {capacity!r}")
    if active is not None:
        active = jnp.asarray(active)
        if active.shape != (means.shape[0],) or active.dtype != jnp.bool_:
            raise ValueError(f"rasterization: active must be a bool array [N] = [{means.shape[0]}], got "
                             f"{active.dtype}{list(active.shape)}")
    out = _rasterize(
        means, quats, scales, opacities, colors, viewmat, K, background, active,
        width=width, height=height, near_plane=float(near_plane), tile_size=int(tile_size),
        capacity=int(capacity), chunk=int(chunk), batch=int(batch), render_depth=bool(render_depth),
    )
    out[2]["capacity"] = int(capacity)
    if not traced and bool(out[2]["overflow"]):
        raise ValueError(
            f"rasterization: {int(out[2]['n_isect'])} tile intersections exceed capacity={capacity}; "
            "pass a larger capacity (or capacity=None outside jit to size it automatically)"
        )
    return out


def gaussian_weights(
    means: Float[ArrayLike, "N 3"],
    quats: Float[ArrayLike, "N 4"],
    scales: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, " N"],
    viewmat: Float[ArrayLike, "4 4"],
    K: Float[ArrayLike, "3 3"],
    width: int,
    height: int,
    pixel_weights: Float[ArrayLike, "H W"],
    **kwargs,
) -> Float[Array, " N"]:
    """Per-Gaussian contribution to weighted pixels: sum_p m_p T_ip alpha_ip.

    The back-projection used for dynamic-Gaussian discovery (DESIGN.md section 1, step 5): with
    m a (soft) mask of moving pixels, Gaussians that paint those pixels get large values. Computed
    as the gradient of sum_p m_p image_p with respect to a zero one-channel colour, i.e. one
    backward pass of the tile rasterizer (memory O(intersections)). ``kwargs`` go to
    ``rasterization`` (capacity, tile_size, near_plane, ...).
    """
    means = jnp.asarray(means)
    dtype = jnp.result_type(means.dtype, jnp.float32)
    m = jnp.asarray(pixel_weights, dtype)
    if m.shape != (int(height), int(width)):
        raise ValueError(f"gaussian_weights: pixel_weights must have shape [H, W]=[{height}, {width}], "
                         f"got {list(m.shape)}")

    def masked(c):
        img, _, _ = rasterization(means, quats, scales, opacities, c, viewmat, K, width, height,
                                  render_depth=False, **kwargs)
        return jnp.sum(img[..., 0] * m)

    return jax.grad(masked)(jnp.zeros((means.shape[0], 1), dtype))[:, 0]
