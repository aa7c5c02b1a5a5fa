"""Training runs of a scene, the trainer processes behind them, and the follow-up of the
other background jobs.

A run belongs to the .blend: its record (``PromptGSRun`` in ``scene.promptgs.runs``)
holds its folder, the settings it started with and its last known state. The scene
shows one run at a time (``settings.shown_run``) in the objects named
:data:`RUN_OBJECTS`; another run's objects are kept under the run's own name in a hidden
collection, so a second run never overwrites the first and runs can be compared.

A trainer that is going is a :class:`LiveRun`, kept here by run folder. Loading another
file detaches it (it goes on); when a file whose scene records that folder is loaded
again it is attached again. Quitting Blender stops it (its checkpoint stays: *Resume*).

Runs are outside undo: the follower changes the scene only where the run is (a new
snapshot, the result, the end) and after an undo or redo :func:`reconcile` puts each
run's record and shown objects back to what the run is now. So Ctrl+Z undoes the user's
edits and never leaves a run half shown.

:func:`drain_and_apply` is the one step a timer calls every 0.25 s; nothing here is a
modal operator. In background Blender timers never fire, so scripts and tests call it.
"""

from __future__ import annotations

import atexit
import json
import re
import shutil
import tempfile
import time
import uuid
import zipfile
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import bpy

from . import colmap, importer, preview, prompts, proposals, reconstruct, results
from .props import ACTIVE_STATES, prefs
from .trainer import (BackgroundCall, TrainerError, TrainerRun, base_python_candidates, check_python,
                      check_source, engine_command, exit_line, find_python, folder_state, probe, probe_summary,
                      reduce_event, setup_command)

POLL_S = 0.25
# The objects that show the shown run (the others' objects carry the run's name).
RUN_OBJECTS = (results.GAUSSIANS, results.LOSS_FIELD)
RESUMABLE = ("CANCELLED", "INTERRUPTED", "ERROR")
# The record fields the follower keeps current (all of a run's progress: the panel of a
# saved file shows where the run was).
RECORD_KEYS = ("status", "message", "error_lines", "warning", "last_output", "log_path", "last_snapshot",
               "result_ply", "backend", "snapshot_step", "step", "iterations", "n_gaussians", "loss", "psnr",
               "elapsed_s", "eta_s", "progress", "cancel_requested")
# Cancel asks first when this much training since the last checkpoint would be done again.
CONFIRM_AFTER_S = 60.0
CANCEL_TIMEOUT_S = 20.0  # a cancel waits this long for the trainer to stop by itself, then forces it


class UserError(Exception):
    """A problem the user can fix; shown in the panel and the status bar."""


def new_progress(**values) -> SimpleNamespace:
    """A run's state as :func:`trainer.reduce_event` keeps it (the record's fields)."""
    state = SimpleNamespace(status="STARTING", message="", error_lines="", warning="", last_output="", log_path="",
                            last_snapshot="", result_ply="", backend="", snapshot_step=0, step=0, iterations=0,
                            n_gaussians=0, loss=0.0, psnr=0.0, elapsed_s=0.0, eta_s=0.0, progress=0.0,
                            cancel_requested=False)
    for key, value in values.items():
        setattr(state, key, value)
    return state


@dataclass
class LiveRun:
    """A trainer process of a run and its progress, whether or not its file is open."""

    run: TrainerRun
    folder: str
    name: str
    scene_key: str  # settings.key of the scene it belongs to
    blend: str  # the .blend it was started from ('' when unsaved)
    job_path: str
    summary: str
    started: str
    checkpoint_every: int
    progress: SimpleNamespace
    attached: bool = True
    changed: bool = True  # the record has not seen the latest event yet
    last_line_at: float = 0.0


_live: dict[str, LiveRun] = {}
_ended: dict[str, LiveRun] = {}  # runs that ended in this session: what undo must not take back
_unreadable: set[tuple[str, int]] = set()  # (path, mtime) of snapshots that failed to load
_dataset_job: TrainerRun | None = None
_setup_job: TrainerRun | None = None
_find_job: BackgroundCall | None = None
_probe_job: BackgroundCall | None = None
notices: list[tuple[str, str]] = []  # (level, message) of the status-bar reports, newest last


