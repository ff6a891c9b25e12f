"""``fgjax bench opticalflow``: end-point error against ground truth and run time per method.

Datasets (under ``--data``, default ``../shared/data`` next to the repository):

- ``middlebury/<Seq>/{frame10.png, frame11.png, flow10.flo}``: EPE over pixels with known flow.
- ``sintel/<scene>/{frame_NNNN.png, gt/frame_NNNN.flo, gt/occlusions/frame_NNNN.png,
  gt/invalid/frame_NNNN.png}``: EPE over non-occluded, valid pixels (flow NNNN -> NNNN+1).

Timing: for each pair the methods run in turn, `--repeats` times (interleaved, so that load on a
shared machine hits them alike); a method's time on a pair is the median of its repeats, and the
table shows the mean of those over the pairs. EPE comes from the first run (all backends are
deterministic for a fixed thread count).

``--record PATH`` writes the table, command, date and machine into PATH between the markers
``<!-- bench:opticalflow:start -->`` and ``<!-- bench:opticalflow:end -->`` (appended if absent),
atomically.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import shlex
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from fgjax.data import flowio as fio
from fgjax.data import opticalflow as of
from fgjax.io import atomic_write

DEFAULT_SPECS = (
    "dis_deepflow",
    "deepflow",
    "dis",
    "dis:finest_scale=1",
    "tvl1",
    "rlof",
    "rlof:use_variational_refinement=true",
    "farneback",
)
MARK_START = "<!-- bench:opticalflow:start -->"
MARK_END = "<!-- bench:opticalflow:end -->"


@dataclasses.dataclass(frozen=True)
class _Pair:
    dataset: str
    name: str
    image0: np.ndarray
    image1: np.ndarray
    gt: np.ndarray
    valid: np.ndarray  # [H, W] bool: pixels scored


def _default_data_dir() -> Path:
    env = os.environ.get("FGJAX_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "data"


def _load_pairs(data: Path) -> list[_Pair]:
    pairs = []
    mb = data / "middlebury"
    if mb.is_dir():
        for seq in sorted(p for p in mb.iterdir() if (p / "flow10.flo").is_file()):
            gt = fio.read_flo(seq / "flow10.flo")
            pairs.append(_Pair("middlebury", seq.name, fio.read_image(seq / "frame10.png"),
                               fio.read_image(seq / "frame11.png"), gt, fio.flow_valid_mask(gt)))
    si = data / "sintel"
    if si.is_dir():
        for scene in sorted(p for p in si.iterdir() if (p / "gt").is_dir()):
            for flo in sorted((scene / "gt").glob("frame_*.flo")):
                k = int(flo.stem.split("_")[1])
                f0, f1 = scene / f"frame_{k:04d}.png", scene / f"frame_{k + 1:04d}.png"
                if not (f0.is_file() and f1.is_file()):
                    continue
                gt = fio.read_flo(flo)
                valid = fio.flow_valid_mask(gt)
                for sub in ("occlusions", "invalid"):
                    m = scene / "gt" / sub / f"{flo.stem}.png"
                    if m.is_file():
                        valid &= cv2.imread(str(m), cv2.IMREAD_GRAYSCALE) == 0
                pairs.append(_Pair("sintel", f"{scene.name}/{flo.stem}", fio.read_image(f0), fio.read_image(f1),
                                   gt, valid))
    return pairs


def _parse_spec(spec: str) -> tuple[str, dict[str, str]]:
    method, *items = spec.split(":")
    overrides = {}
    for item in items:
        k, sep, v = item.partition("=")
        if not sep:
            raise ValueError(f"--method {spec!r}: expected METHOD[:key=value[:key=value...]]")
        overrides[k] = v
    of.resolve_params(method, overrides)  # validate now, before any timing
    return method, overrides


def _epe(flow: np.ndarray, pair: _Pair) -> float:
    return float(np.linalg.norm(flow - pair.gt, axis=-1)[pair.valid].mean())


def run(specs, pairs, repeats: int, log=sys.stderr) -> dict:
    """{spec: {"epe": {pair: e}, "time": {pair: median s}}}."""
    parsed = {s: _parse_spec(s) for s in specs}
    res = {s: {"epe": {}, "time": {}} for s in specs}
    for pair in pairs:
        key = f"{pair.dataset}/{pair.name}"
        times = {s: [] for s in specs}
        for r in range(repeats):
            for s, (method, overrides) in parsed.items():
                t0 = time.perf_counter()
                flow = of.estimate_flow(pair.image0, pair.image1, method, overrides)
                times[s].append(time.perf_counter() - t0)
                if r == 0:
                    res[s]["epe"][key] = _epe(flow, pair)
                if log is not None:
                    print(f"[bench] {key} repeat {r + 1}/{repeats} {s}: {times[s][-1]:.3f} s", file=log, flush=True)
        for s in specs:
            res[s]["time"][key] = statistics.median(times[s])
    return res


def _table(res: dict, pairs: list[_Pair]) -> list[str]:
    datasets = sorted({p.dataset for p in pairs}, key=["middlebury", "sintel"].index)
    head = ["method"]
    for d in datasets:
        names = [p.name for p in pairs if p.dataset == d]
        label = "Middlebury" if d == "middlebury" else "Sintel clean, non-occluded"
        per = f"; {' / '.join(names)}" if len(names) > 1 else f" ({names[0]})"
        head += [f"{label} EPE (mean{per})" if len(names) > 1 else f"{label} EPE{per}", f"{label} s/pair"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for spec, r in res.items():
        row = [f"`{spec}`" + (" (default)" if spec == of.DEFAULT_METHOD else "")]
        for d in datasets:
            keys = [f"{p.dataset}/{p.name}" for p in pairs if p.dataset == d]
            e = f"{np.mean([r['epe'][k] for k in keys]):.4f}"
            if len(keys) > 1:
                e += " (" + " / ".join(f"{r['epe'][k]:.3f}" for k in keys) + ")"
            row += [e, f"{np.mean([r['time'][k] for k in keys]):.3f}"]
        lines.append("| " + " | ".join(row) + " |")
    return lines


def _verdict(res: dict, pairs: list[_Pair]) -> str | None:
    keys = [f"{p.dataset}/{p.name}" for p in pairs if p.dataset == "middlebury"]
    if not keys or of.DEFAULT_METHOD not in res or "deepflow" not in res:
        return None
    e_d, t_d = (np.mean([res[of.DEFAULT_METHOD][f][k] for k in keys]) for f in ("epe", "time"))
    e_r, t_r = (np.mean([res["deepflow"][f][k] for k in keys]) for f in ("epe", "time"))
    ok = e_d <= e_r and t_d <= t_r
    return (f"Default `{of.DEFAULT_METHOD}` vs `deepflow` on Middlebury: EPE {e_d:.4f} vs {e_r:.4f}, "
            f"{t_d:.3f} vs {t_r:.3f} s/pair ({t_r / t_d:.1f}x faster): {'OK' if ok else 'NOT MET'}")


def _machine() -> str:
    return (f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPUs visible, OpenCV {cv2.__version__} "
            f"({cv2.getNumThreads()} threads), Python {platform.python_version()}")


def _record(path: Path, block: str) -> None:
    text = path.read_text() if path.exists() else ""
    section = f"{MARK_START}\n{block.rstrip()}\n{MARK_END}"
    if MARK_START in text and MARK_END in text:
        a, rest = text.split(MARK_START, 1)
        _, b = rest.split(MARK_END, 1)
        new = a + section + b
    else:
        new = (text.rstrip() + "\n\n" if text.strip() else "") + section + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    data = new.encode()
    atomic_write(path, lambda f: f.write(data))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="fgjax bench opticalflow", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=None,
                    help="shared data folder (default: ../shared/data or $FGJAX_SHARED_DATA)")
    ap.add_argument("--method", action="append", dest="specs", metavar="METHOD[:k=v...]",
                    help=f"method with optional overrides, repeatable (default: {', '.join(DEFAULT_SPECS)})")
    ap.add_argument("--repeats", type=int, default=3,
                    help="timed runs per method and pair; the median counts (default 3)")
    ap.add_argument("--datasets", default="middlebury,sintel", help="comma-separated subset (default: both)")
    ap.add_argument("--record", type=Path, metavar="PATH", help="write the results section into this markdown file")
    ap.add_argument("--machine", default=None, help="machine description for --record (default: detected)")
    ap.add_argument("--quiet", action="store_true", help="no per-run progress lines")
    args = ap.parse_args(argv)
    argv_used = sys.argv[1:] if argv is None else argv
    try:
        if args.repeats < 1:
            raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
        specs = args.specs or list(DEFAULT_SPECS)
        for s in specs:
            _parse_spec(s)
        data = args.data or _default_data_dir()
        if not data.is_dir():
            raise FileNotFoundError(f"--data {data}: no such folder "
                                    "(expected ../shared/data with middlebury/ and sintel/)")
        wanted = {d.strip() for d in args.datasets.split(",") if d.strip()}
        pairs = [p for p in _load_pairs(data) if p.dataset in wanted]
        if not pairs:
            raise FileNotFoundError(f"--data {data}: no ground-truth pairs found for {sorted(wanted)}")
    except (ValueError, FileNotFoundError) as e:
        print(f"fgjax bench opticalflow: error: {e}", file=sys.stderr)
        return 2
    res = run(specs, pairs, args.repeats, log=None if args.quiet else sys.stderr)
    lines = _table(res, pairs)
    verdict = _verdict(res, pairs)
    print("\n".join(lines))
    if verdict:
        print("\n" + verdict)
    if args.record:
        cmd = "fgjax bench opticalflow " + " ".join(shlex.quote(a) for a in argv_used)
        block = "\n".join([
            "## Optical flow (`fgjax bench opticalflow`)",
            "",
            f"- Date: {datetime.date.today().isoformat()}",
            f"- Machine: {args.machine or _machine()}",
            f"- Command: `{cmd.strip()}`",
            f"- Time: median of {args.repeats} interleaved runs per pair, mean over pairs; includes the RGB -> grey "
            "conversion. EPE: mean end-point error (px) over pixels with known flow "
            "(Sintel: also non-occluded, valid).",
            "",
            *lines,
            "",
            *([verdict, ""] if verdict else []),
        ])
        _record(args.record, block)
        print(f"\nrecorded in {args.record}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
