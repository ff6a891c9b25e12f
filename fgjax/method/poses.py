"""Camera poses from optical flow: a bundle adjustment over flow tracks, run before stage 1.

Why. With written poses 0.5 degree and 1% of the scene off (``fgjax synth --pose-noise-deg 0.5
--pose-noise-trans 0.01``), stage 1's photometric pose deltas do not find the truth: the deformation
field and the Gaussians absorb the errors, stage 1 fills the room with floaters, and the residual flow
u - u_cam that discovery reads is mostly pose error (docs/benchmarks.md). The flow between frames
constrains the cameras directly, before any Gaussian exists.

Model. Frames are taken in time order; ``flows[i]`` maps frame ``prev[i]``'s pixels to frame i
(`fgjax.method.stage1.estimate_training_flows`). A track starts at a pixel x of a host frame h and
follows the chained flow through the next `length` frames (bilinear lookups; it stops where the flow is
unknown or leaves the image). It is one static point with inverse depth rho in camera h:
X_h = K_h^-1 (x, 1) / rho, seen in frame j at pi(K_j, R x~ + rho t) with (R, t) = T_j T_h^-1 and
x~ = K_h^-1 (x, 1) (homogeneous, so rho -> 0 is a point at infinity and stays finite). Camera i is
T_i = exp(xi_i) T_i^written, the same left-multiplied twist xi = [omega, v] as stage 1's pose deltas.

Cost: sum over observations of w_o |r_o|^2 (r: reprojection minus the tracked pixel, in pixels; w: Cauchy
IRLS weights, so moving parts and flow errors count little) plus sum_i |xi_i / sigma|^2 (the written poses
as a prior: it fixes the gauge and the scale, which the flow cannot see).

Solver: Levenberg-Marquardt. Each inverse depth is a scalar block, so the depths are eliminated by the
Schur complement and only the 6T x 6T camera system is solved (float64, numpy); residuals and Jacobians
come from one vmapped `jax.jacfwd` (float32).

Conventions: OpenCV cameras, ``viewmats`` world-to-camera 4x4, pixel (j, i) centre at (j + 0.5, i + 0.5)
in K's coordinates. Pure functions; no ground truth is read.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fgjax.data.opticalflow import forward_backward_mask
from fgjax.geometry import matmul, se3_exp

__all__ = ["FlowTracks", "flow_tracks", "bundle_adjust", "BundleResult"]


class FlowTracks(NamedTuple):
    """Observations of static-point hypotheses along chained optical flow (numpy)."""

    host: np.ndarray  # [M] int: frame index of each track's first pixel
    xy: np.ndarray  # [M, 2] float: that pixel (K's coordinates)
    obs_track: np.ndarray  # [O] int: track of each observation
    obs_frame: np.ndarray  # [O] int: frame of each observation (never the host)
    obs_xy: np.ndarray  # [O, 2] float: the tracked pixel in that frame


@dataclasses.dataclass(frozen=True)
class BundleResult:
    viewmats: np.ndarray  # [T, 4, 4] refined world-to-camera
    deltas: np.ndarray  # [T, 6] twists [omega, v] with viewmats = se3_exp(deltas) @ written
    inv_depth: np.ndarray  # [M] inverse depth of each track in its host camera
    rms_before: float  # robust (inlier) RMS reprojection error, pixels, at the written poses
    rms_after: float
    inlier_fraction: float  # observations within 2 Cauchy scales at the end
    iterations: int
    time_s: float


def sample_bilinear(field: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Sample `field` [H, W, C] at K-coordinate positions `xy` [N, 2] (pixel centres at +0.5); NaN outside."""
    h, w = field.shape[:2]
    x, y = xy[:, 0] - 0.5, xy[:, 1] - 0.5
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    x0 = np.clip(np.floor(x), 0, max(w - 2, 0)).astype(int)
    y0 = np.clip(np.floor(y), 0, max(h - 2, 0)).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    v = (field[y0, x0] * (1 - fx) * (1 - fy) + field[y0, x1] * fx * (1 - fy)
         + field[y1, x0] * (1 - fx) * fy + field[y1, x1] * fx * fy)
    return np.where(inside[:, None], v, np.nan)


