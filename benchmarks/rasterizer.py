"""Rasterizer benchmark: forward, forward+backward and a full training step on the CPU backend,
for this checkout and, side by side, a baseline build of the project.

Measures medians over repeated runs after warm-up:

- ``forward``: ``render()`` under ``torch.no_grad()``;
- ``forward_backward``: ``render()`` + L1 loss + ``backward()``;
- ``train_step``: the same plus an Adam step on every parameter (means, quaternions,
  log-scales, opacity logits, SH coefficients), as the trainer does: where the build's
  trainer has them, the SH coefficients go to ``render`` apart (``sh_rest``) and Adam is
  its fused step on six one-parameter optimisers (``promptgs_engine/adam.py``);
- the parts of a training step: the C++ entry points (projection and rasterization, forward
  and backward) timed from Python, and, for builds that record them, the C++ stages
  (``_C.stage_times()``: sort, gather, binning, blending, gradient reduction);
- the pure-torch reference rasterizer against the C++ one on a scene small enough for the
  reference, for the speed ratio (this checkout only).

Each build runs in its own worker process (``PYTHONPATH`` set to its checkout), both hold
the same scene, and the repetitions alternate between them (A B B A ...), so a machine
shared with other jobs slows both alike; the JSON holds every sample, the medians, the
ratio baseline / this and the load average. Give ``--baseline`` a checkout of the old
commit with its extension built, e.g.::

    git worktree add ../base main && (cd ../base && python setup.py build_ext --inplace)

The default scene is random Gaussians in front of the camera, sized like a trained scene
(a few pixels at 800×600); ``--ply`` loads trained Gaussians in the standard 3DGS PLY
layout instead, with the camera from ``--dataset`` (first test view, else first train
view) or, without it, a camera looking at the Gaussians' centre.

Writes ``rasterizer.json`` and ``rasterizer.png`` into ``--out``.

    python benchmarks/rasterizer.py       # random Gaussians: 100k at 800x600 and 200x150, 10k at 200x150
    python benchmarks/rasterizer.py --ply run/point_cloud.ply --dataset ../shared/data/tumbler --baseline ../base
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import torch

REPO = Path(__file__).resolve().parents[1]
TARGETS_S = {"800x600": 0.1, "200x150": 0.025}  # training step (issue 21: 0.1 s at 800x600)
FORWARD_TARGET_S = {"800x600": 0.03}


def load_average() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


def timed(fn: Callable[[], object], repeats: int, warmup: int) -> list[list[float]]:
    """[wall seconds, CPU seconds of the process] per run: on a machine busy with other jobs
    the CPU time (all threads) still measures the work, where the wall time mostly measures
    the wait for a core."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        samples.append([time.perf_counter() - t0, time.process_time() - c0])
    return samples


def summary(samples: list[list[float]]) -> dict:
    wall = [s[0] for s in samples]
    cpu = [s[1] for s in samples]
    return {"median_s": statistics.median(wall), "min_s": min(wall), "samples_s": wall,
            "cpu_median_s": statistics.median(cpu), "cpu_samples_s": cpu}


# -- scenes (used by the workers; only the engine's public API, so any build can run them) --


