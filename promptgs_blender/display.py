"""Points objects carrying per-point attributes, drawn with a geometry-nodes modifier.

From Blender 5.1 on (``PointCloud.resize``) the points are a point-cloud object; on 4.2 to
5.0, whose point clouds cannot be resized from Python, a points-only mesh. Either keeps
the data (``foreach_set`` of numpy arrays, no per-point Python) and can change its point
count from one snapshot to the next while the object stays the same. From 5.3 on a point
cloud can be Blender's own Gaussian splats (``type`` ``'GAUSSIAN_SPLAT'``), drawn and
rendered by Blender itself: :func:`set_native` turns the modifier off for them.

The "PromptGS Points" node group draws the points as point-cloud points (cheap: a
million in well under a second), as small ico-spheres (realized: about 12 s per million
to evaluate, so only for small sets) or as splats: one instance of a smooth
icosahedron per Gaussian, moved, turned by its ``rotation`` and stretched by
``SPLAT_SIGMAS`` times its ``scale``, never realized (instancing a million takes a
fraction of a second; the viewport draws the instances on the GPU). The "PromptGS Splat"
material makes each one an emitter of its ``display_color`` whose alpha (the Gaussian's
opacity) falls off as a Gaussian from the centre of its outline (from the angle between
the surface normal and the view ray: exact for a sphere, close for an ellipsoid), mixed
with a transparent shader: front faces only, stochastically blended by Cycles and by
EEVEE's dithered mode, so no sorting is needed. Colour: the ``display_color`` attribute
(the chosen attribute through a colour map, or the RGB colour) read by the materials in
Material Preview and Rendered shading; for Workbench, which ignores attributes, spheres
also get one of 16 colour-map materials per palette from ``display_bin``. Points whose
colour-map value ``display_value`` (0..1) is below the modifier's "Min Value" are not
drawn (the loss field shows its high-loss voxels only).
"""

from __future__ import annotations

import bpy
import numpy as np

N_BINS = 16
NODE_GROUP = "PromptGS Points"
NODE_GROUP_VERSION = 4  # bump when the group changes; older groups are rebuilt
DISPLAY_MATERIAL = "PromptGS Display"
SPLAT_MATERIAL = "PromptGS Splat"
SPLAT_SIGMAS = 3.0  # a splat's mesh reaches this many standard deviations along each axis
SPHERES_UP_TO = 50_000  # "auto" style: spheres up to this many points, plain points above
SPLATS_UP_TO = 500_000  # "auto" style, 4.2–5.2: splats up to this many Gaussians (10 M triangles), points above
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


def splat_material() -> bpy.types.Material:
    """Emission of the instancer's ``display_color`` with alpha × a Gaussian falloff."""
    mat = bpy.data.materials.get(SPLAT_MATERIAL)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(SPLAT_MATERIAL)
    mat.diffuse_color = (0.6, 0.6, 0.6, 1.0)
    mat.use_nodes = True
    if hasattr(mat, "surface_render_method"):
        mat.surface_render_method = "DITHERED"
    mat.use_backface_culling = True
    tree = mat.node_tree
    nodes, links = tree.nodes, tree.links
    nodes.clear()
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_type, attr.attribute_name = "INSTANCER", "display_color"
    geometry = nodes.new("ShaderNodeNewGeometry")
    facing = nodes.new("ShaderNodeVectorMath")
    facing.operation = "DOT_PRODUCT"
    links.new(geometry.outputs["Normal"], facing.inputs[0])
    links.new(geometry.outputs["Incoming"], facing.inputs[1])

    def math(operation, a, b):
        node = nodes.new("ShaderNodeMath")
        node.operation = operation
        for index, value in enumerate((a, b)):
            if isinstance(value, float):
                node.inputs[index].default_value = value
            else:
                links.new(value, node.inputs[index])
        return node.outputs[0]

    # the ray's distance from the centre, in units of the mesh's reach, is sqrt(1 - (N·I)²)
    cos2 = math("MULTIPLY", facing.outputs["Value"], facing.outputs["Value"])
    falloff = math("EXPONENT", math("MULTIPLY", math("SUBTRACT", 1.0, cos2), -0.5 * SPLAT_SIGMAS ** 2), 0.0)
    alpha = math("MULTIPLY", math("MULTIPLY", falloff, attr.outputs["Alpha"]),
                 math("SUBTRACT", 1.0, geometry.outputs["Backfacing"]))
    emit = nodes.new("ShaderNodeEmission")
    links.new(attr.outputs["Color"], emit.inputs["Color"])
    mix = nodes.new("ShaderNodeMixShader")
    links.new(alpha, mix.inputs["Fac"])
    links.new(nodes.new("ShaderNodeBsdfTransparent").outputs[0], mix.inputs[1])
    links.new(emit.outputs[0], mix.inputs[2])
    out = nodes.new("ShaderNodeOutputMaterial")
    links.new(mix.outputs[0], out.inputs["Surface"])
    return mat


