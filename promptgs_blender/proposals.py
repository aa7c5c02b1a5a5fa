"""*Propose Prompts*: boxes around small objects the run still misses, as prompt cubes in a
"Proposed" state that the user accepts or deletes; also the proposals a training run makes
itself (``propose_prompts``: ``RUN/proposals.json``, :func:`follow_training`).

``promptgs propose RUN --out RUN/propose/proposals.json`` runs in the background (the
trainer's environment renders every training view and compares it with its photo; no
torch in Blender), from the run's ``point_cloud.ply`` or, while it still trains, its
newest snapshot. Each proposal becomes a CUBE empty in the "PromptGS Proposed"
collection (inside "PromptGS Prompts", tagged orange in the Outliner, drawn orange in
the viewport by ``overlay.py``), placed with :func:`coords.prompt_box_matrix` under the
dataset root, and carries its confidence and how many views support it; a proposal whose
centre an enabled prompt already holds is left out. Proposed cubes are not sent to the trainer: *Accept* moves one
into the prompts (weight 1), the X deletes it; a cube can be moved or resized before it
is accepted. Beside the loss field, "PromptGS Proposal Points" marks each proposal's
centre, coloured by confidence.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector

from . import coords, display, preview, prompts, results
from .trainer import TrainerRun, check_python, engine_command, exit_line, start_run

PROPOSED = "PromptGS Proposed"
MARKERS = "PromptGS Proposal Points"
OUTLINER_TAG = "COLOR_02"  # orange
COLOR = (1.0, 0.45, 0.05, 1.0)
# The trainer's own threshold for adding proposals (promptgs_engine.propose.TRAIN_MIN_CONFIDENCE);
# the panel counts the proposals above it.
CONFIDENT = 0.3
TRAINING_FILE = "proposals.json"  # what `promptgs train --propose-prompts` writes in its run folder


@dataclass
class ProposeJob:
    run: TrainerRun  # ``promptgs propose`` in the background
    path: Path  # the proposal file it writes
    label: str  # what it proposes from ("the finished run", "snapshot step_000500")
    started: float = field(default_factory=time.time)


_job: ProposeJob | None = None
_training_file: tuple | None = None  # (path, mtime_ns, size) of the training proposal file last shown


class ProposeError(Exception):
    """A problem the user can fix before proposals can be made or shown."""


def current_job() -> ProposeJob | None:
    return _job


def proposed_collection(scene: bpy.types.Scene, create: bool = True) -> bpy.types.Collection | None:
    """The "PromptGS Proposed" collection, a child of the prompts collection."""
    collection = bpy.data.collections.get(PROPOSED)
    if collection is None and create:
        collection = bpy.data.collections.new(PROPOSED)
        collection.color_tag = OUTLINER_TAG
    parent = prompts.prompt_collection(scene, create=create)
    if collection is not None and parent is not None and collection.name not in parent.children:
        parent.children.link(collection)
    return collection


def proposed_objects(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    """The proposed cubes, most confident first."""
    collection = bpy.data.collections.get(PROPOSED)
    if collection is None:
        return []
    cubes = [o for o in collection.objects if o.type == "EMPTY"]
    return sorted(cubes, key=lambda o: (-float(o.get("promptgs_confidence", 0.0)), o.name))


def start(context, python: str, run_dir: Path, last_snapshot: str = "") -> ProposeJob:
    """Start ``promptgs propose`` on a run folder in the background."""
    global _job
    state = context.window_manager.promptgs_run
    if _job is not None and not _job.run.finished:
        raise ProposeError("Proposals are already being made")
    if not (run_dir / "cfg.json").is_file():
        raise ProposeError(f"{run_dir}: not a PromptGS run folder (no cfg.json): train first, or choose a run")
    try:
        extra, label = preview.source_of(run_dir, last_snapshot)
    except preview.PreviewError as exc:
        raise ProposeError(str(exc)) from None
    problem = check_python(python)
    if problem:
        raise ProposeError(problem)
    folder = run_dir / "propose"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "proposals.json"
    argv = engine_command(python, "propose", str(run_dir), "--out", str(path), "--quiet", *extra)
    run = start_run(argv, folder / "propose_stderr.log", folder, ProposeError)
    state.propose_status = "RUNNING"
    state.propose_message = f"Proposing from {label} (every training view is rendered)…"
    _job = ProposeJob(run, path, label)
    return _job


def drain(context) -> bool:
    """Apply the propose job's end, if it came; True while it is still running."""
    global _job
    if _job is None:
        return False
    state = context.window_manager.promptgs_run
    event = _job.run.exit_event()
    if event is not None and event.get("returncode") == 0 and _job.path.is_file():
        try:
            present(context, read_file(_job.path), _job.label, f" ({time.time() - _job.started:.0f} s)")
        except ProposeError as exc:
            state.propose_status, state.propose_message = "ERROR", str(exc)[:300]
    elif event is not None:
        state.propose_status, state.propose_message = "ERROR", exit_line(event, "promptgs propose")
    if _job.run.done:
        _job = None
        return False
    return True


