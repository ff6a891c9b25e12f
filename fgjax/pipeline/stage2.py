"""Stage 2: discovery, clustering, trajectories and the control network (DESIGN.md section 1, steps 5-7).

Library entry point: ``run_stage2(run_dir, data_dir, cfg)``; command line
``python -m fgjax.pipeline.stage2 --run RUN --data DATA`` (writes RUN/stage2.npz and RUN/stage2.json).
The pipeline never reads ground truth (no ``gt/``): only the training images, poses and times.

1. **Discovery** (`fgjax.pipeline.discover.discover`). For each training pair (t-1, t): the stage-1
   Gaussians deformed to time t-1 are rendered from camera t-1 for their expected depth; the camera
   flow is `fgjax.flow.reprojection_flow` of that depth (exact; see docs/benchmarks.md); the optical
   flow t-1 -> t comes from `fgjax.data.opticalflow.estimate_flow` (cached); |u - u_cam| is binarised
   and back-projected through the rasterizer's contribution weights; D is Otsu's cut of the scores.
2. **Clustering** (`fgjax.cluster.cluster_dynamic`) of the canonical centres of D (DBSCAN by default).
3. **Trajectories** ς(t, k): the mean deformed centre of cluster k at each training time, frames in
   time order. The reference time t0 is the first training time; v_c(t, k) = ς(t, k) - ς(t0, k).
4. **Control network** f_Θ(E(v_c, X)) -> (ΔX, Δq, Δs). The controlled scene for per-cluster vectors
   v [K, 3] is

       G_i(v) = G_i(t0) + [f_Θ(v_{k(i)}, X_i) - f_Θ(0, X_i)]   for clustered Gaussians (k(i) >= 0)
       G_i(v) = G_i(t0)                                       for all others

   where G_i(t0) are the stage-1 Gaussians deformed to the reference time (centre, raw quaternion,
   log-scale) and X_i the canonical centre. So v = 0 reproduces the stage-1 scene at t0 exactly,
   everything outside the clusters is frozen at t0 (it is static, or noise D did not take), and a
   cluster's Gaussians move with their own cluster's vector only (`control_apply` is row-wise).
   With ``Stage2Config.control_rigid`` (the default) each cluster is then moved by the rigid motion
   nearest the network's (`controlled_gaussians`' ``rigid``): the parts are rigid, and the network's
   non-rigid residue is its error.
   Opacities and colours are stage 1's and are not trained. Θ is fitted in two phases:
   (a) distillation: ||ΔG_i(v(t)) - (G_i(t) - G_i(t0))||² over the training times, the stage-1
   deformation as teacher (cheap: no rendering); (b) the photometric loss 0.8 L1 + 0.2 (1 - SSIM)
   of controlled renders with v = v_c(t, ·) against the training images, plus beta L_uGS
   (`fgjax.flow.gaussian_flow_loss`) of consecutive frames: the controlled scene at v_c(t-1, ·) and
   v_c(t, ·), both seen by camera t-1, against the observed flow minus the camera flow.

Outputs are written atomically: RUN/stage2.npz (the authoritative result: labels, scores,
trajectories, control parameters, metadata as JSON) and RUN/stage2.json (a readable summary).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from fgjax import cluster
from fgjax.gaussians import Gaussians, activate
from fgjax.io import atomic_write
from fgjax.models.control_net import ControlNet, control_apply, control_init

__all__ = [
    "Stage2Config",
    "Stage2Result",
    "Stage2Error",
    "run_stage2",
    "config_from_overrides",
    "validate_config",
    "select_objects",
    "load_stage2",
    "controlled_gaussians",
    "render_controlled",
    "render_clusters",
    "posed_base",
    "write_cluster_maps",
    "write_controlled_frames",
    "cluster_vectors_at",
    "snap_vector",
    "main",
    "STAGE2_NAME",
]

STAGE2_NAME = "stage2.npz"
FORMAT_VERSION = 1


class Stage2Error(RuntimeError):
    """A run without (usable) stage-2 results, or a stage-2 input that cannot work."""


@dataclasses.dataclass(frozen=True)
class Stage2Config:
    """Options of stage 2 (defaults follow DESIGN.md)."""

    flow_method: str = "dis_deepflow"
    """OpenCV optical-flow method (`fgjax.data.opticalflow.METHODS`)."""
    flow_cache: str | None = None
    """Flow cache folder (None: RUN/flow_cache)."""
    threshold_px: float | str = "otsu"
    """Binarisation of |u - u_cam|: pixels, or "otsu" per frame."""
    min_px: float = 0.5
    """Floor of the Otsu threshold (pixels)."""
    mask_guide_radius: int = 0
    """Snap the moving-pixel masks to the frames' edges before the back-projection (`discover.guide_masks`, a
    guided filter of this radius in pixels); 0: off. On the default scene's 59 pairs (session 31, docs/benchmarks.md)
    radius 4 / 6 halve the static pixels in the masks at the same recall and lift the first labels' `ari` 0.730 ->
    0.748 / 0.761, but the lid's cluster shrinks (592 -> 514 / 353 Gaussians) and end to end the tracking is worse:
    held-out states 26.34 dB at 4 and the door lost at 6, against 28.16 off. Off by default."""
    mask_guide_eps: float = 0.01
    """The guided filter's regularisation (squared intensity, images in [0, 1])."""
    min_alpha: float = 0.5
    """Pixels whose rendered alpha is below this have no trusted depth (excluded from the masks)."""
    score_threshold: float | str = "otsu"
    """Cut of the per-Gaussian scores (a number in [0, 1], or "otsu")."""
    min_score: float = 0.05
    """Scores below this are never dynamic."""
    cluster_method: str = "dbscan"
    eps: float = 0.05
    """DBSCAN radius in scene units."""
    min_samples: int = 5
    min_fraction: float = 0.05
    """Clusters smaller than this fraction of D are dropped (without ``cut_after_local``; with it,
    ``local_min_fraction`` of the clustered Gaussians after the second pass)."""
    cut_after_local: bool = True
    """Cut by size after `fgjax.cluster.localize_clusters` (which needs ``local_radius > 0`` and ``merge_eps > 0``):
    clusters under ``local_min_fraction`` of the clustered Gaussians drop then; before it, only clusters under
    ``local_floor`` of D. A part that moves in few frames scores low in discovery, so its first cluster is small and
    close to a cut of D: in the default scene the lid had 101-188 Gaussians against a 5% cut of 129-152, and a
    4000-step stage 1 lost it on every seed (docs/benchmarks.md, session 19). The second pass grows it 3-5x."""
    local_min_fraction: float = 0.10
    """With ``cut_after_local``: the size cut after the second pass, as a fraction of the clustered Gaussians. After
    that pass the lids of seven runs held 14.2-17.2% of them and the small false fragments (static Gaussians behind the
    lid that it uncovers) 2.1-5.7% (docs/benchmarks.md, session 20); 5% let two of those fragments pass as objects.
    A scene with more than about eight equal moving parts needs it lower."""
    local_floor: float = 0.01
    """With ``cut_after_local``: clusters under this fraction of D drop before the second pass."""
    auto_eps: bool = False
    """Choose eps from the k-distance curve."""
    grow_fraction: float = 0.0
    """Hysteresis: Gaussians scoring at least this fraction of the score threshold join a cluster they touch
    (within `grow_eps`, chained; `fgjax.cluster.grow_clusters`); 0: off (default). Discovery scores only the
    fastest-moving pixels of a part (a door near its hinge barely moves), so a part's cluster starts as its
    fast edge. Measured (docs/benchmarks.md): 0.3 helps the default scene a little (ARI +0.02) but lets the
    quick demo's clusters spread into static surfaces (ARI 0.72 -> 0.33), so it is off by default."""
    grow_eps: float = 0.05
    """Growth radius in scene units (not the automatic DBSCAN eps, which can be much larger)."""
    merge_eps: float = 0.05
    """Before the size cut, join DBSCAN clusters whose closest members are within this distance (scene units)
    and whose motion profiles correlate positively (`fgjax.cluster.merge_fragments`); 0: off. DBSCAN links
    only through core points: a thin gap in a part's dynamic set splits it into fragments that the size
    cut then drops one by one (the default scene's lid in session 15: 85 + 83 Gaussians, 0.026 apart,
    each under the 5% cut of 152)."""
    split_motion: bool = True
    """Split clusters whose members move at different times (`fgjax.cluster.split_by_motion`): two parts
    closer than eps merge into one DBSCAN cluster, but they rarely move together."""
    local_radius: float = 0.1
    """Second selection pass in each cluster's own moving frames (`fgjax.cluster.localize_clusters`):
    unlabelled Gaussians within this radius (scene units) of a cluster are scored over the frames in which
    that cluster moves; 0: off. The global score is diluted by the frames in which a part rests, so a part
    that moves briefly (the default scene's lid) is found only in pieces by the global cut. Measured
    (docs/benchmarks.md, session 4): ARI 0.69 -> 0.78 on the default scene."""
    local_threshold: float = 0.2
    """The cut of that score (the fraction of a Gaussian's painted weight on moving pixels in those frames).
    0.2 brings in missing and wrong Gaussians at about the same rate (docs/benchmarks.md, session 8); with
    the photometric tracking and relabelling (the defaults) it gives the best held-out states (default
    scene: 29.3 dB in session 9; 27.6 with 0.4 in session 7). The quick demo keeps 0.4 (with the flow tracking;
    0.2 is not measured there)."""
    track_masks: str = "frame"
    """Which pixels each tracking step fits (`fgjax.pipeline.track.track_objects`): "frame": those the
    object paints in the stage-1 model at the frame's time (where the image shows it), or "reference":
    those it paints in the reference scene moved by its current pose (session 3; drifts with the pose)."""
    track_joints: str = "auto"
    """"auto": with ``track_masks="frame"``, each object's motion is also fitted as one articulation over all
    its pairs (`fgjax.pipeline.track.fit_joint`: a revolute or prismatic joint), which replaces the
    pair-by-pair poses unless its RMS is more than 3x theirs (+ 0.25 px); "off": pair by pair only."""
    track_chain: int = 0
    """Passes of `fgjax.pipeline.track.chained_joint_poses` after the pair-by-pair tracking (each object's
    reference points followed through chained flow over its moving runs, one joint fitted to all frames);
    0: off (default). Needs ``track_active > 0``. Measured (docs/benchmarks.md, session 6): the drawer's
    trajectory error falls from 0.020 to 0.007, the door's rises from 0.035 to 0.062, the state PSNR goes
    from 25.07 to 24.70 dB."""
    track_photo: int = 50
    """Adam steps per frame of photometric tracking (`fgjax.pipeline.phototrack`: the poses fitted to the
    training images by rendering the reference scene, coarse to fine over blurs of 4, 2 and 0.7 pixels
    (2:2:1 of the steps), then one articulation per object); it replaces the flow-based tracking; 0: off
    (the flow-based tracking, `fgjax.pipeline.track`; the quick demo's choice). Measured
    (docs/benchmarks.md, sessions 7-9), default scene: state PSNR 25.07 dB with the flow tracking, 26.81
    with this alone, 27.62 with ``relabel_steps=150``, 28.5-29.3 with ``local_threshold=0.2`` as well (the
    defaults); ari_controlled 0.76 -> 0.84. It costs ~250 s of the default scene's stage 2 (45 frames x 50
    steps on a 2-core CPU). Under pose noise it is worse than the flow tracking (23.0 against 23.7 dB:
    it fits against uncorrected cameras)."""
    track_photo_radius: float = 0.1
    """Candidates of the photometric tracker's soft membership (scene units; 0: the labels as they are)."""
    track_only_moving: bool = True
    """The photometric tracker redraws, in each frame, only the objects it fits there; the others are drawn
    once per frame and their candidates' memberships learn only in their own frames (`track_photometric`'s
    ``only_moving``; docs/benchmarks.md, session 16: the demo's stage 2 498 s instead of 572 s). False: every
    object in every frame."""
    track_rest: bool = True
    """After the frames are fitted, the photometric tracker compares each object's still spans (the frames after
    a fitted one in which it is not fitted, and keeps that pose) with the object at rest, and takes whichever
    renders closer (`track_photometric`'s ``rest_check``); without it a part that closes again stays wherever its
    last fitted frame put it (the default scene's door 2.5 degrees open, the close pair's drawer 7 degrees turned).
    Measured at the demo's settings, ten pairs off -> on (docs/benchmarks.md, sessions 25-26: the default scene's
    seeds 0-4, the close pair's 0-2, pose noise 0-1): held-out states +0.33 dB on average, higher in nine of the
    ten (-0.45 to +0.79; the close pair 28.29 -> 28.78 dB over its three seeds, every one above 28 with it),
    ``ari_controlled`` +0.003 (-0.014 to +0.024). The one loss is the demo's own run (default scene, seed 0):
    28.34 -> 27.89 dB. It costs the demo about 7 s (12:57 against 12:50). False: off."""
    joint_search: int = 0
    """From this round of tracking on (1: every round; 0: off), after the round's joint fits each fitted object's
    joint is chosen again by the images (`fgjax.pipeline.articulation.search_articulations`: 12 hinges on the
    edges of its principal box, 3 slides along its axes and the fitted joint, each scored by the blurred L1 of its
    best amount in every frame in which the object is displaced); the best replaces the poses where it renders
    closer than they do. Measured at the demo's settings with 2 (docs/benchmarks.md, session 33): in every search
    of rounds 2-3 on the default scene, the close pair and under pose noise the fitted joint won (the lids' 28-45
    degrees off their true hinge on the default scene and under pose noise; the close pair's drawer stayed a
    hinge), so it only refined the amounts: ``ari_controlled`` +0.008, +0.005, -0.004 and the held-out states
    -0.79, +0.01, -0.28 dB against the same runs without it, for about 300 s more of stage 2 on the default scene.
    From round 1 (stage 1's blurred reference) it chose wrong joints for the default scene's door and lid."""
    hinge_trial: int = 150
    """Steps of each trial re-fit of `_hinge_trial` (0: off). After a round's joint fits, a part fitted as a hinge
    that turns 5 degrees or more about an axis more than 2 of its radii from its centre (the far-hinge warning of
    `fgjax.pipeline.phototrack.joint_poses`: a lift mistaken for a turn) is tried against the hinges along the four
    edges of its outline (`fgjax.pipeline.articulation.rect_hinges`) and two slides (``hinge_trial_slide``): the
    hinges' amounts are searched in the images (`search_articulations`), the scene is re-fitted from the round's
    reference under each candidate's poses (the given ones included) for this many steps on the frames where the
    part is displaced, and `_trial_choice` picks by how close each re-fit renders those frames (an edge must beat
    the given poses by ``hinge_trial_margin``, a slide may be within it). The later rounds
    then keep that part's joint (they do not track it again). Why a re-fit: on stage 1's scene, which paints the
    open lid as a blur of its states, the images score the lid's true hinge no better than its lift (0.00844
    against 0.00836 a frame), and every round then re-fits the scene to the lift; re-fitted for 300 steps under
    each, the true hinge renders the displaced frames closer, 0.00872 against 0.00988 (docs/benchmarks.md,
    session 39). Why the later rounds keep it: tracked again from the true poses on a scene re-fitted under them,
    the lid turns only 42 of its 69 degrees (same session). Measured at the demo's settings (session 39): the lid's
    trial chose the edge nearest its true hinge in all five runs; held-out states 28.86 -> 29.30 dB (the demo's
    run), 27.08 -> 29.00 and 27.15 -> 27.76 (pose noise), 28.35 -> 27.59 and 29.62 -> 28.97 (close pair, whose lid
    turns 29-30 of its 71 degrees); `ari_controlled` up on all five; the trial took 115 s of the demo's stage 2
    (516 s against 434).
    0: off."""
    hinge_trial_margin: float = 0.02
    """An edge of `_hinge_trial` replaces the given poses only when its re-fitted loss is below (1 - this) times
    theirs (and no worse than the better slide's); that slide does when its loss is no more than (1 + this) times
    theirs."""
    hinge_trial_slide: bool = True
    """`_hinge_trial` also tries two slides (`fgjax.pipeline.articulation.slide_from_poses`): the given poses' chord
    without their turn, and the same along the part's principal axis nearest it (where that is more than 2 degrees
    off the chord). The better slide wins ties within ``hinge_trial_margin``: a hinge several radii off its part is
    `joint_poses`' sign of a slide fitted as a turn. The close pair's drawer was fitted as a hinge 3.1 radii off it
    turning 36 degrees, and the second pose-noise scene's drawer as one 7.4 radii off turning 6 degrees
    (docs/benchmarks.md, session 40)."""
    hinge_trial_search_slides: bool = True
    """`_hinge_trial`'s slides are also tried with their amounts searched in the images of the round's scene
    (`search_articulations`, each frame from the slide's own amount), as two more candidates. The close pair's
    drawer (seed 0) took the slide along its principal axis with the chord's amounts, which open it 1.4-1.5 times its
    true shift; with searched amounts it opens 0.66-0.89 times it, its re-fitted loss 0.01261 against the given poses'
    0.01378, and the held-out states rose 28.23 -> 29.05 dB (`ari_controlled` 0.925 -> 0.940); the demo's run, pose
    noise and the close pair's seed 1 came out the same to every digit; the second pose-noise scene's drawer became
    a slide with searched amounts in round 3 (re-fitted loss 0.00770 against 0.00814) and its held-out states fell
    28.09 -> 27.78 dB (docs/benchmarks.md, session 41)."""
    hinge_up_deg: float = 25.0
    """> 0: after each round's joint fit, a hinge within this many degrees of the cameras' up
    (`fgjax.pipeline.articulation.camera_up`) is made vertical (`articulation.hinge_made_vertical`), a prior that
    doors hang plumb; 0: off. Only where the cameras are held level and turn enough to fix up
    (`articulation.camera_tilt` within `LEVEL_TILT_DEG` and `LEVEL_AMBIGUITY`), and not for a far hinge
    (`phototrack.is_far_hinge`: the hinge trial's). Measured at 25 (sessions 42-43, stage 2 at the demo's settings,
    held-out states against the defaults before): the second pose-noise scene 29.57 dB against 27.78 (its door 19.6
    degrees off in round 1; its trajectory error 0.007 against 0.017), pose noise 29.47 against 29.15, the close pair
    28.18 against 29.57 (seed 1); docs/benchmarks.md, session 43, has the rest."""
    hinge_trial_edges: int = 2
    """How many of the four edges `_hinge_trial` re-fits: those the images of the round's scene score best
    (`search_articulations`). In every trial logged in sessions 40-41 that chose an edge, it was the one the images
    scored best; two of the seven re-fits are saved for the searched slides' two."""
    track_subset_margin: int = 2
    """The photometric tracker's steps draw only the changing Gaussians and the others whose tiles meet theirs,
    widened by this many tiles (`track_photometric`'s ``subset_margin``; a frame whose part leaves the margin is
    fitted again with every Gaussian; docs/benchmarks.md, session 17: 0.61x the time a frame with one object
    fitted, the same poses up to round-off). -1: every Gaussian at every step."""
    track_rounds: int = 3
    """Rounds of photometric tracking and re-fitting (with ``track_photo > 0`` and ``refit_steps > 0``).
    From the second round on, the tracker renders the previous round's re-fitted scene with its labels
    (stage 1 never moved the parts, so its reference is a blur of their states), each frame may also start
    from the previous round's pose, and the re-fit (with its relabelling) continues from the previous one.
    Each round costs one tracking, its joint fits and one re-fit. Measured (docs/benchmarks.md, sessions 21-22):
    in five stage-2 runs on three stage-1 runs (default scene, close pair, pose noise) two rounds beat one, by
    0.6-2.3 dB of held-out state PSNR and 0.025-0.085 of ``ari_controlled`` (at these defaults on the default
    scene: 26.02 -> 26.82 dB, 0.732 -> 0.816), and in two more with ``track_photo_next=20`` (a third, under pose
    noise, tied); the second round's joints explain their poses far better (robust costs 0.04-0.6 px^2, against
    0.9-2.1 in the first). A third round gained 0.6-1.0 dB on three runs of four but lowered ``ari_controlled``
    on three (session 22). A third round of only the objects whose joint has not converged
    (``track_converged_deg``; stopped when all have) is cheaper and kept ``ari_controlled`` (session 23: at the
    demo's settings +0.78 dB on the default scene, +0.45 under pose noise, +0.02 on the close pair; at these
    defaults +0.05 dB and +0.020 ``ari_controlled`` on the default scene, and -0.43 dB and -0.008 on the close
    pair, where no joint had converged after round 2, so every object was tracked again), so the default is
    three. Session 8, before ``local_threshold=0.2`` and the joint rule of session 18, had seen a second round
    cost 1.25 dB once."""
    track_converged_deg: float = 15.0
    """From the third round on (``track_rounds`` >= 3), an object whose joint kept its kind and moved its axis by
    less than this (degrees, `fgjax.pipeline.phototrack.converged_joints`) from one round to the next is
    converged: later rounds neither track it nor fit its joint again, and they stop when every object has
    converged. 0: every round tracks every object. Measured (docs/benchmarks.md, session 23): from round 1 to
    round 2 the drawers' and doors' axes moved by 1-9 degrees on four runs (default scene, close pair, pose noise,
    and the default scene at these defaults), the lids' by 18-44; after a third round the lids' moved by 3-8. A
    third round of the lid alone took the default scene's held-out states to 28.5 dB at the demo's settings (27.7
    with two rounds; 28.8 with all three objects tracked again, which cost ``ari_controlled``)."""
    track_photo_next: int = 0
    """Adam steps per frame of the photometric tracking in the rounds after the first (``track_rounds``); 0: as
    ``track_photo``. A later round starts each frame from the earlier round's pose as well, so it may need fewer."""
    track_active: float = 0.2
    """Tracking moves an object only in its moving frames (`fgjax.cluster.moving_frames` with this
    ``active`` fraction, widened by one frame); 0: in every frame. Parts rest most of the time; an
    increment fitted while one rests is noise that accumulates."""
    camera_correction: str = "auto"
    """Correct each frame pair's relative camera pose from the flow of the static majority of pixels before
    u - u_cam is thresholded (`fgjax.pipeline.track.camera_correction`): "on", "off", or "auto" = on when
    stage 1 refined the poses (``pose.enabled``: the poses are known to be noisy)."""
    refit_steps: int = 600
    """Steps of `refit_gaussians` (every Gaussian re-fitted to the training images under the tracked
    motion; the controlled scene then starts from them); 0: off (the controlled scene moves stage 1's
    Gaussians at t0). Only with ``trajectories="flow"``."""
    relabel_steps: int = 600
    """The first steps of the re-fit decide, for each Gaussian near a cluster, whether it moves with the
    cluster or stays (`refit_gaussians`' relabelling: both copies rendered, the photometric loss keeps
    one); 0: off. It needs the right motion: with the gt poses (scratch, session 6) it lifts the
    re-fit's held-out states from 29.8 to 32.1 dB, but under the tracked poses, which under-rotate the door
    and the lid, it moves a third of the door to static (ARI 0.78 -> 0.65; state PSNR 25.07 -> 25.35).
    With ``track_photo=50`` (the door turned right) it helps: state PSNR 26.8 -> 27.6 dB (session 7), hence on
    by default with it. The labels improve with the number of steps (session 10, default scene, the same
    tracked poses; ari_controlled / state PSNR): 150 of 300 steps 0.839 / 29.32, 300 of 300 0.857 / 27.87,
    600 of 600 (the default) 0.871 / 28.90, 600 of 750 0.873 / 28.94. The re-fit took 93 s at 600 of 600
    (session 10) against 75 s at 150 of 300 (session 9's phase timing, another day); not timed side by side."""
    relabel_radius: float = 0.1
    """Candidates of the relabelling: Gaussians within this radius (scene units, at t0) of a cluster."""
    hull_fill: bool = True
    """With ``refit_steps > 0``: after the last round's re-fit, the static Gaussians inside the convex hull of a
    cluster's opaque members (opacity >= ``hull_opacity``, at t0) join it (`fgjax.cluster.fill_hulls`), and
    ``hull_refit_steps`` more steps re-fit the scene under those labels. Neither the flow nor the photometric
    relabelling sees a Gaussian that every training frame hides (a drawer's front face when it is out, behind the
    part), and discovery and the relabelling drop a fifth to a third of each part (docs/benchmarks.md, session 24).
    It assumes convex parts (doors, drawers, lids): a concave part's hull takes in the static Gaussians in its
    hollow. Measured at the demo's settings (session 24): ``ari_controlled`` 0.818 -> 0.854 on the default scene,
    0.747 -> 0.796 on the close pair, 0.767 -> 0.799 under pose noise; held-out states +0.04, +0.30 and -0.27 dB.
    False: off."""
    hull_opacity: float = 0.7
    """The members that span `hull_fill`'s hulls: opacity >= this (the faint ones reach out from the part)."""
    hull_max_growth: float = 0.6
    """A cluster whose hull holds more static Gaussians than this times its own size is not filled: its opaque
    members span more than one solid part. Measured (session 24): the fills of the full scenes added 13-40% of a
    cluster; the quick demo's first cluster (a poor stage 1, flow tracking) would have doubled (420 of 424), which
    took its ``ari`` from 0.63 to 0.48."""
    hinge_fill: bool = True
    """With ``refit_steps > 0``: after `hull_fill`, the static Gaussians along a turning part's hinge join it
    (`fgjax.cluster.fill_hinges`): the hinge is the axis of the tracked poses (`fgjax.cluster.hinge_axes`, a part
    that turns by at least ``hinge_min_deg``), the part is the cluster's opaque members (``hull_opacity``), and the
    Gaussians within ``hinge_radius`` times the part's largest distance from the axis, between its ends along it,
    join, when the axis runs along the part (its nearest member within ``hinge_reach`` times that distance). Near
    its hinge a part barely moves, so neither the flow nor the photometric relabelling tells it from the frame
    it hangs on, and the hull of the part's opaque members stops short of it. The same
    ``hull_refit_steps`` re-fit follows. Measured at the demo's settings (session 25, docs/benchmarks.md): only the
    doors turn far enough with an axis along them; ``ari_controlled`` 0.854 -> 0.877 on the default scene and 0.796
    -> 0.816 / 0.853 -> 0.873 on the close pair (two seeds); the held-out states move by -0.4 to +0.8 dB, within
    what the same labels give with another seed. False: off."""
    hinge_radius: float = 0.15
    """`hinge_fill`'s cylinder radius, as a fraction of the part's largest distance from its axis (the default
    scene's door: 0.15 x 0.32 = 0.05 scene units). 0.2 took in more of the frame the door hangs on (a quarter of
    what joined) for the same ARI."""
    hinge_reach: float = 0.15
    """`hinge_fill` leaves a part alone whose nearest opaque member lies farther than this fraction of its
    largest distance from the axis (the axis does not run along the part: a far pivot, a mis-fitted joint)."""
    hinge_min_deg: float = 20.0
    """`hinge_fill` treats a part as turning when its tracked poses turn by at least this many degrees."""
    isolated_factor: float = 2.5
    """After the fills, members farther from every other member of their cluster than this times the cluster's
    median spacing become static (`fgjax.cluster.drop_isolated`), starting the fills' re-fit faded to
    ``ghost_opacity`` like the ghosts (when ``ghost_radius`` > 0); 0: off, else >= 1. The second pass and the fills
    join static Gaussians a few spacings from a part (the box under a lid, a door's frame), and the relabelling does
    not send them back. Measured (docs/benchmarks.md, session 31): labels only, on seven finished runs,
    `ari_controlled` +0.012 on average (-0.025 to +0.030); end to end on six (without the fade) +0.005 to +0.030 on
    five and -0.033 on the close pair's seed 0, the held-out states -0.16 dB on average (-0.66 to +0.89); with the
    fade, on four, +0.007 (-0.023 to +0.025) and -0.09 dB (-0.63 to +0.93; the demo's run 0.873 -> 0.879 and
    28.16 -> 29.09 dB)."""
    colour_radius: float = 0.08
    """After the fills and `isolated_factor`, before `through_prune`: each part's outline relabelled by colour
    (`fgjax.cluster.refine_by_colour`, GrabCut's colour mixtures on the re-fitted Gaussians' DC colours): members
    coloured like the static Gaussians within this distance of the part (scene units) become static, and those
    coloured like the part join it. The motion cues leave the strip along a lid's hinge static and join the box
    under it; where a part differs in colour from its surroundings, its colours tell them apart. The members that
    leave start the re-fit faded like `isolated_factor`'s. 0: off. Measured at the demo's settings (docs/benchmarks.md,
    session 36), ``ari_controlled`` and held-out states against the same runs without it: 0.888 -> 0.928 and 29.42
    -> 28.44 dB on the default scene (`fgjax demo`), 0.839 -> 0.909 and 26.91 -> 27.08 under pose noise, 0.862 ->
    0.894 and 27.78 -> 28.32 / 0.898 -> 0.932 and 28.88 -> 29.99 on the close pair (seeds 0 / 1)."""
    colour_rounds: bool = False
    """With ``colour_radius`` > 0: the outlines are relabelled by colour after each round's re-fit too, so that the
    next round tracks the parts without the Gaussians around them (a lid's box). Measured (session 36): 0.929 / 28.86
    dB on the default scene and 0.923 / 26.56 under pose noise, against 0.931 / 28.67 and 0.916 / 26.94 without."""
    colour_components: int = 4
    """`colour_radius`: Gaussian-mixture components of each colour model."""
    colour_separation: float = 0.65
    """`colour_radius` leaves a part alone whose two colour models tell its members from its surroundings with a
    balanced accuracy below this (a part coloured like what it hangs on). Both sets still hold the errors being
    mended, so a part that does differ scores 0.72-0.97 on the synthetic scenes (session 36)."""
    settle_rest: bool = True
    """With the photometric tracking, ``track_rest`` and ``track_active``, after the outlines are relabelled by
    colour: each object's still spans are put back at rest where that renders closer, judged again with the final
    labels on stage 1's scene (`fgjax.pipeline.phototrack.settle_at_rest`), the fitted frames just before a span
    included where each renders closer at rest. The tracker's own check judges with discovery's labels, or on a scene re-fitted under the pose
    it checks. The close pair's drawer (seed 0) was fitted past rest as it closed and kept 0.18 inside its cabinet
    for the 20 frames after. Measured at the demo's settings against the same runs without it (docs/benchmarks.md,
    session 37): ``ari_controlled`` 0.894 -> 0.929 on that run (the held-out states 28.32 -> 28.35 dB); elsewhere a
    lid's last frames settle, which moves the held-out states by -0.37 to +0.19 dB (the demo 28.67 -> 28.86), or
    nothing does. It costs about 4 s. False: off."""
    through_prune: float = 0.5
    """After the fills and `isolated_factor`, before their re-fit: the static Gaussians with more than this share of
    their painted weight over the training frames where the parts' members cover the pixel (`seen_through`, the
    parts at their tracked poses) get opacity ~0. They lend a part their colour where its own Gaussians are
    sparse (a door's members cover its pixels by ~0.8 on the default scene) and show as streaks of it where a
    held-out state moves the part away. 0: off, else in (0, 1]. Measured at the demo's settings (session 32,
    docs/benchmarks.md), against the same runs without it: `ari_controlled` +0.009 / +0.006 / +0.040 / -0.001
    (default scene, pose noise, close pair seeds 0 and 1), held-out states +0.33 / 0.00 / +0.01 / -0.22 dB; 255-262
    Gaussians pruned, 12-17 s."""
    hull_refit_steps: int = 100
    """Steps of `refit_gaussians` (no relabelling) after `hull_fill`, `hinge_fill`, `isolated_factor`,
    `colour_radius` and `through_prune`: the Gaussians that joined were re-fitted as static, those dropped as
    members; 0: none."""
    refit_lr_scale: float = 1.0
    """Every learning rate of `refit_gaussians` (stage 1's optimiser groups and schedules) times this. Each
    re-fit restarts Adam at stage 1's first learning rates, which might blur what stage 1 had settled; measured at
    the demo's settings on the default scene (session 28, docs/benchmarks.md), it does not: held-out states
    26.01 / 26.58 / 27.89 / 28.11 dB at 0.1 / 0.3 / 1 / 2 (seed 0), and at 2 against 1 on seeds 1 and 2 27.22 /
    27.85 against 28.25 / 28.18 dB; under pose noise 26.81 at 2 against 26.71 at 1."""
    ghost_radius: float = 0.03
    """Before each round's re-fit, static Gaussians within this distance (scene units) of a part's members at any
    of its tracked poses (`fgjax.cluster.near_swept`) start it with their opacity at most ``ghost_opacity``:
    what stage 1 left where the parts pass (its blur of their states) or behind them is hidden at rest, so the
    rest frames cannot correct it and the few frames that show it barely do; faded, it returns only where those
    frames show something. 0: off. Measured at the demo's settings (session 29, docs/benchmarks.md): 0.03 against
    off raised ari_controlled on 4 of 5 runs (default scene seeds 0-2 +0.010 / +0.019 / +0.020, the close pair
    +0.031, pose noise -0.001); the held-out states moved +0.27 / -0.34 / +0.07 / -0.14 / +0.83 dB. 0.08 fades
    static surfaces the re-fit does not restore (seed 0: -0.14 dB, ari_controlled -0.017). 0.02 and 0.05 (session
    30) gave 0.831 and 0.841 on seed 0 against 0.873 at 0.03: the gain is within the spread between radii."""
    ghost_opacity: float = 0.05
    """The opacity ``ghost_radius``'s Gaussians start a re-fit at (at most), in (0, 1)."""
    trajectories: str = "flow"
    """Where the objects' motion comes from: "flow" (rigid poses tracked from optical flow,
    `fgjax.pipeline.track`) or "deformation" (the stage-1 deformation field)."""
    hidden: int = 64
    depth: int = 3
    n_freqs_x: int = 6
    n_freqs_v: int = 4
    distill_steps: int = 500
    distill_batch: int = 8
    """Training times per distillation step (a random minibatch)."""
    photo_steps: int = 200
    control_rigid: bool = True
    """The controlled scene moves each object rigidly: the control network's output for an object's members is
    replaced by the rigid motion closest to it (`controlled_gaussians`' ``rigid``: their reference centres moved by
    the best rotation and shift of their centres, their orientations turned with it, their scales kept), when
    rendering and evaluating; the control network is trained as without it. The parts are rigid, and what the
    network leaves non-rigid is its error: at the demo's settings (300 distillation steps) on the five runs of
    docs/benchmarks.md, session 41, the held-out states rose +0.15 to +0.60 dB (all five). False: the network's
    output as it is (the paper's)."""
    flow_weight: float = 0.01
    """beta of L_uGS in the photometric phase (0: photometric loss only)."""
    flow_threshold: float = 0.5
    """|u - u_cam| below this (pixels) counts as static in L_uGS (0: off)."""
    lr: float = 2e-3
    seed: int = 0


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
        the tracked motion (`Stage2Config.refit_steps`), else None (the stage-1 model at t0).
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


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------