def socket(sockets, name: str):
    """The shown socket called ``name`` among a node's inputs or outputs.

    Sockets are found by name, never by position: a node lists the sockets of every data
    type up to Blender 5.1 (hidden ones included), and only those of its current type
    from 5.2 on.
    """
    for item in sockets:
        if item.name == name and item.enabled:
            return item
    raise KeyError(f"no shown socket named {name!r}")


def node_group() -> bpy.types.NodeTree:
    """The shared geometry-nodes group (inputs: Geometry, Radius, Spheres, Min Value, Splats).

    The geometry is a points-only mesh or a point cloud; both end as points of the
    chosen radius, as ico-spheres on them, or (Splats) as instanced ellipsoids.
    """
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
    face.new_socket("Splats", in_out="INPUT", socket_type="NodeSocketBool").default_value = False
    face.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = group.nodes, group.links
    g_in, g_out = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")

    # hide points whose colour-map value (0..1) is below "Min Value"
    value = nodes.new("GeometryNodeInputNamedAttribute")
    value.data_type = "FLOAT"
    socket(value.inputs, "Name").default_value = "display_value"
    below = nodes.new("FunctionNodeCompare")
    below.data_type, below.operation = "FLOAT", "LESS_THAN"
    links.new(socket(value.outputs, "Attribute"), socket(below.inputs, "A"))
    links.new(socket(g_in.outputs, "Min Value"), socket(below.inputs, "B"))
    delete = nodes.new("GeometryNodeDeleteGeometry")
    delete.domain = "POINT"
    links.new(socket(g_in.outputs, "Geometry"), socket(delete.inputs, "Geometry"))
    links.new(socket(below.outputs, "Result"), socket(delete.inputs, "Selection"))

    # points of the chosen radius, from a mesh's vertices or a point cloud's points
    parts = nodes.new("GeometryNodeSeparateComponents")
    links.new(socket(delete.outputs, "Geometry"), socket(parts.inputs, "Geometry"))
    to_points = nodes.new("GeometryNodeMeshToPoints")
    links.new(socket(parts.outputs, "Mesh"), socket(to_points.inputs, "Mesh"))
    links.new(socket(g_in.outputs, "Radius"), socket(to_points.inputs, "Radius"))
    cloud = nodes.new("GeometryNodeSetPointRadius")
    links.new(socket(parts.outputs, "Point Cloud"), socket(cloud.inputs, "Points"))
    links.new(socket(g_in.outputs, "Radius"), socket(cloud.inputs, "Radius"))
    join = nodes.new("GeometryNodeJoinGeometry")
    links.new(socket(cloud.outputs, "Points"), socket(join.inputs, "Geometry"))
    links.new(socket(to_points.outputs, "Points"), socket(join.inputs, "Geometry"))
    points = socket(join.outputs, "Geometry")

    ico = nodes.new("GeometryNodeMeshIcoSphere")
    socket(ico.inputs, "Subdivisions").default_value = 1
    links.new(socket(g_in.outputs, "Radius"), socket(ico.inputs, "Radius"))
    instance = nodes.new("GeometryNodeInstanceOnPoints")
    links.new(points, socket(instance.inputs, "Points"))
    links.new(socket(ico.outputs, "Mesh"), socket(instance.inputs, "Instance"))
    realize = nodes.new("GeometryNodeRealizeInstances")
    links.new(socket(instance.outputs, "Instances"), socket(realize.inputs, "Geometry"))

    # plain points: one material reading display_color
    points_mat = nodes.new("GeometryNodeSetMaterial")
    socket(points_mat.inputs, "Material").default_value = display_material()
    links.new(points, socket(points_mat.inputs, "Geometry"))
    splats = _splat_instances(nodes, links, socket(delete.outputs, "Geometry"))
    # spheres: the same, then a colour-map material per display_bin (Workbench)
    spheres_mat = nodes.new("GeometryNodeSetMaterial")
    socket(spheres_mat.inputs, "Material").default_value = display_material()
    links.new(socket(realize.outputs, "Geometry"), socket(spheres_mat.inputs, "Geometry"))
    geometry = socket(spheres_mat.outputs, "Geometry")
    bins = nodes.new("GeometryNodeInputNamedAttribute")
    bins.data_type = "INT"
    socket(bins.inputs, "Name").default_value = "display_bin"
    for k in range(N_BINS * len(PALETTES)):
        equal = nodes.new("FunctionNodeCompare")
        equal.data_type, equal.operation = "INT", "EQUAL"
        links.new(socket(bins.outputs, "Attribute"), socket(equal.inputs, "A"))
        socket(equal.inputs, "B").default_value = k
        set_mat = nodes.new("GeometryNodeSetMaterial")
        socket(set_mat.inputs, "Material").default_value = bin_material(k)
        links.new(geometry, socket(set_mat.inputs, "Geometry"))
        links.new(socket(equal.outputs, "Result"), socket(set_mat.inputs, "Selection"))
        geometry = socket(set_mat.outputs, "Geometry")
    switch = nodes.new("GeometryNodeSwitch")
    switch.input_type = "GEOMETRY"
    links.new(socket(g_in.outputs, "Spheres"), socket(switch.inputs, "Switch"))
    links.new(socket(points_mat.outputs, "Geometry"), socket(switch.inputs, "False"))
    links.new(geometry, socket(switch.inputs, "True"))
    splat_switch = nodes.new("GeometryNodeSwitch")
    splat_switch.input_type = "GEOMETRY"
    links.new(socket(g_in.outputs, "Splats"), socket(splat_switch.inputs, "Switch"))
    links.new(switch.outputs[0], socket(splat_switch.inputs, "False"))
    links.new(splats, socket(splat_switch.inputs, "True"))
    links.new(splat_switch.outputs[0], socket(g_out.inputs, "Geometry"))
    return group


