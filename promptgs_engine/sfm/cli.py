"""``promptgs sfm INPUT --out DATASET``: cameras and points from photos or a video.

    promptgs sfm INPUT --out DATASET [--max-image-size PX] [--single-camera | --per-image-camera]
                 [--camera-model MODEL] [--matcher auto|exhaustive|sequential] [--overlap N]
                 [--mapper auto|incremental|global]
                 [--fps F] [--max-frames N] [--min-registered FRACTION] [--overwrite]
                 [--events] [--quiet]

Prints the summary as JSON (also saved as ``DATASET/sfm_summary.json``). A re-run with the
same --out resumes: features and matches already in ``DATASET/colmap/database.db`` are
kept. Exit status 2 with one ``promptgs: error:`` line for bad input.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from .pipeline import CAMERA_MODELS, MAPPERS, SfmOptions


def _size(text: str) -> int | None:
    if text.lower() in ("none", "0", "-1"):
        return None
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of pixels or 'none', got {text!r}") from None


def add_sfm_options(p: argparse.ArgumentParser) -> None:
    """The options `sfm` shares with `train` (which runs sfm on photos or a video)."""
    d = SfmOptions()
    g = p.add_argument_group("structure from motion (photos or a video)")
    g.add_argument("--max-image-size", type=_size, default=d.max_image_size,
                   help=f"longer side (px) of the images features are found on and written at; 'none': as given (default {d.max_image_size})")
    cams = g.add_mutually_exclusive_group()
    cams.add_argument("--single-camera", dest="camera_mode", action="store_const", const="single",
                      help="one camera shared by all images (default for a video, and for photos of one size and focal length)")
    cams.add_argument("--per-image-camera", dest="camera_mode", action="store_const", const="per-image",
                      help="one camera per image (photos from several cameras or zoom settings)")
    g.add_argument("--camera-model", default=d.camera_model, choices=CAMERA_MODELS, metavar="MODEL",
                   help=f"COLMAP camera model the mapper fits (default {d.camera_model}; the output is undistorted to PINHOLE)")
    g.add_argument("--matcher", default=d.matcher, choices=["auto", "exhaustive", "sequential"],
                   help="image pairs to match: every pair, or neighbours in name/time order plus loop pairs (auto: exhaustive up to 150 photos, sequential for more and for a video)")
    g.add_argument("--mapper", default=d.mapper, choices=MAPPERS,
                   help="incremental (COLMAP's), global (GLOMAP's), or auto: incremental, then global when more than 10%% "
                        "of the images are left out, keeping the model with more images (default auto)")
    g.add_argument("--overlap", type=int, default=d.overlap, help=f"sequential: neighbours each image is matched with (default {d.overlap})")
    g.add_argument("--fps", type=float, default=d.fps, help=f"video: frames kept per second, the sharpest of each window (default {d.fps:g})")
    g.add_argument("--max-frames", type=int, help="video: keep at most this many frames")
    g.add_argument("--min-registered", type=float, default=d.min_registered,
                   help=f"fail when fewer than this fraction of the images is registered (default {d.min_registered:g})")
    p.set_defaults(camera_mode="auto")


def sfm_options_from_args(args: argparse.Namespace) -> SfmOptions:
    return SfmOptions(
        max_image_size=args.max_image_size,
        camera_model=args.camera_model,
        camera_mode=args.camera_mode,
        matcher=args.matcher,
        mapper=args.mapper,
        overlap=args.overlap,
        fps=args.fps,
        max_frames=args.max_frames,
        min_registered=args.min_registered,
        num_threads=getattr(args, "sfm_threads", -1),
    )


def add_parser(subparsers: Any) -> None:
    """Register the ``sfm`` subcommand on an argparse subparsers object."""
    p = subparsers.add_parser(
        "sfm",
        help="cameras and points from a folder of photos or a video (pycolmap), written as a dataset to train on",
        description="Structure from motion with pycolmap: SIFT features, matching, incremental or global mapping, undistortion "
        "to PINHOLE. Writes DATASET/images and DATASET/sparse/0 (what `promptgs train` reads) and "
        "DATASET/sfm_summary.json. See docs/sfm.md.",
    )
    p.add_argument("input", type=Path, help="a folder of photos, or a video file")
    p.add_argument("--out", type=Path, required=True, help="dataset folder to write (new, empty, or an earlier sfm output to resume)")
    add_sfm_options(p)
    p.add_argument("--threads", dest="sfm_threads", type=int, default=-1,
                   help="threads for features, matching and mapping (default: every core); with more than one, "
                        "the order in which they finish changes the model slightly from run to run, with 1 it is the same")
    p.add_argument("--overwrite", action="store_true", help="start over: drop the features and matches kept in --out")
    p.add_argument("--events", action="store_true", help="JSON-lines events on stdout (for the Blender add-on), no progress bars")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..events import EventWriter
    from .pipeline import run_sfm

    events = EventWriter.stdout() if args.events else None
    summary = run_sfm(args.input, args.out, sfm_options_from_args(args), overwrite=args.overwrite, events=events, quiet=args.quiet)
    if not args.events:
        print(json.dumps(summary, indent=2))
    return 0
