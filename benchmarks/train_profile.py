"""Where a training step's time goes: the trainer's own step, split by stage.

Runs ``Trainer.train_step`` (the CLI's loop body: view plan and image, render, loss, backward,
Adam, the densification strategy's bookkeeping, the finiteness check) on a real dataset and
times each part with wall clocks around it, plus the C++ stages the extension records itself
(projection, depth sort, binning, gathering, forward blend, backward blend, gradient
reduction; ``_C.stage_times()``, absent from builds older than it). Densification and
opacity resets are switched off so that every measured step does the same work; the
strategy's per-step statistics still run. The steps skip the training PSNR, as the run
loop's steps between its progress reports do.

    python benchmarks/train_profile.py /work/shared/data/tumbler --ply run/point_cloud.ply
    python benchmarks/train_profile.py /work/shared/data/tumbler --images images_4   # SfM points

Writes ``train_profile.json`` (and prints a table) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable

# Idle OpenMP threads sleep, as in the trainer (promptgs_engine sets this too, but only if
# imported before torch loads the OpenMP runtime): with spinning threads a 2-thread step
# measures the spinning.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from opensplat_side_by_side import cpu_model


class Clock:
    """Per-step sums of time by stage name: wall time, or the CPU time of this thread (with one
    thread, the work itself, however busy the machine is)."""

    def __init__(self, cpu: bool = False) -> None:
        self.now = time.thread_time if cpu else time.perf_counter
        self.step: dict[str, float] = defaultdict(float)
        self.steps: list[dict[str, float]] = []

    def wrap(self, name: str, fn: Callable) -> Callable:
        def timed(*args: Any, **kwargs: Any):
            t0 = self.now()
            try:
                return fn(*args, **kwargs)
            finally:
                self.step[name] += self.now() - t0

        return timed

    def end_step(self, total: float, cpp: dict[str, float] | None) -> None:
        s = dict(self.step)
        s["step"] = total
        for k, v in (cpp or {}).items():
            s[f"C++ {k}"] = v
        self.steps.append(s)
        self.step = defaultdict(float)


class TimedExtension:
    """The C++ module with its four entry points timed (the rest passes through)."""

    def __init__(self, ext: Any, clock: Clock) -> None:
        self._ext = ext
        for name in ("rasterize_forward", "rasterize_backward", "project_forward", "project_backward"):
            setattr(self, name, clock.wrap(f"_C.{name}", getattr(ext, name)))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ext, name)


def make_trainer(dataset: Path, images: str, ply: Path | None, out: Path, sh_degree: int, sky: bool = True):
    from promptgs_engine.config import TrainConfig
    from promptgs_engine.gaussians import load_ply
    from promptgs_engine.train import Trainer, make_optimizers

    cfg = TrainConfig(dataset=str(dataset), out=str(out), images=images, iterations=7000, sh_degree=sh_degree, backend="cpu",
                      sky=sky, checkpoint_every=0)
    trainer = Trainer(cfg, quiet=True)
    if ply is not None:
        trainer.params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.detach().float()) for k, v in load_ply(ply).items()})
        trainer.optimizers = make_optimizers(trainer.params, cfg, trainer.scene.extent)
        trainer.schedulers = [torch.optim.lr_scheduler.ExponentialLR(trainer.optimizers["means"], gamma=1.0)]
        trainer.strategy.check_sanity(trainer.params, trainer.optimizers)
        trainer.strategy_state = trainer.strategy.initialize_state(scene_scale=trainer.scene.extent)
    # Same work every step: no growth, pruning or opacity reset during the measurement.
    trainer.strategy.refine_every = 10**9
    trainer.strategy.reset_every = 10**9
    return trainer


def profile(trainer, start_step: int, steps: int, warmup: int, cpu_clock: bool = False) -> dict:
    import promptgs_engine.render.cpu as cpu_backend
    import promptgs_engine.train as train_module

    clock = Clock(cpu_clock)
    ext = cpu_backend._ext()
    has_stages = hasattr(ext, "stage_times")
    timed_ext = TimedExtension(ext, clock)
    cpu_backend._ext = lambda: timed_ext
    trainer.plan_step = clock.wrap("view plan + image", trainer.plan_step)
    if hasattr(train_module, "photometric_maps"):  # the loss as one node: SSIM and L1 forward
        train_module.photometric_maps = clock.wrap("loss forward (SSIM + L1)", train_module.photometric_maps)
    else:
        train_module.ssim_map = clock.wrap("SSIM forward", train_module.ssim_map)
    strat = trainer.strategy
    strat.step_pre_backward = clock.wrap("strategy pre-backward", strat.step_pre_backward)
    strat.step_post_backward = clock.wrap("strategy post-backward", strat.step_post_backward)
    if hasattr(train_module, "fused_adam_step"):  # Adam's step and zero_grad in one call
        train_module.fused_adam_step = clock.wrap("Adam", train_module.fused_adam_step)
    else:
        for opt in trainer.optimizers.values():
            opt.step = clock.wrap("Adam", opt.step)
            opt.zero_grad = clock.wrap("zero_grad", opt.zero_grad)
    trainer.check_finite = clock.wrap("finite check", trainer.check_finite)
    orig_backward = torch.Tensor.backward
    torch.Tensor.backward = clock.wrap("backward (all)", orig_backward)
    trainer.step = start_step
    try:
        for k in range(warmup + steps):
            if has_stages:
                ext.stage_times(True)
            t0 = clock.now()
            trainer.train_step(psnr=False)  # as the run loop's steps between its progress reports
            total = clock.now() - t0
            trainer.step += 1
            cpp = ext.stage_times(True, cpu_clock) if has_stages else None
            if k < warmup:
                clock.step = defaultdict(float)
            else:
                clock.end_step(total, cpp)
    finally:
        torch.Tensor.backward = orig_backward
    keys = sorted({k for s in clock.steps for k in s})
    med = {k: statistics.median(s.get(k, 0.0) for s in clock.steps) for k in keys}
    # Derived parts: what the wrapped calls leave of the backward and of the step.
    derived = {
        "autograd in torch (loss, activations, copies)": med["backward (all)"] - med.get("_C.rasterize_backward", 0)
        - med.get("_C.project_backward", 0),
    }
    named = ["view plan + image", "_C.project_forward", "_C.rasterize_forward", "SSIM forward",
             "loss forward (SSIM + L1)", "strategy pre-backward",
             "backward (all)", "Adam", "zero_grad", "strategy post-backward", "finite check"]
    derived["rest of the step (Python, L1, torch glue)"] = med["step"] - sum(med.get(k, 0.0) for k in named)
    return {"median_s": med, "derived_median_s": derived, "samples": clock.steps}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--images", default="images", help="images folder of the dataset (its size is the training size)")
    ap.add_argument("--ply", type=Path, help="trained Gaussians to start from (default: the SfM points, as a run starts)")
    ap.add_argument("--no-sky", action="store_true",
                    help="the SfM points alone, no far-background points (as benchmarks/opensplat_side_by_side.py)")
    ap.add_argument("--sh-degree", type=int, default=3)
    ap.add_argument("--start-step", type=int, default=1000, help="step number the measured steps start at (SH schedule)")
    ap.add_argument("--steps", type=int, default=15)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="cpu: this thread's CPU time (run with OMP_NUM_THREADS=1; robust on a busy machine)")
    ap.add_argument("--out", type=Path, default=Path("out/train_profile"))
    args = ap.parse_args(argv)
    if args.clock == "cpu" and torch.get_num_threads() != 1:
        raise SystemExit("--clock cpu measures one thread: set OMP_NUM_THREADS=1")

    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        trainer = make_trainer(args.dataset, args.images, args.ply, Path(tmp) / "run", args.sh_degree, sky=not args.no_sky)
        n = trainer.n_gaussians
        res = profile(trainer, args.start_step, args.steps, args.warmup, args.clock == "cpu")
        cam = trainer.scene.train_cameras[0]
    from promptgs_engine import _C

    res.update({
        "dataset": str(args.dataset), "images": args.images, "ply": str(args.ply) if args.ply else None,
        "size": f"{cam.width}x{cam.height}", "n_gaussians": n, "steps": args.steps,
        "sh_degree_active": trainer.active_sh_degree(args.start_step),
        "threads": torch.get_num_threads(), "clock": args.clock, "load_average": [load0, os.getloadavg()[0]],
        "cpu": cpu_model(), "kernels": _C.simd_variant(), "simd_cap": os.environ.get("PROMPTGS_SIMD"),
    })
    med, der = res["median_s"], res["derived_median_s"]
    print(f"{res['size']}, {n} Gaussians, SH degree {res['sh_degree_active']}, {res['threads']} threads, {args.clock} clock, "
          f"load {load0:.1f} -> {res['load_average'][1]:.1f}; medians of {args.steps} steps")
    print(f"{res['cpu'].get('model', '?')}, {res['kernels']} kernels (PROMPTGS_SIMD={res['simd_cap']})")
    for k in sorted(med, key=lambda k: -med[k]):
        print(f"  {k:45s} {med[k] * 1e3:8.2f} ms")
    for k, v in der.items():
        print(f"  {k:45s} {v * 1e3:8.2f} ms")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "train_profile.json"
    path.write_text(json.dumps(res, indent=2))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
