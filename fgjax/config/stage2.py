"""Stage 2's configuration sections, [stage2] (the paper's chain) and [articulate] (the articulated variant), and
their validators."""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any

from fgjax.config.errors import ConfigError, finite

__all__ = ["Stage2Config", "ArticulateConfig", "validate_stage2", "validate_articulate"]


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
    threshold_sigmas: float = 0.0
    """Raise each pair's threshold to the noise of its residual, median + k * 1.4826 MAD of |u - u_cam| over the
    pair's valid pixels, with k this (`fgjax.method.discover.binarize`): a pair whose camera flow is wrong
    everywhere by a pixel is not marked moving. 0: off."""
    depth_tolerance: float = 0.0
    """The rendered depth's relative error delta that discovery allows: u_cam is the camera flow, among the depths
    Z / (1 + delta) .. Z (1 + delta), nearest the optical flow (`fgjax.method.discover.nearest_on_segment`), so a
    static pixel whose depth stage 1 got wrong is not marked moving. 0: the rendered depth as it is (the paper)."""
    min_alpha: float = 0.5
    """Pixels whose rendered alpha is below this have no trusted depth and are left out of the masks."""
    fb_px: float = 0.0
    """> 0: a pair's pixels whose optical flow misses the round trip through the backward flow by this many pixels
    or more, or leaves the second frame (`fgjax.data.opticalflow.forward_backward_mask` with alpha 0 and beta
    ``fb_px``^2: occlusions, flow errors at the image's border), are left out of the masks and of the static flow
    that ``camera_correction`` fits, as unmeasured. 0: off (the paper: every pixel's flow is taken as it is)."""
    agree_sigma: float = 0.0
    """Weight each pixel's back-projection by the agreement of the stage-1 rendering with the image there,
    exp(-e^2 / (2 agree_sigma^2)) for an RMS colour error e (`fgjax.method.discover.agreement`): a moving pixel the
    model paints wrongly (a part it has not moved) is given to no Gaussian. 0: every pixel weighs 1."""
    backproject: str = "pair"
    """Where each pair's moving pixels are credited to Gaussians: "pair", to the Gaussians the stage-1 model paints
    there at the pair's first time (the paper's step 5); "track", where a track of the first frame's pixels reaches
    them (optical flow chained, round-trip checked), to the Gaussians that paint the track's pixel in the first
    frame, and elsewhere as "pair" (`fgjax.method.discover.Reference`)."""
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
    track_from: str = "images"
    """Where each object's poses come from: "images", tracked in the training images (photometric tracking with
    ``track_photo`` > 0, else the optical flow); "field", read off stage 1's deformation field, each object's
    Gaussians at every training time fitted with one rigid motion from the reference (the paper's trajectories,
    `fgjax.articulate.track.field_poses`; needs ``track_photo`` = 0)."""
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
    if cfg.backproject not in ("pair", "track"):
        raise bad("backproject", "'pair' or 'track'")
    if cfg.control_encoding not in ("frequency", "hashgrid"):
        raise bad("control_encoding", "'frequency' or 'hashgrid'")
    for name in ("threshold_px", "score_threshold"):
        v = getattr(cfg, name)
        if v != "otsu" and not (isinstance(v, int | float) and not isinstance(v, str) and v >= 0):
            raise bad(name, "'otsu' or a number >= 0")
    for name in ("min_px", "min_alpha", "min_score", "eps", "min_fraction", "flow_weight", "flow_threshold"):
        if not float(getattr(cfg, name)) >= 0:
            raise bad(name, "a number >= 0")
    for name in ("threshold_sigmas", "depth_tolerance", "agree_sigma", "fb_px"):
        v = getattr(cfg, name)
        if not (finite(v) and v >= 0):
            raise bad(name, "a finite number >= 0 (0: off)")
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
    if cfg.track_from not in ("images", "field"):
        raise bad("track_from", "'images' or 'field'")
    if cfg.track_from == "field" and cfg.track_photo > 0:
        raise ConfigError(f"articulate.track_from = 'field' reads the poses off stage 1's field, so it needs "
                          f"articulate.track_photo = 0 (no photometric tracking); got {cfg.track_photo!r}")
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
        if not (finite(v) and v >= 0):
            raise bad(name, "a finite number >= 0")
    if cfg.track_rounds < 1:
        raise bad("track_rounds", "an integer >= 1")
    if cfg.track_subset_margin < -1:
        raise bad("track_subset_margin", "an integer >= -1 (-1: every Gaussian)")
    if not (finite(cfg.link_min_corr) and -1.0 <= cfg.link_min_corr <= 1.0):
        raise bad("link_min_corr", "a number in [-1, 1] (-1: position alone)")
    if not 0 <= cfg.hinge_up_deg < 90:
        raise bad("hinge_up_deg", "a number in [0, 90) (0: off)")
    if not (finite(cfg.hinge_trial_race) and 0 < cfg.hinge_trial_race <= 1):
        raise bad("hinge_trial_race", "in (0, 1] (1: every candidate gets every step)")
    if not 0 <= cfg.hinge_trial_margin < 1:
        raise bad("hinge_trial_margin", "in [0, 1)")
    if not 0 <= cfg.hinge_trial_edges <= 4:
        raise bad("hinge_trial_edges", "an integer in 0..4")
    if not 0.0 <= cfg.hull_opacity <= 1.0:
        raise bad("hull_opacity", "in [0, 1]")
    if not (finite(cfg.ghost_opacity) and 0 < cfg.ghost_opacity < 1):
        raise bad("ghost_opacity", "in (0, 1)")
    if not (finite(cfg.hinge_min_deg) and 0 < cfg.hinge_min_deg <= 180):
        raise bad("hinge_min_deg", "in (0, 180]")
    if not (finite(cfg.refit_lr_scale) and cfg.refit_lr_scale > 0):
        raise bad("refit_lr_scale", "finite and > 0")
    if not (cfg.isolated_factor == 0 or (finite(cfg.isolated_factor) and cfg.isolated_factor >= 1)):
        raise bad("isolated_factor", "0 (off) or >= 1")
    if cfg.colour_components < 1:
        raise bad("colour_components", "an integer >= 1")
    if not 0 <= cfg.colour_separation <= 1:
        raise bad("colour_separation", "in [0, 1]")
    if not 0 <= cfg.through_prune <= 1:
        raise bad("through_prune", "0 (off) or in (0, 1]")
