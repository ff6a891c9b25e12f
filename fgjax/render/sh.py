"""Real spherical harmonics (degrees 0 to 3) evaluated along view directions.

Same basis, ordering and sign convention as the 3DGS/gsplat reference (``sh2rgb`` adds 0.5 and
clamps at 0 on top of this raw evaluation; ``spherical_harmonics`` returns the raw sum).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from fgjax.geometry import HIGHEST  # full float32 products on every backend (no TF32)

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(degree: int, dirs: Float[Array, "... 3"]) -> Float[Array, "... K"]:
    """SH basis values for unit (or any non-zero) directions; K = (degree + 1)^2."""
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"spherical_harmonics: degree must be 0..3, got {degree}")
    n2 = jnp.sum(dirs * dirs, -1, keepdims=True)
    ok = n2 > 0
    d = jnp.where(ok, dirs, jnp.array([0.0, 0.0, 1.0], dirs.dtype)) / jnp.sqrt(jnp.where(ok, n2, 1.0))
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = [jnp.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return jnp.stack(out, axis=-1)


def spherical_harmonics(
    degree: int, dirs: Float[Array, "N 3"], coeffs: Float[Array, "N K D"]
) -> Float[Array, "N D"]:
    """Evaluate SH of ``degree`` (0-3) with coefficients [N, K, D], K >= (degree+1)^2.

    ``dirs`` are view directions (Gaussian centre minus camera centre; need not be unit).
    Only the first (degree+1)^2 coefficients are used, so one array serves an SH-degree schedule.
    Returns the raw sum; RGB in 3DGS is ``max(result + 0.5, 0)``.
    """
    k = (degree + 1) ** 2
    if coeffs.ndim != 3 or coeffs.shape[1] < k:
        raise ValueError(f"spherical_harmonics: coeffs must be [N, K>={k}, D], got {list(coeffs.shape)}")
    basis = sh_basis(degree, dirs)  # [N, k]
    return jnp.einsum("nk,nkd->nd", basis, coeffs[:, :k], precision=HIGHEST)
