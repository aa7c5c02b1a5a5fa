""""Train focused": job file, trainer process, and applying its events to the scene.

:func:`drain_and_apply` is the one step a timer (or a modal operator, or a test in
background Blender, where timers never fire) calls to move events from the reader
thread's queue into the panel state and the viewport objects.
"""

from __future__ import annotations

import atexit
import json
import tempfile
import time
from pathlib import Path

import bpy

from . import colmap, importer, preview, prompts, proposals, reconstruct
from .results import apply_snapshot, load_result
from .props import prefs
from .trainer import TrainerError, TrainerRun, check_python, engine_command, find_python, reduce_event

_train: TrainerRun | None = None
_dataset_job: TrainerRun | None = None


class UserError(Exception):
    """A problem the user can fix; shown in the panel and the status bar."""


def current_run() -> TrainerRun | None:
    return _train


def trainer_python(context) -> str:
    p = prefs(context)
    if not p.python:
        p.python = find_python()
    return bpy.path.abspath(p.python) if p.python else ""


def output_root(context) -> Path:
    folder = prefs(context).output_dir
    if folder:
        return Path(bpy.path.abspath(folder))
    if bpy.data.filepath:
        return Path(bpy.path.abspath("//promptgs_runs"))
    return Path(tempfile.gettempdir()) / "promptgs_runs"


def dataset_of(context) -> tuple[Path, str, bpy.types.Object | None]:
    settings = context.scene.promptgs
    root = settings.root
    if root is not None and "promptgs_dataset" in root:
        return Path(root["promptgs_dataset"]), settings.images or root.get("promptgs_images", "images"), root
    if not settings.dataset:
        raise UserError("No dataset: import a COLMAP folder first (File > Import > PromptGS COLMAP)")
    return Path(bpy.path.abspath(settings.dataset)), settings.images, None


def check_dataset(dataset: Path, images: str) -> None:
    if not dataset.is_dir():
        raise UserError(f"{dataset}: dataset folder not found")
    try:
        model = colmap.read_model(colmap.find_model_dir(dataset), read_points=False)
    except colmap.ColmapError as exc:
        raise UserError(str(exc)) from None
    problem = importer.check_images(dataset, images, model)
    if problem:
        raise UserError(problem)


def build_job(context, out: Path) -> dict:
    """The job-file object (docs/interfaces.md) for the scene's settings and prompts."""
    settings = context.scene.promptgs
    dataset, images, root = dataset_of(context)
    backend = settings.backend if settings.backend != "PREFS" else prefs(context).device
    job = {
        "dataset": str(dataset),
        "out": str(out),
        "images": images,
        "iterations": settings.iterations,
        "strategy": settings.strategy,
        "backend": backend,
        "snapshot_every": settings.snapshot_every,
        "seed": settings.seed,
    }
    if settings.budget:
        job["budget"] = settings.budget
    if settings.init_ply:  # `promptgs train --init FILE`: start from these Gaussians
        job["init"] = str(Path(bpy.path.abspath(settings.init_ply)))
    if settings.strategy == "promptgs":  # 3DGS and AbsGS train without prompts (the engine refuses them)
        job["prompts"] = prompts.prompt_file(context.scene, root)
        if settings.auto_prompts:
            job["auto_prompts"] = settings.auto_prompts
        if settings.propose_prompts:
            job["propose_prompts"] = True
    if settings.compact:
        job["compact"] = True
    if settings.nproc > 1:
        job["nproc"] = settings.nproc
    return job


def reset_state(state) -> None:
    for key in ("message", "error_lines", "last_output", "log_path", "last_snapshot", "result_ply",
                "backend", "out_dir", "job_path"):
        setattr(state, key, "")
    for key in ("snapshot_step", "step", "iterations", "n_gaussians"):
        setattr(state, key, 0)
    for key in ("loss", "psnr", "elapsed_s", "eta_s", "progress"):
        setattr(state, key, 0.0)
    state.cancel_requested = False


def fail(state, message: str) -> None:
    state.status = "ERROR"
    state.message = message
    raise UserError(message)