def _splat_instances(nodes, links, geometry):
    """Instances of a smooth unit icosahedron on the points: turned by ``rotation``,
    stretched by SPLAT_SIGMAS × ``scale``, with the splat material (not realized)."""
    ico = nodes.new("GeometryNodeMeshIcoSphere")
    socket(ico.inputs, "Radius").default_value = 1.0
    socket(ico.inputs, "Subdivisions").default_value = 1
    smooth = nodes.new("GeometryNodeSetShadeSmooth")
    mesh_input = "Mesh" if any(item.name == "Mesh" for item in smooth.inputs) else "Geometry"  # 5.3: "Mesh"
    links.new(socket(ico.outputs, "Mesh"), socket(smooth.inputs, mesh_input))
    material = nodes.new("GeometryNodeSetMaterial")
    socket(material.inputs, "Material").default_value = splat_material()
    links.new(smooth.outputs[0], socket(material.inputs, "Geometry"))
    rotation = nodes.new("GeometryNodeInputNamedAttribute")
    rotation.data_type = "QUATERNION"
    socket(rotation.inputs, "Name").default_value = "rotation"
    scale = nodes.new("GeometryNodeInputNamedAttribute")
    scale.data_type = "FLOAT_VECTOR"
    socket(scale.inputs, "Name").default_value = "scale"
    stretch = nodes.new("ShaderNodeVectorMath")
    stretch.operation = "SCALE"
    links.new(socket(scale.outputs, "Attribute"), stretch.inputs[0])
    socket(stretch.inputs, "Scale").default_value = SPLAT_SIGMAS
    instance = nodes.new("GeometryNodeInstanceOnPoints")
    links.new(geometry, socket(instance.inputs, "Points"))
    links.new(socket(material.outputs, "Geometry"), socket(instance.inputs, "Instance"))
    links.new(socket(rotation.outputs, "Attribute"), socket(instance.inputs, "Rotation"))
    links.new(socket(stretch.outputs, "Vector"), socket(instance.inputs, "Scale"))
    return socket(instance.outputs, "Instances")


def _socket_id(group: bpy.types.NodeTree, name: str) -> str:
    for item in group.interface.items_tree:
        if getattr(item, "in_out", None) == "INPUT" and item.name == name:
            return item.identifier
    raise KeyError(name)


def modifier_input(mod: bpy.types.Modifier, name: str):
    """The value of a geometry-nodes modifier's input, by the group socket's name."""
    identifier = _socket_id(mod.node_group, name)
    if hasattr(mod, "properties"):  # Blender 5.2+: inputs are no longer ID properties
        return getattr(mod.properties.inputs, identifier).value
    return mod[identifier]


