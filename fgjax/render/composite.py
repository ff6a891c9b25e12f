"""Front-to-back alpha compositing over tiles, with a hand-written VJP.

The per-pixel rule (DESIGN.md section 2): walking the depth-sorted Gaussians of the pixel's tile,
alpha_i = min(0.99, o_i exp(-q_i / 2)); Gaussian i counts when alpha_i >= 1/255; compositing stops
*before* the Gaussian whose inclusion would bring transmittance to <= 1e-4. Output
acc_p = sum_i T_i alpha_i c_i with T_i = prod_{j<i, counted} (1 - alpha_j).

Parallel formulation. Because transmittance only decreases, "stops before" is equivalent to a
mask: i is kept iff counted and L_i + log(1 - alpha_i) > log(1e-4), where L_i = log T_i is the
*unmasked* exclusive prefix sum of log(1 - alpha) (they agree on every kept Gaussian). So no
sequential loop is needed. Each tile's intersection list is cut into chunks of ``chunk`` entries;
chunks are processed ``batch`` at a time inside ``lax.scan``. Within a chunk the prefix sum over
Gaussians is a small triangular matmul; across chunks of the same tile it is a segment-masked
matmul inside the batch plus a carry from the previous batch. Batches beyond the last used chunk
are skipped with ``lax.cond``, so unused capacity and empty tiles cost (almost) nothing.

Backward: with g_p the output cotangent and S_i = sum_{j>i} w_j c_j the suffix of the composite,
  d acc / d alpha_i = T_i c_i - S_i / (1 - alpha_i),
and sum_k g_k S_ik = g.acc - (prefix of w_j g.c_j up to and including i): a *scalar* prefix sum,
computed with the same chunk machinery. Alpha is recomputed, so memory is O(intersections), never
O(pixels x Gaussians).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from fgjax.geometry import HIGHEST, matmul  # full float32 products on every backend (no TF32)
from fgjax.render.project import ALPHA_MAX, ALPHA_MIN, T_MIN


class Chunks(NamedTuple):
    ids: Int[Array, "NCH C"]  # Gaussian id per chunk entry (N = padding)
    live: Bool[Array, "NCH C"]  # entry holds a real intersection
    tile: Int[Array, " NCH"]  # tile of each chunk
    n_used: Int[Array, ""]  # chunks in use (a prefix of the NCH slots)
    tile_on: Bool[Array, " T"] | None = None  # tiles to composite (None: all); see `restrict_tiles`


def make_chunks(
    isect_ids: Int[Array, " M"], tile_start: Int[Array, " T1"], n_gaussians: int, chunk: int
) -> Chunks:
    """Cut each tile's sorted intersection list into chunks of ``chunk`` entries (static count)."""
    capacity = isect_ids.shape[0]
    n_tiles = tile_start.shape[0] - 1
    n_chunks = capacity // chunk + min(n_tiles, capacity)  # sum_t ceil(cnt_t / C) <= M / C + T
    n_chunks = max(n_chunks, 1)
    cnt = tile_start[1:] - tile_start[:-1]  # [T]
    nch = (cnt + chunk - 1) // chunk
    cincl = jnp.cumsum(nch)
    cexcl = cincl - nch
    s = jnp.arange(n_chunks, dtype=jnp.int32)
    starts = jnp.zeros(n_chunks + 1, jnp.int32).at[jnp.minimum(cexcl, n_chunks)].add(1)
    tile = jnp.clip(jnp.cumsum(starts[:n_chunks]) - 1, 0, n_tiles - 1)  # [NCH]
    k = s - cexcl[tile]
    used = s < cincl[-1]
    idx = tile_start[tile][:, None] + k[:, None] * chunk + jnp.arange(chunk, dtype=jnp.int32)  # [NCH, C]
    live = used[:, None] & (idx < tile_start[tile + 1][:, None])
    ids = jnp.where(live, isect_ids[jnp.clip(idx, 0, capacity - 1)], n_gaussians)
    return Chunks(ids=ids, live=live, tile=tile, n_used=cincl[-1])


def restrict_tiles(ch: Chunks, active: Bool[Array, " N"], n_tiles: int) -> Chunks:
    """``ch`` restricted to the tiles that an ``active`` Gaussian reaches (``tile_on`` [T]).

    The compositor skips every batch of chunks whose tiles are all off: those tiles stay empty
    (zero) and pass no gradient. A tile's chunks are contiguous, so a skipped batch never splits
    the running prefix of a tile that is composited.
    """
    act = jnp.concatenate([jnp.asarray(active, bool), jnp.zeros((1,), bool)])  # padding id N is inactive
    hit = jnp.any(act[ch.ids] & ch.live, axis=1)  # [NCH]
    tile_on = jnp.zeros((n_tiles,), bool).at[ch.tile].max(hit)
    return ch._replace(tile_on=tile_on)


