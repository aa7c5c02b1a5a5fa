"""Build the Blender scene of a layout: terrain, flames, drones, sun and sky, camera (bpy)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import bpy
import numpy as np

from . import geometry
from .terrain import Terrain, terrain_colors


@dataclass
class BuiltScene:
    scene: Any
    camera: Any
    terrain: Any
    drones: list[Any] = field(default_factory=list)  # in layout order (id = index + 1)
    flames: list[Any] = field(default_factory=list)  # flame meshes and their lights
    sky_dome: Any = None


def _mesh_object(name: str, verts: np.ndarray, faces: list[list[int]], collection: Any) -> Any:
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(np.asarray(verts, dtype=np.float64).tolist(), [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    collection.objects.link(obj)
    return obj


def _grid_object(name: str, terrain: Terrain, collection: Any) -> Any:
    """The terrain grid, filled with foreach_set (from_pydata is slow for big grids)."""
    verts = terrain.vertices().astype(np.float32)
    quads = terrain.quads().astype(np.int32)
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(verts))
    mesh.vertices.foreach_set("co", verts.ravel())
    mesh.loops.add(quads.size)
    mesh.loops.foreach_set("vertex_index", quads.ravel())
    mesh.polygons.add(len(quads))
    mesh.polygons.foreach_set("loop_start", np.arange(0, quads.size, 4, dtype=np.int32))
    mesh.polygons.foreach_set("use_smooth", np.ones(len(quads), dtype=bool))
    mesh.update(calc_edges=True)
    mesh.validate()
    obj = bpy.data.objects.new(name, mesh)
    collection.objects.link(obj)
    return obj


def _nodes(material: Any) -> tuple[Any, Any]:
    tree = material.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    return tree, out


def _terrain_material(texture: float = 1.0) -> Any:
    """Vertex colours with fine procedural variation and bump, so images hold SIFT texture;
    ``texture`` scales both (1: the mountain presets; less: a smoother ground)."""
    mat = bpy.data.materials.new("terrain")
    mat.use_nodes = True
    tree, out = _nodes(mat)
    n = tree.nodes
    attr = n.new("ShaderNodeAttribute")
    attr.attribute_name = "terrain_colour"
    coord = n.new("ShaderNodeTexCoord")
    fine = n.new("ShaderNodeTexNoise")
    fine.inputs["Scale"].default_value = 0.3
    fine.inputs["Detail"].default_value = 5.0
    fine.inputs["Roughness"].default_value = 0.6
    tree.links.new(coord.outputs["Object"], fine.inputs["Vector"])
    ramp = n.new("ShaderNodeMapRange")
    ramp.inputs["From Min"].default_value = 0.3
    ramp.inputs["From Max"].default_value = 0.7
    ramp.inputs["To Min"].default_value = 1.0 - 0.4 * texture
    ramp.inputs["To Max"].default_value = 1.0 + 0.4 * texture
    tree.links.new(fine.outputs["Fac"], ramp.inputs["Value"])
    mix = n.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    mix.blend_type = "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    tree.links.new(attr.outputs["Color"], mix.inputs["A"])
    tree.links.new(ramp.outputs["Result"], mix.inputs["B"])
    grain = n.new("ShaderNodeTexNoise")
    grain.inputs["Scale"].default_value = 2.0
    grain.inputs["Detail"].default_value = 2.0
    tree.links.new(coord.outputs["Object"], grain.inputs["Vector"])
    bump = n.new("ShaderNodeBump")
    bump.inputs["Strength"].default_value = 0.3 * texture
    tree.links.new(grain.outputs["Fac"], bump.inputs["Height"])
    bsdf = n.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Roughness"].default_value = 0.9
    tree.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])
    tree.links.new(bump.outputs["Normal"], bsdf.inputs["Normal"])
    tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return mat


def _flame_material(strength: float) -> Any:
    """Emission coloured by the vertex colour, fading to transparent where alpha is low."""
    mat = bpy.data.materials.new("flame")
    mat.use_nodes = True
    tree, out = _nodes(mat)
    n = tree.nodes
    attr = n.new("ShaderNodeAttribute")
    attr.attribute_name = "flame_colour"
    emit = n.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = strength
    tree.links.new(attr.outputs["Color"], emit.inputs["Color"])
    transparent = n.new("ShaderNodeBsdfTransparent")
    mix = n.new("ShaderNodeMixShader")
    tree.links.new(attr.outputs["Alpha"], mix.inputs["Fac"])
    tree.links.new(transparent.outputs["BSDF"], mix.inputs[1])
    tree.links.new(emit.outputs["Emission"], mix.inputs[2])
    tree.links.new(mix.outputs["Shader"], out.inputs["Surface"])
    return mat


def _plain_material(name: str, colour: tuple[float, float, float], roughness: float, glow: float = 0.0) -> Any:
    """Principled surface; ``glow`` > 0 adds emission in the same colour (navigation lights)."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    tree, out = _nodes(mat)
    bsdf = tree.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Base Color"].default_value = (*colour, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    if glow > 0:
        bsdf.inputs["Emission Color"].default_value = (*colour, 1.0)
        bsdf.inputs["Emission Strength"].default_value = glow
    tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return mat


