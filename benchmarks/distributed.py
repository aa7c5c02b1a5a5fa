"""Data-parallel training on CPUs: 1 rank, 2 ranks (gloo) and 1 process with 2 threads.

Three set-ups train the same run (3DGS on the mountain dataset, ``--iterations`` views)
side by side, alternated over ``--repeats`` rounds:

- ``1 rank``: one process, one thread, one view a step (today's trainer);
- ``2 ranks``: two gloo ranks of one thread each, two views a step (``promptgs train
  --nproc 2``'s default: ⌈I / 2⌉ steps with the batch rules of promptgs_engine/batch.py);
- ``1 proc x 2 threads``: one process, two OpenMP threads, one view a step.

Each run is a worker process (``--worker``; the 2-rank one under
``python -m torch.distributed.run``) that trains step by step, times the steps, and every
``--eval-every`` views renders the test views (outside the timed steps) for the test PSNR.
Reported per set-up (medians over the rounds): training views per second, the training
time to reach a target test PSNR (the lowest final PSNR of all runs minus 0.25 dB, so
every run reaches it; interpolated between evaluations), the final PSNR and Gaussian
count, and the CPU seconds per view summed over every process and thread (the work,
which a busy shared machine does not inflate as it inflates wall-clock time); and, from
the 2-rank runs, the bytes of the step's all-reduce (gradients and densification
statistics) against the Gaussian count.

Writes ``distributed.json`` and ``distributed.png`` into ``--out``.

    python benchmarks/distributed.py --dataset runs/datasets/mountain-small-s0-spp64
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SETUPS = {
    # name: (processes, threads per process)
    "1 rank": (1, 1),
    "2 ranks": (2, 1),
    "1 proc x 2 threads": (1, 2),
}
TARGET_MARGIN_DB = 0.25


# -- one run (a worker process, or one rank of it) -------------------------------------------


def worker(args: argparse.Namespace) -> None:
    from promptgs_engine import distributed  # first: it sets OMP_WAIT_POLICY before torch loads OpenMP

    import torch

    from promptgs_engine.config import TrainConfig
    from promptgs_engine.data import load_colmap_scene
    from promptgs_engine.evaluation import evaluate
    from promptgs_engine.train import Trainer

    ctx = distributed.init_from_env("cpu", timeout_s=600)
    distributed.set_threads(ctx, "cpu", args.threads)
    cfg = TrainConfig(
        dataset=args.dataset, out=tempfile.mkdtemp(prefix="dist-bench-"), iterations=args.iterations,
        seed=args.seed, backend="cpu", checkpoint_every=0, resolution_scale=args.resolution_scale,
    )
    scene = load_colmap_scene(cfg.dataset, test_every=cfg.test_every)
    trainer = Trainer(cfg, scene=scene, quiet=True, dist=ctx)
    curve, comm = [], []
    train_s = cpu_s = 0.0
    next_eval = 0

    def evaluate_now():
        if ctx.is_writer:
            with torch.no_grad():
                psnr = evaluate(
                    trainer.params, scene.test_cameras, downscale=cfg.downscale, backend="cpu", quiet=True,
                    screen_filter=trainer.screen_filter,
                )["psnr"]
            curve.append({"views": trainer.step * trainer.batch_size, "train_s": train_s, "psnr": psnr, "n_gaussians": trainer.n_gaussians})

    evaluate_now()
    while trainer.step < trainer.total_steps:
        n_before, bytes_before, reduce_before = trainer.n_gaussians, ctx.bytes_reduced, ctx.seconds_reduced
        t0, c0 = time.perf_counter(), time.process_time()
        trainer.train_step()
        step_s = time.perf_counter() - t0
        train_s += step_s
        cpu_s += time.process_time() - c0  # every thread of this process
        trainer.step += 1
        if ctx.distributed:
            comm.append({
                "step": trainer.step, "n_gaussians": n_before, "bytes": ctx.bytes_reduced - bytes_before,
                "allreduce_s": ctx.seconds_reduced - reduce_before, "step_s": step_s,
            })
        views = trainer.step * trainer.batch_size
        if views >= next_eval + args.eval_every or trainer.step == trainer.total_steps:
            next_eval = views
            evaluate_now()
    cpu_per_rank = ctx.all_gather_object(cpu_s)
    if ctx.is_writer:
        result = {
            "world_size": ctx.world_size, "threads": torch.get_num_threads(), "batch_size": trainer.batch_size,
            "steps": trainer.step, "views": trainer.step * trainer.batch_size, "train_s": train_s,
            "cpu_s_per_rank": cpu_per_rank, "cpu_s_per_view": sum(cpu_per_rank) / (trainer.step * trainer.batch_size),
            "images_per_s": trainer.step * trainer.batch_size / train_s, "n_gaussians": trainer.n_gaussians,
            "final_psnr": curve[-1]["psnr"], "curve": curve, "comm": comm,
        }
        Path(args.result).write_text(json.dumps(result))
    ctx.close()


def run_setup(name: str, args: argparse.Namespace, result: Path) -> dict:
    procs, threads = SETUPS[name]
    script = [str(Path(__file__).resolve()), "--worker", "--dataset", args.dataset, "--iterations", str(args.iterations),
              "--seed", str(args.seed), "--eval-every", str(args.eval_every), "--resolution-scale", str(args.resolution_scale), "--threads", str(threads), "--result", str(result)]
    if procs > 1:
        command = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={procs}", *script]
    else:
        command = [sys.executable, *script]
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), OMP_WAIT_POLICY="PASSIVE")
    t0 = time.perf_counter()
    subprocess.run(command, env=env, check=True)
    out = json.loads(result.read_text())
    out["wall_s"] = time.perf_counter() - t0
    return out


# -- the comparison ---------------------------------------------------------------------------


def time_to(curve: list[dict], target: float) -> float | None:
    """Training seconds at which the test PSNR first reaches ``target`` (linear between evaluations)."""
    for a, b in zip(curve, curve[1:]):
        if b["psnr"] >= target > a["psnr"]:
            return a["train_s"] + (target - a["psnr"]) / (b["psnr"] - a["psnr"]) * (b["train_s"] - a["train_s"])
        if a["psnr"] >= target:
            return a["train_s"]
    return curve[-1]["train_s"] if curve and curve[-1]["psnr"] >= target else None


def summarize(runs: dict[str, list[dict]]) -> dict:
    target = min(r["final_psnr"] for rs in runs.values() for r in rs) - TARGET_MARGIN_DB
    out = {"target_psnr": target, "setups": {}}
    for name, rs in runs.items():
        ips = [r["images_per_s"] for r in rs]
        ttt = [time_to(r["curve"], target) for r in rs]
        out["setups"][name] = {
            "processes": SETUPS[name][0], "threads": SETUPS[name][1], "batch_size": rs[0]["batch_size"],
            "images_per_s_median": statistics.median(ips), "images_per_s": ips,
            "time_to_target_s_median": statistics.median([t for t in ttt if t is not None]) if any(t is not None for t in ttt) else None,
            "time_to_target_s": ttt,
            "final_psnr_median": statistics.median(r["final_psnr"] for r in rs),
            "n_gaussians_median": statistics.median(r["n_gaussians"] for r in rs),
            "train_s_median": statistics.median(r["train_s"] for r in rs),
            "cpu_s_per_view_median": statistics.median(r["cpu_s_per_view"] for r in rs),
            "busiest_process_cpu_s_median": statistics.median(max(r["cpu_s_per_rank"]) for r in rs),
        }
    base = out["setups"]["1 rank"]
    for s in out["setups"].values():
        s["speed_vs_1_rank"] = s["images_per_s_median"] / base["images_per_s_median"]
        if s["time_to_target_s_median"] and base["time_to_target_s_median"]:
            s["time_to_target_vs_1_rank"] = s["time_to_target_s_median"] / base["time_to_target_s_median"]
    comm = [c for r in runs.get("2 ranks", []) for c in r["comm"]]
    if comm:
        bytes_per_gaussian = [c["bytes"] / c["n_gaussians"] for c in comm]
        out["allreduce"] = {
            "bytes_per_gaussian_min": min(bytes_per_gaussian),
            "bytes_per_gaussian_max": max(bytes_per_gaussian),
            "note": "one rank's all-reduce payload per step; a ring all-reduce sends and receives 2(W-1)/W of it per rank",
            # rank 0's wall time inside the all-reduce: gloo's transfer over loopback plus
            # waiting for rank 1 to finish its view
            "allreduce_share_of_step_median": statistics.median(c["allreduce_s"] / c["step_s"] for c in comm),
            "allreduce_s_median": statistics.median(c["allreduce_s"] for c in comm),
        }
    return out


def plot(runs: dict[str, list[dict]], summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(runs)
    colors = {"1 rank": "tab:gray", "2 ranks": "tab:blue", "1 proc x 2 threads": "tab:orange"}
    fig, axes = plt.subplots(1, 4, figsize=(21, 4.8))
    ax = axes[0]
    med = [summary["setups"][n]["images_per_s_median"] for n in names]
    ax.bar(names, med, color=[colors[n] for n in names])
    for i, n in enumerate(names):
        vals = summary["setups"][n]["images_per_s"]
        ax.plot([i] * len(vals), vals, "k.", ms=5)
        ax.text(i, med[i], f"{med[i]:.2f}\n({summary['setups'][n]['speed_vs_1_rank']:.2f}x)", ha="center", va="bottom", fontsize=9)
    ax.set_ylabel("training views / s (median, dots: runs)")
    ax.set_title("throughput (wall clock)")
    ax = axes[1]
    med = [summary["setups"][n]["cpu_s_per_view_median"] for n in names]
    ax.bar(names, med, color=[colors[n] for n in names])
    for i, n in enumerate(names):
        vals = [r["cpu_s_per_view"] for r in runs[n]]
        ax.plot([i] * len(vals), vals, "k.", ms=5)
        ax.text(i, med[i], f"{med[i]:.2f}", ha="center", va="bottom", fontsize=9)
    ax.set_ylabel("CPU seconds per view, all processes and threads")
    ax.set_title("work per view")
    ax = axes[2]
    for n in names:
        for k, r in enumerate(runs[n]):
            ax.plot([c["train_s"] for c in r["curve"]], [c["psnr"] for c in r["curve"]], "-", color=colors[n], alpha=0.8, label=n if k == 0 else None)
    ax.axhline(summary["target_psnr"], color="k", ls=":", lw=1, label=f"target {summary['target_psnr']:.2f} dB")
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title("time to a target PSNR")
    ax.legend(fontsize=8)
    ax = axes[3]
    comm = [c for r in runs.get("2 ranks", []) for c in r["comm"]]
    if comm:
        ax.plot([c["n_gaussians"] / 1e3 for c in comm], [c["bytes"] / 2**20 for c in comm], ".", ms=3, color="tab:blue")
    ax.set_xlabel("Gaussians (thousands)")
    ax.set_ylabel("all-reduce payload per step (MiB)")
    ax.set_title("communication, 2 ranks")
    load = summary["machine"]["load_during"]
    fig.suptitle(
        f"data-parallel 3DGS on {Path(summary['dataset']).name} ({summary['iterations']} views, resolution x{summary['resolution_scale']:g}), "
        f"2-core CPU, gloo; machine shared: 1-min load {min(load):.0f}-{max(load):.0f}"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--iterations", type=int, default=600, help="training views per run")
    parser.add_argument("--eval-every", type=int, default=100, help="views between test evaluations")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution-scale", type=float, default=1.0, help="train and evaluate at this fraction of the image size")
    parser.add_argument("--out", type=Path, default=Path("out/distributed"))
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--result", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    loads = [load_before[0]]
    runs: dict[str, list[dict]] = {name: [] for name in SETUPS}
    names = list(SETUPS)
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(args.repeats):
            order = names[round_ % len(names):] + names[: round_ % len(names)]  # alternate who goes first
            for name in order:
                r = run_setup(name, args, Path(tmp) / "result.json")
                runs[name].append(r)
                loads.append(os.getloadavg()[0])
                print(f"round {round_ + 1}: {name}: {r['images_per_s']:.2f} views/s, PSNR {r['final_psnr']:.2f} dB, "
                      f"{r['n_gaussians']} Gaussians, load {os.getloadavg()[0]:.1f}", flush=True)
    summary = summarize(runs)
    summary.update({
        "dataset": args.dataset, "iterations": args.iterations, "repeats": args.repeats, "seed": args.seed,
        "resolution_scale": args.resolution_scale,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "load_before": load_before, "load_after": os.getloadavg(),
                    "load_during": loads},
    })
    (args.out / "distributed.json").write_text(json.dumps({"summary": summary, "runs": runs}, indent=1))
    plot(runs, summary, args.out / "distributed.png")
    print(json.dumps({k: v for k, v in summary.items() if k != "machine"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
