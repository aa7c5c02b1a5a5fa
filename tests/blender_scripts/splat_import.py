"""Blender's own importers on Gaussian splat files (see tests/test_formats_blender.py).

For each file of ``config["files"]`` (a name and a path): a fresh empty scene, Blender's
importer for its type (``wm.ply_import``, ``wm.spz_import``, ``import_scene.gltf``), and
the imported point cloud's attributes saved as ``config["out"]/NAME.npz``, with the
object's type, point-cloud type and world matrix in the results.
"""

import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
from harness import bpy, check, config, finish  # noqa: E402

import numpy as np  # noqa: E402

OUT = Path(config["out"])
WIDTH = {"FLOAT": 1, "FLOAT_VECTOR": 3, "FLOAT4": 4, "QUATERNION": 4, "FLOAT_COLOR": 4}
FIELD = {"FLOAT_VECTOR": "vector", "FLOAT4": "vector", "FLOAT_COLOR": "color"}


def import_file(path: str) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    suffix = Path(path).suffix.lower()
    if suffix == ".ply":
        result = bpy.ops.wm.ply_import(filepath=path)
    elif suffix == ".spz":
        result = bpy.ops.wm.spz_import(filepath=path)
    else:
        result = bpy.ops.import_scene.gltf(filepath=path)
    assert result == {"FINISHED"}, f"{path}: import returned {result}"


def attributes(cloud) -> dict:
    out = {}
    for attr in cloud.attributes:
        if attr.data_type not in WIDTH or attr.name.startswith("."):
            continue
        values = np.empty(len(attr.data) * WIDTH[attr.data_type], dtype=np.float32)
        attr.data.foreach_get(FIELD.get(attr.data_type, "value"), values)
        out[attr.name] = values.reshape(len(attr.data), -1)
    return out


def make_check(name: str, path: str):
    def imported():
        import_file(path)
        objects = list(bpy.data.objects)
        assert len(objects) == 1, f"{len(objects)} objects after importing {path}"
        obj = objects[0]
        values = attributes(obj.data)
        np.savez(OUT / f"{name}.npz", **values)
        return {"object_type": obj.type, "cloud_type": getattr(obj.data, "type", None),
                "matrix_world": [list(row) for row in obj.matrix_world], "n": len(values.get("position", [])),
                "attributes": sorted(values)}

    imported.__name__ = name
    return imported


for name, path in config["files"]:
    check(make_check(name, path))

finish()
