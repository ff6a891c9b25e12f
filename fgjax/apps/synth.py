"""``fgjax synth``: generate a synthetic articulated scene with ground truth (`fgjax.synth.generate`)."""

from __future__ import annotations

import argparse
import contextlib
import sys

from fgjax.synth import MAX_OBJECTS, OBJECT_KINDS, SynthConfig, family_config, generate

__all__ = ["config_from_args", "main"]


def _parser() -> argparse.ArgumentParser:
    d = SynthConfig()
    p = argparse.ArgumentParser(prog="fgjax synth", description="Generate a synthetic articulated scene with "
                                "ground truth (depth, flow, object ids, states, centres).",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", required=True, help="output folder (must be absent or empty unless --overwrite)",
                   default=argparse.SUPPRESS)
    p.add_argument("--objects", default=",".join(d.objects),
                   help=f"comma-separated kinds from {{{','.join(OBJECT_KINDS)}}}, at most {MAX_OBJECTS}")
    p.add_argument("--family", type=int, default=None, metavar="SEED",
                   help="a scene of the random family (fgjax.synth.family): the seed draws the parts, joints, "
                        "colours, schedules, camera path, resolution and frame count; --width/--height/--frames "
                        "override the last three, and the other scene options do not apply")
    p.add_argument("--width", type=int, default=None, help=f"image width in pixels (default {d.width})")
    p.add_argument("--height", type=int, default=None, help=f"image height in pixels (default {d.height})")
    p.add_argument("--frames", type=int, default=None, help=f"number of training frames (default {d.frames})")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of every random choice")
    p.add_argument("--pose-noise-deg", type=float, default=d.pose_noise_deg,
                   help="std of rotation noise on the written training poses (degrees)")
    p.add_argument("--pose-noise-trans", type=float, default=d.pose_noise_trans,
                   help="std of translation noise on the written training poses (fraction of scene size 3.2)")
    p.add_argument("--lighting-change", type=float, nargs="?", const=0.3, default=d.lighting_change,
                   help="brightness drop over the sequence (flag alone: 0.3)")
    p.add_argument("--close-pair", action="store_true", help="put objects 1 and 2 side by side, --close-gap apart")
    p.add_argument("--close-gap", type=float, default=d.close_gap, help="gap of the close pair (scene units)")
    p.add_argument("--test-views", type=int, default=d.test_views,
                   help="test frames from other camera positions at training times")
    p.add_argument("--test-states", type=int, default=d.test_states,
                   help="test frames with object-state combinations unseen in training")
    p.add_argument("--depth-maps", action="store_true",
                   help="also write each frame's depth as a measured one (depth/<frame>.npy: an RGB-D scene)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    """SynthConfig from parsed `fgjax synth` arguments (ValueError on bad values)."""
    d = SynthConfig()
    if args.family is not None:
        if (args.width is None) != (args.height is None):
            raise ValueError("--family: give both --width and --height, or neither (the seed's own size)")
        size = None if args.width is None else (args.width, args.height)
        return family_config(args.family, size=size, frames=args.frames, depth_maps=args.depth_maps)
    objs = tuple(o.strip() for o in str(args.objects).split(",") if o.strip())
    return SynthConfig(
        objects=objs, width=d.width if args.width is None else args.width,
        height=d.height if args.height is None else args.height,
        frames=d.frames if args.frames is None else args.frames, seed=args.seed,
        pose_noise_deg=args.pose_noise_deg, pose_noise_trans=args.pose_noise_trans,
        lighting_change=args.lighting_change, close_pair=args.close_pair, close_gap=args.close_gap,
        test_views=args.test_views, test_states=args.test_states, depth_maps=args.depth_maps,
    )


def main(argv: list[str] | None = None) -> int:
    """``fgjax synth``: generate a scene; prints where things went. Returns the exit status."""
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        cfg = config_from_args(args)
    except ValueError as e:
        print(f"fgjax synth: error: {e}", file=sys.stderr)
        return 2
    say = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    try:
        out = generate(cfg, args.out, overwrite=args.overwrite, progress=say)
    except (FileExistsError, ValueError) as e:
        print(f"fgjax synth: error: {e}", file=sys.stderr)
        return 2
    print(f"scene:        {out}")
    print(f"train:        {out / 'transforms_train.json'}")
    if (out / "transforms_test.json").exists():
        print(f"test:         {out / 'transforms_test.json'}")
    print(f"images:       {out / 'images'}")
    print(f"ground truth: {out / 'gt'} (see gt/meta.json)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