# --- records ---------------------------------------------------------------------------

def shown_record(scene):
    """The record of the run the scene shows, or None."""
    name = scene.promptgs.shown_run
    return scene.promptgs.runs.get(name) if name else None


def find_record(folder: str):
    """(scene, record) of the run folder in any scene of the open file, or (None, None)."""
    for scene in bpy.data.scenes:
        for record in scene.promptgs.runs:
            if record.folder == folder:
                return scene, record
    return None, None


def live_of(record) -> LiveRun | None:
    return _live.get(record.folder) if record is not None else None


def view(record):
    """What the panel shows of a run: the live progress while it trains, else the record."""
    live = live_of(record)
    return live.progress if live is not None and live.attached else record


def any_live() -> LiveRun | None:
    return next(iter(_live.values()), None)


def detached_runs() -> list[LiveRun]:
    """Runs still training whose file is not open (listed in every file's panel)."""
    return [live for live in _live.values() if not live.attached]


def current_run(context=None) -> TrainerRun | None:
    """The trainer of the shown run while it is going, else None."""
    context = context or bpy.context
    live = live_of(shown_record(context.scene))
    return live.run if live is not None else None


def _copy(source, record, keys=RECORD_KEYS) -> None:
    for key in keys:
        value = getattr(source, key)
        if getattr(record, key) != value:
            setattr(record, key, value)


def _scene_context(context, scene):
    """``context`` itself for its own scene, else what the results code needs of another scene."""
    if getattr(context, "scene", None) == scene:
        return context
    return SimpleNamespace(scene=scene, window_manager=bpy.context.window_manager,
                           preferences=bpy.context.preferences, view_layer=scene.view_layers[0])


# --- the objects of runs ---------------------------------------------------------------

def parked_name(name: str, run: str) -> str:
    return f"{name} ({run})"


def _run_collection(context, run: str):
    """The hidden collection that keeps a run's objects while another run is shown."""
    name = f"PromptGS {run}"
    collection = bpy.data.collections.get(name)
    if collection is None:
        collection = bpy.data.collections.new(name)
    parent = results.results_collection(context)
    if collection.name not in parent.children:
        parent.children.link(collection)
    collection.hide_viewport = collection.hide_render = True
    return collection


def _move(obj, collection) -> None:
    for other in list(obj.users_collection):
        other.objects.unlink(obj)
    collection.objects.link(obj)


def park(context) -> None:
    """Keep the shown objects, hidden, under the name of the run they show ("Loaded":
    a PLY loaded by hand)."""
    for name in RUN_OBJECTS:
        obj = bpy.data.objects.get(name)
        if obj is None:
            continue
        owner = obj.get("promptgs_run") or "Loaded"
        _move(obj, _run_collection(context, owner))
        obj.name = parked_name(name, owner)


def unpark(context, record) -> bool:
    """Show ``record``'s kept objects again; False when it has none."""
    found = False
    for name in RUN_OBJECTS:
        obj = bpy.data.objects.get(parked_name(name, record.name))
        if obj is None:
            continue
        _move(obj, results.results_collection(context))
        obj.name = name
        found = True
    collection = bpy.data.collections.get(f"PromptGS {record.name}")
    if collection is not None and not collection.objects:
        bpy.data.collections.remove(collection)
    return found


def show_run(context, name: str) -> None:
    """Make ``name`` the shown run: the current one's objects are kept, hidden."""
    settings = context.scene.promptgs
    record = settings.runs.get(name)
    if record is None:
        raise UserError(f"No run '{name}' in this scene")
    if settings.shown_run == name:
        return
    park(context)
    settings.shown_run = name
    unpark(context, record)
    show_target(context, record)


def remove_run(context, name: str) -> None:
    """Forget a run in this scene and delete its objects (its folder stays on disk)."""
    settings = context.scene.promptgs
    record = settings.runs.get(name)
    if record is None:
        return
    if live_of(record) is not None:
        raise UserError(f"{name} is still training: cancel it first")
    shown = settings.shown_run == name
    for obj_name in RUN_OBJECTS:
        for obj in (bpy.data.objects.get(parked_name(obj_name, name)),
                    bpy.data.objects.get(obj_name) if shown else None):
            if obj is not None:
                bpy.data.objects.remove(obj)
    collection = bpy.data.collections.get(f"PromptGS {name}")
    if collection is not None:
        bpy.data.collections.remove(collection)
    _ended.pop(record.folder, None)
    settings.runs.remove(settings.runs.find(name))
    if shown:
        settings.shown_run = ""


