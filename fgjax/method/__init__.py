"""The paper's method (DESIGN.md section 1): stage-1 training, discovery, clustering, trajectories, the control
network and its controlled scene. Never imports `fgjax.articulate` or `fgjax.apps`."""

from fgjax.method.result import LoadedRun as LoadedRun
from fgjax.method.result import Stage2Error as Stage2Error
from fgjax.method.result import Stage2Result as Stage2Result
from fgjax.method.result import load_stage2 as load_stage2
from fgjax.method.result import render_clusters as render_clusters
from fgjax.method.result import render_controlled as render_controlled
from fgjax.method.result import snap_vector as snap_vector
from fgjax.method.splats import Splats as Splats
from fgjax.method.splats import scene_gaussians as scene_gaussians
from fgjax.method.splats import viewer_gaussians as viewer_gaussians
from fgjax.method.stage1 import run as run_stage1  # noqa: F401
from fgjax.method.stage1 import train_stage1 as train_stage1
from fgjax.method.stage2 import run_stage2 as run_stage2
