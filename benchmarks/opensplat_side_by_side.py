"""Our trainer and OpenSplat's CPU mode side by side: whole training steps on the same scene.

Both train the same COLMAP scene from the same SfM points (no far-background points on our
side, so the Gaussian counts match), at full size from the first step (OpenSplat
``--num-downscales 0``), with the same SH schedule, the same loss (0.8 L1 + 0.2 D-SSIM) and
no densification (ours: refinement and opacity resets off; OpenSplat: ``--warmup-length`` or,
from 1.2.0, ``--densify-from`` past the last step), on the same number of threads
(``OMP_NUM_THREADS``; both get the same environment, ``OMP_WAIT_POLICY=PASSIVE`` and any
``PROMPTGS_SIMD`` included). At the small size OpenSplat reads the dataset's downscaled
images folder (``--colmap-image-path``, in the builds that have it) as we do (``--images``),
or else downscales the full images itself to the same size (``-d``, 4 for ``images_4``).
The flags come from the binary's ``--help``, so OpenSplat 1.1.5 and 1.2.0 both run; the
version (``--version``) goes into the JSON with the commands, our commit, the CPU model
and the kernel level our extension picked (``_C.simd_variant()``, capped by
``PROMPTGS_SIMD``). OpenSplat 1.2.0 steps its optimisers on a cadence of its own (every
step until half the run, then every 32 or 64 steps): what a step of each trainer does is
what it is timed doing.

A step's time is the wall time between two consecutive per-step lines of each trainer's
output, as this script receives them (OpenSplat prints one per step in CPU mode; our worker
does the same): the whole loop body, loss, backward, optimiser and bookkeeping included.
The first ``--skip`` steps of every run are left out (warm-up). Runs alternate between the
two trainers (ours, OpenSplat, OpenSplat, ours, ...), so a machine shared with other jobs
slows both alike.

OpenSplat is not part of this project: build it yourself (CPU mode, against the installed
torch) and pass the binary, e.g.::

    cmake -S OpenSplat -B build -G Ninja -DGPU_RUNTIME=CPU -DCMAKE_BUILD_TYPE=Release \\
        -DCMAKE_PREFIX_PATH=$(python -c 'import torch; print(torch.utils.cmake_prefix_path)')
    cmake --build build -j2
    python benchmarks/opensplat_side_by_side.py build/opensplat /work/shared/data/tumbler

(1.2.0 vendors its dependencies; 1.1.5 fetches nlohmann_json, nanoflann and cxxopts unless
CMake finds them installed.) Writes ``opensplat.json`` and ``opensplat.png`` into ``--out``.
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
        from promptgs_engine import _C

        print(f"gaussians {trainer.n_gaussians}", flush=True)
        print(f"simd {_C.simd_variant()}", flush=True)
        while trainer.step < steps:
            # the PSNR on the steps the CLI's run loop reports, as it measures it
            result = trainer.train_step(psnr=trainer.reports_progress(trainer.step + 1))
            trainer.step += 1
            print(f"Step {trainer.step}: {result.loss:.5f}", flush=True)
    return 0


def image_size(folder: Path) -> tuple[int, int]:
    """(width, height) of the first image of a dataset's images folder."""
    from PIL import Image

    first = min(p for p in folder.iterdir() if p.is_file())
    with Image.open(first) as im:
        return im.width, im.height


def opensplat_command(binary: Path, help_text: str, dataset: Path, images: str, steps: int, interval: int,
                      out_ply: Path) -> list[str]:
    """OpenSplat's command line for our run of ``steps`` steps on ``dataset``/``images``, with the
    flags its ``--help`` lists: the images folder itself (``--colmap-image-path``, in the builds
    that have it) or a downscale of the full images to its size (``-d``), and densification
    off (``--warmup-length``, 1.1.x; ``--densify-from``, 1.2.0)."""
    cmd = [str(binary), str(dataset), "--cpu", "-n", str(steps), "-o", str(out_ply), "--num-downscales", "0",
           "--sh-degree", "3", "--sh-degree-interval", str(interval), "--ssim-weight", "0.2",
           "--refine-every", str(steps + 1)]
    if "--colmap-image-path" in help_text:
        cmd += ["--colmap-image-path", str(dataset / images)]
    elif images != "images":
        factor = image_size(dataset / "images")[0] / image_size(dataset / images)[0]
        if abs(factor - round(factor)) > 1e-6:
            raise SystemExit(f"{dataset / images}: not a whole downscale of {dataset / 'images'} ({factor:.3f}x), "
                             "and this OpenSplat has no --colmap-image-path")
        cmd += ["-d", str(round(factor))]
    if "--warmup-length" in help_text:
        cmd += ["--warmup-length", str(steps + 1)]
    elif "--densify-from" in help_text:
        cmd += ["--densify-from", str(steps + 1)]
    else:
        raise SystemExit(f"{binary}: its --help lists neither --warmup-length nor --densify-from; "
                         "densification cannot be switched off")
    return cmd