def shown_path() -> str:
    """The snapshot or result the shown Gaussians hold ('' when none)."""
    obj = bpy.data.objects.get(results.GAUSSIANS)
    return str(obj.get("promptgs_shows", "")) if obj is not None else ""


def target_of(record) -> tuple[str, str]:
    """(path, kind) of what a run's objects should show: its result, else its newest snapshot."""
    if record.result_ply and Path(record.result_ply).is_file():
        return record.result_ply, "result"
    if record.last_snapshot and Path(record.last_snapshot).is_file():
        return record.last_snapshot, "snapshot"
    return "", ""


def show_target(context, record, progress=None) -> bool:
    """Load what the shown run should show when its objects hold something else; a file
    that cannot be read becomes the run's warning (one line with the log's path)."""
    path, kind = target_of(record)
    if not path or shown_path() == path:
        return False
    key = (path, _mtime(path))
    if key in _unreadable:
        return False
    obj = bpy.data.objects.get(results.GAUSSIANS)
    if obj is not None and obj.get("promptgs_run") not in (None, record.name):
        park(context)  # another run's objects: keep them
    try:
        if kind == "result":
            results.load_result(context, Path(path), keep_scores=True)
        else:
            results.apply_snapshot(context, Path(path))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        _unreadable.add(key)
        warning = f"{Path(path).name}: cannot read the {kind} ({exc}); log: {record.log_path}"[:400]
        for state in (record, progress):
            if state is not None:
                state.warning = warning
        return False
    for name in RUN_OBJECTS:
        obj = bpy.data.objects.get(name)
        if obj is not None:
            obj["promptgs_run"] = record.name
            obj["promptgs_shows"] = path
    record.shown = path
    for state in (record, progress):
        if state is not None:
            state.warning = ""
    return True


def _mtime(path: str) -> int:
    try:
        return Path(path).stat().st_mtime_ns
    except OSError:
        return 0


# --- settings, datasets and job files --------------------------------------------------

def trainer_python(context) -> str:
    p = prefs(context)
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


def has_dataset(context) -> bool:
    settings = context.scene.promptgs
    return bool(settings.dataset) or (settings.root is not None and "promptgs_dataset" in settings.root)


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
        "checkpoint_every": settings.checkpoint_every,
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


def job_summary(job: dict) -> str:
    """'promptgs, 7,000 steps, 2 prompts, cpu, seed 0' for the runs list."""
    parts = [str(job.get("strategy")), f"{int(job.get('iterations', 0)):,} steps"]
    boxes = (job.get("prompts") or {}).get("prompts") if isinstance(job.get("prompts"), dict) else None
    if boxes is not None:
        parts.append(f"{len(boxes)} prompt{'s' if len(boxes) != 1 else ''}")
    parts += [str(job.get("backend")), f"seed {job.get('seed')}"]
    if job.get("nproc"):
        parts.append(f"{job['nproc']} processes")
    return ", ".join(parts)


def scene_key(scene) -> str:
    """The scene's own key (made once, saved with it): which runs belong to it."""
    settings = scene.promptgs
    if not settings.key:
        settings.key = uuid.uuid4().hex
    return settings.key


def _add_record(scene, live: LiveRun):
    """The record of a run in ``scene`` (a new run, or one that an undo took away)."""
    runs = scene.promptgs.runs
    if runs.get(live.name) is not None:
        live.name = _next_name(scene)
    record = runs.add()
    record.name = live.name
    record.folder, record.job_path, record.log_path = live.folder, live.job_path, str(live.run.log_path)
    record.summary, record.started, record.blend = live.summary, live.started, live.blend
    record.checkpoint_every = live.checkpoint_every
    _copy(live.progress, record)
    return record


def _next_name(scene) -> str:
    numbers = [int(m.group(1)) for r in scene.promptgs.runs if (m := re.fullmatch(r"Run (\d+)", r.name))]
    return f"Run {max(numbers, default=0) + 1}"