def _atomic_bytes(path: Path, write) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, write)


def _deformed_fn(spec, static: bool):
    """jitted (params, alive, t) -> (means, raw quats, log_scales) of the stage-1 model at time t."""
    from fgjax.models.deform import deform_apply

    def f(params, t):
        g: Gaussians = params["gaussians"]
        if static or spec is None:
            return g.means, g.quats, g.log_scales
        dx, dq, ds = deform_apply(spec, params["deform"], g.means, t)
        return g.means + dx, g.quats + dq, g.log_scales + ds

    return jax.jit(f)


def _with_geometry(params, means, quats, log_scales):
    g: Gaussians = params["gaussians"]
    return {**params, "gaussians": Gaussians(means, log_scales, quats, g.opacity_logits, g.sh)}


def _with_refit(params, refit):
    """Stage-1 `params` with their Gaussians replaced by stage 2's re-fitted ones (`refit`, numpy leaves;
    None: unchanged)."""
    if refit is None:
        return params
    return {**params, "gaussians": jax.tree_util.tree_map(jnp.asarray, refit)}


def _control_hparams(cfg: Stage2Config, x_scale: float, v_scale: float) -> dict[str, Any]:
    return {"encoding": "frequency", "hidden": cfg.hidden, "depth": cfg.depth, "n_freqs_x": cfg.n_freqs_x,
            "n_freqs_v": cfg.n_freqs_v, "x_scale": float(x_scale), "v_scale": float(v_scale)}


