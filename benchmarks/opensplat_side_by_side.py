"""Our trainer and OpenSplat's CPU mode side by side: whole training steps on the same scene.

Both train the same COLMAP scene from the same SfM points (no far-background points on our
side, so the Gaussian counts match), at full size from the first step (OpenSplat
``--num-downscales 0``), with the same SH schedule, the same loss (0.8 L1 + 0.2 D-SSIM) and
no densification (ours: refinement and opacity resets off; OpenSplat: ``--warmup-length``
past the last step), on the same number of threads (``OMP_NUM_THREADS``; both get the same
environment, ``OMP_WAIT_POLICY=PASSIVE`` included, which our engine sets for itself anyway).
At the small size OpenSplat reads the dataset's downscaled images folder
(``--colmap-image-path``) as we do (``--images``).

A step's time is the wall time between two consecutive per-step lines of each trainer's
output, as this script receives them (OpenSplat prints one per step in CPU mode; our worker
does the same): the whole loop body, loss, backward, optimiser and bookkeeping included.
The first ``--skip`` steps of every run are left out (warm-up). Runs alternate between the
two trainers (ours, OpenSplat, OpenSplat, ours, ...), so a machine shared with other jobs
slows both alike.

OpenSplat is not part of this project: build it yourself (CPU mode, against the installed
torch) and pass the binary, e.g.::

    cmake -S OpenSplat -B build -DGPU_RUNTIME=CPU -DCMAKE_BUILD_TYPE=Release \\
        -DCMAKE_PREFIX_PATH=$(python -c 'import torch; print(torch.utils.cmake_prefix_path)')
    cmake --build build -j2
    python benchmarks/opensplat_side_by_side.py build/opensplat /work/shared/data/tumbler

Writes ``opensplat.json`` and ``opensplat.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def sh_interval(steps: int) -> int:
    """Our schedule's SH degree interval for a run of ``steps`` steps (DefaultSchedule)."""
    from promptgs_engine.strategies import DefaultSchedule

    return DefaultSchedule.for_iterations(steps).sh_degree_interval


