"""Scene layout: terrain, cameras, flames and drones, with the drone-size checks (no bpy).

Everything random comes from one ``numpy.random.Generator`` seeded with ``params["seed"]``,
drawn in a fixed order, so one seed gives one layout on every machine.

Camera convention (COLMAP): x right, y down, z forward; ``world_to_camera`` maps world
points to camera coordinates and a pixel centre (col i, row j) sits at (i + 0.5, j + 0.5).
Blender world = dataset world (identity).

Drone size rule (see docs/dataset.md): a drone's size in an image is the larger side of
the bounding rectangle of its projected 3D bounding box. In every image whose frame it
touches it is at most ``max_px = drone_max_px_1080 * height / 1080`` pixels across (the
paper: at most 10 px in 1080p images). It counts as seen by a view when its centre is in
the frame, no terrain lies between the camera and its centre, and it is at least
``min_visible_px`` across; every drone is seen by at least ``min_views`` training views.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .terrain import Terrain, make_terrain

# Unit drone (size 1 across, origin at the body centre): the half extents of its bounding box.
DRONE_BOX_MIN = np.array([-0.5, -0.5, -0.2])
DRONE_BOX_MAX = np.array([0.5, 0.5, 0.09])

DRONE_COLORS: list[tuple[str, tuple[float, float, float]]] = [
    ("white", (0.9, 0.9, 0.9)),
    ("red", (0.8, 0.02, 0.02)),
    ("yellow", (0.9, 0.7, 0.02)),
    ("orange", (0.95, 0.3, 0.02)),
    ("black", (0.01, 0.01, 0.01)),
    ("magenta", (0.8, 0.03, 0.6)),
]


class LayoutError(ValueError):
    """Parameters that cannot give a valid scene (the message is one line for the user)."""


def max_drone_px(params: dict[str, Any]) -> float:
    """The size limit at this resolution: the 1080p limit scaled with the image height."""
    return float(params["drone_max_px_1080"]) * int(params["height"]) / 1080.0


def check_params(params: dict[str, Any]) -> None:
    """Raise :class:`LayoutError` naming the first impossible parameter."""
    if int(params["width"]) < 16 or int(params["height"]) < 16:
        raise LayoutError(f"image size {params['width']}x{params['height']} is too small (at least 16x16)")
    rings = params["camera_rings"]
    n_views = sum(int(r["count"]) for r in rings)
    if n_views < 1:
        raise LayoutError("zero views: the camera rings hold no cameras")
    test_every = int(params["test_every"])
    n_train = sum(1 for i in range(n_views) if test_every <= 0 or i % test_every != 0)
    if int(params["min_views"]) < 1:
        raise LayoutError(f"min_views must be at least 1, got {params['min_views']}")
    if n_train < int(params["min_views"]):
        raise LayoutError(
            f"{n_views} views give {n_train} training views, fewer than min_views={params['min_views']}"
        )
    if float(params["drone_max_px_1080"]) > 10.0:
        raise LayoutError(
            f"drones of {params['drone_max_px_1080']} px at 1080p are larger than the size limit (10 px at 1080p)"
        )
    if float(params["drone_max_px_1080"]) <= 0:
        raise LayoutError("drone_max_px_1080 must be positive")
    if max_drone_px(params) < float(params["min_visible_px"]):
        raise LayoutError(
            f"at {params['height']} px image height drones may be at most {max_drone_px(params):.2f} px across, "
            f"below min_visible_px={params['min_visible_px']}: use a larger image or a smaller min_visible_px"
        )
    if int(params["n_drones"]) < 1:
        raise LayoutError(f"n_drones must be at least 1, got {params['n_drones']}")
    if not 1 <= int(params["n_drone_groups"]) <= int(params["n_drones"]):
        raise LayoutError(f"n_drone_groups must be between 1 and n_drones, got {params['n_drone_groups']}")
    if int(params["n_flames"]) < 0:
        raise LayoutError(f"n_flames must not be negative, got {params['n_flames']}")
    if int(params["samples"]) < 1:
        raise LayoutError(f"samples must be at least 1, got {params['samples']}")


# ---------------------------------------------------------------------------- cameras


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4×4 COLMAP world_to_camera of a camera at ``centre`` looking at ``target``, world +z up."""
    f = target - centre
    f = f / np.linalg.norm(f)
    r = np.cross(f, np.array([0.0, 0.0, 1.0]))
    r = r / np.linalg.norm(r)
    d = np.cross(f, r)
    r_c2w = np.stack([r, d, f], axis=1)
    w2c = np.eye(4)
    w2c[:3, :3] = r_c2w.T
    w2c[:3, 3] = -r_c2w.T @ centre
    return w2c


