"""What a run draws at each drone, pixel by pixel, and what Gaussians carry it.

Per-object recall (`metrics.object_recall`) asks the render to explain at least half of a
drone's contrast over its mask pixels. This script shows how a run falls short, for each
(drone, test view) pair of a dataset with ``object_masks/``, ``gt_nodrones/`` and
``scene.json`` (the mountain generator's):

* ``peak_carried``: at the mask pixel where the drone changes the truth most, the share of
  that change the render reproduces (projection of render − drone-free truth onto
  truth − drone-free truth; 1 = all of it, 0 = the drone is missing there);
* ``gt_spill`` / ``render_spill``: mean |image − drone-free truth| over the 8 pixels around
  that peak, in the truth and in the render (a render that draws the drone wider than
  the truth spills into them);
* ``ratio``: recall's ratio (render error / contrast over the mask; reconstructed under 0.5).

Per drone: the Gaussians within 3 drone radii of its centre (how many, the largest
opacity among those within one radius, its largest scale in pixels at the first test
view).

    python benchmarks/drone_profile.py runs/bench_g7/runs/mountain_promptgs-1_none_i600_s0 \\
        --out docs/results/drone_profile

Writes ``drone_profile.json`` and ``drone_profile.png`` (truth and render around the
failed pairs of highest contrast, enlarged) into ``--out``.
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

from promptgs_engine.data import load_colmap_scene
from promptgs_engine.evaluation import load_run, object_views, render_view
from promptgs_engine.metrics import visible_objects

PATCH = 4  # pixels on each side of the peak in the PNG


def pair_rows(run: Path) -> tuple[list[dict], list[dict], list[tuple]]:
    cfg, params = load_run(run)
    scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
    rows, patches = [], []
    for view in object_views(cfg, scene):
        cam, gt, ids, free = view.camera, view.gt, view.ids, view.without_objects
        img = render_view(params, cam, cfg.backend, cfg.effective_screen_filter, cfg.rasterize_mode)
        signal = gt - free  # what the drone changes in the truth
        drawn = img - free  # what the render changes against the drone-free truth
        contrast_map = signal.abs().mean(dim=-1)
        for obj, pixels, contrast in visible_objects(ids, contrast_map):
            ratio = float((img - gt).abs().mean(dim=-1)[pixels].mean()) / contrast
            ys, xs = torch.where(pixels)
            k = int(contrast_map[ys, xs].argmax())
            y, x = int(ys[k]), int(xs[k])
            s = signal[y, x]
            carried = float((drawn[y, x] * s).sum() / (s * s).sum().clamp_min(1e-12))
            y0, y1, x0, x1 = max(y - 1, 0), min(y + 2, cam.height), max(x - 1, 0), min(x + 2, cam.width)
            ring = torch.ones(y1 - y0, x1 - x0, dtype=torch.bool)
            ring[y - y0, x - x0] = False
            rows.append({
                "view": view.name, "drone": obj, "n_pixels": int(pixels.sum()), "contrast": contrast,
                "ratio": ratio, "reconstructed": ratio < 0.5, "peak_contrast": float(contrast_map[y, x]),
                "peak_carried": carried,
                "gt_spill": float(signal[y0:y1, x0:x1].abs().mean(dim=-1)[ring].mean()),
                "render_spill": float(drawn[y0:y1, x0:x1].abs().mean(dim=-1)[ring].mean()),
            })
            py0, py1 = max(y - PATCH, 0), min(y + PATCH + 1, cam.height)
            px0, px1 = max(x - PATCH, 0), min(x + PATCH + 1, cam.width)
            patches.append((rows[-1], gt[py0:py1, px0:px1], img[py0:py1, px0:px1]))
    drones = drone_rows(Path(cfg.dataset), params, scene.test_cameras[0].downscaled(cfg.downscale))
    return rows, drones, patches


def drone_rows(dataset: Path, params, camera) -> list[dict]:
    record_path = dataset / "scene.json"
    if not record_path.is_file():
        return []
    means = params["means"].detach()
    opacity = torch.sigmoid(params["opacities"].detach())
    size = torch.exp(params["scales"].detach()).max(dim=-1).values
    out = []
    for drone in json.loads(record_path.read_text()).get("drones", []):
        centre = torch.tensor(drone["centre"], dtype=means.dtype)
        dist = (means - centre).norm(dim=-1)
        near = dist < 3 * drone["radius"]
        core = torch.where(dist < drone["radius"])[0]
        _, _, z = camera.project(centre[None])
        metres_per_px = float(z[0]) / float(camera.K[0, 0])
        row = {"drone": drone["id"], "radius_px": drone["radius"] / metres_per_px, "n_within_3r": int(near.sum()),
               "opacity_sum_within_3r": float(opacity[near].sum())}
        if core.numel():
            best = core[opacity[core].argmax()]
            row.update(core_opacity=float(opacity[best]), core_size_px=float(size[best]) / metres_per_px)
        out.append(row)
    return out


def summary(rows: list[dict]) -> dict:
    def med(key: str, sel: list[dict]) -> float | None:
        return float(np.median([r[key] for r in sel])) if sel else None

    groups = {"all": rows, "reconstructed": [r for r in rows if r["reconstructed"]],
              "missed": [r for r in rows if not r["reconstructed"]]}
    return {
        name: {"n": len(sel), **{f"median_{k}": med(k, sel) for k in ("contrast", "peak_carried", "gt_spill", "render_spill")}}
        for name, sel in groups.items()
    }


def plot(patches: list[tuple], path: Path, n: int = 8) -> None:
    missed = sorted((p for p in patches if not p[0]["reconstructed"]), key=lambda p: -p[0]["contrast"])[:n]
    if not missed:
        return
    fig, axes = plt.subplots(2, len(missed), figsize=(1.6 * len(missed), 3.6), squeeze=False)
    for j, (row, gt, img) in enumerate(missed):
        for i, (label, patch) in enumerate((("truth", gt), ("render", img))):
            ax = axes[i, j]
            ax.imshow(patch.clamp(0, 1).numpy(), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if j == 0:
                ax.set_ylabel(label)
        axes[0, j].set_title(f"{Path(row['view']).stem} #{row['drone']}\nratio {row['ratio']:.2f}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a finished run folder on a dataset with object masks")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    rows, drones, patches = pair_rows(args.run)
    if not rows:
        raise SystemExit(f"{args.run}: its dataset has no object_masks/ and gt_nodrones/ pairs to profile")
    result = {"run": str(args.run), "summary": summary(rows), "pairs": rows, "drones": drones}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "drone_profile.json").write_text(json.dumps(result, indent=2))
    plot(patches, args.out / "drone_profile.png")
    for name, s in result["summary"].items():
        print(f"{name:14s} n={s['n']:3d}  " + "  ".join(f"{k[7:]} {v:.3f}" for k, v in s.items() if k != "n" and v is not None))
    if drones:
        for key in ("core_opacity", "core_size_px", "n_within_3r"):
            values = [d[key] for d in drones if key in d]
            print(f"drones: median {key} {np.median(values):.2f} (of {len(values)})")
    print(f"wrote {args.out / 'drone_profile.json'} and {args.out / 'drone_profile.png'}")


if __name__ == "__main__":
    main()