def synthetic_scene(n: int, sh_degree: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random Gaussians filling the view of the canonical camera (800×600, fx = 700) at
    depths 2–6, with log-normal scales that project to a few pixels, like a trained scene."""
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g) * 4 + 2
    x = (torch.rand(n, generator=g) - 0.5) * (800 / 700) * z * 1.1
    y = (torch.rand(n, generator=g) - 0.5) * (600 / 700) * z * 1.1
    K = (sh_degree + 1) ** 2
    return {
        "means": torch.stack([x, y, z], dim=-1),
        "quats": torch.randn(n, 4, generator=g),
        "log_scales": torch.randn(n, 3, generator=g) * 0.5 + math.log(0.008),
        "opacity_logits": torch.randn(n, generator=g) * 1.5,
        "sh0": torch.rand(n, 1, 3, generator=g) - 0.5,
        "shN": torch.randn(n, K - 1, 3, generator=g) * 0.05,
    }


def canonical_camera(width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    f = 700.0 * width / 800.0
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return torch.eye(4), K


def load_ply(path: Path, sh_degree: int) -> dict[str, torch.Tensor]:
    """Gaussians from a standard 3DGS PLY, with their SH cut or zero-padded to ``sh_degree``."""
    from promptgs_engine.gaussians import load_ply as read_ply

    p = {k: v.detach() for k, v in read_ply(path).items()}
    n = p["means"].shape[0]
    shN = torch.zeros(n, (sh_degree + 1) ** 2 - 1, 3)
    m = min(shN.shape[1], p["shN"].shape[1])
    shN[:, :m] = p["shN"][:, :m]
    return {
        "means": p["means"],
        "quats": p["quats"],
        "log_scales": p["scales"],
        "opacity_logits": p["opacities"],
        "sh0": p["sh0"],
        "shN": shN,
    }


def dataset_camera(dataset: Path, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    from promptgs_engine.data import load_colmap_scene

    scene = load_colmap_scene(dataset)
    cam = (scene.test_cameras or scene.train_cameras)[0]
    K = cam.K.clone().float()
    K[0] *= width / cam.width
    K[1] *= height / cam.height
    return cam.world_to_camera.float(), K


def look_at_camera(means: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A camera on the -z side of the Gaussians' centre looking along +z, covering most of them."""
    centre = means.median(dim=0).values
    spread = (means - centre).abs().quantile(0.9, dim=0)
    dist = float(2.5 * spread[:2].max() + spread[2])
    view = torch.eye(4)
    view[:3, 3] = -(centre - torch.tensor([0.0, 0.0, dist]))
    f = 0.9 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return view, K


class Step:
    """Parameters, optimiser and the render/loss/backward/step closures of one configuration."""

    def __init__(self, scene: dict, view: torch.Tensor, K: torch.Tensor, width: int, height: int, sh_degree: int):
        import inspect

        from promptgs_engine.render import render

        self.params = {k: v.detach().clone().requires_grad_(True) for k, v in scene.items()}
        # One fused Adam per parameter, as the trainer makes them (train.make_optimizers).
        self.optimizers = {
            k: torch.optim.Adam([{"params": [p], "lr": lr}], fused=True)
            for (k, p), lr in zip(self.params.items(), (1.6e-4, 1e-3, 5e-3, 5e-2, 2.5e-3, 1.25e-4))
        }
        # What the build's trainer does where it can: the SH coefficients passed apart
        # (``sh_rest``) rather than concatenated every step, and its own Adam step
        # (promptgs_engine/adam.py). An older build gets the concatenation and
        # ``Optimizer.step``, as its trainer did.
        self.sh_apart = "sh_rest" in inspect.signature(render).parameters
        try:
            from promptgs_engine.adam import fused_adam_step
        except ImportError:
            fused_adam_step = None
        self.fused_adam_step = fused_adam_step
        self.viewmats, self.Ks = view[None], K[None]
        self.width, self.height, self.sh_degree = width, height, sh_degree
        g = torch.Generator().manual_seed(1)
        self.target = torch.rand(1, height, width, 3, generator=g)

    def render(self):
        from promptgs_engine.render import render

        p = self.params
        if self.sh_apart:
            colors, extra = p["sh0"], {"sh_rest": p["shN"]}
        else:
            colors, extra = torch.cat([p["sh0"], p["shN"]], dim=1), {}
        return render(
            p["means"], p["quats"], torch.exp(p["log_scales"]), torch.sigmoid(p["opacity_logits"]), colors,
            self.viewmats, self.Ks, self.width, self.height, sh_degree=self.sh_degree, backend="cpu", **extra,
        )

    def adam_step(self) -> None:
        if self.fused_adam_step is not None:
            self.fused_adam_step(self.optimizers)  # also sets the gradients to None
            return
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)

    def forward(self) -> None:
        with torch.no_grad():
            self.render()

    def forward_backward(self) -> None:
        out, _, _ = self.render()
        (out - self.target).abs().mean().backward()
        for p in self.params.values():
            p.grad = None

    def train_step(self) -> None:
        out, _, info = self.render()
        info["means2d"].retain_grad()  # as the densification strategy does
        (out - self.target).abs().mean().backward()
        self.adam_step()

    def parts(self) -> dict[str, float]:
        """One training step with the C++ entry points timed, plus the C++ stages where the
        build records them; seconds by name."""
        import promptgs_engine.render.cpu as cpu_backend

        ext = cpu_backend._ext()
        times: dict[str, float] = {}

        def wrap(name: str) -> Callable:
            fn = getattr(ext, name)

            def run(*a: Any) -> Any:
                t0 = time.perf_counter()
                out = fn(*a)
                times[f"_C.{name}"] = times.get(f"_C.{name}", 0.0) + time.perf_counter() - t0
                return out

            return run

        class Timed:
            def __getattr__(self, name: str) -> Any:
                return getattr(ext, name)

        timed_ext = Timed()
        for name in ("rasterize_forward", "rasterize_backward", "project_forward", "project_backward"):
            setattr(timed_ext, name, wrap(name))
        if hasattr(ext, "stage_times"):
            ext.stage_times(True)
        original = cpu_backend._ext
        cpu_backend._ext = lambda: timed_ext
        try:
            t0 = time.perf_counter()
            self.train_step()
            times["train_step"] = time.perf_counter() - t0
        finally:
            cpu_backend._ext = original
        # Adam alone, on gradients of the same shapes (train_step's own were used up).
        for p in self.params.values():
            p.grad = torch.zeros_like(p)
        t0 = time.perf_counter()
        self.adam_step()
        times["adam"] = time.perf_counter() - t0
        if hasattr(ext, "stage_times"):
            times.update({f"C++ {k}": v for k, v in ext.stage_times(True).items()})
        return times

    def counts(self) -> dict[str, int]:
        with torch.no_grad():
            _, _, info = self.render()
        from promptgs_engine.render.cpu import _ext

        ext = _ext()
        p = self.params
        m2, cn, dep, radii = info["means2d"][0], info["conics"][0], info["depths"][0], info["radii"][0]
        out = ext.rasterize_forward(
            m2.contiguous(), cn.contiguous(), torch.zeros(m2.shape[0], 3), torch.sigmoid(p["opacity_logits"]).detach(),
            dep.contiguous(), radii.contiguous(), torch.empty(0), self.width, self.height,
        )
        return {"visible_gaussians": int((radii > 0).all(-1).sum()), "tile_intersections": int(out[4].numel())}


