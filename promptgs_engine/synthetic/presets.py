"""Parameter presets of the synthetic mountain dataset.

A parameter set is a plain JSON-ready dict; the Blender-side layout
(``promptgs_blender/dataset/layout.py``) documents what each key means. ``scene.json``
records the full set, so a dataset can be regenerated from it.
"""

from __future__ import annotations

import copy
from typing import Any

COMMON: dict[str, Any] = {
    "seed": 0,
    "fov_deg": 60.0,  # horizontal field of view of the pinhole camera
    "target_height": 14.0,  # cameras look at a point this high over the valley centre (m)
    "target_jitter": 4.0,  # per-view random offset of the look-at point (m)
    "camera_clearance": 8.0,  # cameras stay at least this high above the ground (m)
    "terrain_size": 260.0,  # edge of the square terrain (m)
    "rim_height": 30.0,  # height of the peaks ringing the valley (m)
    "snow_line": 25.0,  # snow above this height (m)
    "flame_height": 5.5,  # mean flame height (m)
    "flame_region_radius": 25.0,  # flames stand within this distance of the valley centre (m)
    "drone_region_radius": 12.0,  # drone groups float within this distance of the centre (m)
    "drone_group_radius": 6.0,  # spread of the drones of one group (m)
    "drone_altitude": [4.0, 16.0],  # drone group heights above the ground (m)
    "drone_max_px_1080": 10.0,  # the paper's limit: at most 10 px across in 1080p images
    "min_visible_px": 1.5,
    "drone_glow": 1.5,  # emission of the drone frames in their own colour (lights), so 2-px drones show  # a view sees a drone only when it is at least this many px across
    "test_every": 8,  # held-out views: every 8th image in name order (index % 8 == 0)
    "sun_elevation_deg": 38.0,
    "sun_azimuth_deg": None,  # None: drawn from the seed
    "mask_supersample": 4,  # masks are rendered at this factor and reduced (see docs/dataset.md)
    "denoise": False,
    "max_bounces": 4,
}

PRESETS: dict[str, dict[str, Any]] = {
    "tiny": {
        "width": 480,
        "height": 270,
        "samples": 4,
        "terrain_resolution": 160,
        "camera_rings": [{"count": 12, "radius": 45.0, "altitude": 5.0, "arc_deg": 110.0, "start_deg": 200.0}],
        "n_flames": 1,
        "n_drones": 6,
        "n_drone_groups": 2,
        "min_views": 4,
    },
    "small": {
        "width": 480,
        "height": 270,
        "samples": 16,
        "terrain_resolution": 256,
        "camera_rings": [
            {"count": 24, "radius": 46.0, "altitude": 5.0, "arc_deg": 360.0, "start_deg": 0.0},
            {"count": 16, "radius": 34.0, "altitude": 14.0, "arc_deg": 360.0, "start_deg": 11.25},
        ],
        "n_flames": 2,
        "n_drones": 16,
        "n_drone_groups": 3,
        "min_views": 8,
    },
    "paper": {
        "width": 1920,
        "height": 1080,
        "samples": 64,
        "terrain_resolution": 512,
        "camera_rings": [
            {"count": 48, "radius": 48.0, "altitude": 5.0, "arc_deg": 360.0, "start_deg": 0.0},
            {"count": 40, "radius": 38.0, "altitude": 12.0, "arc_deg": 360.0, "start_deg": 4.5},
            {"count": 32, "radius": 28.0, "altitude": 22.0, "arc_deg": 360.0, "start_deg": 9.0},
        ],
        "n_flames": 3,
        "n_drones": 40,
        "n_drone_groups": 4,
        "drone_region_radius": 18.0,
        "min_views": 20,
        "mask_supersample": 2,
        "denoise": True,
    },
}


def preset_params(name: str) -> dict[str, Any]:
    """A fresh full parameter dict for a preset; ``KeyError`` for an unknown name."""
    params = copy.deepcopy(COMMON)
    params.update(copy.deepcopy(PRESETS[name]))
    params["preset"] = name
    return params
