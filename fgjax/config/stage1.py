"""Stage 1's configuration sections: [data], [model], [deform], [train], [densify], [flow], [pose], [static].

Every key is optional; the defaults below are what a run gets. `fgjax.config.validate_stage1` checks the ranges.
"""

from __future__ import annotations

import dataclasses

__all__ = ["DataConfig", "ModelConfig", "DeformConfig", "TrainConfig", "DensifyConfig", "FlowConfig",
           "PoseConfig", "StaticConfig"]


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
    joint: str = "free"
    """"bases" kind: each moving basis's motion over the clip: "free" (any rotation and translation at each control
    time) or "screw" (one axis and pivot for the whole clip, an angle about the axis and a translation along it at
    each control time: a hinge, a slide, a spinning part; `fgjax.models.deform`)."""
    anchor: str = "none"
    """"first": the field is zero at the first training time (`fgjax.models.deform.DeformSpec.anchor`): the canonical
    Gaussians are the first frame (where ``model.init = "flow"`` puts them) and a constant offset of the whole scene,
    which neither the flow loss nor the photometric loss pins, cannot drift in. "none": the network's choice."""
    init: str = "random"
    """"bases" kind: "random" logits, or "flow": placed on the moving clusters that the flow finds after the
    warm-up (`fgjax.method.bases_init`)."""
    spans: tuple[int, ...] = (1,)
    """With init = "flow": the frame spans (in time order) of the pairs whose |u - u_cam| the placement reads, each
    span's selection of moving Gaussians united: 1 is consecutive frames; a part that moves under the 1 px floor a
    frame shows over longer spans (`fgjax.method.bases_init`; docs/benchmarks.md, "The placement's frame
    spans")."""
    camera_share: float = 0.0
    """With init = "flow": the placement's moving-pixel floor grows with each pair's camera flow, 1 px +
    camera_share |u_cam| (`fgjax.method.bases_init.moving_clusters`): the camera flow's error is the warm-up depth's
    relative error times its parallax, so a moving camera, and a longer span, needs more evidence. 0: a fixed 1 px;
    with spans 1, 2, 4 the family's tuning seeds choose 0.2 (docs/benchmarks.md, "A floor that grows with the camera
    flow")."""
    place_window: int = 0
    """With init = "flow": > 0: a Gaussian's discovery score is its best run of this many consecutive pairs
    (`fgjax.method.discover.windowed_score`) rather than the share over every pair, in which a part that moves in a
    few pairs is diluted by those in which it rests; 0: every pair."""
    place_agree_sigma: float = 0.0
    """With init = "flow": > 0: each pixel's back-projection is weighted by the agreement of the warm-up model's
    render with the image, exp(-e^2 / (2 place_agree_sigma^2)) for an RMS colour error e
    (`fgjax.method.discover.agreement`): the warm-up model does not move the parts, so a part's moved pixels are
    painted by what it covered or uncovered, which then renders wrongly there. 0: every pixel weighs 1."""
    place_noise_sigmas: float = 0.0
    """With init = "flow": > 0: each pair's 1 px floor is raised, where lower, to the noise of its residual, median +
    place_noise_sigmas * 1.4826 MAD of |u - u_cam| over the pair's valid pixels (`fgjax.method.discover.binarize`,
    as ``stage2.threshold_sigmas``). 0: off."""
    place_free_eps: float = 0.0
    """With init = "flow" and weights = "slot": > 0: the Gaussians the placement calls static that lie within
    place_free_eps times DBSCAN's automatic radius of a moving cluster's Gaussian start on the static basis but are
    free to leave it, as DBSCAN's noise is (`fgjax.method.bases_init.free_near_clusters`): the share of a part's
    Gaussians that the flow's cut misses otherwise stays on the static basis for good. 0: off."""
    hold: int = 150
    """With init = "flow": steps after the placement in which only the bases' motions train, the weights
    held, so that each motion fits its cluster before a weight can leave it (docs/benchmarks.md)."""
    gauge: float = 1.0
    """With init = "flow": weight of the static scene's rigid drift (`fgjax.train.losses.rigid_drift_loss`) at up to
    4096 canonical points that the placement found static, each training step (0: off; 1 chosen on the family's
    tuning seeds: docs/benchmarks.md, "The static scene's drift priced"). Not used with weights = "slot", which
    holds the static Gaussians on the static basis exactly."""
    weights: str = "field"
    """"bases" kind: "field": the weights' logits are the hash-grid MLP of the canonical centre; "slot": with
    init = "flow", each Gaussian stores its own logits, set by the placement, and the Gaussians it labels static
    stay on the static basis (`fgjax.models.deform`, Shape of Motion's per-Gaussian weights)."""


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
    photo_motion_start: int = 0
    """First step at which ``photo_motion`` applies; before it, with the flow loss on, the factor is 0 (the flow loss
    alone trains the motion). 0: ``photo_motion`` from the flow loss's first step (docs/benchmarks.md, "The
    photometric share of the motion from mid-way")."""
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
