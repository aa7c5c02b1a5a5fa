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

# Ground detail, the mountain's values (the `sparse` preset lowers them). A dataset made
# before these settings existed has exactly these.
GROUND_DETAIL: dict[str, Any] = {
    "ridge_octaves": 6,  # octaves of the ridged noise of the peaks
    "ridge_amplitude": 1.0,  # scale of the ridges
    "hill_octaves": 4,  # octaves of the rolling noise of the valley floor
    "colour_jitter": 0.2,  # per-vertex brightness variation of the ground colour (±)
    "texture_strength": 1.0,  # fine procedural colour variation and bump of the ground material
}
COMMON.update(GROUND_DETAIL)

# 40 views on two rings around the valley (`small` and `sparse`).
TWO_RINGS_40_VIEWS = [
    {"count": 24, "radius": 46.0, "altitude": 5.0, "arc_deg": 360.0, "start_deg": 0.0},
    {"count": 16, "radius": 34.0, "altitude": 14.0, "arc_deg": 360.0, "start_deg": 11.25},
]

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
        "camera_rings": TWO_RINGS_40_VIEWS,
        "n_flames": 2,
        "n_drones": 16,
        "n_drone_groups": 3,
        "min_views": 8,
    },
    # A sparser, smoother valley: gentle hills without snow, little fine texture, fewer
    # drones; 3DGS needs few Gaussians here, so what PromptGS adds shows (docs/dataset.md).
    "sparse": {
        "width": 320,
        "height": 240,
        "samples": 32,
        "terrain_resolution": 128,
        "rim_height": 18.0,
        "snow_line": 1000.0,
        "ridge_octaves": 3,
        "ridge_amplitude": 0.4,
        "hill_octaves": 2,
        "colour_jitter": 0.12,
        "texture_strength": 0.8,
        "camera_rings": TWO_RINGS_40_VIEWS,
        "n_flames": 2,
        "n_drones": 8,
        "n_drone_groups": 2,
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
