"""``fgjax bench placement``: which parts the flow placement of the motion bases finds, by the frame spans it reads.

The placement (`fgjax.method.bases_init`, ``deform.init = "flow"``) marks a pixel as moving where the observed
optical flow u and the camera flow u_cam of a frame pair differ by more than 1 px, over the pairs ``deform.spans``
frames apart in time. On scenes with ground truth (``fgjax synth``: gt/train/depth.npy, object_id.npy, states.npy,
viewmats_true.npy) and for each set of spans in ``--spans`` (sets separated by ";", e.g. "1;1,2,4") it prints:

- ``pixels``: the share of each part's pixels, in the frame pairs over which the part's state changes, where
  |u - u_cam| > 1 px with u_cam from the true depth and poses (`fgjax.method.discover.camera_flow_from_depth`) and u
  the estimated optical flow (``flow.method``): the evidence the placement could read with a perfect model. A set of
  spans marks a pixel of source frame a where any of its pairs starting at a does; a part counts at a where its
  state changes over the longest of those pairs. Beside it the share of static pixels marked (``static``);
- ``placed``: stage 1 of the configuration (``--config`` and ``--set``) trained to the end of its warm-up, then the
  placement: the share of each part's Gaussians that it frees (a moving cluster or DBSCAN's noise), where a part's
  Gaussians are those that paint mostly its pixels in the training frames (`painted_parts`; their number is printed
  as ``of``), the number of other Gaussians freed (``others``: Gaussians that paint mostly static pixels) and the
  placement's time; with ``--shares``, for each ``deform.camera_share`` listed (the floor growing with the camera
  flow, 1 px + share |u_cam|) and, with ``--vary``, each value of another setting. Beside it, per part, the moving
  cluster that holds most of its Gaussians and their share in it (`part_clusters`): two parts with the same cluster
  share one basis, which one rigid motion cannot fit.

Results: docs/benchmarks.md, "The placement's frame spans", "A floor that grows with the camera flow" and "Which
parts share a cluster".
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from fgjax import config as C
from fgjax.data.loaders import load_scene
from fgjax.gaussians import activate
from fgjax.geometry import viewmat_to_c2w
from fgjax.io import atomic_write
from fgjax.method import stage1
from fgjax.method.bases_init import place_bases
from fgjax.method.discover import accumulate_scores, camera_flow_from_depth
from fgjax.method.flows import estimate_training_flows, previous_frames

__all__ = ["main", "painted_parts", "part_clusters", "pixel_evidence", "placed_shares"]

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "experiments" / "family.toml"


def pixel_evidence(scene_dir: Path, span_sets: list[tuple[int, ...]], method: str = "dis_deepflow",
                   threshold_px: float = 1.0) -> list[dict]:
    """The ``pixels`` measurement (module docstring) for each set of spans: {"spans", "parts" [K], "static"}."""
    gt = Path(scene_dir) / "gt" / "train"
    sc = load_scene(scene_dir, "train")
    times = np.load(gt / "times.npy")
    if not np.allclose(np.asarray(sc.times), times, atol=1e-5):
        raise ValueError(f"{gt / 'times.npy'} does not list the training frames in the order of the scene's")
    depth, oid, states = np.load(gt / "depth.npy"), np.load(gt / "object_id.npy"), np.load(gt / "states.npy")
    Ks, c2w = np.load(gt / "Ks.npy"), viewmat_to_c2w(np.load(gt / "viewmats_true.npy"))
    order = np.argsort(times, kind="stable")
    hits: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, int]] = {}
    for span in sorted({s for ss in span_sets for s in ss}):
        prev = previous_frames(sc.times, span)
        flows = estimate_training_flows(sc, method, log=lambda *_: None, span=span)  # the placement's own flows
        for i in np.flatnonzero(prev >= 0).tolist():
            a, u = int(prev[i]), flows[i]
            u_cam, ok = camera_flow_from_depth(depth[a], Ks[a], c2w[a], c2w[i])
            ok = ok & (depth[a] > 0)
            hits[(span, a)] = ((np.linalg.norm(u - u_cam, axis=-1) > threshold_px) & ok, ok, i)
    out = []
    for spans in span_sets:
        num, den = np.zeros(states.shape[1]), np.zeros(states.shape[1])
        fp, ns = 0, 0
        for a in order.tolist():
            here = [s for s in spans if (s, a) in hits]
            if not here:
                continue
            hit = np.any([hits[(s, a)][0] for s in here], axis=0)
            ok = np.any([hits[(s, a)][1] for s in here], axis=0)
            i = hits[(max(here), a)][2]
            fp, ns = fp + int(np.sum(hit & ok & (oid[a] == 0))), ns + int(np.sum(ok & (oid[a] == 0)))
            for k in np.flatnonzero(np.abs(states[i] - states[a]) > 1e-4):
                m = ok & (oid[a] == k + 1)
                num[k], den[k] = num[k] + np.sum(hit & m), den[k] + np.sum(m)
        out.append({"spans": list(spans), "parts": [float(x / d) if d else float("nan") for x, d in zip(num, den)],
                    "static": float(fp / ns) if ns else float("nan")})
    return out


def painted_parts(params, alive, scene, gt: Path, *, capacity: int, share: float = 0.5) -> list[np.ndarray]:
    """Per part (gt/meta.json order), the indices of the live Gaussians of which more than ``share`` of what they
    paint over the training frames lies on that part's pixels:

        sum_t w_i(m_kt) / (sum_t w_i(1) + 0.1) > share,

    with w_i(m) = sum_p m_p T_ip alpha_ip the rasterizer's compositing weights (`fgjax.method.discover.
    accumulate_scores`), m_kt the pixels of part k in training frame t (``gt/train/object_id.npy`` equal to its
    label), the canonical Gaussians of ``params`` (no deformation: what the placement reads) and the training cameras
    of ``scene``. With ``share`` >= 0.5 a Gaussian belongs to one part at most. These are the Gaussians that render
    the part, wherever the model put them in depth; `fgjax.bench.motion.part_gaussians` (centres within 0.05 scene
    units of the true surface) counts only those already on it, a few dozen per part on a warm-up model."""
    oid = np.load(gt / "train" / "object_id.npy")
    if oid.shape != (len(scene.times), scene.height, scene.width):
        raise ValueError(f"{gt / 'train' / 'object_id.npy'} has shape {oid.shape}, the training frames are "
                         f"{(len(scene.times), scene.height, scene.width)}")
    quats, scales, opac = activate(params["gaussians"], alive)
    args = (np.asarray(params["gaussians"].means), np.asarray(quats), np.asarray(scales), np.asarray(opac),
            np.asarray(scene.viewmats, np.float32), np.asarray(scene.Ks, np.float32))
    live = np.asarray(alive, bool)
    out = []
    for o in json.loads((gt / "meta.json").read_text())["objects"]:
        sc = accumulate_scores(*args, oid == o["label"], capacity=capacity)
        out.append(np.flatnonzero(live & (sc.score > share)))
    return out


def part_clusters(labels: np.ndarray, parts: list[np.ndarray]) -> tuple[list[int], list[float]]:
    """Per part (its Gaussians' indices in ``parts``), the moving cluster of the placement's ``labels`` [N]
    (`fgjax.method.bases_init.moving_clusters`: j >= 0 a cluster, negative none) that holds most of the part's
    Gaussians (-1: none of them is in a cluster) and the share of the part's Gaussians in it (NaN for a part with
    no Gaussians). Ties go to the lower cluster index (the larger cluster)."""
    labels = np.asarray(labels)
    clusters, shares = [], []
    for p in parts:
        lab = labels[np.asarray(p, np.int64)]
        lab = lab[lab >= 0]
        if not len(lab):
            clusters.append(-1)
            shares.append(0.0 if len(p) else float("nan"))
            continue
        c = int(np.argmax(np.bincount(lab)))
        clusters.append(c)
        shares.append(float(np.sum(lab == c) / len(p)))
    return clusters, shares


def placed_shares(cfg: C.Config, scene_dir: Path, span_sets: list[tuple[int, ...]],
                  camera_shares: list[float] | None = None, variants: list[list[str]] | None = None
                  ) -> tuple[list[dict], float]:
    """The ``placed`` measurement (module docstring) for each set of spans, each ``deform.camera_share`` in
    ``camera_shares`` (None: the configuration's) and each list of overrides in ``variants`` (None: none), on one
    warm-up model; and the warm-up's time (s)."""
    scene = load_scene(scene_dir, "train")
    t0 = time.perf_counter()
    res = stage1.train_stage1(cfg, scene, None, stop_at=cfg.train.warmup_steps, progress=False, log=lambda *_: None)
    warm = time.perf_counter() - t0
    st, spec = res["state"], res["spec"]
    alive = np.asarray(st.densify.alive)
    parts = painted_parts(st.params, alive, scene, Path(scene_dir) / "gt", capacity=st.capacity)
    on_part = np.zeros(len(alive), bool)
    for p in parts:
        on_part[p] = True
    out = []
    for spans, share, extra in ((a, b, c) for a in span_sets for b in camera_shares or [cfg.deform.camera_share]
                                for c in variants or [[]]):
        c2 = C.apply_overrides(cfg, [f"deform.spans={','.join(map(str, spans))}", f"deform.camera_share={share}",
                                     *extra])
        t1 = time.perf_counter()
        _, labels = place_bases(c2, st.params, st.densify.alive, spec, scene, None, capacity=st.capacity,
                                log=lambda *_: None)
        free = (labels >= 0) | ((labels == -1) & alive)
        cl, in_cl = part_clusters(labels, parts)
        out.append({"spans": list(spans), "camera_share": share, "vary": list(extra),
                    "parts": [float(free[p].mean()) if len(p) else float("nan") for p in parts],
                    "part_cluster": cl, "in_cluster": in_cl,
                    "part_size": [len(p) for p in parts],
                    "others": int(np.sum(free & alive & ~on_part)), "clusters": int(labels.max()) + 1,
                    "seconds": time.perf_counter() - t1})
    return out, warm


def _spans(text: str) -> list[tuple[int, ...]]:
    try:
        sets = [tuple(int(x) for x in part.split(",")) for part in text.split(";") if part.strip()]
    except ValueError:
        sets = []
    if not sets or any(not s or min(s) < 1 for s in sets):
        raise SystemExit(f"fgjax bench placement: --spans must look like '1;1,2,4' (frame spans >= 1); got {text!r}")
    return sets


def _variants(vary: list[str]) -> list[list[str]]:
    """Every combination of the ``--vary`` values, as override lists: ["a=1;2", "b=x"] -> [["a=1", "b=x"],
    ["a=2", "b=x"]]; no ``--vary``: one empty list."""
    out: list[list[str]] = [[]]
    for v in vary:
        key, _, values = v.partition("=")
        vals = [x.strip() for x in values.split(";") if x.strip()]
        if not key.strip() or not vals:
            raise ValueError(f"--vary must look like 'deform.place_window=0;3'; got {v!r}")
        out = [[*a, f"{key.strip()}={x}"] for a in out for x in vals]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench placement", description=__doc__.splitlines()[0])
    p.add_argument("--data", action="append", required=True, help="scene folder with gt/ (repeatable)")
    p.add_argument("--spans", default="1;1,2,4", help="sets of frame spans, ';'-separated (default: %(default)s)")
    p.add_argument("--shares", default=None, help="deform.camera_share values of the placement, ';'-separated "
                   "(default: the configuration's)")
    p.add_argument("--vary", action="append", default=[], metavar="SECTION.KEY=A;B",
                   help="measure the placement at each of these values of a setting (repeatable: every combination)")
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="named configuration (default: %(default)s)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    p.add_argument("--pixels-only", action="store_true", help="skip the warm-up and the placement")
    p.add_argument("--json", default=None, help="write the rows here too")
    args = p.parse_args(argv)
    span_sets = _spans(args.spans)
    try:
        shares = None if args.shares is None else [float(x) for x in args.shares.split(";") if x.strip()]
    except ValueError:
        shares = []
    if shares is not None and (not shares or not all(np.isfinite(x) and x >= 0 for x in shares)):
        print(f"fgjax bench placement: --shares must look like '0;0.1' (numbers >= 0); got {args.shares!r}",
              file=sys.stderr)
        return 2
    try:
        variants = _variants(args.vary)
    except ValueError as e:
        print(f"fgjax bench placement: {e}", file=sys.stderr)
        return 2
    cfg = C.load_config(args.config, args.overrides)
    for extra in variants:  # a bad value is refused before any training, naming the key
        C.apply_overrides(cfg, extra)
    if not args.pixels_only and (cfg.deform.kind, cfg.deform.init) != ("bases", "flow"):
        print("fgjax bench placement: the placement needs deform.kind = 'bases' and deform.init = 'flow' (pass "
              "--set deform.kind=bases --set deform.init=flow, or --pixels-only)", file=sys.stderr)
        return 2
    rows = []
    for d in args.data:
        scene_dir = Path(d)
        if not (scene_dir / "gt" / "train" / "object_id.npy").is_file():
            print(f"fgjax bench placement: {scene_dir / 'gt/train/object_id.npy'} is missing (a scene of "
                  "`fgjax synth` has it)", file=sys.stderr)
            return 2
        t0 = time.perf_counter()
        row = {"data": str(scene_dir), "pixels": pixel_evidence(scene_dir, span_sets, cfg.flow.method)}
        row["pixels_seconds"] = time.perf_counter() - t0
        if not args.pixels_only:
            row["placed"], row["warmup_seconds"] = placed_shares(cfg, scene_dir, span_sets, shares, variants)
        rows.append(row)
        fmt = lambda xs: " ".join(f"{x:.2f}" for x in xs)
        print(f"{scene_dir}:")
        for e in row["pixels"]:
            print(f"  spans {','.join(map(str, e['spans'])):<8} pixels {fmt(e['parts'])} (static {e['static']:.3f})")
        for e in row.get("placed", []):
            print(f"  spans {','.join(map(str, e['spans'])):<8} share {e['camera_share']:<5g} "
                  f"{' '.join(e['vary']) + ' ' if e['vary'] else ''}placed {fmt(e['parts'])} "
                  f"of {' '.join(map(str, e['part_size']))} (others {e['others']}, {e['clusters']} clusters, "
                  f"{e['seconds']:.1f} s); part clusters "
                  f"{' '.join(map(str, e['part_cluster']))} holding {fmt(e['in_cluster'])}")
        print(f"  time: pixels {row['pixels_seconds']:.1f} s"
              + (f", warm-up {row['warmup_seconds']:.1f} s" if "warmup_seconds" in row else ""), flush=True)
    if args.json:
        atomic_write(Path(args.json), lambda f: f.write(json.dumps(rows, indent=1).encode()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
