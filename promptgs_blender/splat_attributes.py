"""The attributes of a Gaussians object: Blender 5.3's own Gaussian-splat layout, on every line.

Blender 5.3's PLY importer (``source/blender/io/ply/importer/ply_import_gsplat.cc``) makes
a ``GAUSSIAN_SPLAT`` point cloud with these point attributes, and Cycles and EEVEE draw
from them:

| attribute | type | value |
|---|---|---|
| ``position`` | FLOAT_VECTOR | the centre |
| ``radiance:base`` | FLOAT4 | ``f_dc_0..2`` as stored (degree-0 SH, not RGB), opacity (sigmoid of the logit) |
| ``scale`` | FLOAT_VECTOR | standard deviations (exp of the log scales) |
| ``rotation`` | QUATERNION | w, x, y, z, normalised |
| ``radiance:sh_k`` | FLOAT_VECTOR | higher SH coefficient k of red, green, blue |

The Gaussians object carries exactly these on every line. Before 5.3 there is no FLOAT4
attribute type, so ``radiance:base`` is a FLOAT_COLOR attribute there: four floats as
well, stored as they are. Beside them, for Gaussians read from a PLY: the file's own
opacity logits, log scales and rotations (``ply:opacity``, ``ply:scale``,
``ply:rotation``), so an export of unchanged Gaussians writes the file's values bit for
bit, and the file's other vertex properties under their own names (``nx``, ...; a name
the add-on uses itself gets a ``ply:`` prefix). The data's custom property
``promptgs_ply`` records the file's property order and those names. Every one of them is
a point attribute, so it follows the points a user deletes.
"""

from __future__ import annotations

import json

import bpy
import numpy as np

from . import display
from .splats import SH_COUNTS, Splats

BASE = "radiance:base"
RAW = {"opacity": ("ply:opacity", "FLOAT"), "scale": ("ply:scale", "FLOAT_VECTOR"),
       "rotation": ("ply:rotation", "QUATERNION")}
FILE_PROPERTY = "promptgs_ply"
OWN = {"position", "radius", "scale", "rotation", "score", "error", "display_color", "display_value", "display_bin"}


def sh_name(k: int) -> str:
    return f"radiance:sh_{k}"


def base_type() -> str:
    """FLOAT4 where Blender has it (5.3+), else FLOAT_COLOR (also four floats)."""
    kinds = bpy.types.Attribute.bl_rna.properties["data_type"].enum_items.keys()
    return "FLOAT4" if "FLOAT4" in kinds else "FLOAT_COLOR"


def is_splat_data(data) -> bool:
    """Whether a mesh or point cloud carries Gaussians in this layout (ours, or Blender's import)."""
    return data is not None and hasattr(data, "attributes") and all(
        name in data.attributes for name in (BASE, "scale", "rotation"))


def _extra_name(prop: str) -> str:
    return "ply:" + prop if prop in OWN or prop.startswith(("radiance:", "ply:", ".")) else prop


def write(obj: bpy.types.Object, g: Splats, keep: dict[str, np.ndarray] | None = None) -> None:
    """Give a points object these Gaussians (its data is replaced when the count changes);
    ``keep`` are further FLOAT attributes (``score``, ``error``). Attributes of an earlier
    set that this one does not have (higher SH, a file's properties) are removed."""
    display.set_points(obj, g.means, {})
    data = obj.data
    n = len(g)
    base = np.empty((n, 4), np.float32)
    base[:, :3], base[:, 3] = g.f_dc, g.opacity
    written = {"position", BASE, "scale", "rotation"}
    display.set_attribute(data, BASE, base_type(), base)
    display.set_attribute(data, "scale", "FLOAT_VECTOR", g.scale)
    display.set_attribute(data, "rotation", "QUATERNION", g.rotation)
    for k in range(g.f_rest.shape[1]):
        display.set_attribute(data, sh_name(k), "FLOAT_VECTOR", g.f_rest[:, k])
        written.add(sh_name(k))
    for key, (name, data_type) in RAW.items():
        if key in g.raw:
            display.set_attribute(data, name, data_type, g.raw[key])
            written.add(name)
    extra = {prop: _extra_name(prop) for prop in g.extra}
    for prop, name in extra.items():
        display.set_attribute(data, name, "FLOAT", g.extra[prop])
        written.add(name)
    for name, values in (keep or {}).items():
        display.set_attribute(data, name, "FLOAT", values)
        written.add(name)
    before = json.loads(data.get(FILE_PROPERTY, "{}")).get("extra", {}).values()
    stale = [attr.name for attr in data.attributes if attr.name not in written and (
        attr.name.startswith(("radiance:", "ply:")) or attr.name in before)]
    for name in stale:
        data.attributes.remove(data.attributes[name])
    if g.order or extra:
        data[FILE_PROPERTY] = json.dumps({"order": g.order, "extra": extra})
    elif FILE_PROPERTY in data:
        del data[FILE_PROPERTY]
    display._data_updated(obj)


def read(data) -> Splats:
    """The Gaussians a mesh or point cloud carries (see :func:`write`); also reads what
    Blender's own importer made (5.3+)."""
    if not is_splat_data(data):
        raise ValueError(f"'{data.name}' carries no Gaussians ({BASE}, scale and rotation attributes)")
    attributes = data.attributes
    base = display.get_attribute(data, BASE)
    k = 0
    while sh_name(k) in attributes:
        k += 1
    k = max(count for count in SH_COUNTS if count <= k)  # whole bands only, as Blender renders them
    n = len(base)
    f_rest = np.empty((n, k, 3), np.float32)
    for j in range(k):
        f_rest[:, j] = display.get_attribute(data, sh_name(j))
    info = json.loads(data.get(FILE_PROPERTY, "{}"))
    raw = {key: display.get_attribute(data, name) for key, (name, _) in RAW.items() if name in attributes}
    extra = {prop: display.get_attribute(data, name) for prop, name in info.get("extra", {}).items()
             if name in attributes}
    return Splats(means=display.get_attribute(data, "position"), f_dc=np.ascontiguousarray(base[:, :3]),
                  f_rest=f_rest, opacity=np.ascontiguousarray(base[:, 3]),
                  scale=display.get_attribute(data, "scale"), rotation=display.get_attribute(data, "rotation"),
                  extra=extra, raw=raw, order=list(info.get("order", [])))


def edited(obj: bpy.types.Object, depsgraph) -> Splats:
    """The Gaussians to export: the object's own data, or, when the user added modifiers
    of their own (a crop), what they make of it without the display modifier (4.3+:
    whatever geometry they make; 4.2: the evaluated data)."""
    mod = obj.modifiers.get("PromptGS Display")
    if not any(m.show_viewport for m in obj.modifiers if m != mod):
        return read(obj.data)
    shown = mod.show_viewport if mod is not None else False
    if mod is not None:
        mod.show_viewport = False
    try:
        depsgraph.update()
        evaluated = obj.evaluated_get(depsgraph)
        if hasattr(evaluated, "evaluated_geometry"):  # 4.3+
            geometry = evaluated.evaluated_geometry()
            data = geometry.pointcloud if geometry.pointcloud is not None else geometry.mesh
            if data is None:
                raise ValueError(f"'{obj.name}': its modifiers leave no points")
            return read(data)
        return read(evaluated.data)
    finally:
        if mod is not None:
            mod.show_viewport = shown
            depsgraph.update()
