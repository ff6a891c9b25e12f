"""Stage-2 results: the stage2.npz format, a loaded run, and renders of the controlled scene (DESIGN.md section 1,
steps 7-8).

The controlled scene for per-cluster vectors v [K, 3] is

    G_i(v) = G_i(t0) + [f_Θ(v_{k(i)}, X_i) - f_Θ(0, X_i)]   for clustered Gaussians (k(i) >= 0)
    G_i(v) = G_i(t0)                                       for all others

with G_i(t0) the reference scene (the stage-1 Gaussians deformed to the first training time t0, or the articulated
variant's re-fitted Gaussians) as (centre, raw wxyz quaternion, log-scale), X_i the canonical centre and f_Θ the
control network (`fgjax.models.control_net`). v = 0 reproduces the reference exactly; a cluster moves with its own
vector only. With ``Stage2Config.control_rigid`` each cluster is then moved by the rigid motion nearest the network's
(`controlled_gaussians`' ``rigid``). A user's vector is snapped to the nearest point of the cluster's trajectory
ς(·, k) (`snap_vector`).

RUN/stage2.npz holds labels [N], the dynamic set [N], discovery scores [N], trajectories [K, T, 3] at times [T], the
control network's leaves, the re-fitted Gaussians where the variant made them, and metadata as JSON; RUN/stage2.json
is a readable summary. Both are written atomically.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import zipfile
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from fgjax import cluster
from fgjax.gaussians import Gaussians, activate
from fgjax.geometry import fit_group_poses
from fgjax.io import atomic_write
from fgjax.method.stage1 import load_run
from fgjax.models.control_net import ControlNet, control_apply, control_init, per_gaussian_vectors
from fgjax.models.deform import deform_apply
from fgjax.models.model import render_params
from fgjax.models.posed import label_onehot, transform_gaussians
from fgjax.provenance import file_sha256
from fgjax.render.api import rasterization
from fgjax.train.checkpoint import CHECKPOINT_NAME

__all__ = ["STAGE2_NAME", "FORMAT_VERSION", "Stage2Error", "Stage2Result", "LoadedRun", "load_stage2", "save_stage2",
           "controlled_gaussians", "cluster_vectors_at", "snap_vector", "render_controlled", "posed_base",
           "render_clusters", "with_geometry", "with_refit", "render_capacity", "reference_scene"]


STAGE2_NAME = "stage2.npz"


FORMAT_VERSION = 1


class Stage2Error(RuntimeError):
    """A run without (usable) stage-2 results, or a stage-2 input that cannot work."""


class Stage2Result:
    """Stage-2 results (host-side). Arrays are numpy.

    labels: [N] int, cluster id 0..K-1 of each Gaussian slot, -1 static / noise / dead.
    dynamic: [N] bool, the discovered set D (before clustering).
    scores: [N] float, discovery scores.
    traj: [K, T, 3] ς(t, k) at `traj_times` (sorted training times).
    traj_times: [T].
    t0: the reference time (traj_times[0]).
    control: the trained `ControlNet`.
    meta: dict (config, report, timings, data_dir).
    refit: `Gaussians` (numpy leaves) of the controlled scene's reference when stage 2 re-fitted them under
        the tracked motion (`ArticulateConfig.refit_steps`), else None (the stage-1 model at t0).
    """

    def __init__(self, labels, dynamic, scores, traj, traj_times, control: ControlNet, meta: dict[str, Any],
                 refit: Gaussians | None = None):
        self.refit = refit
        self.labels = np.asarray(labels, np.int64)
        self.dynamic = np.asarray(dynamic, bool)
        self.scores = np.asarray(scores, np.float64)
        self.traj = np.asarray(traj, np.float64).reshape(-1, len(traj_times), 3)
        self.traj_times = np.asarray(traj_times, np.float64)
        self.control = control
        self.meta = meta

    @property
    def num_objects(self) -> int:
        return int(self.traj.shape[0])

    @property
    def t0(self) -> float:
        return float(self.traj_times[0])

    @property
    def rigid(self) -> bool:
        """Whether the controlled scene moves each object rigidly (`Stage2Config.control_rigid`; false for the
        results of a stage 2 older than the option)."""
        return bool(self.meta.get("config", {}).get("control_rigid", False))


def _atomic_bytes(path: Path, write) -> None:
    """`fgjax.io.atomic_write` into a folder made first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, write)


