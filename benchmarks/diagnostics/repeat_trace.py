"""Does one training job give the same bits every time? Train it several times, each in a
fresh process, and report the first step at which any run parts from the first.

Each run steps ``Trainer.train_step`` itself (the CLI's loop body, with the CLI's view of
the configuration) and records, per step, the loss's float bits and hashes of the means
and opacities. Runs of one seed should agree to the last bit for a given thread count
(the C++ kernels fix their summation order); a run that parts shows where.

    python benchmarks/diagnostics/repeat_trace.py --toy --runs 8 --threads 2 --out runs/repeat
    python benchmarks/diagnostics/repeat_trace.py ../shared/data/tumbler --images images_4 --steps 300 --runs 6

Writes ``repeat_trace.json`` (per run: the final loss bits, Gaussian count, and the first
step that differs from run 0, if any) into ``--out`` and prints one line per run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import struct
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def tensor_hash(t) -> str:
    return hashlib.md5(t.detach().contiguous().cpu().numpy().tobytes()).hexdigest()[:12]


def trace_worker(dataset: str, images: str, steps: int, seed: int, strategy: str, threads: int, out: str) -> None:
    """One run: a line per step (step, loss bits, means hash, opacities hash, Gaussians)."""
    import torch

    sys.path.insert(0, str(REPO))
    from promptgs_engine.config import TrainConfig
    from promptgs_engine.train import Trainer

    torch.set_num_threads(threads)
    cfg = TrainConfig(dataset=dataset, out=out, images=images, iterations=steps, strategy=strategy, backend="cpu", seed=seed)
    trainer = Trainer(cfg, quiet=True)  # derives the batch size and screen filter as run_training records them
    while trainer.step < steps:
        result = trainer.train_step()
        trainer.step += 1
        p = trainer.params
        print(trainer.step, struct.pack(">d", result.loss).hex(), tensor_hash(p["means"]), tensor_hash(p["opacities"]),
              trainer.n_gaussians, flush=True)


def first_difference(a: list[str], b: list[str]) -> int | None:
    for line_a, line_b in zip(a, b):
        if line_a != line_b:
            return int(line_a.split()[0])
    return None if len(a) == len(b) else min(len(a), len(b)) + 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", nargs="?", help="COLMAP scene folder (or --toy)")
    ap.add_argument("--toy", action="store_true", help="the embedded toy scene (128×96, 16 views)")
    ap.add_argument("--images", default="images")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--strategy", default="3dgs")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        trace_worker(args.dataset, args.images, args.steps, args.seed, args.strategy, args.threads, args.worker)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    dataset = args.dataset
    if args.toy:
        sys.path.insert(0, str(REPO))
        from promptgs_engine.bench.toy_scene import QUICK_TOY, make_toy_scene

        dataset = str(make_toy_scene(args.out / "toy", QUICK_TOY))
    if not dataset:
        ap.error("give a dataset or --toy")
    traces: list[list[str]] = []
    runs = []
    for i in range(args.runs):
        cmd = [sys.executable, __file__, dataset, "--images", args.images, "--steps", str(args.steps),
               "--seed", str(args.seed), "--strategy", args.strategy, "--threads", str(args.threads),
               "--out", str(args.out), "--worker", str(args.out / f"run{i}")]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            print(proc.stderr[-2000:], file=sys.stderr)
            return proc.returncode
        lines = [l for l in proc.stdout.splitlines() if l and l[0].isdigit()]
        (args.out / f"trace{i}.txt").write_text("\n".join(lines) + "\n")
        traces.append(lines)
        last = lines[-1].split()
        run = {"run": i, "final_loss_bits": last[1], "n_gaussians": int(last[4]),
               "first_step_differing_from_run0": first_difference(traces[0], lines) if i else None}
        runs.append(run)
        print(f"run {i}: loss bits {last[1]}, {last[4]} Gaussians, parts from run 0 at step "
              f"{run['first_step_differing_from_run0']}", flush=True)
    result = {"dataset": dataset, "steps": args.steps, "seed": args.seed, "strategy": args.strategy,
              "threads": args.threads, "runs": runs,
              "distinct_outcomes": len({r["final_loss_bits"] for r in runs})}
    (args.out / "repeat_trace.json").write_text(json.dumps(result, indent=1))
    print(f"{result['distinct_outcomes']} distinct outcome(s) over {args.runs} runs -> {args.out / 'repeat_trace.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