def controlled_gaussians(control: ControlNet, base, canonical, labels, vectors, rigid: bool = False):
    """Geometry of the controlled scene (module docstring, step 4).

    Args:
        control: `ControlNet`.
        base: (means [N, 3], raw quats [N, 4], log_scales [N, 3]) of the stage-1 scene at t0.
        canonical: [N, 3] canonical centres X.
        labels: [N] int cluster ids (-1: not controlled).
        vectors: [K, 3] one control vector per cluster (K >= 1 when any label >= 0).
        rigid: each cluster moved by the rigid motion closest to the network's (`Stage2Config.control_rigid`):
            `fgjax.pipeline.track.fit_group_poses` from the base centres to the network's, applied to the base
            centres and orientations; the base scales. Not differentiable (the fit is held constant).

    Returns:
        (means, quats, log_scales), each [N, ...].
    """
    from fgjax.models.control_net import per_gaussian_vectors

    means0, q0, s0 = base
    labels = jnp.asarray(labels)
    vectors = jnp.asarray(vectors, jnp.float32).reshape(-1, 3)
    v, mask = per_gaussian_vectors(vectors, labels)
    dx1, dq1, ds1 = control_apply(control, v, canonical, mask)
    dx0, dq0, ds0 = control_apply(control, jnp.zeros_like(v), canonical, mask)
    means = means0 + (dx1 - dx0)
    if rigid:
        from fgjax.pipeline.track import fit_group_poses, transform_gaussians

        poses = fit_group_poses(means0, means, labels, int(vectors.shape[0]))  # [K, 4, 4]
        means, quats = transform_gaussians(jnp.asarray(means0, jnp.float32), jnp.asarray(q0, jnp.float32), labels,
                                           poses)
        return means, quats, jnp.asarray(s0, jnp.float32)
    return means, q0 + (dq1 - dq0), s0 + (ds1 - ds0)


# ---------------------------------------------------------------------------------------------
# run-level helpers: a loaded stage-1 run bundled with its stage-2 result
# ---------------------------------------------------------------------------------------------


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
        f = self.__dict__.get("_deformed_jit")
        if f is None:
            f = self.__dict__["_deformed_jit"] = _deformed_fn(self.spec, self.static)
        return f(self.state.params, jnp.asarray(t, jnp.float32))

    def base(self):
        """(means, raw quats, log_scales) of the controlled scene's reference: stage 2's re-fitted Gaussians
        when it made them, else the stage-1 model at t0."""
        if self.s2 is not None and self.s2.refit is not None:
            g = self.s2.refit
            return jnp.asarray(g.means), jnp.asarray(g.quats), jnp.asarray(g.log_scales)
        return self.deformed(self.s2.t0)

    def control_params(self):
        """Parameters whose opacities and colours the controlled scene renders with."""
        return _with_refit(self.state.params, None if self.s2 is None else self.s2.refit)

    def render_geometry(self, means, quats, log_scales, viewmat, K, width: int, height: int, *, colors=None,
                        background=None, capacity=None, params=None):
        """Render given geometry with the run's opacities and colours (or `colors` [N, C]); ``params``: whose
        opacities and colours (default: stage 1's)."""
        from fgjax.pipeline.stage1 import render_params
        from fgjax.render.api import rasterization

        params = _with_geometry(self.state.params if params is None else params, means, quats, log_scales)
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
    """Load a run folder: stage 1 (`fgjax.pipeline.stage1.load_run`) and RUN/stage2.npz.

    Raises:
        FileNotFoundError: not a trained run.
        Stage2Error: stage-2 results missing (when required) or unreadable.
    """
    from fgjax.pipeline.stage1 import load_run

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder {run_dir} does not exist")
    cfg, state, spec, meta = load_run(run_dir)
    state.static = meta.get("static", False)
    p = run_dir / STAGE2_NAME
    if not p.exists():
        if require_stage2:
            raise Stage2Error(f"{run_dir} has no stage-2 results ({STAGE2_NAME}); run stage 2 first: "
                              f"python -m fgjax.pipeline.stage2 --run {run_dir} --data DATA")
        return LoadedRun(run_dir, cfg, state, spec, meta, None)
    try:
        with np.load(p, allow_pickle=False) as z:
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
    except (OSError, ValueError, KeyError) as e:
        raise Stage2Error(f"{p} is not a readable stage-2 result: {e}") from e
    if len(s2.labels) != state.params["gaussians"].means.shape[0]:
        raise Stage2Error(f"{p}: {len(s2.labels)} labels for {state.params['gaussians'].means.shape[0]} Gaussians "
                          "(stage 1 was re-trained after stage 2; run stage 2 again)")
    return LoadedRun(run_dir, cfg, state, spec, meta, s2)


def cluster_vectors_at(s2: Stage2Result, t: float) -> np.ndarray:
    """[K, 3] v_c(t, k) = ς(t, k) - ς(t0, k), linear in time between the stored samples."""
    tt = s2.traj_times
    out = np.zeros((s2.num_objects, 3))
    for k in range(s2.num_objects):
        for d in range(3):
            out[k, d] = np.interp(t, tt, s2.traj[k, :, d]) - s2.traj[k, 0, d]
    return out


def snap_vector(s2: Stage2Result, k: int, vector) -> tuple[np.ndarray, float]:
    """Snap a user displacement for object k (0-based) to its trajectory: (vector on ς(·, k), time)."""
    if not 0 <= k < s2.num_objects:
        raise ValueError(f"object {k + 1} out of range: the run has {s2.num_objects} object(s) (1..{s2.num_objects})")
    snap = cluster.snap_to_trajectory(s2.traj[k], np.asarray(vector, np.float64), times=s2.traj_times)
    return snap.point - s2.traj[k, 0], snap.t


def render_controlled(run: LoadedRun, vectors, viewmat, K, width: int, height: int) -> np.ndarray:
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


def posed_base(run: LoadedRun, labels, poses):
    """(means [N, 3], raw quats [N, 4], log-scales [N, 3]) of the controlled scene's reference (`LoadedRun.base`)
    with each object's Gaussians (``labels`` [N], -1 static) moved rigidly by its pose (``poses`` [K, 4, 4],
    x -> R x + t in scene units; finite); no control network."""
    from fgjax.pipeline.track import transform_gaussians

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


def render_clusters(run: LoadedRun, viewmat, K, width: int, height: int, *, t: float | None = None,
                    vectors=None, source: str = "stage1", alpha_threshold: float = 0.5, labels=None,
                    poses=None) -> np.ndarray:
    """Per-pixel object ids [H, W] int (0 = static or background, k = cluster k - 1 + 1).

    One-hot cluster features (channel 0 for every Gaussian outside the clusters, channel k for
    cluster k - 1) are composited like colour; a pixel takes the argmax channel, and 0 where the
    rendered alpha is below `alpha_threshold`. Geometry: the controlled scene for `vectors` [K, 3] when
    given; else, at time `t` (default: the reference time), ``source`` "stage1": the stage-1 model at t
    (the scene `fgjax render` draws in colour for the same camera), or "control": the controlled scene
    with each object at its trajectory vector v_c(t, k). ``poses`` [K, 4, 4] (instead of `vectors`): the
    controlled scene's reference (`LoadedRun.base`) with each object's Gaussians moved rigidly by its pose, no
    control network (evaluation: the gt motion). ``labels`` [N] (-1..K-1) replaces stage 2's clustering
    (evaluation: `fgjax.pipeline.evaluate`'s labels taken from the ground truth).
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
    from fgjax.pipeline.track import label_onehot

    feat, alpha, _ = run.render_geometry(*geo, viewmat, K, width, height, colors=label_onehot(labels, s2.num_objects),
                                         params=params)
    ids = np.argmax(np.asarray(feat), axis=-1)
    return np.where(np.asarray(alpha) >= alpha_threshold, ids, 0).astype(np.int64)


def write_cluster_maps(run_dir: str | Path | LoadedRun, cams, out: str | Path, log=print,
                       source: str = "control") -> int:
    """``fgjax render --clusters``: from a run folder (or a run already loaded by `load_stage2`), per camera (name,
    viewmat, K, time, w, h) write OUT/{name}_ids.npy (int32 object ids, 0 = static) and OUT/{name}_ids.png
    (colour-coded), drawn from ``source`` (`render_clusters`): "control", the controlled scene with each object at
    its trajectory at the camera's time (what `fgjax eval` scores as ``ari_controlled``), or "stage1", the stage-1
    model at that time (``ari``). Returns the exit status."""
    return _write_renders(run_dir, cams, out, log, clusters=True, source=source)


def write_controlled_frames(run_dir: str | Path | LoadedRun, cams, out: str | Path, log=print) -> int:
    """``fgjax render --source control``: from a run folder (or a run already loaded by `load_stage2`), per camera
    (name, viewmat, K, time, w, h) write OUT/{name}.png, the controlled scene with each object at its trajectory at
    the camera's time (`cluster_vectors_at`, `render_controlled`). Returns the exit status."""
    return _write_renders(run_dir, cams, out, log, clusters=False, source="control")


def _write_renders(run_dir, cams, out, log, *, clusters: bool, source: str) -> int:
    """`write_cluster_maps` (``clusters``) or `write_controlled_frames`: 2 where the run cannot be loaded."""
    import imageio.v3 as iio

    from fgjax.pipeline.demo import ids_to_color

    run = run_dir if isinstance(run_dir, LoadedRun) else _load_for_render(run_dir)
    if run is None:
        return 2
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name, vm, K, t, w, h in cams:
        if clusters:
            ids = render_clusters(run, vm, K, w, h, t=t, source=source)
            np.save(out / f"{name}_ids.npy", ids.astype(np.int32))
            iio.imwrite(out / f"{name}_ids.png", ids_to_color(ids))
        else:
            img = render_controlled(run, cluster_vectors_at(run.s2, float(t)), vm, K, w, h)
            iio.imwrite(out / f"{name}.png", _to_u8(img))
    what = "object-id maps" if clusters else "cameras of the controlled scene"
    log(f"rendered {len(cams)} {what} ({run.s2.num_objects} object(s), {source}) to {out}")
    return 0


def _load_for_render(run_dir: str | Path) -> LoadedRun | None:
    """`load_stage2`, or None after printing why to stderr (a missing run, checkpoint or stage-2 result)."""
    from fgjax.train.checkpoint import CheckpointError

    try:
        return load_stage2(run_dir)
    except (FileNotFoundError, CheckpointError, Stage2Error) as e:
        print(f"fgjax render: {e}", file=sys.stderr)
        return None


# ---------------------------------------------------------------------------------------------
# stage 2
# ---------------------------------------------------------------------------------------------


def _to_u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def discover_run(run: LoadedRun, scene, cfg: Stage2Config, cache_dir: Path, log=print):
    """Step 5 on a stage-1 run: returns (`Discovery`, deformed centres [T, N, 3] in time order, times [T])."""
    from fgjax.data.loaders import viewmat_to_c2w
    from fgjax.data.opticalflow import estimate_flow
    from fgjax.pipeline.discover import camera_flow_from_depth, discover
    from fgjax.render.api import rasterization

    order = np.argsort(scene.times, kind="stable")
    times = scene.times[order]
    alive = run.state.densify.alive
    w, h = scene.width, scene.height
    means_t, quats_t, centres = [], [], []
    depths, alphas = [], []
    g = run.state.params["gaussians"]
    for i in order:
        m, q, ls = run.deformed(float(scene.times[i]))
        centres.append(np.asarray(m))
        params = _with_geometry(run.state.params, m, q, ls)
        qa, sa, oa = activate(params["gaussians"], alive)
        means_t.append(np.asarray(m))
        quats_t.append(np.asarray(qa))
        _, alpha, info = rasterization(m, qa, sa, oa, jnp.zeros((m.shape[0], 1), jnp.float32),
                                       jnp.asarray(scene.viewmats[i], jnp.float32),
                                       jnp.asarray(scene.Ks[i], jnp.float32), w, h, render_depth=True,
                                       tile_size=run.cfg.train.tile_size)
        depths.append(np.asarray(info["depth"]))
        alphas.append(np.asarray(alpha))
    _, sa, oa = activate(g, alive)
    c2w = viewmat_to_c2w(scene.viewmats[order])
    flows, cams, valid = [], [], []
    correct = cfg.camera_correction == "on" or (cfg.camera_correction == "auto" and "pose" in run.state.params)
    if correct:
        from fgjax.pipeline.track import camera_correction
    rms_all: list[float] = []
    t_flow = time.perf_counter()
    for j in range(len(order) - 1):
        a, b = order[j], order[j + 1]
        flows.append(estimate_flow(_to_u8(scene.images[a]), _to_u8(scene.images[b]), cfg.flow_method,
                                   cache_dir=cache_dir))
        trusted = alphas[j] >= cfg.min_alpha  # pixels with a rendered depth to trust
        c2w_b = c2w[j + 1]
        if correct:
            vm_b, rms, _ = camera_correction(depths[j], trusted, flows[-1], scene.viewmats[a], scene.viewmats[b],
                                             scene.Ks[a])
            c2w_b = viewmat_to_c2w(vm_b[None])[0]
            rms_all.append(rms)
        cf, ok = camera_flow_from_depth(depths[j], scene.Ks[a], c2w[j], c2w_b)
        cams.append(cf)
        valid.append(ok & trusted)
    log(f"stage 2: optical flow of {len(flows)} pairs ({time.perf_counter() - t_flow:.1f} s)"
        + (f"; camera poses corrected from the static flow (median inlier RMS {np.nanmedian(rms_all):.2f} px)"
           if correct and rms_all and np.any(np.isfinite(rms_all)) else ""))
    n = len(order) - 1
    thr = cfg.threshold_px if isinstance(cfg.threshold_px, str) else float(cfg.threshold_px)
    # the deformed scales differ from canonical ones only by ds; discovery uses the canonical ones
    disc = discover(np.stack(means_t[:n]), np.stack(quats_t[:n]), np.asarray(sa), np.asarray(oa),
                    scene.viewmats[order][:n], scene.Ks[order][:n], np.stack(flows), np.stack(cams),
                    valid=np.stack(valid), threshold_px=thr, min_px=cfg.min_px,
                    images=scene.images[order][:n] if cfg.mask_guide_radius > 0 else None,
                    guide_radius=cfg.mask_guide_radius, guide_eps=cfg.mask_guide_eps,
                    score_threshold=cfg.score_threshold, min_score=cfg.min_score,
                    per_frame=cfg.local_radius > 0 or cfg.track_active > 0 or cfg.split_motion or cfg.merge_eps > 0)
    dyn = disc.dynamic & np.asarray(alive)
    return disc._replace(dynamic=dyn), np.stack(centres), times, (order, np.stack(flows), np.stack(cams))


