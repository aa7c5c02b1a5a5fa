"""Whole training steps of two checkouts of this repository, side by side on one scene.

Runs the trainer of checkout A and of checkout B (each with its own built extension)
alternately (A, B, B, A, ...) with exactly the work `benchmarks/opensplat_side_by_side.py`
times for our side (SfM points, no densification, 2 threads), and reports each one's
median step time and the ratio B/A of the medians, per run pair and overall, and the same
for the worker's CPU time a step (all threads: on a machine shared with other jobs the
work itself, where wall times mostly measure the others). For a
before/after of a change, build the old commit beside the new one::

    git worktree add --detach ../old <commit> && (cd ../old && python setup.py build_ext --inplace -q)
    python benchmarks/trainer_ab.py ../old . /work/shared/data/tumbler --images images_4 --runs 5

Writes ``trainer_ab.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from opensplat_side_by_side import step_times, timed_run  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("a", type=Path, help="checkout A (the baseline)")
    ap.add_argument("b", type=Path, help="checkout B")
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--images", default="images_4", help="images folder of the dataset (the training size)")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--skip", type=int, default=10, help="first steps of every run left out")
    ap.add_argument("--runs", type=int, default=5, help="runs of each checkout (alternated)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("out/trainer_ab"))
    args = ap.parse_args(argv)
    checkouts = {"a": args.a.resolve(), "b": args.b.resolve()}
    for name, path in checkouts.items():
        if not (path / "benchmarks" / "opensplat_side_by_side.py").is_file():
            raise SystemExit(f"{path}: not a checkout of this repository (checkout {name.upper()})")
    load0 = os.getloadavg()[0]
    medians: dict[str, list[float]] = {"a": [], "b": []}
    cpu_medians: dict[str, list[float]] = {"a": [], "b": []}
    for r in range(args.runs):
        for name in ("a", "b") if r % 2 == 0 else ("b", "a"):
            repo = checkouts[name]
            env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), OMP_WAIT_POLICY="PASSIVE", PYTHONPATH=str(repo))
            cmd = [sys.executable, str(repo / "benchmarks" / "opensplat_side_by_side.py"), "--ours-worker",
                   str(args.dataset), args.images, str(args.steps)]
            run = timed_run(cmd, env, args.steps, cpu=True)
            wall, cpu = run["stamps"], run["cpu_stamps"]
            medians[name].append(statistics.median(step_times(wall, args.skip)))
            # CPU clock ticks are 10 ms: the CPU time of a step is read over the measured steps
            cpu_medians[name].append((cpu[-1] - cpu[args.skip]) / (len(cpu) - 1 - args.skip))
            print(f"run {r + 1} {name.upper()}: median step {medians[name][-1] * 1e3:.2f} ms wall, "
                  f"{cpu_medians[name][-1] * 1e3:.2f} ms CPU (all threads, mean)", flush=True)
    pair_ratios = [b / a for a, b in zip(medians["a"], medians["b"])]
    cpu_ratios = [b / a for a, b in zip(cpu_medians["a"], cpu_medians["b"])]
    res = {
        "a": str(checkouts["a"]), "b": str(checkouts["b"]), "dataset": str(args.dataset), "images": args.images,
        "steps": args.steps, "skip": args.skip, "runs": args.runs, "threads": args.threads,
        "load_average": [load0, os.getloadavg()[0]], "median_step_s": medians,
        "a_median_s": statistics.median(medians["a"]), "b_median_s": statistics.median(medians["b"]),
        "pair_ratios_b_over_a": pair_ratios, "median_pair_ratio_b_over_a": statistics.median(pair_ratios),
        "cpu_s_per_step": cpu_medians, "cpu_pair_ratios_b_over_a": cpu_ratios,
        "median_cpu_pair_ratio_b_over_a": statistics.median(cpu_ratios),
    }
    print(f"A {res['a_median_s'] * 1e3:.2f} ms, B {res['b_median_s'] * 1e3:.2f} ms, B/A pair ratios "
          + ", ".join(f"{x:.3f}" for x in pair_ratios) + f" (median {res['median_pair_ratio_b_over_a']:.3f}); "
          f"load {load0:.1f} -> {res['load_average'][1]:.1f}")
    print("CPU time a step (all threads; robust to other jobs, not to memory contention): B/A pair ratios "
          + ", ".join(f"{x:.3f}" for x in cpu_ratios) + f" (median {res['median_cpu_pair_ratio_b_over_a']:.3f})")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "trainer_ab.json").write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