def start_training(context) -> TrainerRun:
    """Write the job file and start ``promptgs train``; errors land in the panel state too."""
    global _train
    state = context.window_manager.promptgs_run
    if _train is not None and not _train.finished:
        raise UserError("A training run is already going: cancel it first")
    reset_state(state)
    try:
        dataset, images, _ = dataset_of(context)
        check_dataset(dataset, images)
        out = output_root(context) / f"{dataset.name}-{time.strftime('%Y%m%d-%H%M%S')}"
        n = 1
        while out.exists():
            out = out.with_name(f"{out.name.split('~')[0]}~{n}")
            n += 1
        out.mkdir(parents=True)
        job = build_job(context, out)
        job_path = out / "job.json"
        job_path.write_text(json.dumps(job, indent=2))
        state.out_dir, state.job_path = str(out), str(job_path)
        python = trainer_python(context)
        if not python:
            raise TrainerError(check_python(""))
        argv = engine_command(python, "train", str(dataset), "--out", str(out), "--events",
                              "--job", str(job_path))
        run = TrainerRun(argv, out / "trainer_stderr.log", out=out)
        state.log_path = str(run.log_path)
        run.start()
    except (UserError, TrainerError, OSError, ValueError) as exc:
        fail(state, str(exc))
    state.status = "STARTING"
    state.iterations = job["iterations"]
    state.message = "Starting the trainer…"
    _train = run
    if not bpy.app.background and not bpy.app.timers.is_registered(_timer):
        bpy.app.timers.register(_timer, first_interval=0.25)
    return run


def cancel_training(context, block: bool = False) -> None:
    state = context.window_manager.promptgs_run
    if _train is None or _train.finished:
        return
    state.cancel_requested = True
    state.status = "CANCELLING"
    state.message = "Stopping the trainer (the last snapshot is kept)…"
    _train.cancel(block=block)


def drain_and_apply(context=None) -> bool:
    """Apply queued trainer events; True while a job is still running.

    Only the newest snapshot of a batch is loaded. A ``done`` event loads the final PLY.
    The proposals a run makes while it trains (``propose_prompts``) become proposed cubes
    when their file appears (:func:`proposals.follow_training`).
    """
    global _train, _dataset_job
    context = context or bpy.context
    state = context.window_manager.promptgs_run
    busy = False
    if _train is not None:
        events = _train.drain()
        snapshot, result = None, None
        for event in events:
            reduce_event(state, event)
            if event.get("event") == "snapshot" and event.get("path"):
                snapshot = event["path"]
            elif event.get("event") == "done" and event.get("ply"):
                result = event["ply"]
        if snapshot:
            try:
                apply_snapshot(context, Path(snapshot))
            except (OSError, ValueError, KeyError) as exc:
                state.last_output = f"could not read snapshot {snapshot}: {exc}"
        if result:
            try:
                load_result(context, Path(result), keep_scores=True)
            except (OSError, ValueError) as exc:
                state.last_output = f"could not read result {result}: {exc}"
        ended = _train.done
        if state.out_dir:  # proposals of `--propose-prompts`, when the run has written them
            proposals.follow_training(context, Path(state.out_dir), final=ended)
        if ended:
            _train = None
        else:
            busy = True
    if _dataset_job is not None:
        for event in _dataset_job.drain():
            if event.get("event") == "output":
                state.dataset_message = event["line"][:300]
            elif event.get("event") == "exit":
                ok = event.get("returncode") == 0
                state.dataset_status = "DONE" if ok else "ERROR"
                tail = event.get("stderr_tail") or []
                if not ok:
                    state.dataset_message = (tail[-1] if tail else f"exit code {event.get('returncode')}")[:300]
                else:
                    state.dataset_message = f"Dataset written to {_dataset_job.out}"
        if _dataset_job.done:
            _dataset_job = None
        else:
            busy = True
    busy = preview.drain(context) or busy
    busy = proposals.drain(context) or busy
    busy = reconstruct.drain(context) or busy
    _redraw(context)
    return busy


def _redraw(context) -> None:
    wm = context.window_manager
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "PROPERTIES"):
                area.tag_redraw()


def _timer() -> float | None:
    return 0.25 if drain_and_apply(bpy.context) else None


