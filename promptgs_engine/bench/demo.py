"""``promptgs demo``: the difference a prompt makes, end to end, in a few minutes.

Generates the Blender mountain / flames / drones dataset (``small`` preset; kept in
``--data`` and reused by later runs), trains 3DGS and PromptGS with the dataset's
suggested prompts (a box per drone group) on it through ``promptgs bench``, and writes
the report (charts, Table II-style table, crop sheet of the drones). ``--toy`` uses the
embedded toy scene instead, which needs no Blender.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..errors import PromptGSError
from .grid import METHODS, Grid, SceneSpec, run_grid

DEFAULT_METHODS = ["3dgs", "promptgs-2"]


def ensure_mountain(folder: Path, preset: str, seed: int, quiet: bool = False) -> Path:
    """The generated mountain dataset in ``folder``, generated on first use."""
    from ..synthetic.generate import generate
    from ..synthetic.presets import PRESETS, preset_params

    if preset not in PRESETS:
        raise PromptGSError(f"unknown preset {preset!r} (choose {', '.join(PRESETS)})")
    params = preset_params(preset)
    params["seed"] = int(seed)
    if not quiet:
        print(f"dataset: {folder} (mountain, preset {preset}, seed {seed})")
    t0 = time.perf_counter()
    record = generate(params, folder, None, show_progress=not quiet)
    if not quiet:
        print("    reused (already generated)" if record is None else f"    generated in {time.perf_counter() - t0:.0f} s")
    return folder


def ensure_toy(folder: Path) -> Path:
    from .toy_scene import ToySceneConfig, make_toy_scene

    if not (folder / "scene.json").is_file():
        make_toy_scene(folder, ToySceneConfig())
    return folder


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="3DGS vs PromptGS on the generated mountain/drones dataset, with the report")
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="bench folder (results.jsonl, runs/, report/)")
    p.add_argument("--data", type=Path, help="where the dataset is generated and kept (default runs/datasets/mountain-PRESET-sSEED)")
    p.add_argument("--preset", default="small", help="dataset preset: tiny, small or paper (default small)")
    p.add_argument("--dataset-seed", type=int, default=0)
    p.add_argument("--scene", type=Path, help="use this dataset instead of generating one")
    p.add_argument("--toy", action="store_true", help="use the embedded toy scene (no Blender needed)")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=DEFAULT_METHODS)
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    from .report import write_report

    t0 = time.perf_counter()
    if args.scene is not None:
        scene = SceneSpec.parse(str(args.scene))
    elif args.toy:
        scene = SceneSpec.parse(f"toy={ensure_toy(args.out / 'toy_scene')}")
    else:
        data = args.data or Path("runs/datasets") / f"mountain-{args.preset}-s{args.dataset_seed}"
        scene = SceneSpec.parse(f"mountain={ensure_mountain(data, args.preset, args.dataset_seed)}")
    grid = Grid(scenes=[scene], methods=list(args.methods), iterations=[args.iterations], seeds=list(args.seeds))
    run_grid(grid, args.out)
    report = write_report(args.out / "results.jsonl", args.out / "report")
    table = args.out / "report" / "table.md"
    if table.is_file():
        print()
        print(table.read_text())
    print(f"demo finished in {time.perf_counter() - t0:.0f} s")
    print(f"report: {args.out / 'report'}")
    for path in report.get("files", []):
        print(f"    {path}")
    return 0
