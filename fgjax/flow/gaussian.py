"""Gaussian flow: projected 2D covariances, the GaussianFlow affine term, rendered dynamic Gaussian flow
maps, composited inverse depth, the Lemma 1 residual, flow losses and backward warping (DESIGN.md section 1,
steps 3 and 4; conventions in `fgjax.flow`)."""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from fgjax import geometry
from fgjax.flow._common import charbonnier, mm, safe_inv_depth
from fgjax.flow.motion import motion_field_inv_depth, pixel_centers, reprojection_flow
from fgjax.geometry import abs0, as_float
from fgjax.render.api import rasterization
from fgjax.render.project import project_gaussians

# ----------------------------------------------------------------------------------------------
# 2D covariances and the GaussianFlow affine term
# ----------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("width", "height", "blur"))
def project_covariances(
    means: Float[ArrayLike, "N 3"],
    quats: Float[ArrayLike, "N 4"],
    scales: Float[ArrayLike, "N 3"],
    viewmat: Float[ArrayLike, "4 4"],
    K: Float[ArrayLike, "3 3"],
    width: int,
    height: int,
    *,
    blur: float = 0.3,
) -> tuple[Float[Array, "N 2"], Float[Array, "N 2 2"], Float[Array, " N"]]:
    """EWA projection of 3D Gaussians, with the rasterizer's rules (DESIGN section 2).

    Sigma' = J W Sigma W^T J^T + blur I, Sigma = R diag(s^2) R^T (R from the wxyz quaternion), W the
    world-to-camera rotation, J the perspective Jacobian at the centre with x/z clamped to
    [-cx/fx - 0.3 tan_x, (width - cx)/fx + 0.3 tan_x] (tan_x = width / (2 fx)) and y/z likewise; the 2D
    mean itself is not clamped. Uses the rasterizer's projection (``fgjax.render.project``), so both
    always follow the same rule, without rendering and with exact gradients.

    Args:
        means: world-frame centres, [N, 3].
        quats: rotations, wxyz any norm, [N, 4].
        scales: activated scales (> 0), [N, 3].
        viewmat: world-to-camera (OpenCV), [4, 4].
        K: intrinsics, [3, 3].
        width, height: image size in pixels (for the clamp).
        blur: screen-space low-pass variance added to the 2D covariance (0.3 px^2 as in gsplat).

    Returns:
        (means2d [N, 2], cov2d [N, 2, 2], depths [N]); depths are camera z. Centres with z <= 0 get a
        finite but meaningless covariance (the rasterizer culls them).
    """
    means, quats, scales = as_float(means), as_float(quats), as_float(scales)
    viewmat, K = as_float(viewmat), as_float(K)
    p = mm(means, viewmat[:3, :3].T) + viewmat[None, :3, 3]  # [N, 3]
    proj = project_gaussians(
        means, quats, scales, jnp.ones(means.shape[:1], means.dtype), viewmat, K, width, height, near_plane=0.0
    )
    a, b, c = proj.cov2d[:, 0], proj.cov2d[:, 1], proj.cov2d[:, 2]  # includes the 0.3 px^2 low-pass
    cov2 = jnp.stack([jnp.stack([a, b], -1), jnp.stack([b, c], -1)], -2)
    cov2 = cov2 + (blur - 0.3) * jnp.eye(2, dtype=cov2.dtype)[None]
    return geometry.project_points(p, K), cov2, p[:, 2]


@jax.jit
def sqrtm_2x2(s: Float[ArrayLike, "*batch 2 2"]) -> Float[Array, "*batch 2 2"]:
    """Principal square root of symmetric positive semi-definite 2x2 matrices, closed form.

    sqrt(S) = (S + sqrt(det S) I) / sqrt(tr S + 2 sqrt(det S)). Uses only the determinant and trace,
    no eigen-decomposition, so values and gradients are smooth at isotropic S (repeated eigenvalues),
    where eigenvector-based square roots have singular gradients. det S is clamped at 0 and the
    denominator guarded (S = 0 gives 0 with finite gradients).

    Args:
        s: SPD matrices, [..., 2, 2].

    Returns:
        B with B @ B == S, B symmetric positive semi-definite, [..., 2, 2].
    """
    s = as_float(s)
    det = s[..., 0, 0] * s[..., 1, 1] - s[..., 0, 1] * s[..., 1, 0]
    det_pos = det > 0
    sd = jnp.where(det_pos, jnp.sqrt(jnp.where(det_pos, det, 1.0)), 0.0)
    den2 = s[..., 0, 0] + s[..., 1, 1] + 2.0 * sd
    den_pos = den2 > 0
    inv_den = jnp.where(den_pos, 1.0 / jnp.sqrt(jnp.where(den_pos, den2, 1.0)), 0.0)
    eye = jnp.broadcast_to(jnp.eye(2, dtype=s.dtype), s.shape)
    return (s + sd[..., None, None] * eye) * inv_den[..., None, None]


