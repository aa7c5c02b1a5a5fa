"""``promptgs export``: a run's Gaussians, or any PLY, SPZ or glTF file, written as another format."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import PromptGSError
from . import DEFAULT_SUFFIX, FORMATS, SPZ_SH_BITS, format_of, read_splats, save_gaussians

RUN_PLY = "point_cloud.ply"


def add_parser(sub) -> None:
    p = sub.add_parser("export", help="write a run's Gaussians (or a PLY, SPZ or glTF file) as SPZ, glTF or PLY")
    p.add_argument("source", type=Path, help="a run folder (its point_cloud.ply) or a .ply, .spz, .gltf or .glb file")
    p.add_argument("--format", choices=FORMATS, help="spz, gltf (.glb; a .gltf --out writes JSON with the buffer embedded) or ply; default: from --out")
    p.add_argument("--out", type=Path, help="file to write (default: beside the source, with the format's suffix)")
    p.add_argument("--sh-degree", type=int, help="keep SH up to this degree (0..3; default: all the source has)")
    p.add_argument("--spz-version", type=int, choices=(3, 4), default=3,
                   help="SPZ 3 (gzip; every SPZ reader) or 4 (zstd, a stream per attribute; the default of Niantic's library since March 2026)")
    p.add_argument("--spz-sh-bits", type=_sh_bits, default=SPZ_SH_BITS, metavar="B1,B2",
                   help="significant bits of SPZ's SH codes, degree 1 and degrees 2-3 (default 8,8; Niantic's library: 5,4, "
                   "smaller files and a visible loss: benchmarks/formats.py)")
    p.set_defaults(func=cmd_export)


def _sh_bits(text: str) -> tuple[int, int]:
    try:
        first, rest = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two whole numbers like 8,8, got {text!r}") from None
    if not (1 <= first <= 8 and 1 <= rest <= 8):
        raise argparse.ArgumentTypeError(f"SH bits are 1..8, got {text!r}")
    return first, rest


def _source(source: Path) -> tuple[Path, bool]:
    """The Gaussian file of ``source`` and whether it was trained antialiased (a run's setting)."""
    if source.is_dir():
        from ..config import TrainConfig

        if not (source / "cfg.json").is_file():
            raise PromptGSError(f"{source}: not a PromptGS run folder (no cfg.json)")
        if not (source / RUN_PLY).is_file():
            raise PromptGSError(f"{source}: no {RUN_PLY} yet (the run has not finished)")
        return source / RUN_PLY, TrainConfig.load(source / "cfg.json").antialiased
    if not source.is_file():
        raise PromptGSError(f"{source}: no such run folder or file")
    format_of(source)
    return source, False


def cmd_export(args: argparse.Namespace) -> int:
    path, antialiased = _source(args.source)
    kind = args.format or (format_of(args.out) if args.out is not None else None)
    if kind is None:
        raise PromptGSError("export needs --format (spz, gltf or ply) or an --out file name")
    out = args.out or path.with_suffix(DEFAULT_SUFFIX[kind])
    if format_of(out) != kind:
        raise PromptGSError(f"{out}: the name does not fit --format {kind} (use {DEFAULT_SUFFIX[kind]})")
    if out.resolve() == path.resolve():
        raise PromptGSError(f"{path} is already {kind}: give another --out")
    splats = read_splats(path)
    splats.antialiased = splats.antialiased or antialiased
    if args.sh_degree is not None and args.sh_degree > splats.sh_degree:
        raise PromptGSError(f"{path} has SH up to degree {splats.sh_degree}, not {args.sh_degree}")
    save_gaussians(out, splats, kind, sh_degree=args.sh_degree, spz_version=args.spz_version, spz_sh_bits=args.spz_sh_bits)
    size = out.stat().st_size
    print(f"wrote {out}: {splats.n} Gaussians, {size:,} bytes ({size / max(splats.n, 1):.1f} a Gaussian)")
    return 0