def set_modifier_input(mod: bpy.types.Modifier, name: str, value) -> None:
    """Set a geometry-nodes modifier's input, by the group socket's name, on every line."""
    identifier = _socket_id(mod.node_group, name)
    if hasattr(mod, "properties"):
        getattr(mod.properties.inputs, identifier).value = value
    else:
        mod[identifier] = value


def use_spheres(style: str, n: int) -> bool:
    """Whether a display style ('AUTO', 'SPLATS', 'SPHERES', 'POINTS') draws ``n`` points
    (not Gaussians: the sparse points, the loss field) as spheres."""
    return style == "SPHERES" or (style in ("AUTO", "SPLATS") and n <= SPHERES_UP_TO)


def set_style(obj: bpy.types.Object, radius: float | None = None, spheres: bool | None = None,
              min_value: float | None = None, splats: bool | None = None) -> None:
    """Set the display modifier's inputs (None: leave as is)."""
    mod = obj.modifiers.get("PromptGS Display")
    if mod is None:
        return
    if splats is not None:
        set_modifier_input(mod, "Splats", bool(splats))
    if min_value is not None:
        set_modifier_input(mod, "Min Value", float(min_value))
    if radius is not None:
        set_modifier_input(mod, "Radius", float(radius))
    if spheres is not None:
        set_modifier_input(mod, "Spheres", bool(spheres))
    obj.update_tag()


POINTS_TYPES = ("MESH", "POINTCLOUD")


def point_clouds_supported() -> bool:
    """Whether this Blender can size a point cloud from Python (5.1+)."""
    return "resize" in bpy.types.PointCloud.bl_rna.functions


def native_splats_supported() -> bool:
    """Whether this Blender draws and renders Gaussian splats itself (5.3+)."""
    kind = bpy.types.PointCloud.bl_rna.properties.get("type")
    return kind is not None and "GAUSSIAN_SPLAT" in kind.enum_items.keys()


def set_native(obj: bpy.types.Object, native: bool) -> None:
    """Let Blender draw a point cloud as its own Gaussian splats (5.3+), the display
    modifier off; or as plain points through the modifier."""
    if obj.type == "POINTCLOUD" and native_splats_supported():
        kind = "GAUSSIAN_SPLAT" if native else "POINTS"
        if obj.data.type != kind:
            obj.data.type = kind
    native = native and obj.type == "POINTCLOUD" and native_splats_supported()
    mod = obj.modifiers.get("PromptGS Display")
    if mod is not None and (mod.show_viewport == native or mod.show_render == native):
        mod.show_viewport = mod.show_render = not native


def is_points_object(obj: bpy.types.Object | None) -> bool:
    return obj is not None and obj.type in POINTS_TYPES


def points_object(name: str, collection: bpy.types.Collection, parent: bpy.types.Object | None = None,
                  radius: float = 0.01, spheres: bool = True, editable: bool = False) -> bpy.types.Object:
    """The named points object, created on first use (its identity survives updates).

    A point cloud where Blender can resize one from Python (5.1+), else a points-only mesh;
    ``editable`` asks for a mesh on every line (points a user selects in Edit Mode). An
    object of the other kind, from a file saved with another line, is kept and used.
    """
    obj = bpy.data.objects.get(name)
    if not is_points_object(obj):
        cloud = point_clouds_supported() and not editable
        data = bpy.data.pointclouds.new(name) if cloud else bpy.data.meshes.new(name)
        obj = bpy.data.objects.new(name, data)
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


def point_count(obj: bpy.types.Object) -> int:
    """Points of a points object (mesh vertices or point-cloud points)."""
    return len(obj.data.points) if obj.type == "POINTCLOUD" else len(obj.data.vertices)


def _attribute_kind(array: np.ndarray, name: str) -> tuple[str, str, int]:
    width = 1 if array.ndim == 1 else array.shape[1]
    if name == "color" or name == "display_color":
        return "FLOAT_COLOR", "color", 4
    if array.dtype.kind in "iu" and width == 1:
        return "INT", "value", 1
    return {1: ("FLOAT", "value", 1), 3: ("FLOAT_VECTOR", "vector", 3),
            4: ("QUATERNION", "value", 4)}[width]


def _resize(obj: bpy.types.Object, n: int) -> None:
    """Give a points object ``n`` points (their values are set next).

    A point cloud gets a new datablock of that size: Blender 5.1.2 corrupts memory when a
    point cloud that already has points is resized in place. The object stays the same.
    """
    if obj.type == "POINTCLOUD":
        old = obj.data
        name = old.name
        cloud = bpy.data.pointclouds.new(name)
        cloud.resize(n)
        if getattr(old, "type", "POINTS") != "POINTS":
            cloud.type = old.type
        obj.data = cloud
        if old.users == 0:
            bpy.data.pointclouds.remove(old)
            cloud.name = name
    else:
        obj.data.clear_geometry()
        obj.data.vertices.add(n)


