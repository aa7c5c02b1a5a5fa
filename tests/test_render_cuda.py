"""gsplat (CUDA) backend against the C++ CPU backend: same images, gradients and info."""

from __future__ import annotations

import pytest
import torch

from promptgs_engine.render import render

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"),
]

W, H = 96, 64


def scene(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.7 + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.15 + 0.02
    opac = torch.rand(n, generator=g) * 0.9 + 0.05
    sh = torch.randn(n, 16, 3, generator=g) * 0.3
    feats = torch.rand(n, 5, generator=g)
    Ks = torch.tensor([[[80.0, 0.0, W / 2], [0.0, 80.0, H / 2], [0.0, 0.0, 1.0]]]).repeat(2, 1, 1)
    viewmats = torch.eye(4)[None].repeat(2, 1, 1)
    viewmats[1, :3, 3] = torch.tensor([0.2, -0.1, 0.3])
    bg = torch.rand(2, 3, generator=g)
    return (means, quats, scales, opac), sh, feats, viewmats, Ks, bg


def _run(device, params, colors, viewmats, Ks, **kw):
    ps = [t.detach().clone().to(device).requires_grad_() for t in (*params, colors)]
    out, alpha, info = render(*ps, viewmats.to(device), Ks.to(device), W, H, backend="auto", **kw)
    info["means2d"].retain_grad()
    g = torch.Generator().manual_seed(0)
    w = torch.randn(out.shape, generator=g).to(device)
    ((out * w).sum() + alpha.sum()).backward()
    return out.detach().cpu(), alpha.detach().cpu(), [p.grad.cpu() for p in ps], info


@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_cuda_matches_cpu_sh(mode):
    params, sh, _, viewmats, Ks, bg = scene(300, 0)
    cpu = _run("cpu", params, sh, viewmats, Ks, sh_degree=3, render_mode=mode,
               backgrounds=bg)
    gpu = _run("cuda", params, sh, viewmats, Ks, sh_degree=3, render_mode=mode,
               backgrounds=bg.cuda())
    assert gpu[3]["backend"] == "cuda" and cpu[3]["backend"] == "cpu"
    torch.testing.assert_close(gpu[0], cpu[0], atol=2e-3, rtol=1e-3)
    torch.testing.assert_close(gpu[1], cpu[1], atol=1e-3, rtol=1e-3)
    for a, b in zip(gpu[2], cpu[2]):
        assert (a - b).abs().max() <= 1e-2 * b.abs().max() + 1e-4
    torch.testing.assert_close(gpu[3]["radii"].cpu(), cpu[3]["radii"], atol=1, rtol=0)
    torch.testing.assert_close(gpu[3]["means2d"].grad.cpu(), cpu[3]["means2d"].grad, atol=1e-3, rtol=1e-2)


def test_cuda_matches_cpu_features_absgrad():
    params, _, feats, viewmats, Ks, _ = scene(200, 1)
    cpu = _run("cpu", params, feats, viewmats, Ks, absgrad=True)
    gpu = _run("cuda", params, feats, viewmats, Ks, absgrad=True)
    torch.testing.assert_close(gpu[0], cpu[0], atol=2e-3, rtol=1e-3)
    torch.testing.assert_close(
        gpu[3]["means2d"].absgrad.cpu(), cpu[3]["means2d"].absgrad, atol=1e-3, rtol=1e-2
    )


def test_cuda_matches_cpu_with_a_narrow_screen_filter():
    params, sh, _, viewmats, Ks, bg = scene(300, 2)
    cpu = _run("cpu", params, sh, viewmats, Ks, sh_degree=3, backgrounds=bg, eps2d=0.1)
    gpu = _run("cuda", params, sh, viewmats, Ks, sh_degree=3, backgrounds=bg.cuda(), eps2d=0.1)
    torch.testing.assert_close(gpu[0], cpu[0], atol=2e-3, rtol=1e-3)
    for a, b in zip(gpu[2], cpu[2]):
        assert (a - b).abs().max() <= 1e-2 * b.abs().max() + 1e-4
    wide = _run("cpu", params, sh, viewmats, Ks, sh_degree=3, backgrounds=bg)
    assert (wide[0] - cpu[0]).abs().max() > 1e-2  # the filter is used


def test_cuda_matches_cpu_antialiased():
    """gsplat's rasterize_mode="antialiased" and our compensation (filter_compensation)
    scale opacities the same way: images and gradients agree."""
    params, sh, _, viewmats, Ks, bg = scene(300, 3)
    kw = dict(sh_degree=3, eps2d=0.1, rasterize_mode="antialiased")
    cpu = _run("cpu", params, sh, viewmats, Ks, backgrounds=bg, **kw)
    gpu = _run("cuda", params, sh, viewmats, Ks, backgrounds=bg.cuda(), **kw)
    torch.testing.assert_close(gpu[0], cpu[0], atol=2e-3, rtol=1e-3)
    for a, b in zip(gpu[2], cpu[2]):
        assert (a - b).abs().max() <= 1e-2 * b.abs().max() + 1e-4
    classic = _run("cpu", params, sh, viewmats, Ks, backgrounds=bg, sh_degree=3, eps2d=0.1)
    assert (classic[0] - cpu[0]).abs().max() > 1e-2  # the compensation is applied