def _inv_2x2(m: Array) -> Array:
    det = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    ok = det != 0
    inv_det = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), 0.0)
    adj = jnp.stack(
        [jnp.stack([m[..., 1, 1], -m[..., 0, 1]], -1), jnp.stack([-m[..., 1, 0], m[..., 0, 0]], -1)], axis=-2
    )
    return adj * inv_det[..., None, None]


@jax.jit
def gaussian_flow_affine(
    means2d0: Float[ArrayLike, "N 2"],
    cov2d0: Float[ArrayLike, "N 2 2"],
    means2d1: Float[ArrayLike, "N 2"],
    cov2d1: Float[ArrayLike, "N 2 2"],
) -> tuple[Float[Array, "N 2 2"], Float[Array, "N 2"]]:
    """Per-Gaussian affine flow of GaussianFlow, f_i(m) = (M_i - I)(m - mu_i,0) + dmu_i, as (M_i - I, offset).

    M_i = B_i,1 B_i,0^-1 with B = Sigma'^(1/2) (``sqrtm_2x2``), dmu_i = mu_i,1 - mu_i,0. The returned
    offset is dmu_i - (M_i - I) mu_i,0, so f_i(m) = (M_i - I) m + offset_i: both parts are constant per
    Gaussian and can be alpha-composited as 6 colour channels.

    Args:
        means2d0, cov2d0: 2D means [N, 2] and covariances [N, 2, 2] at t-1 (camera t-1).
        means2d1, cov2d1: the same at t, projected with the camera of t-1.

    Returns:
        (M - I [N, 2, 2], offset [N, 2]).
    """
    means2d0, cov2d0 = as_float(means2d0), as_float(cov2d0)
    means2d1, cov2d1 = as_float(means2d1), as_float(cov2d1)
    b0_inv = _inv_2x2(sqrtm_2x2(cov2d0))
    m = mm(sqrtm_2x2(cov2d1), b0_inv)  # [N, 2, 2]
    m_minus_i = m - jnp.broadcast_to(jnp.eye(2, dtype=m.dtype), m.shape)
    offset = (means2d1 - means2d0) - mm(m_minus_i, means2d0[..., None])[..., 0]
    return m_minus_i, offset


# ----------------------------------------------------------------------------------------------
# rendered maps
# ----------------------------------------------------------------------------------------------


class GaussianFlowMaps(NamedTuple):
    """Rendered per-pixel maps of a dynamic Gaussian flow pass (all on the frame t-1 pixel grid)."""

    flow: Float[Array, "H W 2"]
    """Dynamic Gaussian flow sum_i T_i alpha_i f_i(m) (background 0), pixels per frame."""
    alpha: Float[Array, "H W"]
    """Accumulated opacity sum_i T_i alpha_i."""
    inv_depth: Float[Array, "H W"]
    """Composited inverse depth sum_i T_i alpha_i / Z_i (background 0, i.e. at infinity)."""
    overflow: Bool[Array, ""]
    """The rasterizer ran out of intersection slots (only possible under jit with a too small
    ``capacity``); the maps must not be used then."""
    depth: Float[Array, "H W"]
    """Expected depth sum_i T_i alpha_i Z_i / alpha (0 where alpha = 0), the rasterizer's ``info["depth"]``."""


def _rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height, **kw):
    """The flow pass: no background, and the expected depth (``info["depth"]``, `GaussianFlowMaps.depth`)."""
    return rasterization(
        means, quats, scales, opacities, colors, viewmat, K, width, height, background=None, render_depth=True, **kw
    )