def _tracked_poses(run: LoadedRun, scene, order, ref: Gaussians, labels: np.ndarray, num_objects: int, flows,
                   cfg: Stage2Config, moving=None, log=print) -> tuple[np.ndarray, dict]:
    """(poses [K, T, 4, 4] of each object at each training time (time order), tracked from the flow (or the
    images, ``cfg.track_photo``) against the reference scene `ref` (stage 1 at t0, raw parameters), the joint
    fits' kinds and costs (`_photometric_poses`; {} for the flow tracking)).
    ``moving`` [K, T-1]: the pairs in which each object moves (`fgjax.cluster.moving_frames`; None: all)."""
    from fgjax.pipeline.track import track_objects

    if cfg.track_photo > 0:
        return _photometric_poses(run, scene, order, ref, labels, num_objects, cfg, moving, log,
                                  search=cfg.joint_search == 1)
    alive = run.state.densify.alive
    qa, sa, oa = activate(ref, alive)
    if cfg.track_masks == "frame":  # object pixels from the stage-1 model at each frame's time
        ms, qs, ss = [], [], []
        for i in order:
            m, q, ls = run.deformed(float(scene.times[i]))
            q_i, s_i, _ = activate(_with_geometry(run.state.params, m, q, ls)["gaussians"], alive)
            ms.append(np.asarray(m))
            qs.append(np.asarray(q_i))
            ss.append(np.asarray(s_i))
        geo = (np.stack(ms), np.stack(qs), np.stack(ss))
    else:
        geo = (ref.means, qa, sa)
    poses = track_objects(*geo, oa, labels, num_objects, scene.viewmats[order], scene.Ks[order], flows,
                          scene.width, scene.height, moving=moving, joints=cfg.track_joints,
                          tile_size=run.cfg.train.tile_size, log=log)
    if cfg.track_chain > 0 and moving is not None:
        from fgjax.pipeline.track import chained_joint_poses

        for _ in range(int(cfg.track_chain)):
            poses, _ = chained_joint_poses(ref.means, qa, sa, oa, labels, poses, moving, scene.viewmats[order],
                                           scene.Ks[order], flows, scene.width, scene.height,
                                           tile_size=run.cfg.train.tile_size, log=log)
    return poses, {}


def photo_level_steps(n: int) -> tuple[int, int, int]:
    """The photometric tracker's Adam steps per blur level (4, 2, 0.7 pixels) for ``n`` steps a frame (2:2:1)."""
    return max(1, round(0.4 * n)), max(1, round(0.4 * n)), max(1, n - 2 * round(0.4 * n))


def _photometric_poses(run: LoadedRun, scene, order, ref: Gaussians, labels: np.ndarray, num_objects: int,
                       cfg: Stage2Config, moving, log=print, init_poses=None, fixed=None,
                       prev_joints: dict | None = None, search: bool = False) -> tuple[np.ndarray, dict]:
    """`_tracked_poses` by `fgjax.pipeline.phototrack` (``cfg.track_photo`` steps per frame; with
    ``init_poses``, ``cfg.track_photo_next`` where set) from the reference scene `ref` (raw parameters;
    ``init_poses`` [K, T, 4, 4]: an earlier round's poses, a further start of each frame): (poses [K, T, 4, 4],
    {"joint_kinds": [K], "joint_costs": [K] robust costs in px^2, None where kept, "joint_axes": [K] unit axes
    [3], None where kept, "joint_hinge_offsets": [K] a hinge's distance from its part's centre in the part's radii
    (`phototrack.hinge_offset`; over 2: likely a shift fitted as a turn), None for the other joints,
    "hinge_trials": [K] `_hinge_trial`'s record, None where none ran}). ``fixed`` [K]
    bool (needs ``init_poses`` and ``prev_joints``, the earlier round's dict): objects neither tracked nor fitted
    again; they keep ``init_poses`` and their earlier joints."""
    from fgjax.pipeline.phototrack import joint_poses, track_photometric

    n = cfg.track_photo_next if init_poses is not None and cfg.track_photo_next > 0 else cfg.track_photo
    steps = photo_level_steps(int(n))
    vms, Ks = scene.viewmats[order], scene.Ks[order]
    poses, _ = track_photometric(ref, run.state.densify.alive, labels, num_objects, scene.images[order], vms, Ks,
                                 moving=moving, sh_degree=run.cfg.model.sh_degree,
                                 background=run.cfg.model.background, capacity=_render_capacity(run),
                                 tile_size=run.cfg.train.tile_size, steps=steps, radius=cfg.track_photo_radius,
                                 init_poses=init_poses, only_moving=cfg.track_only_moving,
                                 subset_margin=None if cfg.track_subset_margin < 0 else int(cfg.track_subset_margin),
                                 fixed=fixed, rest_check=cfg.track_rest, log=log)
    fixed = np.zeros(num_objects, bool) if fixed is None else np.asarray(fixed, bool)
    rng = np.random.default_rng(cfg.seed)
    m0 = np.asarray(ref.means)
    pts = []
    for k in range(num_objects):
        idx = np.flatnonzero(labels == k)
        # 64 points over every frame pin a joint: 256 took ~165 s for three objects on the default scene, 64 take
        # ~45 s (session 9; the same joint kinds, state PSNR 28.47 -> 29.32 dB, which is within the joint fit's
        # sensitivity to its inputs)
        sel = m0[rng.choice(idx, min(len(idx), 64), replace=False)] if len(idx) else np.zeros((0, 3))
        # a fixed object: no fit (its poses are kept); its points are still drawn, so that the others' draws
        # (and joints) are those of a round that fits every object
        pts.append(np.zeros((0, 3)) if fixed[k] else sel)
    poses, kinds, costs, axes, offsets = joint_poses(pts, poses, vms, Ks, return_axes=True, return_offsets=True,
                                                     log=log)
    if cfg.hinge_up_deg > 0:
        from fgjax.pipeline.articulation import LEVEL_AMBIGUITY, LEVEL_TILT_DEG, camera_tilt, camera_up, \
            hinge_made_vertical
        from fgjax.pipeline.phototrack import is_far_hinge, largest_turn_deg

        up = camera_up(vms)
        tilt, ambiguity = camera_tilt(vms)
        level = tilt <= LEVEL_TILT_DEG and ambiguity <= LEVEL_AMBIGUITY
        alive = np.asarray(run.state.densify.alive, bool)
        hinges = (np.asarray(kinds) == "revolute") & ~fixed  # [K] the round's fitted hinges
        if not level and np.any(hinges):
            log(f"stage 2: the cameras' up is not trusted (tilt {tilt:.2f} degrees RMS, at most {LEVEL_TILT_DEG:g}; "
                f"ambiguity {ambiguity:.3f}, at most {LEVEL_AMBIGUITY:g}): hinges kept as tracked (hinge_up_deg)")
        for k in np.flatnonzero(hinges & level):
            if is_far_hinge(offsets[k], largest_turn_deg(poses[k])):
                continue  # a hinge far off its part is not trusted as a hinge at all (the hinge trial's)
            made = hinge_made_vertical(m0[(labels == k) & alive], poses[k], up, float(cfg.hinge_up_deg))
            if made is not None:
                poses[k], axes[k] = made[0], made[1]
                log(f"stage 2: object {k + 1}'s hinge, {made[2]:.1f} degrees off the cameras' up "
                    f"{np.round(up, 3).tolist()}, made vertical (hinge_up_deg={cfg.hinge_up_deg:g})")
    if search:
        from fgjax.pipeline.articulation import search_articulations

        poses, found = search_articulations(ref, run.state.densify.alive, labels, num_objects, scene.images[order],
                                            vms, Ks, poses, kinds=kinds, objects=~fixed,
                                            sh_degree=run.cfg.model.sh_degree, background=run.cfg.model.background,
                                            capacity=_render_capacity(run), tile_size=run.cfg.train.tile_size,
                                            log=log)
        for k, f in enumerate(found):
            if f is not None and f["replaced"]:
                kinds[k], axes[k], offsets[k] = f["kind"], np.asarray(f["axis"]), np.nan
    trials = {}
    if cfg.hinge_trial > 0:
        poses, trials = _hinge_trial(run, scene, order, ref, labels, num_objects, poses, kinds, offsets, cfg, ~fixed,
                                     log)
        for k, t in trials.items():
            if t["replaced"]:
                kinds[k], axes[k] = t["kind"], np.asarray(t["axis"])
                offsets[k] = np.nan if t["offset"] is None else t["offset"]
    out = {"joint_kinds": list(kinds), "joint_costs": [None if not np.isfinite(c) else float(c) for c in costs],
           "joint_axes": [None if not np.all(np.isfinite(a)) else [float(x) for x in a] for a in axes],
           "joint_hinge_offsets": [None if not np.isfinite(r) else float(r) for r in offsets],
           "hinge_trials": [trials.get(k) for k in range(num_objects)]}
    for k in np.flatnonzero(fixed):  # the earlier round's joint
        for key in out:
            out[key][k] = prev_joints.get(key, [None] * num_objects)[k]
    return poses, out


def _posed_frame_loss(g: Gaussians, alive, labels, pose, viewmat, K, image, background, *, sh_degree: int,
                      width: int, height: int, capacity: int | None, tile_size: int, lam: float):
    """(stage 1's photometric loss of ``image`` [H, W, 3] against `g` (raw parameters) with each object moved by its
    pose (``pose`` [K, 4, 4]; ``labels`` [N], -1 static) seen by one camera, whether the render overflowed)."""
    from fgjax.pipeline.stage1 import render_params
    from fgjax.pipeline.track import transform_gaussians
    from fgjax.train.losses import photometric_loss

    m, q = transform_gaussians(g.means, g.quats, labels, pose)
    img, _, info, _ = render_params({"gaussians": Gaussians(m, g.log_scales, q, g.opacity_logits, g.sh)}, alive,
                                    viewmat, K, 0.0, spec=None, sh_degree=sh_degree, width=width, height=height,
                                    background=background, capacity=capacity, tile_size=tile_size)
    return photometric_loss(img, image, lam), info["overflow"]


@functools.partial(jax.jit, static_argnames=("sh_degree", "width", "height", "capacity", "tile_size", "lam"))
def _posed_loss(g: Gaussians, alive, labels, pose, viewmat, K, image, background, **kw):
    """`_posed_frame_loss`'s loss, inf where the render overflows or the loss is not finite. Jitted once for all
    the scenes and poses of a shape."""
    loss, over = _posed_frame_loss(g, alive, labels, pose, viewmat, K, image, background, **kw)
    return jnp.where(jnp.isfinite(loss) & ~over, loss, jnp.inf)


def _posed_losses(run: LoadedRun, scene, order, gs: Gaussians, labels: np.ndarray, poses: np.ndarray, frames):
    """[F] stage 1's photometric loss of each training frame in ``frames`` (time order) rendered from `gs` (raw
    parameters) with each object moved by its pose (``poses`` [K, T, 4, 4]); inf where the render overflows."""
    g = jax.tree_util.tree_map(jnp.asarray, gs)
    args = (jnp.asarray(run.state.densify.alive), jnp.asarray(labels, jnp.int32))
    bg = jnp.asarray(run.cfg.model.background, jnp.float32)
    kw = dict(sh_degree=int(run.cfg.model.sh_degree), width=int(scene.width), height=int(scene.height),
              capacity=_render_capacity(run), tile_size=int(run.cfg.train.tile_size),
              lam=float(run.cfg.train.lambda_dssim))
    return np.array([float(_posed_loss(g, *args, jnp.asarray(poses[:, f], jnp.float32),
                                       jnp.asarray(scene.viewmats[order[f]], jnp.float32),
                                       jnp.asarray(scene.Ks[order[f]], jnp.float32),
                                       jnp.asarray(scene.images[order[f]]), bg, **kw))
                     for f in np.asarray(frames, np.int64).reshape(-1)])


def _trial_held(history: list[dict], num_objects: int) -> np.ndarray:
    """[K] bool: the objects whose poses a `_hinge_trial` of some earlier round (``history``: each round's joint
    dict) replaced; the later rounds keep their joints."""
    held = np.zeros(num_objects, bool)
    for joints in history:
        for k, rec in enumerate(joints.get("hinge_trials") or []):
            held[k] |= bool(rec and rec.get("replaced"))
    return held


def _trial_name(h: int, axis) -> str:
    """How the log names `_hinge_trial`'s candidate ``h`` (-1 the given poses, -2 the chord's slide, -3 the slide
    along a principal axis, -4 and -5 the same with their amounts searched, else an edge)."""
    if h == -1:
        return "the given poses"
    what = {-2: "slide", -3: "slide along a principal axis", -4: "slide, its amounts searched",
            -5: "slide along a principal axis, its amounts searched"}.get(h, f"edge {h}")
    return f"{what}, axis {np.round(np.asarray(axis), 3).tolist()}"


def _trial_choice(hyps, losses, margin: float) -> int:
    """The index of `_hinge_trial`'s choice among its candidates (``hyps``: -1 the given poses, first; below -1 a
    slide; else an edge) by their re-fitted ``losses``: the best edge when it is below (1 - ``margin``) times the
    given poses' loss and no worse than the best slide's; else the best slide when it is no more than (1 +
    ``margin``) times the given poses' (a hinge far off its part is likely a slide fitted as a turn:
    `joint_poses`); else the given poses (0)."""
    hyps, losses = list(hyps), np.asarray(losses, np.float64)
    if hyps[0] != -1 or not np.all(np.isfinite(losses) | (losses == np.inf)):
        raise ValueError(f"_trial_choice: the given poses come first and the losses are not NaN; got {hyps}, "
                         f"{losses.tolist()}")
    slides = [i for i, h in enumerate(hyps) if h < -1]
    slide = min(slides, key=lambda i: losses[i]) if slides else None
    edges = [i for i, h in enumerate(hyps) if h >= 0]
    if edges:
        e = min(edges, key=lambda i: losses[i])
        if losses[e] < (1.0 - margin) * losses[0] and (slide is None or losses[e] <= losses[slide]):
            return e
    if slide is not None and losses[slide] <= (1.0 + margin) * losses[0]:
        return slide
    return 0


def _trial_slides(points, poses, min_deg: float = 2.0) -> list[tuple]:
    """`_hinge_trial`'s slide candidates for a part (reference points [M, 3]) and its given poses [T, 4, 4]: a list
    of (hypothesis, "prismatic", unit axis [3], pivot 0 [3], poses [T, 4, 4]); -2 the chord of the poses without
    their turn, -3 the same along the part's principal axis nearest it, unless that is within ``min_deg`` of the
    chord (`slide_from_poses`). Empty when the poses do not move the part's centroid."""
    from fgjax.pipeline.articulation import slide_from_poses

    chord = slide_from_poses(points, poses)
    if chord is None:
        return []
    snapped = slide_from_poses(points, poses, snap=True)
    out = []
    for h, (axis, amounts) in ((-2, chord), (-3, snapped)):
        if h == -3 and abs(float(axis @ chord[0])) > np.cos(np.radians(min_deg)):
            continue
        pk = np.tile(np.eye(4, dtype=np.float32), (len(amounts), 1, 1))
        pk[:, :3, 3] = amounts[:, None] * axis
        out.append((h, "prismatic", axis, np.zeros(3), pk))
    return out


