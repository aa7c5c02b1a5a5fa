"""The distribution of PromptGS's Gaussian score S_g over trained models (the paper's Fig. 2).

For each run folder, every training view is rendered once at the training resolution
with the run's filter; the training loss (L1 and D-SSIM) is back-propagated to the
view-space means, and each Gaussian accumulates the score of Eq. 2 exactly as the
PromptGS strategy does during training (`strategies.promptgs.score_terms`, weighted by
the view's loss P^i of Eq. 3). The histogram is of the mean score per view that saw the
Gaussian, over all Gaussians and over those inside the prompt boxes, one curve per run.

    python benchmarks/diagnostics/score_histogram.py RUN_3DGS RUN_PROMPTGS_BEFORE RUN_PROMPTGS_AFTER \\
        --labels 3DGS "PromptGS (threshold)" "PromptGS (score quota)" \\
        --prompts DATASET/prompts_1.json --out runs/score_histogram

Writes ``score_histogram.json`` (per run: counts, quantiles, Tukey fence, the share of
Gaussians above 3DGS's fence) and ``score_histogram.png`` into ``--out``.
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
from promptgs_engine.run_folder import load_run
from promptgs_engine.focus import load_prompt_setting
from promptgs_engine.gaussians import sh_degree_of
from promptgs_engine.losses import edge_loss, ssim_map
from promptgs_engine.prompts import contains_any, load_prompts
from promptgs_engine.render import render
from promptgs_engine.strategies.promptgs import LAMBDA_DSSIM, LAMBDA_EDGE, LAMBDA_L1, prompt_quota, score_terms

# 3DGS's densification settings (gsplat DefaultStrategy), the score's normalisers.
GROW_GRAD2D, GROW_SCALE3D, GROW_SCALE2D = 0.0002, 0.01, 0.05


def run_scores(run: Path) -> tuple[np.ndarray, np.ndarray, object, object]:
    """Mean score per view of every Gaussian of a run (0 where no view saw it), its means,
    the run's config and scene."""
    cfg, params = load_run(run)
    scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
    n = params["means"].shape[0]
    score = torch.zeros(n)
    views = torch.zeros(n)
    colors = torch.cat([params["sh0"], params["shN"]], dim=1).detach()
    for cam in scene.train_cameras:
        cam = cam.downscaled(cfg.downscale)
        gt = cam.load_image()[None]
        img, _, info = render(
            params["means"].detach().requires_grad_(True), params["quats"].detach(), torch.exp(params["scales"].detach()),
            torch.sigmoid(params["opacities"].detach()), colors, cam.world_to_camera[None], cam.K[None],
            cam.width, cam.height, sh_degree=sh_degree_of(params), backend="cpu",
            eps2d=cfg.effective_screen_filter, rasterize_mode=cfg.rasterize_mode,
        )
        info["means2d"].retain_grad()
        img = img[..., :3]
        l1 = (img - gt).abs().mean()
        dssim = (1.0 - ssim_map(img, gt)).mean()
        ((1.0 - cfg.ssim_lambda) * l1 + cfg.ssim_lambda * dssim).backward()
        with torch.no_grad():
            view_loss = LAMBDA_L1 * l1 + LAMBDA_DSSIM * dssim + LAMBDA_EDGE * edge_loss(img, gt)
            _, gs_ids, value = score_terms(params, info, scene.extent, GROW_GRAD2D, GROW_SCALE3D, GROW_SCALE2D, False)
            score.index_add_(0, gs_ids, float(view_loss) * value)
            views.index_add_(0, gs_ids, torch.ones_like(value))
    mean = (score / views.clamp_min(1)).numpy()
    return mean, params["means"].detach().numpy(), cfg, scene


def summary(scores: np.ndarray, fence_3dgs: float | None) -> dict:
    seen = scores[scores > 0]
    quota, fence = prompt_quota(torch.from_numpy(seen)) if seen.size else (0, float("nan"))
    out = {
        "n": int(scores.size),
        "n_seen": int(seen.size),
        "quantiles": {q: float(np.quantile(seen, q)) for q in (0.1, 0.25, 0.5, 0.75, 0.9, 0.99)} if seen.size else {},
        "tukey_fence": fence,
        "above_own_fence": quota,
        "mean_lower_half": float(seen[seen <= np.median(seen)].mean()) if seen.size else None,
    }
    if fence_3dgs is not None and seen.size:
        out["above_3dgs_fence"] = int((seen > fence_3dgs).sum())
        out["share_above_3dgs_fence"] = float((seen > fence_3dgs).mean())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+", help="run folders; the first is the reference (3DGS)")
    ap.add_argument("--labels", nargs="+")
    ap.add_argument("--prompts", type=Path, help="prompt file (default: the first PromptGS run's prompts)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    labels = args.labels or [r.name for r in args.runs]
    results = []
    for run in args.runs:
        scores, means, cfg, scene = run_scores(run)
        results.append((scores, means, cfg, scene))
    if args.prompts is not None:
        boxes = load_prompts(args.prompts)
    else:
        cfg, scene = next(((c, s) for _, _, c, s in results if c.strategy == "promptgs"), (results[0][2], results[0][3]))
        boxes = load_prompt_setting(cfg, scene) if cfg.strategy == "promptgs" else []
    args.out.mkdir(parents=True, exist_ok=True)
    record: dict = {"runs": [str(r) for r in args.runs], "labels": labels, "prompts": [b.to_dict() for b in boxes], "all": {}, "inside": {}}
    panels = [("all", "all Gaussians")] + ([("inside", "inside the prompts")] if boxes else [])
    fig, axes = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 4.4), squeeze=False)
    for ax, (key, title) in zip(axes[0], panels):
        sets = []
        for scores, means, _, _ in results:
            keep = np.ones(len(scores), bool) if key == "all" else contains_any(boxes, torch.from_numpy(means)).numpy()
            sets.append(scores[keep])
        ref_seen = sets[0][sets[0] > 0]
        ref_fence = prompt_quota(torch.from_numpy(ref_seen))[1] if ref_seen.size else None
        hi = max(float(np.quantile(s[s > 0], 0.999)) for s in sets if (s > 0).any())
        bins = np.linspace(0, hi, 60)
        for label, s in zip(labels, sets):
            record[key][label] = summary(s, ref_fence)
            ax.hist(s[s > 0], bins=bins, histtype="step", lw=1.5, label=f"{label} ({(s > 0).sum():,})")
        if ref_fence is not None:
            ax.axvline(ref_fence, color="black", ls="--", lw=1, label=f"{labels[0]}: Tukey fence")
        ax.set_yscale("log")
        ax.set_xlabel("score per view (Eq. 2)")
        ax.set_ylabel("Gaussians")
        ax.set_title(title)
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.suptitle("Distribution of the Gaussian score S_g (paper Fig. 2), trained models")
    fig.tight_layout()
    fig.savefig(args.out / "score_histogram.png", dpi=110)
    (args.out / "score_histogram.json").write_text(json.dumps(record, indent=2))
    print(json.dumps({k: record[k] for k in ("all", "inside")}, indent=1))


if __name__ == "__main__":
    main()