@functools.partial(jax.jit, static_argnames=("spec", "static"))
def _deformed(params: dict, t: Float[ArrayLike, ""], *, spec, static: bool):
    """(means, raw quats, log_scales) of the stage-1 model at time t: the canonical Gaussians plus the field's
    (dX, dq, ds) at t (unchanged when the run is static or has no field). One jitted function for every loaded
    run: JAX keeps one program per (spec, static, parameter shapes), so loading a run again compiles nothing."""
    g: Gaussians = params["gaussians"]
    if static or spec is None:
        return g.means, g.quats, g.log_scales
    dx, dq, ds = deform_apply(spec, params["deform"], g.means, t, quats=g.quats)
    return g.means + dx, g.quats + dq, g.log_scales + ds


def with_geometry(params: dict, means: Float[ArrayLike, "N 3"], quats: Float[ArrayLike, "N 4"],
                  log_scales: Float[ArrayLike, "N 3"]) -> dict:
    """``params`` with its Gaussians' centres, raw quaternions and log-scales replaced (opacities and SH kept)."""
    g: Gaussians = params["gaussians"]
    return {**params, "gaussians": Gaussians(means, log_scales, quats, g.opacity_logits, g.sh)}


def with_refit(params, refit):
    """Stage-1 `params` with their Gaussians replaced by stage 2's re-fitted ones (`refit`, numpy leaves;
    None: unchanged)."""
    if refit is None:
        return params
    return {**params, "gaussians": jax.tree_util.tree_map(jnp.asarray, refit)}


def render_capacity(run: LoadedRun) -> int | None:
    """Tile capacity for renders of moved or controlled geometry: 1.5 x the stage-1 run's (None: the
    rasterizer's default); moved Gaussians can crowd tiles more than stage 1 ever did."""
    cap = int(run.meta.get("capacity") or 0) or None
    return None if cap is None else int(cap * 1.5)


def reference_scene(run: LoadedRun, t: float) -> Gaussians:
    """Stage 1's Gaussians deformed to time `t` (raw parameters, with their opacities and colours): the
    reference scene that the tracked poses move and the re-fit starts from."""
    m, q, ls = run.deformed(t)
    g = run.state.params["gaussians"]
    return Gaussians(m, ls, q, g.opacity_logits, g.sh)


def controlled_gaussians(control: ControlNet, base: tuple, canonical: Float[ArrayLike, "N 3"],
                         labels: Int[ArrayLike, " N"], vectors: Float[ArrayLike, "K 3"], rigid: bool = False
                         ) -> tuple[Float[Array, "N 3"], Float[Array, "N 4"], Float[Array, "N 3"]]:
    """Geometry of the controlled scene (module docstring).

    Args:
        control: `ControlNet`.
        base: (means [N, 3], raw quats [N, 4], log_scales [N, 3]) of the stage-1 scene at t0.
        canonical: [N, 3] canonical centres X.
        labels: [N] int cluster ids (-1: not controlled).
        vectors: [K, 3] one control vector per cluster (K >= 1 when any label >= 0).
        rigid: each cluster moved by the rigid motion closest to the network's (`Stage2Config.control_rigid`):
            `fgjax.geometry.fit_group_poses` from the base centres to the network's, applied to the base
            centres and orientations; the base scales. Not differentiable (the fit is held constant).

    Returns:
        (means, quats, log_scales), each [N, ...].
    """

    means0, q0, s0 = base
    labels = jnp.asarray(labels)
    vectors = jnp.asarray(vectors, jnp.float32).reshape(-1, 3)
    v, mask = per_gaussian_vectors(vectors, labels)
    dx1, dq1, ds1 = control_apply(control, v, canonical, mask)
    dx0, dq0, ds0 = control_apply(control, jnp.zeros_like(v), canonical, mask)
    means = means0 + (dx1 - dx0)
    if rigid:

        poses = fit_group_poses(means0, means, labels, int(vectors.shape[0]))  # [K, 4, 4]
        means, quats = transform_gaussians(jnp.asarray(means0, jnp.float32), jnp.asarray(q0, jnp.float32), labels,
                                           poses)
        return means, quats, jnp.asarray(s0, jnp.float32)
    return means, q0 + (dq1 - dq0), s0 + (ds1 - ds0)