def _hinge_trial(run: LoadedRun, scene, order, ref: Gaussians, labels: np.ndarray, num_objects: int,
                 poses: np.ndarray, kinds, offsets, cfg: Stage2Config, objects, log=print) -> tuple[np.ndarray, dict]:
    """Each far hinge (``Stage2Config.hinge_trial``) tried against hinges along its part's own edges and against
    slides, by re-fits.

    For each object in ``objects`` [K] bool whose joint (``kinds`` [K]) is revolute with a `hinge_offset` ratio
    (``offsets`` [K]) over 2 and a largest turn of 5 degrees or more (`is_far_hinge`): candidates are the given
    poses, with ``hinge_trial_slide`` two slides (`slide_from_poses`: their chord, and along the part's principal
    axis nearest it where that is over 2 degrees off the chord), with ``hinge_trial_search_slides`` the same two
    slides with their amounts searched in the images (each frame from its slide's amount), and the
    ``hinge_trial_edges`` of the four `rect_hinges` of the part's alive members that the images score best, each
    hinge with its best amount in every frame (`search_articulations` on `ref`, the round's reference, raw
    parameters, on the frames where the given poses displace the part). A candidate whose poses are another's (to
    1e-6) takes that one's loss. The trial's labels are ``labels`` with the outlines relabelled
    by colour on `ref` (`_refine_by_colour`, with ``colour_radius`` > 0): with discovery's labels, whose lid takes
    in the rims of its box, the search turns the lid's true hinge only 25 of its 69 degrees, and 69 with these
    (docs/benchmarks.md, session 39). They serve the trial only; the labels returned by the round are unchanged.
    The scene is re-fitted from `ref` under each candidate (`refit_gaussians`, ``hinge_trial`` steps on the frames
    in which some candidate displaces the part, the same seed), and scored by the mean photometric loss of those
    frames rendered from its re-fit; `_trial_choice` picks by those scores (an edge must beat the given poses by
    ``hinge_trial_margin``; the better slide wins ties within it).

    Returns (poses [K, T, 4, 4], {object: {"candidates": [{"hypothesis", "kind", "axis", "pivot", "loss"}, ...]
    (the given poses as hypothesis -1, the slides as -2 and -3, the searched slides as -4 and -5, the edges as 0-3),
    "given_loss", "replaced", "kind" (the chosen joint's, None where kept), "axis", "offset" (None for a slide),
    "frames", "seconds"}}).
    """
    from fgjax.pipeline.articulation import displaced_frames, rect_hinges, search_articulations
    from fgjax.pipeline.phototrack import hinge_offset, is_far_hinge, largest_turn_deg

    poses = np.asarray(poses, np.float32).copy()
    alive = np.asarray(run.state.densify.alive, bool)
    m0 = np.asarray(ref.means, np.float64)
    out = {}
    tl = None  # the trial's labels: the outlines relabelled by colour on the round's reference
    for k in np.flatnonzero(np.asarray(objects, bool)):
        turn = largest_turn_deg(poses[k])
        if kinds[k] != "revolute" or not is_far_hinge(offsets[k], turn):
            continue
        if tl is None:
            tl = _refine_by_colour(labels, ref, alive, cfg, log)[0] if cfg.colour_radius > 0 else labels
        pts = m0[(tl == k) & alive]
        if len(pts) < 3:
            continue
        t0 = time.perf_counter()
        log(f"hinge trial: object {k + 1}'s hinge lies {offsets[k]:.1f} radii off it while it turns {turn:.1f} "
            f"degrees; trying hinges along its edges")
        slides = _trial_slides(pts, poses[k]) if cfg.hinge_trial_slide else []
        hyps = rect_hinges(pts)
        search_kinds, fitted_poses = ["none"] * num_objects, None
        if cfg.hinge_trial_search_slides and slides:  # the chord's slide as the fitted joint (each frame from its
            search_kinds[k] = "prismatic"  # own amount), the other slide as a hypothesis after the edges; the
            fitted_poses = {int(k): slides[0][4]}  # displaced frames and the edges' searches are the given poses'
            hyps += [("prismatic", ax, pv) for _, _, ax, pv, _ in slides[1:]]
        _, found = search_articulations(ref, alive, tl, num_objects, scene.images[order], scene.viewmats[order],
                                        scene.Ks[order], poses, kinds=search_kinds, fitted_poses=fitted_poses,
                                        objects=np.arange(num_objects) == k, keep=len(hyps) + 1,
                                        hypotheses={int(k): hyps}, replace=False, sh_degree=run.cfg.model.sh_degree,
                                        background=run.cfg.model.background, capacity=_render_capacity(run),
                                        tile_size=run.cfg.train.tile_size, log=log)
        if found[k] is None:
            continue
        cands = [(-1, "revolute", None, None, poses[k])] + slides  # (hypothesis, kind, axis, pivot, poses [T, 4, 4])
        shift = 1 if found[k]["fitted_hypothesis"] else 0  # the search's index of the first edge
        edges = sorted((h - shift, c) for h, c in found[k]["candidates"].items() if 0 <= h - shift < 4)
        for h, (kind, ax, pv, pk) in found[k]["candidates"].items():  # the searched slides: -4 the chord's, -5
            if kind == "prismatic":
                cands.append((-4 if h == 0 else -5, kind, ax, pv, pk))
        n_f = max(int(found[k]["frames"]), 1)
        score = {h: found[k]["scores"][h + shift] / n_f for h, _ in edges}
        kept = sorted(score, key=lambda h: score[h])[:max(int(cfg.hinge_trial_edges), 0)]
        cands += [(h, "revolute", ax, pv, pk) for h, (_, ax, pv, pk) in edges if h in kept]
        log(f"hinge trial: object {k + 1}: the images of the round's scene score the edges "
            f"{[round(score[h], 5) for h, _ in edges]} a frame"
            + (f", the given poses {found[k]['score_given'] / n_f:.5f}" if not shift else "")
            + (f"; re-fitting edges {sorted(kept)}" if len(kept) < len(edges) else ""))
        disp = np.zeros(poses.shape[1], bool)
        tol = 1e-3 * float(np.max(np.percentile(pts, 95, 0) - np.percentile(pts, 5, 0)))  # as the search's
        for *_, pk in cands:
            disp |= displaced_frames(pts, pk, tol)
        frames = np.flatnonzero(disp)
        if len(frames) == 0:
            continue
        losses = []
        for n, (h, kind, ax, pv, pk) in enumerate(cands):
            same = next((m for m in range(n) if np.allclose(cands[m][4], pk, rtol=0.0, atol=1e-6)), None)
            if same is not None:  # e.g. a slide whose search kept every amount: the same re-fit
                losses.append(losses[same])
                log(f"hinge trial: object {k + 1}: {_trial_name(h, ax)}: the poses of the "
                    f"{_trial_name(cands[same][0], cands[same][2])}; loss {losses[-1]:.5f}")
                continue
            trial = poses.copy()
            trial[k] = pk
            gs, _ = refit_gaussians(run, scene, order, tl, trial, int(cfg.hinge_trial), seed=cfg.seed, init=ref,
                                    lr_scale=cfg.refit_lr_scale, frames=frames, log=lambda *a: None)
            losses.append(float(np.mean(_posed_losses(run, scene, order, gs, tl, trial, frames))))
            log(f"hinge trial: object {k + 1}: {_trial_name(h, ax)}: loss {losses[-1]:.5f} after a "
                f"{cfg.hinge_trial}-step re-fit on its {len(frames)} displaced frames")
        best = _trial_choice([c[0] for c in cands], losses, cfg.hinge_trial_margin)
        replaced = best > 0
        h, kind, ax, pv, pk = cands[best]
        rec = {"candidates": [{"hypothesis": int(c[0]), "kind": c[1],
                               "axis": None if c[2] is None else [float(x) for x in c[2]],
                               "pivot": None if c[3] is None else [float(x) for x in c[3]], "loss": l}
                              for c, l in zip(cands, losses)],
               "given_loss": losses[0], "replaced": bool(replaced), "kind": kind if replaced else None,
               "frames": int(len(frames)), "axis": None, "offset": None, "seconds": 0.0}
        if replaced:
            poses[k] = pk
            rec["axis"] = [float(x) for x in ax]
            rec["offset"] = hinge_offset(pts, ax, pv)[1] if kind == "revolute" else None
        rec["seconds"] = time.perf_counter() - t0
        out[int(k)] = rec
        where = "" if rec["offset"] is None else f", {rec['offset']:.1f} radii off its centre"
        log(f"hinge trial: object {k + 1}: "
            + (f"replaced by the {_trial_name(h, ax)}{where}, loss {losses[best]:.5f} against the given poses' "
               f"{losses[0]:.5f}" if replaced else
               f"kept (the given poses' {losses[0]:.5f}, the best candidate's {min(losses):.5f})")
            + f" ({rec['seconds']:.1f} s)")
    return poses, out


def _posed_geometry(base, labels: np.ndarray, poses: np.ndarray):
    """The reference geometry `base` (means, raw quats, log-scales) with each object moved by its pose, per
    time: (means [T, N, 3], raw quats [T, N, 4], log-scales [T, N, 3])."""
    from fgjax.pipeline.track import transform_gaussians

    m0, q0, ls0 = base
    ms, qs = [], []
    for j in range(poses.shape[1]):
        m, q = transform_gaussians(jnp.asarray(m0), jnp.asarray(q0), jnp.asarray(labels),
                                   jnp.asarray(poses[:, j], jnp.float32))
        ms.append(np.asarray(m))
        qs.append(np.asarray(q))
    return np.stack(ms), np.stack(qs), np.repeat(np.asarray(ls0)[None], poses.shape[1], axis=0)


def _render_capacity(run: LoadedRun) -> int | None:
    """Tile capacity for renders of moved or controlled geometry: 1.5 x the stage-1 run's (None: the
    rasterizer's default); moved Gaussians can crowd tiles more than stage 1 ever did."""
    cap = int(run.meta.get("capacity") or 0) or None
    return None if cap is None else int(cap * 1.5)


def _fill_hulls(labels: np.ndarray, gs: Gaussians, alive, min_opacity: float, max_growth: float = np.inf,
                log=print) -> np.ndarray:
    """`Stage2Config.hull_fill`: `fgjax.cluster.fill_hulls` on the reference scene ``gs`` (its centres, and
    its members with opacity >= ``min_opacity`` as each hull's core); labels [N] -> labels [N]. Logs how many
    joined each cluster."""
    alive, core = _opaque(gs, alive, min_opacity)
    new = cluster.fill_hulls(np.asarray(gs.means, np.float64), labels, core, alive, max_growth=max_growth)
    log(f"stage 2: {_joined(labels, new)} static Gaussians (objects 1, 2, ...) inside the hulls of the clusters' opaque "
        f"members joined them (a hull holding more than {max_growth:g}x its cluster's size is not filled)")
    return new


def _drop_isolated(labels: np.ndarray, gs: Gaussians, alive, factor: float, log=print) -> tuple[np.ndarray, list[int]]:
    """`Stage2Config.isolated_factor`: `fgjax.cluster.drop_isolated` on the reference scene ``gs`` (centres of the
    alive Gaussians). Returns (labels [N], how many left each cluster [K]) and logs the counts."""
    new = cluster.drop_isolated(np.asarray(gs.means, np.float64), labels, factor, np.asarray(alive, bool))
    left = [int(np.sum((labels == k) & (new != k))) for k in range(int(labels.max(initial=-1)) + 1)]
    log(f"stage 2: {left} members (objects 1, 2, ...) farther than {factor:g}x their cluster's median spacing from "
        f"every other member made static")
    return new, left


_COLOUR_MIN_OPACITY = 0.1  # `_refine_by_colour`: fainter Gaussians' colours do not count (nor change label)


def _refine_by_colour(labels: np.ndarray, gs: Gaussians, alive, cfg: Stage2Config,
                      log=print) -> tuple[np.ndarray, list]:
    """`Stage2Config.colour_radius`: `fgjax.cluster.refine_by_colour` on the reference scene ``gs`` (centres and DC
    colours of the alive Gaussians with opacity >= 0.1). Returns (labels [N], the per-cluster report) and logs it."""
    from fgjax.gaussians import SH_C0

    _, usable = _opaque(gs, alive, _COLOUR_MIN_OPACITY)
    rgb = np.asarray(gs.sh, np.float64)[:, 0, :] * SH_C0 + 0.5  # [N, 3]
    new, report = cluster.refine_by_colour(np.asarray(gs.means, np.float64), np.nan_to_num(rgb), labels, usable,
                                           radius=cfg.colour_radius, n_components=cfg.colour_components,
                                           min_separation=cfg.colour_separation, seed=cfg.seed)
    log(f"stage 2: outlines by colour (objects 1, 2, ...): joined {[r['joined'] for r in report]}, left "
        f"{[r['left'] for r in report]}, colours apart by "
        f"{[None if r['separation'] is None else round(r['separation'], 2) for r in report]}"
        + "".join(f"; object {k + 1} stopped: {r['skipped']}" for k, r in enumerate(report) if r["skipped"]))
    return new, report


def _settle(run: LoadedRun, scene, order, ref: Gaussians, labels: np.ndarray, poses: np.ndarray, moving,
            log=print) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """`Stage2Config.settle_rest`: `fgjax.pipeline.phototrack.settle_at_rest` on the scene ``ref`` (stage 1's)
    with ``labels`` [N], the training frames in time order (`order`)."""
    from fgjax.pipeline.phototrack import settle_at_rest

    return settle_at_rest(ref, run.state.densify.alive, labels, int(poses.shape[0]), scene.images[order],
                          scene.viewmats[order], scene.Ks[order], poses, moving, sh_degree=run.cfg.model.sh_degree,
                          background=run.cfg.model.background, capacity=_render_capacity(run),
                          tile_size=run.cfg.train.tile_size, log=log)


def _opaque(gs: Gaussians, alive, min_opacity: float) -> tuple[np.ndarray, np.ndarray]:
    """(alive [N] bool, core [N] bool: alive with opacity >= ``min_opacity``) of ``gs``: the fills' core (labels
    select the members). The sigmoid is scipy's expit, without exp's overflow at pruned logits."""
    from scipy.special import expit

    alive = np.asarray(alive, bool)
    return alive, alive & (expit(np.asarray(gs.opacity_logits, np.float64)) >= min_opacity)


def _joined(before: np.ndarray, after: np.ndarray) -> list[int]:
    """How many Gaussians joined each cluster from `before` [N] to `after` [N] labels: [K]."""
    return [int(np.sum((after == k) & (before != k))) for k in range(int(after.max(initial=-1)) + 1)]


def _fill_hinges(labels: np.ndarray, gs: Gaussians, alive, poses: np.ndarray, cfg: Stage2Config,
                 log=print) -> tuple[np.ndarray, list]:
    """`Stage2Config.hinge_fill`: `fgjax.cluster.fill_hinges` on the reference scene ``gs`` (centres; the core:
    alive members with opacity >= ``cfg.hull_opacity``) with the hinges of ``poses`` [K, T, 4, 4]
    (`fgjax.cluster.hinge_axes`). Returns (labels [N], hinges: per cluster {"axis", "pivot", "angle_deg"} or
    None where it does not turn by ``cfg.hinge_min_deg``). Logs the hinges and how many joined."""
    alive, core = _opaque(gs, alive, cfg.hull_opacity)
    axes, pivots, angles = cluster.hinge_axes(poses, min_deg=cfg.hinge_min_deg)
    new = cluster.fill_hinges(np.asarray(gs.means, np.float64), labels, core, alive, axes, pivots,
                              radius=cfg.hinge_radius, reach=cfg.hinge_reach, max_growth=cfg.hull_max_growth)
    hinges = [None if not np.all(np.isfinite(a)) else
              {"axis": [float(v) for v in a], "pivot": [float(v) for v in p], "angle_deg": float(g)}
              for a, p, g in zip(axes, pivots, angles)]
    turning = [k + 1 for k, h in enumerate(hinges) if h is not None]
    log(f"stage 2: {_joined(labels, new)} static Gaussians (objects 1, 2, ...) along the hinges of the objects that "
        f"turn by >= {cfg.hinge_min_deg:g} degrees {turning} joined them")
    return new, hinges


def _cap_opacity(gs: Gaussians, mask, opacity: float) -> tuple[Gaussians, np.ndarray]:
    """``gs`` with the opacity of the Gaussians in ``mask`` [N] capped at ``opacity`` in (0, 1); (scene, [N] bool:
    those whose opacity was above it)."""
    cap = float(np.log(opacity) - np.log1p(-opacity))  # logit
    o = np.asarray(gs.opacity_logits)  # [N]
    faded = np.asarray(mask, bool) & (o > cap)
    return Gaussians(gs.means, gs.log_scales, gs.quats, np.where(faded, np.asarray(cap, o.dtype), o), gs.sh), faded


def _fade_dropped(gs: Gaussians, before: np.ndarray, after: np.ndarray, cfg: Stage2Config, what: str,
                  log=print) -> Gaussians:
    """With ``cfg.ghost_radius`` > 0, as the ghosts: the members of ``before`` [N] that are static in ``after`` [N]
    start the last re-fit with their opacity capped at ``cfg.ghost_opacity`` (the re-fit brings back those the
    static frames need); logs how many, "``what`` faded ..."."""
    if cfg.ghost_radius <= 0:
        return gs
    gs, faded = _cap_opacity(gs, (before >= 0) & (after < 0), cfg.ghost_opacity)
    log(f"stage 2: {int(faded.sum())} {what} faded to opacity {cfg.ghost_opacity:g} before the re-fit")
    return gs


