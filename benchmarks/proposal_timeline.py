"""When to propose: proposals from a PromptGS run without prompts at several steps.

Trains PromptGS with no prompt on a dataset with ``scene.json`` objects, and at each of
``--steps`` renders every training view, proposes (`promptgs_engine.propose`), writes
``DIR/step_NNNNNN.json`` and scores the boxes against the true objects
(``proposal_quality.evaluate``). The training itself is not changed by proposing.

    python benchmarks/proposal_timeline.py runs/datasets/mountain-small-s0-spp64 \\
        --iterations 600 --steps 60 97 150 199 299 600 --out docs/results/proposals/timeline

Writes ``DIR/timeline.json`` and ``DIR/timeline.png`` (boxes at or above the trainer's
confidence threshold: correct and wrong ones, recall of the objects, per step).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from promptgs_engine.config import TrainConfig
from promptgs_engine.propose import TRAIN_MIN_CONFIDENCE, params_renderer, propose_views
from promptgs_engine.train import Trainer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from proposal_quality import evaluate  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--steps", type=int, nargs="+", required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = TrainConfig(dataset=str(args.dataset), out=str(args.out / "run"), iterations=args.iterations,
                      strategy="promptgs", seed=args.seed, checkpoint_every=0)
    trainer = Trainer(cfg, quiet=True)
    trainer.out.mkdir(exist_ok=True)
    cameras = trainer.focus.full_cameras
    rows = []
    while trainer.step < args.iterations:
        trainer.train_step()
        trainer.step += 1
        if trainer.step not in args.steps:
            continue
        t0 = time.perf_counter()
        draw = params_renderer(trainer.params, trainer.backend, trainer.screen_filter, cfg.rasterize_mode,
                               trainer.active_sh_degree(trainer.step))
        result = propose_views(draw, cameras, points=trainer.scene.points)
        seconds = time.perf_counter() - t0
        result.info.update({"step": trainer.step, "dataset": str(args.dataset)})
        path = args.out / f"step_{trainer.step:06d}.json"
        result.save(path)
        quality = {k: v for k, v in evaluate(path, args.dataset).items() if not k.startswith("_")}
        at = quality["at_training_threshold"]
        row = {"step": trainer.step, "n_gaussians": trainer.n_gaussians, "propose_seconds": seconds,
               "n_boxes": at["n_proposals"], "precision": at["precision"], "recall": at["recall"],
               "n_correct": round((at["precision"] or 0.0) * at["n_proposals"]), "n_objects": quality["n_objects"],
               "recall_all_confidences": quality["curve"][0]["recall"], "n_all": quality["n_proposals"],
               "candidates_per_view_median": quality["candidates_per_view_median"], "rejected": quality["rejected"]}
        rows.append(row)
        print(json.dumps(row), flush=True)
    (args.out / "timeline.json").write_text(json.dumps({"dataset": str(args.dataset), "iterations": args.iterations,
                                                         "seed": args.seed, "threshold": TRAIN_MIN_CONFIDENCE, "steps": rows}, indent=1))
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    steps = [r["step"] for r in rows]
    ax.bar([s - 6 for s in steps], [r["n_correct"] for r in rows], width=12, color="#2ca02c", label="correct boxes")
    ax.bar([s + 6 for s in steps], [r["n_boxes"] - r["n_correct"] for r in rows], width=12, color="#d62728", label="wrong boxes")
    ax.axhline(rows[0]["n_objects"] if rows else 0, color="0.5", lw=0.8, ls=":", label="objects")
    ax.set_xlabel("training step (PromptGS, no prompt)")
    ax.set_ylabel(f"boxes of confidence ≥ {TRAIN_MIN_CONFIDENCE}")
    ax.legend(fontsize=8)
    ax.set_title(f"{args.dataset.name}: proposals during training (seed {args.seed})", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.out / "timeline.png", dpi=110)
    print(f"wrote {args.out / 'timeline.json'} and {args.out / 'timeline.png'}")


if __name__ == "__main__":
    main()
