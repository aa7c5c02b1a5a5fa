"""What a run shows in the scene: the Gaussians object, the loss field, and the collection
that holds them, made from snapshot arrays or a 3DGS PLY."""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from . import display, plyio

GAUSSIANS = "PromptGS Gaussians"
LOSS_FIELD = "PromptGS Loss Field"
RESULTS = "PromptGS Results"


def results_collection(context) -> bpy.types.Collection:
    collection = bpy.data.collections.get(RESULTS)
    if collection is None:
        collection = bpy.data.collections.new(RESULTS)
    if collection.name not in context.scene.collection.children:
        context.scene.collection.children.link(collection)
    return collection


def show_gaussians(context, data: dict[str, np.ndarray]) -> bpy.types.Object:
    """Update (or create once) the Gaussians object from snapshot-form arrays."""
    settings = context.scene.promptgs
    obj = display.points_object(GAUSSIANS, results_collection(context), settings.root,
                                radius=settings.point_radius, spheres=True)
    n = len(data["means"])
    attributes = {key: data[key] for key in ("opacity", "scale", "rotation", "color") if key in data}
    for key in ("score", "error"):
        attributes[key] = data[key] if key in data else np.zeros(n, np.float32)
    display.set_points(obj, data["means"], attributes)
    display.set_style(obj, spheres=display.use_spheres(settings.display_style, n))
    display.color_by(obj, settings.color_by)
    return obj


def show_loss_field(context, centers: np.ndarray, loss: np.ndarray, attention: np.ndarray) -> bpy.types.Object:
    settings = context.scene.promptgs
    obj = display.points_object(LOSS_FIELD, results_collection(context), settings.root,
                                radius=settings.point_radius * 3.0, spheres=True)
    display.set_points(obj, centers, {"loss": loss, "attention": attention})
    step = display.grid_step(centers)
    if step > 0:
        obj["promptgs_voxel_size"] = step
    display.set_style(obj, radius=field_radius(obj, settings), min_value=settings.field_cutoff,
                      spheres=display.use_spheres(settings.display_style, len(centers)))
    display.color_by(obj, "loss", palette=1)
    return obj


def field_radius(obj: bpy.types.Object, settings) -> float:
    """Loss-field dots: a quarter of the voxel size (three Gaussian dots when unknown)."""
    voxel = obj.get("promptgs_voxel_size", 0.0)
    return 0.25 * voxel if voxel > 0 else 3.0 * settings.point_radius


def apply_snapshot(context, path: Path) -> bpy.types.Object:
    with np.load(path) as npz:
        data = {key: npz[key] for key in npz.files}
    obj = show_gaussians(context, data)
    if "field_centers" in data and len(data["field_centers"]):
        show_loss_field(context, data["field_centers"], data.get("field_loss", np.zeros(len(data["field_centers"]))),
                        data.get("field_attention", np.zeros(len(data["field_centers"]))))
    return obj


def load_result(context, path: Path, keep_scores: bool = False) -> bpy.types.Object:
    """Show a standard 3DGS PLY as the Gaussians object (score/error kept when counts match)."""
    data = plyio.read_gaussians(path)
    obj = bpy.data.objects.get(GAUSSIANS)
    if keep_scores and display.is_points_object(obj) and display.point_count(obj) == len(data["means"]):
        for key in ("score", "error"):
            if key in obj.data.attributes:
                data[key] = display.get_attribute(obj, key)
    return show_gaussians(context, data)


def recolor(context) -> None:
    """Colour the Gaussians by the attribute the scene's settings name."""
    obj = bpy.data.objects.get(GAUSSIANS)
    if display.is_points_object(obj):
        display.color_by(obj, context.scene.promptgs.color_by)


def restyle(context) -> None:
    """Apply the scene's dot size and display style to the Gaussians and the loss field."""
    settings = context.scene.promptgs
    obj = bpy.data.objects.get(GAUSSIANS)
    if display.is_points_object(obj):
        display.set_style(obj, radius=settings.point_radius,
                          spheres=display.use_spheres(settings.display_style, display.point_count(obj)))
    obj = bpy.data.objects.get(LOSS_FIELD)
    if display.is_points_object(obj):
        display.set_style(obj, radius=field_radius(obj, settings), min_value=settings.field_cutoff,
                          spheres=display.use_spheres(settings.display_style, display.point_count(obj)))
