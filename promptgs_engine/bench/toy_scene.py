"""A small synthetic scene with tiny objects, rendered from known Gaussians.

A textured ground plane seen from a ring of cameras, with a few tiny "drones" (clusters
of small saturated Gaussians, 2–4 px across) floating above it. The COLMAP model's
points sample the ground only, as SfM would: the drones start with no points at all,
which is the failure PromptGS addresses. It needs no Blender and builds in seconds, so
tests and quick experiments use it; the Blender mountain dataset is the realistic one.

Outputs the layout of the Blender generator: ``images/``, ``sparse/0/``,
``object_masks/`` (8-bit PNG, drone id per pixel, 0 = none), ``gt_nodrones/``,
``test.txt``, ``scene.json`` (drones, suggested prompt boxes).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import torch
from PIL import Image

from ..render import render


@dataclass
class ToySceneConfig:
    width: int = 256
    height: int = 192
    focal: float = 220.0
    n_views: int = 32
    ring_radius: float = 6.0
    ring_height: float = 3.0
    ground_half_size: float = 4.0
    ground_grid: int = 110
    backdrop_radius: float = 12.0
    backdrop_height: float = 7.0
    texture_noise: float = 0.06
    n_sfm_points: int = 3000
    drone_size: float = 0.07  # metres across one drone's body
    seed: int = 0


# The tests' toy scene (128×96, 16 views): a 300-step run trains in seconds.
QUICK_TOY = ToySceneConfig(width=128, height=96, focal=110.0, n_views=16, ground_grid=60, n_sfm_points=1500)


DRONE_GROUPS = (
    # centre of the group, offsets of its drones, colours
    ((1.0, 0.6, 1.0), ((0.0, 0.0, 0.0), (0.35, -0.25, 0.2), (-0.3, 0.3, -0.15)), ((1.0, 0.1, 0.1), (1.0, 0.9, 0.1), (0.1, 0.9, 1.0))),
    ((-1.1, -0.8, 1.3), ((0.0, 0.0, 0.0), (0.3, 0.3, -0.2)), ((1.0, 0.2, 0.9), (0.2, 1.0, 0.2))),
)


def look_at(camera_center: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera [4, 4] in COLMAP convention (x right, y down, z forward)."""
    forward = target - camera_center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = -rot @ camera_center
    return m


def _ground(cfg: ToySceneConfig, rng: np.random.Generator) -> dict[str, torch.Tensor]:
    """A textured ground disc out to the backdrop, and the backdrop: a textured cylinder
    ("distant hills") that fills every view above the horizon."""
    r = cfg.backdrop_radius
    spacing = 2 * cfg.ground_half_size / (cfg.ground_grid - 1)
    xs = np.arange(-r, r + spacing / 2, spacing)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    inside = gx**2 + gy**2 <= r**2
    gx, gy = gx[inside], gy[inside]
    ground_means = np.stack([gx, gy, 0.02 * np.sin(gx * 1.7)], 1)
    ground_colors = np.stack(
        [
            0.45 + 0.2 * np.sin(gx * 1.3) * np.cos(gy * 0.9),
            0.5 + 0.15 * np.sin(gx * 0.5 + gy * 2.1),
            0.35 + 0.2 * np.cos(gy * 1.7 - gx * 0.4),
        ],
        -1,
    )
    ground_scales = np.tile([spacing * 0.7, spacing * 0.7, spacing * 0.1], (len(gx), 1))

    step = spacing * 2
    angles = np.arange(0, 2 * np.pi, step / r)
    heights = np.arange(-0.5, cfg.backdrop_height, step)
    ga, gz = np.meshgrid(angles, heights, indexing="ij")
    ga, gz = ga.ravel(), gz.ravel()
    back_means = np.stack([r * np.cos(ga), r * np.sin(ga), gz], 1)
    ridge = 2.5 + 1.2 * np.sin(3 * ga) + 0.6 * np.sin(7 * ga + 1.0)
    hill = gz < ridge
    back_colors = np.where(
        hill[:, None],
        np.stack([0.3 + 0.1 * np.sin(5 * ga + gz), 0.42 + 0.1 * np.cos(4 * ga), 0.3 + 0.05 * gz / cfg.backdrop_height], 1),
        np.stack([0.5 + 0.05 * gz / cfg.backdrop_height + 0.05 * np.sin(2 * ga), 0.65 + 0.03 * np.sin(3 * ga), 0.9 + 0 * ga], 1),
    )
    back_scales = np.tile([step * 0.7, step * 0.7, step * 0.7], (len(ga), 1))

    means = np.concatenate([ground_means, back_means])
    colors = np.concatenate([ground_colors, back_colors])
    colors = np.clip(colors + cfg.texture_noise * rng.standard_normal(colors.shape), 0.02, 0.98)
    return _gaussians(means, np.concatenate([ground_scales, back_scales]), colors, opacity=0.98)


def _gaussians(means, scales, colors, opacity) -> dict[str, torch.Tensor]:
    n = len(means)
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    return {
        "means": torch.tensor(means, dtype=torch.float32),
        "scales": torch.tensor(scales, dtype=torch.float32),
        "quats": torch.tensor(quats, dtype=torch.float32),
        "opacities": torch.full((n,), opacity, dtype=torch.float32),
        "colors": torch.tensor(colors, dtype=torch.float32),
    }


