"""Everything in ``scene.json`` that is computed after rendering: mask statistics, prompt
boxes around drone groups, SfM points near drones and on the terrain, the test split."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

PROMPT_MARGIN = 1.5  # metres added on every side of a drone group's bounding box
MIN_PROMPT_SIZE = 3.0  # metres: the smallest edge of a suggested prompt box


def read_mask(path: Path) -> np.ndarray:
    """[H, W] int64 instance ids of a 16-bit mask PNG (0 = no drone)."""
    return np.asarray(Image.open(path), dtype=np.int64)


def mask_statistics(root: Path, layout: dict[str, Any]) -> None:
    """Add to each drone view: mask pixel count, centroid (pixel centres at +0.5), extent and
    the distance between the centroid and the projected drone centre; per drone the number
    of training views whose mask holds it."""
    split = {c["name"]: c["split"] for c in layout["cameras"]}
    masks = {name: read_mask(root / "object_masks" / name) for name in split}
    for drone in layout["drones"]:
        n_train = 0
        for view in drone["views"]:
            ys, xs = np.nonzero(masks[view["name"]] == drone["id"])
            view["mask_pixels"] = int(len(xs))
            if len(xs):
                cx, cy = float(xs.mean() + 0.5), float(ys.mean() + 0.5)
                view["mask_centroid"] = [cx, cy]
                view["mask_extent_px"] = [int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]
                view["mask_error_px"] = float(np.hypot(cx - view["uv"][0], cy - view["uv"][1]))
                n_train += split[view["name"]] == "train"
        drone["n_train_views_in_mask"] = n_train


def prompt_boxes(drones: list[dict[str, Any]]) -> dict[str, Any]:
    """One axis-aligned prompt per drone group, in the prompt file format."""
    prompts = []
    for group in sorted({d["group"] for d in drones}):
        members = [d for d in drones if d["group"] == group]
        centres = np.array([d["centre"] for d in members])
        radius = max(d["radius"] for d in members)
        lo = centres.min(axis=0) - radius - PROMPT_MARGIN
        hi = centres.max(axis=0) + radius + PROMPT_MARGIN
        size = np.maximum(hi - lo, MIN_PROMPT_SIZE)
        prompts.append(
            {
                "center": ((lo + hi) / 2).tolist(),
                "size": size.tolist(),
                "rotation_wxyz": [1.0, 0.0, 0.0, 0.0],
                "weight": 1.0,
            }
        )
    return {"prompts": prompts}


def terrain_height(heights: np.ndarray, size: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear height of the terrain grid (row = y, column = x, centred, edge ``size``)."""
    n = heights.shape[0]
    step = size / (n - 1)
    gx = np.clip((x + size / 2) / step, 0, n - 1.000001)
    gy = np.clip((y + size / 2) / step, 0, n - 1.000001)
    ix, iy = np.floor(gx).astype(int), np.floor(gy).astype(int)
    fx, fy = gx - ix, gy - iy
    top = heights[iy, ix] * (1 - fx) + heights[iy, ix + 1] * fx
    bottom = heights[iy + 1, ix] * (1 - fx) + heights[iy + 1, ix + 1] * fx
    return top * (1 - fy) + bottom * fy


def sfm_statistics(points: np.ndarray, layout: dict[str, Any], heights: np.ndarray) -> dict[str, Any]:
    """Per drone: triangulated points within its bounding radius and within 1 m, nearest
    distance; overall: how many points lie on the terrain (within 1 m vertically)."""
    for drone in layout["drones"]:
        if len(points):
            d = np.linalg.norm(points - np.asarray(drone["centre"]), axis=1)
            drone["sfm_points_within_radius"] = int((d <= drone["radius"]).sum())
            drone["sfm_points_within_1m"] = int((d <= 1.0).sum())
            drone["sfm_nearest_point_m"] = float(d.min())
        else:
            drone["sfm_points_within_radius"] = drone["sfm_points_within_1m"] = 0
            drone["sfm_nearest_point_m"] = None
    if not len(points):
        return {"n_points": 0, "n_on_terrain": 0, "median_abs_height_error_m": None}
    dz = points[:, 2] - terrain_height(heights, float(layout["terrain"]["size"]), points[:, 0], points[:, 1])
    return {
        "n_points": int(len(points)),
        "n_on_terrain": int((np.abs(dz) <= 1.0).sum()),
        "median_abs_height_error_m": float(np.median(np.abs(dz))),
        "n_within_drone_radius": int(sum(d["sfm_points_within_radius"] for d in layout["drones"])),
    }


def test_names(layout: dict[str, Any]) -> list[str]:
    return [c["name"] for c in layout["cameras"] if c["split"] == "test"]
