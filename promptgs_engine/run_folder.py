"""The run folder: what a training run writes, and reading a run back.

A run folder holds ``cfg.json`` (the settings), ``train.log``, ``ckpt.pt`` (the last good
checkpoint, resumable), ``snapshots/`` (for the Blender add-on), and at the end
``point_cloud.ply``, ``train.json`` (the training summary) and ``metrics.json`` (the
test-view metrics). docs/interfaces.md describes each file.
"""

from __future__ import annotations

from pathlib import Path

import torch

from .config import TrainConfig
from .errors import PromptGSError
from .events import read_snapshot_params
from .formats import load_gaussians
from .gaussians import load_ply

CONFIG = "cfg.json"
LOG = "train.log"
CHECKPOINT = "ckpt.pt"
FINAL_PLY = "point_cloud.ply"
SUMMARY = "train.json"
METRICS = "metrics.json"
RENDERS = "renders"  # test-view renders, written when the evaluation is asked to keep them


def check_out_dir(out: Path, resume: bool, overwrite: bool) -> None:
    """Refuse to write over a finished or interrupted run unless told to."""
    if not out.exists():
        return
    if not out.is_dir():
        raise PromptGSError(f"{out}: exists and is not a folder")
    if overwrite or resume:
        return
    if (out / FINAL_PLY).exists() or (out / METRICS).exists():
        raise PromptGSError(f"{out}: already holds a finished run (use another --out, or --overwrite)")
    if (out / CHECKPOINT).exists():
        raise PromptGSError(f"{out}: holds an unfinished run (use --resume to continue it, or --overwrite)")
    if (out / CONFIG).exists():
        raise PromptGSError(f"{out}: holds a run that stopped before its first checkpoint (use --overwrite to start it again)")


def load_run(
    run_dir: Path, snapshot: Path | None = None, gaussians: Path | None = None
) -> tuple[TrainConfig, torch.nn.ParameterDict]:
    """A run's settings and Gaussians: its ``point_cloud.ply``, a snapshot of it, or the
    ``gaussians`` of a PLY, SPZ or glTF file (formats/)."""
    run_dir = Path(run_dir)
    if not (run_dir / CONFIG).is_file():
        raise PromptGSError(f"{run_dir}: not a PromptGS run folder (no {CONFIG})")
    cfg = TrainConfig.load(run_dir / CONFIG)
    if snapshot is not None:
        return cfg, read_snapshot_params(snapshot)
    if gaussians is not None:
        return cfg, load_gaussians(gaussians)
    if not (run_dir / FINAL_PLY).is_file():
        raise PromptGSError(f"{run_dir}: no {FINAL_PLY} yet (the run has not finished); a snapshot can be rendered")
    return cfg, load_ply(run_dir / FINAL_PLY)


def atomic_torch_save(obj: object, path: Path) -> None:
    """``torch.save`` to ``path`` through a temporary file: a crash never leaves half a file."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    tmp.replace(path)
