"""``promptgs bench``: a grid of training runs, one process per cell, results in JSONL.

A cell is (scene × method × budget × iterations × seed). Each trains in its own
``python -m promptgs_engine train`` process (so one cell's memory or crash cannot touch
the next, and its peak memory is its own), is evaluated on the scene's test views (with
object masks and recall where the dataset has them), and appends one line to
``RESULTS.jsonl`` (schema in docs/interfaces.md). Running the same grid again skips the
cells that already have an ``ok`` line, so an interrupted benchmark resumes where it
stopped.

Methods: ``3dgs``, ``absgs``, ``promptgs-center`` (``--center-prompt``: one box where the
cameras look, sized from the scene's extent; the paper's Ours*), ``promptgs-1`` (one box:
the dataset's ``prompts_1.json``, else one box around its suggested prompts),
``promptgs-2`` (the dataset's ``prompts_2.json``, else its suggested prompts, a box per
object group), ``promptgs-auto`` (prompts proposed by the error field),
``promptgs-propose`` (no box drawn: prompts proposed where several views agree the render
misses a small object, ``--propose-prompts``). A prompt method on a scene
without those prompts is not applicable and is skipped with a note. Any method with
``+compact`` appended (``3dgs+compact``, ``promptgs-1+compact``) trains with ``--compact``.

Processes: with ``nproc`` N > 1 (``--nproc``, or the grid file's ``"nproc"``) every cell
trains as N ranks on this machine (``promptgs train --nproc N``, one view per rank and
step; docs/distributed.md); its cell ids end in ``/pN`` and one bench folder holds one
process count.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import PromptGSError
from ..prompts import PromptBox, prompts_from_json, save_prompts
from .process import NAN, OK, classify, error_message, run_logged

SCHEMA = "promptgs-bench/1"
BASE_METHODS = ("3dgs", "absgs", "promptgs-center", "promptgs-1", "promptgs-2", "promptgs-auto", "promptgs-propose")
COMPACT_SUFFIX = "+compact"
METHODS = BASE_METHODS + tuple(m + COMPACT_SUFFIX for m in BASE_METHODS)
AUTO_PROMPTS = 3  # proposals taken from the error field by promptgs-auto


@dataclass(frozen=True)
class SceneSpec:
    """A dataset in the grid; ``iterations`` overrides the grid's for this scene."""

    name: str
    path: Path
    images: str = "images"
    iterations: tuple[int, ...] | None = None
    resolution_scale: float = 1.0

    @classmethod
    def parse(cls, text: str) -> "SceneSpec":
        """``PATH``, or ``NAME=PATH``, optionally ``...@IMAGES`` (e.g. ``tumbler=../data/tumbler@images_4``)."""
        name, _, rest = text.rpartition("=")
        path, _, images = rest.partition("@")
        path_obj = Path(path).expanduser()
        return cls(name=name or path_obj.resolve().name, path=path_obj.resolve(), images=images or "images")