_PRUNED_OPACITY = 1e-6  # the opacity `_prune_seen_through` sets


class TileOverflow(ValueError):
    """A render overflowed its tile capacity, so the per-Gaussian weights it gave would be incomplete."""


def seen_through(gs: Gaussians, alive, labels: np.ndarray, poses: np.ndarray, viewmats, Ks, width: int, height: int,
                 *, capacity: int | None = None, tile_size: int = 16) -> np.ndarray:
    """Per Gaussian, the fraction of the weight it paints over the frames (sum over pixels p of T_p alpha_p, as in
    `fgjax.render.api.gaussian_weights`) that falls where the parts' members cover the pixel: [N] in [0, 1] (0 for
    a Gaussian that paints nothing, or is dead).

    Frame i renders the reference scene ``gs`` (raw parameters) with each cluster's members (``labels`` [N], -1
    static) moved by its pose ``poses[:, i]`` ([K, T, 4, 4], `fgjax.pipeline.track.transform_gaussians`) from the
    camera ``viewmats[i]`` ([T, 4, 4] OpenCV world-to-camera) with ``Ks[i]`` ([T, 3, 3]). The members' coverage
    of a pixel is their composited share of it (an image of 1 for members and 0 for the rest, no background),
    in [0, 1]. A static Gaussian whose weight lies mostly there is seen through a part (or mixed into its edge)
    in the training frames: it lends the part its colour where the part's own Gaussians are sparse, and shows
    when a held-out state moves the part away.

    Raises ValueError on mismatched shapes, and `TileOverflow` (a ValueError) when a frame's render overflows the
    tile ``capacity`` (its weights would be incomplete)."""
    from fgjax.pipeline.track import transform_gaussians
    from fgjax.render.api import gaussian_weights, rasterization

    n = int(np.shape(gs.means)[0])
    k = int(np.asarray(labels).max(initial=-1)) + 1
    if np.shape(labels) != (n,) or np.shape(alive) != (n,):
        raise ValueError(f"seen_through: labels and alive must have shape [{n}], got {list(np.shape(labels))} and "
                         f"{list(np.shape(alive))}")
    t = int(np.shape(poses)[1]) if np.ndim(poses) == 4 else -1
    if np.ndim(poses) != 4 or np.shape(poses)[0] < k or np.shape(poses)[2:] != (4, 4) \
            or np.shape(viewmats) != (t, 4, 4) or np.shape(Ks) != (t, 3, 3):
        raise ValueError(f"seen_through: poses must be [K >= {k}, T, 4, 4] with viewmats [T, 4, 4] and Ks [T, 3, 3], "
                         f"got {list(np.shape(poses))}, {list(np.shape(viewmats))} and {list(np.shape(Ks))}")
    alive_j = jnp.asarray(np.asarray(alive, bool))
    lab = jnp.asarray(np.asarray(labels, np.int32))
    member = (lab >= 0).astype(jnp.float32)[:, None]  # [N, 1]
    q0 = jnp.asarray(gs.quats)
    _, s, o = activate(jax.tree_util.tree_map(jnp.asarray, gs), alive_j)
    poses_j = jnp.asarray(poses, jnp.float32)  # [K, T, 4, 4]

    @jax.jit
    def frame(pose, vm, K):  # ([N] weight under the members' coverage, [N] weight)
        m, q = transform_gaussians(jnp.asarray(gs.means), q0, lab, pose)
        cov, _, info = rasterization(m, q, s, o, member, vm, K, int(width), int(height), capacity=capacity,
                                     tile_size=tile_size, render_depth=False)
        kw = dict(capacity=capacity, tile_size=tile_size)
        return (gaussian_weights(m, q, s, o, vm, K, width, height, jnp.clip(cov[..., 0], 0.0, 1.0), **kw),
                gaussian_weights(m, q, s, o, vm, K, width, height, jnp.ones((int(height), int(width))), **kw),
                info["overflow"])

    inside = np.zeros(len(lab))
    total = np.zeros(len(lab))
    for i in range(int(poses_j.shape[1])):
        a, b, over = frame(poses_j[:, i], jnp.asarray(viewmats[i], jnp.float32), jnp.asarray(Ks[i], jnp.float32))
        if bool(over):
            raise TileOverflow(f"seen_through: frame {i}'s render overflowed the tile capacity ({capacity})")
        inside += np.asarray(a, np.float64)
        total += np.asarray(b, np.float64)
    ratio = np.where(total > 0, inside / np.maximum(total, 1e-30), 0.0)
    return np.clip(np.where(np.asarray(alive, bool), ratio, 0.0), 0.0, 1.0)


def _prune_seen_through(gs: Gaussians, labels: np.ndarray, poses: np.ndarray, run: LoadedRun, scene, order,
                        max_ratio: float, log=print) -> tuple[Gaussians, int]:
    """`Stage2Config.through_prune`: the alive static Gaussians of ``gs`` whose `seen_through` share over the
    training frames (time order ``order``, the parts at ``poses``) exceeds ``max_ratio`` get opacity ~0
    (`_PRUNED_OPACITY`, which no re-fit brings back: the sigmoid's gradient vanishes there). Returns (scene, how
    many)."""
    t0 = time.perf_counter()
    try:
        ratio = seen_through(gs, run.state.densify.alive, labels, poses, scene.viewmats[order], scene.Ks[order],
                             scene.width, scene.height, capacity=_render_capacity(run), tile_size=run.cfg.train.tile_size)
    except TileOverflow as e:  # prune nothing rather than on partial weights
        log(f"stage 2: no static Gaussians pruned as seen through the parts: {e}")
        return gs, 0
    sel = (np.asarray(labels) < 0) & np.asarray(run.state.densify.alive, bool) & (ratio > max_ratio)
    gs, pruned = _cap_opacity(gs, sel, _PRUNED_OPACITY)
    log(f"stage 2: {int(pruned.sum())} static Gaussians seen through the parts (more than {max_ratio:g} of their "
        f"weight where the members cover the pixel) pruned ({time.perf_counter() - t0:.1f} s)")
    return gs, int(pruned.sum())


def _fade_ghosts(gs: Gaussians, labels: np.ndarray, poses: np.ndarray, alive, cfg: Stage2Config,
                 log=print) -> Gaussians:
    """`Stage2Config.ghost_radius`: the opacity of alive static Gaussians of ``gs`` near the volume the parts
    sweep under ``poses`` [K, T, 4, 4] (`fgjax.cluster.near_swept`) capped at ``cfg.ghost_opacity``."""
    near = cluster.near_swept(np.asarray(gs.means, np.float64), labels, poses, cfg.ghost_radius) & np.asarray(alive, bool)
    gs, faded = _cap_opacity(gs, near, cfg.ghost_opacity)
    log(f"stage 2: {int(faded.sum())} static Gaussians near the parts' swept volume faded to opacity "
        f"{cfg.ghost_opacity:g} before the re-fit ({int(near.sum())} within {cfg.ghost_radius:g})")
    return gs


def _reference_scene(run: LoadedRun, t: float) -> Gaussians:
    """Stage 1's Gaussians deformed to time `t` (raw parameters, with their opacities and colours): the
    reference scene that the tracked poses move and the re-fit starts from."""
    m, q, ls = run.deformed(t)
    g = run.state.params["gaussians"]
    return Gaussians(m, ls, q, g.opacity_logits, g.sh)


def _guarded_update(loss_fn, opt, p, st, i):
    """(params, opt_state, loss, skipped): one `opt` step on ``loss_fn(params, i) -> (loss, overflow)``; a step
    whose render overflowed the tile capacity or whose loss is not finite leaves params and state unchanged."""
    (loss, over), gr = jax.value_and_grad(loss_fn, has_aux=True)(p, i)
    up, st2 = opt.update(gr, st, p)
    new = optax.apply_updates(p, up)
    bad = over | ~jnp.isfinite(loss)
    keep = lambda a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(bad, y, x), a, b)
    return keep(new, p), keep(st2, st), loss, bad


def _guarded_step(loss_fn, opt):
    """jitted (params, opt_state, i) -> `_guarded_update`."""
    return jax.jit(functools.partial(_guarded_update, loss_fn, opt))


@functools.lru_cache(maxsize=16)
def _refit_optimizer(steps: int, scene_extent: float, num_sh_coeffs: int, lr_scale: float):
    """`refit_gaussians`' optimiser: stage 1's groups and rates (decaying over ``steps``) times ``lr_scale``.
    Memoised (it is a pure function of its arguments), so that the re-fits of one configuration, e.g. a hinge
    trial's candidates, share one compiled `_posed_refit_step`."""
    from fgjax.train.optim import OptimSpec, make_optimizer

    # Adam's update is linear in its learning rate: scaling the update scales every group's rate and schedule
    return optax.chain(make_optimizer(OptimSpec(steps=steps, scene_extent=scene_extent), num_sh_coeffs),
                       optax.scale(lr_scale))


@functools.partial(jax.jit, static_argnames=("opt", "sh_degree", "width", "height", "capacity", "tile_size", "lam"))
def _posed_refit_step(p, st, i, labels, poses, viewmats, Ks, images, background, alive, *, opt, **kw):
    """`_guarded_update` of `_posed_frame_loss` on training frame i (time order) with each object moved by its
    pose (``poses`` [K, T, 4, 4]). Everything but the optimiser and the render's settings is an argument, so one
    compiled step serves every re-fit of a shape."""

    def loss_fn(p_, i_):
        return _posed_frame_loss(p_["gaussians"], alive, labels, poses[:, i_], viewmats[i_], Ks[i_], images[i_],
                                 background, **kw)

    return _guarded_update(loss_fn, opt, p, st, i)


def refit_gaussians(run: LoadedRun, scene, order, labels: np.ndarray, poses: np.ndarray, steps: int, *, seed: int = 0,
                    relabel_steps: int = 0, relabel_radius: float = 0.1, relabel_lr: float = 0.05,
                    init: Gaussians | None = None, lr_scale: float = 1.0, frames=None,
                    log=print) -> tuple[Gaussians, np.ndarray]:
    """Re-fit the reference Gaussians (stage 1 at t0, or ``init``: an earlier re-fit's) to the training
    images under the tracked motion.

    Stage 1 never moved the parts (docs/benchmarks.md), so their Gaussians are a blur of their states that
    the deformation field's time dependence hides frame by frame; moved rigidly by the tracked poses they
    carry that blur into every state (with the true poses and labels, held-out states reach only ~25.6 dB).
    Here every Gaussian's parameters (centres, scales, rotations, opacities, SH) are optimised with the
    photometric loss of stage 1 on frame i rendered with each object moved by its pose T_k(t_i)
    (`track.transform_gaussians`; static Gaussians stay), with stage 1's optimiser groups and
    learning rates (decaying over `steps`), all times ``lr_scale``. No densification. A step whose render
    overflows the tile capacity or whose loss is not finite is skipped.

    Relabelling (the first ``relabel_steps`` of the steps): discovery labels a part by where its residual
    flow is large, so a door's hinge side is missed and static surfaces next to a part can join it. Each
    candidate, a Gaussian within ``relabel_radius`` (scene units, at t0) of a cluster's members, is then
    rendered twice: moved with its nearest cluster k_g with opacity sigma(o) pi_g, and static with
    opacity sigma(o) (1 - pi_g), pi_g = sigmoid(l_g) (l_g starts at +2 for members, -2 for the others,
    and is trained with Adam at ``relabel_lr``). Where k_g's pose differs from the reference the two copies
    part, and the photometric loss keeps the one that is where the image shows it. Afterwards a candidate
    joins k_g when pi_g > 0.5 and is static otherwise; the remaining steps re-fit with those labels.
    Those steps draw frames in which some object is away from its reference pose (all frames when none).

    ``frames``: the training frames (time order) the steps draw from; None: all.

    Returns:
        (`Gaussians` (numpy leaves) of the reference scene, labels [N] after relabelling (the input labels
        when ``relabel_steps`` is 0)).
    """
    from fgjax.pipeline.stage1 import render_params, scene_extent
    from fgjax.train.losses import photometric_loss

    t_start = time.perf_counter()
    ref = _reference_scene(run, float(scene.times[order[0]])) if init is None else init
    params = {"gaussians": jax.tree_util.tree_map(jnp.asarray, ref)}
    alive = run.state.densify.alive
    pj = jnp.asarray(poses, jnp.float32)  # [K, T, 4, 4]
    images = jnp.asarray(scene.images[order])
    vms = jnp.asarray(scene.viewmats[order], jnp.float32)
    Ks = jnp.asarray(scene.Ks[order], jnp.float32)
    bg = jnp.asarray(run.cfg.model.background, jnp.float32)
    cap = _render_capacity(run)
    lam = float(run.cfg.train.lambda_dssim)
    opt = _refit_optimizer(max(int(steps), 1), float(scene_extent(scene.viewmats)), int(ref.sh.shape[1]),
                           float(lr_scale))

    def photo(gs: Gaussians, alive_, i):
        """(photometric loss, overflow) of training frame i (time order) rendered from `gs` as given."""
        img, _, info, _ = render_params({"gaussians": gs}, alive_, vms[i], Ks[i], 0.0, spec=None,
                                        sh_degree=run.cfg.model.sh_degree, width=scene.width, height=scene.height,
                                        background=bg, capacity=cap, tile_size=run.cfg.train.tile_size)
        return photometric_loss(img, images[i], lam), info["overflow"]

    st = opt.init(params)
    rng = np.random.default_rng(seed + 2)
    losses, n_bad = [], 0
    n_rel = min(int(relabel_steps), int(steps))
    labels = np.asarray(labels, np.int64)
    if n_rel > 0 and labels.max(initial=-1) >= 0:
        params, st, labels, info = _relabel(params, st, opt, labels, np.asarray(poses), photo, alive, n_rel,
                                            relabel_radius, relabel_lr, rng)
        losses += info.pop("losses")
        n_bad += info.pop("skipped")
        log(f"stage 2: relabelled by motion in {n_rel} steps: {info}")
    else:
        n_rel = 0
    lab, alive_j = jnp.asarray(labels), jnp.asarray(alive)
    kw = dict(opt=opt, sh_degree=int(run.cfg.model.sh_degree), width=int(scene.width), height=int(scene.height),
              capacity=cap, tile_size=int(run.cfg.train.tile_size), lam=lam)
    step = functools.partial(_posed_refit_step, **kw)
    pool = np.arange(len(order)) if frames is None else np.asarray(frames, np.int64).reshape(-1)
    if len(pool) == 0 or pool.min() < 0 or pool.max() >= len(order):
        raise ValueError(f"refit_gaussians: frames must be indices into the {len(order)} training frames, got "
                         f"{pool.tolist()}")
    for _ in range(int(steps) - n_rel):
        params, st, loss, bad = step(params, st, jnp.asarray(pool[rng.integers(len(pool))], jnp.int32), lab, pj, vms,
                                     Ks, images, bg, alive_j)
        losses.append(loss)
        n_bad += int(bad)
    if losses:
        losses = [float(x) for x in losses]
        log(f"stage 2: re-fitted the Gaussians under the tracked motion, {steps} steps, loss "
            f"{np.mean(losses[:10]):.4f} -> {np.mean(losses[-10:]):.4f} ({n_bad} skipped, "
            f"{time.perf_counter() - t_start:.1f} s)")
    return jax.tree_util.tree_map(np.asarray, params["gaussians"]), labels


def _paired(a: optax.GradientTransformation, b: optax.GradientTransformation) -> optax.GradientTransformation:
    """`a` on the first element of a (params, params) pair, `b` on the second."""

    def init(p):
        return a.init(p[0]), b.init(p[1])

    def update(u, s, p=None):
        ua, sa = a.update(u[0], s[0], None if p is None else p[0])
        ub, sb = b.update(u[1], s[1], None if p is None else p[1])
        return (ua, ub), (sa, sb)

    return optax.GradientTransformation(init, update)


