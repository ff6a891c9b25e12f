"""Dynamic-Gaussian selection, clustering into objects, trajectories and trajectory snapping.

DESIGN.md section 1, steps 5 (selection of the dynamic set D from per-Gaussian scores), 6 (DBSCAN /
HDBSCAN on the canonical centres of D; the trajectory ς(t, k) of cluster k is the mean deformed
centre of its Gaussians) and 8 (a user's 3D vector is snapped to the nearest point of ς(·, k)).

Layering (DESIGN.md section 3): numpy + scikit-learn only; nothing here knows of JAX or of models.
Every function takes and returns plain numpy arrays. Label conventions: cluster labels are
0..K-1, ordered by decreasing cluster size (ties: by first occurrence), and -1 is noise.

Modules: `fgjax.cluster.dbscan` (selection, clustering, reports, trajectories, snapping),
`fgjax.cluster.motion` (clustering by motion, per-frame motion of clusters), `fgjax.cluster.regions` (spatial
label passes).
"""

from __future__ import annotations

from fgjax.cluster.dbscan import ClusterReport as ClusterReport
from fgjax.cluster.dbscan import Snap as Snap
from fgjax.cluster.dbscan import auto_eps as auto_eps
from fgjax.cluster.dbscan import cluster_dynamic as cluster_dynamic
from fgjax.cluster.dbscan import cluster_report as cluster_report
from fgjax.cluster.dbscan import k_distances as k_distances
from fgjax.cluster.dbscan import otsu_threshold as otsu_threshold
from fgjax.cluster.dbscan import relabel_by_size as relabel_by_size
from fgjax.cluster.dbscan import select_dynamic as select_dynamic
from fgjax.cluster.dbscan import size_cut as size_cut
from fgjax.cluster.dbscan import snap_to_trajectory as snap_to_trajectory
from fgjax.cluster.dbscan import trajectories as trajectories
from fgjax.cluster.motion import Localized as Localized
from fgjax.cluster.motion import activity_correlation as activity_correlation
from fgjax.cluster.motion import cluster_by_motion as cluster_by_motion
from fgjax.cluster.motion import localize_clusters as localize_clusters
from fgjax.cluster.motion import merge_fragments as merge_fragments
from fgjax.cluster.motion import moving_frames as moving_frames
from fgjax.cluster.motion import split_by_motion as split_by_motion
from fgjax.cluster.motion import true_runs as true_runs
from fgjax.cluster.regions import drop_isolated as drop_isolated
from fgjax.cluster.regions import fill_hinges as fill_hinges
from fgjax.cluster.regions import fill_hulls as fill_hulls
from fgjax.cluster.regions import hinge_axes as hinge_axes
from fgjax.cluster.regions import near_swept as near_swept
from fgjax.cluster.regions import refine_by_colour as refine_by_colour

__all__ = [
    "fill_hulls", "hinge_axes", "fill_hinges", "drop_isolated", "refine_by_colour", "near_swept",
    "cluster_by_motion", "activity_correlation", "localize_clusters", "split_by_motion", "merge_fragments",
    "true_runs", "moving_frames", "Localized",
    "otsu_threshold", "select_dynamic", "k_distances", "auto_eps", "cluster_dynamic", "relabel_by_size", "size_cut",
    "ClusterReport", "cluster_report", "trajectories", "Snap", "snap_to_trajectory",
]
