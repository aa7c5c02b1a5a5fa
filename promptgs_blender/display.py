"""Points objects carrying per-point attributes, drawn with a geometry-nodes modifier.

A points-only mesh keeps the data (``foreach_set`` of numpy arrays, no per-point Python)
and can change its point count from one snapshot to the next while the object stays the
same. The "PromptGS Points" node group draws the points either as point-cloud points
(cheap: a million in well under a second) or as small ico-spheres (about 12 s per million
to evaluate, so only for small sets). Colour: the ``display_color`` attribute (the chosen
attribute through a colour map, or the RGB colour) read by the "PromptGS Display"
material in Material Preview and Rendered shading; for Workbench, which ignores
attributes, spheres also get one of 16 colour-map materials per palette from
``display_bin``. Points
whose colour-map value ``display_value`` (0..1) is below the modifier's "Min Value" are
not drawn (the loss field shows its high-loss voxels only).
"""

from __future__ import annotations

import bpy
import numpy as np

N_BINS = 16
NODE_GROUP = "PromptGS Points"
NODE_GROUP_VERSION = 2  # bump when the group changes; older groups are rebuilt
DISPLAY_MATERIAL = "PromptGS Display"
SPHERES_UP_TO = 50_000  # "auto" style: spheres up to this many points, plain points above
# colour ramps (control points, linear RGB): 0 dark blue → green → yellow (Gaussians),
# 1 dark red → orange → pale yellow (the loss field)
PALETTES = (
    np.array([[0.07, 0.02, 0.20], [0.10, 0.20, 0.55], [0.05, 0.45, 0.50],
              [0.20, 0.70, 0.25], [0.80, 0.85, 0.10], [1.00, 0.95, 0.35]]),
    np.array([[0.25, 0.01, 0.01], [0.60, 0.03, 0.02], [0.90, 0.20, 0.02],
              [1.00, 0.50, 0.05], [1.00, 0.80, 0.30], [1.00, 1.00, 0.80]]),
)


def colormap(t: np.ndarray, palette: int = 0) -> np.ndarray:
    """RGB of values in [0, 1] on a ramp."""
    ramp = PALETTES[palette]
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0)
    x = np.linspace(0.0, 1.0, len(ramp))
    return np.stack([np.interp(t, x, ramp[:, c]) for c in range(3)], axis=-1)