def intrinsics(params: dict[str, Any]) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of the shared pinhole camera: square pixels, centred principal point."""
    w, h = int(params["width"]), int(params["height"])
    fx = w / 2.0 / math.tan(math.radians(float(params["fov_deg"])) / 2.0)
    return fx, fx, w / 2.0, h / 2.0


def make_cameras(rng: np.random.Generator, params: dict[str, Any], terrain: Terrain) -> list[dict[str, Any]]:
    """Cameras on rings (arcs) around the valley centre, all looking near the centre."""
    fx, fy, cx, cy = intrinsics(params)
    target_z = float(terrain.height_at(0.0, 0.0)) + float(params["target_height"])
    jitter = float(params["target_jitter"])
    cams: list[dict[str, Any]] = []
    for ring in params["camera_rings"]:
        count = int(ring["count"])
        arc = float(ring["arc_deg"])
        start = math.radians(float(ring.get("start_deg", 0.0)))
        full = abs(arc - 360.0) < 1e-6
        for k in range(count):
            frac = k / count if full else (k / max(count - 1, 1))
            a = start + math.radians(arc) * frac
            x, y = float(ring["radius"]) * math.cos(a), float(ring["radius"]) * math.sin(a)
            ground = float(terrain.height_at(x, y))
            z = max(target_z + float(ring["altitude"]), ground + float(params["camera_clearance"]))
            target = np.array([0.0, 0.0, target_z]) + rng.uniform(-jitter, jitter, size=3) * np.array([1, 1, 0.3])
            cams.append({"centre": np.array([x, y, z]), "world_to_camera": look_at(np.array([x, y, z]), target)})
    names = [f"{i:04d}.png" for i in range(len(cams))]
    test_every = int(params["test_every"])
    out = []
    for i, (name, cam) in enumerate(zip(names, cams)):
        out.append(
            {
                "name": name,
                "split": "test" if test_every > 0 and i % test_every == 0 else "train",
                "width": int(params["width"]),
                "height": int(params["height"]),
                "fx": fx,
                "fy": fy,
                "cx": cx,
                "cy": cy,
                "world_to_camera": cam["world_to_camera"],
                "centre": cam["centre"],
            }
        )
    return out


def project(cams: list[dict[str, Any]], points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [V, P, 2] and depths [V, P] of world points [P, 3] in every camera."""
    w2c = np.stack([c["world_to_camera"] for c in cams])  # [V, 4, 4]
    k = np.array([[c["fx"], c["fy"], c["cx"], c["cy"]] for c in cams])  # [V, 4]
    pc = np.einsum("vij,pj->vpi", w2c[:, :3, :3], points) + w2c[:, None, :3, 3]
    z = pc[..., 2]
    safe = np.where(np.abs(z) < 1e-9, 1e-9, z)
    u = k[:, None, 0] * pc[..., 0] / safe + k[:, None, 2]
    v = k[:, None, 1] * pc[..., 1] / safe + k[:, None, 3]
    return np.stack([u, v], axis=-1), z


def occluded(terrain: Terrain, origins: np.ndarray, point: np.ndarray, clearance: float = 0.3) -> np.ndarray:
    """[V] bool: does the terrain cut the segment from each origin [V, 3] to ``point``?"""
    t = np.linspace(0.02, 0.98, 96)[None, :, None]
    seg = origins[:, None, :] * (1 - t) + point[None, None, :] * t  # [V, T, 3]
    ground = terrain.height_at(seg[..., 0], seg[..., 1])
    return np.any(seg[..., 2] < ground + clearance, axis=1)


def drone_corners(centre: np.ndarray, size: float, rotation: np.ndarray) -> np.ndarray:
    """[8, 3] world corners of a drone's bounding box."""
    lo, hi = DRONE_BOX_MIN * size, DRONE_BOX_MAX * size
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return corners @ rotation.T + centre


