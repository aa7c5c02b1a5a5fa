"""Datasets: COLMAP scenes read through pycolmap into `Scene` / `Camera` (docs/interfaces.md)."""

from .colmap import load_colmap_scene
from .images import IMAGE_CACHE, set_image_cache_bytes
from .scene import Camera, Scene

__all__ = ["Camera", "Scene", "load_colmap_scene", "set_image_cache_bytes", "IMAGE_CACHE"]
