"""Import a COLMAP dataset: root empty, one camera per image, sparse points."""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix

from . import colmap, coords, display

SPARSE_NAME = "PromptGS Sparse Points"


def image_dir(dataset: Path, images: str) -> Path:
    return Path(dataset) / (images or "images")


def check_images(dataset: Path, images: str, model: colmap.Model) -> str:
    """'' when the images the model refers to are there, else a one-line problem."""
    folder = image_dir(dataset, images)
    if not folder.is_dir():
        return f"{folder}: no such image folder (the dataset needs its images next to sparse/)"
    names = [im.name for im in model.images.values()]
    missing = [n for n in names if not (folder / n).is_file()]
    if len(missing) == len(names):
        return f"{folder}: none of the {len(names)} images of the model are there (e.g. {names[0]})"
    if missing:
        return f"{folder}: {len(missing)} of {len(names)} images missing (e.g. {missing[0]})"
    return ""


def camera_resolution(cam_obj: bpy.types.Object) -> tuple[int, int]:
    return int(cam_obj.data["promptgs_width"]), int(cam_obj.data["promptgs_height"])


def use_camera(scene: bpy.types.Scene, cam_obj: bpy.types.Object) -> None:
    """Make an imported camera the scene camera with its image's resolution (and pixel
    aspect, for cameras with fy ≠ fx)."""
    scene.camera = cam_obj
    if "promptgs_width" in cam_obj.data:
        scene.render.resolution_x, scene.render.resolution_y = camera_resolution(cam_obj)
        scene.render.resolution_percentage = 100
        aspect = cam_obj.data.get("promptgs_pixel_aspect", (1.0, 1.0))
        scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = float(aspect[0]), float(aspect[1])


def import_colmap(context, dataset: str, images: str = "images", backgrounds: bool = False,
                  up: str = "AUTO") -> tuple[bpy.types.Object, list[str]]:
    """Import a dataset folder; returns the root empty and warnings for the user.

    Raises :class:`colmap.ColmapError` with a one-line message when the model is unusable.
    """
    dataset_path = Path(bpy.path.abspath(dataset)).resolve()
    model = colmap.read_model(colmap.find_model_dir(dataset_path))
    if not model.images:
        raise colmap.ColmapError(f"{model.path}: the model has no images")
    warnings = []
    problem = check_images(dataset_path, images, model)
    if problem:
        warnings.append(problem)
    notes = sorted({c.distortion_note() for c in model.cameras.values()} - {""})
    warnings += notes

    scene = context.scene
    collection = bpy.data.collections.new(f"PromptGS {dataset_path.name}")
    scene.collection.children.link(collection)
    up_vec = {"AUTO": None, "-Y": (0, -1, 0), "+Y": (0, 1, 0), "+Z": (0, 0, 1)}[up]
    if up_vec is None:
        up_vec = coords.estimate_up([im.qvec for im in model.images.values()])
    center = np.median(model.points, axis=0) if len(model.points) else np.zeros(3)
    root = bpy.data.objects.new(f"PromptGS Root {dataset_path.name}", None)
    root.empty_display_type = "PLAIN_AXES"
    root.matrix_world = Matrix(coords.dataset_to_blender(up_vec, center).tolist())
    root["promptgs_dataset"] = str(dataset_path)
    root["promptgs_images"] = images
    collection.objects.link(root)

    cam_collection = bpy.data.collections.new(f"{collection.name} Cameras")
    collection.children.link(cam_collection)
    folder = image_dir(dataset_path, images)
    first = None
    for image in model.sorted_images():
        cam = model.cameras[image.camera_id]
        fx, fy, cx, cy = cam.pinhole()
        width, height = cam.width, cam.height  # the model's size; a downscaled image folder keeps the ratios
        path = folder / image.name
        data = bpy.data.cameras.new(image.name)
        settings = coords.blender_camera_settings(width, height, fx, fy, cx, cy)
        data["promptgs_pixel_aspect"] = settings.pop("pixel_aspect")
        for key, value in settings.items():
            setattr(data, key, value)
        data.display_size = 0.2
        data["promptgs_width"], data["promptgs_height"] = width, height
        data["promptgs_model"] = cam.model
        data["promptgs_params"] = cam.params.tolist()
        obj = bpy.data.objects.new(image.name, data)
        obj["promptgs_image"] = image.name
        obj.parent = root
        obj.matrix_basis = Matrix(coords.colmap_camera_to_blender(image.qvec, image.tvec).tolist())
        cam_collection.objects.link(obj)
        if backgrounds and path.is_file():
            data.show_background_images = True
            background = data.background_images.new()
            background.image = bpy.data.images.load(str(path), check_existing=True)
            background.alpha = 0.6
        first = first or obj

    if len(model.points):
        points = display.points_object(SPARSE_NAME + f" {dataset_path.name}", collection, root,
                                       radius=_point_radius(model.points),
                                       spheres=display.use_spheres("AUTO", len(model.points)), editable=True)
        display.set_points(points, model.points, {
            "color": model.colors.astype(np.float32) / 255.0,
            "error": model.errors.astype(np.float32),
        })
        display.color_by(points, "color")

    settings = scene.promptgs
    settings.dataset = str(dataset_path)
    settings.images = images
    settings.root = root
    settings.distortion = "; ".join(notes)
    settings.point_radius = _point_radius(model.points) if len(model.points) else settings.point_radius
    use_camera(scene, first)
    return root, warnings


def _point_radius(points: np.ndarray) -> float:
    """A display radius of about 1/400 of the scene's robust extent."""
    lo, hi = np.percentile(points, [5, 95], axis=0)
    return float(max(np.linalg.norm(hi - lo) / 400.0, 1e-4))