def dynamic_gaussian_flow(
    means0: Float[ArrayLike, "N 3"],
    quats0: Float[ArrayLike, "N 4"],
    scales0: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, " N"],
    means1: Float[ArrayLike, "N 3"],
    viewmat: Float[ArrayLike, "4 4"],
    K: Float[ArrayLike, "3 3"],
    width: int,
    height: int,
    *,
    anisotropic: bool = False,
    quats1: Float[ArrayLike, "N 4"] | None = None,
    scales1: Float[ArrayLike, "N 3"] | None = None,
    near_plane: float = 0.01,
    tile_size: int = 16,
    capacity: int | None = None,
) -> GaussianFlowMaps:
    """Dynamic Gaussian flow map u~_GS(m) = sum_i T_i alpha_i f_i(m), rendered with ``fgjax.rasterization``.

    Both frames' Gaussians are projected with the camera of frame t-1 (``viewmat``), so only object
    motion remains (DESIGN section 1, step 4); T_i alpha_i are those of the frame t-1 Gaussians
    (``means0, quats0, scales0, opacities``). Background 0.

    - Isotropic (default, the paper's form): f_i = dmu_i = mu_i(t) - mu_i(t-1), composited as 2 colour
      channels.
    - Anisotropic (GaussianFlow): f_i(m) = (M_i - I)(m - mu_i,t-1) + dmu_i with M_i = B_i,t B_i,t-1^-1,
      B = Sigma'^(1/2) in closed form (``gaussian_flow_affine``), composited as 6 channels
      [(M - I) row-major, offset] and evaluated as flow(m) = R_M(m) m + R_off(m) at pixel centres m.
      The 2D covariances come from ``project_covariances`` (same EWA rule as the rasterizer).

    A 3rd (or 7th) channel carries 1/Z_i (camera depth of the frame t-1 centre), giving the composited
    inverse depth of Lemma 1 from the same pass.

    Args:
        means0, quats0, scales0, opacities: frame t-1 Gaussians (world frame, wxyz any norm, activated
            scales > 0, opacities in [0, 1]), [N, 3], [N, 4], [N, 3], [N].
        means1: frame t centres (world frame), [N, 3].
        viewmat: world-to-camera of frame t-1 (OpenCV), [4, 4].
        K: intrinsics, [3, 3].
        width, height: image size (static ints).
        anisotropic: use the GaussianFlow affine term.
        quats1, scales1: frame t rotations/scales for the anisotropic form (default: frame t-1's, so that
            only the projection of the moved centre changes the 2D covariance).
        near_plane, tile_size, capacity: passed to the rasterizer.

    Returns:
        ``GaussianFlowMaps(flow [H, W, 2], alpha [H, W], inv_depth [H, W], overflow [], depth [H, W])``.

    Outside ``jax.jit`` with ``capacity=None`` the rasterizer sizes its intersection buffer exactly; under
    jit pass a ``capacity`` (or check ``overflow``).
    """
    means0, quats0, scales0 = as_float(means0), as_float(quats0), as_float(scales0)
    opacities, means1, viewmat, K = as_float(opacities), as_float(means1), as_float(viewmat), as_float(K)
    n = means0.shape[0]
    for name, x, tail in (
        ("means0", means0, (n, 3)),
        ("quats0", quats0, (n, 4)),
        ("scales0", scales0, (n, 3)),
        ("means1", means1, (n, 3)),
        ("viewmat", viewmat, (4, 4)),
        ("K", K, (3, 3)),
    ):
        if x.shape != tail:
            raise ValueError(f"{name} must have shape {list(tail)}; got {list(x.shape)}.")
    if opacities.shape != (n,):
        raise ValueError(f"opacities must have shape [{n}]; got {list(opacities.shape)}.")
    kw = dict(near_plane=near_plane, tile_size=tile_size, capacity=capacity)
    if not anisotropic:
        colors = _iso_colors(means0, means1, viewmat, K)  # [N, 3]
        image, alpha, info = _rasterize(means0, quats0, scales0, opacities, colors, viewmat, K, width, height, **kw)
        return GaussianFlowMaps(image[..., :2], alpha, image[..., 2], jnp.asarray(info["overflow"]), info["depth"])
    quats1 = quats0 if quats1 is None else as_float(quats1)
    scales1 = scales0 if scales1 is None else as_float(scales1)
    colors = _aniso_colors(means0, quats0, scales0, means1, quats1, scales1, viewmat, K, width, height)  # [N, 7]
    image, alpha, info = _rasterize(means0, quats0, scales0, opacities, colors, viewmat, K, width, height, **kw)
    return GaussianFlowMaps(_aniso_flow(image), alpha, image[..., 6], jnp.asarray(info["overflow"]), info["depth"])