def flow_tracks(flows: np.ndarray, prev: np.ndarray, *, length: int = 4, stride: int = 8) -> FlowTracks:
    """Tracks along chained flow: from every `stride`-th pixel of every frame that has a successor, through
    up to `length` following frames in time order.

    Args:
        flows: [T, H, W, 2] flow into frame i from frame prev[i], on prev[i]'s grid (NaN = unknown).
        prev: [T] previous frame in time order (-1 for the first), `stage1.previous_frames`.
    """
    t, h, w = flows.shape[:3]
    nxt = np.full(t, -1, np.int64)
    for i, p in enumerate(np.asarray(prev)):
        if p >= 0:
            nxt[p] = i
    ys, xs = np.mgrid[stride // 2:h:stride, stride // 2:w:stride]
    grid = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], -1).astype(np.float64)  # [G, 2]
    host, xy, o_track, o_frame, o_xy = [], [], [], [], []
    m = 0
    for f in range(t):
        if nxt[f] < 0:
            continue
        pos, ids, frame = grid.copy(), np.arange(m, m + len(grid)), f
        host.append(np.full(len(grid), f))
        xy.append(grid)
        m += len(grid)
        for _ in range(length):
            j = nxt[frame]
            if j < 0 or len(pos) == 0:
                break
            pos = pos + sample_bilinear(flows[j].astype(np.float64), pos)
            ok = np.all(np.isfinite(pos), -1) & (pos[:, 0] >= 0) & (pos[:, 1] >= 0) & (pos[:, 0] <= w) & (
                pos[:, 1] <= h)
            pos, ids = pos[ok], ids[ok]
            o_track.append(ids)
            o_frame.append(np.full(len(ids), j))
            o_xy.append(pos)
            frame = j
    cat = (lambda a, shape: np.concatenate(a) if a else np.zeros(shape))
    return FlowTracks(cat(host, (0,)).astype(np.int64), cat(xy, (0, 2)), cat(o_track, (0,)).astype(np.int64),
                      cat(o_frame, (0,)).astype(np.int64), cat(o_xy, (0, 2)))


def _residual(xi_h, xi_j, rho, vm_h, vm_j, k_h, k_j, xy, obs):
    """Reprojection minus observation [2] (pixels) and whether the point is in front of camera j."""
    t_h = matmul(se3_exp(xi_h), vm_h)
    t_j = matmul(se3_exp(xi_j), vm_j)
    rel_r = matmul(t_j[:3, :3], t_h[:3, :3].T)  # T_j T_h^-1
    rel_t = t_j[:3, 3] - matmul(rel_r, t_h[:3, 3])
    ray = jnp.stack([(xy[0] - k_h[0, 2]) / k_h[0, 0], (xy[1] - k_h[1, 2]) / k_h[1, 1], 1.0])
    p = matmul(rel_r, ray) + rho * rel_t  # homogeneous: the point times rho, in camera j
    front = p[2] > 1e-3 * jnp.linalg.norm(p)
    z = jnp.where(front, p[2], 1.0)
    uv = jnp.stack([k_j[0, 0] * p[0] / z + k_j[0, 2], k_j[1, 1] * p[1] / z + k_j[1, 2]])
    return jnp.where(front, uv - obs, 0.0), front


@functools.partial(jax.jit, static_argnames=("jac",))
def _linearise(xi, rho, viewmats, Ks, host, track, frame, xy, obs, jac: bool = True):
    """Residuals [O, 2], front [O] and (with `jac`) Jacobians wrt xi_host [O, 2, 6], xi_frame [O, 2, 6],
    rho [O, 2] of every observation."""
    h = host[track]
    args = (xi[h], xi[frame], rho[track], viewmats[h], viewmats[frame], Ks[h], Ks[frame], xy[track], obs)
    r, front = jax.vmap(_residual)(*args)
    if not jac:
        return r, front
    jfun = jax.vmap(jax.jacfwd(lambda a, b, c, *rest: _residual(a, b, c, *rest)[0], argnums=(0, 1, 2)))
    j_h, j_j, j_r = jfun(*args)
    return r, front, j_h, j_j, j_r


