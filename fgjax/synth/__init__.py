"""Synthetic articulated scenes with ground truth (``fgjax synth``, `fgjax.apps.synth`).

A procedural room (floor and three walls, textured so that optical flow has something to track)
with movable objects of four kinds, all built from Gaussians and rendered with
`fgjax.rasterization`:

- ``door``: a cabinet (static, open-front box) whose door rotates about a vertical hinge on its
  left front edge, up to 85 degrees, swinging towards the camera;
- ``drawer``: a chest (static) whose drawer (front panel + tray) slides out along the chest's
  front normal, up to 0.75 of the chest depth;
- ``lid``: a chest (static, open top) whose lid rotates about a horizontal hinge on the back top
  edge, up to 75 degrees;
- ``free``: a ball that rolls along a curved path on the floor towards the camera (translation
  plus rolling rotation; a straight path when it is one of the close pair).

Units and frames. World z is up, the floor is z = 0, the room spans x, y in [-1.6, 1.6] and
z in [0, 1.6] (3.2 units across, `ROOM_SIZE`). Objects are 0.2-0.5 units across. Gaussians on a
movable part are spaced `SynthConfig.object_spacing` (0.025) apart, so DBSCAN with eps 0.05 groups
each part; distinct objects are more than 0.1 apart at every state (`SynthScene.min_separation`),
except with ``close_pair``, which puts the first two objects side by side with the nearest
Gaussian centres of their moving parts `SynthConfig.close_gap` (0.05) apart in the canonical state
(their motions keep them about that far apart). Where the two parts sit at different heights (a
ball next to a lid) the whole objects stop at 0.8 gap instead and the parts' actual gap, recorded
as `SynthScene.close_gap`, is larger. Cameras are OpenCV (x right, y down, z forward),
``viewmat`` world-to-camera, pixel (j, i) centred at (j + 0.5, i + 0.5) (DESIGN.md section 2).

Kinematics. Object k has a rigid transform T_k(s) of its state s in [0, 1] (s = 0: closed, the
canonical pose in which the Gaussians are stored): X' = R(s)(X - p) + p + d(s) with pivot p.
Its state follows a schedule s_k(t): keyframes joined by smoothstep segments (zero velocity at
each keyframe), so there are rests at the start, between movements and at the end; each object
opens, holds and closes in its own time window, so objects move at different times.

The camera sweeps an arc (``orbit_deg``, 60 degrees by default) around the objects at about 2
units, with smooth hand-held jitter (position, look-at point and roll).

Ground truth (written by `generate`; ``gt/meta.json`` lists every file):

- depth: the rasterizer's expected camera z-depth (sum T a z / alpha), 0 where alpha <= 1e-6;
- object id per pixel: argmax of the composited one-hot labels (0 = static, k = object k),
  -1 where alpha < 0.5 (``valid`` False);
- optical flow t-1 -> t on frame t-1's grid, ``[T-1, H, W, 2]`` (dx, dy) in pixels: the centre m
  of each valid pixel is back-projected with its expected depth to a world point X (true camera
  t-1), moved with its object's rigid motion T_k(s_t) T_k(s_{t-1})^-1 (identity for static
  pixels), and projected with the true camera t: flow = pi_t(X') - m. Camera flow =
  pi_t(X) - m (the point held static); object flow = flow - camera flow (exactly 0 on static
  pixels). Approximation: at object boundaries the composited depth and id mix the front and
  back surfaces, so the flow there is that of a point in between (it is exact wherever one
  opaque surface covers the pixel). ``flow_occluded`` marks points that leave the image or land
  behind frame t's surface (depth test, 3 % + 0.01 tolerance);
- per-Gaussian labels, the canonical (state 0) Gaussians (``gt/canonical.npz``), per-frame
  object states and 3D centres (mean of the object's deformed Gaussians), the true poses.

Options: the object kinds and count (up to `MAX_OBJECTS`), resolution, frame count, seed, pose
noise on the *written training* poses (the images are rendered from the true poses, which are
stored in ``gt/``; test poses are written exact), a lighting change (a per-frame global gain
g(t) = 1 - a * smoothstep((t - 0.3) / 0.4) that multiplies the rendered RGB; brightness
constancy breaks, the geometry and the flow do not change), and a close pair.

Test split (``transforms_test.json``): ``view`` frames at training times seen from other camera
positions (azimuth +-10 degrees off the arc, higher and closer), with the schedule's states; and
``state`` frames seen from a training camera with object-state combinations the training
schedule never shows (all objects open at once, to different degrees); their ``time`` is the
training camera's time, so they are meant for control evaluation (``gt/test/kind.npy``,
``gt/meta.json`` say which frame is which).

The scene family (`fgjax.synth.family`, ``fgjax synth --family SEED``) draws a random scene per seed: part
kinds, joint axes, sizes, colours, schedules, camera paths and resolutions (its docstring lists them).

Modules: `fgjax.synth.parts` (numpy helpers, surfaces, the room and the object kinds),
`fgjax.synth.scene` (config, kinematics, layout, `make_scene`, camera path), `fgjax.synth.render`
(rendering, ground-truth flow, flow colours), `fgjax.synth.write` (`generate`),
`fgjax.synth.family` (the scene family).
"""