def _new_folder(context, dataset: Path) -> Path:
    out = output_root(context) / f"{dataset.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    n = 1
    while out.exists():
        out = out.with_name(f"{out.name.split('~')[0]}~{n}")
        n += 1
    out.mkdir(parents=True)
    return out


# --- start, resume, cancel -------------------------------------------------------------

def _launch(argv: list[str], out: Path, append_log: bool) -> TrainerRun:
    run = TrainerRun(argv, out / "trainer_stderr.log", out=out, append_log=append_log)
    run.start()
    return run


def start_training(context) -> LiveRun:
    """Write the job file and start ``promptgs train`` as a new run of the scene. A
    problem before the trainer starts is the scene's ``start_error`` (and raised)."""
    scene = context.scene
    settings = scene.promptgs
    settings.start_error = ""
    out = None
    try:
        if any_live() is not None:
            raise UserError("A training run is already going: cancel it first")
        dataset, images, _ = dataset_of(context)
        check_dataset(dataset, images)
        python = trainer_python(context)
        if not python:
            raise TrainerError(check_python(""))
        job = build_job(context, Path("OUT"))
        out = _new_folder(context, dataset)
        job["out"] = str(out)
        job_path = out / "job.json"
        job_path.write_text(json.dumps(job, indent=2))
        argv = engine_command(python, "train", str(dataset), "--out", str(out), "--events", "--job", str(job_path))
        run = _launch(argv, out, append_log=False)
    except (UserError, TrainerError, OSError, ValueError) as exc:
        if out is not None:
            shutil.rmtree(out, ignore_errors=True)  # nothing ran: no run to keep
        settings.start_error = str(exc)
        raise UserError(str(exc)) from None
    progress = new_progress(iterations=job["iterations"], log_path=str(run.log_path), message="Starting the trainer…")
    live = LiveRun(run, str(out), _next_name(scene), scene_key(scene), bpy.data.filepath, str(job_path),
                   job_summary(job), time.strftime("%Y-%m-%d %H:%M"), job["checkpoint_every"], progress)
    _live[str(out)] = live
    old = shown_record(scene)
    if settings.replace_shown:  # the new run takes over the shown objects
        if old is not None:
            old.shown = ""
        for name in RUN_OBJECTS:
            obj = bpy.data.objects.get(name)
            if obj is not None:
                obj["promptgs_run"], obj["promptgs_shows"] = live.name, ""
    else:
        park(context)
    record = _add_record(scene, live)
    settings.shown_run = record.name
    _follow()
    return live


def resumable(record) -> bool:
    return (record is not None and record.status in RESUMABLE and live_of(record) is None
            and (Path(record.folder) / "ckpt.pt").is_file() and not (Path(record.folder) / "point_cloud.ply").is_file())


