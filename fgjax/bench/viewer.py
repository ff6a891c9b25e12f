"""``fgjax bench viewer``: the time `fgjax view` takes from a change of a control to the Gaussians ready to send.

    fgjax bench viewer --run RUN [--changes 50] [--seed 0]

On a run with stage 2, each change moves one object's slider (the objects in turn) to a random position along its
trajectory and computes the viewer's Gaussians for the new state (`fgjax.method.splats.viewer_gaussians`: the
controlled scene, activated: centres, covariances, colours, opacities); then as many changes of the time slider
(the stage-1 scene at a random time). Prints the Gaussians and objects, the first call of each kind (it compiles)
and the median, 90th percentile and largest wall time of the rest.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from fgjax.method.result import load_stage2
from fgjax.method.splats import active_slots, viewer_gaussians

__all__ = ["main", "viewer_bench"]


def viewer_bench(run_dir, *, changes: int = 50, seed: int = 0) -> dict:
    """{"gaussians", "objects", "control_first_s", "control_s" [changes], "time_first_s", "time_s" [changes]}."""
    if changes < 1:
        raise ValueError(f"--changes must be >= 1, got {changes}")
    run = load_stage2(run_dir)
    k = run.s2.num_objects
    if k == 0:
        raise ValueError(f"{run_dir}: stage 2 found no objects; nothing to control")
    rng = np.random.default_rng(seed)
    positions = np.zeros(k)

    def timed(time_, controls) -> float:
        t = time.perf_counter()
        viewer_gaussians(run, time_, controls)
        return time.perf_counter() - t

    out = {"gaussians": len(active_slots(run)), "objects": k, "control_first_s": timed(None, positions),
           "time_first_s": timed(0.0, None), "control_s": [], "time_s": []}
    for i in range(changes):
        positions = positions.copy()
        positions[i % k] = rng.uniform()
        out["control_s"].append(timed(None, positions))
    for _ in range(changes):
        out["time_s"].append(timed(float(rng.uniform()), None))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax bench viewer", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="run folder with stage-2 results")
    p.add_argument("--changes", type=int, default=50, help="changes of each kind (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random positions and times")
    args = p.parse_args(argv)
    r = viewer_bench(args.run, changes=args.changes, seed=args.seed)
    print(f"{args.run}: {r['gaussians']} Gaussians, {r['objects']} object(s); {args.changes} changes of each kind")
    for name, label in (("control", "an object's slider (controlled scene)"), ("time", "the time slider (stage 1)")):
        ms = 1000.0 * np.asarray(r[f"{name}_s"])
        print(f"{label}: first {1000.0 * r[f'{name}_first_s']:.0f} ms (compiles); then median {np.median(ms):.1f} ms, "
              f"90th percentile {np.percentile(ms, 90):.1f} ms, largest {ms.max():.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
