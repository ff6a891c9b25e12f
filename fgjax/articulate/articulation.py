"""One articulation per part over all its frames, chosen by the images: a discrete search over hinges and slides.

The photometric tracker (`fgjax.articulate.phototrack`) fits six degrees of freedom per frame, and `joint_poses`
then fits one joint to those poses. A single image does not pin a part's pose (six free parameters can render closer
to one image than the truth), while along the true joint the true amount renders closest. So here the joint itself is
chosen by the images:

1. Hypotheses (`articulation_hypotheses`): from a part's reference points, its principal axes and their 5th-95th
   percentile extents; a hinge along each axis through each of the four edges of the box around the others
   (12 hinges), a slide along each axis (3), and the joint already fitted (`joint_from_poses`).
2. Each hypothesis is scored by the images of the frames in which the part is displaced (its pose is not the
   identity): in each, the amount (an angle, or a shift in scene units) is searched on a grid and refined by
   halving steps, and the frame's loss is the least mean absolute difference of the rendered and the observed
   image, both blurred by ``sigma`` pixels, over the amounts tried. A hypothesis' score is the sum over the
   frames. First on the ``screen_frames`` frames of largest displacement, then the ``keep`` best (and the fitted
   joint) on all of them, where a frame right after another starts from that one's amount, and the fitted joint
   from its own amounts.
3. The best hypothesis replaces the part's poses only where its score is below that of the poses as given
   (rendered as they are): the search never makes the images worse on the frames it scores.

The hinge trial (`fgjax.articulate.trial`) uses this search for the amounts of its candidate joints.

Only the part searched moves; the others are drawn at their given poses in each frame. The frame without the part
is rendered once (its tiles reached by no member are pasted from it, as in the tracker).

Conventions: OpenCV cameras (world-to-camera `viewmats` [T, 4, 4], `Ks` [T, 3, 3]); poses [K, T, 4, 4] are
world-space rigid transforms of each object from the reference scene (pose 0 = I); quaternions wxyz.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int

from fgjax import geometry
from fgjax.articulate.phototrack import blur_kernel, blur_with
from fgjax.gaussians import Gaussians
from fgjax.geometry import HIGHEST
from fgjax.models.model import render_params
from fgjax.models.posed import transform_gaussians

__all__ = ["articulation_hypotheses", "rect_hinges", "joint_from_poses", "slide_from_poses", "articulated_pose",
           "camera_up", "camera_tilt", "LEVEL_TILT_DEG", "LEVEL_AMBIGUITY", "hinge_made_vertical", "displaced_frames",
           "search_articulations"]

REVOLUTE, PRISMATIC = "revolute", "prismatic"


def articulation_hypotheses(points: Float[ArrayLike, "M 3"]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Candidate joints of a part from its reference points [M, 3] (M >= 3): a list of (kind, unit axis [3],
    pivot [3]). Principal axes e_a of the centred points, extents lo_a..hi_a their 5th and 95th percentiles
    along each; for each axis a, a hinge along e_a through each of the 4 edges of the box lo..hi in the other
    two axes (pivot at the median along e_a), then a slide along each e_a (pivot: the median point). 15 in all."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) < 3:
        raise ValueError(f"articulation_hypotheses: at least 3 points needed, got {len(p)}")
    if not np.all(np.isfinite(p)):
        raise ValueError("articulation_hypotheses: the points must be finite")
    c = np.median(p, 0)  # [3]
    _, _, vt = np.linalg.svd(p - p.mean(0), full_matrices=False)
    e = vt  # [3, 3] rows: principal axes, largest spread first
    proj = (p - c) @ e.T  # [M, 3]
    lo, hi = np.percentile(proj, 5, axis=0), np.percentile(proj, 95, axis=0)
    out = []
    for a in range(3):
        b, d = [x for x in range(3) if x != a]
        for sb in (lo[b], hi[b]):
            for sd in (lo[d], hi[d]):
                out.append((REVOLUTE, e[a].copy(), c + sb * e[b] + sd * e[d]))
    out += [(PRISMATIC, e[a].copy(), c.copy()) for a in range(3)]
    return out


def rect_hinges(points: Float[ArrayLike, "M 3"], step_deg: float = 1.0) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The four hinges along the edges of a flat part (a lid, a door, a flap): a list of (``"revolute"``, unit
    axis [3], pivot [3]) from its reference points [M, 3] (M >= 3).

    The part's plane is that of the points' two largest principal axes; its normal n is the smallest. In the
    plane, the rectangle of least area whose sides run from the 2nd to the 98th percentile of the points along
    them is found over directions ``step_deg`` apart; the hinges run along its sides, through the 5th and 95th
    percentiles across them, at the median along n. `articulation_hypotheses`' hinges follow the principal axes,
    and a square part's in-plane axes are arbitrary, while a rectangle's sides follow its edges. The 5th-95th
    percentile rectangle of a uniform square is 6-9 degrees off its sides (its
    projections' tails thin as it turns); the 1st-99th is pulled off by 5% of stray points."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) < 3:
        raise ValueError(f"rect_hinges: at least 3 points needed, got {len(p)}")
    if not np.all(np.isfinite(p)):
        raise ValueError("rect_hinges: the points must be finite")
    if not (np.isfinite(step_deg) and 0 < step_deg <= 45):
        raise ValueError(f"rect_hinges: step_deg must be in (0, 45], got {step_deg!r}")
    c = np.median(p, 0)  # [3]
    _, _, vt = np.linalg.svd(p - p.mean(0), full_matrices=False)
    e1, n = vt[0], vt[2]  # largest principal axis, the plane's normal
    e2 = np.cross(n, e1)
    q = p - c  # [M, 3]
    th = np.radians(np.arange(0.0, 90.0 - 1e-9, float(step_deg)))  # [A]: a rectangle repeats every 90 degrees
    u = np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2  # [A, 3] one side's direction
    v = np.cross(n, u)  # [A, 3] the other's
    lo_u, hi_u = np.percentile(q @ u.T, [2, 98], axis=0)  # [A] each
    lo_v, hi_v = np.percentile(q @ v.T, [2, 98], axis=0)
    j = int(np.argmin((hi_u - lo_u) * (hi_v - lo_v)))
    (lo_u, hi_u), (lo_v, hi_v) = np.percentile(q @ u[j], [5, 95]), np.percentile(q @ v[j], [5, 95])
    mid = float(np.median(q @ n))
    out = []
    for a, b, lo, hi in ((u[j], v[j], lo_v, hi_v), (v[j], -u[j], -hi_u, -lo_u)):
        out += [(REVOLUTE, a.copy(), c + s * b + mid * n) for s in (lo, hi)]
    return out


def joint_from_poses(poses, kind: str):
    """(unit axis [3], pivot [3]) of a one-joint trajectory ``poses`` [T, 4, 4] (e.g. `joint_poses`' output):
    the axis of its largest rotation (revolute; the pivot is the point of the axis nearest the origin) or the
    direction of its largest shift (prismatic; pivot 0). None when every pose is the identity."""
    P = np.asarray(poses, np.float64)
    if kind == REVOLUTE:
        rv = np.asarray(geometry.so3_log(jnp.asarray(P[:, :3, :3])), np.float64)  # [T, 3]
        j = int(np.argmax(np.linalg.norm(rv, axis=1)))
        ang = float(np.linalg.norm(rv[j]))
        if not ang > 1e-6:
            return None
        axis = rv[j] / ang
        # x -> R x + t turns about the line {p + s axis} iff t = (I - R) p; least squares, min-norm along the axis
        piv = np.linalg.lstsq(np.eye(3) - P[j, :3, :3], P[j, :3, 3], rcond=1e-9)[0]
        return axis, piv - axis * float(piv @ axis)
    if kind == PRISMATIC:
        sh = P[:, :3, 3]
        j = int(np.argmax(np.linalg.norm(sh, axis=1)))
        n = float(np.linalg.norm(sh[j]))
        return (sh[j] / n, np.zeros(3)) if n > 1e-12 else None
    raise ValueError(f"joint_from_poses: kind must be {REVOLUTE!r} or {PRISMATIC!r}, got {kind!r}")


def slide_from_poses(points: Float[ArrayLike, "M 3"], poses: Float[ArrayLike, "T 4 4"], *, snap: bool = False):
    """The slide nearest a part's trajectory: (unit axis [3], amounts [T]) from its reference points [M, 3] and
    poses [T, 4, 4], or None when no pose moves the points' centroid.

    Each frame's best pure shift of the points is the shift of their centroid c, d_t = R_t c + t_t - c; the axis
    is the direction that holds most of the shifts (the first right singular vector of the uncentred [T, 3]
    stack; a slide starts at rest), signed so that the largest amount is positive, and the amounts are d_t along
    it. Exact for the poses of a slide; for a turn about a far line (a slide fitted as a turn) it keeps the chord
    and drops the turn. ``snap``: the axis is instead the principal axis of the points nearest that direction (a
    drawer slides along one of its box's axes; with fewer than 3 points, the chord). `articulated_pose` (``revolute``
    false) gives the slide's poses."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    P = np.asarray(poses, np.float64)
    if len(p) == 0 or P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ValueError(f"slide_from_poses: points must be [M >= 1, 3] and poses [T, 4, 4], got "
                         f"{list(np.shape(points))} and {list(np.shape(poses))}")
    c = p.mean(0)
    d = np.einsum("tij,j->ti", P[:, :3, :3], c) + P[:, :3, 3] - c  # [T, 3]
    if not np.all(np.isfinite(d)):
        raise ValueError("slide_from_poses: the points and the poses must be finite")
    if not np.max(np.linalg.norm(d, axis=1)) > 1e-12:
        return None
    axis = np.linalg.svd(d, full_matrices=False)[2][0]  # [3]
    if snap and len(p) >= 3:
        pa = np.linalg.svd(p - c, full_matrices=False)[2]  # [3, 3] principal axes
        axis = pa[int(np.argmax(np.abs(pa @ axis)))]
    amounts = d @ axis  # [T]
    if amounts[int(np.argmax(np.abs(amounts)))] < 0:
        axis, amounts = -axis, -amounts
    return axis, amounts


def articulated_pose(revolute, axis, pivot, amount):
    """World transform [4, 4]: a turn by ``amount`` radians about the unit ``axis`` [3] through ``pivot`` [3]
    (``revolute`` true) or a shift by ``amount`` along it (false). Traceable (``revolute`` may be a traced bool)."""
    axis, pivot = jnp.asarray(axis), jnp.asarray(pivot)
    rot = geometry.so3_exp(amount * axis)
    rot = jnp.where(revolute, rot, jnp.eye(3, dtype=rot.dtype))
    t = jnp.where(revolute, pivot - jnp.matmul(rot, pivot, precision=HIGHEST), amount * axis)
    return geometry.make_pose(rot, t)


def camera_up(viewmats: Float[ArrayLike, "T 4 4"]) -> Float[np.ndarray, "3"]:
    """[3] unit world "up" from world-to-camera ``viewmats`` [T, 4, 4] (OpenCV: x right, y down) held level: the
    direction most nearly orthogonal to every camera's right axis (the last right singular vector of their stack),
    signed towards the cameras' mean up (-y). Unlike the mean of the cameras' up axes, it does not tilt when the
    cameras look down."""
    R = np.asarray(viewmats, np.float64)[:, :3, :3]
    up = np.linalg.svd(R[:, 0, :])[2][-1]  # full: one camera gives a direction orthogonal to its right axis
    return up if float(up @ -R[:, 1, :].mean(0)) >= 0 else -up


LEVEL_TILT_DEG = 2.0  # `camera_tilt`: the largest RMS tilt for cameras taken as held level (synthetic scenes 0.4-0.6)
LEVEL_AMBIGUITY = 0.1  # `camera_tilt`: the largest ambiguity for a usable up (synthetic scenes 0.02-0.04)


def camera_tilt(viewmats: Float[ArrayLike, "T 4 4"]) -> tuple[float, float]:
    """How well `camera_up` is determined by world-to-camera ``viewmats`` [T, 4, 4]: (tilt, ambiguity). The tilt is
    the RMS angle in degrees of the cameras' right axes out of the plane normal to that up (0 for cameras held level;
    roll and pose noise raise it). The ambiguity is the ratio of the smallest to the middle singular value of the
    right axes' stack: near 0 where the cameras turn enough about up to fix it, 1 where any direction in a plane
    would do (cameras all facing one way); infinite for fewer than three cameras, which are level by construction."""
    right = np.asarray(viewmats, np.float64)[:, 0, :3]  # [T, 3]
    if len(right) < 3:
        return 0.0, float("inf")
    s = np.linalg.svd(right, compute_uv=False)  # [3]
    tilt = float(np.degrees(np.arcsin(min(1.0, s[2] / np.sqrt(len(right))))))
    return tilt, float(s[2] / s[1]) if s[1] > 0 else float("inf")


def hinge_made_vertical(points: Float[ArrayLike, "M 3"], poses: Float[ArrayLike, "T 4 4"], up: Float[ArrayLike, "3"],
                        max_deg: float):
    """A hinge within ``max_deg`` degrees of ``up`` [3] turned onto it: (poses [T, 4, 4], axis [3], degrees it was
    off), or None where ``poses`` [T, 4, 4] do not turn or their hinge (`joint_from_poses`) is farther off. The new
    hinge passes through the point of the old one nearest the part's centroid (reference points [M, 3]), and each
    frame turns by its old turn about the old axis (the component of its rotation vector along it)."""
    j = joint_from_poses(poses, REVOLUTE)
    if j is None:
        return None
    axis, pivot = j
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    off = float(np.degrees(np.arccos(min(abs(float(axis @ u)), 1.0))))
    if off > max_deg:
        return None
    new_axis = u if float(axis @ u) >= 0 else -u
    p = np.asarray(points, np.float64).reshape(-1, 3)
    at = pivot + axis * float((p.mean(0) - pivot) @ axis) if len(p) else pivot  # no points: the hinge's own point
    turns = _amounts(poses, REVOLUTE, axis)  # [T]
    out = np.stack([np.asarray(articulated_pose(True, new_axis, at, a), np.float64) for a in turns])
    return out.astype(np.asarray(poses).dtype), new_axis, off


def _amounts(poses, kind: str, axis) -> np.ndarray:
    """[T] each pose's amount along the unit ``axis`` [3]: its rotation vector's component (revolute) or its
    shift's (prismatic); exact for the poses of one joint (`joint_from_poses`)."""
    P = np.asarray(poses, np.float64)
    if kind == REVOLUTE:
        return np.asarray(geometry.so3_log(jnp.asarray(P[:, :3, :3])), np.float64) @ np.asarray(axis, np.float64)
    return P[:, :3, 3] @ np.asarray(axis, np.float64)


def _largest_displacement(points, poses) -> np.ndarray:
    """[T] the largest distance any of ``points`` [M, 3] is moved by each of ``poses`` [T, 4, 4]."""
    p = np.asarray(points, np.float64)
    P = np.asarray(poses, np.float64)
    moved = np.einsum("tij,mj->tmi", P[:, :3, :3], p) + P[:, None, :3, 3]
    return np.max(np.linalg.norm(moved - p[None], axis=-1), axis=1)


def displaced_frames(points, poses, tol: float) -> np.ndarray:
    """[T] bool: the frames in which ``poses`` [T, 4, 4] move some of ``points`` [M, 3] by more than ``tol``."""
    return _largest_displacement(points, poses) > tol


def search_articulations(gaussians: Gaussians, alive: Bool[ArrayLike, " N"], labels: Int[ArrayLike, " N"],
                         num_objects: int, images: Float[ArrayLike, "T H W 3"], viewmats: Float[ArrayLike, "T 4 4"],
                         Ks: Float[ArrayLike, "T 3 3"], poses: Float[ArrayLike, "K T 4 4"], *, kinds,
                         sh_degree: int, background, capacity: int | None = None, tile_size: int = 8,
                         objects=None, sigma: float = 2.0, grid: int = 21, refine: int = 3,
                         max_turn_deg: float = 100.0, max_shift: float = 2.0, screen_frames: int = 4, keep: int = 2,
                         warm_start: bool = True, hypotheses: dict | None = None, fitted_poses: dict | None = None,
                         replace: bool = True, log=print):
    """Each part's poses replaced by the one articulation that renders closest to its frames (module docstring).

    Args:
        gaussians: the reference scene (raw parameters), which the poses move; alive [N] bool; labels [N] in -1..K-1.
        images: [T, H, W, 3]; viewmats, Ks: [T, 4, 4], [T, 3, 3], the frames of ``poses`` [K, T, 4, 4].
        kinds: [K] each object's fitted joint ("revolute", "prismatic"; anything else: no fitted hypothesis).
        objects: [K] bool, the objects searched (None: all).
        sigma: blur of the loss (pixels). grid, refine: amounts on the grid, then halving steps about the best.
        max_turn_deg, max_shift: the grid spans +-max_turn_deg degrees, or +-max_shift times the part's largest
            extent (5th-95th percentile) for a slide.
        screen_frames, keep: hypotheses are screened on this many frames, the ``keep`` best scored on all (all of
            them, unscreened, when there are no more than ``keep``; "screen" is then nan).
        warm_start: on all frames, a frame right after a displaced one searches about that one's amount (+-1 grid
            step, then the halving steps) instead of the whole grid.
        hypotheses: {object: list of (kind, unit axis [3], pivot [3])} replacing `articulation_hypotheses` for those
            objects (e.g. `rect_hinges`); the fitted joint is still added first.
        fitted_poses: {object: poses [T, 4, 4]} from which those objects' fitted joint (of kind ``kinds[k]``) and its
            amounts are read instead of from ``poses``, which still give the displaced frames, the other objects'
            poses, the given poses' loss and the candidates' poses outside the displaced frames.
        replace: false: the poses are returned as given, whatever scores best (see "candidates").

    Returns:
        (poses [K, T, 4, 4], info: list of K dicts (None where not searched) with "kind", "axis", "pivot",
        "score", "score_given" (the given poses' loss summed over the same frames), "replaced", "frames", "renders",
        "hypothesis" (the best one's index; 0 is the fitted joint where "fitted_hypothesis"), "screen" (each
        hypothesis' loss summed over the screening frames), "scores" ({index: loss summed over all the frames}) and
        "candidates" ({index: (kind, axis [3], pivot [3], poses [T, 4, 4])}: each hypothesis scored on all the frames
        with its best amounts there; the given poses elsewhere).
    """
    poses = np.asarray(poses, np.float32).copy()
    labels = np.asarray(labels, np.int64)
    alive_np = np.asarray(alive, bool)
    t_all = poses.shape[1]
    objects = np.ones(num_objects, bool) if objects is None else np.asarray(objects, bool)
    info: list = [None] * num_objects
    if num_objects == 0 or t_all < 2 or not objects.any():
        return poses, info
    g = jax.tree_util.tree_map(jnp.asarray, gaussians)
    m_ref = np.asarray(g.means, np.float64)
    lab_j, alive_j = jnp.asarray(labels, jnp.int32), jnp.asarray(alive_np)
    vms, Kj = jnp.asarray(viewmats, jnp.float32), jnp.asarray(Ks, jnp.float32)
    bg = jnp.asarray(background, jnp.float32)
    images = jnp.asarray(images, jnp.float32)
    width, height = int(images.shape[2]), int(images.shape[1])
    kern = jnp.asarray(blur_kernel(float(sigma)), jnp.float32)

    def draw(P, i, live, active):
        m, q = transform_gaussians(g.means, g.quats, lab_j, P)
        gs = Gaussians(m, g.log_scales, q, g.opacity_logits, g.sh)
        img, _, info_, _ = render_params({"gaussians": gs}, live, vms[i], Kj[i], 0.0, spec=None, sh_degree=sh_degree,
                                         width=width, height=height, background=bg, capacity=capacity,
                                         tile_size=tile_size, active=active)
        return img, info_

    @jax.jit
    def rest_image(P, i, k):
        """Frame i without object k's members, the others at P [K, 4, 4]: [H, W, 3]."""
        return draw(P, i, alive_j & (lab_j != k), None)[0]

    @jax.jit
    def losses(amounts, rev, axis, pivot, P, i, k, rest, target):
        """[G] blurred L1 losses of frame i with object k at each of `amounts` [G] along the joint."""
        member = alive_j & (lab_j == k)

        def one(a):
            Pk = P.at[k].set(articulated_pose(rev, axis, pivot, a).astype(P.dtype))
            img, inf = draw(Pk, i, alive_j, member)
            on = jnp.repeat(jnp.repeat(inf["tile_on"], tile_size, 0), tile_size, 1)[:height, :width]
            img = jnp.where(on[..., None], img, rest)
            loss = jnp.mean(jnp.abs(blur_with(img, kern) - target))
            return jnp.where(jnp.isfinite(loss) & ~inf["overflow"], loss, jnp.inf)

        return jax.lax.map(one, amounts)

    @jax.jit
    def given_loss(P, i, target):
        img, inf = draw(P, i, alive_j, None)
        loss = jnp.mean(jnp.abs(blur_with(img, kern) - target))
        return jnp.where(jnp.isfinite(loss) & ~inf["overflow"], loss, jnp.inf)

    targets: dict[int, jnp.ndarray] = {}

    def target(i):
        if i not in targets:
            targets[i] = blur_with(images[i], kern)
        return targets[i]

    for k in np.flatnonzero(objects):
        t0 = time.perf_counter()
        pts = m_ref[(labels == k) & alive_np]
        if len(pts) < 3:
            continue
        extent = np.percentile(pts, 95, axis=0) - np.percentile(pts, 5, axis=0)
        size = float(np.max(extent))
        frames = np.flatnonzero(displaced_frames(pts, poses[k], 1e-3 * max(size, 1e-9)))
        if len(frames) == 0:
            continue
        own = None if hypotheses is None else hypotheses.get(int(k))
        hyps = articulation_hypotheses(pts) if own is None else list(own)
        source = poses[k] if fitted_poses is None or int(k) not in fitted_poses else np.asarray(fitted_poses[int(k)])
        fitted = joint_from_poses(source, kinds[k]) if kinds[k] in (REVOLUTE, PRISMATIC) else None
        if fitted is not None:
            hyps = [(kinds[k], *fitted)] + hyps
            fitted_amount = _amounts(source, kinds[k], fitted[0])  # [T]
        span = np.radians(max_turn_deg)
        rests = {int(i): rest_image(jnp.asarray(poses[:, i]), jnp.asarray(i, jnp.int32), jnp.asarray(k, jnp.int32))
                 for i in frames}
        n_renders = 0

        def frame_best(h, i, start=None):
            """(loss, amount) of hypothesis h in frame i: the grid, then halving steps about the best; from
            ``start`` (the amount of the frame before): that amount and +-1 grid step, then the halving steps."""
            nonlocal n_renders
            kind, axis, pivot = h
            rev = kind == REVOLUTE
            lim = span if rev else max_shift * size
            args = (jnp.asarray(rev), jnp.asarray(axis, jnp.float32), jnp.asarray(pivot, jnp.float32),
                    jnp.asarray(poses[:, i]), jnp.asarray(i, jnp.int32), jnp.asarray(k, jnp.int32), rests[int(i)],
                    target(int(i)))
            step = 2 * lim / (grid - 1)
            am = np.linspace(-lim, lim, grid) if start is None else np.array([start, start - step, start + step])
            ls = np.asarray(losses(jnp.asarray(am, jnp.float32), *args), np.float64)
            n_renders += len(am)
            j = int(np.argmin(ls))
            best, a = float(ls[j]), float(am[j])
            step /= 2
            for _ in range(refine):
                cand = np.array([a - step, a + step])
                lc = np.asarray(losses(jnp.asarray(cand, jnp.float32), *args), np.float64)
                n_renders += 2
                if lc.min() < best:
                    best, a = float(lc.min()), float(cand[int(np.argmin(lc))])
                step /= 2
            return best, a

        def all_frames(h):
            """[(loss, amount)] of hypothesis h in each displaced frame, in time order; a frame right after another
            starts from that one's amount (a part moves little from one frame to the next); the fitted joint
            starts from its own amounts."""
            out = []
            for n, i in enumerate(frames):
                if h == 0 and fitted is not None:
                    out.append(frame_best(hyps[0], i, fitted_amount[i]))
                    continue
                warm = warm_start and n > 0 and frames[n - 1] == i - 1
                out.append(frame_best(hyps[h], i, out[-1][1] if warm else None))
            return out

        if keep >= len(hyps):  # every hypothesis is scored on all the frames: no screening
            screen = np.full(len(hyps), np.nan)
            top = list(range(len(hyps)))
        else:  # screened on the frames of largest displacement
            key = frames[np.argsort(-_largest_displacement(pts, poses[k, frames]))[:screen_frames]]
            screen = np.array([sum(frame_best(h, i, fitted_amount[i] if n == 0 and fitted is not None else None)[0]
                                   for i in key) for n, h in enumerate(hyps)])
            top = list(np.argsort(screen)[:keep])
        if fitted is not None and 0 not in top:
            top.append(0)
        scores = {}
        for h in top:
            res = all_frames(h)
            scores[h] = (sum(r[0] for r in res), [r[1] for r in res])
        given = sum(float(given_loss(jnp.asarray(poses[:, i]), jnp.asarray(i, jnp.int32), target(int(i))))
                    for i in frames)
        n_renders += 2 * len(frames)  # the rests and the given poses
        h_best = min(scores, key=lambda h: scores[h][0])
        score, amounts = scores[h_best]
        kind, axis, pivot = hyps[h_best]
        candidates = {}
        for h, (_, am) in scores.items():
            pk = poses[k].copy()
            for i, a in zip(frames, am):
                pk[i] = np.asarray(articulated_pose(hyps[h][0] == REVOLUTE, hyps[h][1], hyps[h][2], a), np.float32)
            candidates[int(h)] = (hyps[h][0], np.asarray(hyps[h][1], np.float64),
                                  np.asarray(hyps[h][2], np.float64), pk)
        replaced = bool(replace and score < given)
        if replaced:
            poses[k] = candidates[int(h_best)][3]
        info[k] = dict(kind=kind, axis=[float(x) for x in axis], pivot=[float(x) for x in pivot], score=float(score),
                       score_given=float(given), replaced=replaced, frames=int(len(frames)), renders=int(n_renders),
                       hypothesis=int(h_best), fitted_hypothesis=fitted is not None,
                       screen=[float(x) for x in screen], scores={int(h): float(v[0]) for h, v in scores.items()},
                       candidates=candidates)
        amt = np.degrees(np.max(np.abs(amounts))) if kind == REVOLUTE else float(np.max(np.abs(amounts)))
        log(f"articulation search: object {k + 1}: {len(hyps)} hypotheses over {len(frames)} displaced frames; best "
            f"{kind} (hypothesis {h_best}{', the fitted joint' if fitted is not None and h_best == 0 else ''}), axis "
            f"{np.round(axis, 3).tolist()}, largest {'turn' if kind == REVOLUTE else 'shift'} "
            f"{amt:.3g}{' degrees' if kind == REVOLUTE else ''}; loss {score / len(frames):.5f} a frame against the "
            f"given poses' {given / len(frames):.5f} -> {'replaced' if replaced else 'kept'}"
            f"{'' if replace else ' (not replacing)'} ({n_renders} renders, "
            f"{time.perf_counter() - t0:.1f} s)")
    return poses, info
