"""The promptgs command line: train, eval, render, export, propose, sfm, demo, dataset, bench, report, stability.

Bad input ends with a one-line ``promptgs: error: …`` on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path

from . import __version__
from .errors import PromptGSError


def _budget(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number or 'auto', got {text!r}") from None


def _add_train(sub) -> None:
    p = sub.add_parser("train", help="train Gaussians on a COLMAP dataset, or on photos or a video (sfm runs first)")
    p.add_argument("dataset", nargs="?", help="dataset folder (images/ and sparse/0/), or a folder of photos or a video: sfm runs first into OUT/sfm")
    p.add_argument("--out", help="run folder to write")
    p.add_argument("--job", type=Path, help="JSON job file; its keys are these options (command-line options win)")
    p.add_argument("--images", help="images folder name inside the dataset (default: images)")
    p.add_argument("--iterations", type=int)
    p.add_argument("--backend", choices=["auto", "cpu", "cuda"])
    p.add_argument("--strategy", choices=["3dgs", "absgs", "promptgs"])
    p.add_argument("--seed", type=int)
    p.add_argument("--resolution-scale", type=float, help="train at this fraction of the image size (0.25: a quarter)")
    p.add_argument("--sh-degree", type=int)
    p.add_argument("--budget", type=_budget, help="maximum number of Gaussians, or 'auto': stop growing when added Gaussians stop lowering the loss")
    p.add_argument("--prompts", help="prompt file (JSON boxes in dataset coordinates)")
    p.add_argument("--center-prompt", action="store_true", default=None, help="one box where the training cameras look, sized from the scene's extent (the paper's Ours*; prompts.scene_center_prompt)")
    p.add_argument("--auto-prompts", type=int, help="add the error field's top N proposals as prompts")
    p.add_argument(
        "--propose-prompts", action="store_true", default=None,
        help="PromptGS: after a warm-up, add prompt boxes where several views agree the render misses a small "
        "object (written to RUN/proposals.json; see `promptgs propose`)",
    )
    p.add_argument("--no-sky", dest="sky", action="store_false", default=None, help="no far background shell at the start (SfM points only)")
    p.add_argument(
        "--progressive", action=argparse.BooleanOptionalAction, default=None,
        help="PromptGS: train whole views at 8x/4x/2x below full size for 70%% of the run (default on; --no-progressive: full size throughout)",
    )
    p.add_argument(
        "--screen-filter", type=float,
        help="screen-space filter of full-size renders, a variance in pixels² (default: 0.1 for promptgs, 0.3 as in 3DGS for the baselines)",
    )
    p.add_argument(
        "--antialiased", action=argparse.BooleanOptionalAction, default=None,
        help="scale each Gaussian's opacity so the screen filter keeps its energy (Mip-Splatting's 2D filter): "
        "objects smaller than a pixel stay consistent across distances and resolutions "
        "(default off: 3DGS's classic filter)",
    )
    p.add_argument(
        "--compact", action=argparse.BooleanOptionalAction, default=None,
        help="at 60%% of the run (after growth ends; PromptGS: not before its views reach full size), remove the 40%% of the Gaussians that carry the least "
        "blending weight in the training views (at most 5%% of it), and fine-tune the rest; prompted objects are kept",
    )
    p.add_argument("--init", help="start from the Gaussians of this .ply, .spz, .gltf or .glb file instead of the SfM points (no sky shell)")
    p.add_argument("--export", help="also write the final Gaussians as these formats beside RUN/point_cloud.ply: spz, gltf (comma-separated)")
    p.add_argument("--snapshot-every", type=int, help="write a snapshot for the Blender add-on every N steps")
    p.add_argument("--checkpoint-every", type=int)
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace a run already in --out")
    p.add_argument("--events", action="store_true", help="JSON-lines events on stdout (for the Blender add-on)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    dist = p.add_argument_group("several processes (docs/distributed.md)")
    dist.add_argument(
        "--nproc", type=int,
        help="train with N processes on this machine (starts torchrun; job file key 'nproc'); "
        "under torchrun the launcher decides and this is ignored",
    )
    dist.add_argument("--batch-size", type=int, help="views per step over all processes (default: one per process)")
    dist.add_argument("--threads", type=int, help="OpenMP threads per process (default: cores / processes on the CPU backend)")
    dist.add_argument(
        "--dist-timeout", type=float,
        help="seconds a process waits for the others before the run stops with an error (default 300)",
    )
    from .sfm.cli import add_sfm_options

    add_sfm_options(p)
    p.set_defaults(func=cmd_train)


_TRAIN_KEYS = (
    "dataset", "out", "images", "iterations", "backend", "strategy", "seed", "resolution_scale",
    "sh_degree", "budget", "prompts", "center_prompt", "auto_prompts", "propose_prompts", "sky", "progressive", "screen_filter", "antialiased", "compact", "snapshot_every", "checkpoint_every",
    "batch_size", "init", "export",
)
# Job-file keys that say how to run, not what to train (not TrainConfig fields).
_RUN_KEYS = ("nproc",)


def train_config_from_args(args: argparse.Namespace):
    from .config import TrainConfig

    settings: dict = {}
    if args.job is not None:
        try:
            settings = json.loads(args.job.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise PromptGSError(f"{args.job}: cannot read job file ({exc})") from exc
        if not isinstance(settings, dict):
            raise PromptGSError(f"{args.job}: a job file holds one JSON object")
        for flag in ("resume", "overwrite"):
            settings.pop(flag, None)
        for key in _RUN_KEYS:
            value = settings.pop(key, None)
            if getattr(args, key, None) is None:
                setattr(args, key, value)
    for key in _TRAIN_KEYS:
        value = getattr(args, key)
        if value is not None:
            settings[key] = value
    missing = {
        "dataset": "train needs a dataset (the DATASET argument, or the job file's key 'dataset')",
        "out": "train needs a run folder (--out, or the job file's key 'out')",
    }
    for key, message in missing.items():
        if not settings.get(key):
            raise PromptGSError(message)
    return TrainConfig.from_json(settings)


def cmd_train(args: argparse.Namespace) -> int:
    from . import distributed
    from .events import EventWriter
    from .render import resolve_backend
    from .run import run_training

    cfg = train_config_from_args(args)
    nproc = args.nproc
    if nproc is not None and (isinstance(nproc, bool) or not isinstance(nproc, int) or nproc < 1):
        raise PromptGSError(f"nproc must be a positive whole number of processes, got {nproc!r}")
    if nproc and nproc > 1 and not distributed.launched_by_torchrun():
        # Photos or a video are reconstructed once, here, before the ranks start; the
        # ranks then find the finished reconstruction in OUT/sfm.
        _sfm_first(cfg, args, EventWriter.stdout() if args.events else None)
        argv = list(getattr(args, "argv", None) or [])
        forwarded = distributed.strip_option(argv[argv.index("train") + 1 :], "--nproc")
        return distributed.launch(nproc, forwarded, out=cfg.out, threads=args.threads)
    backend = resolve_backend(cfg.backend)
    ctx = distributed.init_from_env(backend, timeout_s=args.dist_timeout or distributed.DEFAULT_TIMEOUT_S)
    try:
        distributed.set_threads(ctx, backend, args.threads)
        events = EventWriter.stdout() if args.events and ctx.is_writer else None
        _sfm_first(cfg, args, events, ranks=ctx.world_size)
        metrics = run_training(cfg, resume=args.resume, overwrite=args.overwrite, events=events, quiet=args.quiet, dist=ctx)
    finally:
        ctx.close()
    if not args.events and ctx.is_writer:
        _print_metrics(metrics)
    return 0


def _sfm_first(cfg, args: argparse.Namespace, events, ranks: int = 1) -> None:
    """Photos or a video as DATASET: reconstruct them into OUT/sfm and train on that.
    Ranks of a distributed run (``ranks`` > 1) only take a reconstruction already there:
    `promptgs train --nproc` makes it before it starts them."""
    from .sfm import needs_sfm, sfm_dataset_for_run
    from .sfm.chain import SFM_FOLDER
    from .sfm.cli import sfm_options_from_args
    from .sfm.pipeline import finished_summary

    dataset = Path(cfg.dataset).expanduser()
    if not needs_sfm(dataset):
        return
    if cfg.images != "images":
        raise PromptGSError(f"{dataset}: --images names a folder inside a COLMAP dataset; photos or a video are reconstructed first and take no --images")
    if ranks > 1 and finished_summary(Path(cfg.out) / SFM_FOLDER) is None:
        raise PromptGSError(
            f"{dataset}: photos or a video are reconstructed before the ranks start: use `promptgs train --nproc N`, "
            "or `promptgs sfm` first and train the ranks on its dataset"
        )
    cfg.dataset = str(sfm_dataset_for_run(dataset, Path(cfg.out), sfm_options_from_args(args), events=events, quiet=args.quiet))


def _print_metrics(metrics: dict) -> None:
    shown = {k: v for k, v in metrics.items() if k != "per_image"}
    print(json.dumps(shown, indent=2))


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="evaluate a run folder on its test views")
    p.add_argument("run", type=Path, help="run folder, or a .ply/.spz/.gltf/.glb file inside one")
    p.add_argument(
        "--gaussians", type=Path,
        help="evaluate this .ply, .spz, .gltf or .glb file with the run's dataset and settings (printed; RUN/metrics.json untouched)",
    )
    p.add_argument("--masks", type=Path, help="object masks (white = object), same names as the images")
    p.add_argument("--save-renders", action="store_true", help="keep the test-view renders in RUN/renders/")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_eval)


def cmd_eval(args: argparse.Namespace) -> int:
    from .evaluation import evaluate_run

    run, gaussians = (args.run.parent, args.run) if args.run.is_file() else (args.run, args.gaussians)
    _print_metrics(evaluate_run(run, mask_dir=args.masks, quiet=args.quiet, save_renders=args.save_renders, gaussians=gaussians))
    return 0


def _add_render(sub) -> None:
    p = sub.add_parser("render", help="render views of a run to PNG")
    p.add_argument("run", type=Path)
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--camera", action="append", help="image name of a camera (repeatable)")
    which.add_argument("--all", action="store_true", help="every camera of the dataset")
    which.add_argument(
        "--camera-file", type=Path,
        help="JSON cameras with any pose and intrinsics, in dataset coordinates (docs/interfaces.md)",
    )
    p.add_argument(
        "--snapshot", type=Path,
        help="render this snapshot .npz of a run still training instead of its point_cloud.ply (DC colour only)",
    )
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_render)


def cmd_render(args: argparse.Namespace) -> int:
    from .evaluation import render_run

    paths = render_run(
        args.run, args.out, None if args.all else args.camera, quiet=args.quiet,
        camera_file=args.camera_file, snapshot=args.snapshot,
    )
    print(f"wrote {len(paths)} images to {args.out}")
    return 0


def _add_export(sub) -> None:
    from .formats import FORMATS, SPZ_SH_BITS

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
        from .config import TrainConfig
        from .run_folder import CONFIG, FINAL_PLY

        if not (source / CONFIG).is_file():
            raise PromptGSError(f"{source}: not a PromptGS run folder (no {CONFIG})")
        if not (source / FINAL_PLY).is_file():
            raise PromptGSError(f"{source}: no {FINAL_PLY} yet (the run has not finished)")
        return source / FINAL_PLY, TrainConfig.load(source / CONFIG).antialiased
    if not source.is_file():
        raise PromptGSError(f"{source}: no such run folder or file")
    from .formats import format_of

    format_of(source)
    return source, False


def cmd_export(args: argparse.Namespace) -> int:
    from .formats import DEFAULT_SUFFIX, format_of, read_splats, save_gaussians

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


def _add_propose(sub) -> None:
    from .propose import PROPOSALS_FILE

    p = sub.add_parser("propose", help="propose prompt boxes where the run misses small objects that several views show")
    p.add_argument("run", type=Path, help="a run folder (its point_cloud.ply, or --snapshot)")
    p.add_argument("--out", type=Path, help=f"proposal file to write (default RUN/{PROPOSALS_FILE})")
    p.add_argument("--snapshot", type=Path, help="propose from this snapshot .npz of a run still training (DC colour only)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_propose)


def cmd_propose(args: argparse.Namespace) -> int:
    from .propose import propose_run

    result, path = propose_run(args.run, args.out, args.snapshot, quiet=args.quiet)
    reasons: dict[str, int] = {}
    for r in result.rejected:
        reasons[r.reason] = reasons.get(r.reason, 0) + 1
    print(f"{len(result.proposals)} proposals, rejected {reasons or 'none'}, "
          f"{sum(len(v) for v in result.unmatched.values())} unmatched strong candidates; wrote {path}")
    for i, p in enumerate(result.proposals):
        print(f"  {i}: confidence {p.confidence:.2f}, centre {[round(v, 3) for v in p.box.center]}, "
              f"seen by {p.n_seeing} views, supported by {p.n_supporting}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="promptgs", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"promptgs {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_train(sub)
    _add_eval(sub)
    _add_render(sub)
    from .sfm.cli import add_parser as add_sfm

    add_sfm(sub)
    from .bench.demo import add_parser as add_demo
    from .bench.grid import add_parser as add_bench
    from .bench.report import add_parser as add_report
    from .bench.stability import add_parser as add_stability
    from .synthetic.cli import add_parser as add_dataset

    add_demo(sub)
    add_dataset(sub)
    add_bench(sub)
    add_report(sub)
    add_stability(sub)
    _add_export(sub)
    _add_propose(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    # Cancel (from the Blender add-on, or Ctrl-C) is SIGINT, which stops training cleanly
    # with the last checkpoint and snapshot kept. A process started by a parent that
    # ignores SIGINT (a background job of a script, some launchers) inherits the ignore
    # and Python then installs no handler: restore it so cancel always works.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from .lifeline import watch_from_env

    watch_from_env()  # a client's pipe on stdin (PROMPTGS_LIFELINE=stdin): stop when it closes
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # `train --nproc` hands them to torchrun
    try:
        return args.func(args)
    except PromptGSError as exc:
        print(f"promptgs: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("promptgs: interrupted; the last checkpoint is kept", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