_BEHIND_PX = 100.0  # residual charged to an observation behind its camera (cost only; no gradient)


def _cauchy_weights(r: np.ndarray, front: np.ndarray, scale: float) -> np.ndarray:
    n2 = np.sum(r * r, -1)
    return np.where(front, 1.0 / (1.0 + n2 / scale ** 2), 0.0)


def _robust_cost(r, front, scale, xi, prior_w) -> float:
    """Cauchy cost (scale^2 log(1 + |r|^2 / scale^2)) of the observations plus the prior."""
    n2 = np.where(front, np.sum(np.asarray(r, np.float64) ** 2, -1), _BEHIND_PX ** 2)
    data = np.sum(scale ** 2 * np.log1p(n2 / scale ** 2))
    return float(data + np.sum(prior_w * np.asarray(xi, np.float64) ** 2))


def _triangulate_inverse_depth(viewmats, Ks, tr: FlowTracks) -> np.ndarray:
    """Inverse depth of each track in its host camera with the cameras fixed: the linear least-squares
    solution of x_o (R x~ + rho t)_z = (R x~ + rho t)_x (and likewise y) over the track's observations
    (normalised coordinates); exact for exact data. Tracks whose solution lies behind the host get 0
    (a point at infinity)."""
    vm = np.asarray(viewmats, np.float64)
    ks = np.asarray(Ks, np.float64)
    h, j = tr.host[tr.obs_track], tr.obs_frame
    rel = vm[j] @ np.linalg.inv(vm)[h]  # [O, 4, 4]: camera h -> camera j (one inverse per camera)
    xy = tr.xy[tr.obs_track]
    ray = np.stack([(xy[:, 0] - ks[h, 0, 2]) / ks[h, 0, 0], (xy[:, 1] - ks[h, 1, 2]) / ks[h, 1, 1],
                    np.ones(len(h))], -1)
    a = np.einsum("oij,oj->oi", rel[:, :3, :3], ray)  # R x~ [O, 3]
    t = rel[:, :3, 3]
    obs = np.stack([(tr.obs_xy[:, 0] - ks[j, 0, 2]) / ks[j, 0, 0], (tr.obs_xy[:, 1] - ks[j, 1, 2]) / ks[j, 1, 1]], -1)
    coef = obs * t[:, 2:3] - t[:, :2]  # [O, 2]: rho * coef = rhs
    rhs = a[:, :2] - obs * a[:, 2:3]
    num = np.bincount(tr.obs_track, np.sum(coef * rhs, -1), len(tr.host))
    den = np.bincount(tr.obs_track, np.sum(coef * coef, -1), len(tr.host))
    rho = np.where(den > 1e-12, num / np.maximum(den, 1e-12), 0.0)
    return np.clip(rho, 0.0, 1e3)