def _drone(center: np.ndarray, size: float, color) -> dict[str, torch.Tensor]:
    """A body and four arms: five small Gaussians."""
    arm = size * 0.5
    offsets = np.array([[0, 0, 0], [arm, arm, 0], [-arm, arm, 0], [arm, -arm, 0], [-arm, -arm, 0]])
    scales = np.array([[size * 0.3] * 3] + [[size * 0.18] * 3] * 4)
    return _gaussians(center + offsets, scales, np.tile(color, (5, 1)), opacity=0.99)


def _concat(parts: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


def _render(g: dict[str, torch.Tensor], viewmat: np.ndarray, K: np.ndarray, cfg: ToySceneConfig):
    img, alpha, _ = render(
        g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
        torch.tensor(viewmat, dtype=torch.float32)[None], torch.tensor(K, dtype=torch.float32)[None],
        cfg.width, cfg.height, backgrounds=torch.tensor([[0.55, 0.7, 0.9]]), backend="cpu",
    )
    return img[0].clamp(0, 1), alpha[0, ..., 0]


def _save_png(path: Path, img: torch.Tensor) -> None:
    Image.fromarray((img.numpy() * 255).round().astype(np.uint8)).save(path)


def make_toy_scene(out: Path, cfg: ToySceneConfig | None = None) -> Path:
    """Render the scene into ``out`` (a COLMAP dataset folder) and return it."""
    cfg = cfg or ToySceneConfig()
    out = Path(out)
    rng = np.random.default_rng(cfg.seed)
    for sub in ("images", "sparse/0", "object_masks", "gt_nodrones"):
        (out / sub).mkdir(parents=True, exist_ok=True)

    ground = _ground(cfg, rng)
    drones, drone_info, prompts = [], [], []
    for center, offsets, colors in DRONE_GROUPS:
        group_points = []
        for off, col in zip(offsets, colors):
            c = np.asarray(center) + np.asarray(off)
            drones.append(_drone(c, cfg.drone_size, col))
            drone_info.append({"id": len(drone_info) + 1, "center": c.tolist(), "size": cfg.drone_size, "color": list(col)})
            group_points.append(c)
        pts = np.asarray(group_points)
        lo, hi = pts.min(0) - 0.25, pts.max(0) + 0.25
        prompts.append({"center": ((lo + hi) / 2).tolist(), "size": (hi - lo).tolist(), "rotation_wxyz": [1, 0, 0, 0], "weight": 1.0})
    scene_all = _concat([ground] + drones)

    K = np.array([[cfg.focal, 0, cfg.width / 2], [0, cfg.focal, cfg.height / 2], [0, 0, 1.0]])
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera(
        model="PINHOLE", width=cfg.width, height=cfg.height,
        params=[cfg.focal, cfg.focal, cfg.width / 2, cfg.height / 2], camera_id=1,
    )
    rec.add_camera_with_trivial_rig(camera)
    names = []
    for i in range(cfg.n_views):
        angle = 2 * math.pi * i / cfg.n_views
        height = cfg.ring_height + 0.6 * math.sin(3 * angle)
        center = np.array([cfg.ring_radius * math.cos(angle), cfg.ring_radius * math.sin(angle), height])
        viewmat = look_at(center, np.array([0.0, 0.0, 0.6]))
        name = f"view_{i:03d}.png"
        names.append(name)
        img, _ = _render(scene_all, viewmat, K, cfg)
        _save_png(out / "images" / name, img)
        nodrones, _ = _render(ground, viewmat, K, cfg)
        _save_png(out / "gt_nodrones" / name, nodrones)
        ids = np.zeros((cfg.height, cfg.width), dtype=np.uint8)
        # Instance ids: a drone's pixels where it is the visible foreground.
        for info, drone in zip(drone_info, drones):
            _, alpha = _render(drone, viewmat, K, cfg)
            ids[alpha.numpy() > 0.3] = info["id"]
        Image.fromarray(ids).save(out / "object_masks" / name)
        image = pycolmap.Image(name=name, camera_id=1, image_id=i + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(viewmat[:3, :3]), viewmat[:3, 3])
        rec.add_image_with_trivial_frame(image, pose)

    # SfM-like points: ground only, with a little noise; the drones get none.
    pick = rng.choice(len(ground["means"]), size=min(cfg.n_sfm_points, len(ground["means"])), replace=False)
    for j in pick:
        xyz = ground["means"][j].numpy().astype(np.float64) + 0.01 * rng.standard_normal(3)
        color = (ground["colors"][j].numpy() * 255).round().astype(np.uint8)
        rec.add_point3D(xyz, pycolmap.Track(), color)
    rec.write_binary(str(out / "sparse/0"))

    test = [n for k, n in enumerate(sorted(names)) if k % 8 == 0]
    (out / "test.txt").write_text("\n".join(test) + "\n")
    (out / "scene.json").write_text(
        json.dumps(
            {
                "generator": "promptgs toy scene",
                "config": cfg.__dict__,
                "drones": drone_info,
                "prompts": prompts,
            },
            indent=2,
        )
    )
    (out / "prompts_1.json").write_text(json.dumps({"prompts": [_union(prompts)]}, indent=2))
    (out / "prompts_2.json").write_text(json.dumps({"prompts": prompts}, indent=2))
    return out


def _union(prompts: list[dict]) -> dict:
    lo = np.min([np.asarray(p["center"]) - np.asarray(p["size"]) / 2 for p in prompts], axis=0)
    hi = np.max([np.asarray(p["center"]) + np.asarray(p["size"]) / 2 for p in prompts], axis=0)
    return {"center": ((lo + hi) / 2).tolist(), "size": (hi - lo).tolist(), "rotation_wxyz": [1, 0, 0, 0], "weight": 1.0}