@dataclass
class Grid:
    scenes: list[SceneSpec]
    methods: list[str] = field(default_factory=lambda: ["3dgs", "absgs", "promptgs-1"])
    budgets: list[int | str | None] = field(default_factory=lambda: [None])
    iterations: list[int] = field(default_factory=lambda: [600])
    seeds: list[int] = field(default_factory=lambda: [0])
    nproc: int = 1  # training processes per cell

    def validate(self) -> None:
        if not self.scenes:
            raise PromptGSError("bench needs at least one scene")
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown:
            raise PromptGSError(f"unknown method {unknown[0]!r} (use {', '.join(METHODS)})")
        for scene in self.scenes:
            if not scene.path.is_dir():
                raise PromptGSError(f"{scene.path}: dataset folder not found (scene {scene.name!r})")
        names = [s.name for s in self.scenes]
        if len(set(names)) != len(names):
            raise PromptGSError(f"two scenes are named alike ({', '.join(names)}); name them NAME=PATH")
        for b in self.budgets:
            if b not in (None, "auto") and not (isinstance(b, int) and b > 0):
                raise PromptGSError(f"budget {b!r}: use a positive whole number, 'auto' or 'none'")
        if isinstance(self.nproc, bool) or not isinstance(self.nproc, int) or self.nproc < 1:
            raise PromptGSError(f"nproc {self.nproc!r}: use a positive whole number of processes")

    def cells(self) -> list["Cell"]:
        """Seed by seed, so a partly run grid holds whole comparisons, and slow periods of
        a shared machine spread over the methods rather than falling on one."""
        out = []
        for scene in self.scenes:
            for iterations in scene.iterations or self.iterations:
                for seed in self.seeds:
                    for method in self.methods:
                        for budget in self.budgets:
                            out.append(Cell(scene, method, budget, iterations, seed, self.nproc))
        return out

    @classmethod
    def from_json(cls, data: dict, base: Path = Path(".")) -> "Grid":
        """A grid file: ``{"scenes": [{"name", "path", "images", "iterations"}...],
        "methods": [...], "budgets": [...], "iterations": [...], "seeds": [...], "nproc": N}``;
        scene paths are relative to the grid file."""
        try:
            scenes = [
                SceneSpec(
                    name=s.get("name") or Path(s["path"]).name,
                    path=(base / s["path"]).resolve(),
                    images=s.get("images", "images"),
                    iterations=tuple(s["iterations"]) if s.get("iterations") else None,
                    resolution_scale=float(s.get("resolution_scale", 1.0)),
                )
                for s in data["scenes"]
            ]
            grid = cls(scenes=scenes)
            for key in ("methods", "budgets", "iterations", "seeds"):
                if key in data:
                    setattr(grid, key, list(data[key]))
            if "nproc" in data:
                grid.nproc = data["nproc"]
        except (KeyError, TypeError) as exc:
            raise PromptGSError(f"grid file: missing or malformed entry ({exc})") from exc
        return grid


@dataclass(frozen=True)
class Cell:
    scene: SceneSpec
    method: str
    budget: int | str | None
    iterations: int
    seed: int
    nproc: int = 1

    @property
    def id(self) -> str:
        budget = "none" if self.budget is None else str(self.budget)
        procs = f"/p{self.nproc}" if self.nproc != 1 else ""
        return f"{self.scene.name}/{self.method}/{budget}/i{self.iterations}/s{self.seed}{procs}"

    @property
    def base_method(self) -> str:
        """The method without ``+compact``."""
        return self.method.removesuffix(COMPACT_SUFFIX)

    @property
    def compact(self) -> bool:
        return self.method.endswith(COMPACT_SUFFIX)

    @property
    def strategy(self) -> str:
        base = self.base_method
        return "promptgs" if base.startswith("promptgs") else base

    @property
    def prompt(self) -> str | None:
        base = self.base_method
        return base.split("-", 1)[1] if base.startswith("promptgs-") else None

    def run_dir(self, out: Path) -> Path:
        return out / "runs" / self.id.replace("/", "_")


# -- prompts per scene ------------------------------------------------------------------


def suggested_prompts(dataset: Path) -> list[PromptBox]:
    """The prompt boxes a dataset suggests in ``scene.json`` (the generators write them)."""
    path = dataset / "scene.json"
    if not path.is_file():
        return []
    try:
        record = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PromptGSError(f"{path}: cannot read ({exc})") from exc
    return prompts_from_json(record["prompts"], source=str(path)) if record.get("prompts") else []


def enclosing_box(boxes: list[PromptBox]) -> PromptBox:
    """One axis-aligned box around the corners of all ``boxes``."""
    corners = np.concatenate([b.corners().numpy() for b in boxes])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    return PromptBox(center=tuple((lo + hi) / 2), size=tuple(hi - lo))


def prompt_file_for(cell: Cell, run_dir: Path) -> Path | None:
    """The prompt file of a ``promptgs-1`` / ``promptgs-2`` cell, or None when the scene
    has no such prompts (the cell is not applicable)."""
    dataset = cell.scene.path
    own = dataset / f"prompts_{cell.prompt}.json"
    if own.is_file():
        return own
    boxes = suggested_prompts(dataset)
    if not boxes:
        return None
    if cell.prompt == "1":
        boxes = [enclosing_box(boxes)]
    path = run_dir.parent / f"{cell.scene.name}_prompts_{cell.prompt}.json"
    save_prompts(path, boxes)
    return path