def _relabel(params, st, opt, labels, poses, photo, alive, steps, radius, lr, rng):
    """The relabelling phase of `refit_gaussians` (``photo(gaussians, alive, i)``: its render and loss of
    frame i): (params, opt state, new labels [N], info)."""
    from fgjax.pipeline.phototrack import mixed_copies, relabel_candidates, soft_members
    from fgjax.pipeline.track import transform_gaussians

    g0 = params["gaussians"]
    cand, k_c = relabel_candidates(np.asarray(g0.means), labels, np.asarray(alive), float(radius))
    lab_m, cj, alive2, logits0 = soft_members(labels, cand, k_c, alive)  # the first copy moves with k_c
    pj = jnp.asarray(poses, jnp.float32)

    def loss_mixed(p_lg, i):
        p, lg = p_lg
        g = p["gaussians"]
        m, q = transform_gaussians(g.means, g.quats, lab_m, pj[:, i])
        both = mixed_copies(g, m, q, cj, lg)
        return photo(both, alive2, i)

    opt_l = optax.adam(lr)
    step = _guarded_step(loss_mixed, _paired(opt, opt_l))
    # frames where some object is away from its reference pose: only there do the two copies part
    away = np.any(np.abs(poses - np.eye(4)).reshape(poses.shape[0], poses.shape[1], -1).max(-1) > 1e-4, axis=0)
    frames = np.flatnonzero(away) if away.any() else np.arange(poses.shape[1])
    p_lg, st_pair = (params, logits0), (st, opt_l.init(logits0))
    losses, n_bad = [], 0
    for _ in range(int(steps)):
        p_lg, st_pair, loss, bad = step(p_lg, st_pair, jnp.asarray(rng.choice(frames), jnp.int32))
        losses.append(loss)
        n_bad += int(bad)
    (params, lg), st = p_lg, st_pair[0]
    pi = np.asarray(jax.nn.sigmoid(lg))
    new = labels.copy()
    new[cand] = np.where(pi > 0.5, k_c, -1)
    for k in range(int(labels.max()) + 1):  # a cluster is never emptied: it keeps its members then
        if not np.any(new == k):
            new[labels == k] = k
    info = {"candidates": int(len(cand)), "joined": int(np.sum((labels[cand] < 0) & (new[cand] >= 0))),
            "left": int(np.sum((labels[cand] >= 0) & (new[cand] < 0))), "frames": int(len(frames)),
            "losses": losses, "skipped": n_bad}
    return params, st, new, info


def _train_control(run: LoadedRun, scene, order, labels: np.ndarray, traj: np.ndarray, cfg: Stage2Config,
                   centres_q_s, flows=None, log=print, refit: Gaussians | None = None) -> tuple[ControlNet, dict[str, Any]]:
    """Fit Θ: distillation from the deformation field, then the photometric loss plus beta L_uGS (module
    docstring). `flows` [T-1, H, W, 2]: observed flow between consecutive frames in time order (None: no
    flow term)."""
    from fgjax.train.losses import photometric_loss

    k = traj.shape[0]
    canonical = run.state.params["gaussians"].means  # the control network's input X
    params = _with_refit(run.state.params, refit)  # whose opacities and colours the renders use
    sel = np.flatnonzero(labels >= 0)
    ext = float(np.max(np.abs(np.asarray(canonical)[sel] - np.asarray(canonical)[sel].mean(0)))) if len(sel) else 1.0
    v_all = traj - traj[:, :1]  # [K, T, 3]
    v_scale = float(max(np.max(np.linalg.norm(v_all, axis=-1), initial=0.0), 1e-3))
    hp = _control_hparams(cfg, x_scale=max(2.0 * ext, 1e-3), v_scale=v_scale)
    control = control_init(jax.random.key(cfg.seed), **hp)
    stats: dict[str, Any] = {"control": hp}
    if len(sel) == 0 or k == 0:
        return control, stats
    means_t, quats_t, ls_t = centres_q_s  # [T, N, ...] in time order
    lab_sel = jnp.asarray(labels[sel])
    x_sel = canonical[sel]
    tgt = (jnp.asarray(means_t[:, sel] - means_t[:1, sel]), jnp.asarray(quats_t[:, sel] - quats_t[:1, sel]),
           jnp.asarray(ls_t[:, sel] - ls_t[:1, sel]))  # [T, M, ...]
    v_t = jnp.asarray(v_all.transpose(1, 0, 2), jnp.float32)  # [T, K, 3]
    opt = optax.adam(cfg.lr)

    def offsets(ctrl, vecs):  # vecs [K, 3] -> offsets of the selected Gaussians
        z = jnp.zeros((len(sel), 3), jnp.float32)
        v = vecs[lab_sel]
        a = control_apply(ctrl, v, x_sel)
        b = control_apply(ctrl, z, x_sel)
        return tuple(u - w for u, w in zip(a, b, strict=True))

    def distill_loss(ctrl, ti):  # ti [B]: a minibatch of training times
        d = jax.vmap(lambda vv: offsets(ctrl, vv))(v_t[ti])
        scale2 = v_scale ** 2
        return (jnp.mean(jnp.sum((d[0] - tgt[0][ti]) ** 2, -1)) / scale2
                + jnp.mean(jnp.sum((d[1] - tgt[1][ti]) ** 2, -1)) + jnp.mean(jnp.sum((d[2] - tgt[2][ti]) ** 2, -1)))

    @jax.jit
    def distill_step(ctrl, st, ti):
        loss, gr = jax.value_and_grad(distill_loss)(ctrl, ti)
        up, st = opt.update(gr, st, ctrl)
        return optax.apply_updates(ctrl, up), st, loss

    t0 = time.perf_counter()
    st = opt.init(control)
    loss = jnp.nan
    first = None
    n_t = int(v_t.shape[0])
    bsz = min(cfg.distill_batch, n_t)
    rng_d = np.random.default_rng(cfg.seed + 1)
    for i in range(cfg.distill_steps):
        ti = jnp.asarray(rng_d.choice(n_t, size=bsz, replace=False), jnp.int32)
        control, st, loss = distill_step(control, st, ti)
        if i == 0:
            first = float(loss)
    stats["distill"] = {"steps": cfg.distill_steps, "loss_first": first, "loss_last": float(loss),
                        "time_s": time.perf_counter() - t0}
    log(f"stage 2: distillation {cfg.distill_steps} steps, loss "
        f"{'-' if first is None else format(first, '.3g')} -> {float(loss):.3g} "
        f"({time.perf_counter() - t0:.1f} s)")
    if cfg.photo_steps <= 0:
        return control, stats
    # photometric fine-tuning of Θ only
    from fgjax.pipeline.stage1 import render_params

    base = (jnp.asarray(means_t[0]), jnp.asarray(quats_t[0]), jnp.asarray(ls_t[0]))
    labels_j = jnp.asarray(labels)
    bg = jnp.asarray(run.cfg.model.background, jnp.float32)
    cap = _render_capacity(run)
    images = jnp.asarray(scene.images[order])
    vms = jnp.asarray(scene.viewmats[order], jnp.float32)
    Ks = jnp.asarray(scene.Ks[order], jnp.float32)
    lam = float(run.cfg.train.lambda_dssim)
    opt2 = optax.adam(cfg.lr * 0.25)

    beta = float(cfg.flow_weight) if flows is not None and len(order) > 1 else 0.0
    if beta > 0:
        flows_j = jnp.asarray(np.asarray(flows, np.float32))  # [T-1, H, W, 2]: order[j] -> order[j + 1]
    alive = run.state.densify.alive

    def photo_loss(ctrl, i):
        geo = controlled_gaussians(ctrl, base, canonical, labels_j, v_t[i])
        p = _with_geometry(params, *geo)
        img, _, info, _ = render_params(p, alive, vms[i], Ks[i], 0.0, spec=None,
                                        sh_degree=run.cfg.model.sh_degree, width=scene.width, height=scene.height,
                                        background=bg, capacity=cap, tile_size=run.cfg.train.tile_size)
        loss, over = photometric_loss(img, images[i], lam), info["overflow"]
        if beta > 0:  # L_uGS of the pair (i - 1, i) in time order: the controlled scene at both vectors
            from fgjax.flow import gaussian_flow_loss

            j = jnp.maximum(i - 1, 0)
            geo0 = controlled_gaussians(ctrl, base, canonical, labels_j, v_t[j])
            q0, s0, o0 = activate(_with_geometry(params, *geo0)["gaussians"], alive)
            lf, of = gaussian_flow_loss(geo0[0], q0, s0, o0, geo[0], vms[j], vms[i], Ks[j], flows_j[j],
                                        scene.width, scene.height, capacity=cap,
                                        threshold=cfg.flow_threshold if cfg.flow_threshold > 0 else None,
                                        tile_size=run.cfg.train.tile_size)
            loss = loss + beta * jnp.where(i > 0, lf, 0.0)
            over = over | of
        return loss, over

    photo_step = _guarded_step(photo_loss, opt2)

    t1 = time.perf_counter()
    st = opt2.init(control)
    rng = np.random.default_rng(cfg.seed)
    losses, n_bad = [], 0
    for _ in range(cfg.photo_steps):
        control, st, loss, bad = photo_step(control, st, jnp.asarray(rng.integers(len(order)), jnp.int32))
        losses.append(loss)
        n_bad += int(bad)
    losses = [float(x) for x in losses]
    stats["photometric"] = {"steps": cfg.photo_steps, "loss_first": losses[0], "loss_last_10": float(np.mean(losses[-10:])),
                            "skipped_steps": n_bad, "time_s": time.perf_counter() - t1, "flow_weight": beta}
    log(f"stage 2: photometric {cfg.photo_steps} steps, loss {losses[0]:.4f} -> {np.mean(losses[-10:]):.4f} "
        f"({n_bad} skipped, {time.perf_counter() - t1:.1f} s)")
    return control, stats


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


def select_objects(canonical: np.ndarray, disc, cfg: Stage2Config, candidates: np.ndarray, *, log=print,
                   t_start: float | None = None):
    """Steps 6-7 on discovery's result: the dynamic set D clustered into objects. DBSCAN (or HDBSCAN) on the
    canonical centres [N, 3] of D, fragments merged, the grow and motion-split passes when on, the second pass in
    each cluster's moving frames (``candidates`` [N] bool: the Gaussians it may join), and the size cut (after that
    pass with ``cfg.cut_after_local``). Returns (labels [N] in -1..K-1, largest first; `disc` with D widened by the
    joined Gaussians; `fgjax.cluster.cluster_report` of D's labels)."""
    t_start = time.perf_counter() if t_start is None else t_start
    n_dyn = int(disc.dynamic.sum())
    idx = np.flatnonzero(disc.dynamic)
    merge = cfg.merge_eps > 0 and disc.scores.moving_t is not None
    lab_d = cluster.cluster_dynamic(canonical[idx], cfg.cluster_method, eps=cfg.eps, min_samples=cfg.min_samples,
                                    min_fraction=0.0 if merge else cfg.min_fraction, auto_eps=cfg.auto_eps)
    cut_late = merge and cfg.cut_after_local and cfg.local_radius > 0
    if merge:  # fragments of one part first, then the size cut (late: only the floor now)
        lab_d = cluster.merge_fragments(canonical[idx], lab_d, disc.scores.moving_t[:, idx],
                                        disc.scores.total_t[:, idx], eps=cfg.merge_eps)
        frac = cfg.local_floor if cut_late else cfg.min_fraction
        lab_d = cluster.relabel_by_size(lab_d, min_size=cluster.size_cut(frac, len(idx)))
    labels = np.full(len(canonical), -1, np.int64)
    labels[idx] = lab_d
    report = cluster.cluster_report(lab_d)
    log(f"stage 2: {n_dyn} dynamic Gaussians (score threshold {disc.threshold:.3f}); {report} "
        f"({time.perf_counter() - t_start:.1f} s)")
    if cfg.grow_fraction > 0 and report.n_clusters:
        eps = cfg.grow_eps
        cand = candidates & (disc.scores.score >= cfg.grow_fraction * disc.threshold)
        before = int(np.sum(labels >= 0))
        labels = cluster.grow_clusters(canonical, labels, cand, eps)
        disc = disc._replace(dynamic=disc.dynamic | (labels >= 0))
        report = cluster.cluster_report(labels[disc.dynamic])
        log(f"stage 2: grown from {before} to {int(np.sum(labels >= 0))} clustered Gaussians (scores >= "
            f"{cfg.grow_fraction * disc.threshold:.3f} within {eps:.3f} of a cluster); sizes {list(report.sizes)}")
    if cfg.split_motion and report.n_clusters:
        split = cluster.split_by_motion(canonical, labels, disc.scores.moving_t, disc.scores.total_t)
        new = cluster.cluster_report(split[split >= 0])
        if new.n_clusters != report.n_clusters:
            log(f"stage 2: split by the times their members move: {report.n_clusters} -> {new.n_clusters} "
                f"cluster(s), sizes {list(new.sizes)}")
        labels, report = split, cluster.cluster_report(split[disc.dynamic | (split >= 0)])
    if cfg.local_radius > 0 and report.n_clusters:
        dyn_before = disc.dynamic
        loc = cluster.localize_clusters(canonical, labels, disc.scores.moving_t, disc.scores.total_t,
                                        radius=cfg.local_radius, threshold=cfg.local_threshold,
                                        candidates=candidates)
        labels = loc.labels
        disc = disc._replace(dynamic=disc.dynamic | (labels >= 0))
        report = cluster.cluster_report(labels[disc.dynamic])
        log(f"stage 2: each cluster's moving frames {[int(f.sum()) for f in loc.frames]}; "
            f"{list(loc.joined)} Gaussians joined (score >= {cfg.local_threshold} in those frames within "
            f"{cfg.local_radius} of the cluster); sizes {list(report.sizes)}")
        if cut_late:
            cut = cluster.size_cut(cfg.local_min_fraction, int(np.sum(labels >= 0)))
            labels = cluster.relabel_by_size(labels, min_size=cut)
            disc = disc._replace(dynamic=dyn_before | (labels >= 0))  # the dropped clusters' joined ones leave D
            report = cluster.cluster_report(labels[disc.dynamic])
            log(f"stage 2: the size cut ({cfg.local_min_fraction:g} of the clustered Gaussians: {cut}) keeps "
                f"{report.n_clusters} cluster(s) of sizes {list(report.sizes)}")
    return labels, disc, report


