"""The articulated variant of stage 2 (opt-in, ``[stage2] variant = "articulated"``): rigid part tracking, joint
fitting, the hinge trial, re-fitting and label passes, composed with `fgjax.method`'s discovery and control
network."""

from fgjax.articulate.pipeline import run_articulated as run_articulated
