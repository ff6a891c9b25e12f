"""The whole configuration (`Config`, one field per TOML table), its stage-1 validation, TOML loading, ``key=value``
overrides and writing back to TOML."""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

from fgjax.config.errors import ConfigError, finite
from fgjax.config.stage1 import (
    DataConfig,
    DeformConfig,
    DensifyConfig,
    FlowConfig,
    ModelConfig,
    PoseConfig,
    StaticConfig,
    TrainConfig,
)
from fgjax.config.stage2 import ArticulateConfig, Stage2Config, validate_articulate, validate_stage2

__all__ = ["Config", "validate_stage1", "from_dict", "apply_overrides", "load_config", "to_toml", "to_dict"]


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
    need(finite(m.init_scale) and m.init_scale > 0, "model.init_scale", "> 0", m.init_scale)
    need(len(m.background) == 3 and all(0.0 <= c <= 1.0 for c in m.background), "model.background",
         "three numbers in [0, 1]", m.background)
    need(f.kind in ("hash", "frequency", "bases"), "deform.kind", "'hash', 'frequency' or 'bases'", f.kind)
    need(f.bases >= 2, "deform.bases", ">= 2", f.bases)
    need(f.knots >= 2, "deform.knots", ">= 2", f.knots)
    need(f.joint == "free" or (f.joint == "screw" and f.kind == "bases"), "deform.joint",
         "'free', or 'screw' with deform.kind = 'bases'", f.joint)
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
        need(finite(v) and v > 0, f"train.{k}", "a finite number > 0", v)
    need(0.0 <= t.lambda_dssim <= 1.0, "train.lambda_dssim", "in [0, 1]", t.lambda_dssim)
    need(finite(t.scale_reg) and t.scale_reg >= 0, "train.scale_reg", ">= 0", t.scale_reg)
    need(t.rigid_neighbours >= 1, "train.rigid_neighbours", ">= 1", t.rigid_neighbours)
    need(finite(t.capacity_margin) and t.capacity_margin >= 1.0, "train.capacity_margin", ">= 1", t.capacity_margin)
    need(t.tile_size in (4, 8, 16, 32), "train.tile_size", "4, 8, 16 or 32", t.tile_size)
    for k in ("start", "stop", "every", "reset_every"):
        need(getattr(dn, k) >= 0, f"densify.{k}", ">= 0", getattr(dn, k))
    for k in ("grad_threshold", "percent_dense", "prune_opacity", "max_world_scale"):
        v = getattr(dn, k)
        need(finite(v) and v >= 0, f"densify.{k}", "a finite number >= 0", v)
    need(finite(fl.weight) and fl.weight >= 0, "flow.weight", ">= 0", fl.weight)
    need(finite(fl.threshold) and fl.threshold >= 0, "flow.threshold", ">= 0", fl.threshold)
    need(fl.start >= 0, "flow.start", ">= 0", fl.start)
    need(fl.photo_motion_start >= 0, "flow.photo_motion_start", ">= 0", fl.photo_motion_start)
    need(f.anchor in ("none", "first"), "deform.anchor", "'none' or 'first'", f.anchor)
    need(f.init in ("random", "flow"), "deform.init", "'random' or 'flow'", f.init)
    need(f.hold >= 0, "deform.hold", ">= 0", f.hold)
    need(len(f.spans) > 0 and min(f.spans) >= 1 and len(set(f.spans)) == len(f.spans), "deform.spans",
         "a list of distinct frame spans >= 1", list(f.spans))
    need(f.weights == "field" or (f.weights == "slot" and f.kind == "bases" and f.init == "flow"), "deform.weights",
         "'field', or 'slot' with deform.kind = 'bases' and deform.init = 'flow'", f.weights)
    need(finite(f.gauge) and f.gauge >= 0, "deform.gauge", "a finite number >= 0", f.gauge)
    need(finite(f.camera_share) and f.camera_share >= 0, "deform.camera_share", "a finite number >= 0",
         f.camera_share)
    need(f.place_window >= 0, "deform.place_window", "an integer >= 0 (0: every pair)", f.place_window)
    need(finite(f.place_agree_sigma) and f.place_agree_sigma >= 0, "deform.place_agree_sigma",
         "a finite number >= 0 (0: off)", f.place_agree_sigma)
    need(finite(f.place_noise_sigmas) and f.place_noise_sigmas >= 0, "deform.place_noise_sigmas",
         "a finite number >= 0 (0: off)", f.place_noise_sigmas)
    need(finite(f.place_free_eps) and f.place_free_eps >= 0, "deform.place_free_eps", "a finite number >= 0 (0: off)",
         f.place_free_eps)
    need(fl.loss in ("pair", "track"), "flow.loss", "'pair' or 'track'", fl.loss)
    need(fl.gaussian_flow in ("isotropic", "anisotropic"), "flow.gaussian_flow", "'isotropic' or 'anisotropic'",
         fl.gaussian_flow)
    need(fl.camera_depth in ("composited", "expected"), "flow.camera_depth", "'composited' or 'expected'",
         fl.camera_depth)
    need(finite(fl.photo_motion) and 0 <= fl.photo_motion <= 1, "flow.photo_motion", "in [0, 1]", fl.photo_motion)
    need(fl.norm in ("l1", "charbonnier"), "flow.norm", "'l1' or 'charbonnier'", fl.norm)
    need(finite(fl.charbonnier_px) and fl.charbonnier_px > 0, "flow.charbonnier_px", "a finite number > 0",
         fl.charbonnier_px)
    for k in ("lr", "lr_final"):
        v = getattr(cfg.pose, k)
        need(finite(v) and v > 0, f"pose.{k}", "a finite number > 0", v)
    need(0.0 < t.time_window_start <= 1.0, "train.time_window_start", "in (0, 1]", t.time_window_start)
    need(finite(t.depth_weight) and t.depth_weight >= 0, "train.depth_weight", "a finite number >= 0", t.depth_weight)
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
    need(finite(cfg.static.threshold) and cfg.static.threshold >= 0, "static.threshold", ">= 0",
         cfg.static.threshold)
