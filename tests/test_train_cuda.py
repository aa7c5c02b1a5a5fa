"""The trainer end to end on the CUDA backend (gsplat): each strategy trains, evaluates and
renders on the GPU, and what it trains renders the same on the CPU backend."""

from __future__ import annotations

import json

import pytest
import torch

from promptgs_engine.cli import main
from promptgs_engine.data import load_colmap_scene
from promptgs_engine.evaluation import evaluate
from promptgs_engine.run_folder import load_run

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"),
]

STEPS = "150"


def _train(toy, out, backend: str, strategy: str, extra: list[str]) -> dict:
    args = ["train", str(toy), "--out", str(out), "--iterations", STEPS, "--backend", backend,
            "--strategy", strategy, "--seed", "0", "--quiet", *extra]
    assert main(args) == 0
    return json.loads((out / "metrics.json").read_text())


@pytest.mark.parametrize(
    "strategy, extra",
    [("3dgs", []), ("absgs", []), ("promptgs", ["--prompts", "PROMPTS"]), ("promptgs", ["--auto-prompts", "2"])],
    ids=["3dgs", "absgs", "promptgs-box", "promptgs-auto"],
)
def test_a_cuda_run_trains_evaluates_and_renders_like_a_cpu_run(toy, tmp_path, strategy, extra):
    extra = [str(toy / "prompts_1.json") if a == "PROMPTS" else a for a in extra]
    gpu = _train(toy, tmp_path / "gpu", "cuda", strategy, extra)
    cpu = _train(toy, tmp_path / "cpu", "cpu", strategy, extra)
    assert gpu["backend"] == "cuda" and gpu["peak_gpu_mb"] > 0 and cpu["peak_gpu_mb"] is None
    # gsplat adds with atomics and the two rasterizers round differently, so the runs part
    # after the first refinement; they must still land in the same place. On this toy
    # scene at 150 steps one 3DGS seed's CPU run alone spans 21.58-22.26 dB with the
    # thread count and the processor (summation order), and the GPU's runs of seeds 0-3
    # 22.44-22.64 dB on an H100: 1.5 dB holds that spread,
    # while a run that learns at a third of the pace (50 steps: 19.4 dB) is 2.9 dB short.
    assert abs(gpu["psnr"] - cpu["psnr"]) < 1.5, (gpu["psnr"], cpu["psnr"])
    assert 0.8 < gpu["n_gaussians"] / cpu["n_gaussians"] < 1.25
    if "masked_psnr" in cpu:
        assert abs(gpu["masked_psnr"] - cpu["masked_psnr"]) < 2.0

    # The Gaussians the GPU trained render the same on the CPU backend.
    cfg, params = load_run(tmp_path / "gpu")
    scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
    on_cpu = evaluate(params, scene.test_cameras, cfg.downscale, backend="cpu", quiet=True,
                      screen_filter=cfg.effective_screen_filter, rasterize_mode=cfg.rasterize_mode)
    assert abs(on_cpu["psnr"] - gpu["psnr"]) < 0.05

    assert main(["render", str(tmp_path / "gpu"), "--all", "--out", str(tmp_path / "png"), "--quiet"]) == 0
    assert len(list((tmp_path / "png").glob("*.png"))) == len(scene.train_cameras) + len(scene.test_cameras)
