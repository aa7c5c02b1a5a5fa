"""Synthetic mountain / flames / tiny-drones dataset generator (Blender side).

Only ``bpy`` and ``numpy`` are used here. The layout (terrain heights, cameras, drone and
flame placement, projection checks) is pure numpy and runs without Blender; building and
rendering the scene needs ``bpy``. The engine's ``promptgs dataset`` command runs
:func:`generate.main` in a Blender process and then adds the COLMAP model.

Modules import ``bpy`` lazily so that ``layout`` can run in any Python with numpy.
"""