@dataclasses.dataclass
class LoadedRun:
    """A stage-1 run (config, state, spec, model.json) and, when present, its stage-2 result."""

    run_dir: Path
    cfg: Any
    state: Any
    spec: Any
    meta: dict[str, Any]
    s2: Stage2Result | None

    @property
    def static(self) -> bool:
        return bool(self.meta.get("static", False))

    def deformed(self, t: float):
        """(means, raw quats, log_scales) of the stage-1 model at time t."""
        return _deformed(self.state.params, jnp.asarray(t, jnp.float32), spec=self.spec, static=self.static)

    def base(self):
        """(means, raw quats, log_scales) of the controlled scene's reference: stage 2's re-fitted Gaussians
        when it made them, else the stage-1 model at t0."""
        if self.s2 is not None and self.s2.refit is not None:
            g = self.s2.refit
            return jnp.asarray(g.means), jnp.asarray(g.quats), jnp.asarray(g.log_scales)
        return self.deformed(self.s2.t0)

    def control_params(self):
        """Parameters whose opacities and colours the controlled scene renders with."""
        return with_refit(self.state.params, None if self.s2 is None else self.s2.refit)

    def render_geometry(self, means, quats, log_scales, viewmat, K, width: int, height: int, *, colors=None,
                        background=None, capacity=None, params=None):
        """Render given geometry with the run's opacities and colours (or `colors` [N, C]); ``params``: whose
        opacities and colours (default: stage 1's)."""

        params = with_geometry(self.state.params if params is None else params, means, quats, log_scales)
        vm = jnp.asarray(viewmat, jnp.float32)
        Kj = jnp.asarray(K, jnp.float32)
        if colors is None:
            bg = jnp.asarray(self.cfg.model.background if background is None else background, jnp.float32)
            img, alpha, info, _ = render_params(params, self.state.densify.alive, vm, Kj, 0.0, spec=None,
                                                sh_degree=self.cfg.model.sh_degree, width=int(width),
                                                height=int(height), background=bg, capacity=capacity,
                                                tile_size=self.cfg.train.tile_size)
            return img, alpha, info
        q, s, o = activate(params["gaussians"], self.state.densify.alive)
        return rasterization(params["gaussians"].means, q, s, o, jnp.asarray(colors, jnp.float32), vm, Kj,
                             int(width), int(height), background=None if background is None else
                             jnp.asarray(background, jnp.float32), capacity=capacity,
                             tile_size=self.cfg.train.tile_size, render_depth=False)


def load_stage2(run_dir: str | Path, *, require_stage2: bool = True) -> LoadedRun:
    """Load a run folder: stage 1 (`fgjax.method.stage1.load_run`) and RUN/stage2.npz.

    Raises:
        FileNotFoundError: not a trained run.
        Stage2Error: stage-2 results missing (when required) or unreadable.
    """

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder {run_dir} does not exist")
    cfg, state, spec, meta = load_run(run_dir)
    state.static = meta.get("static", False)
    p = run_dir / STAGE2_NAME
    if not p.exists():
        if require_stage2:
            raise Stage2Error(f"{run_dir} has no stage-2 results ({STAGE2_NAME}); run stage 2 first: "
                              f"fgjax stage2 --run {run_dir} --data DATA")
        return LoadedRun(run_dir, cfg, state, spec, meta, None)
    try:
        with open(p, "rb") as fh, np.load(fh, allow_pickle=False) as z:  # our handle: closed on a bad zip too
            m = json.loads(str(z["meta"]))
            if m.get("format_version") != FORMAT_VERSION:
                raise Stage2Error(f"{p}: format version {m.get('format_version')} != {FORMAT_VERSION}")
            template = control_init(jax.random.key(0), **m["control"])
            leaves, treedef = jax.tree_util.tree_flatten(template)
            new = [jnp.asarray(z[f"control_{i}"]) for i in range(len(leaves))]
            for a, b in zip(leaves, new, strict=True):
                if a.shape != b.shape:
                    raise Stage2Error(f"{p}: control parameter shape {b.shape} != {a.shape}")
            control = jax.tree_util.tree_unflatten(treedef, new)
            refit = None
            if "refit_means" in z.files:
                refit = Gaussians(*(np.asarray(z[f"refit_{f}"]) for f in
                                    ("means", "log_scales", "quats", "opacity_logits", "sh")))
                if refit.means.shape != tuple(state.params["gaussians"].means.shape):
                    raise Stage2Error(f"{p}: re-fitted Gaussians of shape {refit.means.shape} for "
                                      f"{tuple(state.params['gaussians'].means.shape)}")
            s2 = Stage2Result(z["labels"], z["dynamic"], z["scores"], z["traj"], z["traj_times"], control, m, refit)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:
        raise Stage2Error(f"{p} is not a readable stage-2 result: {e}") from e
    built_on = s2.meta.get("stage1_checkpoint")
    if built_on is not None:
        now = file_sha256(run_dir / CHECKPOINT_NAME)
        if built_on.get("sha256") != now:
            raise Stage2Error(f"{p} was built on stage-1 checkpoint {str(built_on.get('sha256'))[:12]} (step "
                              f"{built_on.get('step')}), but {run_dir / CHECKPOINT_NAME} is now {now[:12]} (step "
                              f"{int(state.step)}): stage 1 was trained again; run stage 2 again")
    if len(s2.labels) != state.params["gaussians"].means.shape[0]:
        raise Stage2Error(f"{p}: {len(s2.labels)} labels for {state.params['gaussians'].means.shape[0]} Gaussians "
                          "(stage 1 was re-trained after stage 2; run stage 2 again)")
    return LoadedRun(run_dir, cfg, state, spec, meta, s2)


