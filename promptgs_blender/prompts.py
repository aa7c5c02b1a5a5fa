"""Prompt cubes: CUBE empties in the "PromptGS Prompts" collection."""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Matrix, Vector

from . import coords

COLLECTION = "PromptGS Prompts"


def prompt_collection(scene: bpy.types.Scene, create: bool = True) -> bpy.types.Collection | None:
    collection = bpy.data.collections.get(COLLECTION)
    if collection is None and create:
        collection = bpy.data.collections.new(COLLECTION)
    if collection is not None and create and collection.name not in scene.collection.children:
        scene.collection.children.link(collection)
    return collection


def prompt_objects(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    collection = prompt_collection(scene, create=False)
    if collection is None:
        return []
    return sorted((o for o in collection.objects if o.type == "EMPTY"), key=lambda o: o.name)


def add_prompt(context, location: Vector, half_size: Vector, name: str = "Prompt") -> bpy.types.Object:
    """A CUBE empty spanning ``location ± half_size`` (world axes)."""
    obj = bpy.data.objects.new(name, None)
    obj.empty_display_type = "CUBE"
    obj.empty_display_size = 1.0
    obj.location = location
    obj.scale = half_size
    obj.show_in_front = True
    obj.promptgs_weight = 1.0
    obj.promptgs_enabled = True
    prompt_collection(context.scene).objects.link(obj)
    return obj


def selected_points_bounds(context) -> tuple[Vector, Vector] | None:
    """World-space centre and half size of the selected vertices of the edited mesh."""
    obj = context.edit_object
    if obj is None or obj.type != "MESH":
        return None
    obj.update_from_editmode()
    mesh = obj.data
    n = len(mesh.vertices)
    selected = np.zeros(n, bool)
    mesh.vertices.foreach_get("select", selected)
    if not selected.any():
        return None
    co = np.empty(n * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    local = co.reshape(n, 3)[selected].astype(np.float64)
    world = local @ np.array(obj.matrix_world)[:3, :3].T + np.array(obj.matrix_world)[:3, 3]
    lo, hi = world.min(axis=0), world.max(axis=0)
    half = np.maximum((hi - lo) / 2.0 * 1.1, 1e-3)
    return Vector((lo + hi) / 2.0), Vector(half)


def dataset_matrix(root: bpy.types.Object | None) -> Matrix:
    """Blender world → dataset world."""
    return root.matrix_world.inverted() if root is not None else Matrix.Identity(4)


def prompt_file(scene: bpy.types.Scene, root: bpy.types.Object | None) -> dict:
    """The enabled prompts in the prompt-file format (dataset coordinates)."""
    to_dataset = dataset_matrix(root)
    out = []
    for obj in prompt_objects(scene):
        if not obj.promptgs_enabled:
            continue
        try:
            box = coords.prompt_box(np.array(to_dataset @ obj.matrix_world), obj.empty_display_size)
        except ValueError as exc:
            raise ValueError(f"prompt '{obj.name}': {exc}") from None
        box["weight"] = float(obj.promptgs_weight)
        out.append(box)
    return {"prompts": out}
