"""Tiny-object comparison: 3DGS, AbsGS and PromptGS (1 and 2 prompts) on one scene.

Every method trains with the same iterations and seed, one after the other in this
process, and is evaluated on the held-out views with the scene's object masks. Writes
``results.json`` (every run's metrics) and ``comparison.png``, and prints a table with
the differences to 3DGS and AbsGS. ``promptgs demo`` runs it on the embedded toy scene.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

from ..config import TrainConfig
from ..train import run_training
from .toy_scene import ToySceneConfig, make_toy_scene

METHODS = {
    "3dgs": {"strategy": "3dgs"},
    "absgs": {"strategy": "absgs"},
    "promptgs-1": {"strategy": "promptgs", "prompts": "prompts_1.json"},
    "promptgs-2": {"strategy": "promptgs", "prompts": "prompts_2.json"},
}
REPORTED = ("psnr", "masked_psnr", "object_region_psnr", "ssim", "n_gaussians", "train_seconds")


def ensure_toy_scene(folder: Path) -> Path:
    """The embedded toy scene, generated once and reused."""
    if not (folder / "scene.json").is_file():
        make_toy_scene(folder, ToySceneConfig())
    return folder


def run_comparison(
    scene: Path,
    out: Path,
    iterations: int,
    seeds: list[int],
    methods: list[str] | None = None,
    quiet: bool = True,
) -> dict:
    scene, out = Path(scene), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / "results.json"
    runs = json.loads(results_path.read_text()) if results_path.is_file() else []
    done = {(r["method"], r["seed"], r["iterations"]) for r in runs}
    for seed in seeds:
        for method in methods or list(METHODS):
            if (method, seed, iterations) in done:
                continue  # resumable: finished cells are kept
            settings = dict(METHODS[method])
            if "prompts" in settings:
                settings["prompts"] = str(scene / settings["prompts"])
            run_dir = out / f"{method}_s{seed}_i{iterations}"
            cfg = TrainConfig(dataset=str(scene), out=str(run_dir), iterations=iterations, seed=seed, checkpoint_every=0, **settings)
            metrics = run_training(cfg, overwrite=True, quiet=quiet)
            row = {"method": method, "seed": seed, "iterations": iterations, **{k: metrics.get(k) for k in REPORTED}}
            runs.append(row)
            results_path.write_text(json.dumps(runs, indent=2))
            if not quiet:
                print(f"{method} seed {seed}: " + ", ".join(f"{k}={_fmt(row[k])}" for k in REPORTED))
    summary = summarize([r for r in runs if r["iterations"] == iterations and r["seed"] in seeds])
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    plot(summary, out / "comparison.png")
    return summary


def _fmt(v) -> str:
    return "-" if v is None else (f"{v:.2f}" if isinstance(v, float) else str(v))


def summarize(runs: list[dict]) -> dict:
    """Mean and standard deviation over seeds, per method."""
    out: dict = {}
    for method in dict.fromkeys(r["method"] for r in runs):
        rows = [r for r in runs if r["method"] == method]
        out[method] = {}
        for key in REPORTED:
            vals = [r[key] for r in rows if r.get(key) is not None]
            if vals:
                out[method][key] = statistics.fmean(vals)
                out[method][key + "_std"] = statistics.pstdev(vals) if len(vals) > 1 else 0.0
        out[method]["n_seeds"] = len(rows)
    return out


def table(summary: dict) -> str:
    base = summary.get("3dgs", {})
    abs_ = summary.get("absgs", {})
    lines = [
        "| method | PSNR | masked PSNR | object-region PSNR | Gaussians | train s | Δ masked vs 3DGS | Δ masked vs AbsGS | time vs 3DGS |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for method, m in summary.items():
        d3 = m.get("masked_psnr", 0) - base.get("masked_psnr", 0) if base else None
        da = m.get("masked_psnr", 0) - abs_.get("masked_psnr", 0) if abs_ else None
        t = m.get("train_seconds", 0) / base["train_seconds"] if base.get("train_seconds") else None
        lines.append(
            f"| {method} | {m.get('psnr', 0):.2f} ± {m.get('psnr_std', 0):.2f} | {m.get('masked_psnr', 0):.2f} ± {m.get('masked_psnr_std', 0):.2f} "
            f"| {m.get('object_region_psnr', 0):.2f} | {m.get('n_gaussians', 0):.0f} | {m.get('train_seconds', 0):.0f} "
            f"| {d3:+.2f} | {da:+.2f} | {t:.2f}× |"
        )
    return "\n".join(lines)


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(summary)
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
    for ax, (key, label) in zip(
        axes,
        [("masked_psnr", "masked (object) PSNR, dB"), ("psnr", "PSNR, dB"), ("n_gaussians", "Gaussians"), ("train_seconds", "training time, s")],
    ):
        vals = [summary[m].get(key, 0) for m in methods]
        errs = [summary[m].get(key + "_std", 0) for m in methods]
        ax.bar(methods, vals, yerr=errs, color=["#888", "#6a9", "#e63", "#c31"][: len(methods)])
        ax.set_title(label)
        ax.tick_params(axis="x", rotation=20)
        if "psnr" in key:
            lo = min(vals) - 2
            ax.set_ylim(max(lo, 0), max(vals) + 1)
    fig.suptitle("Tiny objects: same scene, same iterations")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
