"""A run's scene as plain Gaussians, for export (`fgjax export`) and for a viewer (`fgjax view`) (DESIGN.md section
1, step 8).

Two scenes, each of the run's active Gaussians only (the slots stage 1's alive mask keeps, in slot order):

- the stage-1 scene at time t: centres, raw quaternions and log-scales of the canonical Gaussians deformed by the
  deformation field, G_i(t) = G_i + f(X_i, t) (`LoadedRun.deformed`), with stage 1's opacities and SH;
- the controlled scene for per-object vectors v [K, 3] (`fgjax.method.result.controlled_gaussians`: each object's
  Gaussians moved by the control network from the reference scene), with the opacities and SH the controlled scene
  renders with (`LoadedRun.control_params`: stage 2's re-fitted ones where it made them).

Both are what `fgjax render` and `fgjax control` draw for the same inputs. A viewer gets the activated form
(`Splats`): centres, covariances Σ = R diag(s)^2 R^T (R from the normalised wxyz quaternion, s = exp(log-scale)),
opacities sigmoid(logit) and the view-independent colour max(C0 sh_0 + 0.5, 0) clipped to 1 (the SH's DC term;
a splat viewer without SH shows that).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from fgjax.gaussians import SH_C0, Gaussians
from fgjax.geometry import HIGHEST, quat_to_rotmat
from fgjax.method.result import (
    LoadedRun,
    Stage2Error,
    Stage2Result,
    cluster_vectors_at,
    controlled_gaussians,
    snap_vector,
)

__all__ = ["Splats", "active_slots", "object_labels", "scene_gaussians", "trajectory_vectors", "splat_arrays",
           "viewer_gaussians"]


class Splats(NamedTuple):
    """The active Gaussians of a scene, raw and activated (M = number of active slots).

    gaussians: `Gaussians` with numpy float32 leaves [M, ...] (raw parameters: what a .ply file stores).
    labels: [M] int, object id 0..K-1 of each Gaussian, -1 static (all -1 without stage 2).
    centers: [M, 3] float32.
    covariances: [M, 3, 3] float32, R diag(s)^2 R^T.
    rgbs: [M, 3] float32 in [0, 1], the DC colour.
    opacities: [M, 1] float32 in [0, 1].
    """

    gaussians: Gaussians
    labels: Int[np.ndarray, " M"]
    centers: Float[np.ndarray, "M 3"]
    covariances: Float[np.ndarray, "M 3 3"]
    rgbs: Float[np.ndarray, "M 3"]
    opacities: Float[np.ndarray, "M 1"]


def active_slots(run: LoadedRun) -> Int[np.ndarray, " M"]:
    """Indices [M] of the slots in use (stage 1's alive mask), increasing."""
    return np.flatnonzero(np.asarray(run.state.densify.alive))


def object_labels(run: LoadedRun) -> Int[np.ndarray, " M"]:
    """Object id [M] of each active Gaussian (0..K-1, -1 static); all -1 when the run has no stage-2 results."""
    idx = active_slots(run)
    return np.full(len(idx), -1, np.int64) if run.s2 is None else np.asarray(run.s2.labels, np.int64)[idx]


@functools.partial(jax.jit, static_argnames=("rigid",))
def _controlled_rows(control, base, canonical, labels, vectors, rows, *, rigid: bool):
    """`controlled_gaussians` computed on the rows ``rows`` [R] only (the objects' Gaussians) and scattered into the
    reference scene ``base``: every other row is its reference exactly (the network's offsets of a static Gaussian
    are zero, and each row depends on its own inputs alone), at R/N of the network's cost. Compiled once per
    shape; a control change re-runs it."""
    m0, q0, s0 = base
    m, q, s = controlled_gaussians(control, (m0[rows], q0[rows], s0[rows]), canonical[rows], labels[rows], vectors,
                                   rigid=rigid)
    return m0.at[rows].set(m), q0.at[rows].set(q), s0.at[rows].set(s)


def scene_gaussians(run: LoadedRun, *, time: float | None = None,
                    vectors: Float[ArrayLike, "K 3"] | None = None) -> Gaussians:
    """Raw parameters of the active Gaussians (numpy float32 leaves [M, ...]) of one of the module's two scenes.

    Args:
        run: a loaded run (`fgjax.method.result.load_stage2`).
        time: the stage-1 scene at this normalised time (0..1).
        vectors: instead, the controlled scene with these per-object vectors [K, 3] (scene units), used as given
            (snap them first with `snap_vector` or `trajectory_vectors`); needs stage-2 results.

    Returns:
        `Gaussians` of the M active slots, in slot order.
    """
    if (time is None) == (vectors is None):
        raise ValueError("scene_gaussians: give time (the stage-1 scene) or vectors (the controlled scene), "
                         "one of them")
    means, quats, log_scales, g = _geometry(run, time, vectors)
    idx = active_slots(run)
    leaves = (means, log_scales, quats, g.opacity_logits, g.sh)
    return Gaussians(*(np.asarray(x, np.float32)[idx] for x in leaves))


def _geometry(run: LoadedRun, time, vectors):
    """(means, raw quats, log-scales [N, ...] of every slot, the `Gaussians` whose opacities and SH go with them)."""
    if vectors is None:
        if not np.isfinite(time):
            raise ValueError(f"time must be finite, got {time}")
        m, q, ls = run.deformed(float(time))
        return m, q, ls, run.state.params["gaussians"]
    s2 = run.s2
    if s2 is None:
        raise Stage2Error(f"{run.run_dir} has no stage-2 results: the controlled scene needs "
                          f"`fgjax stage2 --run {run.run_dir}`")
    vec = np.asarray(vectors, np.float64).reshape(-1, 3)
    if vec.shape[0] != s2.num_objects:
        raise ValueError(f"vectors must have shape [{s2.num_objects}, 3] (one per object), got {list(vec.shape)}")
    rows = np.flatnonzero(s2.labels >= 0)
    if len(rows) == 0:
        m, q, ls = run.base()
    else:
        base = tuple(jnp.asarray(x, jnp.float32) for x in run.base())
        m, q, ls = _controlled_rows(s2.control, base, run.state.params["gaussians"].means, jnp.asarray(s2.labels),
                                    jnp.asarray(vec, jnp.float32), jnp.asarray(rows), rigid=s2.rigid)
    return m, q, ls, run.control_params()["gaussians"]


def trajectory_vectors(s2: Stage2Result, positions: Float[ArrayLike, " K"]) -> Float[np.ndarray, "K 3"]:
    """Per-object vectors [K, 3] at ``positions`` [K] along each object's trajectory, snapped (`snap_vector`).

    Position p in [0, 1] is the trajectory time τ = τ_0 + p (τ_{T-1} - τ_0) over the stored samples; the vector is
    ς(τ, k) - ς(τ_0, k) (`cluster_vectors_at`), a point of the polyline that `snap_vector` then returns (the
    earliest of equally near points, as `fgjax control` snaps a typed vector). p = 0 is the rest state."""
    p = np.asarray(positions, np.float64).reshape(-1)
    if p.shape != (s2.num_objects,):
        raise ValueError(f"positions must have shape [{s2.num_objects}] (one per object), got {list(p.shape)}")
    if not np.all(np.isfinite(p)) or np.any(p < 0) or np.any(p > 1):
        raise ValueError(f"positions must lie in [0, 1], got {p.tolist()}")
    t0, t1 = s2.traj_times[0], s2.traj_times[-1]
    out = np.zeros((s2.num_objects, 3))
    for k in range(s2.num_objects):
        on = cluster_vectors_at(s2, t0 + p[k] * (t1 - t0))[k]
        out[k] = snap_vector(s2, k, on)[0]
    return out


@jax.jit
def _activated(quats, log_scales, opacity_logits, sh0):
    """(covariances [M, 3, 3], rgbs [M, 3], opacities [M, 1]) from raw parameters; sh0 [M, 3] the DC term."""
    rot = quat_to_rotmat(quats)  # [M, 3, 3], any non-zero norm
    rs = rot * jnp.exp(log_scales)[:, None, :]  # R diag(s)
    cov = jnp.einsum("mij,mkj->mik", rs, rs, precision=HIGHEST)
    rgb = jnp.clip(SH_C0 * sh0 + 0.5, 0.0, 1.0)
    return cov, rgb, jax.nn.sigmoid(opacity_logits)[:, None]


def splat_arrays(g: Gaussians) -> tuple[Float[Array, "M 3 3"], Float[Array, "M 3"], Float[Array, "M 1"]]:
    """Activated (covariances, DC colours, opacities) of raw Gaussians (the module docstring's formulas)."""
    return _activated(jnp.asarray(g.quats), jnp.asarray(g.log_scales), jnp.asarray(g.opacity_logits),
                      jnp.asarray(g.sh)[:, 0])


def viewer_gaussians(run: LoadedRun, time: float | None, controls: Float[ArrayLike, " K"] | None) -> Splats:
    """What a viewer shows for its inputs: the active Gaussians, raw and activated (`Splats`).

    A pure function of its arguments (the run is read, never changed): only the Gaussians are computed, no image.

    Args:
        run: a loaded run.
        time: with ``controls`` None, the stage-1 scene at this normalised time (0..1).
        controls: [K] positions in [0, 1] along each object's trajectory (`trajectory_vectors`; 0 the rest
            state): the controlled scene, ``time`` unused. Needs stage-2 results.

    Returns:
        `Splats` of the M active Gaussians.
    """
    vectors = None if controls is None else trajectory_vectors(_need_s2(run), controls)
    g = scene_gaussians(run, time=None if vectors is not None else (0.0 if time is None else time), vectors=vectors)
    cov, rgb, opac = splat_arrays(g)
    return Splats(g, object_labels(run), g.means, np.asarray(cov, np.float32), np.asarray(rgb, np.float32),
                  np.asarray(opac, np.float32))


def _need_s2(run: LoadedRun) -> Stage2Result:
    if run.s2 is None:
        raise Stage2Error(f"{run.run_dir} has no stage-2 results: controls need `fgjax stage2 --run {run.run_dir}`")
    return run.s2