def projected_sizes(cams: list[dict[str, Any]], corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per view: size across in pixels (larger side of the corners' bounding rectangle) and
    whether the box touches the frame with every corner in front of the camera."""
    uv, z = project(cams, corners)  # [V, 8, 2], [V, 8]
    span = uv.max(axis=1) - uv.min(axis=1)
    size = span.max(axis=1)
    w = np.array([c["width"] for c in cams])
    h = np.array([c["height"] for c in cams])
    in_front = np.all(z > 0.05, axis=1)
    touches = (uv[..., 0].max(1) >= 0) & (uv[..., 0].min(1) <= w) & (uv[..., 1].max(1) >= 0) & (uv[..., 1].min(1) <= h)
    return size, in_front & touches


def rotation_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Rotation matrix R = Rz(yaw) @ Ry(pitch) @ Rx(roll), angles in radians."""
    cz, sz = math.cos(yaw), math.sin(yaw)
    cy, sy = math.cos(pitch), math.sin(pitch)
    cx, sx = math.cos(roll), math.sin(roll)
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    return rz @ ry @ rx


# ---------------------------------------------------------------------------- flames


def place_flames(rng: np.random.Generator, params: dict[str, Any], terrain: Terrain) -> list[dict[str, Any]]:
    """Flames on fairly flat ground of the valley, spaced apart."""
    flames: list[dict[str, Any]] = []
    region = float(params["flame_region_radius"])
    nz = terrain.normals_z()
    step = terrain.size / (terrain.n - 1)
    for _ in range(int(params["n_flames"])):
        for _attempt in range(500):
            a, r = rng.uniform(0, 2 * np.pi), region * math.sqrt(rng.uniform(0.05, 1.0))
            x, y = r * math.cos(a), r * math.sin(a)
            col = int(round((x + terrain.size / 2) / step))
            row = int(round((y + terrain.size / 2) / step))
            if nz[row, col] < 0.8:
                continue
            if any(math.hypot(x - f["centre"][0], y - f["centre"][1]) < 12.0 for f in flames):
                continue
            height = float(params["flame_height"]) * rng.uniform(0.75, 1.25)
            flames.append(
                {
                    "id": len(flames) + 1,
                    "centre": [x, y, float(terrain.height_at(x, y))],
                    "height": height,
                    "radius": 0.4 * height,
                    "n_tongues": int(rng.integers(6, 10)),
                    "mesh_seed": int(rng.integers(0, 2**31 - 1)),
                }
            )
            break
        else:
            raise LayoutError("could not find flat ground for a flame: use fewer flames or a larger flame_region_radius")
    return flames


# ---------------------------------------------------------------------------- drones


def place_drones(
    rng: np.random.Generator,
    params: dict[str, Any],
    terrain: Terrain,
    cams: list[dict[str, Any]],
    flames: list[dict[str, Any]],
) -> list[dict[str, Any]]:
    """Drones in groups floating over the valley, each sized to meet the size rule."""
    max_px = max_drone_px(params)
    min_px = float(params["min_visible_px"])
    min_views = int(params["min_views"])
    train = np.array([c["split"] == "train" for c in cams])
    origins = np.stack([c["centre"] for c in cams])
    w = np.array([c["width"] for c in cams])
    h = np.array([c["height"] for c in cams])
    alt_lo, alt_hi = (float(v) for v in params["drone_altitude"])
    group_radius = float(params["drone_group_radius"])
    region = float(params["drone_region_radius"])
    n_groups = int(params["n_drone_groups"])
    n_drones = int(params["n_drones"])

    groups = []
    for _ in range(n_groups):
        for _attempt in range(500):
            a, r = rng.uniform(0, 2 * np.pi), region * math.sqrt(rng.uniform(0.0, 1.0))
            x, y = r * math.cos(a), r * math.sin(a)
            if any(math.hypot(x - g[0], y - g[1]) < 1.5 * group_radius for g in groups):
                continue
            groups.append(np.array([x, y, float(terrain.height_at(x, y)) + rng.uniform(alt_lo, alt_hi)]))
            break
        else:
            raise LayoutError("could not place the drone groups apart: use fewer groups or a larger drone_region_radius")

    drones: list[dict[str, Any]] = []
    failures: dict[str, int] = {"ground": 0, "flame": 0, "spacing": 0, "views": 0}
    for i in range(n_drones):
        g = i % n_groups
        for _attempt in range(400):
            offset = rng.normal(size=3) * np.array([1.0, 1.0, 0.4]) * group_radius / 2.0
            centre = groups[g] + offset
            ground = float(terrain.height_at(centre[0], centre[1]))
            if centre[2] < ground + alt_lo * 0.5:
                failures["ground"] += 1
                continue
            if any(math.hypot(centre[0] - f["centre"][0], centre[1] - f["centre"][1]) < 2.0 * f["radius"] + 2.0
                   and centre[2] < f["centre"][2] + f["height"] + 3.0 for f in flames):
                failures["flame"] += 1
                continue
            if any(np.linalg.norm(centre - np.array(d["centre"])) < 1.5 for d in drones):
                failures["spacing"] += 1
                continue
            yaw = rng.uniform(0, 2 * np.pi)
            tilt = rng.normal(size=2) * math.radians(5.0)
            rot = rotation_zyx(yaw, tilt[0], tilt[1])
            fill = rng.uniform(0.75, 0.98)
            color_name, color = DRONE_COLORS[int(rng.integers(len(DRONE_COLORS)))]
            unit, touches = projected_sizes(cams, drone_corners(centre, 1.0, rot))
            if not touches.any():
                failures["views"] += 1
                continue
            size = fill * max_px / float(unit[touches].max())
            for _shrink in range(20):  # perspective is not exactly linear in the size
                px, touches = projected_sizes(cams, drone_corners(centre, size, rot))
                if px[touches].max() <= max_px * 0.999:
                    break
                size *= 0.98
            uv, z = project(cams, centre[None])
            uv, z = uv[:, 0], z[:, 0]
            in_frame = (z > 0.05) & (uv[:, 0] >= 1) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 1) & (uv[:, 1] <= h - 1)
            hidden = occluded(terrain, origins, centre)
            seen = in_frame & ~hidden & (px >= min_px)
            if int((seen & train).sum()) < min_views:
                failures["views"] += 1
                continue
            drones.append(
                {
                    "id": len(drones) + 1,
                    "group": g,
                    "centre": centre.tolist(),
                    "size": float(size),
                    "box_min": (DRONE_BOX_MIN * size).tolist(),
                    "box_max": (DRONE_BOX_MAX * size).tolist(),
                    "radius": float(np.linalg.norm(np.maximum(-DRONE_BOX_MIN, DRONE_BOX_MAX)) * size),
                    "rotation": rot.tolist(),
                    "yaw_deg": math.degrees(yaw),
                    "color_name": color_name,
                    "color": list(color),
                    "max_px": float(px[touches].max()),
                    "views": [
                        {
                            "name": cams[v]["name"],
                            "uv": [float(uv[v, 0]), float(uv[v, 1])],
                            "size_px": float(px[v]),
                            "in_frame": bool(in_frame[v]),
                            "occluded": bool(hidden[v]),
                            "seen": bool(seen[v]),
                        }
                        for v in range(len(cams))
                        if touches[v]
                    ],
                    "n_train_views_seen": int((seen & train).sum()),
                }
            )
            break
        else:
            raise LayoutError(
                f"could not place drone {i + 1} seen by {min_views} training views at >= {min_px} px "
                f"(rejections: {failures}); use fewer min_views, a smaller min_visible_px or more views"
            )
    return drones


# ---------------------------------------------------------------------------- all


def make_layout(params: dict[str, Any]) -> tuple[Terrain, dict[str, Any]]:
    """The terrain and a JSON-ready description of cameras, flames and drones."""
    check_params(params)
    rng = np.random.default_rng(int(params["seed"]))
    terrain = make_terrain(
        rng, float(params["terrain_size"]), int(params["terrain_resolution"]), float(params["rim_height"]),
        ridge_octaves=int(params.get("ridge_octaves", 6)), ridge_amplitude=float(params.get("ridge_amplitude", 1.0)),
        hill_octaves=int(params.get("hill_octaves", 4)),
    )
    cams = make_cameras(rng, params, terrain)
    flames = place_flames(rng, params, terrain)
    drones = place_drones(rng, params, terrain, cams, flames)
    sun_azimuth = float(params["sun_azimuth_deg"]) if params.get("sun_azimuth_deg") is not None else float(rng.uniform(0, 360))
    colour_seed = int(rng.integers(0, 2**31 - 1))
    layout = {
        "cameras": [
            {
                **{k: v for k, v in c.items() if k not in ("world_to_camera", "centre")},
                "world_to_camera": np.asarray(c["world_to_camera"]).tolist(),
                "centre": np.asarray(c["centre"]).tolist(),
            }
            for c in cams
        ],
        "flames": flames,
        "drones": drones,
        "sun": {"elevation_deg": float(params["sun_elevation_deg"]), "azimuth_deg": sun_azimuth},
        "terrain": {
            "size": terrain.size,
            "resolution": terrain.n,
            "height_min": float(terrain.heights.min()),
            "height_max": float(terrain.heights.max()),
            "colour_seed": colour_seed,
        },
        "limits": {"max_drone_px": max_drone_px(params), "min_visible_px": float(params["min_visible_px"]),
                   "min_views": int(params["min_views"])},
    }
    return terrain, layout