def read_file(path: Path) -> list[dict]:
    """The proposals of a proposal file (``promptgs-proposals/1``), most confident first."""
    return load(path)[0]


def load(path: Path) -> tuple[list[dict], dict]:
    """(the proposals, most confident first; the whole file) of a proposal file."""
    try:
        data = json.loads(Path(path).read_text())
        entries = data["prompts"]
        for entry in entries:
            coords.prompt_box_matrix(entry)  # checks size and rotation
            float(entry.get("confidence", 1.0))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ProposeError(f"{path}: not a proposal file ({type(exc).__name__}: {exc})") from None
    return sorted(entries, key=lambda e: -float(e.get("confidence", 1.0))), data


def inside_prompts(context, entries: list[dict]) -> list[bool]:
    """For each entry, whether an enabled prompt cube already holds its centre (as the
    trainer skips a proposal an existing prompt holds)."""
    to_blender = prompts.dataset_matrix(context.scene.promptgs.root).inverted()
    cubes = [(o.matrix_world.inverted(), o.empty_display_size) for o in prompts.prompt_objects(context.scene)
             if o.promptgs_enabled]
    held = []
    for entry in entries:
        centre = to_blender @ Vector(entry["center"])
        held.append(any(max(abs(x) for x in inverse @ centre) <= size for inverse, size in cubes))
    return held


def present(context, entries: list[dict], label: str, note: str = "") -> list[bpy.types.Object]:
    """Replace the proposed cubes with the entries no prompt holds yet; the panel says
    how many came from ``label`` and how confident they are."""
    state = context.window_manager.promptgs_run
    held = inside_prompts(context, entries)
    cubes = show(context, [e for e, h in zip(entries, held) if not h])
    confident = sum(float(c["promptgs_confidence"]) >= CONFIDENT for c in cubes)
    skipped = f", {sum(held)} already inside prompts" if any(held) else ""
    state.propose_status = "DONE"
    state.propose_message = (f"{len(cubes)} proposals from {label}, {confident} of confidence "
                             f"≥ {CONFIDENT}{skipped}{note}")
    return cubes


def follow_training(context, run_dir: Path, final: bool = False) -> list[bpy.types.Object] | None:
    """Show the proposal file a training run writes at its proposal step
    (``train --propose-prompts``: ``RUN/proposals.json``) as proposed cubes, once for each
    version of the file (the trainer writes it again to add ``trained_as``); returns the
    cubes when it showed them. A file that cannot be read is read again on the next call
    (it may be half written); at the end of the run (``final``) that is an error in the panel."""
    global _training_file
    path = Path(run_dir) / TRAINING_FILE
    try:
        stat = path.stat()
    except OSError:
        return None
    version = (str(path), stat.st_mtime_ns, stat.st_size)
    if version == _training_file:
        return None
    state = context.window_manager.promptgs_run
    try:
        entries, data = load(path)
    except ProposeError as exc:
        if final:
            _training_file = version
            state.propose_status, state.propose_message = "ERROR", str(exc)[:300]
        return None
    _training_file = version
    trained = len(data.get("trained_as") or [])
    step = data.get("step")
    return present(context, entries, f"training step {step}" if step is not None else "the training run",
                   f" (the run trains {trained} box{'es' if trained > 1 else ''} around them)" if trained else "")


