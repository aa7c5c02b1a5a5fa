"""How much larger a Gaussian's view-space gradient is when a view is rendered below full size.

PromptGS's growth statistics (gsplat's ``grad2d``: the norm of the gradient of the loss
with respect to each projected centre, in pixels of the image rendered) are gathered
partly on downscaled steps (progressive resolution). This script loads a trained run's
checkpoint and, for a few training views, renders each at full size and at 2× and 4×
below, computes the training loss (`photometric_loss`) against the matching ground truth
and its gradients, and reports the ratio of the mean gradient norms over the Gaussians
visible at both sizes.

    python benchmarks/gradient_inflation.py runs/bench_g4/runs/mountain_3dgs_none_i600_s0 --out runs/inflation

Writes ``gradient_inflation.json`` into ``--out`` and prints the means.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from promptgs_engine.config import TrainConfig
from promptgs_engine.losses import photometric_loss
from promptgs_engine.train import Trainer

FACTORS = (2, 4)
MIN_WIDTH = 32  # a downscaled view narrower than this is left out


def view_gradients(trainer: Trainer, camera) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-Gaussian gradient norms (pixels of this camera) and the visibility mask."""
    for p in trainer.params.values():
        p.grad = None
    out, _, info = trainer.render_cameras([camera], sh_degree=trainer.cfg.sh_degree)
    loss = photometric_loss(out[..., :3], camera.load_image()[None], trainer.cfg.ssim_lambda)
    info["means2d"].retain_grad()
    loss.backward()
    grad = info["means2d"].grad[0].clone()
    grad[:, 0] *= camera.width / 2.0
    grad[:, 1] *= camera.height / 2.0
    return grad.norm(dim=-1), (info["radii"][0] > 0).all(dim=-1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run folder with cfg.json and ckpt.pt")
    ap.add_argument("--views", type=int, default=7, help="training views to sample, evenly spaced")
    ap.add_argument("--out", type=Path, default=Path("runs/gradient_inflation"))
    args = ap.parse_args()

    cfg = TrainConfig.load(args.run / "cfg.json")
    cfg.out = str(args.out / "trainer")
    trainer = Trainer(cfg, quiet=True)
    trainer.load_checkpoint(args.run / "ckpt.pt")
    cameras = trainer.scene.train_cameras
    ratios: dict[int, list[float]] = {f: [] for f in FACTORS}
    for i in range(0, len(cameras), max(1, len(cameras) // args.views)):
        full = cameras[i].downscaled(cfg.downscale)
        g_full, seen_full = view_gradients(trainer, full)
        for f in FACTORS:
            if full.width // f < MIN_WIDTH:
                continue
            g_low, seen_low = view_gradients(trainer, full.downscaled(f))
            both = seen_full & seen_low
            ratios[f].append(float(g_low[both].mean() / g_full[both].mean()))
    result = {
        "run": str(args.run),
        "n_gaussians": int(trainer.params["means"].shape[0]),
        "mean_ratio": {str(f): sum(r) / len(r) for f, r in ratios.items() if r},
        "per_view": {str(f): r for f, r in ratios.items()},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gradient_inflation.json").write_text(json.dumps(result, indent=2))
    print(args.run, {f: round(v, 2) for f, v in result["mean_ratio"].items()})


if __name__ == "__main__":
    main()
