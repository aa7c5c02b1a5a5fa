"""*Reconstruct from Photos*: ``promptgs sfm`` in the background, then the import of its result.

A folder of photos or a video file goes to ``promptgs sfm INPUT --out DATASET --events``
(pycolmap in the trainer's environment; docs/sfm.md). The panel shows the current stage
with its progress (``features 31/77``); Cancel interrupts it (the trainer keeps what was
extracted and matched, and the same command resumes); when it is done the dataset is
imported as *Import COLMAP Dataset* does.
"""

from __future__ import annotations

from pathlib import Path

from . import colmap, importer
from .trainer import TrainerRun, engine_command, start_run

# The engine's video containers (promptgs_engine.sfm.video.VIDEO_SUFFIXES): any other
# picked file is a photo, and means the folder it is in.
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".mts", ".m2ts", ".mpg", ".mpeg", ".wmv",
                  ".flv", ".3gp")

_job: TrainerRun | None = None
_stage: dict = {}  # the job's last sfm_stage event


class ReconstructError(Exception):
    """A problem the user can fix before a reconstruction can start."""


def current_job() -> TrainerRun | None:
    return _job


def source_of(picked: Path | None, directory: Path) -> Path:
    """What the file browser's choice means: a video file is itself; a photo (any other
    file) is the folder it is in; nothing picked is the folder."""
    if picked is not None and picked.is_file():
        return picked if picked.suffix.lower() in VIDEO_SUFFIXES else picked.parent
    return directory


def running() -> bool:
    return _job is not None


def start(context, python: str, source: Path, out: Path) -> TrainerRun:
    """Start ``promptgs sfm SOURCE --out OUT --events`` in the background."""
    global _job
    state = context.window_manager.promptgs_run
    if _job is not None and not _job.finished:
        raise ReconstructError("A reconstruction is already running")
    if not source.exists():
        raise ReconstructError(f"{source}: not found (choose a folder of photos or a video file)")
    out.parent.mkdir(parents=True, exist_ok=True)
    run = start_run(engine_command(python, "sfm", str(source), "--out", str(out), "--events"),
                    out.parent / f"{out.name}_sfm_stderr.log", out, ReconstructError)
    state.sfm_status, state.sfm_message, state.sfm_out = "RUNNING", f"Starting structure from motion on {source.name}…", str(out)
    state.sfm_progress = 0.0
    _job = run
    _stage.clear()
    return run


def cancel() -> None:
    if _job is not None and _job.running:
        _job.cancel(block=False)


def stage_line(event: dict, stage: dict) -> str:
    """'features 31/77 img (2/4)' from a progress event and the stage it belongs to."""
    done, total = event.get("done"), event.get("total")
    count = f" {done}/{total}" if total else (f" {done}" if done is not None else "")
    unit = f" {event.get('unit')}" if event.get("unit") and done is not None else ""
    position = f" ({stage.get('index')}/{stage.get('n_stages')})" if stage.get("index") else ""
    return f"{event.get('stage', stage.get('stage', ''))}{count}{unit}{position}"


def drain(context) -> bool:
    """Apply the reconstruction's events; True while it is still running."""
    global _job
    if _job is None:
        return False
    state = context.window_manager.promptgs_run
    for event in _job.drain():
        kind = event.get("event")
        if kind == "sfm_stage":
            _stage.clear()
            _stage.update(event)
            detail = f": {event['detail']}" if event.get("detail") else ""
            state.sfm_message = f"{stage_line({}, event)}{detail}"
            state.sfm_progress = 0.0
        elif kind == "sfm_progress":
            state.sfm_message = stage_line(event, _stage)
            if event.get("total"):
                state.sfm_progress = min(1.0, float(event.get("done") or 0) / float(event["total"]))
        elif kind == "sfm_done":
            summary = event.get("summary") or {}
            state.sfm_out = str(event.get("out") or state.sfm_out)
            try:
                root, _ = importer.import_colmap(context, state.sfm_out)
            except (colmap.ColmapError, OSError) as exc:
                state.sfm_status, state.sfm_message = "ERROR", f"reconstructed, but the import failed: {exc}"
            else:
                state.sfm_status = "DONE"
                state.sfm_message = (f"{summary.get('images_registered', '?')} of {summary.get('images_given', '?')} "
                                     f"images registered, {summary.get('points', '?')} points: imported as {root.name}")
        elif kind == "error":
            state.sfm_status = "CANCELLED" if _job.cancel_requested else "ERROR"
            state.sfm_message = str(event.get("message") or "structure from motion failed")[:300]
        elif kind == "output":
            state.sfm_message = str(event.get("line", ""))[:300]
        elif kind == "exit" and state.sfm_status == "RUNNING":
            tail = event.get("stderr_tail") or []
            state.sfm_status = "CANCELLED" if _job.cancel_requested else "ERROR"
            state.sfm_message = (tail[-1] if tail else f"promptgs sfm exited with code {event.get('returncode')}")[:300]
    if _job.done:
        _job = None
        return False
    return True


def stop() -> None:
    global _job
    if _job is not None and _job.running:
        _job.cancel(timeout=10.0, block=True)
    _job = None
