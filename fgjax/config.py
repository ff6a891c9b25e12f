"""Typed run configuration: per-component frozen dataclasses, TOML loading, ``key=value`` overrides.

A TOML file has one table per component ([data], [model], [deform], [train], [densify], [flow],
[pose], [static] for stage 1; [stage2] for the paper's stage 2 and [articulate] for the articulated variant); every
key is optional (defaults below). Overrides use dotted names,
``train.steps=3000``, and are type-checked against the field's declared type. Components never import
this module: the pipeline converts these dataclasses into the arguments they take.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

__all__ = [
    "DataConfig", "ModelConfig", "DeformConfig", "TrainConfig", "DensifyConfig", "FlowConfig",
    "PoseConfig", "StaticConfig", "Stage2Config", "ArticulateConfig", "Config", "validate_stage1",
    "validate_stage2", "validate_articulate", "load_config", "apply_overrides", "to_toml", "from_dict",
    "ConfigError",
]


class ConfigError(ValueError):
    """A bad configuration value or key (the message names the key)."""


@dataclasses.dataclass(frozen=True)
class DataConfig:
    downscale: int = 1
    """Integer image downscale factor at load time."""
    test_every_train: int = 0
    """If > 0 and the dataset has no test split, hold out every n-th training frame."""


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    sh_degree: int = 3
    """Highest SH degree (0..3)."""
    init_points: int = 20000
    """Initial Gaussians (no SfM points needed; see `init`)."""
    init: str = "flow"
    """"flow": points triangulated from optical flow between posed frames (`fgjax.method.init_points`),
    topped up with random points; "depth": the measured depth of the training frames back-projected
    (`fgjax.method.init_points.depth_point_cloud`; an RGB-D capture), topped up the same way, and "flow" on a
    scene without depth maps; "random": random points in the scene box that some camera sees."""
    init_random_fraction: float = 0.2
    """With init = "flow" or "depth": this fraction of the initial points is random (what the flow or sensor misses)."""
    init_flow_gap: int = 4
    """With init = "flow": frame offset of the triangulated pairs."""
    capacity: int = 60000
    """Fixed number of Gaussian slots (densification stops when full)."""
    init_opacity: float = 0.1
    """Initial activated opacity."""
    init_scale: float = 1.0
    """Multiplier on the initial neighbour-distance scale."""
    background: tuple[float, ...] = (1.0, 1.0, 1.0)
    """Background RGB used in rendering (matches the loader's alpha compositing)."""
    seed: int = 0
    """Seed for initialisation and training randomness."""


@dataclasses.dataclass(frozen=True)
class DeformConfig:
    kind: str = "hash"
    """"frequency" (Deformable-3DGS 8x256 MLP), "hash" (hash grid + small MLP) or "bases" (a few rigid motions
    blended per point by weights from the hash-grid MLP: `fgjax.models.deform`)."""
    depth: int = 2
    """MLP hidden layers (8 for Deformable-3DGS)."""
    width: int = 64
    """MLP width (256 for Deformable-3DGS)."""
    skip: int = 0
    """Re-concatenate the input after this layer (4 for Deformable-3DGS; 0 = none)."""
    x_freqs: int = 10
    """Frequencies of gamma(X) for the frequency field."""
    t_freqs: int = 6
    """Frequencies of gamma(t)."""
    hash_levels: int = 8
    hash_log2_table: int = 15
    hash_features: int = 2
    hash_base_res: int = 8
    hash_max_res: int = 256
    x_freqs_hash: int = 2
    """Low frequencies of gamma(X) next to the hash features."""
    bases: int = 6
    """"bases" kind: rigid motions, the static one included."""
    knots: int = 16
    """"bases" kind: control times of each motion over the clip."""
    anchor: str = "none"
    """"first": the field is zero at the first training time (`fgjax.models.deform.DeformSpec.anchor`): the canonical
    Gaussians are the first frame (where ``model.init = "flow"`` puts them) and a constant offset of the whole scene,
    which neither the flow loss nor the photometric loss pins, cannot drift in. "none": the network's choice."""
    init: str = "random"
    """"bases" kind: "random" logits, or "flow": placed on the moving clusters that the flow finds after the
    warm-up (`fgjax.method.bases_init`)."""
    hold: int = 150
    """With init = "flow": steps after the placement in which only the bases' motions and pivots train, the weights
    held, so that each motion fits its cluster before a weight can leave it (docs/benchmarks.md)."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    steps: int = 6000
    """Optimisation steps."""
    batch_size: int = 1
    """Cameras per step (data-parallel over devices when > 1)."""
    warmup_steps: int = 500
    """Steps with the deformation field off (static Gaussians only), as in Deformable-3DGS."""
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    """Mean learning rates (times the scene scale), exponentially decayed over `steps`."""
    lr_deform: float = 1.6e-4
    lr_deform_final: float = 1.6e-5
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_sh: float = 2.5e-3
    """SH DC learning rate; higher orders use lr_sh / 20."""
    lr_hash_factor: float = 10.0
    """Multiplier on lr_deform for the hash tables (grids train faster at higher rates)."""
    sh_increase_every: int = 1000
    """Raise the active SH degree by one every n steps (up to model.sh_degree)."""
    lambda_dssim: float = 0.2
    """Loss = (1 - l) L1 + l (1 - SSIM)."""
    scale_reg: float = 0.01
    """Weight of the scale regulariser mean(relu(max scale - scale_reg_max))."""
    scale_reg_max: float = 0.05
    """Scales above this (scene units) are penalised."""
    rigid_weight: float = 0.0
    """Weight of the isometry regulariser on the deformation (``fgjax.train.losses.isometry_loss``: neighbour
    distances keep their canonical length; 0: off)."""
    rigid_scale_weight: float = 0.0
    """Weight of ``fgjax.train.losses.scale_change_loss`` (deformed Gaussians keep their sizes; 0: off)."""
    rigid_cap: float = 0.0
    """Saturation of one neighbour pair's relative stretch in that regulariser (cap tanh(stretch / cap)), so
    that pairs spanning a moving part's boundary break instead of holding the part in place (0: linear)."""
    depth_weight: float = 0.0
    """Weight of ``fgjax.train.losses.depth_loss`` (rendered against measured depth, on the pixels that have one)
    where the scene has depth maps (an RGB-D capture); ignored, with one log line, where it has none (0: off)."""
    rigid_neighbours: int = 8
    """Neighbours per Gaussian in that regulariser (graph rebuilt after each densification)."""
    coarse_to_fine: int = 0
    """If > 0: the first this-many steps train on 2x2-averaged images at half resolution (cheaper steps;
    the flow loss waits for full resolution)."""
    time_curriculum: int = 0
    """If > 0: frames are drawn only from the earliest part of the video, a window that starts at
    `time_window_start` of the frames (in time order) during the warm-up and opens linearly to all frames
    over this many steps after it. Parts then move a little at a time, so the local photometric and flow
    gradients can follow them (0: all frames from the start)."""
    field_only_steps: int = 0
    """Steps right after the warm-up in which only the deformation field (and camera poses) train, the
    canonical Gaussians frozen, so that a part's changed state must be explained by moving it rather
    than by re-colouring it (0: off)."""
    error_sampling: float = 0.0
    """Fraction of the steps that draw their frames with probability proportional to each frame's squared
    last MSE (the frames where a part has moved are the worst ones); the rest draw uniformly (0: off)."""
    time_window_start: float = 0.1
    """Fraction of the frames (earliest first) in the window during the warm-up (with time_curriculum)."""
    log_every: int = 100
    """Host sync / progress line every n steps."""
    eval_every: int = 0
    """Evaluate on test views every n steps (0: only at the end)."""
    checkpoint_every: int = 1000
    """Write a checkpoint every n steps (and at the end)."""
    capacity_margin: float = 1.5
    """Tile-intersection capacity = margin x the largest count over the training cameras."""
    tile_size: int = 8
    tile_capacity: int = 0
    """Static tile-intersection capacity of the step (0: sized from the training cameras; grows on overflow)."""
    video_frames: int = 30
    """Frames of the time-sweep video (0: none)."""


@dataclasses.dataclass(frozen=True)
class DensifyConfig:
    enabled: bool = True
    start: int = 500
    stop: int = 4000
    every: int = 100
    grad_threshold: float = 0.0002
    """Mean screen-space gradient norm (NDC units, as 3DGS) above which a Gaussian is densified."""
    percent_dense: float = 0.01
    """Gaussians larger than this fraction of the scene extent are split, smaller ones cloned."""
    prune_opacity: float = 0.005
    reset_every: int = 3000
    """Opacity reset period (0: never)."""
    max_world_scale: float = 0.1
    """Prune Gaussians whose largest scale exceeds this fraction of the scene extent."""


@dataclasses.dataclass(frozen=True)
class FlowConfig:
    enabled: bool = False
    """Add beta L_uGS (needs optical flow; estimated and cached when absent)."""
    weight: float = 0.01
    """beta."""
    method: str = "dis_deepflow"
    threshold: float = 0.5
    """"pair": flow-target magnitude threshold (pixels) below which motion counts as static; "track": residuals under
    this many pixels cost nothing (0: off)."""
    loss: str = "pair"
    """Which flow loss: "pair" is L_uGS of consecutive frames (the paper; `fgjax.flow.gaussian_flow_loss`); "track"
    is the first frame's pixels tracked by chaining the optical flow through the video (forward-backward checked)
    against the rendered correspondence of the Gaussians that paint them there (`fgjax.flow.track`): positions
    instead of velocities, no camera flow in the target."""
    gaussian_flow: str = "isotropic"
    """The rendered dynamic Gaussian flow of the "pair" loss: "isotropic" composites each Gaussian's centre
    displacement (the paper's form); "anisotropic" GaussianFlow's affine flow of each Gaussian's 2D shape
    (`fgjax.flow.dynamic_gaussian_flow`)."""
    camera_depth: str = "composited"
    """The depth the "pair" loss's camera flow u_cam is computed from: "composited" is 1 / sum_i w_i / Z_i, for which
    Lemma 1's residual vanishes (DESIGN.md section 1, step 4); "expected" is sum_i w_i Z_i / alpha, which leaves the
    residual in the target (`fgjax.flow.maps_camera_flow`)."""
    norm: str = "l1"
    """The flow loss's penalty on each pixel's residual (the "pair" loss's r = u - u_cam - u~_GS,
    `fgjax.flow.flow_loss`; the "track" loss's r = C - D, `fgjax.flow.track`): "l1" is |r_x| + |r_y|;
    "charbonnier" is c^2 (sqrt(1 + |r|^2 / c^2) - 1) with c = ``charbonnier_px``, squared below c and linear
    beyond. Under L1 a deformation field shared by the whole scene learns none of a small part's motion from
    velocity targets; under the squared form it does (docs/benchmarks.md, "Can the field learn a local motion?")."""
    charbonnier_px: float = 10.0
    """c of ``norm = "charbonnier"``, in pixels."""
    photo_motion: float = 1.0
    """While the flow loss is on, the factor on the photometric loss's gradient into the deformation field's
    displacements dx (the flow loss's reaches them in full). 1: both losses train the motion (the paper); 0: the
    motion is learned from the dynamic flow alone and the photometric loss trains appearance, sizes and rotations.
    With canonical Gaussians fitted before the parts move (the warm-up), the photometric loss prefers them where they
    are and pulls a part back from the motion the flow loss gives it (docs/benchmarks.md, "Do the parts move?")."""
    start: int = 1000
    """First step with the flow loss (it also needs the deformation field on, i.e. after the warm-up).
    Training flows come from ``method`` (OpenCV, cached under RUN/flow_cache) unless passed to
    ``train_stage1(flows=...)``; the camera flow is the exact reprojection of the rendered depth of frame t-1."""


@dataclasses.dataclass(frozen=True)
class PoseConfig:
    enabled: bool = False
    """Refine per-frame se(3) camera deltas."""
    lr: float = 1e-4
    lr_final: float = 1e-6
    bundle: bool = False
    """Before training, refine the written poses by a bundle adjustment over optical-flow tracks
    (`fgjax.method.poses`); the corrections become the initial pose deltas (needs ``enabled``)."""
    bundle_prior_deg: float = 1.0
    """Prior standard deviation of the written rotations' errors (degrees)."""
    bundle_prior_trans: float = 0.05
    """Prior standard deviation of the written camera positions' errors (scene units)."""
    bundle_cauchy_px: float = 0.25
    """Final Cauchy scale of the reprojection residuals (pixels)."""
    bundle_fb_px: float = 0.0
    """> 0: the bundle adjustment's flow tracks stop where the forward-backward round trip misses by this many
    pixels or more (`fgjax.data.opticalflow.forward_backward_mask`: occlusions, flow smoothed across edges); 0: off."""


@dataclasses.dataclass(frozen=True)
class StaticConfig:
    detect: bool = True
    """Detect a static scene from consecutive-frame residuals after camera-motion compensation."""
    force: str = "auto"
    """"auto", "static" or "dynamic"."""
    threshold: float = 0.02
    """Mean absolute photometric residual above which frames count as dynamic."""


@dataclasses.dataclass(frozen=True)
class Config:
    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    deform: DeformConfig = DeformConfig()
    train: TrainConfig = TrainConfig()
    densify: DensifyConfig = DensifyConfig()
    flow: FlowConfig = FlowConfig()
    pose: PoseConfig = PoseConfig()
    static: StaticConfig = StaticConfig()
    stage2: Stage2Config = dataclasses.field(default_factory=lambda: Stage2Config())
    articulate: ArticulateConfig = dataclasses.field(default_factory=lambda: ArticulateConfig())


def _coerce(key: str, typ: Any, value: Any) -> Any:
    origin = typing.get_origin(typ)
    if typ is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no"):
            return value.lower() in ("true", "1", "yes")
        raise ConfigError(f"config key '{key}' expects a bool; got {value!r}")
    if typ is int:
        if isinstance(value, bool):
            raise ConfigError(f"config key '{key}' expects an int; got {value!r}")
        if isinstance(value, int):
            return value
        if isinstance(value, str):
            try:
                return int(value)
            except ValueError:
                pass
        raise ConfigError(f"config key '{key}' expects an int; got {value!r}")
    if typ is float:
        if isinstance(value, bool):
            raise ConfigError(f"config key '{key}' expects a float; got {value!r}")
        if isinstance(value, int | float):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                pass
        raise ConfigError(f"config key '{key}' expects a float; got {value!r}")
    if typ is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"config key '{key}' expects a string; got {value!r}")
    if origin is types.UnionType:  # float | str: a number where it parses as one, else the string
        args = typing.get_args(typ)
        if float in args and not isinstance(value, bool):
            try:
                return float(value)
            except (TypeError, ValueError):
                pass
        if str in args and isinstance(value, str):
            return value
        raise ConfigError(f"config key '{key}' expects one of {[a.__name__ for a in args]}; got {value!r}")
    if origin is tuple:
        if isinstance(value, str):
            value = [v for v in value.strip("()[] ").split(",") if v.strip()]
        if not isinstance(value, list | tuple):
            raise ConfigError(f"config key '{key}' expects a list; got {value!r}")
        return tuple(_coerce(key, typing.get_args(typ)[0], v) for v in value)
    raise ConfigError(f"config key '{key}' has an unsupported type {typ}")