def resume_training(context, name: str = "") -> LiveRun:
    """Continue a stopped run of the scene from its last checkpoint (``train --resume``)."""
    scene = context.scene
    record = scene.promptgs.runs.get(name) if name else shown_record(scene)
    if record is None:
        raise UserError("No run to resume")
    if any_live() is not None:
        raise UserError("A training run is already going: cancel it first")
    folder = Path(record.folder)
    if not resumable(record):
        raise UserError(f"{folder}: nothing to resume (a stopped run with a checkpoint, ckpt.pt, and no result)")
    python = trainer_python(context)
    try:
        if not python:
            raise TrainerError(check_python(""))
        job = json.loads(Path(record.job_path or folder / "job.json").read_text())
        argv = engine_command(python, "train", str(job["dataset"]), "--out", str(folder), "--events",
                              "--job", str(record.job_path or folder / "job.json"), "--resume")
        run = _launch(argv, folder, append_log=True)
    except (TrainerError, OSError, ValueError, KeyError) as exc:
        record.message = str(exc)
        raise UserError(str(exc)) from None
    show_run(context, record.name)
    before = (record.step // max(record.checkpoint_every, 1)) * max(record.checkpoint_every, 1)
    progress = new_progress(**{key: getattr(record, key) for key in RECORD_KEYS})
    progress.status, progress.cancel_requested, progress.error_lines = "STARTING", False, ""
    progress.message = f"Resuming from its last checkpoint (step {before:,} or later)…"
    live = LiveRun(run, str(folder), record.name, scene_key(scene), bpy.data.filepath,
                   record.job_path or str(folder / "job.json"), record.summary, record.started,
                   record.checkpoint_every, progress)
    _ended.pop(str(folder), None)
    _copy(progress, record)
    _live[str(folder)] = live
    _follow()
    return live


def unsaved_seconds(record) -> float:
    """Training time since the run's last checkpoint (what a cancel makes it train again)."""
    state = view(record)
    every = max(record.checkpoint_every, 1)
    if state.step <= 0 or state.elapsed_s <= 0:
        return 0.0
    return state.elapsed_s * (state.step % every) / state.step


def cancel_training(context, name: str = "", block: bool = False) -> None:
    """Stop the run's trainer, every process of it (see TrainerRun.cancel); the last
    snapshot stays shown and the checkpoint stays for *Resume*."""
    record = context.scene.promptgs.runs.get(name) if name else shown_record(context.scene)
    live = live_of(record)
    if live is None:
        return
    _cancel(live, block)
    _copy(live.progress, record)


def _cancel(live: LiveRun, block: bool) -> None:
    live.progress.cancel_requested = True
    live.progress.status = "CANCELLING"
    live.progress.message = "Stopping the trainer (the last snapshot and checkpoint are kept)…"
    live.changed = True
    live.run.cancel(timeout=CANCEL_TIMEOUT_S, block=block)


def cancel_detached(folder: str) -> None:
    live = _live.get(folder)
    if live is not None:
        _cancel(live, block=False)


def attach_here(context, folder: str) -> None:
    """Make a detached run (its file not open) a run of this scene."""
    live = _live.get(folder)
    if live is None:
        raise UserError(f"{folder}: not training")
    scene = context.scene
    park(context)
    live.scene_key = scene_key(scene)
    record = _add_record(scene, live)
    scene.promptgs.shown_run = record.name
    live.attached = True
    live.changed = True


# --- following ---------------------------------------------------------------------------

def _follow() -> None:
    """Make sure the follower timer runs (it survives file loads)."""
    if not bpy.app.timers.is_registered(_timer):
        bpy.app.timers.register(_timer, first_interval=POLL_S, persistent=True)


def _timer() -> float | None:
    return POLL_S if drain_and_apply(bpy.context) else None


def _follow_run(context, live: LiveRun) -> bool:
    """Apply a live run's new events; False once it has ended."""
    progress = live.progress
    for event in live.run.drain():
        reduce_event(progress, event)
        live.changed |= event.get("event") not in ("progress", "output")
    if time.time() - live.last_line_at > 1.0:  # its log's newest line, once a second
        live.last_line_at = time.time()
        line = live.run.last_line()
        if line and line != progress.last_output:
            progress.last_output = line
    ended = live.run.done
    scene, record = find_record(live.folder) if live.attached else (None, None)
    if record is None:
        live.attached = False  # its record is gone (an undo of Train Focused): listed as detached
    else:
        if live.changed or ended:
            _copy(progress, record)
            live.changed = False
        ctx = _scene_context(context, scene)
        if scene.promptgs.shown_run == record.name:
            show_target(ctx, record, progress)
        proposals.follow_training(ctx, Path(live.folder), final=ended)
    if ended:
        _live.pop(live.folder, None)
        _ended[live.folder] = live
        level = {"DONE": "INFO", "CANCELLED": "WARNING"}.get(progress.status, "ERROR")
        where = "" if record is not None else f" ({Path(live.blend).name or 'an unsaved file'})"
        notify(level, f"PromptGS {live.name}{where}: {progress.message or progress.status.title()}")
    return not ended


def drain_and_apply(context=None) -> bool:
    """Apply queued events of every job; True while one is still running."""
    context = context or bpy.context
    if getattr(context.window_manager, "is_interface_locked", False):
        return True  # rendering: Blender data must not change now; the events wait
    busy = False
    jobs = context.window_manager.promptgs_run
    before = {key: getattr(jobs, f"{key}_status") for key, _label in JOBS}
    for live in list(_live.values()):
        busy = _follow_run(context, live) or busy
    busy = _drain_dataset(context) or busy
    busy = _drain_setup(context) or busy
    busy = _drain_checks(context) or busy
    busy = preview.drain(context) or busy
    busy = proposals.drain(context) or busy
    busy = reconstruct.drain(context) or busy
    _report_job_ends(jobs, before)
    _redraw(context)
    return busy


# The jobs whose state is on the window manager: (field prefix, what the report calls it).
JOBS = (("dataset", "Test Dataset"), ("sfm", "Reconstruct from Photos"), ("preview", "Render Preview"),
        ("propose", "Propose Prompts"), ("setup", "Set Up Trainer"))


def _report_job_ends(jobs, before: dict[str, str]) -> None:
    """A status-bar report for each of those jobs that ended in this step (a run's own
    report is in _follow_run)."""
    for key, label in JOBS:
        status = getattr(jobs, f"{key}_status")
        if before[key] == "RUNNING" and status != "RUNNING":
            level = {"DONE": "INFO", "CANCELLED": "WARNING"}.get(status, "ERROR")
            log = f" (log: {jobs.setup_log})" if key == "setup" and status == "ERROR" else ""
            notify(level, f"PromptGS {label}: {getattr(jobs, f'{key}_message')}{log}")


def _truth(record) -> SimpleNamespace | None:
    """What a run is now, when something outside the scene knows better than its record:
    the live trainer, a run that ended in this session, or (a record that says it is
    training, from a saved file) its folder."""
    live = _live.get(record.folder)
    if live is not None:
        if not live.attached:
            live.attached, live.name = True, record.name
        return live.progress
    if record.folder in _ended:
        return _ended[record.folder].progress
    if record.status in ACTIVE_STATES or not Path(record.folder).is_dir():
        found = folder_state(Path(record.folder))
        state = new_progress(**{key: getattr(record, key) for key in RECORD_KEYS})
        for key, value in found.items():
            setattr(state, key, value)
        state.cancel_requested = False
        return state
    return None


def reconcile(context=None) -> None:
    """Bring every scene's runs and shown objects in line with what the runs are now
    (after undo or redo, and when a file is loaded; see the module's docstring)."""
    context = context or bpy.context
    for scene in bpy.data.scenes:
        key = scene.promptgs.key
        for entry in list(_live.values()) + list(_ended.values()) if key else []:
            if entry.scene_key == key and find_record(entry.folder)[1] is None:
                record = _add_record(scene, entry)  # an undo went back to before the run started
                if entry.folder in _live:
                    ctx = _scene_context(context, scene)
                    park(ctx)
                    scene.promptgs.shown_run = record.name
        for record in scene.promptgs.runs:
            truth = _truth(record)
            if truth is not None:
                _copy(truth, record)
        record = shown_record(scene)
        if record is not None:
            show_target(_scene_context(context, scene), record, getattr(live_of(record), "progress", None))
    if _live:
        _follow()


def _redraw(context) -> None:
    wm = context.window_manager
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "PROPERTIES", "PREFERENCES"):
                area.tag_redraw()


