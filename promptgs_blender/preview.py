"""*Render Preview*: the trained Gaussians seen from a Blender camera, rendered by the trainer.

The active scene camera (a dataset camera or any camera the user placed) is written as a
camera file in dataset coordinates, through the same Blender → dataset transform as the
prompts (:func:`prompts.dataset_matrix`); ``promptgs render RUN --camera-file`` renders it
with the trainer's own rasterizer in a background process (no torch in Blender), from the
run's ``point_cloud.ply`` or, while it still trains, its latest snapshot. The result becomes
the image datablock "PromptGS Preview"; for a dataset camera, "PromptGS Preview | Image"
holds the render beside the dataset's photo. Both show in an Image Editor when Blender has
a window.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np

from . import coords, prompts
from .trainer import TrainerRun, check_python, engine_command, exit_line, start_run

PREVIEW = "PromptGS Preview"
SIDE_BY_SIDE = "PromptGS Preview | Image"



@dataclass
class PreviewJob:
    run: TrainerRun  # ``promptgs render`` in the background
    image_path: Path  # the PNG it writes
    camera: str  # the Blender camera object it renders
    started: float = field(default_factory=time.time)


_job: PreviewJob | None = None


class PreviewError(Exception):
    """A problem the user can fix before a preview can start."""


def current_job() -> PreviewJob | None:
    return _job


def render_size(scene: bpy.types.Scene) -> tuple[int, int]:
    """The scene's output size in pixels (resolution × percentage)."""
    r = scene.render
    return (max(1, round(r.resolution_x * r.resolution_percentage / 100)),
            max(1, round(r.resolution_y * r.resolution_percentage / 100)))


def camera_entry(scene: bpy.types.Scene, camera: bpy.types.Object, root: bpy.types.Object | None) -> dict:
    """The camera-file object (docs/interfaces.md) of a Blender camera at the scene's size."""
    data = camera.data
    if data.type != "PERSP":
        raise PreviewError(f"camera '{camera.name}' is {data.type.lower()}: the preview needs a perspective camera")
    width, height = render_size(scene)
    fx, fy, cx, cy = coords.blender_camera_intrinsics(
        width, height, data.lens, data.sensor_width, data.sensor_height, data.sensor_fit,
        data.shift_x, data.shift_y, (scene.render.pixel_aspect_x, scene.render.pixel_aspect_y))
    camera_to_dataset = np.array(prompts.dataset_matrix(root) @ camera.matrix_world)
    return {"name": camera.get("promptgs_image") or camera.name, "width": width, "height": height,
            "K": [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]],
            "world_to_camera": coords.blender_camera_to_colmap(camera_to_dataset).tolist()}


def source_of(run_dir: Path, last_snapshot: str) -> tuple[list[str], str]:
    """What to render of a run: its final PLY, else its newest snapshot (arguments, label)."""
    if (run_dir / "point_cloud.ply").is_file():
        return [], "the finished run"
    snapshots = sorted((run_dir / "snapshots").glob("step_*.npz"))
    snapshot = Path(last_snapshot) if last_snapshot and Path(last_snapshot).is_file() else (
        snapshots[-1] if snapshots else None)
    if snapshot is None:
        raise PreviewError(f"{run_dir}: nothing to render yet (no snapshot and no point_cloud.ply)")
    return ["--snapshot", str(snapshot)], f"snapshot {snapshot.stem}"


def start(context, python: str, run_dir: Path, last_snapshot: str = "") -> PreviewJob:
    """Write the active camera's file and start ``promptgs render`` on it in the background."""
    global _job
    scene = context.scene
    state = context.window_manager.promptgs_run
    if _job is not None and not _job.run.finished:
        raise PreviewError("A preview is already rendering")
    camera = scene.camera
    if camera is None:
        raise PreviewError("No active camera: pick one (a dataset camera, or any camera you placed)")
    if not (run_dir / "cfg.json").is_file():
        raise PreviewError(f"{run_dir}: not a PromptGS run folder (no cfg.json): train first, or choose a run")
    extra, label = source_of(run_dir, last_snapshot)
    entry = camera_entry(scene, camera, scene.promptgs.root)
    folder = run_dir / "preview"
    folder.mkdir(parents=True, exist_ok=True)
    camera_file = folder / "camera.json"
    camera_file.write_text(json.dumps(entry, indent=1))
    problem = check_python(python)
    if problem:
        raise PreviewError(problem)
    argv = engine_command(python, "render", str(run_dir), "--camera-file", str(camera_file),
                          "--out", str(folder), "--quiet", *extra)
    run = start_run(argv, folder / "render_stderr.log", folder, PreviewError)
    job = PreviewJob(run, folder / (Path(entry["name"]).stem + ".png"), camera.name)
    state.preview_status = "RUNNING"
    state.preview_message = f"Rendering {label} from '{camera.name}'…"
    _job = job
    return job