def bin_material(index: int) -> bpy.types.Material:
    """Material of ``display_bin`` ``index``: palette ``index // N_BINS``, step ``index % N_BINS``."""
    name = f"PromptGS Map {index:02d}"
    mat = bpy.data.materials.get(name)
    if mat is None:
        mat = bpy.data.materials.new(name)
        rgb = colormap((index % N_BINS + 0.5) / N_BINS, index // N_BINS)
        mat.diffuse_color = (*rgb, 1.0)
        mat.use_nodes = True
        tree = mat.node_tree
        tree.nodes.clear()
        emit = tree.nodes.new("ShaderNodeEmission")
        emit.inputs["Color"].default_value = (*rgb, 1.0)
        out = tree.nodes.new("ShaderNodeOutputMaterial")
        tree.links.new(emit.outputs[0], out.inputs["Surface"])
    return mat


def display_material() -> bpy.types.Material:
    mat = bpy.data.materials.get(DISPLAY_MATERIAL)
    if mat is None:
        mat = bpy.data.materials.new(DISPLAY_MATERIAL)
        mat.diffuse_color = (0.6, 0.6, 0.6, 1.0)
        mat.use_nodes = True
        tree = mat.node_tree
        tree.nodes.clear()
        attr = tree.nodes.new("ShaderNodeAttribute")
        attr.attribute_name = "display_color"
        emit = tree.nodes.new("ShaderNodeEmission")
        out = tree.nodes.new("ShaderNodeOutputMaterial")
        tree.links.new(attr.outputs["Color"], emit.inputs["Color"])
        tree.links.new(emit.outputs[0], out.inputs["Surface"])
    return mat


def node_group() -> bpy.types.NodeTree:
    """The shared geometry-nodes group (inputs: Geometry, Radius, Spheres)."""
    group = bpy.data.node_groups.get(NODE_GROUP)
    if group is not None:
        if group.get("promptgs_version") == NODE_GROUP_VERSION:
            return group
        bpy.data.node_groups.remove(group)  # from an older version of the add-on
    group = bpy.data.node_groups.new(NODE_GROUP, "GeometryNodeTree")
    group["promptgs_version"] = NODE_GROUP_VERSION
    face = group.interface
    face.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    radius = face.new_socket("Radius", in_out="INPUT", socket_type="NodeSocketFloat")
    radius.default_value, radius.min_value = 0.01, 0.0
    spheres = face.new_socket("Spheres", in_out="INPUT", socket_type="NodeSocketBool")
    spheres.default_value = True
    cutoff = face.new_socket("Min Value", in_out="INPUT", socket_type="NodeSocketFloat")
    cutoff.default_value, cutoff.min_value, cutoff.max_value = 0.0, 0.0, 1.0
    face.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = group.nodes, group.links
    g_in, g_out = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")

    # hide points whose colour-map value (0..1) is below "Min Value"
    value = nodes.new("GeometryNodeInputNamedAttribute")
    value.data_type = "FLOAT"
    value.inputs["Name"].default_value = "display_value"
    below = nodes.new("FunctionNodeCompare")
    below.data_type, below.operation = "FLOAT", "LESS_THAN"
    links.new(value.outputs["Attribute"], below.inputs[0])
    links.new(g_in.outputs["Min Value"], below.inputs[1])
    delete = nodes.new("GeometryNodeDeleteGeometry")
    delete.domain = "POINT"
    links.new(g_in.outputs["Geometry"], delete.inputs["Geometry"])
    links.new(below.outputs["Result"], delete.inputs["Selection"])
    source = delete.outputs["Geometry"]

    to_points = nodes.new("GeometryNodeMeshToPoints")
    links.new(source, to_points.inputs["Mesh"])
    links.new(g_in.outputs["Radius"], to_points.inputs["Radius"])
    ico = nodes.new("GeometryNodeMeshIcoSphere")
    ico.inputs["Subdivisions"].default_value = 1
    links.new(g_in.outputs["Radius"], ico.inputs["Radius"])
    instance = nodes.new("GeometryNodeInstanceOnPoints")
    links.new(source, instance.inputs["Points"])
    links.new(ico.outputs["Mesh"], instance.inputs["Instance"])
    realize = nodes.new("GeometryNodeRealizeInstances")
    links.new(instance.outputs["Instances"], realize.inputs["Geometry"])

    # plain points: one material reading display_color
    points_mat = nodes.new("GeometryNodeSetMaterial")
    points_mat.inputs["Material"].default_value = display_material()
    links.new(to_points.outputs["Points"], points_mat.inputs["Geometry"])
    # spheres: the same, then a colour-map material per display_bin (Workbench)
    spheres_mat = nodes.new("GeometryNodeSetMaterial")
    spheres_mat.inputs["Material"].default_value = display_material()
    links.new(realize.outputs["Geometry"], spheres_mat.inputs["Geometry"])
    geometry = spheres_mat.outputs["Geometry"]
    bins = nodes.new("GeometryNodeInputNamedAttribute")
    bins.data_type = "INT"
    bins.inputs["Name"].default_value = "display_bin"
    for k in range(N_BINS * len(PALETTES)):
        equal = nodes.new("FunctionNodeCompare")
        equal.data_type, equal.operation = "INT", "EQUAL"
        links.new(bins.outputs["Attribute"], equal.inputs[2])
        equal.inputs[3].default_value = k
        set_mat = nodes.new("GeometryNodeSetMaterial")
        set_mat.inputs["Material"].default_value = bin_material(k)
        links.new(geometry, set_mat.inputs["Geometry"])
        links.new(equal.outputs["Result"], set_mat.inputs["Selection"])
        geometry = set_mat.outputs["Geometry"]
    switch = nodes.new("GeometryNodeSwitch")
    switch.input_type = "GEOMETRY"
    links.new(g_in.outputs["Spheres"], switch.inputs["Switch"])
    links.new(points_mat.outputs["Geometry"], switch.inputs["False"])
    links.new(geometry, switch.inputs["True"])
    geometry = switch.outputs[0]
    links.new(geometry, g_out.inputs["Geometry"])
    return group


def _socket_id(group: bpy.types.NodeTree, name: str) -> str:
    for item in group.interface.items_tree:
        if getattr(item, "in_out", None) == "INPUT" and item.name == name:
            return item.identifier
    raise KeyError(name)


def use_spheres(style: str, n: int) -> bool:
    """Whether a display style ('AUTO', 'SPHERES', 'POINTS') draws ``n`` points as spheres."""
    return style == "SPHERES" or (style == "AUTO" and n <= SPHERES_UP_TO)


def set_style(obj: bpy.types.Object, radius: float | None = None, spheres: bool | None = None,
              min_value: float | None = None) -> None:
    """Set the display modifier's inputs (None: leave as is)."""
    mod = obj.modifiers.get("PromptGS Display")
    if mod is None:
        return
    if min_value is not None:
        mod[_socket_id(mod.node_group, "Min Value")] = float(min_value)
    if radius is not None:
        mod[_socket_id(mod.node_group, "Radius")] = float(radius)
    if spheres is not None:
        mod[_socket_id(mod.node_group, "Spheres")] = bool(spheres)
    obj.update_tag()


def points_object(name: str, collection: bpy.types.Collection, parent: bpy.types.Object | None = None,
                  radius: float = 0.01, spheres: bool = True) -> bpy.types.Object:
    """The named points object, created on first use (its identity survives updates)."""
    obj = bpy.data.objects.get(name)
    if obj is None or obj.type != "MESH":
        mesh = bpy.data.meshes.new(name)
        obj = bpy.data.objects.new(name, mesh)
        mod = obj.modifiers.new("PromptGS Display", "NODES")
        mod.node_group = node_group()
        set_style(obj, radius, spheres)
    if collection not in obj.users_collection:
        collection.objects.link(obj)
    if parent is not None and obj.parent != parent:
        obj.parent = parent
        obj.matrix_parent_inverse.identity()
        obj.matrix_basis.identity()
    return obj


def _attribute_kind(array: np.ndarray, name: str) -> tuple[str, str, int]:
    width = 1 if array.ndim == 1 else array.shape[1]
    if name == "color" or name == "display_color":
        return "FLOAT_COLOR", "color", 4
    if array.dtype.kind in "iu" and width == 1:
        return "INT", "value", 1
    return {1: ("FLOAT", "value", 1), 3: ("FLOAT_VECTOR", "vector", 3),
            4: ("QUATERNION", "value", 4)}[width]


def set_points(obj: bpy.types.Object, positions: np.ndarray | None, attributes: dict[str, np.ndarray]) -> None:
    """Replace the points (unless ``positions`` is None) and set attributes, in place."""
    mesh = obj.data
    if positions is None:
        n = len(mesh.vertices)
    else:
        positions = np.ascontiguousarray(positions, np.float32).reshape(-1, 3)
        n = len(positions)
        if len(mesh.vertices) != n:
            mesh.clear_geometry()
            mesh.vertices.add(n)
        mesh.vertices.foreach_set("co", positions.ravel())
    for name, array in attributes.items():
        array = np.asarray(array)
        data_type, prop, width = _attribute_kind(array, name)
        if data_type == "FLOAT_COLOR" and array.ndim == 2 and array.shape[1] == 3:
            array = np.concatenate([array, np.ones((n, 1), array.dtype)], axis=1)
        attr = mesh.attributes.get(name)
        if attr is not None and (attr.data_type != data_type or attr.domain != "POINT"):
            mesh.attributes.remove(attr)
            attr = None
        if attr is None:
            attr = mesh.attributes.new(name, data_type, "POINT")
        dtype = np.int32 if data_type == "INT" else np.float32
        attr.data.foreach_set(prop, np.ascontiguousarray(array, dtype).reshape(n * width))
    mesh.update()


def get_attribute(obj: bpy.types.Object, name: str) -> np.ndarray:
    """A point attribute as a numpy array ([N] or [N, width])."""
    mesh = obj.data
    attr = mesh.attributes[name]
    n = len(mesh.vertices)
    if name == "position":
        out = np.empty(n * 3, np.float32)
        mesh.vertices.foreach_get("co", out)
        return out.reshape(n, 3)
    width = {"FLOAT": 1, "INT": 1, "FLOAT_VECTOR": 3, "QUATERNION": 4, "FLOAT_COLOR": 4}[attr.data_type]
    prop = {"FLOAT_VECTOR": "vector", "FLOAT_COLOR": "color"}.get(attr.data_type, "value")
    out = np.empty(n * width, np.int32 if attr.data_type == "INT" else np.float32)
    attr.data.foreach_get(prop, out)
    return out if width == 1 else out.reshape(n, width)


def color_by(obj: bpy.types.Object, name: str, palette: int = 0) -> None:
    """Colour the points by one attribute: colour-map bins, or RGB for ``color``."""
    mesh = obj.data
    n = len(mesh.vertices)
    note = ""
    t = np.ones(n)
    if name == "color" or name not in mesh.attributes:
        bins = np.full(n, -1, np.int32)
        note = "" if name == "color" else f"no '{name}' attribute: RGB colours"
    else:
        values = get_attribute(obj, name).astype(np.float64)
        if values.ndim == 2:
            values = values.mean(axis=1) if name == "scale" else np.linalg.norm(values, axis=1)
        lo, hi = (np.percentile(values, [2, 98]) if n else (0.0, 1.0))
        t = (values - lo) / (hi - lo) if hi > lo else np.full(n, 0.5)
        bins = np.clip((t * N_BINS).astype(np.int32), 0, N_BINS - 1)
        if n and not hi > lo:
            note = f"'{name}' is {lo:g} everywhere" + (" (the strategy computes none)" if lo == 0 else "")
        elif n:
            note = f"'{name}': {lo:.3g} … {hi:.3g} (2–98 %)"
    obj["promptgs_color_note"] = note
    if name == "color" and "color" in mesh.attributes:
        rgb = get_attribute(obj, "color")[:, :3]
    elif name == "color" or name not in mesh.attributes:
        rgb = np.full((n, 3), 0.6)
    else:
        rgb = colormap((bins + 0.5) / N_BINS, palette)
        bins = bins + palette * N_BINS
    set_points(obj, None, {"display_color": rgb, "display_value": np.clip(t, 0.0, 1.0).astype(np.float32)})
    set_points_attribute(obj, "display_bin", bins)
    obj["promptgs_color_by"] = name


def set_points_attribute(obj: bpy.types.Object, name: str, values: np.ndarray) -> None:
    mesh = obj.data
    data_type, prop, width = _attribute_kind(np.asarray(values), name)
    attr = mesh.attributes.get(name) or mesh.attributes.new(name, data_type, "POINT")
    attr.data.foreach_set(prop, np.ascontiguousarray(values).ravel())
    mesh.update()


def grid_step(centers: np.ndarray) -> float:
    """The spacing of points on a regular grid (e.g. voxel centres); 0 when unknown."""
    steps = []
    for axis in range(3):
        values = np.unique(np.round(np.asarray(centers, np.float64)[:, axis], 6))
        diffs = np.diff(values)
        diffs = diffs[diffs > 1e-9]
        if len(diffs):
            steps.append(float(diffs.min()))
    return min(steps) if steps else 0.0
