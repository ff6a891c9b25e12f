"""The in-memory scene every loader returns, and the scene normalisation.

Conventions (DESIGN.md section 2):

- Cameras are OpenCV: x right, y down, z forward. ``viewmats[t]`` is the 4x4
  world-to-camera matrix of frame t; ``Ks[t]`` is a pinhole 3x3 (zero skew);
  pixel (j, i) has its centre at (j + 0.5, i + 0.5).
- Everything geometric in a `Scene` (viewmats, depths) is in *normalised scene
  units*: x_normalised = (x_world - centre) * scale, with (centre, scale) kept in
  `Scene.normalization` so that any output can be mapped back to world units.
- Times are normalised to [0, 1] over the sequence.

This is the data layer: plain numpy, not a JAX pytree. Convert with
``jnp.asarray`` where a model needs the arrays.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from jaxtyping import Float

__all__ = ["Normalization", "Scene", "camera_centres", "compute_normalization"]

# Tolerances for the rigid-pose checks (shared with the loaders).
ROTATION_TOL = 1e-3  # max |R^T R - I| accepted as a rotation
BOTTOM_ROW_TOL = 1e-6  # max |last row - (0, 0, 0, 1)|


def rigid_problem(mats: np.ndarray) -> tuple[int, str] | None:
    """First non-rigid 4x4 in `mats` [T, 4, 4], as (index, reason); None when all are rigid."""
    for i, m in enumerate(mats):
        if not np.all(np.isfinite(m)):
            return i, "has non-finite entries"
        if np.max(np.abs(m[3] - np.array([0.0, 0.0, 0.0, 1.0]))) > BOTTOM_ROW_TOL:
            return i, f"has last row {m[3].tolist()}, expected [0, 0, 0, 1]"
        r = m[:3, :3]
        err = float(np.max(np.abs(r.T @ r - np.eye(3))))
        if err > ROTATION_TOL:
            return i, f"rotation block is not orthonormal (max |R^T R - I| = {err:.3g} > {ROTATION_TOL})"
        det = float(np.linalg.det(r))
        if det < 0:
            return i, f"rotation block has det {det:.3g} < 0 (a reflection, not a rotation)"
    return None


def camera_centres(viewmats: Float[np.ndarray, "T 4 4"]) -> Float[np.ndarray, "T 3"]:
    """Camera centres c = -R^T t of OpenCV world-to-camera matrices, in the same units."""
    viewmats = np.asarray(viewmats, dtype=np.float64)
    r = viewmats[..., :3, :3]  # [T, 3, 3]
    t = viewmats[..., :3, 3]  # [T, 3]
    return -np.einsum("...ji,...j->...i", r, t)


@dataclasses.dataclass(frozen=True, eq=False)
class Normalization:
    """Similarity x_normalised = (x_world - centre) * scale, recorded so outputs map back.

    Poses: a world-to-camera [R | t] becomes [R | scale * (R centre + t)] (the camera
    frame is scaled with the world, so camera-space depths are multiplied by `scale`
    too). Lengths (depths, DBSCAN eps, Gaussian scales) are multiplied by `scale`.

    Attributes:
        centre: [3] world point that maps to the origin.
        scale: positive float, normalised units per world unit.
    """

    centre: Float[np.ndarray, 3]
    scale: float

    def __post_init__(self):
        centre = np.asarray(self.centre, dtype=np.float64)
        if centre.shape != (3,) or not np.all(np.isfinite(centre)):
            raise ValueError(f"Normalization.centre must be 3 finite numbers; got {self.centre!r}")
        scale = float(self.scale)
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"Normalization.scale must be finite and > 0; got {self.scale!r}")
        object.__setattr__(self, "centre", centre)
        object.__setattr__(self, "scale", scale)

    @classmethod
    def identity(cls) -> Normalization:
        """No normalisation: centre 0, scale 1."""
        return cls(np.zeros(3), 1.0)

    def points_to_scene(self, x: Float[np.ndarray, "*B 3"]) -> Float[np.ndarray, "*B 3"]:
        """World points -> normalised points."""
        return (np.asarray(x, dtype=np.float64) - self.centre) * self.scale

    def points_to_world(self, x: Float[np.ndarray, "*B 3"]) -> Float[np.ndarray, "*B 3"]:
        """Normalised points -> world points."""
        return np.asarray(x, dtype=np.float64) / self.scale + self.centre

    def lengths_to_scene(self, d: Any) -> Any:
        """World lengths (depths, radii) -> normalised lengths."""
        return np.asarray(d) * self.scale

    def lengths_to_world(self, d: Any) -> Any:
        """Normalised lengths -> world lengths."""
        return np.asarray(d) / self.scale

    def viewmats_to_scene(self, viewmats: Float[np.ndarray, "*B 4 4"]) -> Float[np.ndarray, "*B 4 4"]:
        """OpenCV world-to-camera matrices in world units -> in normalised units."""
        v = np.array(viewmats, dtype=np.float64)  # copy
        r = v[..., :3, :3]
        v[..., :3, 3] = self.scale * (np.einsum("...ij,j->...i", r, self.centre) + v[..., :3, 3])
        return v

    def viewmats_to_world(self, viewmats: Float[np.ndarray, "*B 4 4"]) -> Float[np.ndarray, "*B 4 4"]:
        """OpenCV world-to-camera matrices in normalised units -> in world units."""
        v = np.array(viewmats, dtype=np.float64)  # copy
        r = v[..., :3, :3]
        v[..., :3, 3] = v[..., :3, 3] / self.scale - np.einsum("...ij,j->...i", r, self.centre)
        return v

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (floats round-trip exactly through `json`)."""
        return {"centre": [float(c) for c in self.centre], "scale": float(self.scale)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Normalization:
        """Inverse of `to_dict`."""
        return cls(np.asarray(d["centre"], dtype=np.float64), float(d["scale"]))


def compute_normalization(
    centres: Float[np.ndarray, "T 3"], *, radius: float = 1.0
) -> Normalization:
    """Normalisation that puts the camera centres in a ball of `radius` about the origin.

    centre = mean of the camera centres; scale = radius / max_t |c_t - centre|, so the
    farthest camera lies exactly at distance `radius`. When the cameras (nearly) coincide
    (one frame, or a static camera: max distance <= 1e-9 * (1 + |centre|)) the scale is 1.
    Caveat: for forward-facing captures with a short baseline this blows the scene up
    (objects end up many units away); pass an explicit `Normalization` there.

    Args:
        centres: [T, 3] camera centres in world units.
        radius: target radius of the camera ball, in normalised units.

    Returns:
        The `Normalization`.
    """
    centres = np.asarray(centres, dtype=np.float64)
    if centres.ndim != 2 or centres.shape[1] != 3 or centres.shape[0] == 0:
        raise ValueError(f"compute_normalization: centres must be [T, 3] with T >= 1; got {centres.shape}")
    if not np.all(np.isfinite(centres)):
        raise ValueError("compute_normalization: centres contain non-finite values")
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"compute_normalization: radius must be > 0; got {radius}")
    centre = centres.mean(axis=0)
    extent = float(np.max(np.linalg.norm(centres - centre, axis=-1)))
    if extent <= 1e-9 * (1.0 + float(np.linalg.norm(centre))):
        return Normalization(centre, 1.0)
    return Normalization(centre, radius / extent)