def reference_ratio(n: int, width: int, height: int, repeats: int, warmup: int, sh_degree: int) -> dict:
    """forward+backward of the C++ backend and of the torch reference on the same small scene."""
    from promptgs_engine.render import render
    from promptgs_engine.render.reference import render_reference

    scene = synthetic_scene(n, sh_degree, seed=3)
    view, K = canonical_camera(width, height)

    def fb(fn):
        def run():
            p = {k: v.detach().clone().requires_grad_(True) for k, v in scene.items()}
            out, _, _ = fn(
                p["means"], p["quats"], torch.exp(p["log_scales"]), torch.sigmoid(p["opacity_logits"]),
                torch.cat([p["sh0"], p["shN"]], 1), view[None], K[None], width, height, sh_degree=sh_degree,
            )
            out.sum().backward()
        return run

    cpu = summary(timed(fb(render), repeats, warmup))
    ref = summary(timed(fb(render_reference), repeats, warmup))
    return {"n_gaussians": n, "size": f"{width}x{height}", "cpu": cpu, "reference": ref,
            "reference_over_cpu": ref["median_s"] / cpu["median_s"]}


# -- worker process: one build, commands as JSON lines on stdin, answers on stdout ----------


def worker(args: argparse.Namespace) -> int:
    from promptgs_engine import _C

    out = sys.stdout
    sys.stdout = sys.stderr  # nothing but answers on the pipe
    full = load_ply(args.ply, args.sh_degree) if args.ply else None
    steps: dict[str, Step] = {}
    for line in sys.stdin:
        cmd = json.loads(line)
        op = cmd["op"]
        if op == "info":
            import promptgs_engine

            reply: Any = {
                "package": str(Path(promptgs_engine.__file__).parent), "threads": _C.num_threads(),
                "simd": _C.simd_variant() if hasattr(_C, "simd_variant") else "?",
                "stage_times": hasattr(_C, "stage_times"), "torch_threads": torch.get_num_threads(),
            }
        elif op == "setup":
            w, h = (int(v) for v in cmd["size"].split("x"))
            scene = full if full is not None else synthetic_scene(cmd["n"], args.sh_degree)
            if args.ply:
                view, K = dataset_camera(args.dataset, w, h) if args.dataset else look_at_camera(scene["means"], w, h)
            else:
                view, K = canonical_camera(w, h)
            steps[cmd["key"]] = Step(scene, view, K, w, h, args.sh_degree)
            reply = {"n_gaussians": int(scene["means"].shape[0]), **steps[cmd["key"]].counts()}
        elif op == "time":
            step = steps[cmd["key"]]
            if cmd["kind"] == "parts":
                for _ in range(cmd["warmup"]):
                    step.parts()
                reply = [step.parts() for _ in range(cmd["repeats"])]
            else:
                reply = timed(getattr(step, cmd["kind"]), cmd["repeats"], cmd["warmup"])
        elif op == "reference":
            reply = reference_ratio(cmd["n"], cmd["width"], cmd["height"], cmd["repeats"], 1, args.sh_degree)
        elif op == "quit":
            break
        else:
            raise ValueError(f"unknown op {op!r}")
        out.write(json.dumps(reply) + "\n")
        out.flush()
    return 0


