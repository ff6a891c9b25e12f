"""Typed run configuration: per-component frozen dataclasses, TOML loading, ``key=value`` overrides.

A TOML file has one table per component ([data], [model], [deform], [train], [densify], [flow],
[pose], [static]); every key is optional (defaults below). Overrides use dotted names,
``train.steps=3000``, and are type-checked against the field's declared type. Components never import
this module: the pipeline converts these dataclasses into the arguments they take.
"""

from __future__ import annotations

import dataclasses
import tomllib
import typing
from pathlib import Path
from typing import Any

__all__ = [
    "DataConfig", "ModelConfig", "DeformConfig", "TrainConfig", "DensifyConfig", "FlowConfig",
    "PoseConfig", "StaticConfig", "Config", "load_config", "apply_overrides", "to_toml", "from_dict",
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
    """"flow": points triangulated from optical flow between posed frames (`fgjax.pipeline.init_points`),
    topped up with random points; "random": random points in the scene box that some camera sees."""
    init_random_fraction: float = 0.2
    """With init = "flow": this fraction of the initial points is random (covers untextured regions)."""
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
    """"frequency" (Deformable-3DGS 8x256 MLP) or "hash" (hash grid + small MLP)."""
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
    """Flow-target magnitude threshold (pixels) below which motion counts as static (0: off)."""
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
    (`fgjax.pipeline.poses`); the corrections become the initial pose deltas (needs ``enabled``)."""
    bundle_prior_deg: float = 1.0
    """Prior standard deviation of the written rotations' errors (degrees)."""
    bundle_prior_trans: float = 0.05
    """Prior standard deviation of the written camera positions' errors (scene units)."""
    bundle_cauchy_px: float = 0.25
    """Final Cauchy scale of the reprojection residuals (pixels)."""
    bundle_fb_px: float = 0.0
    """> 0: the bundle adjustment's flow tracks stop where the forward flow fails the round trip through the backward
    flow by this much or more (pixels; `fgjax.data.opticalflow.forward_backward_mask`: occlusions, flow smoothed across
    depth edges); 0: off (the default). On the pose-noise scene, 0.1 px took the adjusted rotations from 0.218 to
    0.160 degree off the truth, and after stage 1 from 0.168 to 0.118, with stage 1's test views at 29.12 dB
    instead of 28.82; but stage 2 on that stage-1 run lost the door in both of its seeds (held-out states 24.15
    and 23.97 dB against 26.91 and 28.05). On a second pose-noise scene it gained a little (27.18 -> 27.47 dB), so
    it stays off (docs/benchmarks.md, session 35)."""


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
    return dataclasses.replace(base, **updates)


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