def _as_float(name: str, x: Any, dtype) -> np.ndarray:
    arr = np.asarray(x)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)) or arr.dtype == bool:
        raise ValueError(f"Scene.{name} must be a real float array; got dtype {arr.dtype}")
    return arr.astype(dtype, copy=False)


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A posed, time-stamped monocular sequence in normalised scene units.

    Attributes:
        images: [T, H, W, 3] float32 RGB in [0, 1] (alpha already composited).
        Ks: [T, 3, 3] float64 pinhole intrinsics (zero skew, last row (0, 0, 1)),
            in pixels, principal point in the pixel-centre-at-+0.5 convention.
        viewmats: [T, 4, 4] float64 OpenCV world-to-camera, normalised units.
        times: [T] float64 in [0, 1].
        width, height: image size in pixels (W, H).
        frame_names: T names (paths relative to the dataset folder, no extension, or ids).
        normalization: the map from world to normalised units.
        depths: optional [T, H, W] float32 camera z-depth in normalised units; 0 = unknown.
        masks: optional [T, H, W] bool or integer labels (0 = background).

    Construction validates shapes, dtypes and values, naming the offending field;
    float inputs are cast to the dtypes above.
    """

    images: Float[np.ndarray, "T H W 3"]
    Ks: Float[np.ndarray, "T 3 3"]
    viewmats: Float[np.ndarray, "T 4 4"]
    times: Float[np.ndarray, " T"]
    width: int
    height: int
    frame_names: list[str]
    normalization: Normalization = dataclasses.field(default_factory=Normalization.identity)
    depths: Float[np.ndarray, "T H W"] | None = None
    masks: np.ndarray | None = None

    def __post_init__(self):
        images = _as_float("images", self.images, np.float32)
        if images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] < 1:
            raise ValueError(f"Scene.images must be [T, H, W, 3] with T >= 1; got shape {images.shape}")
        t, h, w, _ = images.shape
        if not np.all(np.isfinite(images)) or images.min() < 0.0 or images.max() > 1.0:
            raise ValueError(
                f"Scene.images must be finite and in [0, 1]; got range [{np.nanmin(images)}, {np.nanmax(images)}]"
            )
        if int(self.width) != w or int(self.height) != h:
            raise ValueError(
                f"Scene.width/height = ({self.width}, {self.height}) disagree with Scene.images "
                f"of shape {images.shape} (W={w}, H={h})"
            )
        object.__setattr__(self, "images", images)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

        ks = _as_float("Ks", self.Ks, np.float64)
        if ks.shape != (t, 3, 3):
            raise ValueError(f"Scene.Ks must be [T, 3, 3] = [{t}, 3, 3]; got shape {ks.shape}")
        if not np.all(np.isfinite(ks)):
            raise ValueError("Scene.Ks has non-finite entries")
        bad = np.flatnonzero(
            (np.abs(ks[:, 2] - np.array([0.0, 0.0, 1.0])).max(-1) > 0)
            | (ks[:, 0, 1] != 0)
            | (ks[:, 1, 0] != 0)
            | (ks[:, 0, 0] <= 0)
            | (ks[:, 1, 1] <= 0)
        )
        if bad.size:
            raise ValueError(
                f"Scene.Ks[{bad[0]}] is not a zero-skew pinhole with fx, fy > 0 and last row (0, 0, 1): "
                f"{ks[bad[0]].tolist()}"
            )
        object.__setattr__(self, "Ks", ks)

        vm = _as_float("viewmats", self.viewmats, np.float64)
        if vm.shape != (t, 4, 4):
            raise ValueError(f"Scene.viewmats must be [T, 4, 4] = [{t}, 4, 4]; got shape {vm.shape}")
        problem = rigid_problem(vm)
        if problem is not None:
            raise ValueError(f"Scene.viewmats[{problem[0]}] {problem[1]}")
        object.__setattr__(self, "viewmats", vm)

        times = _as_float("times", self.times, np.float64)
        if times.shape != (t,):
            raise ValueError(f"Scene.times must be [T] = [{t}]; got shape {times.shape}")
        if not np.all(np.isfinite(times)) or times.min() < 0.0 or times.max() > 1.0:
            raise ValueError(f"Scene.times must be finite and in [0, 1]; got {times.tolist()}")
        object.__setattr__(self, "times", times)

        if isinstance(self.frame_names, str | bytes) or not isinstance(self.frame_names, Sequence):
            raise ValueError(f"Scene.frame_names must be a list of str; got {type(self.frame_names).__name__}")
        names = list(self.frame_names)
        if len(names) != t or not all(isinstance(n, str) for n in names):
            raise ValueError(f"Scene.frame_names must be {t} strings; got {len(names)} items")
        object.__setattr__(self, "frame_names", names)

        if not isinstance(self.normalization, Normalization):
            raise ValueError(
                f"Scene.normalization must be a Normalization; got {type(self.normalization).__name__}"
            )

        if self.depths is not None:
            d = _as_float("depths", self.depths, np.float32)
            if d.shape != (t, h, w):
                raise ValueError(f"Scene.depths must be [T, H, W] = [{t}, {h}, {w}]; got shape {d.shape}")
            if not np.all(np.isfinite(d)) or d.min() < 0:
                raise ValueError("Scene.depths must be finite and >= 0 (0 marks unknown depth)")
            object.__setattr__(self, "depths", d)
        if self.masks is not None:
            m = np.asarray(self.masks)
            if not (m.dtype == bool or np.issubdtype(m.dtype, np.integer)):
                raise ValueError(f"Scene.masks must be bool or integer; got dtype {m.dtype}")
            if m.shape != (t, h, w):
                raise ValueError(f"Scene.masks must be [T, H, W] = [{t}, {h}, {w}]; got shape {m.shape}")
            object.__setattr__(self, "masks", m)

    @property
    def num_frames(self) -> int:
        """T."""
        return int(self.images.shape[0])

    @property
    def camtoworlds(self) -> Float[np.ndarray, "T 4 4"]:
        """OpenCV camera-to-world matrices (inverses of `viewmats`), normalised units."""
        r = self.viewmats[:, :3, :3]
        c2w = np.zeros_like(self.viewmats)
        c2w[:, :3, :3] = np.swapaxes(r, -1, -2)
        c2w[:, :3, 3] = camera_centres(self.viewmats)
        c2w[:, 3, 3] = 1.0
        return c2w

    def viewmats_world(self) -> Float[np.ndarray, "T 4 4"]:
        """`viewmats` mapped back to world units."""
        return self.normalization.viewmats_to_world(self.viewmats)

    def subset(self, indices: Sequence[int] | np.ndarray) -> Scene:
        """The frames at `indices` (same normalisation; times are kept, not re-normalised)."""
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        return dataclasses.replace(
            self,
            images=self.images[idx],
            Ks=self.Ks[idx],
            viewmats=self.viewmats[idx],
            times=self.times[idx],
            frame_names=[self.frame_names[i] for i in idx],
            depths=None if self.depths is None else self.depths[idx],
            masks=None if self.masks is None else self.masks[idx],
        )
