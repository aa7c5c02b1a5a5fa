"""Our trainer's CUDA backend against gsplat's own training step, side by side.

Side A is our trainer (``python -m promptgs_engine train ... --strategy 3dgs --no-sky``);
its time is ``train_seconds`` of ``train.json`` (the training loop only). Side B restates
the default training step of gsplat 1.5.3's ``examples/simple_trainer.py``, which cannot
run here as is (it needs viser, nerfview, fused-ssim and a pycolmap fork, and downloads
LPIPS weights): Gaussians at the SfM points with scales from the RMS distance to the three
nearest neighbours, opacity 0.1, SH degree 3 with sh0 from the point colours and the
degree raised every ``--sh-interval`` steps, one torch Adam per parameter with
simple_trainer's learning rates (means × scene scale, decayed exponentially to 0.01×),
one random training view per step at full resolution,
``gsplat.rasterization(packed=False, absgrad=False)``, loss 0.8·L1 + 0.2·(1 − SSIM), then
the optimisers, the scheduler and ``gsplat.strategy.DefaultStrategy``.

What differs from simple_trainer, on purpose:
- SSIM is our ``promptgs_engine.losses.photometric_maps`` (torch convolutions on CUDA,
  "same" padding), the function our trainer uses, instead of fused-ssim, so the SSIM cost
  is the same on both sides; no viewer, no data loader workers (the training images are
  decoded onto the device before the loop), no evaluation inside the loop.
- The refinement schedule (start, stop, interval, opacity reset) is our
  ``DefaultSchedule.for_iterations(steps)``, so densification follows the same steps, and
  so is the SH interval unless ``--sh-interval`` is given (simple_trainer: 1000; ours
  scales with the run, 233 at 7000 steps; the SH degree changes the render cost).
- The scene scale is our ``scene.extent``: simple_trainer's 1.1 × camera radius, but in
  the dataset's coordinates (simple_trainer normalises the world first; the means
  learning rate and the strategy's size thresholds scale with it alike).
- simple_trainer's Adam is torch's default one; ours is ``fused=True``. Side B keeps
  gsplat's: that difference is part of what is measured.
- gsplat 1.5.3's DefaultStrategy never resets opacity (an operator-precedence slip, see
  ``promptgs_engine/strategies/default.py``); side B applies the reset at the steps its
  ``reset_every`` names, as ours does and as simple_trainer means to, so both sides grow
  and prune alike. The Gaussian counts of both sides are in the JSON.

Each run index trains A and B (seed = run index), each in a fresh process (fresh CUDA
context); even run indices train A first and odd ones B first, so that warm-up and machine
load drift fall on both sides alike. ``--device cpu`` is a smoke mode: side A
uses ``--backend cpu``, side B our CPU rasterizer in place of ``gsplat.rasterization``.

    python benchmarks/gsplat_side_by_side.py ../shared/data/tumbler --out out/gsplat
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SSIM_NOTE = "promptgs_engine.losses.photometric_maps on both sides (torch SSIM on CUDA, no fused-ssim)"


def run_ours(dataset: str, images: str, steps: int, seed: int, device: str) -> dict:
    """Side A: our trainer's CLI in a subprocess; its loop time, Gaussians and test PSNR."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        cmd = [sys.executable, "-m", "promptgs_engine", "train", dataset, "--images", images,
               "--backend", "cuda" if device == "cuda" else "cpu", "--iterations", str(steps),
               "--strategy", "3dgs", "--no-sky", "--seed", str(seed), "--quiet", "--out", str(out)]
        check_run(cmd)
        train = json.loads((out / "train.json").read_text())
        metrics_path = out / "metrics.json"
        psnr = json.loads(metrics_path.read_text()).get("psnr") if metrics_path.exists() else None
    return {"train_seconds": train["train_seconds"], "n_gaussians": train["n_gaussians"], "psnr": psnr}


def run_gsplat(dataset: str, images: str, steps: int, seed: int, device: str, sh_interval: int) -> dict:
    """Side B in a subprocess (this script's ``--worker`` mode); the worker's JSON line."""
    cmd = [sys.executable, __file__, dataset, "--images", images, "--steps", str(steps),
           "--device", device, "--sh-interval", str(sh_interval), "--worker", str(seed)]
    return json.loads(check_run(cmd).strip().splitlines()[-1])


def check_run(cmd: list[str]) -> str:
    """Run ``cmd`` from the repository root; its stdout, or an error with its output's tail."""
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=os.environ.copy())
    if proc.returncode != 0:
        tail = (proc.stdout + proc.stderr).strip().splitlines()[-15:]
        raise RuntimeError(f"{' '.join(cmd[:4])} ... exited with {proc.returncode}:\n" + "\n".join(tail))
    return proc.stdout