from __future__ import annotations

from fgjax.synth.family import family_config as family_config
from fgjax.synth.family import make_family_scene as make_family_scene
from fgjax.synth.family import parse_seeds as parse_seeds
from fgjax.synth.parts import ROOM_HALF as ROOM_HALF
from fgjax.synth.parts import ROOM_HEIGHT as ROOM_HEIGHT
from fgjax.synth.parts import ROOM_SIZE as ROOM_SIZE
from fgjax.synth.render import VALID_ALPHA as VALID_ALPHA
from fgjax.synth.render import Renders as Renders
from fgjax.synth.render import flow_to_color as flow_to_color
from fgjax.synth.render import ground_truth_flow as ground_truth_flow
from fgjax.synth.render import render_sequence as render_sequence
from fgjax.synth.render import sequence_flow as sequence_flow
from fgjax.synth.scene import FAMILY_KINDS as FAMILY_KINDS
from fgjax.synth.scene import MAX_OBJECTS as MAX_OBJECTS
from fgjax.synth.scene import OBJECT_KINDS as OBJECT_KINDS
from fgjax.synth.scene import SynthConfig as SynthConfig
from fgjax.synth.scene import SynthObject as SynthObject
from fgjax.synth.scene import SynthScene as SynthScene
from fgjax.synth.scene import camera_c2w as camera_c2w
from fgjax.synth.scene import compose_transforms as compose_transforms
from fgjax.synth.scene import deform as deform
from fgjax.synth.scene import make_scene as make_scene
from fgjax.synth.scene import object_centres as object_centres
from fgjax.synth.scene import object_state as object_state
from fgjax.synth.scene import object_transform as object_transform
from fgjax.synth.scene import scene_states as scene_states
from fgjax.synth.write import FORMAT_VERSION as FORMAT_VERSION
from fgjax.synth.write import GENERATOR as GENERATOR
from fgjax.synth.write import generate as generate

__all__ = [
    "OBJECT_KINDS", "MAX_OBJECTS", "ROOM_HALF", "ROOM_HEIGHT", "ROOM_SIZE", "GENERATOR", "FORMAT_VERSION",
    "VALID_ALPHA", "SynthConfig", "SynthObject", "SynthScene", "Renders", "make_scene", "object_state",
    "object_transform", "scene_states", "deform", "object_centres", "camera_c2w", "render_sequence",
    "ground_truth_flow", "sequence_flow", "flow_to_color", "generate", "FAMILY_KINDS", "compose_transforms",
    "family_config", "make_family_scene", "parse_seeds",
]