@jax.jit
def _iso_colors(means0, means1, viewmat, K):
    """Per-Gaussian channels [dmu (2), 1/Z_i (1)], both frames projected with camera t-1."""
    view_rot, view_t = viewmat[:3, :3], viewmat[:3, 3]
    p0 = mm(means0, view_rot.T) + view_t[None]  # [N, 3]
    p1 = mm(means1, view_rot.T) + view_t[None]  # [N, 3]
    dmu = geometry.project_points(p1, K) - geometry.project_points(p0, K)  # [N, 2]
    return jnp.concatenate([dmu, safe_inv_depth(p0[:, 2])[:, None]], axis=-1)


@functools.partial(jax.jit, static_argnames=("width", "height"))
def _aniso_colors(means0, quats0, scales0, means1, quats1, scales1, viewmat, K, width, height):
    """Per-Gaussian channels [(M - I) row-major (4), offset (2), 1/Z_i (1)]."""
    n = means0.shape[0]
    mu0, cov0, z0 = project_covariances(means0, quats0, scales0, viewmat, K, width, height)
    mu1, cov1, _ = project_covariances(means1, quats1, scales1, viewmat, K, width, height)
    m_minus_i, offset = gaussian_flow_affine(mu0, cov0, mu1, cov1)
    return jnp.concatenate([m_minus_i.reshape(n, 4), offset, safe_inv_depth(z0)[:, None]], axis=-1)


@jax.jit
def _aniso_flow(image):
    """flow(m) = R_M(m) m + R_off(m) at the pixel centres, from the 7-channel composite."""
    height, width = image.shape[:2]
    pix = pixel_centers(height, width, image.dtype)  # [H, W, 2]
    r_m = image[..., :4].reshape(height, width, 2, 2)
    return mm(r_m, pix[..., None])[..., 0] + image[..., 4:6]


def composited_inverse_depth(
    means: Float[ArrayLike, "N 3"],
    quats: Float[ArrayLike, "N 4"],
    scales: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, " N"],
    viewmat: Float[ArrayLike, "4 4"],
    K: Float[ArrayLike, "3 3"],
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    tile_size: int = 16,
    capacity: int | None = None,
) -> tuple[Float[Array, "H W"], Float[Array, "H W"], Bool[Array, ""]]:
    """Composited inverse depth rho(m) = sum_i T_i alpha_i / Z_i (background 0), alpha, and overflow.

    This is the depth for which Lemma 1's residual vanishes: with 1/Z = rho, the composite of the
    per-Gaussian camera flows equals ``motion_field_inv_depth(m, rho, ...)`` plus (1 - alpha) B omega
    (the background at infinity). Z_i is the camera z of centre i. (``dynamic_gaussian_flow`` returns
    the same map from its own pass.)

    Args:
        means, quats, scales, opacities: Gaussians (world frame, wxyz, activated), [N, ...].
        viewmat: world-to-camera (OpenCV), [4, 4].
        K: intrinsics, [3, 3].
        width, height: image size.

    Returns:
        (inv_depth [H, W], alpha [H, W], overflow []): overflow as in ``GaussianFlowMaps``.
    """
    means, viewmat = as_float(means), as_float(viewmat)
    colors = _inv_depth_colors(means, viewmat)  # [N, 1]
    image, alpha, info = _rasterize(
        means, quats, scales, opacities, colors, viewmat, K, width, height,
        near_plane=near_plane, tile_size=tile_size, capacity=capacity,
    )  # fmt: skip
    return image[..., 0], alpha, jnp.asarray(info["overflow"])


@jax.jit
def _inv_depth_colors(means, viewmat):
    z = mm(means, viewmat[2, :3]) + viewmat[2, 3]  # [N]
    return safe_inv_depth(z)[:, None]