def save_stage2(run_dir: Path, s2: Stage2Result) -> Path:
    """Write RUN/stage2.npz (atomic) and RUN/stage2.json (atomic, readable summary)."""
    leaves = jax.tree_util.tree_leaves(s2.control)
    arrays = {"labels": s2.labels.astype(np.int32), "dynamic": s2.dynamic, "scores": s2.scores.astype(np.float32),
              "traj": s2.traj.astype(np.float64), "traj_times": s2.traj_times,
              "meta": np.array(json.dumps(s2.meta))}
    for i, a in enumerate(leaves):
        arrays[f"control_{i}"] = np.asarray(a)
    if s2.refit is not None:
        for f in ("means", "log_scales", "quats", "opacity_logits", "sh"):
            arrays[f"refit_{f}"] = np.asarray(getattr(s2.refit, f), np.float32)
    p = run_dir / STAGE2_NAME
    _atomic_bytes(p, lambda f: np.savez(f, **arrays))
    summary = {k: v for k, v in s2.meta.items()}
    summary["trajectories"] = s2.traj.tolist()
    summary["traj_times"] = s2.traj_times.tolist()
    _atomic_bytes(run_dir / "stage2.json", lambda f: f.write(json.dumps(summary, indent=1).encode()))
    return p


def cluster_vectors_at(s2: Stage2Result, t: float) -> Float[np.ndarray, "K 3"]:
    """[K, 3] v_c(t, k) = ς(t, k) - ς(t0, k), linear in time between the stored samples."""
    tt = s2.traj_times
    out = np.zeros((s2.num_objects, 3))
    for k in range(s2.num_objects):
        for d in range(3):
            out[k, d] = np.interp(t, tt, s2.traj[k, :, d]) - s2.traj[k, 0, d]
    return out


def snap_vector(s2: Stage2Result, k: int, vector: Float[ArrayLike, "3"]) -> tuple[Float[np.ndarray, "3"], float]:
    """Snap a user displacement for object k (0-based) to its trajectory: (vector on ς(·, k), time)."""
    if not 0 <= k < s2.num_objects:
        raise ValueError(f"object {k + 1} out of range: the run has {s2.num_objects} object(s) (1..{s2.num_objects})")
    snap = cluster.snap_to_trajectory(s2.traj[k], np.asarray(vector, np.float64), times=s2.traj_times)
    return snap.point - s2.traj[k, 0], snap.t


def render_controlled(run: LoadedRun, vectors: Float[ArrayLike, "K 3"], viewmat: Float[ArrayLike, "4 4"],
                      K: Float[ArrayLike, "3 3"], width: int, height: int) -> Float[np.ndarray, "H W 3"]:
    """Image [H, W, 3] of the controlled scene for per-cluster vectors [K, 3] (used as given, not snapped)."""
    s2 = run.s2
    if s2 is None:
        raise Stage2Error("render_controlled needs stage-2 results")
    base = run.base()
    canonical = run.state.params["gaussians"].means
    vec = np.zeros((max(s2.num_objects, 1), 3)) if s2.num_objects == 0 else np.asarray(vectors, np.float64)
    geo = controlled_gaussians(s2.control, base, canonical, jnp.asarray(s2.labels), jnp.asarray(vec, jnp.float32),
                               rigid=s2.rigid)
    img, _, _ = run.render_geometry(*geo, viewmat, K, width, height, params=run.control_params())
    return np.clip(np.asarray(img), 0.0, 1.0)