def notify(level: str, message: str) -> None:
    """A report in the status bar (and the console), wherever the user is looking."""
    notices.append((level, message))
    del notices[:-50]
    windows = list(getattr(bpy.context.window_manager, "windows", []))
    try:
        if windows:
            with bpy.context.temp_override(window=windows[0]):
                bpy.ops.promptgs.notify("INVOKE_DEFAULT", level=level, message=message)
        else:
            bpy.ops.promptgs.notify(level=level, message=message)
    except (RuntimeError, TypeError, AttributeError):
        print(f"PromptGS: {message}")


# --- the other background jobs ---------------------------------------------------------

def _drain_dataset(context) -> bool:
    global _dataset_job
    if _dataset_job is None:
        return False
    state = context.window_manager.promptgs_run
    for event in _dataset_job.drain():
        if event.get("event") == "output":
            state.dataset_message = event["line"][:300]
        elif event.get("event") == "exit":
            ok = event.get("returncode") == 0
            state.dataset_status = "DONE" if ok else "ERROR"
            state.dataset_message = f"Dataset written to {_dataset_job.out}" if ok else exit_line(event, "promptgs dataset")
    if _dataset_job.done:
        _dataset_job = None
        return False
    return True


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
    _follow()
    return run


def dataset_running() -> bool:
    return _dataset_job is not None


