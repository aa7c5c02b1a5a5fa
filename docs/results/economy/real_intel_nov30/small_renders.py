"""A render's forward and backward at full size, 2x and 4x below it, on two threads and on
one: eight training views of a trained run, five times each, after two warm-up views; the
milliseconds per view, each thread count measured twice in turn.

    python docs/results/economy/real_intel_nov30/small_renders.py RUN
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import torch

from promptgs_engine.data import load_colmap_scene
from promptgs_engine.evaluation import load_run
from promptgs_engine.render import render

SCREEN_FILTER = 0.1  # PromptGS's, px²
VIEWS, REPEATS = 8, 5


def main(run: Path) -> None:
    cfg, loaded = load_run(run)
    scene = load_colmap_scene(Path(cfg.dataset), images=cfg.images)
    params = {k: v.detach().clone().requires_grad_(True) for k, v in loaded.items()}
    cameras = [c.downscaled(cfg.downscale) for c in scene.train_cameras[:VIEWS]]
    print(f"{len(params['means'])} Gaussians")

    def forward_backward(cam) -> None:
        img, _, info = render(
            params["means"], params["quats"], params["scales"].exp(), torch.sigmoid(params["opacities"]),
            params["sh0"], cam.world_to_camera[None], cam.K[None], cam.width, cam.height,
            sh_degree=cfg.sh_degree, eps2d=SCREEN_FILTER, sh_rest=params["shN"],
        )
        info["means2d"].retain_grad()
        img.sum().backward()

    for factor in (1, 2, 4):
        views = [c.downscaled(factor) for c in cameras]
        for threads in (2, 1, 2, 1):
            torch.set_num_threads(threads)
            for cam in views[:2]:
                forward_backward(cam)
            start = time.perf_counter()
            for _ in range(REPEATS):
                for cam in views:
                    forward_backward(cam)
            ms = (time.perf_counter() - start) / (REPEATS * len(views)) * 1000
            print(f"{views[0].width}x{views[0].height}, {threads} thread(s): {ms:.2f} ms a view")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
