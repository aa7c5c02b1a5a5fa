"""Undistortion of non-pinhole COLMAP models into a cached pinhole copy (through pycolmap).

The cache folder holds `sparse/` (the undistorted PINHOLE model), `images/` (the
undistorted images, same relative names) and `stamp.json`. The stamp records a hash of
the source model files, the source image files' names, sizes and modification times,
and the undistortion options; a cache whose stamp differs is rebuilt.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Iterator

import pycolmap

from ..errors import DatasetError

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
CACHE_FORMAT = 1


def camera_model_name(camera: "pycolmap.Camera") -> str:
    return camera.model.name


def needs_undistortion(rec: "pycolmap.Reconstruction") -> bool:
    """Whether any camera of the model has distortion (is not a pinhole model)."""
    return any(camera_model_name(c) not in PINHOLE_MODELS for c in rec.cameras.values())


def check_undistortable(rec: "pycolmap.Reconstruction", model_dir: Path) -> None:
    """DatasetError for a camera model we cannot turn into a pinhole (e.g. equirectangular)."""
    for cam_id, cam in sorted(rec.cameras.items()):
        is_persp = cam.is_perspective() if callable(cam.is_perspective) else cam.is_perspective
        if not is_persp:
            raise DatasetError(
                f"{model_dir}: camera {cam_id} has camera model {camera_model_name(cam)}, "
                f"which is not supported (only perspective models can be undistorted to a pinhole)"
            )


@contextlib.contextmanager
def quiet_colmap_log() -> Iterator[None]:
    """Keep COLMAP's per-image info lines off stderr while undistorting."""
    old = pycolmap.logging.minloglevel
    try:
        pycolmap.logging.minloglevel = 1  # warnings and above
        yield
    finally:
        pycolmap.logging.minloglevel = old


def _cache_key(model_dir: Path, images_dir: Path, names: list[str], scaled_sizes: dict[int, tuple[int, int]]) -> str:
    h = hashlib.sha256()
    h.update(f"format {CACHE_FORMAT}\n".encode())
    for f in sorted(model_dir.iterdir()):
        if f.is_file() and f.suffix in (".bin", ".txt"):
            h.update(f.name.encode())
            with open(f, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
    for name in sorted(names):
        st = (images_dir / name).stat()
        h.update(f"{name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    h.update(json.dumps(sorted(scaled_sizes.items())).encode())
    h.update(str(pycolmap.UndistortCameraOptions().todict()).encode())
    return h.hexdigest()


def undistorted_model(
    rec: "pycolmap.Reconstruction",
    model_dir: Path,
    images_dir: Path,
    names: list[str],
    camera_sizes: dict[int, tuple[int, int]],
    cache: Path,
) -> tuple["pycolmap.Reconstruction", Path]:
    """A pinhole version of `rec` and the folder of its undistorted images, from `cache`.

    `camera_sizes` maps camera id to the (width, height) of that camera's image files;
    where it differs from the model's size (an `images_4` folder), the camera is
    rescaled before undistortion. Builds the cache when missing or stale.
    """
    key = _cache_key(model_dir, images_dir, names, camera_sizes)
    stamp = cache / "stamp.json"
    if stamp.is_file():
        try:
            if json.loads(stamp.read_text()).get("key") == key:
                return pycolmap.Reconstruction(str(cache / "sparse")), cache / "images"
        except (ValueError, OSError):
            pass  # unreadable or partial cache: rebuild it

    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DatasetError(f"{cache.parent}: cannot create the undistortion cache folder ({e}); pass cache_dir") from None
    work = cache.parent / f"{cache.name}.tmp-{os.getpid()}"
    shutil.rmtree(work, ignore_errors=True)
    try:
        src = rec
        if any((c.width, c.height) != camera_sizes.get(i, (c.width, c.height)) for i, c in rec.cameras.items()):
            src = pycolmap.Reconstruction(rec)
            for cam_id, (w, h) in camera_sizes.items():
                cam = src.cameras[cam_id]
                if (cam.width, cam.height) != (w, h):
                    cam.rescale(w, h)
                    src.cameras[cam_id] = cam
        in_model = work / "input_model"
        in_model.mkdir(parents=True)
        src.write(str(in_model))
        out = work / "out"
        with quiet_colmap_log():
            pycolmap.undistort_images(str(out), str(in_model), str(images_dir), image_names=names)
        shutil.rmtree(cache, ignore_errors=True)
        cache.mkdir(parents=True)
        (out / "sparse").rename(cache / "sparse")
        (out / "images").rename(cache / "images")
        stamp.write_text(json.dumps({"key": key, "source": str(model_dir), "images": str(images_dir)}))
    except OSError as e:
        raise DatasetError(f"{cache}: cannot write the undistorted copy ({e}); pass cache_dir") from None
    except ValueError as e:
        raise DatasetError(f"{model_dir}: undistortion failed ({str(e).splitlines()[0]})") from None
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return pycolmap.Reconstruction(str(cache / "sparse")), cache / "images"
