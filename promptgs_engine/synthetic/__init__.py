"""Synthetic datasets rendered with Blender: ``promptgs dataset mountain`` (see docs/dataset.md).

The engine side never imports bpy: it runs ``promptgs_blender/dataset`` in a Blender
process, then builds the COLMAP model with pycolmap and writes ``scene.json``.
"""