def start_dataset_job(context, out: Path, preset: str, seed: int) -> TrainerRun:
    """``promptgs dataset mountain`` in the background (it renders with Blender)."""
    global _dataset_job
    state = context.window_manager.promptgs_run
    if _dataset_job is not None and not _dataset_job.finished:
        raise UserError("A dataset is already being generated")
    python = trainer_python(context)
    try:
        if not python:
            raise TrainerError(check_python(""))
        out.mkdir(parents=True, exist_ok=True)
        argv = engine_command(python, "dataset", "mountain", "--preset", preset, "--out", str(out),
                              "--seed", str(seed))
        run = TrainerRun(argv, out / "dataset_stderr.log", out=out)
        run.start()
    except (TrainerError, OSError) as exc:
        state.dataset_status, state.dataset_message = "ERROR", str(exc)
        raise UserError(str(exc)) from None
    state.dataset_status, state.dataset_message = "RUNNING", f"Generating into {out}…"
    state.dataset_out = str(out)
    _dataset_job = run
    if not bpy.app.background and not bpy.app.timers.is_registered(_timer):
        bpy.app.timers.register(_timer, first_interval=0.5)
    return run


def chosen_run(context) -> tuple[Path, str]:
    """The run that *Render Preview* and *Propose Prompts* work on: the chosen run folder,
    else the current or last training run; with the newest snapshot the add-on saw of it."""
    settings, state = context.scene.promptgs, context.window_manager.promptgs_run
    folder = bpy.path.abspath(settings.preview_run) if settings.preview_run else state.out_dir
    if not folder:
        raise UserError("No run: train first, or choose a run folder")
    return Path(folder), state.last_snapshot if folder == state.out_dir else ""


def _poll_in_background() -> None:
    if not bpy.app.background and not bpy.app.timers.is_registered(_timer):
        bpy.app.timers.register(_timer, first_interval=0.25)


def _start_on_chosen_run(context, start, errors: type[Exception], job: str):
    """``start(context, python, run_folder, last_snapshot)`` on the chosen run; a problem
    goes to the panel's ``JOB_status`` / ``JOB_message`` and is raised as a UserError."""
    state = context.window_manager.promptgs_run
    folder, last_snapshot = chosen_run(context)
    try:
        started = start(context, trainer_python(context), folder, last_snapshot)
    except (errors, OSError) as exc:
        setattr(state, f"{job}_status", "ERROR")
        setattr(state, f"{job}_message", str(exc))
        raise UserError(str(exc)) from None
    _poll_in_background()
    return started


def start_preview(context) -> preview.PreviewJob:
    """*Render Preview* of the chosen run (default: the current or last training run)."""
    return _start_on_chosen_run(context, preview.start, preview.PreviewError, "preview")


def start_propose(context) -> proposals.ProposeJob:
    """*Propose Prompts* from the chosen run (default: the current or last training run)."""
    return _start_on_chosen_run(context, proposals.start, proposals.ProposeError, "propose")


def start_reconstruction(context, source: Path) -> None:
    """*Reconstruct from Photos*: ``promptgs sfm`` on a folder of photos or a video, into a
    new folder of the output root; imported when it is done."""
    state = context.window_manager.promptgs_run
    name = source.stem if source.is_file() else source.name
    out = output_root(context) / f"{name}-sfm-{time.strftime('%Y%m%d-%H%M%S')}"
    try:
        python = trainer_python(context)
        if not python:
            raise TrainerError(check_python(""))
        reconstruct.start(context, python, source, out)
    except (reconstruct.ReconstructError, TrainerError, OSError) as exc:
        state.sfm_status, state.sfm_message = "ERROR", str(exc)
        raise UserError(str(exc)) from None
    if not bpy.app.background and not bpy.app.timers.is_registered(_timer):
        bpy.app.timers.register(_timer, first_interval=0.25)


def stop_all(*_args) -> None:
    """Stop running jobs (Blender quits, another file loads, the add-on is disabled)."""
    global _train, _dataset_job
    for run in (_train, _dataset_job):
        if run is not None and run.running:
            run.cancel(timeout=10.0, block=True)
    _train = _dataset_job = None
    preview.stop()
    proposals.stop()
    reconstruct.stop()


@bpy.app.handlers.persistent
def _on_load_pre(*_args) -> None:
    stop_all()


def register():
    bpy.app.handlers.load_pre.append(_on_load_pre)
    atexit.register(stop_all)


def unregister():
    stop_all()
    if _on_load_pre in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_on_load_pre)
    atexit.unregister(stop_all)
    if bpy.app.timers.is_registered(_timer):
        bpy.app.timers.unregister(_timer)