def gsplat_worker(dataset: str, images: str, steps: int, seed: int, device: str, sh_interval: int) -> dict:
    """simple_trainer's default training step (see the module docstring), timed."""
    import torch
    from gsplat.strategy import DefaultStrategy
    from gsplat.strategy.ops import reset_opa

    from promptgs_engine.data import load_colmap_scene
    from promptgs_engine.evaluation import evaluate
    from promptgs_engine.gaussians import nearest_neighbor_distance, num_sh_bases, rgb_to_sh
    from promptgs_engine.losses import photometric_maps
    from promptgs_engine.render import render
    from promptgs_engine.strategies import DefaultSchedule

    torch.manual_seed(seed)
    dev = torch.device(device)
    scene = load_colmap_scene(dataset, images=images)
    cams = scene.train_cameras
    gts = [c.load_image().to(dev) for c in cams]
    viewmats = [c.world_to_camera[None].to(dev) for c in cams]
    Ks = [c.K[None].to(dev) for c in cams]

    points, colors = scene.points.float(), scene.point_colors.float().clamp(0, 1)
    n, sh_degree = points.shape[0], 3
    sh = torch.zeros(n, num_sh_bases(sh_degree), 3)
    sh[:, 0] = rgb_to_sh(colors)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    init = {
        "means": points, "scales": torch.log(nearest_neighbor_distance(points, rms=True)).unsqueeze(-1).repeat(1, 3), "quats": quats,
        "opacities": torch.logit(torch.full((n,), 0.1)), "sh0": sh[:, :1], "shN": sh[:, 1:],
    }
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.contiguous().to(dev)) for k, v in init.items()})
    lrs = {"means": 1.6e-4 * scene.extent, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2,
           "sh0": 2.5e-3, "shN": 2.5e-3 / 20}
    optimizers = {k: torch.optim.Adam([{"params": [params[k]], "lr": lr, "name": k}], eps=1e-15)
                  for k, lr in lrs.items()}
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], gamma=0.01 ** (1.0 / steps))
    sched = DefaultSchedule.for_iterations(steps)
    strategy = DefaultStrategy(refine_start_iter=sched.refine_start_iter, refine_stop_iter=sched.refine_stop_iter,
                               refine_every=sched.refine_every, reset_every=sched.reset_every)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=scene.extent)

    def rasterize(i: int, degree: int):
        colors_sh = torch.cat([params["sh0"], params["shN"]], dim=1)
        args = (params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
                colors_sh, viewmats[i], Ks[i], cams[i].width, cams[i].height)
        if device == "cpu":  # smoke mode: our CPU rasterizer
            return render(*args, sh_degree=degree, backend="cpu")
        from gsplat import rasterization

        return rasterization(*args, sh_degree=degree, packed=False, absgrad=False)

    def sync() -> None:
        if device == "cuda":
            torch.cuda.synchronize()

    order: list[int] = []
    sync()
    t0 = time.perf_counter()
    for step in range(steps):
        if not order:  # a fresh shuffle of the views per epoch, as simple_trainer's loader
            order = torch.randperm(len(cams)).tolist()
        i = order.pop()
        img, _, info = rasterize(i, min(step // sh_interval, sh_degree))
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss, _, _ = photometric_maps(img, gts[i][None], 0.2)
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        scheduler.step()
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        if 0 < step < sched.refine_stop_iter and step % sched.reset_every == 0:
            reset_opa(params=params, optimizers=optimizers, state=state, value=strategy.prune_opa * 2.0)
    sync()
    seconds = time.perf_counter() - t0
    backend = "cuda" if device == "cuda" else "cpu"
    psnr = evaluate(params, scene.test_cameras, backend=backend, quiet=True)["psnr"] if scene.test_cameras else None
    return {"train_seconds": seconds, "n_gaussians": int(params["means"].shape[0]), "psnr": psnr}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(9, 4))
    runs = range(len(result["runs"]))
    for j, (side, color) in enumerate((("ours", "tab:green"), ("gsplat", "tab:gray"))):
        values = [r[side]["ms_per_step"] for r in result["runs"]]
        ax.bar([x + (j - 0.5) * 0.4 for x in runs], values, 0.4, color=color, label=f"{side} (median {result[side]['median_ms_per_step']:.2f})")
    ax.set_xticks(list(runs), [f"run {r}" for r in runs])
    ax.set_ylabel("ms per training step")
    ax.legend(fontsize=8)
    bx.plot(list(runs), [r["ratio"] for r in result["runs"]], "o-", color="tab:blue")
    bx.axhline(1.0, color="k", lw=0.8)
    bx.axhline(1.1, color="tab:red", lw=0.8, ls="--", label="goal: within 10%")
    bx.set_xticks(list(runs), [f"run {r}" for r in runs])
    bx.set_ylabel("ours / gsplat (ms per step)")
    bx.legend(fontsize=8)
    fig.suptitle(f"{Path(result['dataset']).name}/{result['images']}, {result['steps']} steps on {result['device_name']}; "
                 f"median ratio {result['median_ratio']:.2f}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", help="COLMAP scene folder (images/, sparse/0/)")
    ap.add_argument("--images", default="images", help="images folder inside the dataset")
    ap.add_argument("--steps", type=int, default=7000)
    ap.add_argument("--runs", type=int, default=3, help="pairs, ours first on even run indices and gsplat first on odd; seed = run index")
    ap.add_argument("--device", default="cuda", choices=("cuda", "cpu"), help="cpu: smoke mode")
    ap.add_argument("--out", type=Path, default=Path("out/gsplat_side_by_side"), help="writes OUT.json and OUT.png")
    ap.add_argument("--sh-interval", type=int, help="gsplat side's SH degree interval (default: ours for --steps)")
    ap.add_argument("--worker", type=int, metavar="SEED", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    from promptgs_engine.strategies import DefaultSchedule

    sh_interval = args.sh_interval or DefaultSchedule.for_iterations(args.steps).sh_degree_interval
    if args.worker is not None:
        result = gsplat_worker(args.dataset, args.images, args.steps, args.worker, args.device, sh_interval)
        print(json.dumps(result), flush=True)
        return 0

    import gsplat
    import torch

    device_name = torch.cuda.get_device_name(0) if args.device == "cuda" else "cpu (smoke mode)"
    load_start = os.getloadavg()[0]
    runs = []
    for seed in range(args.runs):
        # Pairs alternate their order, so that warm-up and drift fall on both sides alike.
        first = "ours" if seed % 2 == 0 else "gsplat"
        if first == "ours":
            ours = run_ours(args.dataset, args.images, args.steps, seed, args.device)
            theirs = run_gsplat(args.dataset, args.images, args.steps, seed, args.device, sh_interval)
        else:
            theirs = run_gsplat(args.dataset, args.images, args.steps, seed, args.device, sh_interval)
            ours = run_ours(args.dataset, args.images, args.steps, seed, args.device)
        for side in (ours, theirs):
            side["ms_per_step"] = side["train_seconds"] / args.steps * 1e3
        runs.append({"seed": seed, "first": first, "ours": ours, "gsplat": theirs, "ratio": ours["ms_per_step"] / theirs["ms_per_step"]})
        print(f"run {seed} ({first} first): ours {ours['ms_per_step']:.2f} ms/step ({ours['n_gaussians']} Gaussians), "
              f"gsplat {theirs['ms_per_step']:.2f} ms/step ({theirs['n_gaussians']}), ratio {runs[-1]['ratio']:.3f}", flush=True)
    result = {
        "dataset": str(args.dataset), "images": args.images, "steps": args.steps, "device": args.device,
        "device_name": device_name, "ssim": SSIM_NOTE, "gsplat_version": gsplat.__version__,
        "schedule": vars(DefaultSchedule.for_iterations(args.steps)), "gsplat_sh_interval": sh_interval,
        "load_average": [load_start, os.getloadavg()[0]], "runs": runs,
        "median_ratio": statistics.median(r["ratio"] for r in runs),
    }
    for side in ("ours", "gsplat"):
        result[side] = {f"median_{key}": statistics.median(r[side][key] for r in runs)
                        for key in ("ms_per_step", "n_gaussians")}
        psnrs = [r[side]["psnr"] for r in runs if r[side]["psnr"] is not None and math.isfinite(r[side]["psnr"])]
        result[side]["median_psnr"] = statistics.median(psnrs) if psnrs else None
    json_path, png_path = Path(f"{args.out}.json"), Path(f"{args.out}.png")
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(result, indent=2))
    plot(result, png_path)
    print(f"median ms/step: ours {result['ours']['median_ms_per_step']:.2f}, gsplat {result['gsplat']['median_ms_per_step']:.2f}; "
          f"median ratio ours/gsplat {result['median_ratio']:.3f} -> {json_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
