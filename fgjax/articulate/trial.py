"""The hinge trial: a part fitted as a far hinge (a lift mistaken for a turn) tried against hinges along its own
edges and against slides, each judged by how closely the scene re-fitted under it renders the frames it moves in.
"""

from __future__ import annotations

import time

import numpy as np
from jaxtyping import Float, Int

from fgjax.articulate.articulation import (
    displaced_frames,
    rect_hinges,
    search_articulations,
    slide_from_poses,
)
from fgjax.articulate.labels import refine_by_colour
from fgjax.articulate.phototrack import hinge_offset, is_far_hinge, largest_turn_deg
from fgjax.articulate.refit import posed_losses, refit_gaussians
from fgjax.config import ArticulateConfig
from fgjax.data.scene import Scene
from fgjax.gaussians import Gaussians
from fgjax.method.result import LoadedRun, render_capacity

__all__ = ["hinge_trial", "trial_held", "trial_name", "trial_choice", "trial_slides"]


def trial_held(history: list[dict], num_objects: int) -> np.ndarray:
    """[K] bool: the objects whose poses a `hinge_trial` of some earlier round (``history``: each round's joint
    dict) replaced; the later rounds keep their joints."""
    held = np.zeros(num_objects, bool)
    for joints in history:
        for k, rec in enumerate(joints.get("hinge_trials") or []):
            held[k] |= bool(rec and rec.get("replaced"))
    return held


def trial_name(h: int, axis) -> str:
    """How the log names `hinge_trial`'s candidate ``h`` (-1 the given poses, -2 the chord's slide, -3 the slide
    along a principal axis, -4 and -5 the same with their amounts searched, else an edge)."""
    if h == -1:
        return "the given poses"
    what = {-2: "slide", -3: "slide along a principal axis", -4: "slide, its amounts searched",
            -5: "slide along a principal axis, its amounts searched"}.get(h, f"edge {h}")
    return f"{what}, axis {np.round(np.asarray(axis), 3).tolist()}"


def trial_finalists(hyps, losses) -> tuple[int | None, int | None]:
    """The indices of the best slide (``hyps`` below -1) and the best edge (``hyps`` >= 0) by ``losses`` (None
    where there is none): with the given poses, the only candidates `trial_choice` compares."""
    slides = [i for i, h in enumerate(hyps) if h < -1]
    edges = [i for i, h in enumerate(hyps) if h >= 0]
    return tuple(min(g, key=lambda i: losses[i]) if g else None for g in (slides, edges))


def trial_choice(hyps, losses, margin: float) -> int:
    """The index of `hinge_trial`'s choice among its candidates (``hyps``: -1 the given poses, first; below -1 a
    slide; else an edge) by their re-fitted ``losses``: the best edge when it is below (1 - ``margin``) times the
    given poses' loss and no worse than the best slide's; else the best slide when it is no more than (1 +
    ``margin``) times the given poses' (a hinge far off its part is likely a slide fitted as a turn:
    `joint_poses`); else the given poses (0)."""
    hyps, losses = list(hyps), np.asarray(losses, np.float64)
    if hyps[0] != -1 or not np.all(np.isfinite(losses) | (losses == np.inf)):
        raise ValueError(f"trial_choice: the given poses come first and the losses are not NaN; got {hyps}, "
                         f"{losses.tolist()}")
    slide, e = trial_finalists(hyps, losses)
    if e is not None:
        if losses[e] < (1.0 - margin) * losses[0] and (slide is None or losses[e] <= losses[slide]):
            return e
    if slide is not None and losses[slide] <= (1.0 + margin) * losses[0]:
        return slide
    return 0


def trial_slides(points, poses, min_deg: float = 2.0) -> list[tuple]:
    """`hinge_trial`'s slide candidates for a part (reference points [M, 3]) and its given poses [T, 4, 4]: a list
    of (hypothesis, "prismatic", unit axis [3], pivot 0 [3], poses [T, 4, 4]); -2 the chord of the poses without
    their turn, -3 the same along the part's principal axis nearest it, unless that is within ``min_deg`` of the
    chord (`slide_from_poses`). Empty when the poses do not move the part's centroid."""

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