def _data_updated(obj: bpy.types.Object) -> None:
    if obj.type == "POINTCLOUD":
        obj.data.update_tag()
    else:
        obj.data.update()


FOREACH = {"FLOAT": ("value", 1), "INT": ("value", 1), "FLOAT_VECTOR": ("vector", 3), "FLOAT4": ("vector", 4),
           "QUATERNION": ("value", 4), "FLOAT_COLOR": ("color", 4)}  # data type: (foreach key, width)


def set_attribute(data, name: str, data_type: str, array: np.ndarray) -> None:
    """Set (or create) a point attribute of a mesh or point cloud from a numpy array."""
    attr = data.attributes.get(name)
    if attr is not None and (attr.data_type != data_type or attr.domain != "POINT"):
        data.attributes.remove(attr)
        attr = None
    if attr is None:
        attr = data.attributes.new(name, data_type, "POINT")
    prop, _ = FOREACH[data_type]
    attr.data.foreach_set(prop, np.ascontiguousarray(array, np.int32 if data_type == "INT" else np.float32).ravel())


def set_points(obj: bpy.types.Object, positions: np.ndarray | None, attributes: dict[str, np.ndarray]) -> None:
    """Replace the points (unless ``positions`` is None) and set attributes, in place."""
    if positions is None:
        n = point_count(obj)
    else:
        positions = np.ascontiguousarray(positions, np.float32).reshape(-1, 3)
        n = len(positions)
        if point_count(obj) != n:
            _resize(obj, n)
        obj.data.attributes["position"].data.foreach_set("vector", positions.ravel())
    for name, array in attributes.items():
        array = np.asarray(array)
        data_type, _, width = _attribute_kind(array, name)
        if data_type == "FLOAT_COLOR" and array.ndim == 2 and array.shape[1] == 3:
            array = np.concatenate([array, np.ones((n, 1), array.dtype)], axis=1)
        set_attribute(obj.data, name, data_type, array.reshape(n * width))
    _data_updated(obj)


def get_attribute(obj: bpy.types.Object | bpy.types.ID, name: str) -> np.ndarray:
    """A point attribute of an object's data (or of a mesh or point cloud) as a numpy
    array ([N] or [N, width])."""
    data = obj.data if isinstance(obj, bpy.types.Object) else obj
    attr = data.attributes[name]
    n = len(attr.data)
    prop, width = FOREACH[attr.data_type]
    out = np.empty(n * width, np.int32 if attr.data_type == "INT" else np.float32)
    attr.data.foreach_get(prop, out)
    return out if width == 1 else out.reshape(n, width)


def color_by(obj: bpy.types.Object, name: str, palette: int = 0, sources: dict[str, np.ndarray] | None = None,
             alpha: np.ndarray | None = None) -> None:
    """Colour the points by one attribute: colour-map bins, or RGB for ``color``.

    ``sources`` gives values that are not stored under their name (e.g. a Gaussian's
    opacity, or ``color``: linear RGB to show as it is); ``alpha`` the colour's alpha
    (the splats' opacity; 1 when None).
    """
    sources = sources or {}
    attributes = obj.data.attributes
    n = point_count(obj)
    note = ""
    t = np.ones(n)
    known = name in sources or name in attributes
    if name == "color" or not known:
        bins = np.full(n, -1, np.int32)
        note = "" if name == "color" else f"no '{name}' attribute: RGB colours"
    else:
        values = np.asarray(sources[name] if name in sources else get_attribute(obj, name), np.float64)
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
    if name == "color" and "color" in sources:
        rgb = sources["color"]
    elif name == "color" and "color" in attributes:
        rgb = get_attribute(obj, "color")[:, :3]
    elif name == "color" or not known:
        rgb = np.full((n, 3), 0.6)
    else:
        rgb = colormap((bins + 0.5) / N_BINS, palette)
        bins = bins + palette * N_BINS
    rgba = np.empty((n, 4), np.float32)
    rgba[:, :3] = rgb
    rgba[:, 3] = 1.0 if alpha is None else alpha
    set_points(obj, None, {"display_color": rgba, "display_value": np.clip(t, 0.0, 1.0).astype(np.float32),
                           "display_bin": bins})
    obj["promptgs_color_by"] = name


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