def bundle_adjust(viewmats: np.ndarray, Ks: np.ndarray, flows: np.ndarray, prev: np.ndarray, *,
                  prior_rot_deg: float = 1.0, prior_trans: float = 0.05, length: int = 4, stride: int = 8,
                  iterations: int = 30, cauchy_px: float = 0.25, backward: np.ndarray | None = None,
                  fb_px: float = 0.1, log=print) -> BundleResult:
    """Refine written cameras `viewmats` [T, 4, 4] (world-to-camera) from optical flow (see the module doc).

    Args:
        Ks: [T, 3, 3] intrinsics.
        flows, prev: as for `flow_tracks`.
        prior_rot_deg, prior_trans: standard deviations of the written poses' errors (degrees; scene
            units), the prior's weights.
        cauchy_px: final Cauchy scale (pixels); it starts at 4x this and halves while the fit improves.
        backward: [T, H, W, 2] optional: backward[i] is the flow from frame i to frame prev[i], on frame i's
            grid. When given, the tracks stop where a forward flow fails the round trip by ``fb_px`` pixels or more
            (`fgjax.data.opticalflow.forward_backward_mask` with alpha 0 and beta ``fb_px``^2): occlusions and flow
            smoothed across depth edges.

    Returns:
        `BundleResult`; with no usable track the written poses come back unchanged.
    """
    t0 = time.time()
    vm = np.asarray(viewmats, np.float64)
    ks = np.asarray(Ks, np.float64)
    if vm.ndim != 3 or vm.shape[1:] != (4, 4) or ks.shape != (len(vm), 3, 3):
        raise ValueError(f"bundle_adjust: viewmats [T, 4, 4] and Ks [T, 3, 3] expected; got {vm.shape}, {ks.shape}")
    if flows.shape[0] != len(vm) or len(prev) != len(vm):
        raise ValueError(f"bundle_adjust: {flows.shape[0]} flows and {len(prev)} predecessors for {len(vm)} cameras")
    if not (prior_rot_deg > 0 and prior_trans > 0):
        raise ValueError("bundle_adjust: prior_rot_deg and prior_trans must be > 0")
    nt = len(vm)
    flows = np.asarray(flows)
    if backward is not None:
        backward = np.asarray(backward)
        if backward.shape != flows.shape:
            raise ValueError(f"bundle_adjust: backward flows must have the forward flows' shape {list(flows.shape)}, "
                             f"got {list(backward.shape)}")
        if not fb_px > 0:
            raise ValueError(f"bundle_adjust: fb_px must be > 0 with backward flows; got {fb_px}")
        flows = flows.copy()
        for i, j in enumerate(np.asarray(prev)):
            if j >= 0:  # |w_f + w_b|^2 < fb_px^2 (Sundaram et al.'s test without its relative term)
                flows[i][~forward_backward_mask(flows[i], backward[i], alpha=0.0, beta=fb_px ** 2)] = np.nan
    tr = flow_tracks(flows, np.asarray(prev), length=length, stride=stride)
    xi = np.zeros((nt, 6))
    if len(tr.obs_track) == 0:
        return BundleResult(vm, xi, np.zeros(0), 0.0, 0.0, 0.0, 0, time.time() - t0)
    prior_w = np.tile(np.r_[np.full(3, 1.0 / np.radians(prior_rot_deg) ** 2), np.full(3, 1.0 / prior_trans ** 2)],
                      (nt, 1))  # [T, 6]
    rho = _triangulate_inverse_depth(vm, ks, tr)
    consts = (jnp.asarray(vm, jnp.float32), jnp.asarray(ks, jnp.float32), jnp.asarray(tr.host),
              jnp.asarray(tr.obs_track), jnp.asarray(tr.obs_frame), jnp.asarray(tr.xy, jnp.float32),
              jnp.asarray(tr.obs_xy, jnp.float32))

    def lin(xi_, rho_, jac=True):
        out = _linearise(jnp.asarray(xi_, jnp.float32), jnp.asarray(rho_, jnp.float32), *consts, jac=jac)
        return tuple(np.asarray(a, np.float64) for a in out)

    def inlier_rms(r, front, scale):
        n = np.sqrt(np.sum(r * r, -1))
        ok = (front > 0) & (n < 2 * scale)
        return float(np.sqrt(np.mean(n[ok] ** 2))) if ok.any() else float("nan")

    scale = 4.0 * cauchy_px
    r, front = lin(xi, rho, jac=False)
    rms_before = inlier_rms(r, front, 4.0 * cauchy_px)
    lam, it = 1e-3, 0
    hs, js = tr.host[tr.obs_track], tr.obs_frame
    m, p = len(rho), 6 * nt
    for it in range(1, iterations + 1):
        r, front, j_h, j_j, j_r = lin(xi, rho)
        w = _cauchy_weights(r, front > 0, scale)
        cost = _robust_cost(r, front > 0, scale, xi, prior_w)
        # normal equations: cameras (dense 6T x 6T), inverse depths (diagonal), their coupling [M, 6T]
        h_pp = np.zeros((nt, nt, 6, 6))
        wj_h, wj_j = w[:, None, None] * j_h, w[:, None, None] * j_j
        np.add.at(h_pp, (hs, hs), np.einsum("oki,okj->oij", wj_h, j_h))
        np.add.at(h_pp, (js, js), np.einsum("oki,okj->oij", wj_j, j_j))
        cross = np.einsum("oki,okj->oij", wj_h, j_j)
        np.add.at(h_pp, (hs, js), cross)
        np.add.at(h_pp, (js, hs), np.transpose(cross, (0, 2, 1)))
        h_pp = h_pp.transpose(0, 2, 1, 3).reshape(p, p)
        g_p = np.zeros((nt, 6))
        np.add.at(g_p, hs, np.einsum("oki,ok->oi", wj_h, r))
        np.add.at(g_p, js, np.einsum("oki,ok->oi", wj_j, r))
        g_p = g_p.reshape(p) + (prior_w * xi).reshape(p)
        h_pp += np.diag(prior_w.reshape(p))
        h_pr = np.zeros((m, nt, 6))
        np.add.at(h_pr, (tr.obs_track, hs), np.einsum("oki,ok->oi", wj_h, j_r))
        np.add.at(h_pr, (tr.obs_track, js), np.einsum("oki,ok->oi", wj_j, j_r))
        h_pr = h_pr.reshape(m, p)
        h_rr = np.bincount(tr.obs_track, w * np.sum(j_r * j_r, -1), m)
        g_r = np.bincount(tr.obs_track, w * np.sum(j_r * r, -1), m)
        improved = False
        for _ in range(8):  # LM: raise the damping until the step lowers the cost
            a_pp = h_pp + lam * np.diag(np.diag(h_pp))
            a_rr = h_rr * (1.0 + lam) + 1e-9
            e = h_pr / a_rr[:, None]  # [M, 6T]
            s = a_pp - h_pr.T @ e
            b = g_p - e.T @ g_r
            try:
                d_p = -np.linalg.solve(s, b)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            d_r = -(g_r + h_pr @ d_p) / a_rr
            xi_new = xi + d_p.reshape(nt, 6)
            rho_new = np.clip(rho + d_r, 0.0, 1e3)
            r_new, f_new = lin(xi_new, rho_new, jac=False)
            if np.all(np.isfinite(xi_new)) and _robust_cost(r_new, f_new > 0, scale, xi_new, prior_w) < cost:
                xi, rho, lam, improved = xi_new, rho_new, max(lam / 3.0, 1e-7), True
                break
            lam *= 10.0
        converged = not improved or float(np.max(np.abs(d_p))) < 1e-6
        if converged and scale <= cauchy_px:
            break
        scale = max(cauchy_px, scale / 2.0)  # anneal the Cauchy scale towards cauchy_px
    r, front = lin(xi, rho, jac=False)
    rms_after = inlier_rms(r, front, 4.0 * cauchy_px)
    n = np.sqrt(np.sum(r * r, -1))
    inl = float(np.mean((front > 0) & (n < 2 * cauchy_px)))
    out = np.asarray(se3_exp(jnp.asarray(xi, jnp.float32)), np.float64) @ vm  # se3_exp is batched
    res = BundleResult(out, xi, rho, rms_before, rms_after, inl, it, time.time() - t0)
    log(f"pose bundle adjustment: {nt} cameras, {m} flow tracks, {len(tr.obs_track)} observations; inlier RMS "
        f"{rms_before:.3f} -> {rms_after:.3f} px ({100 * inl:.0f}% within {2 * cauchy_px:g} px), {it} iterations, "
        f"{res.time_s:.1f} s")
    return res