def drain(context) -> bool:
    """Apply the preview job's end, if it came; True while it is still running."""
    global _job
    if _job is None:
        return False
    state = context.window_manager.promptgs_run
    event = _job.run.exit_event()
    if event is not None and event.get("returncode") == 0 and _job.image_path.is_file():
        image = show(context, _job.image_path, bpy.data.objects.get(_job.camera))
        state.preview_status = "DONE"
        state.preview_message = (f"{image.name}: '{_job.camera}', {image.size[0]}×{image.size[1]}, "
                                 f"{time.time() - _job.started:.1f} s")
    elif event is not None:
        state.preview_status, state.preview_message = "ERROR", exit_line(event, "render")
    if _job.run.done:
        _job = None
        return False
    return True


def _load(name: str, path: Path) -> bpy.types.Image:
    """The named image datablock holding the file at ``path`` (reloaded when it exists)."""
    image = bpy.data.images.get(name)
    if image is not None and bpy.path.abspath(image.filepath) != str(path):
        bpy.data.images.remove(image)
        image = None
    if image is None:
        image = bpy.data.images.load(str(path))
        image.name = name
    else:
        image.reload()
    return image


def pixels(image: bpy.types.Image) -> np.ndarray:
    """[height, width, 4] float32, top row first (Blender stores the bottom row first)."""
    out = np.empty(image.size[0] * image.size[1] * 4, np.float32)
    image.pixels.foreach_get(out)
    return out.reshape(image.size[1], image.size[0], 4)[::-1]


def dataset_photo(camera: bpy.types.Object | None) -> Path | None:
    """The dataset image of an imported camera (the images folder it was imported with)."""
    if camera is None or "promptgs_image" not in camera:
        return None
    root = camera.parent
    if root is None or "promptgs_dataset" not in root:
        return None
    path = Path(root["promptgs_dataset"]) / root.get("promptgs_images", "images") / camera["promptgs_image"]
    return path if path.is_file() else None


def side_by_side(render: bpy.types.Image, photo_path: Path) -> bpy.types.Image:
    """One image with the render on the left and the photo (scaled to the render's height) on the right."""
    photo = bpy.data.images.load(str(photo_path), check_existing=True)
    left, right = pixels(render), pixels(photo)
    height = left.shape[0]
    rows = (np.arange(height) * right.shape[0] / height).astype(int)
    width = max(1, round(right.shape[1] * height / right.shape[0]))
    cols = (np.arange(width) * right.shape[1] / width).astype(int)
    both = np.concatenate([left, right[rows][:, cols]], axis=1)
    image = bpy.data.images.get(SIDE_BY_SIDE)
    if image is not None and tuple(image.size) != (both.shape[1], both.shape[0]):
        bpy.data.images.remove(image)
        image = None
    if image is None:
        image = bpy.data.images.new(SIDE_BY_SIDE, both.shape[1], both.shape[0], alpha=False)
    image.pixels.foreach_set(np.ascontiguousarray(both[::-1]).ravel())
    image.update()
    return image


def _image_editor(context):
    """An Image Editor area of an open window, or None."""
    for window in getattr(context.window_manager, "windows", []):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                return area
    return None


def show(context, path: Path, camera: bpy.types.Object | None) -> bpy.types.Image:
    """Load the rendered PNG (and the side-by-side for a dataset camera); show it in an
    Image Editor, opening Blender's render view when no window has one."""
    image = _load(PREVIEW, path)
    photo = dataset_photo(camera)
    shown = side_by_side(image, photo) if photo is not None else image
    if bpy.app.background:
        return image
    area = _image_editor(context)
    if area is None:
        try:
            bpy.ops.render.view_show("INVOKE_DEFAULT")  # where the user's preferences show renders
        except RuntimeError:
            return image
        area = _image_editor(context)
    if area is not None:
        area.spaces.active.image = shown
        area.tag_redraw()
    return image


def stop() -> None:
    global _job
    if _job is not None and _job.run.running:
        _job.run.cancel(timeout=5.0, block=True)
    _job = None
