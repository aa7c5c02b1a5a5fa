"""Cameras given as a JSON file rather than by a dataset: any pose, any intrinsics.

``promptgs render RUN --camera-file FILE`` renders them (the Blender add-on's *Render
Preview* writes one for the active camera). The file holds one camera object, or
``{"cameras": [...]}`` with several::

    {"name": "preview", "width": 800, "height": 600,
     "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
     "world_to_camera": [[...4 rows of 4...]]}

in dataset (COLMAP) world coordinates and COLMAP's camera convention (x right, y down,
z forward; pixel centres at integer + 0.5), as :class:`~promptgs_engine.data.Camera`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ..errors import DatasetError
from .scene import Camera


def _matrix(path: Path, index: int, item: dict, key: str, shape: tuple[int, int]) -> torch.Tensor:
    try:
        value = np.asarray(item[key], dtype=np.float64)
    except KeyError:
        raise DatasetError(f"{path}: camera {index} has no {key!r}") from None
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: camera {index}: {key!r} is not a matrix of numbers") from None
    if value.shape != shape:
        raise DatasetError(f"{path}: camera {index}: {key!r} must be {shape[0]}x{shape[1]}, got shape {value.shape}")
    if not np.isfinite(value).all():
        raise DatasetError(f"{path}: camera {index}: {key!r} holds NaN or inf")
    return torch.from_numpy(value).float()


def _size(path: Path, index: int, item: dict, key: str) -> int:
    value = item.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise DatasetError(f"{path}: camera {index}: {key!r} must be a positive whole number of pixels, got {value!r}")
    return value


def load_camera_file(path: str | Path) -> list[Camera]:
    """The cameras of a camera file; a one-line :class:`DatasetError` for anything unusable."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such camera file") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read camera file ({exc})") from None
    items = data.get("cameras") if isinstance(data, dict) and "cameras" in data else [data]
    if not isinstance(items, list) or not items or not all(isinstance(item, dict) for item in items):
        raise DatasetError(f"{path}: a camera file holds a camera object or {{\"cameras\": [objects]}}")
    cameras = []
    for index, item in enumerate(items):
        K = _matrix(path, index, item, "K", (3, 3))
        world_to_camera = _matrix(path, index, item, "world_to_camera", (4, 4))
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise DatasetError(f"{path}: camera {index}: focal lengths must be positive (K[0][0], K[1][1])")
        name = str(item.get("name") or f"camera_{index}")
        cameras.append(Camera(name, _size(path, index, item, "width"), _size(path, index, item, "height"),
                              K, world_to_camera, image_path=Path()))
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise DatasetError(f"{path}: two cameras share a name")
    return cameras


def camera_file_entry(camera: Camera) -> dict:
    """The JSON object of one camera (the inverse of :func:`load_camera_file`)."""
    return {"name": camera.name, "width": camera.width, "height": camera.height,
            "K": camera.K.double().tolist(), "world_to_camera": camera.world_to_camera.double().tolist()}
