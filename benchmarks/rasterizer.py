"""Rasterizer benchmark: forward, forward+backward and a full training step on the CPU backend.

Measures, in one process, medians over repeated runs after warm-up:

- ``forward``: ``render()`` under ``torch.no_grad()``;
- ``forward_backward``: ``render()`` + L1 loss + ``backward()``;
- ``train_step``: the same plus an Adam step on every parameter (means, quaternions,
  log-scales, opacity logits, SH coefficients), as the trainer does;
- a breakdown of the step: projection + SH in torch, the C++ rasterizer forward and
  backward on their own;
- the pure-torch reference rasterizer against the C++ one on a scene small enough for the
  reference, for the speed ratio.

The default scene is random Gaussians in front of the camera, sized like a trained scene
(a few pixels at 800×600); ``--ply`` loads trained Gaussians in the standard 3DGS PLY
layout instead, with the camera from ``--dataset`` (first test view, else first train
view) or, without it, a camera looking at the Gaussians' centre.

Writes ``rasterizer.json`` and ``rasterizer.png`` into ``--out``.

    python benchmarks/rasterizer.py       # random Gaussians: 100k at 800x600 and 200x150, 10k at 200x150
    python benchmarks/rasterizer.py --ply run/point_cloud.ply --dataset ../shared/data/tumbler
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import torch

from promptgs_engine.render import render
from promptgs_engine.render.cpu import project_cpu
from promptgs_engine.render.projection import camera_centers, project_gaussians
from promptgs_engine.render.reference import render_reference
from promptgs_engine.render.sh import sh_to_color

TARGETS_S = {"800x600": 0.3, "200x150": 0.025}  # training step, issue 2 ("Show")


def load_average() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


def timed(fn: Callable[[], object], repeats: int, warmup: int) -> dict:
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return {"median_s": statistics.median(samples), "min_s": min(samples), "samples_s": samples}


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
        self.params = {k: v.detach().clone().requires_grad_(True) for k, v in scene.items()}
        # fused=True: torch's single-kernel CPU Adam, about 3x faster than the default here
        self.opt = torch.optim.Adam(
            [{"params": [p], "lr": lr} for p, lr in zip(self.params.values(), (1.6e-4, 1e-3, 5e-3, 5e-2, 2.5e-3, 1.25e-4))],
            fused=True,
        )
        self.viewmats, self.Ks = view[None], K[None]
        self.width, self.height, self.sh_degree = width, height, sh_degree
        g = torch.Generator().manual_seed(1)
        self.target = torch.rand(1, height, width, 3, generator=g)

    def render(self):
        p = self.params
        colors = torch.cat([p["sh0"], p["shN"]], dim=1)
        return render(
            p["means"], p["quats"], torch.exp(p["log_scales"]), torch.sigmoid(p["opacity_logits"]), colors,
            self.viewmats, self.Ks, self.width, self.height, sh_degree=self.sh_degree, backend="cpu",
        )

    def forward(self) -> None:
        with torch.no_grad():
            self.render()

    def forward_backward(self) -> None:
        out, _, _ = self.render()
        (out - self.target).abs().mean().backward()
        for p in self.params.values():
            p.grad = None

    def train_step(self) -> None:
        self.opt.zero_grad(set_to_none=True)
        out, _, info = self.render()
        info["means2d"].retain_grad()  # as the densification strategy does
        (out - self.target).abs().mean().backward()
        self.opt.step()

    def breakdown(self, repeats: int, warmup: int) -> dict:
        """Projection + SH (torch, forward and backward) and the C++ passes on their own."""
        from promptgs_engine import _C

        p = {k: v.detach().clone().requires_grad_(True) for k, v in self.params.items()}

        def proj_sh():
            scales, opac = torch.exp(p["log_scales"]), torch.sigmoid(p["opacity_logits"])
            m2, conics, depths, radii = project_gaussians(
                p["means"], p["quats"], scales, opac, self.viewmats, self.Ks, self.width, self.height
            )
            colors = sh_to_color(self.sh_degree, p["means"], torch.cat([p["sh0"], p["shN"]], 1), camera_centers(self.viewmats))
            return m2, conics, depths, radii, colors, opac

        def proj_sh_fb():
            m2, conics, depths, _, colors, opac = proj_sh()
            (m2.sum() + conics.sum() + depths.sum() + colors.sum() + opac.sum()).backward()

        def proj_sh_cpp_fb():
            scales, opac = torch.exp(p["log_scales"]), torch.sigmoid(p["opacity_logits"])
            m2, conics, depths, _, colors = project_cpu(
                p["means"], p["quats"], scales, opac, self.viewmats, self.Ks, self.width, self.height, 0.01, 1e10,
                sh=torch.cat([p["sh0"], p["shN"]], 1), sh_degree=self.sh_degree,
            )
            (m2.sum() + conics.sum() + depths.sum() + colors.sum() + opac.sum()).backward()

        def adam_only():
            self.opt.step()

        self.train_step()  # leaves gradients in place for the optimiser-only timing

        with torch.no_grad():
            m2, conics, depths, radii, colors, opac = proj_sh()
        args = [t[0].contiguous() if t.dim() > 1 and t.shape[0] == 1 else t.contiguous() for t in (m2, conics, colors)]
        m2c, cnc, colc = args
        opc, dc, rc = opac.contiguous(), depths[0].contiguous(), radii[0].contiguous()
        bg = torch.empty(0)
        fwd_out = _C.rasterize_forward(m2c, cnc, colc, opc, dc, rc, bg, self.width, self.height)
        gimg = torch.randn(self.height, self.width, 3)
        galpha = torch.zeros(self.height, self.width, 1)

        def bwd():
            _C.rasterize_backward(m2c, cnc, colc, opc, rc, bg, self.width, self.height, *fwd_out[3:7],
                                  fwd_out[1], fwd_out[2], gimg, galpha, False)

        return {
            "projection_sh_cpp_forward_backward": timed(proj_sh_cpp_fb, repeats, warmup),
            "projection_sh_torch_forward_backward": timed(proj_sh_fb, repeats, warmup),
            "adam_step": timed(adam_only, repeats, warmup),
            "rasterize_forward": timed(lambda: _C.rasterize_forward(m2c, cnc, colc, opc, dc, rc, bg, self.width, self.height), repeats, warmup),
            "rasterize_backward": timed(bwd, repeats, warmup),
            "visible_gaussians": int((radii > 0).all(-1).sum()),
            "tile_intersections": int(fwd_out[4].numel()),
        }


def reference_ratio(n: int, width: int, height: int, repeats: int, warmup: int, sh_degree: int) -> dict:
    """forward+backward of the C++ backend and of the torch reference on the same small scene."""
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

    cpu = timed(fb(render), repeats, warmup)
    ref = timed(fb(render_reference), repeats, warmup)
    return {"n_gaussians": n, "size": f"{width}x{height}", "cpu": cpu, "reference": ref,
            "reference_over_cpu": ref["median_s"] / cpu["median_s"]}


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(results["configs"])
    kinds = ["forward", "forward_backward", "train_step"]
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.25
    for j, kind in enumerate(kinds):
        vals = [results["configs"][k][kind]["median_s"] * 1000 for k in keys]
        label = {"forward": "forward", "forward_backward": "forward + backward", "train_step": "training step"}[kind]
        bars = ax.bar([i + (j - 1) * width for i in range(len(keys))], vals, width, label=label)
        ax.bar_label(bars, fmt="%.0f", fontsize=7)
    for i, k in enumerate(keys):
        size = results["configs"][k]["size"]
        if size in TARGETS_S:
            ax.hlines(TARGETS_S[size] * 1000, i - 1.5 * width, i + 1.5 * width, colors="k", linestyles="--")
    ax.set_xticks(range(len(keys)), [f"{results['configs'][k]['size']}\n{results['configs'][k]['n_gaussians']} Gaussians" for k in keys])
    ax.set_ylabel("median time (ms)")
    m = results["machine"]
    ax.set_title(f"PromptGS CPU backend ({m['threads']} threads, {m['simd']}, load {m['load_average_start']:.1f}); dashed: step target", fontsize=10)
    ax.legend(fontsize=8)
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
    ap.add_argument("--sh-degree", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--reference-n", type=int, default=300)
    ap.add_argument("--reference-size", default="64x48")
    ap.add_argument("--out", type=Path, default=Path("out/bench"))
    args = ap.parse_args(argv)

    from promptgs_engine import _C

    configs = []
    for item in args.configs.split(","):
        size, _, count = item.partition(":")
        configs.append((size, int(count) if count else 100_000))
    if args.ply:
        full = load_ply(args.ply, args.sh_degree)
    else:
        full = synthetic_scene(max(c for _, c in configs), args.sh_degree)
    n_full = full["means"].shape[0]
    machine = {
        "platform": platform.platform(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "threads": _C.num_threads(),
        "simd": _C.simd_variant() if hasattr(_C, "simd_variant") else "?",
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "load_average_start": load_average(),
    }
    results: dict = {"machine": machine, "scene": str(args.ply) if args.ply else "random", "configs": {}}
    print(f"scene: {results['scene']}, SH degree {args.sh_degree}; "
          f"{machine['threads']} threads ({machine['simd']}); load {machine['load_average_start']:.2f}")

    for size, count in configs:
        w, h = (int(v) for v in size.split("x"))
        n = n_full if args.ply else min(count, n_full)
        scene = {k: v[:n] for k, v in full.items()}
        key = f"{size}:{n}"
        if args.ply:
            view, K = dataset_camera(args.dataset, w, h) if args.dataset else look_at_camera(scene["means"], w, h)
        else:
            view, K = canonical_camera(w, h)
        step = Step(scene, view, K, w, h, args.sh_degree)
        load0 = load_average()
        r = {
            "n_gaussians": n,
            "forward": timed(step.forward, args.repeats, args.warmup),
            "forward_backward": timed(step.forward_backward, args.repeats, args.warmup),
            "train_step": timed(step.train_step, args.repeats, args.warmup),
        }
        r["breakdown"] = step.breakdown(args.repeats, args.warmup)
        r["load_average"] = [load0, load_average()]
        r["size"] = size
        results["configs"][key] = r
        b = r["breakdown"]
        ms = lambda d: d["median_s"] * 1e3  # noqa: E731
        target = TARGETS_S.get(size)
        print(
            f"{size}, {n} Gaussians: forward {ms(r['forward']):.1f} ms | forward+backward {ms(r['forward_backward']):.1f} ms"
            f" | train step {ms(r['train_step']):.1f} ms" + (f" (target {target * 1e3:.0f} ms)" if target else "")
            + f"\n    parts: rasterize fwd {ms(b['rasterize_forward']):.1f} ms, bwd {ms(b['rasterize_backward']):.1f} ms;"
            f" projection+SH fwd+bwd C++ {ms(b['projection_sh_cpp_forward_backward']):.1f} ms"
            f" (torch {ms(b['projection_sh_torch_forward_backward']):.1f} ms); Adam {ms(b['adam_step']):.1f} ms;"
            f" {b['visible_gaussians']} visible, {b['tile_intersections']} tile intersections;"
            f" load {r['load_average'][0]:.2f} -> {r['load_average'][1]:.2f}"
        )

    rw, rh = (int(v) for v in args.reference_size.split("x"))
    ref = reference_ratio(args.reference_n, rw, rh, max(3, args.repeats // 2), 1, args.sh_degree)
    results["reference"] = ref
    print(
        f"reference ({ref['n_gaussians']} Gaussians, {ref['size']}, forward+backward): torch "
        f"{ref['reference']['median_s'] * 1e3:.1f} ms vs C++ {ref['cpu']['median_s'] * 1e3:.2f} ms "
        f"= {ref['reference_over_cpu']:.0f}x"
    )
    machine["load_average_end"] = load_average()

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "rasterizer.json").write_text(json.dumps(results, indent=2))
    plot(results, args.out / "rasterizer.png")
    print(f"wrote {args.out / 'rasterizer.json'} and {args.out / 'rasterizer.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
