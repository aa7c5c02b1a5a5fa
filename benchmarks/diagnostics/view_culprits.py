"""Which Gaussians of a trained run spoil one test view, and where they came from.

The test view is rendered with the run's filter; the squared error against its ground
truth is back-propagated to the opacities, and the Gaussians are ranked by how much the
error falls per unit of opacity removed (gradient × opacity). The top 1, 3, 10, 30 and 100
are then removed and the view rendered again without them: a view spoilt by a floater
gains most of its PSNR back with the first one or few. For each of the top Gaussians:
its place, size and opacity, its distance from the test camera and from the nearest
training camera, the training views that see it (radius and depth there, and where its
centre projects), and, from the run's checkpoint, the step it was born at (growth,
resampling or the start) and whether resampling made it.

    python benchmarks/diagnostics/view_culprits.py runs/sparse/runs/sparse_promptgs-propose_none_i1500_s2 \\
        --view 0024.png --out runs/view_culprits

Writes ``view_culprits.json`` and ``view_culprits.png`` (ground truth, the run's render,
the render without the top Gaussian) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from promptgs_engine.data import Camera, load_colmap_scene
from promptgs_engine.evaluation import render_view
from promptgs_engine.run_folder import load_run
from promptgs_engine.gaussians import sh_degree_of
from promptgs_engine.metrics import psnr
from promptgs_engine.prompts import camera_center
from promptgs_engine.render import render

REMOVED = (1, 3, 10, 30, 100)
DESCRIBED = 5


def draw(params: dict[str, torch.Tensor], camera: Camera, cfg, opacity_logits: torch.Tensor | None = None):
    """The run's render of ``camera`` (with its filter), opacities from ``opacity_logits``
    where given (to take their gradient); (image [1, H, W, 3], alpha, info)."""
    logits = params["opacities"] if opacity_logits is None else opacity_logits
    return render(
        params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(logits),
        torch.cat([params["sh0"], params["shN"]], dim=1), camera.world_to_camera[None], camera.K[None],
        camera.width, camera.height, sh_degree=sh_degree_of(params), backend="cpu",
        eps2d=cfg.effective_screen_filter, rasterize_mode=cfg.rasterize_mode,
    )


def ranked_by_error(params: dict[str, torch.Tensor], camera: Camera, gt: torch.Tensor, cfg) -> torch.Tensor:
    """Gaussian indices, the one whose opacity adds most to the view's squared error first."""
    logits = params["opacities"].clone().requires_grad_(True)
    img, _, _ = draw(params, camera, cfg, logits)
    ((img[0].clamp(0, 1) - gt) ** 2).sum().backward()
    return torch.argsort(-(logits.grad * torch.sigmoid(params["opacities"])).flatten())


def seen_by(params: dict[str, torch.Tensor], ids: list[int], cameras: list[Camera], cfg) -> dict[int, list[dict]]:
    """For each Gaussian of ``ids``, the training views whose render it is in."""
    out: dict[int, list[dict]] = {i: [] for i in ids}
    with torch.no_grad():
        for cam in cameras:
            _, _, info = draw(params, cam, cfg)
            radii = info["radii"][0]
            for i in ids:
                if bool((radii[i] > 0).all()):
                    out[i].append({
                        "view": cam.name,
                        "radius_px": int(radii[i].max()),
                        "depth": round(float(info["depths"][0][i]), 3),
                        "centre_px": [round(float(v), 1) for v in info["means2d"][0][i]],
                        "centre_in_frame": bool(0 <= info["means2d"][0][i][0] < cam.width and 0 <= info["means2d"][0][i][1] < cam.height),
                    })
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--view", required=True, help="the test view's image name (e.g. 0024.png)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    cfg, loaded = load_run(args.run)
    params = {k: v.detach() for k, v in loaded.items()}
    scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
    tests = {c.name: c for c in scene.test_cameras}
    if args.view not in tests:
        raise SystemExit(f"{args.view}: not a test view of {cfg.dataset} (test views: {', '.join(sorted(tests))})")
    camera = tests[args.view].downscaled(cfg.downscale)
    train = [c.downscaled(cfg.downscale) for c in scene.train_cameras]
    gt = camera.load_image()

    def image_of(p: dict[str, torch.Tensor]) -> torch.Tensor:
        return render_view(p, camera, backend="cpu", screen_filter=cfg.effective_screen_filter, rasterize_mode=cfg.rasterize_mode)

    full = image_of(params)
    order = ranked_by_error(params, camera, gt, cfg)
    n = params["means"].shape[0]
    removed = []
    without_top = None
    for k in REMOVED:
        keep = torch.ones(n, dtype=torch.bool)
        keep[order[:k]] = False
        img = image_of({key: v[keep] for key, v in params.items()})
        removed.append({"removed": k, "psnr": psnr(img, gt)})
        if k == 1:
            without_top = img
    state = {}
    ckpt_path = args.run / "ckpt.pt"
    if ckpt_path.is_file():
        state = torch.load(ckpt_path, map_location="cpu", weights_only=False).get("strategy_state", {})
    top = order[:DESCRIBED].tolist()
    views = seen_by(params, top, train, cfg)
    test_centre = torch.as_tensor(camera_center(camera), dtype=torch.float32)
    train_centres = torch.as_tensor(np.stack([camera_center(c) for c in train]), dtype=torch.float32)
    described = []
    for i in top:
        m = params["means"][i]
        entry = {
            "index": i,
            "position": [round(float(v), 3) for v in m],
            "scale": [round(float(v), 3) for v in torch.exp(params["scales"][i])],
            "opacity": round(float(torch.sigmoid(params["opacities"][i])), 4),
            "distance_to_test_camera": round(float((m - test_centre).norm()), 3),
            "distance_to_nearest_training_camera": round(float((train_centres - m).norm(dim=1).min()), 3),
            "training_views": views[i],
        }
        for key in ("born", "carved", "background"):
            value = state.get(key)
            if isinstance(value, torch.Tensor) and value.shape[0] == n:
                entry[key] = float(value[i])
        described.append(entry)
    result = {
        "run": str(args.run),
        "view": args.view,
        "psnr": psnr(full, gt),
        "scene_extent": float(scene.extent),
        "n_gaussians": n,
        "without_top": removed,
        "top": described,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "view_culprits.json").write_text(json.dumps(result, indent=2))
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for ax, img, title in zip(
        axes, (gt, full, without_top),
        ("ground truth", f"the run: {result['psnr']:.2f} dB", f"without the top Gaussian: {removed[0]['psnr']:.2f} dB"),
    ):
        ax.imshow(img.numpy())
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(f"{args.run.name}, {args.view}", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out / "view_culprits.png", dpi=110)
    plt.close(fig)
    print(f"{args.view}: {result['psnr']:.2f} dB; without the top " + ", ".join(f"{r['removed']}: {r['psnr']:.2f}" for r in removed))
    for e in described:
        print(f"  {e['index']}: opacity {e['opacity']}, {e['distance_to_test_camera']} from the test camera, "
              f"{e['distance_to_nearest_training_camera']} from the nearest training camera, in {len(e['training_views'])} training views, born {e.get('born')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