def setup_folder(context) -> Path:
    """Where *Set Up Trainer* makes the environment (default: in the extension's user folder)."""
    folder = prefs(context).setup_folder
    if folder:
        return Path(bpy.path.abspath(folder))
    return Path(bpy.utils.extension_path_user(__package__, path="trainer-env", create=True))


def start_setup(context) -> TrainerRun:
    """*Set Up Trainer*: a virtual environment with torch and the engine, in the background."""
    global _setup_job
    p, jobs = prefs(context), context.window_manager.promptgs_run
    if _setup_job is not None:
        raise UserError("The trainer is already being set up")
    folder = setup_folder(context)
    base = bpy.path.abspath(p.setup_base) if p.setup_base else base_python_candidates()[0]
    source = bpy.path.abspath(p.setup_source).rstrip("/\\") if p.setup_source else ""
    problem = check_source(source) or check_python(base)
    if not problem and folder.is_dir() and any(folder.iterdir()) and not (folder / "pyvenv.cfg").is_file():
        problem = f"{folder}: not empty and not a Python environment: choose an empty folder"
    try:
        if problem:
            raise TrainerError(problem)
        folder.mkdir(parents=True, exist_ok=True)
        run = TrainerRun(setup_command(base, folder, source, p.torch_index), folder / "promptgs-setup.log", out=folder)
        run.start()
    except (TrainerError, OSError) as exc:
        jobs.setup_status, jobs.setup_message, jobs.setup_log = "ERROR", str(exc), ""
        raise UserError(str(exc)) from None
    jobs.setup_status, jobs.setup_progress = "RUNNING", 0.0
    jobs.setup_stage, jobs.setup_message, jobs.setup_log = "Starting…", f"Making {folder} from {base}", str(run.log_path)
    _setup_job = run
    _follow()
    return run


def setup_running() -> bool:
    return _setup_job is not None


def _drain_setup(context) -> bool:
    global _setup_job
    if _setup_job is None:
        return False
    p, jobs = prefs(context), context.window_manager.promptgs_run
    for event in _setup_job.drain():
        kind = event.get("event")
        if kind == "setup_stage":
            jobs.setup_stage = f"{event.get('index')}/{event.get('n_stages')}: {event.get('stage')}"
            jobs.setup_progress = (int(event.get("index") or 1) - 1) / max(int(event.get("n_stages") or 1), 1)
        elif kind == "output":
            jobs.setup_message = event["line"][:300]
        elif kind == "setup_done":
            p.python = event["python"]
            p.probe_result = probe_summary(event.get("probe") or {})
            jobs.setup_status, jobs.setup_progress = "DONE", 1.0
            jobs.setup_message = f"Trainer Python set to {event['python']}: {p.probe_result}"
        elif kind == "error":
            jobs.setup_status, jobs.setup_message = "ERROR", str(event.get("message"))[:400]
        elif kind == "exit" and jobs.setup_status == "RUNNING":
            jobs.setup_status, jobs.setup_message = "ERROR", exit_line(event, "the set-up")
    if _setup_job.done:
        _setup_job = None
        return False
    return True


def start_find(context) -> None:
    """*Find*: look for a Python with promptgs_engine in the background."""
    global _find_job
    if _find_job is not None:
        return
    jobs = context.window_manager.promptgs_run
    jobs.find_status, jobs.find_message = "RUNNING", "Looking for a Python with promptgs_engine…"
    _find_job = BackgroundCall(find_python)
    _follow()


def start_probe(context) -> None:
    """*Test*: run the trainer Python once in the background (engine version, backends)."""
    global _probe_job
    if _probe_job is not None:
        return
    p, jobs = prefs(context), context.window_manager.promptgs_run
    jobs.probe_status, p.probe_result = "RUNNING", f"Testing {p.python or 'the trainer'}…"
    _probe_job = BackgroundCall(probe, trainer_python(context))
    _follow()


def checks_running() -> tuple[bool, bool]:
    """Whether *Find* and *Test* are running."""
    return _find_job is not None, _probe_job is not None


