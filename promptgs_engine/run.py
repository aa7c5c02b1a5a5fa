"""A training run as a job: ``promptgs train``, the benchmarks and the Blender add-on's
runs all go through `run_training`, which checks the input, writes the run folder
(run_folder.py), trains (`train.Trainer`), evaluates (`evaluation.evaluate_run`) and
reports (events.py)."""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

from .config import TrainConfig
from .data import load_colmap_scene
from .determinism import settle_mkl
from .distributed import Dist
from .errors import PromptGSError
from .evaluation import evaluate_run
from .events import EventWriter
from .focus import load_prompt_setting
from .formats import EXPORT_NAMES
from .prompts import check_visible
from .run_folder import CHECKPOINT, CONFIG, FINAL_PLY, LOG, METRICS, SUMMARY, check_out_dir
from .train import Trainer

log = logging.getLogger("promptgs.run")


def _attach_log_file(path: Path) -> logging.Handler:
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("promptgs")
    root.setLevel(logging.INFO)
    root.addHandler(handler)
    return handler


def run_training(
    cfg: TrainConfig,
    resume: bool = False,
    overwrite: bool = False,
    events: EventWriter | None = None,
    quiet: bool = False,
    dist: Dist | None = None,
) -> dict:
    """Train a run folder from start (or from its checkpoint), evaluate it, return metrics.

    The dataset and the prompts are read before anything is written, so bad input
    leaves ``cfg.out`` untouched. On failure the error is logged and sent as an event,
    and the last good checkpoint stays in the run folder. In a distributed run (``dist``)
    every rank trains and rank 0 alone writes the run folder, sends events and evaluates;
    the other ranks return an empty dict.
    """
    settle_mkl()  # before the scene is read (determinism.py)
    dist = dist or Dist()
    writer = dist.is_writer
    events = (events or EventWriter()) if writer else EventWriter()
    out = Path(cfg.out)
    check_out_dir(out, resume, overwrite)
    if resume and not (out / CHECKPOINT).is_file():
        raise PromptGSError(f"{out}: nothing to resume (no {CHECKPOINT})")
    if resume and (out / CONFIG).is_file():
        saved = TrainConfig.load(out / CONFIG)
        saved.iterations = cfg.iterations  # a resumed run may be extended
        cfg = saved
    cfg.validate()
    # The run folder records its views per step: a resumed run keeps them at any world size.
    cfg.batch_size = int(cfg.batch_size or dist.world_size)
    # The run folder records the filter its renders use (evaluation renders with it too).
    cfg.screen_filter = cfg.effective_screen_filter
    scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
    if cfg.strategy == "promptgs" and cfg.prompts is not None and not resume:
        # The prompts are input too: a missing or malformed file, or a box that no training
        # camera sees, ends here, before the run folder is written.
        boxes = load_prompt_setting(replace(cfg, center_prompt=False))
        if boxes:
            source = "job file prompts" if isinstance(cfg.prompts, (dict, list)) else str(cfg.prompts)
            check_visible(boxes, scene.train_cameras, source=source)
    dist.barrier("the start (every rank reads the run folder before rank 0 writes it)")
    log_path = out / LOG
    handler = None
    if writer:
        out.mkdir(parents=True, exist_ok=True)
        if overwrite and not resume:
            for name in (CHECKPOINT, FINAL_PLY, METRICS, SUMMARY, *EXPORT_NAMES):
                (out / name).unlink(missing_ok=True)
        (out / CONFIG).write_text(json.dumps(cfg.to_json(), indent=2))
        handler = _attach_log_file(log_path)
    trainer = None
    try:
        trainer = Trainer(cfg, scene=scene, events=events, quiet=quiet or not writer, dist=dist)
        if resume:
            trainer.load_checkpoint(out / CHECKPOINT)
            log.info("resumed at step %d", trainer.step)
        if dist.distributed:
            log.info("%d ranks (%s), %d views a step", dist.world_size, dist.backend, trainer.batch_size)
        summary = trainer.train()
        if not writer:
            return {}
        (out / SUMMARY).write_text(json.dumps(summary, indent=2))
        metrics = evaluate_run(out, scene=scene, quiet=trainer.quiet, save_renders=cfg.save_test_renders)
        events.emit("done", out=str(out), ply=str(out / FINAL_PLY), metrics={k: v for k, v in metrics.items() if k != "per_image"})
        return metrics
    except (Exception, KeyboardInterrupt) as exc:
        step = trainer.step if trainer is not None else None
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if writer:
            log.exception("training failed at step %s", step)
        events.emit("error", message=message, step=step, log=str(log_path))
        raise
    finally:
        if handler is not None:
            logging.getLogger("promptgs").removeHandler(handler)
            handler.close()