@jax.jit
def lemma1_residual(
    xy: Float[ArrayLike, "*batch 2"],
    K: Float[ArrayLike, "3 3"],
    v: Float[ArrayLike, 3],
    inv_depth_gs: Float[ArrayLike, "*batch"],
    depth: Float[ArrayLike, "*batch"],
) -> Float[Array, "*batch 2"]:
    """Residual Delta of Lemma 1: A v (sum_i T_i alpha_i / Z_i - 1/Z).

    For composited Gaussians each moving with image velocity u_i = A v / Z_i + B omega + dmu_i, over a
    background at infinity, u = sum_i w_i u_i + (1 - alpha) B omega = u_cam(Z) + u~_GS + Delta with
    w_i = T_i alpha_i and u_cam(Z) = A v / Z + B omega (``motion_field``). This equals the paper's
    A sum_i w_i v (1/Z_i - 1/Z) when alpha = 1, and vanishes when 1/Z = sum_i w_i / Z_i
    (``composited_inverse_depth``). The expected depth sum_i w_i Z_i does not make it vanish.

    Args:
        xy: pixel coordinates (centres at +0.5), [..., 2].
        K: intrinsics, [3, 3] (zero skew assumed).
        v: camera translational velocity (camera-0 coordinates), [3].
        inv_depth_gs: composited inverse depth sum_i T_i alpha_i / Z_i, [...].
        depth: the depth Z used for u_cam, [...]; non-positive or non-finite means infinity.

    Returns:
        Delta, [..., 2].
    """
    zero = jnp.zeros(3, dtype=jnp.result_type(as_float(v).dtype, as_float(xy).dtype))
    d_rho = as_float(inv_depth_gs) - safe_inv_depth(as_float(depth))
    return motion_field_inv_depth(xy, d_rho, K, v, zero)


# ----------------------------------------------------------------------------------------------
# loss and warping
# ----------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("norm", "threshold", "scale"))
def flow_loss(
    flow: Float[ArrayLike, "*batch H W 2"],
    flow_cam: Float[ArrayLike, "*batch H W 2"],
    flow_gs: Float[ArrayLike, "*batch H W 2"],
    valid: Bool[ArrayLike, "*batch H W"] | Float[ArrayLike, "*batch H W"] | None = None,
    *,
    norm: Literal["l1", "l2", "charbonnier"] = "l1",
    threshold: float | None = None,
    scale: float = 10.0,
) -> Float[Array, ""]:
    """Dynamic flow loss L_uGS = mean over valid pixels of ||u - u_cam - u~_GS|| (DESIGN section 1, step 4).

    The target is the observed flow minus the camera flow, d = u - u_cam. With ``threshold`` set, target
    vectors with |d| < threshold pixels are treated as static (d := 0): optical-flow noise below the
    threshold then pulls the Gaussian flow towards zero instead of fitting noise; pixels are not dropped.

    Args:
        flow: observed optical flow u, [..., H, W, 2].
        flow_cam: camera flow u_cam (``motion_field`` or ``reprojection_flow``), [..., H, W, 2].
        flow_gs: rendered dynamic Gaussian flow u~_GS (``dynamic_gaussian_flow``), [..., H, W, 2].
        valid: pixel mask (bool, or float weights in [0, 1]), [..., H, W]; None = all pixels.
        norm: "l1" = |dx| + |dy| per pixel (zero gradient where a component's residual is exactly 0);
            "l2" = sqrt(dx^2 + dy^2) per pixel (end-point error; zero
            gradient at a zero residual instead of NaN);
            "charbonnier" = c^2 (sqrt(1 + |r|^2 / c^2) - 1) with c = ``scale`` (Charbonnier 1994): |r|^2 / 2 for
            |r| << c, so a parameter shared by many pixels moves towards the mean of what they ask rather than
            the median, and c |r| beyond (robust); gradient r / sqrt(1 + |r|^2 / c^2), smooth at 0.
        threshold: optional magnitude threshold (pixels) on the target u - u_cam; None = off. A Python
            float (static under jit, like ``norm``).
        scale: c of "charbonnier", in pixels (> 0; a Python float, static under jit).

    Returns:
        Scalar loss: sum(w * err) / max(sum(w), 1) with w the validity weights (0 when nothing is valid).
    """
    flow, flow_cam, flow_gs = as_float(flow), as_float(flow_cam), as_float(flow_gs)
    if flow.shape != flow_cam.shape or flow.shape != flow_gs.shape or flow.shape[-1:] != (2,):
        raise ValueError(
            f"flow, flow_cam, flow_gs must share one shape [..., H, W, 2]; got {list(flow.shape)}, "
            f"{list(flow_cam.shape)}, {list(flow_gs.shape)}."
        )
    if norm not in ("l1", "l2", "charbonnier"):
        raise ValueError(f"norm must be 'l1', 'l2' or 'charbonnier'; got {norm!r}.")
    if not scale > 0:
        raise ValueError(f"scale must be > 0; got {scale!r}.")
    target = flow - flow_cam  # [..., H, W, 2]
    if threshold is not None:
        mag2 = jnp.sum(target * target, axis=-1, keepdims=True)
        target = jnp.where(mag2 >= threshold * threshold, target, 0.0)
    r = target - flow_gs
    if norm == "l1":
        # abs0: jnp.abs's derivative 1 at r = 0 would push every pixel whose target and flow agree exactly (a static
        # pixel at rest, a thresholded target) towards +x, +y
        err = jnp.sum(abs0(r), axis=-1)
    elif norm == "charbonnier":
        err = charbonnier(jnp.sum(r * r, axis=-1), scale)
    else:
        err = geometry.safe_norm(r)
    if valid is None:
        w = jnp.ones_like(err)
    else:
        valid = jnp.asarray(valid)
        if valid.shape != err.shape:
            raise ValueError(f"valid must have shape {list(err.shape)}; got {list(valid.shape)}.")
        w = valid.astype(err.dtype)
    return jnp.sum(w * err) / jnp.maximum(jnp.sum(w), 1.0)