def _batch_used(ch: Chunks, bidx, tile, batch: int):
    """Whether batch ``bidx`` (chunk tiles ``tile`` [B]) holds chunks in use on tiles to composite."""
    used = bidx * batch < ch.n_used
    return used if ch.tile_on is None else used & jnp.any(ch.tile_on[tile])


class _Static(NamedTuple):
    width: int
    height: int
    tile_size: int
    chunk: int
    batch: int


def _pixel_basis(tile_size: int, dtype) -> Float[Array, "P 6"]:
    """Pixel centres of a tile relative to the tile centre, and their quadratic basis.

    Returns [x^2, x y, y^2, x, y, 1] per pixel (row-major inside the tile); x, y are in
    [-tile_size/2 + 0.5, tile_size/2 - 0.5]. Centred coordinates keep float32 round-off small.
    """
    r = jnp.arange(tile_size, dtype=dtype) + 0.5 - 0.5 * tile_size
    y, x = jnp.meshgrid(r, r, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    return jnp.stack([x * x, x * y, y * y, x, y, jnp.ones_like(x)], axis=-1)


def _local_means(tile, mean, tile_size: int, n_tiles_x: int):
    """Gaussian centres relative to the centre of their chunk's tile: [B, C, 2]."""
    centre = (jnp.stack([tile % n_tiles_x, tile // n_tiles_x], -1).astype(mean.dtype) + 0.5) * tile_size  # [B, 2]
    return mean - centre[:, None, :]


def _alpha(basis, m_local, conic, opac, live):
    """alpha [B, C, P] (clamped), the unclamped o exp(-q/2), and the counted mask.

    q = a dx^2 + 2 b dx dy + c dy^2 from the offsets directly (exact in float32 to round-off);
    forward and backward call this same function so their keep decisions agree bit for bit.
    """
    dx = basis[None, None, :, 3] - m_local[..., 0:1]  # [B, C, P]
    dy = basis[None, None, :, 4] - m_local[..., 1:2]
    a, b, c = conic[..., 0:1], conic[..., 1:2], conic[..., 2:3]
    q = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
    raw = opac[..., None] * jnp.exp(-0.5 * jnp.maximum(q, 0.0))  # [B, C, P]
    alpha = jnp.minimum(ALPHA_MAX, raw)
    on = live[..., None] & (alpha >= ALPHA_MIN)
    return alpha, raw, on


def _segment_prefix(tile, vals, carry_tile, carry_val):
    """Exclusive prefix over earlier chunks of the same tile (inside the batch, plus the carry).

    tile [B] sorted; vals [B, P]. Returns prefix [B, P] and the new carry (tile, inclusive sum).
    """
    bsz = tile.shape[0]
    earlier = jnp.tril(jnp.ones((bsz, bsz), bool), k=-1)
    mask = (earlier & (tile[:, None] == tile[None, :])).astype(vals.dtype)  # [B, B]
    pre = matmul(mask, vals) + jnp.where(tile == carry_tile, 1.0, 0.0).astype(vals.dtype)[:, None] * carry_val
    return pre, (tile[-1], pre[-1] + vals[-1])


def _prefix_sum(x, inclusive: bool):
    """Prefix sum over the chunk axis (axis 1) of x [B, C, P], in two levels of small matmuls.

    The chunk is split into groups of g = 8 entries: a triangular g x g matmul inside each group
    plus a triangular matmul over the group sums costs about 2 g + C / g multiply-adds per entry
    instead of C for one C x C triangular matmul.
    """
    B, C, P = x.shape
    g = 8 if C % 8 == 0 and C > 8 else C
    k = 0 if inclusive else -1
    tri_in = jnp.tril(jnp.ones((g, g), x.dtype), k=k)
    xg = x.reshape(B, C // g, g, P)
    within = jnp.einsum("ij,bgjp->bgip", tri_in, xg, precision=HIGHEST)
    if C // g > 1:
        tri_out = jnp.tril(jnp.ones((C // g, C // g), x.dtype), k=-1)
        before = jnp.einsum("gh,bhp->bgp", tri_out, xg.sum(2), precision=HIGHEST)  # sum of earlier groups
        within = within + before[:, :, None, :]
    return within.reshape(B, C, P)


def _batches(x, batch):
    return x.reshape((x.shape[0] // batch, batch) + x.shape[1:])


def _pad_chunks(ch: Chunks, batch: int, n: int) -> Chunks:
    nch = ch.ids.shape[0]
    pad = (-nch) % batch
    if pad == 0:
        return ch
    return Chunks(
        ids=jnp.concatenate([ch.ids, jnp.full((pad, ch.ids.shape[1]), n, ch.ids.dtype)]),
        live=jnp.concatenate([ch.live, jnp.zeros((pad, ch.live.shape[1]), bool)]),
        tile=jnp.concatenate([ch.tile, jnp.full((pad,), ch.tile[-1], ch.tile.dtype)]),
        n_used=ch.n_used,
        tile_on=ch.tile_on,
    )


def _with_padding_row(*arrays):
    """Append row N, a harmless Gaussian (all zeros: opacity 0) that padding entries point to."""
    return tuple(jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)]) for x in arrays)


def _forward_impl(st: _Static, means2d, conics, opac, colors, ch: Chunks):
    """Returns acc [n_tiles, P, K] and the per-chunk transmittance prefix L0 [NCH, P]."""
    dtype = colors.dtype
    n = means2d.shape[0]
    ntx = -(-st.width // st.tile_size)
    nty = -(-st.height // st.tile_size)
    n_tiles = ntx * nty
    P = st.tile_size * st.tile_size
    K = colors.shape[-1]
    ch = _pad_chunks(ch, st.batch, n)
    m2, cn, op, co = _with_padding_row(means2d, conics, opac, colors)
    log_tmin = math.log(T_MIN)
    nb = ch.ids.shape[0] // st.batch
    basis = _pixel_basis(st.tile_size, dtype)

    def body(carry, xs):
        bidx, ids, live, tile = xs

        def compute(carry):
            c_tile, c_val = carry
            ml = _local_means(tile, m2[ids], st.tile_size, ntx)
            alpha, _, on = _alpha(basis, ml, cn[ids], op[ids], live)
            lg = jnp.where(on, jnp.log(1.0 - alpha), 0.0)  # [B, C, P]; 1 - alpha >= 0.01
            pre, new_carry = _segment_prefix(tile, lg.sum(1), c_tile, c_val)  # [B, P]
            L = pre[:, None, :] + _prefix_sum(lg, inclusive=False)
            keep = on & (L + lg > log_tmin)
            w = jnp.where(keep, alpha * jnp.exp(L), 0.0)  # [B, C, P]
            out = jnp.einsum("bcp,bck->bpk", w, co[ids], precision=HIGHEST)  # [B, P, K]
            return new_carry, (out, pre)

        def skip(carry):
            return carry, (jnp.zeros((st.batch, P, K), dtype), jnp.zeros((st.batch, P), dtype))

        return jax.lax.cond(_batch_used(ch, bidx, tile, st.batch), compute, skip, carry)

    xs = (jnp.arange(nb), _batches(ch.ids, st.batch), _batches(ch.live, st.batch), _batches(ch.tile, st.batch))
    init = (jnp.array(-1, jnp.int32), jnp.zeros((P,), dtype))
    _, (out, pre) = jax.lax.scan(body, init, xs)
    out = out.reshape(-1, P, K)
    acc = jnp.zeros((n_tiles, P, K), dtype).at[ch.tile].add(out)
    return acc, pre.reshape(-1, P)


def _backward_impl(st: _Static, means2d, conics, opac, colors, ch: Chunks, pre, acc, g_acc):
    dtype = colors.dtype
    n = means2d.shape[0]
    ntx = -(-st.width // st.tile_size)
    P = st.tile_size * st.tile_size
    K = colors.shape[-1]
    ch = _pad_chunks(ch, st.batch, n)
    m2, cn, op, co = _with_padding_row(means2d, conics, opac, colors)
    log_tmin = math.log(T_MIN)
    g_dot_acc = jnp.sum(g_acc * acc, axis=-1)  # [T, P]
    basis = _pixel_basis(st.tile_size, dtype)
    nb = ch.ids.shape[0] // st.batch
    G = 6 + K  # per-entry gradient row: mean x,y; conic a,b,c; opacity; colours

    def body(carry, xs):
        bidx, ids, live, tile, pre_b = xs

        def compute(carry):
            c_tile, c_val = carry
            con, o, col = cn[ids], op[ids], co[ids]
            ml = _local_means(tile, m2[ids], st.tile_size, ntx)
            alpha, raw, on = _alpha(basis, ml, con, o, live)
            lg = jnp.where(on, jnp.log(1.0 - alpha), 0.0)
            L = pre_b[:, None, :] + _prefix_sum(lg, inclusive=False)
            keep = on & (L + lg > log_tmin)
            T = jnp.exp(L)
            w = jnp.where(keep, alpha * T, 0.0)  # [B, C, P]
            gt = g_acc[tile]  # [B, P, K]
            gc = jnp.einsum("bck,bpk->bcp", col, gt, precision=HIGHEST)  # g . c_i per pixel
            a = w * gc
            apre, new_carry = _segment_prefix(tile, a.sum(1), c_tile, c_val)  # [B, P]
            suffix = g_dot_acc[tile][:, None, :] - apre[:, None, :] - _prefix_sum(a, inclusive=True)
            d_alpha = jnp.where(keep & (raw < ALPHA_MAX), T * gc - suffix / (1.0 - alpha), 0.0)
            d_q = -0.5 * d_alpha * raw  # d alpha / d q = -alpha / 2 when unclamped
            # Moments of d_q over the pixel basis give every per-entry sum in one matmul:
            # sum_p d_q [x^2, xy, y^2, x, y, 1].
            mom = jnp.einsum("bcp,pf->bcf", d_q, basis, precision=HIGHEST)
            Sxx, Sxy, Syy, Sx, Sy, S = (mom[..., i] for i in range(6))
            mx, my = ml[..., 0], ml[..., 1]
            ca, cb, cc = con[..., 0], con[..., 1], con[..., 2]
            Dx = Sx - mx * S  # sum d_q dx
            Dy = Sy - my * S
            g_ca = Sxx - 2.0 * mx * Sx + mx * mx * S  # sum d_q dx^2
            g_cb = 2.0 * (Sxy - my * Sx - mx * Sy + mx * my * S)  # sum d_q 2 dx dy
            g_cc = Syy - 2.0 * my * Sy + my * my * S
            g_mx = -2.0 * (ca * Dx + cb * Dy)
            g_my = -2.0 * (cb * Dx + cc * Dy)
            g_o = -2.0 * S / jnp.where(o > 0, o, 1.0)  # sum d_alpha exp(-q/2) = -2 sum d_q / o
            g_col = jnp.einsum("bcp,bpk->bck", w, gt, precision=HIGHEST)  # [B, C, K]
            rows = jnp.concatenate([jnp.stack([g_mx, g_my, g_ca, g_cb, g_cc, g_o], -1), g_col], -1)
            return new_carry, rows

        def skip(carry):
            return carry, jnp.zeros((st.batch, st.chunk, G), dtype)

        return jax.lax.cond(_batch_used(ch, bidx, tile, st.batch), compute, skip, carry)

    xs = (
        jnp.arange(nb),
        _batches(ch.ids, st.batch),
        _batches(ch.live, st.batch),
        _batches(ch.tile, st.batch),
        _batches(jnp.concatenate([pre, jnp.zeros((ch.ids.shape[0] - pre.shape[0], P), dtype)]), st.batch),
    )
    init = (jnp.array(-1, jnp.int32), jnp.zeros((P,), dtype))
    _, rows = jax.lax.scan(body, init, xs)
    rows = rows.reshape(-1, G)
    grads = jnp.zeros((n + 1, G), dtype).at[ch.ids.reshape(-1)].add(rows)[:n]
    return grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 6:]


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _composite(st: _Static, means2d, conics, opac, colors, ch: Chunks):
    acc, _ = _forward_impl(st, means2d, conics, opac, colors, ch)
    return acc


def _composite_fwd(st, means2d, conics, opac, colors, ch):
    acc, pre = _forward_impl(st, means2d, conics, opac, colors, ch)
    return acc, (means2d, conics, opac, colors, ch, pre, acc)


def _composite_bwd(st, res, g_acc):
    means2d, conics, opac, colors, ch, pre, acc = res
    g_m, g_c, g_o, g_col = _backward_impl(st, means2d, conics, opac, colors, ch, pre, acc, g_acc)
    zero_ch = jax.tree_util.tree_map(lambda x: None, ch)
    return g_m, g_c, g_o, g_col, zero_ch


_composite.defvjp(_composite_fwd, _composite_bwd)


def composite(
    means2d: Float[Array, "N 2"],
    conics: Float[Array, "N 3"],
    opacities: Float[Array, " N"],
    colors: Float[Array, "N K"],
    chunks: Chunks,
    *,
    width: int,
    height: int,
    tile_size: int,
    chunk: int,
    batch: int,
) -> Float[Array, "H W K"]:
    """Composite ``colors`` front to back over the binned tiles; returns sum_i T_i alpha_i c_i."""
    st = _Static(width, height, tile_size, chunk, batch)
    acc = _composite(st, means2d, conics, opacities, colors, chunks)  # [T, P, K]
    if chunks.tile_on is not None:  # tiles off stay empty even where a batch also held tiles on
        acc = jnp.where(chunks.tile_on[:, None, None], acc, 0.0)
    ntx = -(-width // tile_size)
    nty = -(-height // tile_size)
    K = colors.shape[-1]
    img = acc.reshape(nty, ntx, tile_size, tile_size, K).transpose(0, 2, 1, 3, 4)
    return img.reshape(nty * tile_size, ntx * tile_size, K)[:height, :width]
