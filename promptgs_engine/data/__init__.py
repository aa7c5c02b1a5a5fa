"""Datasets: COLMAP scenes read through pycolmap into `Scene` / `Camera` (docs/interfaces.md)."""

from .camera_file import load_camera_file
from .colmap import load_colmap_scene
from .images import IMAGE_CACHE, set_image_cache_bytes
from .scene import Camera, Scene

__all__ = ["Camera", "Scene", "load_camera_file", "load_colmap_scene", "set_image_cache_bytes", "IMAGE_CACHE"]
