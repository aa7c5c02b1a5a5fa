"""Proposed prompt cubes drawn in their own colour in every 3D viewport.

Blender draws every empty in the theme's colour (an object's colour does not reach an
empty's wireframe), so a proposed cube would look like an accepted prompt. A ``POST_VIEW``
draw handler on ``SpaceView3D``, added when the add-on is registered and removed when it
is unregistered, draws the 12 edges of each visible proposed cube over it with the
``gpu`` module's builtin ``POLYLINE_UNIFORM_COLOR`` shader (the same name and uniforms
on Blender 4.2 to 5.2; it draws lines wider than a pixel on every GPU backend): orange, a
lighter orange when selected, in front of everything as the cube itself is. Accepted
prompts keep the theme colour. Blender draws nothing in background mode; the geometry
(:func:`cube_edges`, :func:`proposed_edges`) is plain numpy.
"""

from __future__ import annotations

import bpy
import numpy as np

from . import proposals

COLOR = proposals.COLOR
SELECTED_COLOR = (1.0, 0.75, 0.35, 1.0)
LINE_WIDTH = 2.0  # pixels

# The unit cube of a CUBE empty (corners at ±1 × display size) and its 12 edges.
CORNERS = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]

_handler = None


def cube_edges(matrix, size: float = 1.0) -> np.ndarray:
    """[24, 3] float32: the 12 edges (pairs of world points) of a CUBE empty with this
    world matrix and display size."""
    m = np.array(matrix, dtype=np.float64).reshape(4, 4)
    world = (CORNERS * size) @ m[:3, :3].T + m[:3, 3]
    return world[np.array(EDGES).ravel()].astype(np.float32)


def _visible(obj: bpy.types.Object, context) -> bool:
    space = getattr(context, "space_data", None)
    view_layer = getattr(context, "view_layer", None)
    try:
        if space is not None and space.type == "VIEW_3D":
            return obj.visible_get(view_layer=view_layer, viewport=space)
        return obj.visible_get(view_layer=view_layer) if view_layer is not None else obj.visible_get()
    except (RuntimeError, TypeError, ReferenceError):
        return False


def proposed_edges(context) -> tuple[np.ndarray, np.ndarray]:
    """The edges of the visible proposed cubes: (not selected, selected), each [24·n, 3]."""
    plain, selected = [], []
    for obj in proposals.proposed_objects(context.scene):
        if obj.empty_display_type != "CUBE" or not _visible(obj, context):
            continue
        (selected if obj.select_get() else plain).append(cube_edges(obj.matrix_world, obj.empty_display_size))
    empty = np.zeros((0, 3), np.float32)
    return (np.concatenate(plain) if plain else empty), (np.concatenate(selected) if selected else empty)


def draw_lines(edges: np.ndarray, color, viewport_size: tuple[float, float]) -> None:
    """Draw line segments (pairs of points, world coordinates) with the current view and
    projection matrices, over everything."""
    import gpu
    from gpu_extras.batch import batch_for_shader

    shader = gpu.shader.from_builtin("POLYLINE_UNIFORM_COLOR")
    batch = batch_for_shader(shader, "LINES", {"pos": [tuple(p) for p in edges]})
    depth, blend = gpu.state.depth_test_get(), gpu.state.blend_get()
    gpu.state.depth_test_set("NONE")
    gpu.state.blend_set("ALPHA")
    shader.bind()
    shader.uniform_float("viewportSize", viewport_size)
    shader.uniform_float("lineWidth", LINE_WIDTH)
    shader.uniform_float("color", color)
    batch.draw(shader)
    gpu.state.depth_test_set(depth)
    gpu.state.blend_set(blend)


def draw(context=None) -> None:
    """The viewport callback: the proposed cubes in their colour."""
    context = context or bpy.context
    if getattr(context, "scene", None) is None or bpy.data.collections.get(proposals.PROPOSED) is None:
        return
    plain, selected = proposed_edges(context)
    if not len(plain) and not len(selected):
        return
    import gpu

    _, _, width, height = gpu.state.viewport_get()
    for edges, color in ((plain, COLOR), (selected, SELECTED_COLOR)):
        if len(edges):
            draw_lines(edges, color, (float(width), float(height)))


def _callback() -> None:
    draw(bpy.context)


def handler():
    """The registered draw handler, or None."""
    return _handler


def register():
    global _handler
    if _handler is None:
        _handler = bpy.types.SpaceView3D.draw_handler_add(_callback, (), "WINDOW", "POST_VIEW")


def unregister():
    global _handler
    if _handler is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_handler, "WINDOW")
        _handler = None