def _add_colour_attribute(obj: Any, name: str, rgba: np.ndarray) -> None:
    attr = obj.data.color_attributes.new(name=name, type="FLOAT_COLOR", domain="POINT")
    attr.data.foreach_set("color", np.asarray(rgba, dtype=np.float32).ravel())


def _sun_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector from the ground towards the sun."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


SKY_AMBIENT = (0.42, 0.55, 0.8)  # colour of the uniform sky light


def _world(scene: Any, collection: Any, sun: dict[str, float]) -> Any:
    """Uniform sky light plus a sky dome that only camera rays see.

    Cycles renders a constant world much faster than a textured one (no importance map, no
    shader evaluation per bounce), so the physical sky texture sits on a far dome visible to
    the camera alone, and the light from the sky is a uniform blue.
    """
    world = bpy.data.worlds.new("sky_light")
    scene.world = world
    world.use_nodes = True
    tree = world.node_tree
    tree.nodes.clear()
    bg = tree.nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (*SKY_AMBIENT, 1.0)
    bg.inputs["Strength"].default_value = 0.6
    out = tree.nodes.new("ShaderNodeOutputWorld")
    tree.links.new(bg.outputs["Background"], out.inputs["Surface"])
    world.color = (0.0, 0.0, 0.0)  # what the mask (Workbench) pass shows behind everything

    mat = bpy.data.materials.new("sky_dome")
    mat.use_nodes = True
    mtree, mout = _nodes(mat)
    geo = mtree.nodes.new("ShaderNodeNewGeometry")
    sky = mtree.nodes.new("ShaderNodeTexSky")
    if "MULTIPLE_SCATTERING" in {e.identifier for e in sky.bl_rna.properties["sky_type"].enum_items}:
        sky.sky_type = "MULTIPLE_SCATTERING"
    if hasattr(sky, "sun_elevation"):
        sky.sun_elevation = math.radians(sun["elevation_deg"])
        sky.sun_rotation = math.radians(sun["azimuth_deg"] + 90.0)
    if hasattr(sky, "sun_disc"):
        sky.sun_disc = False
    norm = mtree.nodes.new("ShaderNodeVectorMath")
    norm.operation = "NORMALIZE"
    mtree.links.new(geo.outputs["Position"], norm.inputs[0])
    mtree.links.new(norm.outputs["Vector"], sky.inputs["Vector"])
    emit = mtree.nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 0.15
    mtree.links.new(sky.outputs["Color"], emit.inputs["Color"])
    mtree.links.new(emit.outputs["Emission"], mout.inputs["Surface"])

    radius, rings, segs = 1500.0, 16, 48
    verts = []
    for j in range(rings + 1):
        el = math.radians(-10.0 + 100.0 * j / rings)
        for i in range(segs):
            az = 2 * math.pi * i / segs
            verts.append((radius * math.cos(el) * math.cos(az), radius * math.cos(el) * math.sin(az), radius * math.sin(el)))
    faces = [[j * segs + i, j * segs + (i + 1) % segs, (j + 1) * segs + (i + 1) % segs, (j + 1) * segs + i]
             for j in range(rings) for i in range(segs)]
    dome = _mesh_object("sky_dome", np.array(verts), faces, collection)
    dome.data.materials.append(mat)
    dome.color = (0.0, 0.0, 0.0, 1.0)
    for ray in ("visible_diffuse", "visible_glossy", "visible_transmission", "visible_volume_scatter", "visible_shadow"):
        setattr(dome, ray, False)
    return dome