def _section_types(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def from_dict(d: dict[str, Any], base: Config | None = None) -> Config:
    """Config from nested {section: {key: value}}, on top of `base` (defaults), type-checked."""
    base = base or Config()
    sections = {f.name: f for f in dataclasses.fields(Config)}
    updates = {}
    for sec, vals in d.items():
        if sec not in sections:
            raise ConfigError(f"unknown config section '{sec}' (choose from {', '.join(sections)})")
        if not isinstance(vals, dict):
            raise ConfigError(f"config section '{sec}' must be a table; got {vals!r}")
        cur = getattr(base, sec)
        types = _section_types(type(cur))
        kw = {}
        for k, v in vals.items():
            if k not in types:
                raise ConfigError(f"unknown config key '{sec}.{k}' (choose from {', '.join(types)})")
            kw[k] = _coerce(f"{sec}.{k}", types[k], v)
        updates[sec] = dataclasses.replace(cur, **kw)
    cfg = dataclasses.replace(base, **updates)
    validate_stage1(cfg)
    validate_stage2(cfg.stage2)
    validate_articulate(cfg.articulate)
    return cfg


def apply_overrides(cfg: Config, overrides: list[str]) -> Config:
    """Apply ``section.key=value`` strings (type-checked; errors name the key)."""
    d: dict[str, dict[str, Any]] = {}
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.key=value")
        k, v = item.split("=", 1)
        k = k.strip()
        if k.count(".") != 1:
            raise ConfigError(f"override key '{k}' must be section.key (e.g. train.steps)")
        sec, name = k.split(".")
        d.setdefault(sec, {})[name] = v.strip()
    return from_dict(d, cfg)


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults, then the TOML file at `path` (if any), then the overrides."""
    cfg = Config()
    if path is not None:
        p = Path(path)
        try:
            with open(p, "rb") as f:
                data = tomllib.load(f)
        except FileNotFoundError:
            raise ConfigError(f"config file {p} does not exist") from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"config file {p} is not valid TOML: {e}") from None
        cfg = from_dict(data, cfg)
    return apply_overrides(cfg, overrides or [])


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, tuple | list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def to_toml(cfg: Config) -> str:
    """The full effective config as TOML (round-trips through `load_config`)."""
    lines = []
    for f in dataclasses.fields(cfg):
        lines.append(f"[{f.name}]")
        sec = getattr(cfg, f.name)
        for g in dataclasses.fields(sec):
            lines.append(f"{g.name} = {_toml_value(getattr(sec, g.name))}")
        lines.append("")
    return "\n".join(lines)


def to_dict(cfg: Config) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


@dataclasses.dataclass(frozen=True)
class Stage2Config:
    """Stage 2, the paper's chain (DESIGN.md section 1, steps 2 and 5-8): discovery, DBSCAN, trajectories,
    control network. ``variant`` names the chain that runs; "articulated" composes it with `ArticulateConfig`."""

    variant: str = "paper"
    """"paper": trajectories from the stage-1 deformation field (`fgjax.method.run_stage2`); "articulated": rigid
    parts tracked in the images, re-fitted and relabelled (`fgjax.articulate.run_articulated`)."""
    flow_method: str = "dis_deepflow"
    """OpenCV optical-flow method (`fgjax.data.opticalflow.METHODS`)."""
    flow_cache: str = ""
    """Flow cache folder ("": RUN/flow_cache)."""
    threshold_px: float | str = "otsu"
    """Binarisation of |u - u_cam|: "otsu" (per frame) or a number of pixels."""
    min_px: float = 0.5
    """Floor of the Otsu threshold (pixels)."""
    min_alpha: float = 0.5
    """Pixels whose rendered alpha is below this have no trusted depth and are left out of the masks."""
    score_threshold: float | str = "otsu"
    """Cut of the per-Gaussian discovery scores: "otsu" or a number in [0, 1]."""
    min_score: float = 0.05
    """Scores below this are never dynamic."""
    camera_correction: str = "auto"
    """Correct each pair's relative camera pose from the flow of the static majority of pixels before |u - u_cam| is
    thresholded (`fgjax.method.camera.camera_correction`): "on", "off", or "auto" (on when stage 1 refined the
    poses)."""
    cluster_method: str = "dbscan"
    """"dbscan" or "hdbscan" (`fgjax.cluster.cluster_dynamic`)."""
    eps: float = 0.05
    """DBSCAN radius in scene units."""
    min_samples: int = 5
    """DBSCAN's core-point neighbourhood size."""
    min_fraction: float = 0.05
    """Clusters smaller than this fraction of the dynamic set are dropped."""
    auto_eps: bool = False
    """Choose eps from the k-distance curve (`fgjax.cluster.auto_eps`)."""
    control_encoding: str = "frequency"
    """The control network's encoding E of the canonical centre X: "frequency" (γ, NeRF's) or "hashgrid" (a
    multiresolution hash grid, `fgjax.models.control_net.HASH_LEVELS`...)."""
    hidden: int = 64
    """Control network width."""
    depth: int = 3
    """Control network hidden layers."""
    n_freqs_x: int = 6
    """Frequency-encoding octaves of the canonical centre."""
    n_freqs_v: int = 4
    """Frequency-encoding octaves of the control vector."""
    distill_steps: int = 500
    """Adam steps distilling the trajectories' geometry into the control network."""
    distill_batch: int = 8
    """Training times per distillation step (a random minibatch)."""
    photo_steps: int = 200
    """Steps of the photometric (+ beta L_uGS) fine-tuning of the control network; 0: none."""
    control_rigid: bool = False
    """Move each object by the rigid motion closest to the network's output (`fgjax.method.result.
    controlled_gaussians`); False: the network's output as it is (the paper's)."""
    flow_weight: float = 0.01
    """beta of L_uGS in the photometric phase (0: photometric loss only)."""
    flow_threshold: float = 0.5
    """|u - u_cam| below this (pixels) counts as static in L_uGS (0: off)."""
    lr: float = 2e-3
    """Learning rate of the control network."""
    seed: int = 0
    """Seed of every random draw in stage 2."""


@dataclasses.dataclass(frozen=True)
class ArticulateConfig:
    """The articulated variant (`fgjax.articulate`): parts tracked as rigid bodies on revolute or prismatic joints,
    the scene re-fitted under their motion, labels refined. docs/architecture.md describes each step."""

    link_min_corr: float = -1.0
    """DBSCAN links two dynamic Gaussians within eps only when their activity profiles over the pairs correlate by
    at least this much (`fgjax.cluster.cluster_by_motion`); -1: every pair within eps (position alone, the
    paper's step 6)."""
    merge_eps: float = 0.05
    """Join DBSCAN clusters whose closest members are within this distance and whose motion profiles correlate
    (`fgjax.cluster.merge_fragments`); 0: off."""
    split_motion: bool = True
    """Split clusters whose members move at different times (`fgjax.cluster.split_by_motion`)."""
    local_radius: float = 0.1
    """Second selection pass in each cluster's own moving frames (`fgjax.cluster.localize_clusters`) over the
    Gaussians within this radius; 0: off."""
    local_threshold: float = 0.2
    """The second pass's score cut (share of a Gaussian's painted weight on moving pixels in those frames)."""
    cut_after_local: bool = True
    """Apply the size cut after the second pass (``local_min_fraction`` of the clustered Gaussians) rather than
    before it; before it only clusters under ``local_floor`` of the dynamic set drop."""
    local_min_fraction: float = 0.10
    """The size cut after the second pass, as a fraction of the clustered Gaussians."""
    local_floor: float = 0.01
    """With ``cut_after_local``: clusters under this fraction of the dynamic set drop before the second pass."""
    track_active: float = 0.2
    """Track an object only in its moving frames (`fgjax.cluster.moving_frames` with this ``active`` fraction,
    widened by one frame); 0: in every frame."""
    track_photo: int = 50
    """Adam steps per frame of photometric tracking (`fgjax.articulate.phototrack`); 0: flow-based tracking
    (`fgjax.articulate.track`)."""
    track_photo_next: int = 0
    """Steps per frame in the rounds after the first; 0: as ``track_photo``."""
    track_photo_radius: float = 0.1
    """Candidates of the photometric tracker's soft membership (scene units; 0: the labels as they are)."""
    track_only_moving: bool = True
    """Redraw, in each frame, only the objects fitted there (the others are drawn once per frame)."""
    track_rest: bool = True
    """Put each object's still spans back at rest where that renders closer (`track_photometric`'s
    ``rest_check``)."""
    track_subset_margin: int = 2
    """Draw only the changing Gaussians and those whose tiles meet theirs, widened by this many tiles; -1: all."""
    track_joints: str = "auto"
    """Flow tracking: "auto" fits one revolute or prismatic joint per object over its pairs
    (`fgjax.articulate.track.fit_joint`), "off" keeps the pair-by-pair poses."""
    track_rounds: int = 3
    """Rounds of photometric tracking and re-fitting; later rounds render the previous round's re-fitted scene."""
    track_converged_deg: float = 15.0
    """From round 3 on, an object whose joint kept its kind and moved its axis by less than this (degrees) is not
    tracked again; 0: every round tracks every object."""
    hinge_up_deg: float = 25.0
    """A hinge within this many degrees of the cameras' up is made vertical, when the cameras are level
    (`fgjax.articulate.articulation.camera_tilt`) and the hinge is not far off its part; 0: off."""
    hinge_trial: int = 150
    """Re-fit steps of each candidate of the hinge trial (`fgjax.articulate.trial.hinge_trial`); 0: off."""
    hinge_trial_race: float = 0.2
    """Share of the hinge trial's steps that every candidate gets; then only the given poses, the best slide and the
    best edge go on for the rest (successive halving); 1: every candidate gets all of them."""
    hinge_trial_margin: float = 0.02
    """An edge replaces the given poses only when its re-fitted loss is below (1 - margin) times theirs; a slide
    when it is at most (1 + margin) times theirs."""
    hinge_trial_slide: bool = True
    """The trial also tries two slides (`fgjax.articulate.articulation.slide_from_poses`)."""
    hinge_trial_search_slides: bool = True
    """The trial's slides are also tried with their amounts searched in the images."""
    hinge_trial_edges: int = 2
    """How many of the part's four edges the trial re-fits (those the images score best)."""
    refit_steps: int = 600
    """Steps of `fgjax.articulate.refit.refit_gaussians` per round; 0: the controlled scene moves stage 1's
    Gaussians."""
    refit_lr_scale: float = 1.0
    """Every learning rate of the re-fit (stage 1's groups and schedules) times this."""
    relabel_steps: int = 600
    """The first steps of each re-fit decide, for each Gaussian near a cluster, whether it moves with it; 0: off."""
    relabel_radius: float = 0.1
    """Candidates of the relabelling: Gaussians within this radius (scene units) of a cluster."""
    ghost_radius: float = 0.03
    """Before each re-fit, static Gaussians within this distance of a part's swept volume start it faded to
    ``ghost_opacity`` (`fgjax.cluster.near_swept`); 0: off."""
    ghost_opacity: float = 0.05
    """The opacity the faded Gaussians start a re-fit at (at most), in (0, 1)."""
    hull_fill: bool = False
    """Static Gaussians inside the convex hull of a cluster's opaque members join it (`fgjax.cluster.fill_hulls`).
    This and the other label passes (``hinge_fill``, ``isolated_factor``, ``colour_radius``, ``through_prune``) are
    off by default: together they lower the ARI on the scene family's tuning and validation seeds
    (docs/benchmarks.md, "Label passes"); `experiments/articulated.toml` and `experiments/demo_quick.toml` turn them
    on for the hand-made scenes."""
    hull_opacity: float = 0.7
    """Members with at least this opacity span the hulls (and the hinge fill's part)."""
    hull_max_growth: float = 0.6
    """A hull holding more static Gaussians than this times its cluster's size is not filled."""
    hinge_fill: bool = False
    """Static Gaussians along a turning part's hinge join it (`fgjax.cluster.fill_hinges`); off by default (see
    ``hull_fill``)."""
    hinge_radius: float = 0.15
    """The hinge fill's cylinder radius, as a fraction of the part's largest distance from its axis."""
    hinge_reach: float = 0.15
    """The hinge fill skips a part whose nearest opaque member is farther than this fraction from the axis."""
    hinge_min_deg: float = 20.0
    """The hinge fill treats a part as turning when its poses turn by at least this many degrees."""
    isolated_factor: float = 0.0
    """Members farther from every other member than this times their cluster's median spacing become static
    (`fgjax.cluster.drop_isolated`); 0: off (the default, see ``hull_fill``), else >= 1."""
    colour_radius: float = 0.0
    """Each part's outline relabelled by colour against the static Gaussians within this distance
    (`fgjax.cluster.refine_by_colour`); 0: off (the default, see ``hull_fill``)."""
    colour_components: int = 4
    """Gaussian-mixture components of each colour model."""
    colour_separation: float = 0.65
    """Parts whose colour models separate members from surroundings with a balanced accuracy below this are left
    alone."""
    settle_rest: bool = True
    """After the label passes, each object's still spans are put back at rest where that renders closer
    (`fgjax.articulate.phototrack.settle_at_rest`)."""
    through_prune: float = 0.0
    """Static Gaussians with more than this share of their painted weight where the parts cover the pixel get
    opacity ~0 (`fgjax.articulate.labels.seen_through`); 0: off (the default, see ``hull_fill``)."""
    hull_refit_steps: int = 100
    """Re-fit steps after the label passes; 0: none."""


def _finite(x: float) -> bool:
    """Neither NaN nor infinite."""
    return x == x and abs(x) != float("inf")


def validate_stage1(cfg: Config) -> None:
    """Raise `ConfigError` naming ``section.key`` when a stage-1 value is out of its range (counts that must be
    positive, rates and weights that must be finite and positive or non-negative, choices among names)."""
    def need(ok: bool, key: str, want: str, value: Any) -> None:
        if not ok:
            raise ConfigError(f"config key '{key}' must be {want}; got {value!r}")

    d, m, f, t, dn, fl = cfg.data, cfg.model, cfg.deform, cfg.train, cfg.densify, cfg.flow
    need(d.downscale >= 1, "data.downscale", ">= 1", d.downscale)
    need(d.test_every_train >= 0, "data.test_every_train", ">= 0", d.test_every_train)
    need(0 <= m.sh_degree <= 3, "model.sh_degree", "in 0..3", m.sh_degree)
    need(m.init in ("flow", "depth", "random"), "model.init", "'flow', 'depth' or 'random'", m.init)
    need(m.init_points >= 1, "model.init_points", ">= 1", m.init_points)
    need(m.capacity >= m.init_points, "model.capacity", f">= model.init_points ({m.init_points})", m.capacity)
    need(0.0 <= m.init_random_fraction <= 1.0, "model.init_random_fraction", "in [0, 1]", m.init_random_fraction)
    need(m.init_flow_gap >= 1, "model.init_flow_gap", ">= 1", m.init_flow_gap)
    need(0.0 < m.init_opacity < 1.0, "model.init_opacity", "in (0, 1)", m.init_opacity)
    need(_finite(m.init_scale) and m.init_scale > 0, "model.init_scale", "> 0", m.init_scale)
    need(len(m.background) == 3 and all(0.0 <= c <= 1.0 for c in m.background), "model.background",
         "three numbers in [0, 1]", m.background)
    need(f.kind in ("hash", "frequency", "bases"), "deform.kind", "'hash', 'frequency' or 'bases'", f.kind)
    need(f.bases >= 2, "deform.bases", ">= 2", f.bases)
    need(f.knots >= 2, "deform.knots", ">= 2", f.knots)
    for k in ("depth", "width", "hash_levels", "hash_features", "hash_base_res", "hash_max_res"):
        need(getattr(f, k) >= 1, f"deform.{k}", ">= 1", getattr(f, k))
    for k in ("skip", "x_freqs", "t_freqs", "x_freqs_hash"):
        need(getattr(f, k) >= 0, f"deform.{k}", ">= 0", getattr(f, k))
    need(t.steps >= 1, "train.steps", ">= 1", t.steps)
    need(t.batch_size >= 1, "train.batch_size", ">= 1", t.batch_size)
    for k in ("warmup_steps", "sh_increase_every", "eval_every", "checkpoint_every", "tile_capacity", "video_frames"):
        need(getattr(t, k) >= 0, f"train.{k}", ">= 0", getattr(t, k))
    need(t.log_every >= 1, "train.log_every", ">= 1", t.log_every)
    for k in ("lr_means", "lr_means_final", "lr_deform", "lr_deform_final", "lr_opacity", "lr_scales", "lr_quats",
              "lr_sh", "lr_hash_factor", "scale_reg_max"):
        v = getattr(t, k)
        need(_finite(v) and v > 0, f"train.{k}", "a finite number > 0", v)
    need(0.0 <= t.lambda_dssim <= 1.0, "train.lambda_dssim", "in [0, 1]", t.lambda_dssim)
    need(_finite(t.scale_reg) and t.scale_reg >= 0, "train.scale_reg", ">= 0", t.scale_reg)
    need(t.rigid_neighbours >= 1, "train.rigid_neighbours", ">= 1", t.rigid_neighbours)
    need(_finite(t.capacity_margin) and t.capacity_margin >= 1.0, "train.capacity_margin", ">= 1", t.capacity_margin)
    need(t.tile_size in (4, 8, 16, 32), "train.tile_size", "4, 8, 16 or 32", t.tile_size)
    for k in ("start", "stop", "every", "reset_every"):
        need(getattr(dn, k) >= 0, f"densify.{k}", ">= 0", getattr(dn, k))
    for k in ("grad_threshold", "percent_dense", "prune_opacity", "max_world_scale"):
        v = getattr(dn, k)
        need(_finite(v) and v >= 0, f"densify.{k}", "a finite number >= 0", v)
    need(_finite(fl.weight) and fl.weight >= 0, "flow.weight", ">= 0", fl.weight)
    need(_finite(fl.threshold) and fl.threshold >= 0, "flow.threshold", ">= 0", fl.threshold)
    need(fl.start >= 0, "flow.start", ">= 0", fl.start)
    need(f.anchor in ("none", "first"), "deform.anchor", "'none' or 'first'", f.anchor)
    need(f.init in ("random", "flow"), "deform.init", "'random' or 'flow'", f.init)
    need(f.hold >= 0, "deform.hold", ">= 0", f.hold)
    need(fl.loss in ("pair", "track"), "flow.loss", "'pair' or 'track'", fl.loss)
    need(fl.gaussian_flow in ("isotropic", "anisotropic"), "flow.gaussian_flow", "'isotropic' or 'anisotropic'",
         fl.gaussian_flow)
    need(fl.camera_depth in ("composited", "expected"), "flow.camera_depth", "'composited' or 'expected'",
         fl.camera_depth)
    need(_finite(fl.photo_motion) and 0 <= fl.photo_motion <= 1, "flow.photo_motion", "in [0, 1]", fl.photo_motion)
    need(fl.norm in ("l1", "charbonnier"), "flow.norm", "'l1' or 'charbonnier'", fl.norm)
    need(_finite(fl.charbonnier_px) and fl.charbonnier_px > 0, "flow.charbonnier_px", "a finite number > 0",
         fl.charbonnier_px)
    for k in ("lr", "lr_final"):
        v = getattr(cfg.pose, k)
        need(_finite(v) and v > 0, f"pose.{k}", "a finite number > 0", v)
    need(0.0 < t.time_window_start <= 1.0, "train.time_window_start", "in (0, 1]", t.time_window_start)
    need(_finite(t.depth_weight) and t.depth_weight >= 0, "train.depth_weight", "a finite number >= 0", t.depth_weight)
    need(0.0 <= t.error_sampling <= 1.0, "train.error_sampling", "in [0, 1]", t.error_sampling)
    for k in ("time_curriculum", "rigid_cap", "rigid_weight", "rigid_scale_weight", "coarse_to_fine",
              "field_only_steps"):
        need(getattr(t, k) >= 0, f"train.{k}", ">= 0", getattr(t, k))
    if cfg.pose.bundle and not cfg.pose.enabled:
        raise ConfigError("config key 'pose.bundle' needs 'pose.enabled = true' (the bundle adjustment's corrections "
                          "are stored as the pose deltas)")
    for k in ("bundle_prior_deg", "bundle_prior_trans", "bundle_cauchy_px"):
        need(getattr(cfg.pose, k) > 0, f"pose.{k}", "> 0", getattr(cfg.pose, k))
    need(cfg.pose.bundle_fb_px >= 0, "pose.bundle_fb_px", ">= 0 (0: off)", cfg.pose.bundle_fb_px)
    need(cfg.static.force in ("auto", "static", "dynamic"), "static.force", "'auto', 'static' or 'dynamic'",
         cfg.static.force)
    need(_finite(cfg.static.threshold) and cfg.static.threshold >= 0, "static.threshold", ">= 0",
         cfg.static.threshold)


def _check_types(section: str, cfg: Any) -> None:
    """Raise `ConfigError` naming ``section.field`` when a value does not have its field's declared type (a bool is
    not an int, an int is a float, ``float | str`` takes either)."""
    for name, typ in typing.get_type_hints(type(cfg)).items():
        v = getattr(cfg, name)
        allowed = typing.get_args(typ) if typing.get_origin(typ) is types.UnionType else (typ,)
        ok = any(
            (t is bool and isinstance(v, bool))
            or (t is int and isinstance(v, int) and not isinstance(v, bool))
            or (t is float and isinstance(v, int | float) and not isinstance(v, bool))
            or (t is str and isinstance(v, str))
            for t in allowed
        )
        if not ok:
            want = " or ".join(getattr(t, "__name__", str(t)) for t in allowed)
            raise ConfigError(f"{section}.{name} must be of type {want}; got {v!r}")


def validate_stage2(cfg: Stage2Config) -> None:
    """Raise `ConfigError` naming the field when a `Stage2Config` value has the wrong type or is out of range."""
    def bad(name: str, want: str) -> ConfigError:
        return ConfigError(f"stage2.{name} must be {want}; got {getattr(cfg, name)!r}")

    _check_types("stage2", cfg)

    if cfg.variant not in ("paper", "articulated"):
        raise bad("variant", "'paper' or 'articulated'")
    if cfg.camera_correction not in ("auto", "on", "off"):
        raise bad("camera_correction", "'auto', 'on' or 'off'")
    if cfg.cluster_method not in ("dbscan", "hdbscan"):
        raise bad("cluster_method", "'dbscan' or 'hdbscan'")
    if cfg.control_encoding not in ("frequency", "hashgrid"):
        raise bad("control_encoding", "'frequency' or 'hashgrid'")
    for name in ("threshold_px", "score_threshold"):
        v = getattr(cfg, name)
        if v != "otsu" and not (isinstance(v, int | float) and not isinstance(v, str) and v >= 0):
            raise bad(name, "'otsu' or a number >= 0")
    for name in ("min_px", "min_alpha", "min_score", "eps", "min_fraction", "flow_weight", "flow_threshold"):
        if not float(getattr(cfg, name)) >= 0:
            raise bad(name, "a number >= 0")
    if not cfg.eps > 0:
        raise bad("eps", "> 0")
    if not cfg.lr > 0:
        raise bad("lr", "> 0")
    for name in ("min_samples", "hidden", "depth", "distill_batch"):
        if getattr(cfg, name) < 1:
            raise bad(name, "an integer >= 1")
    for name in ("n_freqs_x", "n_freqs_v", "distill_steps", "photo_steps"):
        if getattr(cfg, name) < 0:
            raise bad(name, "an integer >= 0")


def validate_articulate(cfg: ArticulateConfig) -> None:
    """Raise `ConfigError` naming the field when an `ArticulateConfig` value has the wrong type or is out of range."""
    def bad(name: str, want: str) -> ConfigError:
        return ConfigError(f"articulate.{name} must be {want}; got {getattr(cfg, name)!r}")

    _check_types("articulate", cfg)

    if cfg.track_joints not in ("auto", "off"):
        raise bad("track_joints", "'auto' or 'off'")
    for name in ("local_floor", "local_min_fraction"):
        if not 0.0 <= getattr(cfg, name) < 1.0:
            raise bad(name, "in [0, 1)")
    for name in ("track_photo", "track_photo_next", "hinge_trial", "refit_steps", "relabel_steps",
                 "hull_refit_steps"):
        if getattr(cfg, name) < 0:
            raise bad(name, "an integer >= 0")
    for name in ("merge_eps", "local_radius", "local_threshold", "track_active", "track_photo_radius",
                 "relabel_radius", "track_converged_deg", "ghost_radius", "hull_max_growth", "hinge_radius",
                 "hinge_reach", "colour_radius"):
        v = getattr(cfg, name)
        if not (_finite(v) and v >= 0):
            raise bad(name, "a finite number >= 0")
    if cfg.track_rounds < 1:
        raise bad("track_rounds", "an integer >= 1")
    if cfg.track_subset_margin < -1:
        raise bad("track_subset_margin", "an integer >= -1 (-1: every Gaussian)")
    if not (_finite(cfg.link_min_corr) and -1.0 <= cfg.link_min_corr <= 1.0):
        raise bad("link_min_corr", "a number in [-1, 1] (-1: position alone)")
    if not 0 <= cfg.hinge_up_deg < 90:
        raise bad("hinge_up_deg", "a number in [0, 90) (0: off)")
    if not (_finite(cfg.hinge_trial_race) and 0 < cfg.hinge_trial_race <= 1):
        raise bad("hinge_trial_race", "in (0, 1] (1: every candidate gets every step)")
    if not 0 <= cfg.hinge_trial_margin < 1:
        raise bad("hinge_trial_margin", "in [0, 1)")
    if not 0 <= cfg.hinge_trial_edges <= 4:
        raise bad("hinge_trial_edges", "an integer in 0..4")
    if not 0.0 <= cfg.hull_opacity <= 1.0:
        raise bad("hull_opacity", "in [0, 1]")
    if not (_finite(cfg.ghost_opacity) and 0 < cfg.ghost_opacity < 1):
        raise bad("ghost_opacity", "in (0, 1)")
    if not (_finite(cfg.hinge_min_deg) and 0 < cfg.hinge_min_deg <= 180):
        raise bad("hinge_min_deg", "in (0, 180]")
    if not (_finite(cfg.refit_lr_scale) and cfg.refit_lr_scale > 0):
        raise bad("refit_lr_scale", "finite and > 0")
    if not (cfg.isolated_factor == 0 or (_finite(cfg.isolated_factor) and cfg.isolated_factor >= 1)):
        raise bad("isolated_factor", "0 (off) or >= 1")
    if cfg.colour_components < 1:
        raise bad("colour_components", "an integer >= 1")
    if not 0 <= cfg.colour_separation <= 1:
        raise bad("colour_separation", "in [0, 1]")
    if not 0 <= cfg.through_prune <= 1:
        raise bad("through_prune", "0 (off) or in (0, 1]")