def clear(context) -> None:
    """Delete every proposed cube (and the proposal points)."""
    for obj in proposed_objects(context.scene):
        bpy.data.objects.remove(obj)
    update_markers(context)


def show(context, entries: list[dict]) -> list[bpy.types.Object]:
    """Replace the proposed cubes with one per entry (prompt-file boxes, dataset coordinates)."""
    clear(context)
    root = context.scene.promptgs.root
    to_blender = prompts.dataset_matrix(root).inverted()
    collection = proposed_collection(context.scene)
    cubes = []
    for i, entry in enumerate(entries):
        obj = bpy.data.objects.new(f"Proposed {i + 1:02d}", None)
        obj.empty_display_type = "CUBE"
        obj.empty_display_size = 1.0
        obj.matrix_world = to_blender @ Matrix(coords.prompt_box_matrix(entry).tolist())
        obj.show_in_front = True
        obj.color = COLOR
        evidence = entry.get("evidence") or {}
        obj["promptgs_proposed"] = True
        obj["promptgs_confidence"] = float(entry.get("confidence", 1.0))
        obj["promptgs_views"] = f"{evidence.get('n_supporting', '?')}/{evidence.get('n_seeing', '?')} views"
        obj.promptgs_weight = 1.0
        obj.promptgs_enabled = True
        collection.objects.link(obj)
        cubes.append(obj)
    update_markers(context)
    return cubes


def accept(context, obj: bpy.types.Object) -> bpy.types.Object:
    """A proposed cube becomes a normal prompt (weight 1), where the user left it."""
    if obj.get("promptgs_proposed") is None:
        raise ProposeError(f"'{obj.name}' is not a proposed prompt")
    target = prompts.prompt_collection(context.scene)
    for collection in list(obj.users_collection):
        collection.objects.unlink(obj)
    target.objects.link(obj)
    for key in ("promptgs_proposed", "promptgs_confidence", "promptgs_views"):
        del obj[key]
    obj.name = "Prompt"
    obj.promptgs_weight = 1.0
    obj.promptgs_enabled = True
    update_markers(context)
    return obj


def update_markers(context) -> bpy.types.Object | None:
    """The proposal points (centre, confidence) beside the loss field; removed when no
    proposal is left."""
    cubes = proposed_objects(context.scene)
    marker = bpy.data.objects.get(MARKERS)
    if not cubes:
        if marker is not None:
            bpy.data.objects.remove(marker)
        return None
    root = context.scene.promptgs.root
    to_dataset = prompts.dataset_matrix(root)
    centres = np.array([tuple((to_dataset @ c.matrix_world).translation) for c in cubes], np.float32)
    confidence = np.array([float(c["promptgs_confidence"]) for c in cubes], np.float32)
    # a sphere inside the smallest box: half its shortest half-edge
    half = min(min(c.matrix_world.to_scale()) * c.empty_display_size for c in cubes)
    marker = display.points_object(MARKERS, results.results_collection(context), root, radius=0.5 * half)
    display.set_points(marker, centres, {"confidence": confidence})
    display.set_style(marker, radius=0.5 * half, spheres=True)
    display.color_by(marker, "confidence")
    return marker


def stop() -> None:
    global _job
    if _job is not None and _job.run.running:
        _job.run.cancel(timeout=5.0, block=True)
    _job = None