def maps_camera_flow(
    maps: GaussianFlowMaps, viewmat0: Float[ArrayLike, "4 4"], viewmat1: Float[ArrayLike, "4 4"],
    K: Float[ArrayLike, "3 3"], camera_depth: str = "composited",
) -> tuple[Float[Array, "H W 2"], Bool[Array, "H W"]]:
    """(u_cam [H, W, 2], ok [H, W]): the camera flow of a dynamic-flow pass's depth, the exact ``reprojection_flow``
    from camera t-1 (``viewmat0``, the pass's camera) to camera t (``viewmat1``) of

    - ``camera_depth="composited"``: 1 / composited inverse depth, so that Lemma 1's Delta vanishes (the default);
    - ``camera_depth="expected"``: the expected depth sum_i T_i alpha_i Z_i / alpha, with which Delta
      (``lemma1_residual``) stays in u - u_cam wherever the Gaussians of a pixel lie at different depths.

    The depth is held fixed (stop-gradient); pixels with inverse depth <= 1e-6 (or no expected depth) have none and
    are not ok."""
    if camera_depth == "composited":
        inv_d = jax.lax.stop_gradient(maps.inv_depth)
        has = inv_d > 1e-6
        depth = jnp.where(has, 1.0 / jnp.where(has, inv_d, 1.0), 0.0)  # [H, W]
    elif camera_depth == "expected":
        depth = jax.lax.stop_gradient(maps.depth)
        depth = jnp.where(depth > 1e-6, depth, 0.0)
    else:
        raise ValueError(f"maps_camera_flow: camera_depth must be 'composited' or 'expected', got {camera_depth!r}")
    c2w0, c2w1 = geometry.se3_inverse(as_float(viewmat0)), geometry.se3_inverse(as_float(viewmat1))
    return reprojection_flow(depth, K, c2w0, c2w1)