def validate_config(cfg: Stage2Config) -> None:
    """Raise ValueError naming the field when a `Stage2Config` value is out of its range (`run_stage2` checks
    this before any work; ``fgjax demo`` before stage 1)."""
    if cfg.trajectories not in ("flow", "deformation"):
        raise ValueError(f"Stage2Config.trajectories must be 'flow' or 'deformation'; got {cfg.trajectories!r}")
    if cfg.track_joints not in ("auto", "off"):
        raise ValueError(f"Stage2Config.track_joints must be 'auto' or 'off'; got {cfg.track_joints!r}")
    if cfg.track_masks not in ("frame", "reference"):
        raise ValueError(f"Stage2Config.track_masks must be 'frame' or 'reference'; got {cfg.track_masks!r}")
    for name in ("local_floor", "local_min_fraction"):
        if not 0.0 <= getattr(cfg, name) < 1.0:
            raise ValueError(f"Stage2Config.{name} must be in [0, 1), got {getattr(cfg, name)!r}")
    if cfg.track_photo < 0 or cfg.track_photo_radius < 0 or cfg.track_photo_next < 0:
        raise ValueError(f"Stage2Config.track_photo, track_photo_radius and track_photo_next must be >= 0; got "
                         f"{cfg.track_photo!r}, {cfg.track_photo_radius!r}, {cfg.track_photo_next!r}")
    if cfg.track_rounds < 1:
        raise ValueError(f"Stage2Config.track_rounds must be >= 1; got {cfg.track_rounds!r}")
    if not (isinstance(cfg.joint_search, (int, np.integer)) and not isinstance(cfg.joint_search, bool)
            and cfg.joint_search >= 0):
        raise ValueError(f"Stage2Config.joint_search must be an integer >= 0 (the first round searched; 0: off); got "
                         f"{cfg.joint_search!r}")
    if not (isinstance(cfg.hinge_trial, (int, np.integer)) and not isinstance(cfg.hinge_trial, bool)
            and cfg.hinge_trial >= 0):
        raise ValueError(f"Stage2Config.hinge_trial must be an integer >= 0 (0: off), got {cfg.hinge_trial!r}")
    if not 0 <= cfg.hinge_trial_margin < 1:  # NaN too
        raise ValueError(f"Stage2Config.hinge_trial_margin must be in [0, 1), got {cfg.hinge_trial_margin!r}")
    if not isinstance(cfg.hinge_trial_slide, (bool, np.bool_)):
        raise ValueError(f"Stage2Config.hinge_trial_slide must be true or false, got {cfg.hinge_trial_slide!r}")
    if not isinstance(cfg.hinge_trial_search_slides, (bool, np.bool_)):
        raise ValueError(f"Stage2Config.hinge_trial_search_slides must be true or false, got "
                         f"{cfg.hinge_trial_search_slides!r}")
    if not (isinstance(cfg.hinge_up_deg, (int, float, np.integer, np.floating))
            and not isinstance(cfg.hinge_up_deg, bool) and 0 <= cfg.hinge_up_deg < 90):
        raise ValueError(f"Stage2Config.hinge_up_deg must be a number in [0, 90) (0: off), got {cfg.hinge_up_deg!r}")
    if not (isinstance(cfg.hinge_trial_edges, (int, np.integer)) and not isinstance(cfg.hinge_trial_edges, bool)
            and 0 <= cfg.hinge_trial_edges <= 4):
        raise ValueError(f"Stage2Config.hinge_trial_edges must be an integer in 0..4, got {cfg.hinge_trial_edges!r}")
    if not isinstance(cfg.control_rigid, (bool, np.bool_)):
        raise ValueError(f"Stage2Config.control_rigid must be true or false, got {cfg.control_rigid!r}")
    if not cfg.track_converged_deg >= 0:
        raise ValueError(f"Stage2Config.track_converged_deg must be >= 0 (0: every round tracks every object); got "
                         f"{cfg.track_converged_deg!r}")
    if not 0.0 <= cfg.hull_opacity <= 1.0:
        raise ValueError(f"Stage2Config.hull_opacity must be in [0, 1], got {cfg.hull_opacity!r}")
    if not cfg.hull_max_growth >= 0:
        raise ValueError(f"Stage2Config.hull_max_growth must be >= 0, got {cfg.hull_max_growth!r}")
    if not (np.isfinite(cfg.ghost_radius) and cfg.ghost_radius >= 0):
        raise ValueError(f"Stage2Config.ghost_radius must be finite and >= 0, got {cfg.ghost_radius!r}")
    if not (np.isfinite(cfg.ghost_opacity) and 0 < cfg.ghost_opacity < 1):
        raise ValueError(f"Stage2Config.ghost_opacity must be in (0, 1), got {cfg.ghost_opacity!r}")
    if not (np.isfinite(cfg.hinge_radius) and cfg.hinge_radius >= 0):
        raise ValueError(f"Stage2Config.hinge_radius must be finite and >= 0, got {cfg.hinge_radius!r}")
    if not (np.isfinite(cfg.hinge_reach) and cfg.hinge_reach >= 0):
        raise ValueError(f"Stage2Config.hinge_reach must be finite and >= 0, got {cfg.hinge_reach!r}")
    if not (np.isfinite(cfg.hinge_min_deg) and 0 < cfg.hinge_min_deg <= 180):
        raise ValueError(f"Stage2Config.hinge_min_deg must be in (0, 180], got {cfg.hinge_min_deg!r}")
    if not (np.isfinite(cfg.refit_lr_scale) and cfg.refit_lr_scale > 0):
        raise ValueError(f"Stage2Config.refit_lr_scale must be finite and > 0, got {cfg.refit_lr_scale!r}")
    if not (cfg.isolated_factor == 0 or cfg.isolated_factor >= 1):
        raise ValueError(f"Stage2Config.isolated_factor must be 0 (off) or >= 1, got {cfg.isolated_factor!r}")
    if not (np.isfinite(cfg.colour_radius) and cfg.colour_radius >= 0):
        raise ValueError(f"Stage2Config.colour_radius must be finite and >= 0 (0: off), got {cfg.colour_radius!r}")
    if not (isinstance(cfg.colour_components, (int, np.integer)) and not isinstance(cfg.colour_components, bool)
            and cfg.colour_components >= 1):
        raise ValueError(f"Stage2Config.colour_components must be an integer >= 1, got {cfg.colour_components!r}")
    if not 0 <= cfg.colour_separation <= 1:  # NaN too
        raise ValueError(f"Stage2Config.colour_separation must be in [0, 1], got {cfg.colour_separation!r}")
    if not (np.isfinite(cfg.through_prune) and 0 <= cfg.through_prune <= 1):
        raise ValueError(f"Stage2Config.through_prune must be 0 (off) or in (0, 1], got {cfg.through_prune!r}")
    if cfg.hull_refit_steps < 0:
        raise ValueError(f"Stage2Config.hull_refit_steps must be >= 0, got {cfg.hull_refit_steps!r}")
    if int(cfg.mask_guide_radius) != cfg.mask_guide_radius or cfg.mask_guide_radius < 0:
        raise ValueError(f"Stage2Config.mask_guide_radius must be an integer >= 0, got {cfg.mask_guide_radius!r}")
    if not (np.isfinite(cfg.mask_guide_eps) and cfg.mask_guide_eps > 0):
        raise ValueError(f"Stage2Config.mask_guide_eps must be finite and > 0, got {cfg.mask_guide_eps!r}")
    if cfg.camera_correction not in ("auto", "on", "off"):
        raise ValueError(f"Stage2Config.camera_correction must be 'auto', 'on' or 'off'; got {cfg.camera_correction!r}")


def run_stage2(run_dir: str | Path, data_dir: str | Path, cfg: Stage2Config = Stage2Config(), *,
               log=print) -> Stage2Result:
    """Steps 5-7 on a trained stage-1 run; writes RUN/stage2.npz and RUN/stage2.json.

    Args:
        run_dir: stage-1 run folder (`fgjax train`).
        data_dir: the dataset the run was trained on (training split only is read; never gt/).
        cfg: `Stage2Config`.

    Returns:
        `Stage2Result`.
    """
    from fgjax.data.loaders import load_scene
    from fgjax.data.scene import Normalization

    if cfg.track_rounds > 1 and (cfg.track_photo == 0 or cfg.refit_steps == 0 or cfg.trajectories != "flow"):
        log(f"stage 2: track_rounds={cfg.track_rounds} has no effect without track_photo > 0, refit_steps > 0 and "
            f"trajectories='flow'; one round")
    validate_config(cfg)  # before any work is done
    t_start = time.perf_counter()
    run_dir, data_dir = Path(run_dir), Path(data_dir)
    run = load_stage2(run_dir, require_stage2=False)
    scene = load_scene(data_dir, "train", normalize=Normalization.from_dict(run.meta["normalization"]),
                       downscale=run.cfg.data.downscale)
    if (scene.width, scene.height) != (run.meta["width"], run.meta["height"]):
        raise Stage2Error(f"{data_dir}: images are {scene.width}x{scene.height} but the run was trained on "
                          f"{run.meta['width']}x{run.meta['height']}")
    if scene.num_frames < 2:
        raise Stage2Error(f"{data_dir}: stage 2 needs at least 2 training frames, got {scene.num_frames}")
    if "pose" in run.state.params:  # discovery's u_cam and the tracking need the cameras stage 1 refined
        from fgjax.pipeline.stage1 import refined_viewmats

        try:
            vms = refined_viewmats(run.state.params, scene.viewmats)
        except ValueError as e:
            raise Stage2Error(f"{data_dir}: {e}") from None
        scene = dataclasses.replace(scene, viewmats=vms.astype(scene.viewmats.dtype))
        log("stage 2: using stage 1's refined camera poses")
    cache = Path(cfg.flow_cache) if cfg.flow_cache else run_dir / "flow_cache"
    disc, centres, times, (order, flows, _) = discover_run(run, scene, cfg, cache, log)
    canonical = np.asarray(run.state.params["gaussians"].means)
    labels, disc, report = select_objects(canonical, disc, cfg, np.asarray(run.state.densify.alive), log=log,
                                          t_start=t_start)
    n_dyn = int(disc.dynamic.sum())
    # trajectories and the teacher geometry over all training times (time order)
    refit, joints, fills, history = None, {}, {}, []
    if cfg.trajectories == "flow" and report.n_clusters:
        moving = None
        if cfg.track_active > 0 and disc.scores.moving_t is not None:
            moving = cluster.moving_frames(labels, disc.scores.moving_t, disc.scores.total_t,
                                           active=cfg.track_active, dilate=1)
            log(f"stage 2: tracking each object over its moving pairs {[int(f.sum()) for f in moving]} of "
                f"{moving.shape[1]} ({time.perf_counter() - t_start:.1f} s)")
        reference = _reference_scene(run, float(times[0]))  # the scene the poses move
        base = (reference.means, reference.quats, reference.log_scales)
        poses, joints = _tracked_poses(run, scene, order, reference, labels, report.n_clusters, flows, cfg, moving,
                                       log)
        if cfg.refit_steps > 0:
            rounds = int(cfg.track_rounds) if cfg.track_photo > 0 else 1
            refit = reference  # the first re-fit starts from the reference the poses move
            history = [joints]
            for r in range(rounds):
                fixed = None
                if r >= 2 and cfg.track_converged_deg > 0:  # objects whose joint stayed put in the last round
                    from fgjax.pipeline.phototrack import converged_joints

                    a, b = history[-2], history[-1]
                    nan3 = [np.nan] * 3
                    fixed = converged_joints(a["joint_kinds"], [x or nan3 for x in a["joint_axes"]],
                                             b["joint_kinds"], [x or nan3 for x in b["joint_axes"]],
                                             cfg.track_converged_deg)
                    if fixed.all():
                        log(f"stage 2: every joint converged (the same kind, the axis within "
                            f"{cfg.track_converged_deg:g} degrees of the last round's); no round {r + 1}")
                        break
                held = _trial_held(history, report.n_clusters)  # joints chosen by a hinge trial are kept
                if r > 0 and held.any():
                    fixed = held if fixed is None else fixed | held
                    if fixed.all():
                        log(f"stage 2: every joint converged or was chosen by a hinge trial; no round {r + 1}")
                        break
                if r > 0:  # track again, rendering the last re-fit (module docstring of phototrack)
                    log(f"stage 2: tracking and re-fitting, round {r + 1} of {rounds}"
                        + ("" if fixed is None or not fixed.any() else
                           f": objects {(np.flatnonzero(~fixed) + 1).tolist()} only (the joints of "
                           f"{(np.flatnonzero(fixed) + 1).tolist()} converged"
                           + (" or were chosen by a hinge trial)" if held.any() else ")")))
                    poses, joints = _photometric_poses(run, scene, order, refit, labels, report.n_clusters, cfg,
                                                       moving, log, init_poses=poses, fixed=fixed, prev_joints=joints,
                                                       search=0 < cfg.joint_search <= r + 1)
                    history.append(joints)
                if cfg.ghost_radius > 0:
                    refit = _fade_ghosts(refit, labels, poses, run.state.densify.alive, cfg, log)
                refit, labels = refit_gaussians(run, scene, order, labels, poses, cfg.refit_steps, seed=cfg.seed + r,
                                                relabel_steps=cfg.relabel_steps, relabel_radius=cfg.relabel_radius,
                                                init=refit, lr_scale=cfg.refit_lr_scale, log=log)
                if cfg.colour_rounds and cfg.colour_radius > 0 and r < rounds - 1:  # the next round tracks these
                    labels, _ = _refine_by_colour(labels, refit, run.state.densify.alive, cfg, log)
            filled = labels
            if cfg.hull_fill:
                filled = _fill_hulls(filled, refit, run.state.densify.alive, cfg.hull_opacity, cfg.hull_max_growth,
                                     log)
                fills["hull_joined"] = _joined(labels, filled)
            if cfg.hinge_fill:
                before = filled
                filled, fills["hinges"] = _fill_hinges(before, refit, run.state.densify.alive, poses, cfg, log)
                fills["hinge_joined"] = _joined(before, filled)
            if cfg.isolated_factor > 0:
                before = filled
                filled, fills["isolated_dropped"] = _drop_isolated(before, refit, run.state.densify.alive,
                                                                   cfg.isolated_factor, log)
                refit = _fade_dropped(refit, before, filled, cfg, "of them", log)
            if cfg.colour_radius > 0:
                before = filled
                filled, rep = _refine_by_colour(before, refit, run.state.densify.alive, cfg, log)
                fills["colour_joined"] = [r["joined"] for r in rep]
                fills["colour_left"] = [r["left"] for r in rep]
                refit = _fade_dropped(refit, before, filled, cfg, "of those that left", log)
            if cfg.settle_rest and cfg.track_rest and moving is not None and cfg.track_photo > 0:
                poses, settled = _settle(run, scene, order, reference, filled, poses, moving, log)
                fills["settled"] = [list(x) for x in settled]
            if cfg.through_prune > 0:
                refit, fills["through_pruned"] = _prune_seen_through(refit, filled, poses, run, scene, order,
                                                                     cfg.through_prune, log)
            if (cfg.hull_fill or cfg.hinge_fill or cfg.isolated_factor > 0 or cfg.colour_radius > 0
                    or cfg.through_prune > 0 or fills.get("settled")) and cfg.hull_refit_steps > 0:
                refit, _ = refit_gaussians(run, scene, order, filled, poses, cfg.hull_refit_steps,
                                           seed=cfg.seed + rounds, init=refit, lr_scale=cfg.refit_lr_scale, log=log)
            labels = filled
            report = cluster.cluster_report(labels[disc.dynamic | (labels >= 0)])
            base = (refit.means, refit.quats, refit.log_scales)
        centres, qs, ls = _posed_geometry(base, labels, poses)
    else:
        qs, ls = [], []
        for t in times:
            _, q, s = run.deformed(float(t))
            qs.append(np.asarray(q))
            ls.append(np.asarray(s))
    traj = cluster.trajectories(centres, labels) if report.n_clusters else np.zeros((0, len(times), 3))
    control, stats = _train_control(run, scene, order, labels, traj, cfg, (centres, np.stack(qs), np.stack(ls)),
                                    flows, log, refit=refit)
    meta = {
        "format_version": FORMAT_VERSION,
        "data_dir": str(data_dir.resolve()),
        "config": dataclasses.asdict(cfg),
        "num_dynamic": n_dyn,
        "score_threshold": disc.threshold,
        "num_objects": report.n_clusters,
        "cluster_sizes": list(report.sizes),
        "num_noise": report.n_noise,
        "moving_pixel_fraction": float(disc.masks.mean()),
        "flow_loss": bool(stats.get("photometric", {}).get("flow_weight", 0.0) > 0),
        # the photometric tracking's joint kinds, robust costs (px^2; over 4: tracking likely lost), axes and hinge
        # offsets (radii; over 2: likely a shift fitted as a turn) of the last round
        **{key: v for key, v in joints.items() if key != "hinge_trials"},
        # `_hinge_trial`'s records of every round that tracked (a list over rounds of lists over objects)
        **({"hinge_trials": [h.get("hinge_trials") for h in history]} if cfg.hinge_trial > 0 and history else {}),
        **fills,  # Gaussians that joined each cluster by hull_fill / hinge_fill, and the hinges found
        "time_s": time.perf_counter() - t_start,
        **stats,
    }
    res = Stage2Result(labels, disc.dynamic, disc.scores.score, traj, times, control, meta, refit)
    save_stage2(run_dir, res)
    log(f"stage 2: wrote {run_dir / STAGE2_NAME} ({meta['time_s']:.1f} s)")
    return res


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fgjax stage2", description="Stage 2: discovery, clustering, control network.")
    p.add_argument("--run", required=True, help="stage-1 run folder")
    p.add_argument("--data", required=True, help="the dataset the run was trained on")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a Stage2Config field, e.g. --set eps=0.08 (repeatable)")
    return p


_TRUE, _FALSE = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


def config_from_overrides(items: list[str], base: Stage2Config | None = None, *, prefix: str = "") -> Stage2Config:
    """`base` (default: `Stage2Config()`) with ``KEY=VALUE`` strings applied (``fgjax stage2 --set``).

    Each value is parsed as its field's type: a bool from true/false, 1/0, yes/no or on/off (any case),
    an int, a float, and for ``threshold_px`` and ``score_threshold`` "otsu" or a float. Raises ValueError
    naming the key on an unknown key or a value of the wrong type (the values' ranges are checked by
    `validate_config`). `prefix` goes before the key in the messages (``fgjax demo``'s "stage2.").
    """
    fields = {f.name: f for f in dataclasses.fields(Stage2Config)}
    defaults = Stage2Config()
    kw: dict[str, Any] = {}
    for it in items:
        if "=" not in it:
            raise ValueError(f"--set {prefix}{it}: expected KEY=VALUE")
        key, val = (x.strip() for x in it.split("=", 1))
        if key not in fields:
            raise ValueError(f"--set {prefix}{key}: unknown stage-2 option (choose from {', '.join(fields)})")
        default = getattr(defaults, key)
        if isinstance(default, bool):
            if val.lower() not in _TRUE + _FALSE:
                raise ValueError(f"--set {prefix}{key}={val}: expected true or false")
            kw[key] = val.lower() in _TRUE
        elif key in ("threshold_px", "score_threshold") and val == "otsu":
            kw[key] = val
        elif isinstance(default, int | float) or key in ("threshold_px", "score_threshold"):
            typ = int if isinstance(default, int) else float
            try:
                kw[key] = typ(val)
            except ValueError:
                want = "an integer" if typ is int else "a number" if isinstance(default, float) else "a number or 'otsu'"
                raise ValueError(f"--set {prefix}{key}={val}: expected {want}") from None
        else:
            kw[key] = val
    return dataclasses.replace(defaults if base is None else base, **kw)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        cfg = config_from_overrides(args.overrides)
        run_stage2(args.run, args.data, cfg, log=lambda m: print(m, file=sys.stderr, flush=True))
    except (ValueError, FileNotFoundError, Stage2Error) as e:
        print(f"fgjax stage2: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