def posed_base(run: LoadedRun, labels: Int[ArrayLike, " N"], poses: Float[ArrayLike, "K 4 4"]
               ) -> tuple[Float[Array, "N 3"], Float[Array, "N 4"], Float[Array, "N 3"]]:
    """(means [N, 3], raw quats [N, 4], log-scales [N, 3]) of the controlled scene's reference (`LoadedRun.base`)
    with each object's Gaussians (``labels`` [N], -1 static) moved rigidly by its pose (``poses`` [K, 4, 4],
    x -> R x + t in scene units; finite); no control network."""

    if run.s2 is None:
        raise Stage2Error("posed_base needs stage-2 results")
    k = run.s2.num_objects
    poses = np.asarray(poses, np.float32)
    if poses.shape != (k, 4, 4):
        raise ValueError(f"posed_base: poses must have shape [{k}, 4, 4], got {list(poses.shape)}")
    if not np.isfinite(poses).all():
        raise ValueError("posed_base: poses must be finite")
    m0, q0, ls0 = run.base()
    m, q = transform_gaussians(m0, q0, jnp.asarray(labels), jnp.asarray(poses))
    return m, q, ls0


def render_clusters(run: LoadedRun, viewmat: Float[ArrayLike, "4 4"], K: Float[ArrayLike, "3 3"], width: int,
                    height: int, *, t: float | None = None, vectors: Float[ArrayLike, "K 3"] | None = None,
                    source: str = "stage1", alpha_threshold: float = 0.5, labels: Int[ArrayLike, " N"] | None = None,
                    poses: Float[ArrayLike, "K 4 4"] | None = None) -> Int[np.ndarray, "H W"]:
    """Per-pixel object ids [H, W] int (0 = static or background, k = cluster k - 1 + 1).

    One-hot cluster features (channel 0 for every Gaussian outside the clusters, channel k for
    cluster k - 1) are composited like colour; a pixel takes the argmax channel, and 0 where the
    rendered alpha is below `alpha_threshold`. Geometry: the controlled scene for `vectors` [K, 3] when
    given; else, at time `t` (default: the reference time), ``source`` "stage1": the stage-1 model at t
    (the scene `fgjax render` draws in colour for the same camera), or "control": the controlled scene
    with each object at its trajectory vector v_c(t, k). ``poses`` [K, 4, 4] (instead of `vectors`): the
    controlled scene's reference (`LoadedRun.base`) with each object's Gaussians moved rigidly by its pose, no
    control network (evaluation: the gt motion). ``labels`` [N] (-1..K-1) replaces stage 2's clustering
    (evaluation: `fgjax.method.evaluate`'s labels taken from the ground truth).
    """
    s2 = run.s2
    if s2 is None:
        raise Stage2Error("render_clusters needs stage-2 results")
    if source not in ("stage1", "control"):
        raise ValueError(f"render_clusters: source must be 'stage1' or 'control', got {source!r}")
    labels = s2.labels if labels is None else np.asarray(labels, np.int64)
    if labels.shape != s2.labels.shape:
        raise ValueError(f"render_clusters: labels must have shape {list(s2.labels.shape)}, got {list(labels.shape)}")
    if poses is not None and vectors is not None:
        raise ValueError("render_clusters: give vectors or poses, not both")
    if poses is None and vectors is None and source == "control" and s2.num_objects > 0:  # each object at v_c(t, k)
        vectors = cluster_vectors_at(s2, s2.t0 if t is None else float(t))
    params = None
    if poses is not None:
        geo, params = posed_base(run, labels, poses), run.control_params()
    elif vectors is not None:
        geo = controlled_gaussians(s2.control, run.base(), run.state.params["gaussians"].means,
                                   jnp.asarray(labels), jnp.asarray(np.asarray(vectors).reshape(-1, 3), jnp.float32),
                                   rigid=s2.rigid)
        params = run.control_params()
    else:
        geo = run.deformed(s2.t0 if t is None else float(t))

    feat, alpha, _ = run.render_geometry(*geo, viewmat, K, width, height, colors=label_onehot(labels, s2.num_objects),
                                         params=params)
    ids = np.argmax(np.asarray(feat), axis=-1)
    return np.where(np.asarray(alpha) >= alpha_threshold, ids, 0).astype(np.int64)