def gaussian_flow_loss(
    means0: Float[ArrayLike, "N 3"],
    quats0: Float[ArrayLike, "N 4"],
    scales0: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, " N"],
    means1: Float[ArrayLike, "N 3"],
    viewmat0: Float[ArrayLike, "4 4"],
    viewmat1: Float[ArrayLike, "4 4"],
    K: Float[ArrayLike, "3 3"],
    flow: Float[ArrayLike, "H W 2"],
    width: int,
    height: int,
    *,
    threshold: float | None = None,
    min_alpha: float = 0.5,
    capacity: int | None = None,
    tile_size: int = 8,
    anisotropic: bool = False,
    quats1: Float[ArrayLike, "N 4"] | None = None,
    scales1: Float[ArrayLike, "N 3"] | None = None,
    camera_depth: str = "composited",
    norm: Literal["l1", "l2", "charbonnier"] = "l1",
    scale: float = 10.0,
) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """L_uGS of one frame pair from Gaussians (DESIGN section 1, step 4): (loss, overflow flag).

    u~_GS is ``dynamic_gaussian_flow`` of the frame t-1 Gaussians (``means0, quats0, scales0``,
    activated) moving to ``means1``, both projected with camera t-1 (``viewmat0``); u_cam is the exact
    ``reprojection_flow`` of their composited depth (1 / composited inverse depth, so Lemma 1's Delta
    vanishes) from camera t-1 to camera t (``viewmat1``), held fixed (stop-gradient), as are the alpha
    and depth maps. Valid pixels: rendered alpha > ``min_alpha``, a finite observed ``flow`` (NaN =
    unknown) and a reprojection in front of camera t. Gradients reach the Gaussians through u~_GS.

    Variants (the paper's ablation, its Table 8): ``anisotropic`` renders u~_GS in GaussianFlow's affine form with the
    frame t rotations and scales ``quats1, scales1`` (`dynamic_gaussian_flow`); ``camera_depth="expected"`` takes
    u_cam from the expected depth, leaving Lemma 1's residual in the target (`maps_camera_flow`). ``norm`` and
    ``scale``: the per-pixel penalty (`flow_loss`).
    """
    maps = dynamic_gaussian_flow(means0, quats0, scales0, opacities, means1, viewmat0, K, width, height,
                                 anisotropic=anisotropic, quats1=quats1, scales1=scales1, capacity=capacity,
                                 tile_size=tile_size)
    u_cam, cam_ok = maps_camera_flow(maps, viewmat0, viewmat1, K, camera_depth)
    u_obs = as_float(flow)
    known = jnp.all(jnp.isfinite(u_obs), axis=-1)
    valid = cam_ok & known & (jax.lax.stop_gradient(maps.alpha) > min_alpha)
    loss = flow_loss(jnp.where(known[..., None], u_obs, 0.0), jax.lax.stop_gradient(u_cam), maps.flow, valid,
                     threshold=threshold, norm=norm, scale=scale)
    return loss, maps.overflow


@jax.jit
def warp_backward(
    image: Float[ArrayLike, "H W C"], flow: Float[ArrayLike, "H W 2"]
) -> tuple[Float[Array, "H W C"], Bool[Array, "H W"]]:
    """Backward warp: out(m) = image(m + flow(m)), bilinear, for a forward flow from frame t-1 to t.

    With ``image`` = frame t and ``flow`` the t-1 -> t flow, ``out`` approximates frame t-1. Sample
    positions use pixel centres at +0.5 (array index = coordinate - 0.5); samples outside the image
    clamp to the border and are flagged invalid.

    Args:
        image: frame t, [H, W, C] float.
        flow: forward flow (dx, dy) on frame t-1's grid, [H, W, 2].

    Returns:
        (warped [H, W, C], inside [H, W]) with inside False where m + flow(m) leaves the image
        (or the flow is not finite).
    """
    image, flow = as_float(image), as_float(flow)
    h, w = image.shape[:2]
    if flow.shape != (h, w, 2):
        raise ValueError(f"flow must have shape [{h}, {w}, 2]; got {list(flow.shape)}.")
    finite = jnp.all(jnp.isfinite(flow), axis=-1)
    flow = jnp.where(finite[..., None], flow, 0.0)
    pos = pixel_centers(h, w, flow.dtype) + flow - 0.5  # continuous array indices (col, row)
    inside = finite & (pos[..., 0] >= 0) & (pos[..., 0] <= w - 1) & (pos[..., 1] >= 0) & (pos[..., 1] <= h - 1)
    x = jnp.clip(pos[..., 0], 0.0, w - 1.0)
    y = jnp.clip(pos[..., 1], 0.0, h - 1.0)
    x0 = jnp.clip(jnp.floor(x), 0, max(w - 2, 0)).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(y), 0, max(h - 2, 0)).astype(jnp.int32)
    x1, y1 = jnp.minimum(x0 + 1, w - 1), jnp.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    out = (
        image[y0, x0] * (1 - fx) * (1 - fy)
        + image[y0, x1] * fx * (1 - fy)
        + image[y1, x0] * (1 - fx) * fy
        + image[y1, x1] * fx * fy
    )
    return out, inside