def build_scene(terrain: Terrain, layout: dict[str, Any], params: dict[str, Any]) -> BuiltScene:
    """A fresh scene with everything in ``layout``; render settings for Cycles on the CPU."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    coll = scene.collection

    # Terrain
    scorch = [(f["centre"][0], f["centre"][1]) for f in layout["flames"]]
    colours = terrain_colors(
        np.random.default_rng(layout["terrain"]["colour_seed"]), terrain, float(params["snow_line"]),
        scorch, 1.5 * float(params["flame_height"]), colour_jitter=float(params.get("colour_jitter", 0.2)),
    )
    terrain_obj = _grid_object("terrain", terrain, coll)
    _add_colour_attribute(terrain_obj, "terrain_colour", np.concatenate([colours, np.ones((len(colours), 1))], axis=1))
    terrain_obj.data.materials.append(_terrain_material(float(params.get("texture_strength", 1.0))))
    terrain_obj.color = (0.0, 0.0, 0.0, 1.0)

    # Flames, each with a warm point light for the glow on the ground
    built_flames = []
    flame_mat = _flame_material(strength=1.8)
    for f in layout["flames"]:
        verts, faces, rgba = geometry.flame_mesh(f["mesh_seed"], f["height"], f["radius"], f["n_tongues"])
        obj = _mesh_object(f"flame_{f['id']}", verts, faces, coll)
        _add_colour_attribute(obj, "flame_colour", rgba)
        obj.data.materials.append(flame_mat)
        obj.location = f["centre"]
        obj.color = (0.0, 0.0, 0.0, 1.0)
        light = bpy.data.lights.new(f"flame_light_{f['id']}", "POINT")
        light.color = (1.0, 0.45, 0.12)
        light.energy = 2500.0 * (f["height"] / 4.0) ** 2
        light.shadow_soft_size = f["radius"]
        light_obj = bpy.data.objects.new(f"flame_light_{f['id']}", light)
        light_obj.location = (f["centre"][0], f["centre"][1], f["centre"][2] + 0.5 * f["height"])
        coll.objects.link(light_obj)
        built_flames += [obj, light_obj]

    # Drones: frame in the drone colour, rotor discs a darker shade
    parts = geometry.drone_parts()
    materials: dict[str, tuple[Any, Any]] = {}
    drones = []
    for d in layout["drones"]:
        if d["color_name"] not in materials:
            c = tuple(d["color"])
            materials[d["color_name"]] = (
                _plain_material(f"drone_{d['color_name']}", c, 0.35, glow=float(params["drone_glow"])),
                _plain_material(f"rotor_{d['color_name']}", tuple(0.45 * x + 0.02 for x in c), 0.5),
            )
        frame_mat, rotor_mat = materials[d["color_name"]]
        verts = np.concatenate([parts["frame"][0], parts["rotors"][0]])
        n_frame = len(parts["frame"][1])
        faces = parts["frame"][1] + [[i + len(parts["frame"][0]) for i in f] for f in parts["rotors"][1]]
        obj = _mesh_object(f"drone_{d['id']:03d}", verts, faces, coll)
        obj.data.materials.append(frame_mat)
        obj.data.materials.append(rotor_mat)
        obj.data.polygons.foreach_set("material_index", np.array([0] * n_frame + [1] * (len(faces) - n_frame), dtype=np.int32))
        m = np.eye(4)
        m[:3, :3] = np.asarray(d["rotation"]) * d["size"]
        m[:3, 3] = d["centre"]
        obj.matrix_world = _matrix(m)
        drones.append(obj)

    # Sun and sky
    sun = layout["sun"]
    dome = _world(scene, coll, sun)
    sun_light = bpy.data.lights.new("sun", "SUN")
    sun_light.energy = 4.0
    sun_light.angle = math.radians(1.5)
    sun_obj = bpy.data.objects.new("sun", sun_light)
    direction = _sun_direction(sun["elevation_deg"], sun["azimuth_deg"])
    sun_obj.rotation_euler = _rotation_to(direction).to_euler()
    coll.objects.link(sun_obj)

    # Camera: Blender looks down -z with y up; sensor fit horizontal
    cam0 = layout["cameras"][0]
    cam_data = bpy.data.cameras.new("camera")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.sensor_width = 36.0
    cam_data.lens = cam0["fx"] * 36.0 / cam0["width"]
    cam_data.clip_start = 0.1
    cam_data.clip_end = 2000.0
    cam_obj = bpy.data.objects.new("camera", cam_data)
    coll.objects.link(cam_obj)
    scene.camera = cam_obj

    # Render settings
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(params["samples"])
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.seed = int(params["seed"])
    scene.cycles.use_animated_seed = False
    scene.cycles.use_denoising = bool(params["denoise"])
    scene.cycles.max_bounces = int(params["max_bounces"])
    scene.cycles.diffuse_bounces = min(2, int(params["max_bounces"]))
    scene.cycles.glossy_bounces = min(2, int(params["max_bounces"]))
    scene.cycles.transparent_max_bounces = 16
    scene.cycles.caustics_reflective = False
    scene.cycles.caustics_refractive = False
    scene.cycles.pixel_filter_type = "BOX"  # each pixel is the mean over its own area: tiny drones stay crisp
    scene.cycles.filter_width = 1.0
    scene.render.resolution_x = int(params["width"])
    scene.render.resolution_y = int(params["height"])
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"
    scene.render.image_settings.color_depth = "8"
    scene.view_settings.view_transform = "AgX"
    scene.view_settings.look = "AgX - Medium High Contrast"
    scene.render.use_persistent_data = True
    return BuiltScene(scene=scene, camera=cam_obj, terrain=terrain_obj, drones=drones, flames=built_flames, sky_dome=dome)


def _matrix(m: np.ndarray) -> Any:
    from mathutils import Matrix

    return Matrix([list(map(float, row)) for row in m])


def _rotation_to(direction: np.ndarray) -> Any:
    """Rotation taking a sun lamp's -z (its light direction) to point away from ``direction``."""
    from mathutils import Vector

    return Vector((float(direction[0]), float(direction[1]), float(direction[2]))).to_track_quat("Z", "Y")


def camera_matrix_world(world_to_camera: list[list[float]]) -> Any:
    """Blender camera matrix_world for a COLMAP world_to_camera (flip y and z camera axes)."""
    w2c = np.asarray(world_to_camera, dtype=np.float64)
    c2w = np.linalg.inv(w2c)
    c2w[:3, :3] = c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    return _matrix(c2w)