def job_for(cell: Cell, out: Path) -> dict | None:
    """The training job (TrainConfig keys) of a cell, or None if not applicable."""
    run_dir = cell.run_dir(out)
    job: dict[str, Any] = {
        "dataset": str(cell.scene.path),
        "out": str(run_dir),
        "images": cell.scene.images,
        "iterations": cell.iterations,
        "seed": cell.seed,
        "strategy": cell.strategy,
        "resolution_scale": cell.scene.resolution_scale,
        "budget": cell.budget,
        "checkpoint_every": 0,
        "save_test_renders": True,
    }
    if cell.nproc > 1:
        job["nproc"] = cell.nproc
    if cell.compact:
        job["compact"] = True
    if cell.prompt == "center":
        job["center_prompt"] = True
    elif cell.prompt == "auto":
        job["auto_prompts"] = AUTO_PROMPTS
    elif cell.prompt == "propose":
        job["propose_prompts"] = True
    elif cell.prompt in ("1", "2"):
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        prompts = prompt_file_for(cell, run_dir)
        if prompts is None:
            return None
        job["prompts"] = str(prompts)
    return job


# -- results file -----------------------------------------------------------------------


def read_results(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise PromptGSError(f"{path}:{n}: not a JSON line ({exc.msg})") from exc
    return rows


def append_result(path: Path, row: dict) -> None:
    """Append one line and flush it to disk, so a finished cell is never lost."""
    with path.open("a") as f:
        f.write(json.dumps(row) + "\n")
        f.flush()
        os.fsync(f.fileno())


# -- running ----------------------------------------------------------------------------

RunFn = Callable[[list[str], Path], tuple[int, float, float | None]]


def run_process(command: list[str], log_path: Path) -> tuple[int, float, float | None]:
    """Run ``command`` with its output in ``log_path``; (exit code, wall seconds, peak RSS MiB)."""
    result = run_logged(command, log_path)
    return result.returncode, result.seconds, result.peak_rss_mb


METRIC_KEYS = (
    "train_seconds", "n_gaussians", "psnr", "ssim", "masked_psnr", "object_region_psnr",
    "recall", "n_recall_pairs", "recall_per_object",
)


def run_cell(cell: Cell, out: Path, run: RunFn = run_process) -> dict | None:
    """Train and evaluate one cell in its own process; the JSONL row, or None if the
    cell does not apply to its scene."""
    job = job_for(cell, out)
    if job is None:
        return None
    run_dir = cell.run_dir(out)
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    job_path = run_dir.parent / (run_dir.name + ".job.json")
    job_path.write_text(json.dumps(job, indent=2))
    log_path = run_dir.parent / (run_dir.name + ".log")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    command = [sys.executable, "-m", "promptgs_engine", "train", "--job", str(job_path), "--overwrite", "--quiet"]
    code, wall, peak = run(command, log_path)
    row: dict[str, Any] = {
        "schema": SCHEMA,
        "cell": cell.id,
        "scene": cell.scene.name,
        "dataset": str(cell.scene.path),
        "images": cell.scene.images,
        "method": cell.method,
        "strategy": cell.strategy,
        "prompt": cell.prompt,
        "budget": cell.budget,
        "iterations": cell.iterations,
        "seed": cell.seed,
        "nproc": cell.nproc,
        "run_dir": str(run_dir),
        "wall_seconds": wall,
        "peak_rss_mb": peak,
        "finished_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "load_avg": load,
    }
    output = log_path.read_text(errors="replace") if log_path.is_file() else ""
    ended = classify(code, output, run_dir)
    if ended["metrics"] is not None:
        metrics = ended["metrics"]
        row.update({k: metrics.get(k) for k in METRIC_KEYS})
        row["seconds_per_step"] = (metrics.get("train_seconds") or 0.0) / max(cell.iterations, 1)
    if ended["outcome"] == OK:
        row["status"], row["error"] = "ok", None
    elif ended["outcome"] == NAN:
        row["status"], row["error"] = "error", f"metrics are {ended['message']}"
    else:
        row["status"], row["error"] = "error", f"exit {code}: {error_message(output)}"
    return row


def run_grid(grid: Grid, out: Path, run: RunFn = run_process, quiet: bool = False) -> list[dict]:
    """Run every cell of ``grid`` not yet finished in ``out/results.jsonl``; returns all rows."""
    grid.validate()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results.jsonl"
    earlier = read_results(results)
    others = sorted({int(r.get("nproc", 1)) for r in earlier} - {grid.nproc})
    if others:
        raise PromptGSError(
            f"{out}: holds cells trained with {others[0]} processes, this grid asks for {grid.nproc} (use another --out)"
        )
    done = {r["cell"] for r in earlier if r.get("status") == "ok"}
    cells = grid.cells()
    todo = [c for c in cells if c.id not in done]
    if not quiet:
        print(f"bench: {len(cells)} cells, {len(cells) - len(todo)} already done, results in {results}")
    for i, cell in enumerate(todo, 1):
        if not quiet:
            print(f"[{i}/{len(todo)}] {cell.id} ...", flush=True)
        row = run_cell(cell, out, run)
        if row is None:
            if not quiet:
                print(f"    not applicable: {cell.scene.name} has no prompts for {cell.method}")
            continue
        append_result(results, row)
        if not quiet:
            if row["status"] == "ok":
                masked = "" if row.get("masked_psnr") is None else f", masked {row['masked_psnr']:.2f} dB"
                recall = "" if row.get("recall") is None else f", recall {row['recall']:.2f}"
                print(
                    f"    PSNR {row['psnr']:.2f} dB{masked}{recall}, {row['n_gaussians']} Gaussians, "
                    f"{row['wall_seconds']:.0f} s, {row['peak_rss_mb']:.0f} MiB"
                )
            else:
                print(f"    failed: {row['error']}")
    return read_results(results)


# -- command line -----------------------------------------------------------------------


def _budget_arg(text: str) -> int | str | None:
    if text.lower() == "none":
        return None
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise PromptGSError(f"budget {text!r}: use a positive whole number, 'auto' or 'none'") from None


def add_parser(sub) -> None:
    p = sub.add_parser(
        "bench",
        help="run a grid of trainings (scene × method × budget × iterations × seed) into a JSONL file",
        description=__doc__.split("\n\n")[1],
    )
    p.add_argument("--scene", action="append", default=[], metavar="[NAME=]PATH[@IMAGES]", help="a COLMAP dataset (repeatable)")
    p.add_argument("--grid", type=Path, help="grid file (JSON); command-line options add to / override it")
    p.add_argument("--methods", nargs="+", choices=METHODS)
    p.add_argument("--budgets", nargs="+", help="maximum Gaussians per cell: numbers, 'auto', 'none' (default none)")
    p.add_argument("--iterations", type=int, nargs="+", help="training steps per cell, for every scene (overrides the grid file)")
    p.add_argument("--seeds", type=int, nargs="+")
    p.add_argument("--nproc", type=int, help="train every cell with N processes on this machine (default 1)")
    p.add_argument("--out", type=Path, required=True, help="bench folder: results.jsonl and runs/")
    p.add_argument("--report", action="store_true", help="write the report (charts, table, crop sheet) into OUT/report when done")
    p.set_defaults(func=cmd_bench)


def grid_from_args(args) -> Grid:
    if args.grid is not None:
        try:
            data = json.loads(args.grid.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise PromptGSError(f"{args.grid}: cannot read grid file ({exc})") from exc
        grid = Grid.from_json(data, base=args.grid.parent)
    else:
        grid = Grid(scenes=[])
    grid.scenes += [SceneSpec.parse(s) for s in args.scene]
    if args.methods:
        grid.methods = list(args.methods)
    if args.budgets:
        grid.budgets = [_budget_arg(b) for b in args.budgets]
    if args.iterations:  # for every scene, including those whose grid entry sets its own
        grid.iterations = list(args.iterations)
        grid.scenes = [dataclasses.replace(s, iterations=None) for s in grid.scenes]
    if args.seeds:
        grid.seeds = list(args.seeds)
    if args.nproc is not None:
        grid.nproc = args.nproc
    return grid


def cmd_bench(args) -> int:
    grid = grid_from_args(args)
    rows = run_grid(grid, args.out)
    failed = [r for r in rows if r.get("status") != "ok"]
    print(f"bench: {len(rows) - len(failed)} cells ok, {len(failed)} failed; results in {args.out / 'results.jsonl'}")
    if args.report:
        from .report import write_report

        written = write_report(args.out / "results.jsonl", args.out / "report")
        print(f"report: {args.out / 'report'} ({len(written.get('files', []))} files)")
    return 0