def hinge_trial(run: LoadedRun, scene: Scene, order: Int[np.ndarray, " T"], ref: Gaussians,
                 labels: Int[np.ndarray, " N"], num_objects: int,
                 poses: Float[np.ndarray, "K T 4 4"], kinds, offsets, cfg: ArticulateConfig, objects, seed: int = 0,
                 log=print) -> tuple[Float[np.ndarray, "K T 4 4"], dict]:
    """Each far hinge (``ArticulateConfig.hinge_trial``) tried against hinges along its part's own edges and against
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
    by colour on `ref` (`refine_by_colour`, with ``colour_radius`` > 0), so that Gaussians of the
    surroundings that joined the part (a lid's box rims) do not hold its hinge back. They serve the trial only; the
    labels returned by the round are unchanged.
    The scene is re-fitted from `ref` under each candidate (`refit_gaussians` on the frames in which some candidate
    displaces the part, the same seed), and scored by the mean photometric loss of those frames rendered from its
    re-fit; `trial_choice` picks by those scores (an edge must beat the given poses by ``hinge_trial_margin``; the
    better slide wins ties within it). The ``hinge_trial`` steps are raced (successive halving, Jamieson and
    Talwalkar 2016): every candidate gets ``hinge_trial_race`` of them, then only the three that `trial_choice`
    compares (the given poses, the best slide, the best edge) go on from their re-fits for the rest.

    Returns (poses [K, T, 4, 4], {object: {"candidates": [{"hypothesis", "kind", "axis", "pivot", "loss"}, ...]
    (the given poses as hypothesis -1, the slides as -2 and -3, the searched slides as -4 and -5, the edges as 0-3;
    "steps": the re-fit steps its loss is after),
    "given_loss", "replaced", "kind" (the chosen joint's, None where kept), "axis", "offset" (None for a slide),
    "frames", "seconds"}}).
    """

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
            tl = refine_by_colour(labels, ref, alive, cfg, seed, log)[0] if cfg.colour_radius > 0 else labels
        pts = m0[(tl == k) & alive]
        if len(pts) < 3:
            continue
        t0 = time.perf_counter()
        log(f"hinge trial: object {k + 1}'s hinge lies {offsets[k]:.1f} radii off it while it turns {turn:.1f} "
            f"degrees; trying hinges along its edges")
        slides = trial_slides(pts, poses[k]) if cfg.hinge_trial_slide else []
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
                                        background=run.cfg.model.background, capacity=render_capacity(run),
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
        steps = int(cfg.hinge_trial)
        first = steps if cfg.hinge_trial_race >= 1.0 else max(1, int(round(cfg.hinge_trial_race * steps)))

        def refit(pk, init, n_steps):
            trial = poses.copy()
            trial[k] = pk
            gs, _ = refit_gaussians(run, scene, order, tl, trial, n_steps, seed=seed, init=init,
                                    lr_scale=cfg.refit_lr_scale, frames=frames, log=lambda *a: None)
            return gs, float(np.mean(posed_losses(run, scene, order, gs, tl, trial, frames)))

        losses, fits, same_as, done = [], [], [], [first] * len(cands)  # done: the steps each loss is after
        for n, (h, kind, ax, pv, pk) in enumerate(cands):  # round 1: every candidate, `first` steps
            same = next((m for m in range(n) if np.allclose(cands[m][4], pk, rtol=0.0, atol=1e-6)), None)
            same_as.append(same)
            if same is not None:  # e.g. a slide whose search kept every amount: the same re-fit
                losses.append(losses[same])
                fits.append(None)
                log(f"hinge trial: object {k + 1}: {trial_name(h, ax)}: the poses of the "
                    f"{trial_name(cands[same][0], cands[same][2])}; loss {losses[-1]:.5f}")
                continue
            gs, loss = refit(pk, ref, first)
            losses.append(loss)
            fits.append(gs)
            log(f"hinge trial: object {k + 1}: {trial_name(h, ax)}: loss {loss:.5f} after a "
                f"{first}-step re-fit on its {len(frames)} displaced frames")
        hyps_k = [c[0] for c in cands]
        final = list(range(len(cands)))
        if first < steps:  # round 2: only the candidates `trial_choice` compares go on
            final = [0] + [i for i in trial_finalists(hyps_k, losses) if i is not None]
            for src in dict.fromkeys(i if same_as[i] is None else same_as[i] for i in final):  # each re-fit once
                fits[src], losses[src] = refit(cands[src][4], fits[src], steps - first)
                done[src] = steps
                log(f"hinge trial: object {k + 1}: {trial_name(cands[src][0], cands[src][2])}: loss "
                    f"{losses[src]:.5f} after {steps - first} more steps")
            for i in final:
                if same_as[i] is not None:
                    losses[i], done[i] = losses[same_as[i]], done[same_as[i]]
        best = final[trial_choice([hyps_k[i] for i in final], [losses[i] for i in final], cfg.hinge_trial_margin)]
        replaced = best > 0
        h, kind, ax, pv, pk = cands[best]
        rec = {"candidates": [{"hypothesis": int(c[0]), "kind": c[1],
                               "axis": None if c[2] is None else [float(x) for x in c[2]],
                               "pivot": None if c[3] is None else [float(x) for x in c[3]], "loss": l,
                               "steps": n}
                              for c, l, n in zip(cands, losses, done, strict=True)],
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
            + (f"replaced by the {trial_name(h, ax)}{where}, loss {losses[best]:.5f} against the given poses' "
               f"{losses[0]:.5f}" if replaced else
               f"kept (the given poses' {losses[0]:.5f}, the best candidate's {min(losses):.5f})")
            + f" ({rec['seconds']:.1f} s)")
    return poses, out