def ours_worker(dataset: str, images: str, steps: int) -> int:
    """Train without densification, printing one line per finished step."""
    from promptgs_engine.config import TrainConfig
    from promptgs_engine.train import Trainer

    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig(dataset=dataset, out=str(Path(tmp) / "run"), images=images, iterations=steps, backend="cpu",
                          sky=False, checkpoint_every=0)
        trainer = Trainer(cfg, quiet=True)
        trainer.strategy.refine_every = 10**9  # no growth or pruning
        trainer.strategy.reset_every = 10**9  # no opacity reset
        print(f"gaussians {trainer.n_gaussians}", flush=True)
        while trainer.step < steps:
            result = trainer.train_step()
            trainer.step += 1
            print(f"Step {trainer.step}: {result.loss:.5f}", flush=True)
    return 0


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a running process, all its threads (Linux), or None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def timed_run(cmd: list[str], env: dict, steps: int, cpu: bool = False) -> dict:
    """Run a trainer; the arrival time of each 'Step N' line, and the other lines' tail.
    With ``cpu``, also the trainer's CPU time (all threads) at each of those lines."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, bufsize=1)
    stamps: list[float] = []
    cpu_stamps: list[float] = []
    other: list[str] = []
    assert proc.stdout
    for line in proc.stdout:
        if line.startswith("Step "):
            stamps.append(time.perf_counter())
            if cpu:
                cpu_stamps.append(cpu_seconds(proc.pid) or float("nan"))
        else:
            other.append(line.rstrip())
    rc = proc.wait()
    if rc != 0 or len(stamps) < steps:
        tail = "\n".join(other[-15:])
        raise RuntimeError(f"{cmd[0]} exited with {rc} after {len(stamps)} steps:\n{tail}")
    run = {"stamps": stamps, "wall_s": time.perf_counter() - t0, "log_tail": other[-3:]}
    if cpu:
        run["cpu_stamps"] = cpu_stamps
    return run


def step_times(stamps: list[float], skip: int) -> list[float]:
    return [b - a for a, b in zip(stamps[skip:], stamps[skip + 1 :])]


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = list(results["sizes"])
    fig, ax = plt.subplots(figsize=(7, 4))
    w = 0.35
    for i, size in enumerate(sizes):
        r = results["sizes"][size]
        for j, (name, color) in enumerate((("promptgs", "tab:green"), ("opensplat", "tab:gray"))):
            v = r[name]["median_step_s"] * 1e3
            bar = ax.bar(i + (j - 0.5) * w, v, w, color=color, label=name if i == 0 else None)
            ax.bar_label(bar, fmt="%.0f ms", fontsize=8)
    ax.set_yscale("log")
    ax.set_xticks(range(len(sizes)), [f"{s}\n{results['sizes'][s]['ratio']:.1f}x faster" for s in sizes])
    ax.set_ylabel("median whole training step (ms, log)")
    m = results["machine"]
    ax.set_title(f"Tumbler, {results['n_gaussians']:,} SfM Gaussians, no densification, {m['threads']} threads each;\n"
                 f"{results['runs']} alternated runs of {results['steps']} steps, load {m['load_average_start']:.1f}-"
                 f"{m['load_average_end']:.1f}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("opensplat", type=Path, nargs="?", help="OpenSplat binary built in CPU mode")
    ap.add_argument("dataset", type=Path, nargs="?", help="COLMAP dataset (images/, sparse/0/)")
    ap.add_argument("--sizes", default="images,images_4", help="image folders of the dataset, one run per size")
    ap.add_argument("--steps", type=int, default=100, help="steps per run")
    ap.add_argument("--skip", type=int, default=10, help="first steps of every run left out")
    ap.add_argument("--runs", type=int, default=3, help="runs per trainer and size (alternated)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("out/opensplat"))
    ap.add_argument("--ours-worker", nargs=3, metavar=("DATASET", "IMAGES", "STEPS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.ours_worker:
        d, im, st = args.ours_worker
        return ours_worker(d, im, int(st))
    if args.opensplat is None or args.dataset is None:
        ap.error("give the OpenSplat binary and the dataset")
    if not os.access(args.opensplat, os.X_OK):
        raise SystemExit(f"{args.opensplat}: not an executable OpenSplat binary")

    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), OMP_WAIT_POLICY="PASSIVE",
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    interval = sh_interval(args.steps)
    machine = {"threads": args.threads, "cpu_count": os.cpu_count(), "load_average_start": os.getloadavg()[0]}
    results: dict = {"machine": machine, "dataset": str(args.dataset), "steps": args.steps, "skip": args.skip,
                     "runs": args.runs, "sh_degree_interval": interval, "opensplat": str(args.opensplat), "sizes": {}}
    version = subprocess.run([str(args.opensplat), "--version"], capture_output=True, text=True, env=env)
    results["opensplat_version"] = version.stdout.strip()
    n_gaussians = None
    with tempfile.TemporaryDirectory() as tmp:
        for images in args.sizes.split(","):
            ours_cmd = [sys.executable, str(Path(__file__).resolve()), "--ours-worker", str(args.dataset), images,
                        str(args.steps)]
            theirs_cmd = [
                str(args.opensplat), str(args.dataset), "--cpu", "-n", str(args.steps), "-o", str(Path(tmp) / "splat.ply"),
                "--colmap-image-path", str(args.dataset / images), "--num-downscales", "0",
                "--sh-degree", "3", "--sh-degree-interval", str(interval), "--ssim-weight", "0.2",
                "--warmup-length", str(args.steps + 1), "--refine-every", str(args.steps + 1),
            ]
            runs: dict[str, list[dict]] = {"promptgs": [], "opensplat": []}
            for rep in range(args.runs):
                order = ["promptgs", "opensplat"] if rep % 2 == 0 else ["opensplat", "promptgs"]
                for name in order:
                    cmd = ours_cmd if name == "promptgs" else theirs_cmd
                    load = os.getloadavg()[0]
                    run = timed_run(cmd, env, args.steps)
                    run["load_average"] = [load, os.getloadavg()[0]]
                    run["step_s"] = step_times(run.pop("stamps"), args.skip)
                    runs[name].append(run)
                    print(f"{images} {name} run {rep + 1}: median step {statistics.median(run['step_s']) * 1e3:.1f} ms "
                          f"(load {run['load_average'][0]:.1f})", flush=True)
            size = None
            r: dict = {}
            for name, rs in runs.items():
                all_steps = [t for run in rs for t in run["step_s"]]
                r[name] = {"median_step_s": statistics.median(all_steps),
                           "run_medians_s": [statistics.median(run["step_s"]) for run in rs], "runs": rs}
            r["ratio"] = r["opensplat"]["median_step_s"] / r["promptgs"]["median_step_s"]
            from PIL import Image

            first = sorted((args.dataset / images).iterdir())[0]
            with Image.open(first) as im:
                size = f"{im.width}x{im.height}"
            results["sizes"][size] = r
            print(f"{size}: promptgs {r['promptgs']['median_step_s'] * 1e3:.1f} ms, opensplat "
                  f"{r['opensplat']['median_step_s'] * 1e3:.1f} ms per step: {r['ratio']:.1f}x", flush=True)
    # The Gaussian count both start from (our worker prints it).
    from promptgs_engine.data import load_colmap_scene

    n_gaussians = int(load_colmap_scene(args.dataset).points.shape[0])
    results["n_gaussians"] = n_gaussians
    machine["load_average_end"] = os.getloadavg()[0]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "opensplat.json").write_text(json.dumps(results, indent=2))
    plot(results, args.out / "opensplat.png")
    print(f"wrote {args.out / 'opensplat.json'} and {args.out / 'opensplat.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