def cpu_model() -> dict:
    """The CPU's model name, family and model numbers, and vector extensions (Linux
    /proc/cpuinfo; empty elsewhere). Virtual machines often report a bare name ("AMD EPYC")
    for CPUs of different generations; the family and model numbers tell them apart."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {}
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    flags = set(fields.get("flags", "").split())
    return {"model": fields.get("model name", "?"), "family": fields.get("cpu family"),
            "model_number": fields.get("model"), "avx2": "avx2" in flags, "avx512f": "avx512f" in flags}


def cpu_line(cpu: dict) -> str:
    """The CPU model, its family and model numbers and its widest vector extension, e.g.
    "AMD EPYC, family 26 model 2 (AVX-512)"."""
    widest = "AVX-512" if cpu.get("avx512f") else "AVX2" if cpu.get("avx2") else "no AVX2"
    numbers = f", family {cpu['family']} model {cpu['model_number']}" if cpu.get("family") else ""
    return f"{cpu.get('model', '?')}{numbers} ({widest})"


def our_commit() -> str:
    """``git describe --always --dirty`` of this checkout, or "unknown"."""
    run = subprocess.run(["git", "-C", str(REPO), "describe", "--always", "--dirty", "--abbrev=10"],
                         capture_output=True, text=True, check=False)
    return run.stdout.strip() if run.returncode == 0 else "unknown"


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
    run = {"stamps": stamps, "wall_s": time.perf_counter() - t0, "log_tail": other[-3:], "other": other}
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
                 f"{m['load_average_end']:.1f}; OpenSplat {results['opensplat_version']};\n"
                 f"PromptGS {results['promptgs_commit']} ({results['promptgs_kernels']} kernels); {cpu_line(m['cpu'])}",
                 fontsize=8)
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
    machine = {"threads": args.threads, "cpu_count": os.cpu_count(), "cpu": cpu_model(),
               "load_average_start": os.getloadavg()[0]}
    version = subprocess.run([str(args.opensplat), "--version"], capture_output=True, text=True, env=env, check=False)
    help_text = subprocess.run([str(args.opensplat), "--help"], capture_output=True, text=True, env=env,
                               check=False).stdout
    results: dict = {"machine": machine, "dataset": str(args.dataset), "steps": args.steps, "skip": args.skip,
                     "runs": args.runs, "sh_degree_interval": interval, "opensplat": str(args.opensplat),
                     "opensplat_version": version.stdout.strip().splitlines()[0] if version.stdout.strip() else "?",
                     "promptgs_commit": our_commit(), "promptgs_simd_cap": os.environ.get("PROMPTGS_SIMD"),
                     "promptgs_kernels": None, "opensplat_commands": {}, "sizes": {}}
    print(f"OpenSplat {results['opensplat_version']}, PromptGS {results['promptgs_commit']}, "
          f"{cpu_line(machine['cpu'])}, PROMPTGS_SIMD={results['promptgs_simd_cap']}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for images in args.sizes.split(","):
            ours_cmd = [sys.executable, str(Path(__file__).resolve()), "--ours-worker", str(args.dataset), images,
                        str(args.steps)]
            theirs_cmd = opensplat_command(args.opensplat, help_text, args.dataset, images, args.steps, interval,
                                           Path(tmp) / "splat.ply")
            results["opensplat_commands"][images] = theirs_cmd[1:]
            runs: dict[str, list[dict]] = {"promptgs": [], "opensplat": []}
            for rep in range(args.runs):
                order = ["promptgs", "opensplat"] if rep % 2 == 0 else ["opensplat", "promptgs"]
                for name in order:
                    cmd = ours_cmd if name == "promptgs" else theirs_cmd
                    load = os.getloadavg()[0]
                    run = timed_run(cmd, env, args.steps)
                    if name == "promptgs":
                        kernels = [line.split()[1] for line in run["other"] if line.startswith("simd ")]
                        if results["promptgs_kernels"] not in (None, *kernels):
                            raise RuntimeError(f"our worker picked {kernels} kernels, {results['promptgs_kernels']} before")
                        results["promptgs_kernels"] = kernels[0] if kernels else "?"
                    del run["other"]
                    run["load_average"] = [load, os.getloadavg()[0]]
                    run["step_s"] = step_times(run.pop("stamps"), args.skip)
                    runs[name].append(run)
                    print(f"{images} {name} run {rep + 1}: median step {statistics.median(run['step_s']) * 1e3:.1f} ms "
                          f"(load {run['load_average'][0]:.1f})", flush=True)
            r: dict = {}
            for name, rs in runs.items():
                all_steps = [t for run in rs for t in run["step_s"]]
                r[name] = {"median_step_s": statistics.median(all_steps),
                           "run_medians_s": [statistics.median(run["step_s"]) for run in rs], "runs": rs}
            r["ratio"] = r["opensplat"]["median_step_s"] / r["promptgs"]["median_step_s"]
            size = "{}x{}".format(*image_size(args.dataset / images))
            results["sizes"][size] = r
            print(f"{size}: promptgs {r['promptgs']['median_step_s'] * 1e3:.1f} ms, opensplat "
                  f"{r['opensplat']['median_step_s'] * 1e3:.1f} ms per step: {r['ratio']:.1f}x", flush=True)
    # The Gaussian count both start from (our worker prints it).
    from promptgs_engine.data import load_colmap_scene

    results["n_gaussians"] = int(load_colmap_scene(args.dataset).points.shape[0])
    machine["load_average_end"] = os.getloadavg()[0]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "opensplat.json").write_text(json.dumps(results, indent=2))
    plot(results, args.out / "opensplat.png")
    print(f"wrote {args.out / 'opensplat.json'} and {args.out / 'opensplat.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