def _drain_checks(context) -> bool:
    global _find_job, _probe_job
    p, jobs = prefs(context), context.window_manager.promptgs_run
    if _find_job is not None and _find_job.done:
        found = _find_job.result if _find_job.error is None else ""
        if found:
            p.python = found
            jobs.find_status, jobs.find_message = "DONE", f"Found {found}"
        else:
            jobs.find_status = "ERROR"
            jobs.find_message = "No Python with promptgs_engine found: set the path, or Set Up Trainer"
        _find_job = None
    if _probe_job is not None and _probe_job.done:
        info = _probe_job.result if _probe_job.error is None else {"error": str(_probe_job.error)}
        jobs.probe_status = "ERROR" if "error" in info else "DONE"
        p.probe_result = info["error"] if "error" in info else probe_summary(info)
        _probe_job = None
    return _find_job is not None or _probe_job is not None


def chosen_run(context) -> tuple[Path, str]:
    """The run that *Render Preview* and *Propose Prompts* work on: the chosen run folder,
    else the shown run; with the newest snapshot the add-on saw of it."""
    settings = context.scene.promptgs
    record = shown_record(context.scene)
    folder = bpy.path.abspath(settings.preview_run) if settings.preview_run else (record.folder if record else "")
    if not folder:
        raise UserError("No run: train first, or choose a run folder")
    same = record is not None and Path(folder) == Path(record.folder)
    return Path(folder), view(record).last_snapshot if same else ""


def _start_on_chosen_run(context, start, errors: type[Exception], job: str):
    """``start(context, python, run_folder, last_snapshot)`` on the chosen run; a problem
    goes to the panel's ``JOB_status`` / ``JOB_message`` and is raised as a UserError."""
    state = context.window_manager.promptgs_run
    try:
        folder, last_snapshot = chosen_run(context)
        started = start(context, trainer_python(context), folder, last_snapshot)
    except (errors, OSError, UserError) as exc:
        setattr(state, f"{job}_status", "ERROR")
        setattr(state, f"{job}_message", str(exc))
        raise UserError(str(exc)) from None
    _follow()
    return started


def start_preview(context) -> preview.PreviewJob:
    """*Render Preview* of the chosen run (default: the shown run)."""
    return _start_on_chosen_run(context, preview.start, preview.PreviewError, "preview")


def start_propose(context) -> proposals.ProposeJob:
    """*Propose Prompts* from the chosen run (default: the shown run)."""
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
    _follow()


# --- file loads, undo, quitting ----------------------------------------------------------

def stop_all(*_args) -> None:
    """Stop every job, each process of each (Blender quits, the add-on is disabled)."""
    global _dataset_job, _setup_job
    for job in [live.run for live in _live.values()] + [_dataset_job, _setup_job]:
        if job is not None and job.running:
            job.cancel(timeout=10.0, block=True)
    _live.clear()
    _dataset_job = _setup_job = None
    preview.stop()
    proposals.stop()
    reconstruct.stop()


@bpy.app.handlers.persistent
def _on_load_pre(*_args) -> None:
    """Another file loads: training runs go on, detached (re-attached when a file that
    records them is opened); the jobs that work on this file's objects stop."""
    for live in _live.values():
        live.attached = False
    preview.stop()
    proposals.stop()
    reconstruct.stop()


@bpy.app.handlers.persistent
def _on_load_post(*_args) -> None:
    reconcile(bpy.context)


@bpy.app.handlers.persistent
def _on_undo_redo(*_args) -> None:
    reconcile(bpy.context)


@bpy.app.handlers.persistent
def _on_save_pre(*_args) -> None:
    """The file keeps the runs' newest progress."""
    for live in _live.values():
        _scene, record = find_record(live.folder) if live.attached else (None, None)
        if record is not None:
            _copy(live.progress, record)


HANDLERS = (("load_pre", _on_load_pre), ("load_post", _on_load_post), ("undo_post", _on_undo_redo),
            ("redo_post", _on_undo_redo), ("save_pre", _on_save_pre))


def register():
    for name, handler in HANDLERS:
        getattr(bpy.app.handlers, name).append(handler)
    atexit.register(stop_all)


def unregister():
    stop_all()
    for name, handler in HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if handler in handlers:
            handlers.remove(handler)
    atexit.unregister(stop_all)
    if bpy.app.timers.is_registered(_timer):
        bpy.app.timers.unregister(_timer)
