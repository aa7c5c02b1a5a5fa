"""How the CPU backend's cost grows with the work: time and peak memory against the number of
Gaussians and against the image size, for the forward pass, the backward pass and a whole
training step, with the scaling exponent fitted on log-log axes.

Every point runs in a fresh process (so its peak resident memory is its own) on random
Gaussians sized like a trained scene (``rasterizer.synthetic_scene``: a few pixels each at
800×600, and proportionally more at larger sizes, since the focal length grows with the
width). A training step here is the trainer's: render, (1 − 0.2)·L1 + 0.2·D-SSIM, backward,
Adam on every parameter. ``forward`` is a render without gradients; ``backward`` is
``loss.backward()`` alone, after a render with gradients. Each time is recorded as wall time
and as the process's CPU time (all threads): on a machine busy with other jobs the second
still measures the work.

    python benchmarks/scaling.py --out out/scaling

Writes ``scaling.json`` and ``scaling.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
KINDS = ("forward", "backward", "train_step")


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def point(size: str, n: int, repeats: int, warmup: int) -> dict:
    """Measure one (size, count) point in this process."""
    import torch

    sys.path.insert(0, str(HERE))
    from rasterizer import Step, canonical_camera, synthetic_scene

    from promptgs_engine.losses import ssim_map

    w, h = (int(v) for v in size.split("x"))
    scene = synthetic_scene(n, 3)
    view, K = canonical_camera(w, h)
    step = Step(scene, view, K, w, h, 3)
    rss_scene = rss_mb()

    def loss_of(out):
        img = out[..., :3]
        return 0.8 * (img - step.target).abs().mean() + 0.2 * (1.0 - ssim_map(img, step.target)).mean()

    def forward():
        with torch.no_grad():
            step.render()

    def backward_only() -> tuple[float, float]:
        out, _, info = step.render()
        info["means2d"].retain_grad()
        loss = loss_of(out)
        t0, c0 = time.perf_counter(), time.process_time()
        loss.backward()
        dt = (time.perf_counter() - t0, time.process_time() - c0)
        for p in step.params.values():
            p.grad = None
        return dt

    def train_step():
        out, _, info = step.render()
        info["means2d"].retain_grad()
        loss_of(out).backward()
        step.adam_step()  # the trainer's Adam; also sets the gradients to None

    def clock(fn) -> tuple[float, float]:
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        return time.perf_counter() - t0, time.process_time() - c0

    for _ in range(warmup):
        forward(), backward_only(), train_step()
    samples = {k: [] for k in KINDS}
    for _ in range(repeats):
        samples["forward"].append(clock(forward))
        samples["backward"].append(backward_only())
        samples["train_step"].append(clock(train_step))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {
        "size": size, "pixels": w * h, "n_gaussians": n,
        **{k: {"median_s": statistics.median(w for w, _ in v), "cpu_median_s": statistics.median(c for _, c in v),
               "samples_s": [w for w, _ in v], "cpu_samples_s": [c for _, c in v]} for k, v in samples.items()},
        "peak_rss_mb": peak, "rss_with_scene_mb": rss_scene, "step_memory_mb": peak - rss_scene,
        "load_average": os.getloadavg()[0],
    }


def run_point(size: str, n: int, repeats: int, warmup: int) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--point", f"{size}:{n}",
           "--repeats", str(repeats), "--warmup", str(warmup)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def fit_exponent(xs: list[float], ys: list[float]) -> float:
    """Slope of log y against log x (least squares)."""
    lx, ly = [math.log(x) for x in xs], [math.log(y) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sum((a - mx) ** 2 for a in lx)


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 8))
    sweeps = [("counts", "n_gaussians", f"Gaussians (at {results['count_size']})"),
              ("sizes", "pixels", f"pixels (with {results['size_count']:,} Gaussians)")]
    colors = {"forward": "tab:blue", "backward": "tab:orange", "train_step": "tab:green"}
    for col, (sweep, xkey, xlabel) in enumerate(sweeps):
        pts = results[sweep]["points"]
        xs = [p[xkey] for p in pts]
        ax = axes[0][col]
        for kind in KINDS:
            ys = [p[kind]["median_s"] * 1e3 for p in pts]
            e = results[sweep]["exponents"][kind]
            ax.loglog(xs, ys, "o-", color=colors[kind], label=f"{kind.replace('_', ' ')}, wall (slope {e:.2f})")
            ys = [p[kind]["cpu_median_s"] * 1e3 for p in pts]
            e = results[sweep]["exponents"][f"{kind}_cpu"]
            ax.loglog(xs, ys, "x:", color=colors[kind], label=f"{kind.replace('_', ' ')}, CPU time (slope {e:.2f})")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("median time (ms)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        if sweep == "sizes":
            for p in pts:
                ax.annotate(p["size"], (p["pixels"], p["train_step"]["median_s"] * 1e3), fontsize=7,
                            textcoords="offset points", xytext=(3, 4))
        ax = axes[1][col]
        mem = [p["step_memory_mb"] for p in pts]
        e = results[sweep]["exponents"]["step_memory_mb"]
        ax.loglog(xs, mem, "s-", color="tab:purple", label=f"step memory over the scene (slope {e:.2f})")
        ax.loglog(xs, [p["peak_rss_mb"] for p in pts], "^--", color="tab:gray", label="peak RSS of the process")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("MiB")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    m = results["machine"]
    fig.suptitle(f"PromptGS CPU backend scaling ({m['threads']} threads, load {m['load_average_start']:.1f}-"
                 f"{m['load_average_end']:.1f}); slopes fitted on log-log axes", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--counts", default="10000,30000,100000,300000,1000000")
    ap.add_argument("--count-size", default="800x600", help="image size of the count sweep")
    ap.add_argument("--sizes", default="200x150,400x300,800x600,1280x720,1920x1080")
    ap.add_argument("--size-count", type=int, default=100_000, help="Gaussians in the size sweep")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("out/scaling"))
    ap.add_argument("--point", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.point:
        size, _, n = args.point.partition(":")
        print(json.dumps(point(size, int(n), args.repeats, args.warmup)))
        return 0

    import torch

    from promptgs_engine import _C

    machine = {"threads": _C.num_threads(), "simd": _C.simd_variant(), "torch": torch.__version__,
               "cpu_count": os.cpu_count(), "load_average_start": os.getloadavg()[0]}
    results: dict = {"machine": machine, "count_size": args.count_size, "size_count": args.size_count}
    sweeps = {
        "counts": [(args.count_size, int(n)) for n in args.counts.split(",")],
        "sizes": [(s, args.size_count) for s in args.sizes.split(",")],
    }
    for sweep, pts in sweeps.items():
        done = []
        for size, n in pts:
            p = run_point(size, n, args.repeats, args.warmup)
            done.append(p)
            print(f"{sweep}: {size}, {n:,} Gaussians: " + ", ".join(
                f"{k} {p[k]['median_s'] * 1e3:.1f} ms (CPU {p[k]['cpu_median_s'] * 1e3:.1f})" for k in KINDS)
                  + f"; peak {p['peak_rss_mb']:.0f} MiB (step {p['step_memory_mb']:.0f} MiB); load {p['load_average']:.1f}")
        xkey = "n_gaussians" if sweep == "counts" else "pixels"
        xs = [p[xkey] for p in done]
        exps = {k: fit_exponent(xs, [p[k]["median_s"] for p in done]) for k in KINDS}
        exps.update({f"{k}_cpu": fit_exponent(xs, [p[k]["cpu_median_s"] for p in done]) for k in KINDS})
        exps["step_memory_mb"] = fit_exponent(xs, [max(p["step_memory_mb"], 1e-3) for p in done])
        results[sweep] = {"points": done, "exponents": exps}
        print(f"{sweep}: fitted exponents " + ", ".join(f"{k} {v:.2f}" for k, v in exps.items()))
    machine["load_average_end"] = os.getloadavg()[0]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "scaling.json").write_text(json.dumps(results, indent=2))
    plot(results, args.out / "scaling.png")
    print(f"wrote {args.out / 'scaling.json'} and {args.out / 'scaling.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
