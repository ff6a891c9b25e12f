"""Typed run configuration: per-component frozen dataclasses, TOML loading, ``key=value`` overrides.

A TOML file has one table per component ([data], [model], [deform], [train], [densify], [flow],
[pose], [static] for stage 1; [stage2] for the paper's stage 2 and [articulate] for the articulated variant); every
key is optional. Overrides use dotted names, ``train.steps=3000``, and are type-checked against the field's declared
type. Components never import this package: the pipeline converts these dataclasses into the arguments they take.

Modules: `fgjax.config.stage1` (stage 1's sections, each key's default and meaning), `fgjax.config.stage2`
([stage2], [articulate] and their validators), `fgjax.config.loading` (`Config`, TOML in and out, overrides,
stage 1's validation), `fgjax.config.errors` (`ConfigError`).
"""

from __future__ import annotations

from fgjax.config.errors import ConfigError
from fgjax.config.loading import (
    Config,
    apply_overrides,
    from_dict,
    load_config,
    to_dict,
    to_toml,
    validate_stage1,
)
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

__all__ = [
    "DataConfig", "ModelConfig", "DeformConfig", "TrainConfig", "DensifyConfig", "FlowConfig",
    "PoseConfig", "StaticConfig", "Stage2Config", "ArticulateConfig", "Config", "validate_stage1",
    "validate_stage2", "validate_articulate", "load_config", "apply_overrides", "to_toml", "from_dict",
    "to_dict", "ConfigError",
]
