"""How much of each drone's contrast a model loses to the background alone.

Per-object recall (`metrics.object_recall`) counts a drone as reconstructed in a test
view when the render's error over the drone's pixels is under half its contrast (the
error of the drone-free ground truth there). Drones of one or two pixels have little
contrast, so the error a model makes on the terrain *behind* them already weighs. For
each (drone, test view) pair this script reports:

* ``contrast``: mean |drone-free truth − truth| over the drone's pixels (as recall);
* ``floor``: mean |BASELINE render − drone-free truth| there, i.e. how far a model
  without the drone (3DGS) is from the background it shows. A drone that does not
  fully cover its pixels leaves that error in them;
* for each RUN, its recall ratio (render error / contrast; reconstructed under 0.5).

    python benchmarks/recall_floor.py runs/bench_g5/runs/mountain_3dgs_none_i600_s0 \\
        runs/bench_g5/runs/mountain_promptgs-1_none_i600_s0 --out docs/results/recall_floor

Writes ``recall_floor.json`` and ``recall_floor.png`` (floor / contrast against the run's
ratio, one point per pair) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from promptgs_engine.data import load_colmap_scene
from promptgs_engine.evaluation import NO_OBJECTS, load_run, object_views, render_view
from promptgs_engine.metrics import visible_objects


def pairs(baseline: Path, runs: list[Path]) -> list[dict]:
    cfg, base = load_run(baseline)
    models = [load_run(r) for r in runs]
    scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
    rows = []
    for view in object_views(cfg, scene):
        cam, gt, ids, free = view.camera, view.gt, view.ids, view.without_objects
        contrast_map = (free - gt).abs().mean(dim=-1)
        floor_map = (render_view(base, cam, cfg.backend, cfg.effective_screen_filter, cfg.rasterize_mode) - free).abs().mean(dim=-1)
        error_maps = [
            (render_view(m, cam, cfg.backend, run_cfg.effective_screen_filter, run_cfg.rasterize_mode) - gt).abs().mean(dim=-1) for run_cfg, m in models
        ]
        for obj, pixels, contrast in visible_objects(ids, contrast_map):
            rows.append({
                "view": view.name, "object": obj, "pixels": int(pixels.sum()),
                "contrast": contrast, "floor": float(floor_map[pixels].mean()),
                "ratios": [float(e[pixels].mean()) / contrast for e in error_maps],
            })
    return rows


def summary(rows: list[dict], runs: list[Path]) -> dict:
    c = np.array([r["contrast"] for r in rows])
    f = np.array([r["floor"] for r in rows])
    q = [0.1, 0.25, 0.5, 0.75, 0.9]
    out = {
        "pairs": len(rows),
        "contrast_quantiles": dict(zip(map(str, q), np.quantile(c, q).round(4).tolist())),
        "floor_quantiles": dict(zip(map(str, q), np.quantile(f, q).round(4).tolist())),
        "pairs_floor_at_least_half_contrast": int((f >= 0.5 * c).sum()),
        "runs": {},
    }
    for i, run in enumerate(runs):
        ratio = np.array([r["ratios"][i] for r in rows])
        hard = f >= 0.5 * c
        out["runs"][run.name] = {
            "recall": float((ratio < 0.5).mean()),
            "recall_where_floor_under_half": float((ratio[~hard] < 0.5).mean()) if (~hard).any() else None,
            "recall_where_floor_at_least_half": float((ratio[hard] < 0.5).mean()) if hard.any() else None,
            "ratio_median": float(np.median(ratio)),
        }
    return out


def plot(rows: list[dict], runs: list[Path], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 4.5))
    rel = np.array([r["floor"] / r["contrast"] for r in rows])
    for i, run in enumerate(runs):
        ax.scatter(rel, [r["ratios"][i] for r in rows], s=14, alpha=0.7, label=run.name)
    ax.axhline(0.5, color="k", lw=0.8, ls="--")
    ax.axvline(0.5, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("baseline background error / drone contrast (over the drone's pixels)")
    ax.set_ylabel("render error / contrast (reconstructed below 0.5)")
    ax.set_title("Recall pairs: how much the background already costs")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("baseline", type=Path, help="a run folder of a model without the drones (3DGS)")
    ap.add_argument("runs", type=Path, nargs="*", help="run folders whose recall ratios to list")
    ap.add_argument("--out", type=Path, default=Path("runs/recall_floor"))
    args = ap.parse_args()
    rows = pairs(args.baseline, args.runs)
    if not rows:
        raise SystemExit(f"{args.baseline}: its dataset has no test views with object masks and {NO_OBJECTS}/")
    args.out.mkdir(parents=True, exist_ok=True)
    result = {"baseline": str(args.baseline), **summary(rows, args.runs), "rows": rows}
    (args.out / "recall_floor.json").write_text(json.dumps(result, indent=2))
    plot(rows, args.runs, args.out / "recall_floor.png")
    print(json.dumps({k: v for k, v in result.items() if k != "rows"}, indent=2))


if __name__ == "__main__":
    main()
