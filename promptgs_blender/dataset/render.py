"""Render colour images (Cycles), instance masks (Workbench) and drone-free test views (bpy).

Instance masks: every drone object gets a flat colour that encodes its id; the Workbench
engine renders them without anti-aliasing at ``mask_supersample`` times the image size
(terrain black; flames and sky dome hidden, so drones behind a flame still count), and each image pixel
takes the id that covers most of its sub-pixels (0 where none does). A drone that covers
any sub-pixel of a pixel is therefore in the mask, as it tints that pixel in the image.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable

import bpy
import numpy as np

from .build import BuiltScene, camera_matrix_world
from .png16 import write_png16

Progress = Callable[[str, int, int], None]


def _render_to(scene: Any, path: Path) -> None:
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def render_images(built: BuiltScene, cameras: list[dict[str, Any]], folder: Path, progress: Progress, stage: str) -> None:
    """Cycles render of every camera into ``folder/<name>``."""
    folder.mkdir(parents=True, exist_ok=True)
    progress(stage, 0, len(cameras))
    for i, cam in enumerate(cameras):
        built.camera.matrix_world = camera_matrix_world(cam["world_to_camera"])
        _render_to(built.scene, folder / cam["name"])
        progress(stage, i + 1, len(cameras))


def _id_colour(drone_id: int) -> tuple[float, float, float, float]:
    """Flat colour of a drone in the mask pass: red = id low byte, green = high byte, blue = flag."""
    return ((drone_id % 256) / 255.0, (drone_id // 256) / 255.0, 1.0, 1.0)


def _decode_ids(path: Path, width: int, height: int) -> np.ndarray:
    """[H, W] ids from a mask-pass PNG (row 0 at the top)."""
    img = bpy.data.images.load(str(path), check_existing=False)
    try:
        img.colorspace_settings.name = "Non-Color"
        px = np.empty(width * height * 4, dtype=np.float32)
        img.pixels.foreach_get(px)
    finally:
        bpy.data.images.remove(img)
    rgba = np.rint(px.reshape(height, width, 4)[::-1] * 255.0).astype(np.int64)
    ids = rgba[..., 0] + 256 * rgba[..., 1]
    return np.where(rgba[..., 2] == 255, ids, 0)


def reduce_ids(ids: np.ndarray, factor: int) -> np.ndarray:
    """[H*f, W*f] sub-pixel ids to [H, W]: per pixel the id covering most sub-pixels, 0 if none."""
    hh, ww = ids.shape
    blocks = ids.reshape(hh // factor, factor, ww // factor, factor).transpose(0, 2, 1, 3).reshape(hh // factor, ww // factor, -1)
    best = np.zeros(blocks.shape[:2], dtype=np.int64)
    best_count = np.zeros(blocks.shape[:2], dtype=np.int64)
    for value in np.unique(ids):
        if value == 0:
            continue
        count = (blocks == value).sum(axis=-1)
        better = count > best_count
        best[better] = value
        best_count[better] = count[better]
    return best


def render_masks(built: BuiltScene, cameras: list[dict[str, Any]], folder: Path, factor: int, progress: Progress) -> None:
    """16-bit instance-id PNGs (0 = no drone, k = drone k) into ``folder/<name>``."""
    folder.mkdir(parents=True, exist_ok=True)
    scene = built.scene
    saved = {
        "engine": scene.render.engine,
        "x": scene.render.resolution_x,
        "y": scene.render.resolution_y,
        "view": scene.view_settings.view_transform,
    }
    width, height = saved["x"], saved["y"]
    scene.render.engine = "BLENDER_WORKBENCH"
    shading = scene.display.shading
    shading.light = "FLAT"
    shading.color_type = "OBJECT"
    shading.show_shadows = False
    shading.show_cavity = False
    shading.show_object_outline = False
    shading.show_specular_highlight = False
    shading.show_xray = False
    shading.background_type = "WORLD"
    scene.display.render_aa = "OFF"
    scene.view_settings.view_transform = "Raw"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.render.dither_intensity = 0.0
    scene.render.resolution_x = width * factor
    scene.render.resolution_y = height * factor
    hidden = built.flames + ([built.sky_dome] if built.sky_dome is not None else [])
    for obj in hidden:
        obj.hide_render = True
    for k, obj in enumerate(built.drones):
        obj.color = _id_colour(k + 1)
    tmp = folder / f".mask_pass_{os.getpid()}.png"
    try:
        for i, cam in enumerate(cameras):
            built.camera.matrix_world = camera_matrix_world(cam["world_to_camera"])
            _render_to(scene, tmp)
            ids = _decode_ids(tmp, width * factor, height * factor)
            write_png16(folder / cam["name"], reduce_ids(ids, factor))
            progress("masks", i + 1, len(cameras))
    finally:
        tmp.unlink(missing_ok=True)
        for obj in hidden:
            obj.hide_render = False
        scene.render.engine = saved["engine"]
        scene.render.resolution_x, scene.render.resolution_y = width, height
        scene.view_settings.view_transform = saved["view"]


def render_all(built: BuiltScene, layout: dict[str, Any], params: dict[str, Any], out: Path, progress: Progress) -> None:
    """images/ (all views), gt_nodrones/ (test views, drones hidden), object_masks/ (all views)."""
    cameras = layout["cameras"]
    render_images(built, cameras, out / "images", progress, "images")
    test = [c for c in cameras if c["split"] == "test"]
    for obj in built.drones:
        obj.hide_render = True
    try:
        render_images(built, test, out / "gt_nodrones", progress, "gt_nodrones")
    finally:
        for obj in built.drones:
            obj.hide_render = False
    render_masks(built, cameras, out / "object_masks", int(params["mask_supersample"]), progress)


def progress_printer(stage: str, done: int, total: int) -> None:
    """Report progress on stdout as one marked JSON line (the engine's runner reads these)."""
    print("PROMPTGS_PROGRESS " + json.dumps({"stage": stage, "done": done, "total": total}), flush=True)
