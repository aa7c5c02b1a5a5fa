"""What a run shows in the scene: the Gaussians object, the loss field, and the collection
that holds them, made from snapshot arrays or a 3DGS PLY; and the Gaussians written back
out as a PLY.

The Gaussians object carries Blender 5.3's own Gaussian-splat attributes on every line
(:mod:`splat_attributes`). On 5.3+ Blender draws it itself (a ``GAUSSIAN_SPLAT`` point
cloud); on 4.2 to 5.2 the display modifier draws splats (instanced ellipsoids) up to
``display.SPLATS_UP_TO`` Gaussians and points above, or what *Draw As* asks for.
"""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from . import display, plyio, splat_attributes, splats

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
    n = len(data["means"])
    keep = {key: data[key] if key in data else np.zeros(n, np.float32) for key in ("score", "error")}
    return show_splats(context, splats.from_snapshot(data), keep)


def show_splats(context, g: splats.Splats, keep: dict[str, np.ndarray] | None = None) -> bpy.types.Object:
    """Update (or create once) the Gaussians object from Gaussians (``keep``: ``score``, ``error``)."""
    settings = context.scene.promptgs
    obj = display.points_object(GAUSSIANS, results_collection(context), settings.root,
                                radius=settings.point_radius, spheres=True)
    n = len(g)
    keep = dict(keep or {})
    for key in ("score", "error"):
        keep.setdefault(key, np.zeros(n, np.float32))
    splat_attributes.write(obj, g, keep)
    style_gaussians(obj, settings, g)
    return obj


def gaussians_mode(style: str, n: int) -> str:
    """How *Draw As* ``style`` shows ``n`` Gaussians: NATIVE (Blender's splats, 5.3+),
    SPLATS (instanced ellipsoids), SPHERES or POINTS."""
    if style in ("AUTO", "SPLATS"):
        if display.native_splats_supported():
            return "NATIVE"
        return "SPLATS" if style == "SPLATS" or n <= display.SPLATS_UP_TO else "POINTS"
    return style


def _colour_sources(obj: bpy.types.Object, g: splats.Splats | None) -> tuple[dict, np.ndarray]:
    """What *Colour By* reads that is not an attribute of that name: the colour (linear
    RGB of the degree-0 term) and the opacity; and the alpha of the splats' colour."""
    if g is None:
        base = display.get_attribute(obj, splat_attributes.BASE)
        dc, opacity = base[:, :3], base[:, 3]
    else:
        dc, opacity = g.f_dc, g.opacity
    rgb = splats.srgb_to_linear(np.clip(np.float32(0.5) + np.float32(splats.SH_C0) * dc, 0.0, 1.0))
    return {"color": rgb, "opacity": opacity}, opacity


def style_gaussians(obj: bpy.types.Object, settings, g: splats.Splats | None = None) -> None:
    """Apply *Draw As*, *Point Size* and *Colour By* to the Gaussians object. Native
    splats show their own colours, so colours are computed only for the other modes."""
    if not splat_attributes.is_splat_data(obj.data):
        return
    mode = gaussians_mode(settings.display_style, display.point_count(obj))
    display.set_native(obj, mode == "NATIVE")
    obj["promptgs_mode"] = mode
    if mode == "NATIVE":
        obj["promptgs_color_by"] = ""
        obj["promptgs_color_note"] = "Blender draws these splats itself: Draw As Points or Spheres to colour by attribute" \
            if settings.color_by != "color" else ""
        return
    display.set_style(obj, radius=settings.point_radius, spheres=mode == "SPHERES", splats=mode == "SPLATS")
    sources, alpha = _colour_sources(obj, g)
    display.color_by(obj, settings.color_by, sources=sources, alpha=alpha)


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
    """Show a 3DGS PLY (ours or another trainer's) as the Gaussians object, with all its
    SH and properties; score/error kept when the counts match."""
    g = plyio.read_splats(path)
    obj = bpy.data.objects.get(GAUSSIANS)
    keep = {}
    if keep_scores and display.is_points_object(obj) and display.point_count(obj) == len(g):
        keep = {key: display.get_attribute(obj, key) for key in ("score", "error") if key in obj.data.attributes}
    return show_splats(context, g, keep)


def dataset_matrix(context, obj: bpy.types.Object) -> np.ndarray:
    """Object → dataset coordinates: ``root.matrix_world⁻¹ @ obj.matrix_world`` (the
    object's world matrix when there is no dataset root). For a child of the root it is
    the object's own local matrix, exactly the identity when it was not moved (a product
    with the root's inverse would be off by rounding)."""
    root = context.scene.promptgs.root
    if root is not None and obj.parent == root and obj.parent_type == "OBJECT":
        return np.array(obj.matrix_parent_inverse, np.float64) @ np.array(obj.matrix_basis, np.float64)
    matrix = obj.matrix_world if root is None else root.matrix_world.inverted() @ obj.matrix_world
    return np.array(matrix, np.float64)


def gaussians_to_export(context, obj: bpy.types.Object | None = None) -> bpy.types.Object:
    """The object *Export Gaussians* writes: ``obj`` (or the active object) when it carries
    Gaussians, e.g. one Blender 5.3 imported itself, else the PromptGS Gaussians."""
    for candidate in (obj, context.view_layer.objects.active, bpy.data.objects.get(GAUSSIANS)):
        if candidate is not None and splat_attributes.is_splat_data(candidate.data):
            return candidate
    raise ValueError("no Gaussians to export: train, or load a result first")


def export_gaussians(context, path: Path, obj: bpy.types.Object | None = None) -> int:
    """Write the Gaussians object, as the user edited it, to a standard 3DGS PLY in dataset
    coordinates; returns how many Gaussians were written. In Edit Mode the edits are taken
    from the edit data first."""
    obj = gaussians_to_export(context, obj)
    if obj.mode == "EDIT":
        obj.update_from_editmode()
    g = splat_attributes.edited(obj, context.evaluated_depsgraph_get())
    try:
        g = splats.transformed(g, dataset_matrix(context, obj))
    except ValueError as exc:
        raise ValueError(f"'{obj.name}' cannot be written in dataset coordinates: {exc}") from None
    plyio.write_splats(path, g)
    return len(g)


def recolor(context) -> None:
    """Colour the Gaussians by the attribute the scene's settings name."""
    obj = bpy.data.objects.get(GAUSSIANS)
    if display.is_points_object(obj):
        style_gaussians(obj, context.scene.promptgs)


def restyle(context) -> None:
    """Apply the scene's dot size and display style to the Gaussians and the loss field."""
    settings = context.scene.promptgs
    obj = bpy.data.objects.get(GAUSSIANS)
    if display.is_points_object(obj):
        style_gaussians(obj, settings)
    obj = bpy.data.objects.get(LOSS_FIELD)
    if display.is_points_object(obj):
        display.set_style(obj, radius=field_radius(obj, settings), min_value=settings.field_cutoff,
                          spheres=display.use_spheres(settings.display_style, display.point_count(obj)))
