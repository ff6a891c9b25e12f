"""Tile binning: which Gaussians touch which tiles, sorted by tile then depth, in static shapes.

Every (Gaussian, tile) pair whose tile overlaps the bounding box of the Gaussian's
alpha >= 1/255 ellipse is one *intersection*. Intersections live in a fixed-capacity array
(``capacity`` slots); the number actually needed is returned with an overflow flag, so that the
caller can raise outside jit or re-run with a larger capacity. Nothing is dropped silently: when
``overflow`` is true the image is not to be trusted and the API says so.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


class Bins(NamedTuple):
    isect_ids: Int[Array, " M"]  # Gaussian index per slot, sorted by (tile, depth); N in unused slots
    tile_start: Int[Array, " T1"]  # [n_tiles + 1] offsets into isect_ids
    n_isect: Int[Array, ""]  # intersections needed (may exceed capacity)
    overflow: Bool[Array, ""]  # n_isect > capacity
    n_composited: Int[Array, ""]  # slots that survive the exact ellipse-tile test
    tile_rect: Int[Array, "N 4"]  # x0, y0, x1, y1 (half-open) tile range of each Gaussian


def tile_ranges(
    means2d: Float[Array, "N 2"],
    extent: Float[Array, "N 2"],
    valid: Bool[Array, " N"],
    tile_size: int,
    width: int,
    height: int,
) -> Int[Array, "N 4"]:
    """Half-open tile rectangle [x0, x1) x [y0, y1) covering the pixel centres inside the bbox.

    Pixel (j, i) has its centre at (j + 0.5, i + 0.5). The bbox is widened by a tiny relative
    margin so that round-off can only add a tile, never lose one (extra tiles cost time, not
    correctness: the per-pixel alpha test decides).
    """
    ntx = -(-width // tile_size)
    nty = -(-height // tile_size)
    e = extent * (1.0 + 1e-3) + 1e-2  # [N, 2]
    lo = means2d - e - 0.5  # first pixel index (continuous) per axis
    hi = means2d + e - 0.5
    lim = jnp.array([ntx, nty], means2d.dtype)
    # Clamp in float before the int cast so that huge or far-away values cannot overflow.
    t0 = jnp.clip(jnp.ceil(jnp.clip(lo, -1.0, 1e7)) / tile_size, 0, lim)
    t0 = jnp.floor(t0)
    t1 = jnp.clip(jnp.floor(jnp.clip(hi, -1.0, 1e7)) / tile_size, -1, lim - 1)
    t1 = jnp.floor(t1) + 1
    t0 = t0.astype(jnp.int32)
    t1 = jnp.maximum(t1.astype(jnp.int32), t0)
    empty = ~valid | jnp.any(t1 <= t0, axis=-1)
    rect = jnp.concatenate([t0, t1], axis=-1)  # x0, y0, x1, y1
    return jnp.where(empty[:, None], 0, rect)


def ellipse_hits_tile(
    mean: Float[Array, "M 2"],
    conic: Float[Array, "M 3"],
    r2: Float[Array, " M"],
    tx: Int[Array, " M"],
    ty: Int[Array, " M"],
    tile_size: int,
) -> Bool[Array, " M"]:
    """Whether some pixel centre of tile (tx, ty) can have q <= r2 (i.e. alpha >= 1/255).

    Exact test of the ellipse against the box spanned by the tile's pixel centres: the minimum
    of the convex quadratic q over a box is 0 when the centre is inside, else it lies on one of
    the four edges, where it is a clamped 1D minimisation. A small relative margin keeps the test
    conservative under round-off (extra pairs cost time, never correctness).
    """
    a, b, c = conic[:, 0], conic[:, 1], conic[:, 2]
    lo_x = (tx * tile_size).astype(mean.dtype) + 0.5 - mean[:, 0]  # box in offsets d = x - mean
    hi_x = lo_x + (tile_size - 1)
    lo_y = (ty * tile_size).astype(mean.dtype) + 0.5 - mean[:, 1]
    hi_y = lo_y + (tile_size - 1)
    inside = (lo_x <= 0) & (hi_x >= 0) & (lo_y <= 0) & (hi_y >= 0)
    safe_a = jnp.where(a > 0, a, 1.0)
    safe_c = jnp.where(c > 0, c, 1.0)

    def q(dx, dy):
        return a * dx * dx + 2.0 * b * dx * dy + c * dy * dy

    def on_x_edge(dx):  # dx fixed, minimise over dy in [lo_y, hi_y]
        return q(dx, jnp.clip(-b * dx / safe_c, lo_y, hi_y))

    def on_y_edge(dy):
        return q(jnp.clip(-b * dy / safe_a, lo_x, hi_x), dy)

    qmin = jnp.minimum(jnp.minimum(on_x_edge(lo_x), on_x_edge(hi_x)), jnp.minimum(on_y_edge(lo_y), on_y_edge(hi_y)))
    return inside | (qmin <= r2 * (1.0 + 1e-3) + 1e-3)


def bin_gaussians(
    rect: Int[Array, "N 4"],
    depths: Float[Array, " N"],
    n_tiles_x: int,
    n_tiles_y: int,
    capacity: int,
    ellipse: tuple | None = None,
    tile_size: int | None = None,
) -> Bins:
    """Sort all (Gaussian, tile) intersections by tile, then by depth (front to back).

    Gaussians are first ordered by depth; their intersections are laid out in that order
    (one contiguous run per Gaussian, located by an exclusive cumulative sum); a sort by
    tile id then yields tile-major, depth-minor order. Work is O(capacity log capacity).

    With ``ellipse = (means2d, conics, r2)`` (and ``tile_size``), bbox tiles that the
    alpha >= 1/255 ellipse does not reach are sorted past the end, so they are never composited
    (the capacity still counts the bbox slots, so it does not depend on this test).
    """
    n = depths.shape[0]
    n_tiles = n_tiles_x * n_tiles_y
    w = rect[:, 2] - rect[:, 0]  # [N]
    h = rect[:, 3] - rect[:, 1]
    counts = w * h  # [N]
    key = jnp.where(counts > 0, depths, jnp.inf)
    order = jnp.argsort(key, stable=True)  # [N] front to back; empty ones last
    counts_o = counts[order]
    incl = jnp.cumsum(counts_o)  # [N]
    excl = incl - counts_o
    n_isect = incl[-1] if n > 0 else jnp.zeros((), jnp.int32)

    slots = jnp.arange(capacity, dtype=jnp.int32)
    # rank[s] = position (in depth order) of the Gaussian that owns slot s: count the runs that
    # start at or before s. Zero-length runs share a start with the next run and sort before it.
    starts = jnp.zeros(capacity + 1, jnp.int32).at[jnp.minimum(excl, capacity)].add(1)
    rank = jnp.clip(jnp.cumsum(starts[:capacity]) - 1, 0, max(n - 1, 0))  # [M]
    if n == 0:
        gid = jnp.zeros(capacity, jnp.int32)
        in_use = jnp.zeros(capacity, bool)
        tile = jnp.full(capacity, n_tiles, jnp.int32)
    else:
        gid = order[rank]  # [M]
        k = slots - excl[rank]  # index of this tile within the Gaussian's rectangle
        in_use = slots < n_isect
        wg = jnp.maximum(w[gid], 1)
        tx = rect[gid, 0] + k % wg
        ty = rect[gid, 1] + k // wg
        if ellipse is not None:
            m2, cn, r2 = ellipse
            in_use = in_use & ellipse_hits_tile(m2[gid], cn[gid], r2[gid], tx, ty, tile_size)
        tile = jnp.where(in_use, ty * n_tiles_x + tx, n_tiles)  # unused slots sort last
    if (n_tiles + 1) * max(n, 1) < 2**31 - 1:
        # One int32 key (tile, depth rank): a single-operand sort, ~2x faster than a stable
        # two-operand sort on CPU. rank is the Gaussian's position in depth order.
        packed = jax.lax.sort(tile * max(n, 1) + rank.astype(jnp.int32))
        tile_sorted = packed // max(n, 1)
        gid_sorted = jnp.where(tile_sorted < n_tiles, order[packed % max(n, 1)] if n > 0 else n, n)
    else:
        tile_sorted, gid_sorted = jax.lax.sort((tile, jnp.where(in_use, gid, n)), num_keys=1, is_stable=True)
    tile_start = jnp.searchsorted(tile_sorted, jnp.arange(n_tiles + 1, dtype=jnp.int32), side="left")
    return Bins(
        isect_ids=gid_sorted.astype(jnp.int32),
        tile_start=tile_start.astype(jnp.int32),
        n_isect=n_isect,
        overflow=n_isect > capacity,
        n_composited=jnp.sum(in_use).astype(jnp.int32),
        tile_rect=rect,
    )