class Worker:
    """A worker process running one build."""

    def __init__(self, name: str, root: Path, args: argparse.Namespace):
        self.name, self.root = name, root
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--sh-degree", str(args.sh_degree)]
        if args.ply:
            cmd += ["--ply", str(args.ply.resolve())]
        if args.dataset:
            cmd += ["--dataset", str(args.dataset.resolve())]
        env = dict(os.environ, PYTHONPATH=str(root))
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=root)

    def ask(self, **cmd: Any) -> Any:
        assert self.proc.stdin and self.proc.stdout
        self.proc.stdin.write(json.dumps(cmd) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"worker {self.name} ({self.root}) stopped; see its messages above")
        return json.loads(line)

    def close(self) -> None:
        try:
            self.ask(op="quit") if self.proc.poll() is None else None
        except (RuntimeError, BrokenPipeError, json.JSONDecodeError):
            pass
        self.proc.wait(timeout=60)


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(results["configs"])
    builds = list(results["builds"])
    kinds = ["forward", "forward_backward", "train_step"]
    labels = {"forward": "forward", "forward_backward": "forward + backward", "train_step": "training step"}
    colors = {"forward": "tab:blue", "forward_backward": "tab:orange", "train_step": "tab:green"}
    fig, ax = plt.subplots(figsize=(max(8, 3.2 * len(keys)), 4.5))
    nb = len(kinds) * len(builds)
    width = 0.8 / nb
    for i, key in enumerate(keys):
        cfg = results["configs"][key]
        for j, kind in enumerate(kinds):
            for b, build in enumerate(builds):
                x = i - 0.4 + width * (j * len(builds) + b + 0.5)
                v = cfg[build][kind]["median_s"] * 1000
                bar = ax.bar(x, v, width, color=colors[kind], alpha=1.0 if build == "this" else 0.45,
                             hatch=None if build == "this" else "//", edgecolor="k", linewidth=0.3,
                             label=f"{labels[kind]} ({build})" if i == 0 else None)
                ax.bar_label(bar, fmt="%.0f", fontsize=6)
        size = cfg["size"]
        if size in TARGETS_S:
            ax.hlines(TARGETS_S[size] * 1000, i - 0.45, i + 0.45, colors="k", linestyles="--", linewidth=1)
        if size in FORWARD_TARGET_S:
            ax.hlines(FORWARD_TARGET_S[size] * 1000, i - 0.45, i + 0.45, colors="tab:blue", linestyles=":", linewidth=1)
    ticks = []
    for key in keys:
        cfg = results["configs"][key]
        t = f"{cfg['size']}, {cfg['n_gaussians']:,} Gaussians"
        if "baseline" in cfg:
            t += (f"\nstep {cfg['ratio_baseline_over_this']['train_step']:.2f}x faster (wall), "
                  f"{cfg['cpu_ratio_baseline_over_this']['train_step']:.2f}x (CPU time)")
        ticks.append(t)
    ax.set_xticks(range(len(keys)), ticks, fontsize=8)
    ax.set_ylabel("median time (ms)")
    m = results["machine"]
    ax.set_title(
        f"PromptGS CPU backend: this build vs baseline ({m['threads']} threads, {m['simd']}, load "
        f"{m['load_average_start']:.1f}-{m['load_average_end']:.1f}); dashed: step target, dotted: forward target",
        fontsize=9,
    )
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--configs", default="800x600:100000,200x150:100000,200x150:10000",
        help="comma-separated WIDTHxHEIGHT:N (random Gaussians; N is ignored with --ply)",
    )
    ap.add_argument("--ply", type=Path, help="trained Gaussians (standard 3DGS PLY)")
    ap.add_argument("--dataset", type=Path, help="COLMAP dataset whose first test camera views the --ply scene")
    ap.add_argument("--baseline", type=Path, help="checkout of another build (extension built) to run side by side")
    ap.add_argument("--sh-degree", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--reference-n", type=int, default=300)
    ap.add_argument("--reference-size", default="64x48")
    ap.add_argument("--out", type=Path, default=Path("out/bench"))
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args)

    builds = {"this": REPO}
    if args.baseline:
        if not (args.baseline / "promptgs_engine").is_dir():
            raise SystemExit(f"--baseline {args.baseline}: no promptgs_engine package there")
        builds["baseline"] = args.baseline.resolve()
    workers = {name: Worker(name, root, args) for name, root in builds.items()}
    try:
        infos = {name: w.ask(op="info") for name, w in workers.items()}
        machine = {
            "platform": platform.platform(), "processor": platform.processor(), "cpu_count": os.cpu_count(),
            "threads": infos["this"]["threads"], "simd": infos["this"]["simd"], "torch": torch.__version__,
            "torch_threads": infos["this"]["torch_threads"], "load_average_start": load_average(),
        }
        results: dict = {"machine": machine, "scene": str(args.ply) if args.ply else "random",
                         "builds": {name: {"root": str(root), **infos[name]} for name, root in builds.items()},
                         "configs": {}}
        print(f"scene: {results['scene']}, SH degree {args.sh_degree}; {machine['threads']} threads "
              f"({machine['simd']}); builds: " + ", ".join(f"{n} = {r}" for n, r in builds.items())
              + f"; load {machine['load_average_start']:.2f}")
        kinds = ["forward", "forward_backward", "train_step"]
        for item in args.configs.split(","):
            size, _, count = item.partition(":")
            key = f"{size}:{count or 100000}"
            setups = {name: w.ask(op="setup", key=key, size=size, n=int(count or 100_000)) for name, w in workers.items()}
            r: dict = {"size": size, **setups["this"], "load_average": [load_average()]}
            samples = {name: {k: [] for k in kinds} for name in workers}
            parts = {name: [] for name in workers}
            for name, w in workers.items():  # warm-up
                for kind in kinds:
                    w.ask(op="time", key=key, kind=kind, repeats=0, warmup=args.warmup)
            for rep in range(args.repeats):  # alternate: A B, B A, A B, ...
                order = list(workers) if rep % 2 == 0 else list(workers)[::-1]
                for name in order:
                    for kind in kinds:
                        samples[name][kind] += workers[name].ask(op="time", key=key, kind=kind, repeats=1, warmup=0)
                    parts[name] += workers[name].ask(op="time", key=key, kind="parts", repeats=1, warmup=0)
            for name in workers:
                r[name] = {k: summary(v) for k, v in samples[name].items()}
                names = sorted({k for p in parts[name] for k in p})
                r[name]["parts_median_s"] = {k: statistics.median(p.get(k, 0.0) for p in parts[name]) for k in names}
            if "baseline" in workers:
                r["ratio_baseline_over_this"] = {k: r["baseline"][k]["median_s"] / r["this"][k]["median_s"] for k in kinds}
                r["cpu_ratio_baseline_over_this"] = {
                    k: r["baseline"][k]["cpu_median_s"] / r["this"][k]["cpu_median_s"] for k in kinds
                }
            r["load_average"].append(load_average())
            results["configs"][key] = r
            ms = lambda d: d["median_s"] * 1e3  # noqa: E731
            for name in workers:
                t = r[name]
                pm = t["parts_median_s"]
                cms = lambda d: d["cpu_median_s"] * 1e3  # noqa: E731
                print(f"{size}, {r['n_gaussians']} Gaussians [{name}]: forward {ms(t['forward']):.1f} ms | "
                      f"forward+backward {ms(t['forward_backward']):.1f} ms | train step {ms(t['train_step']):.1f} ms"
                      + (f" (target {TARGETS_S[size] * 1e3:.0f} ms)" if size in TARGETS_S else "")
                      + f"; CPU time: forward {cms(t['forward']):.1f}, step {cms(t['train_step']):.1f} ms")
                print("    parts: " + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in pm.items() if k != "train_step") + " ms")
            if "ratio_baseline_over_this" in r:
                rt, rc = r["ratio_baseline_over_this"], r["cpu_ratio_baseline_over_this"]
                print("    baseline / this, wall: " + ", ".join(f"{k} {v:.2f}x" for k, v in rt.items())
                      + "; CPU time: " + ", ".join(f"{k} {v:.2f}x" for k, v in rc.items()))
            print(f"    {r['visible_gaussians']} visible, {r['tile_intersections']} tile intersections; "
                  f"load {r['load_average'][0]:.2f} -> {r['load_average'][1]:.2f}")

        rw, rh = (int(v) for v in args.reference_size.split("x"))
        ref = workers["this"].ask(op="reference", n=args.reference_n, width=rw, height=rh, repeats=max(3, args.repeats // 2))
        results["reference"] = ref
        print(
            f"reference ({ref['n_gaussians']} Gaussians, {ref['size']}, forward+backward): torch "
            f"{ref['reference']['median_s'] * 1e3:.1f} ms vs C++ {ref['cpu']['median_s'] * 1e3:.2f} ms "
            f"= {ref['reference_over_cpu']:.0f}x"
        )
    finally:
        for w in workers.values():
            w.close()
    machine["load_average_end"] = load_average()

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "rasterizer.json").write_text(json.dumps(results, indent=2))
    plot(results, args.out / "rasterizer.png")
    print(f"wrote {args.out / 'rasterizer.json'} and {args.out / 'rasterizer.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
