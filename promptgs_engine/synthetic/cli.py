"""``promptgs dataset mountain``: generate a synthetic mountain / flames / tiny-drones dataset.

    promptgs dataset mountain --preset tiny|small|paper --out DIR [--seed 0] [--blender PATH]
                              [--samples N] [--views N] [--width W] [--height H] [--drones N]
                              [--drone-groups N] [--flames N] [--min-views N] [--drone-px P]
                              [--min-visible-px P] [--denoise | --no-denoise] [--dry-run]

Exit status 0 on success (also when DIR already holds this very dataset), 2 with one
``error:`` line on stderr for bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ..errors import PromptGSError
from .presets import PRESETS, preset_params


def add_parser(subparsers: Any) -> None:
    """Register the ``dataset`` subcommand on an argparse subparsers object."""
    p = subparsers.add_parser(
        "dataset",
        help="generate a synthetic dataset (mountain terrain, flames, tiny drones) with Blender",
        description="Render a synthetic mountain / flames / tiny-drones dataset with Blender (Cycles, CPU) and "
        "build its COLMAP model (known poses, SIFT points triangulated with pycolmap). See docs/dataset.md.",
    )
    p.add_argument("kind", help="dataset kind: mountain")
    p.add_argument("--preset", default="small", help=f"parameter preset: {', '.join(PRESETS)} (default small)")
    p.add_argument("--out", type=Path, help="output folder (new or empty)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the layout and the renderer (default 0)")
    p.add_argument("--blender", help="Blender binary to run (default: the bpy module of this Python)")
    p.add_argument("--samples", type=int, help="Cycles samples per pixel")
    p.add_argument("--views", type=int, help="number of views, spread over the preset's camera rings")
    p.add_argument("--width", type=int, help="image width in pixels")
    p.add_argument("--height", type=int, help="image height in pixels")
    p.add_argument("--drones", type=int, help="number of drones")
    p.add_argument("--drone-groups", type=int, help="number of drone groups (one prompt box each)")
    p.add_argument("--flames", type=int, help="number of flames")
    p.add_argument("--min-views", type=int, help="training views that must see every drone")
    p.add_argument("--drone-px", type=float, help="largest drone size in px at 1080p (at most 10, the paper's limit)")
    p.add_argument("--min-visible-px", type=float, help="smallest size (px) at which a view counts as seeing a drone")
    p.add_argument("--denoise", action=argparse.BooleanOptionalAction, default=None, help="OpenImageDenoise on the renders")
    p.add_argument("--dry-run", action="store_true", help="print the layout part of scene.json; render nothing")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _split_views(rings: list[dict[str, Any]], n: int) -> list[dict[str, Any]]:
    """Spread n views over the rings in proportion to their preset counts."""
    total = sum(int(r["count"]) for r in rings)
    counts = [int(n * int(r["count"]) // total) for r in rings]
    counts[0] += n - sum(counts)
    return [dict(r, count=c) for r, c in zip(rings, counts) if c > 0] or [dict(rings[0], count=0)]


def params_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The full parameter set: the preset with the command-line overrides."""
    if args.kind != "mountain":
        raise PromptGSError(f"unknown dataset kind '{args.kind}' (available: mountain)")
    if args.preset not in PRESETS:
        raise PromptGSError(f"unknown preset '{args.preset}' (choose {', '.join(PRESETS)})")
    params = preset_params(args.preset)
    params["seed"] = int(args.seed)
    overrides = {
        "samples": args.samples,
        "width": args.width,
        "height": args.height,
        "n_drones": args.drones,
        "n_drone_groups": args.drone_groups,
        "n_flames": args.flames,
        "min_views": args.min_views,
        "drone_max_px_1080": args.drone_px,
        "min_visible_px": args.min_visible_px,
        "denoise": args.denoise,
    }
    params.update({k: v for k, v in overrides.items() if v is not None})
    if args.drones is not None and args.drone_groups is None:
        params["n_drone_groups"] = max(1, min(params["n_drone_groups"], args.drones))
    if args.views is not None:
        if args.views < 1:
            raise PromptGSError(f"--views {args.views}: zero views, need at least 1")
        params["camera_rings"] = _split_views(params["camera_rings"], args.views)
    return params


def run(args: argparse.Namespace) -> int:
    """Run ``promptgs dataset``; returns the exit status."""
    from .generate import dry_run, generate

    try:
        params = params_from_args(args)
        if args.dry_run:
            record = dry_run(params, args.blender)
            print(json.dumps(record, indent=1))
            return 0
        if args.out is None:
            raise PromptGSError("--out is required (the folder to write the dataset into)")
        record = generate(params, args.out, args.blender, show_progress=not args.quiet)
    except PromptGSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if record is None:
        print(f"{args.out}: already holds this dataset (same preset, seed and parameters); nothing to do")
        return 0
    sfm = record["sfm"]
    near = [d["sfm_points_within_radius"] for d in record["drones"]]
    print(
        f"{args.out}: {len(record['cameras'])} views ({len(record['test_images'])} test), "
        f"{len(record['drones'])} drones, {len(record['flames'])} flames, {sfm['n_points']} SfM points "
        f"({sfm['n_on_terrain']} on the terrain, {sum(near)} within drone radii), "
        f"{record['timings']['total_s']:.0f} s"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="promptgs")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args))
