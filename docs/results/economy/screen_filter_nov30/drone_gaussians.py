"""Two measurements of trained runs on a generated mountain dataset, one JSON line per run.

- The drones' Gaussians against the drones: the Gaussians within 0.5 units of a drone's
  centre with opacity over 0.1, their size (the geometric mean of the three scales)
  projected at the drone's depth in each test view that sees it, as a variance in px²;
  beside it the drone's own, a filled square of its projected side (`scene.json`'s
  `size_px`) whose variance is side² / 12. Quantiles 10 / 50 / 90 %.
- Where the run's Gaussians lie: within 60 units of the origin (the scene the cameras
  look at), beyond 200 (past the terrain's edge: the far background shell), the rest, and
  how many end with an opacity under 0.05.

    python docs/results/economy/screen_filter_nov30/drone_gaussians.py RUN [RUN ...]
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from promptgs_engine.data import load_colmap_scene
from promptgs_engine.evaluation import load_run

DRONE_GAUSSIANS_WITHIN = 0.5  # scene units, as benchmarks/drone_fit.py
STRONG_OPACITY = 0.1
NEAR, FAR = 60.0, 200.0  # scene units from the origin
FAINT_OPACITY = 0.05


def quantiles(values: list[float]) -> list[float]:
    q = torch.tensor(values, dtype=torch.float64).quantile(torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64))
    return [round(x, 3) for x in q.tolist()]


def measure(run: Path) -> dict:
    cfg, params = load_run(run)
    dataset = Path(cfg.dataset)
    meta = json.loads((dataset / "scene.json").read_text())
    scene = load_colmap_scene(dataset, images=cfg.images)
    cameras = {c.name: c.downscaled(cfg.downscale) for c in scene.test_cameras}
    means = params["means"].detach()
    scales = params["scales"].detach().exp()
    opacity = torch.sigmoid(params["opacities"].detach()).reshape(-1)
    fitted, drone, per_drone = [], [], []
    for d in meta["drones"]:
        centre = torch.tensor(d["centre"], dtype=means.dtype)
        mine = ((means - centre).norm(dim=1) < DRONE_GAUSSIANS_WITHIN) & (opacity > STRONG_OPACITY)
        per_drone.append(int(mine.sum()))
        size = scales[mine].prod(dim=1).pow(1 / 3)
        for view in d["views"]:
            cam = cameras.get(view["name"])
            if cam is None or not view["in_frame"] or view["occluded"]:
                continue
            depth = float(cam.project(centre[None])[2][0])
            focal = float(cam.K[0, 0])
            drone.append(view["size_px"] ** 2 / 12)
            fitted += [float(s * focal / depth) ** 2 for s in size]
    radius = means.norm(dim=1)
    return {
        "run": str(run), "screen_filter": cfg.effective_screen_filter, "pairs": len(drone),
        "drone_gaussians_per_drone": per_drone,
        "drone_gaussians_var_px2_q10_50_90": quantiles(fitted) if fitted else None,
        "drones_square_var_px2_q10_50_90": quantiles(drone),
        "gaussians": int(means.shape[0]), "within_60": int((radius < NEAR).sum()),
        "beyond_200": int((radius > FAR).sum()), "opacity_under_0.05": int((opacity < FAINT_OPACITY).sum()),
    }


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        print(json.dumps(measure(Path(arg))))
