"""Stage-2 configuration: every field's type and range is checked, and the error names the field."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from fgjax.articulate.labels import LABEL_PASSES, label_passes_on
from fgjax.config import (
    ArticulateConfig,
    ConfigError,
    Stage2Config,
    load_config,
    to_dict,
    validate_articulate,
    validate_stage2,
)

REPO = Path(__file__).resolve().parents[2]
SECTIONS = [("stage2", Stage2Config, validate_stage2), ("articulate", ArticulateConfig, validate_articulate)]


def _wrong_type(value):
    """A value of another type than ``value``'s that no field's type accepts."""
    return [1, 2] if not isinstance(value, list) else "x"


@pytest.mark.parametrize("section,cls,validate", SECTIONS)
def test_every_field_rejects_a_value_of_the_wrong_type_naming_it(section, cls, validate):
    validate(cls())  # the defaults are valid
    for f in dataclasses.fields(cls):
        bad = dataclasses.replace(cls(), **{f.name: _wrong_type(getattr(cls(), f.name))})
        with pytest.raises(ConfigError, match=rf"^{section}\.{f.name} "):
            validate(bad)


@pytest.mark.parametrize("section,cls,validate", SECTIONS)
def test_a_bool_is_not_a_number(section, cls, validate):
    numeric = [f.name for f in dataclasses.fields(cls) if type(getattr(cls(), f.name)) in (int, float)]
    assert numeric
    for name in numeric:
        with pytest.raises(ConfigError, match=rf"^{section}\.{name} "):
            validate(dataclasses.replace(cls(), **{name: True}))


@pytest.mark.parametrize("section,field,value", [
    ("stage2", "variant", "other"), ("stage2", "eps", 0.0), ("stage2", "eps", -1.0), ("stage2", "min_samples", 0),
    ("stage2", "threshold_px", "sometimes"), ("stage2", "threshold_px", -0.5), ("stage2", "lr", 0.0),
    ("stage2", "distill_steps", -1), ("stage2", "camera_correction", "maybe"), ("stage2", "cluster_method", "kmeans"),
    ("stage2", "backproject", "first"),
    ("stage2", "control_encoding", "fourier"), ("stage2", "threshold_sigmas", -1.0),
    ("stage2", "threshold_sigmas", float("nan")), ("stage2", "agree_sigma", -0.1),
    ("stage2", "agree_sigma", float("inf")),
    ("stage2", "agree_sigma", float("nan")), ("stage2", "depth_tolerance", -0.1),
    ("stage2", "depth_tolerance", float("inf")), ("stage2", "fb_px", -1.0), ("stage2", "fb_px", float("nan")),
    ("articulate", "track_rounds", 0), ("articulate", "hinge_up_deg", 90.0), ("articulate", "ghost_opacity", 1.0),
    ("articulate", "link_min_corr", 1.5), ("articulate", "link_min_corr", float("nan")),
    ("articulate", "hinge_trial_race", 0.0), ("articulate", "hinge_trial_race", 1.5),
    ("articulate", "isolated_factor", 0.5), ("articulate", "hinge_trial_edges", 5), ("articulate", "local_floor", 1.0),
    ("articulate", "track_joints", "sometimes"), ("articulate", "refit_lr_scale", 0.0),
    ("articulate", "merge_eps", float("nan")), ("articulate", "track_subset_margin", -2),
    ("articulate", "track_from", "flow"),
])
def test_out_of_range_values_are_refused_naming_the_field(section, field, value):
    cls, validate = {"stage2": (Stage2Config, validate_stage2), "articulate": (ArticulateConfig, validate_articulate)}[
        section]
    with pytest.raises(ConfigError, match=rf"^{section}\.{field} "):
        validate(dataclasses.replace(cls(), **{field: value}))


def test_poses_read_off_the_field_refuse_photometric_tracking():
    """``articulate.track_from = "field"`` takes the poses from stage 1's field, so a photometric tracker asked for
    beside it (``track_photo`` > 0, the library's default) is refused, naming both fields, not silently skipped."""
    validate_articulate(dataclasses.replace(ArticulateConfig(), track_from="field", track_photo=0))
    with pytest.raises(ConfigError, match=r"articulate\.track_from = 'field'.*articulate\.track_photo = 0"):
        validate_articulate(dataclasses.replace(ArticulateConfig(), track_from="field"))


def test_overrides_parse_numbers_and_otsu_and_are_validated():
    cfg = load_config(None, ["stage2.threshold_px=1.5", "stage2.score_threshold=otsu", "articulate.track_rounds=2"])
    assert cfg.stage2.threshold_px == 1.5 and cfg.stage2.score_threshold == "otsu"
    assert cfg.articulate.track_rounds == 2
    with pytest.raises(ConfigError, match=r"^articulate\.track_rounds "):
        load_config(None, ["articulate.track_rounds=0"])
    with pytest.raises(ConfigError, match="stage2.eps"):
        load_config(None, ["stage2.eps=wide"])


@pytest.mark.parametrize("name,variant", [("paper", "paper"), ("articulated", "articulated"),
                                          ("demo_quick", "articulated"), ("quick", "paper")])
def test_named_configurations_load_and_name_their_variant(name, variant):
    cfg = load_config(REPO / "experiments" / f"{name}.toml")
    assert cfg.stage2.variant == variant


def test_family_bases_is_the_family_configuration_with_the_documented_stage1_recipe():
    """experiments/family_bases.toml is what docs/benchmarks.md runs as `--config experiments/family.toml [STAGE1]
    --set deform.init=flow --set deform.weights=slot` ("Do the parts move?", "The weights stored per Gaussian"):
    the same configuration key for key, so the named file reproduces those tables and differs from the family's
    default in stage 1's motion only."""
    stage1 = ["deform.kind=bases", "flow.enabled=true", "flow.norm=charbonnier", "flow.start=100",
              "flow.photo_motion=0", "train.rigid_weight=0", "train.lr_deform=1.6e-3", "train.lr_deform_final=1.6e-4",
              "train.steps=3000", "train.warmup_steps=300", "deform.init=flow", "deform.weights=slot"]
    named = load_config(REPO / "experiments" / "family_bases.toml")
    assert to_dict(named) == to_dict(load_config(REPO / "experiments" / "family.toml", stage1))
    assert (named.deform.kind, named.deform.weights, named.flow.enabled) == ("bases", "slot", True)


def test_label_passes_are_off_by_default_and_on_only_in_the_hand_made_scenes_configurations():
    """The articulated variant's label passes lower the family benchmark's ARI (docs/benchmarks.md, "Label passes"):
    the library default and the family's configuration leave them off; the demo's configurations turn them on."""
    hand_made = {"articulated", "demo_quick"}
    named = sorted((REPO / "experiments").glob("*.toml"))
    assert hand_made < {f.stem for f in named} and "family" in {f.stem for f in named}
    passes = LABEL_PASSES
    assert passes == ("hull_fill", "hinge_fill", "isolated_factor", "colour_radius", "through_prune")
    assert label_passes_on(load_config(None).articulate) == ()
    for f in named:
        a = load_config(f).articulate
        assert label_passes_on(a) == (passes if f.stem in hand_made else ()), (f.name, a)
    # one pass on, by its key's own kind of value
    assert label_passes_on(ArticulateConfig(colour_radius=0.05)) == ("colour_radius",)
    assert label_passes_on(ArticulateConfig(hinge_fill=True, through_prune=0.5)) == ("hinge_fill", "through_prune")


@pytest.mark.parametrize("override,key", [("flow.loss=other", "flow.loss"),
                                          ("flow.photo_motion=1.5", "flow.photo_motion"),
                                          ("flow.photo_motion_start=-1", "flow.photo_motion_start"),
                                          ("deform.anchor=last", "deform.anchor"), ("deform.kind=mlp", "deform.kind"),
                                          ("deform.init=tracks", "deform.init"), ("deform.hold=-1", "deform.hold"),
                                          ("deform.gauge=-1", "deform.gauge"), ("deform.gauge=nan", "deform.gauge"),
                                          ("deform.weights=slot", "deform.weights"),
                                          ("deform.weights=mlp", "deform.weights"),
                                          ("deform.spans=0,1", "deform.spans"), ("deform.spans=1,1", "deform.spans"),
                                          ("deform.spans=", "deform.spans"),
                                          ("deform.camera_share=-0.1", "deform.camera_share"),
                                          ("deform.camera_share=inf", "deform.camera_share"),
                                          ("deform.place_window=-1", "deform.place_window"),
                                          ("deform.place_agree_sigma=-0.1", "deform.place_agree_sigma"),
                                          ("deform.place_agree_sigma=nan", "deform.place_agree_sigma"),
                                          ("deform.place_noise_sigmas=-1", "deform.place_noise_sigmas"),
                                          ("deform.place_noise_sigmas=inf", "deform.place_noise_sigmas"),
                                          ("deform.place_free_eps=-1", "deform.place_free_eps"),
                                          ("deform.place_free_eps=nan", "deform.place_free_eps"),
                                          ("deform.bases=1", "deform.bases"), ("deform.knots=1", "deform.knots"),
                                          ("deform.joint=screw", "deform.joint"), ("deform.joint=ball", "deform.joint"),
                                          ("flow.gaussian_flow=affine", "flow.gaussian_flow"),
                                          ("flow.camera_depth=median", "flow.camera_depth"),
                                          ("flow.norm=l2", "flow.norm"),
                                          ("flow.charbonnier_px=0", "flow.charbonnier_px")])
def test_stage1_flow_options_are_validated(override, key):
    with pytest.raises(ConfigError, match=rf"^config key '{key}' must be "):
        load_config(None, overrides=[override])  # "config key 'KEY' must be ..."
    assert load_config(None, overrides=["flow.loss=track"]).flow.loss == "track"
    cfg = load_config(None, overrides=["flow.gaussian_flow=anisotropic", "flow.camera_depth=expected"])
    assert (cfg.flow.gaussian_flow, cfg.flow.camera_depth) == ("anisotropic", "expected")
    assert load_config(None, overrides=["flow.norm=charbonnier"]).flow.norm == "charbonnier"
    assert load_config(None, overrides=["deform.kind=bases", "deform.bases=4"]).deform.bases == 4
    slot = ["deform.kind=bases", "deform.init=flow", "deform.weights=slot"]
    assert load_config(None, overrides=slot).deform.weights == "slot"
    assert load_config(None, overrides=["deform.kind=bases", "deform.joint=screw"]).deform.joint == "screw"
    assert load_config(None, overrides=["deform.spans=1,2,4"]).deform.spans == (1, 2, 4)
    assert load_config(None, overrides=["flow.norm=charbonnier", "flow.loss=track"]).flow.norm == "charbonnier"
