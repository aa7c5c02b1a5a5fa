"""The C++ CPU rasterizer behind render(): parity with the torch reference (images and every
gradient), finite differences, absgrad, culling, and the info contract gsplat's strategies read."""

from __future__ import annotations

import pytest
import torch

from promptgs_engine.render import RenderBackendError, render, resolve_backend
from promptgs_engine.render.cpu import rasterize_cpu
from promptgs_engine.render.projection import project_gaussians
from promptgs_engine.render.reference import render_reference

W, H = 61, 45  # not multiples of the 16-pixel tile


def make_scene(n: int, seed: int, spread: float = 0.7, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * spread + torch.tensor([0.0, 0.0, 3.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.15 + 0.02
    opacities = torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05
    return means, quats, scales, opacities


def cameras(c: int, dtype=torch.float64):
    Ks = torch.tensor([[55.0, 0.0, W / 2 + 1.3], [0.0, 57.0, H / 2 - 0.7], [0.0, 0.0, 1.0]], dtype=dtype)
    Ks = Ks[None].repeat(c, 1, 1)
    viewmats = torch.eye(4, dtype=dtype)[None].repeat(c, 1, 1)
    for i in range(1, c):  # further cameras: small rotation about y and a shift
        a = 0.15 * i
        R = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
        R[0, 0], R[0, 2], R[2, 0], R[2, 2] = torch.cos(torch.tensor(a)), torch.sin(torch.tensor(a)), -torch.sin(torch.tensor(a)), torch.cos(torch.tensor(a))
        viewmats[i, :3, :3] = R
        viewmats[i, :3, 3] = torch.tensor([0.1 * i, -0.05 * i, 0.2 * i], dtype=dtype)
    return viewmats, Ks


def run_both(n, seed, colors64, sh_degree=None, bg=True, mode="RGB", n_cams=1, eps2d=0.3, rasterize_mode="classic"):
    """Render with the C++ backend (float32) and the reference (float64); backprop the same
    random linear loss through both; return outputs and gradients."""
    scene = make_scene(n, seed)
    viewmats, Ks = cameras(n_cams)
    D = 3 if sh_degree is not None else colors64.shape[-1]
    g = torch.Generator().manual_seed(seed + 1)
    backgrounds = torch.rand(n_cams, D, generator=g, dtype=torch.float64) if bg else None
    results = []
    weights = None
    for dtype, fn in ((torch.float32, render), (torch.float64, render_reference)):
        params = [t.detach().clone().to(dtype).requires_grad_() for t in (*scene, colors64)]
        kw = dict(sh_degree=sh_degree, render_mode=mode, eps2d=eps2d, rasterize_mode=rasterize_mode)
        kw["backgrounds"] = None if backgrounds is None else backgrounds.to(dtype)
        if fn is render:
            kw["backend"] = "cpu"
        out, alpha, info = fn(*params, viewmats.to(dtype), Ks.to(dtype), W, H, **kw)
        info["means2d"].retain_grad()
        if weights is None:
            weights = (torch.randn(out.shape, generator=g, dtype=torch.float64),
                       torch.randn(alpha.shape, generator=g, dtype=torch.float64))
        loss = (out * weights[0].to(dtype)).sum() + (alpha * weights[1].to(dtype)).sum()
        loss.backward()
        grads = [p.grad.double() for p in params] + [info["means2d"].grad.double()]
        results.append((out.detach().double(), alpha.detach().double(), grads, info))
    return results


GRAD_NAMES = ["means", "quats", "scales", "opacities", "colors", "means2d"]


def assert_close_grads(cpu, ref, rtol=2e-4):
    for name, a, b in zip(GRAD_NAMES, cpu[2], ref[2]):
        scale = b.abs().max().item()
        assert scale > 0, f"{name}: reference gradient is all zero, the scene tests nothing"
        err = (a - b).abs().max().item()
        assert err <= rtol * scale + 1e-6, f"{name}: max |cpu - reference| = {err:.3g} (scale {scale:.3g})"


@pytest.mark.parametrize("D", [1, 3, 4, 7])
@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_cpu_matches_reference_features(D, mode):
    n = 250
    colors = torch.rand(n, D, generator=torch.Generator().manual_seed(D), dtype=torch.float64)
    cpu, ref = run_both(n, seed=10 + D, colors64=colors, mode=mode)
    assert cpu[0].shape == (1, H, W, D + (mode == "RGB+ED"))
    assert cpu[1].shape == (1, H, W, 1)
    assert (cpu[0] - ref[0]).abs().max().item() < 2e-5 * max(1.0, ref[0].abs().max().item())
    assert (cpu[1] - ref[1]).abs().max().item() < 1e-5
    assert ref[1].max() > 0.9 and ref[1].min() < 0.5  # overlapping and sparse regions both present
    assert (cpu[3]["radii"] - ref[3]["radii"]).abs().max() <= 1  # float32 vs float64 rounding of ceil()
    assert_close_grads(cpu, ref, rtol=5e-4 if mode == "RGB+ED" else 2e-4)


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_cpu_matches_reference_sh_two_cameras(sh_degree):
    n = 150
    K = (sh_degree + 1) ** 2 + 1  # more coefficients than the degree uses
    colors = torch.randn(n, K, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.3
    cpu, ref = run_both(n, seed=20 + sh_degree, colors64=colors, sh_degree=sh_degree, n_cams=2)
    assert cpu[0].shape == (2, H, W, 3)
    assert (cpu[0] - ref[0]).abs().max().item() < 2e-5
    assert_close_grads(cpu, ref)
    # coefficients above the degree get no gradient
    assert cpu[2][4][:, (sh_degree + 1) ** 2 :].abs().max() == 0


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_sh_rest_apart_equals_the_concatenated_coefficients_bit_for_bit(sh_degree):
    """render(colors=sh0, sh_rest=shN) is render(colors=cat([sh0, shN])): the same images and
    the same gradients, with each part's gradient where the concatenation's would be."""
    n, views = 120, cameras(2, dtype=torch.float32)
    geometry = [t.float() for t in make_scene(n, seed=7)]
    coefs = torch.randn(n, 16, 3, generator=torch.Generator().manual_seed(4)) * 0.3
    weights = torch.rand(2, H, W, 3, generator=torch.Generator().manual_seed(5))
    outs = []
    for apart in (False, True):
        sh0 = coefs[:, :1].clone().requires_grad_(True)
        shN = coefs[:, 1:].clone().requires_grad_(True)
        means, quats, scales, opacities = (t.clone().requires_grad_(True) for t in geometry)
        kwargs = {"sh_rest": shN} if apart else {}
        img, alpha, _ = render(means, quats, scales, opacities, sh0 if apart else torch.cat([sh0, shN], 1), *views, W, H,
                               sh_degree=sh_degree, backend="cpu", **kwargs)
        ((img * weights).sum() + alpha.sum()).backward()
        outs.append([img, alpha] + [t.grad for t in (means, quats, scales, sh0, shN)])
    for a, b in zip(*outs):
        assert torch.equal(a, b)
    if sh_degree < 3:  # unused coefficients: no gradient
        assert outs[1][6][:, (sh_degree + 1) ** 2 - 1 :].abs().max() == 0
    if sh_degree:
        assert outs[1][6].abs().max() > 0


def test_cpu_matches_reference_with_a_narrow_screen_filter():
    n = 120
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    cpu, ref = run_both(n, seed=31, colors64=colors, n_cams=2, eps2d=0.1)
    assert (cpu[0] - ref[0]).abs().max().item() < 2e-5
    assert_close_grads(cpu, ref)
    # The filter is really used: the same scene renders differently with 3DGS's.
    wide, _ = run_both(n, seed=31, colors64=colors, n_cams=2, eps2d=0.3)
    assert (wide[0] - cpu[0]).abs().max().item() > 1e-2


@pytest.mark.parametrize("eps2d", [0.1, 0.3])
@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_screen_filter_sets_the_footprint_of_a_point(eps2d, backend):
    """A Gaussian far smaller than a pixel, centred on a pixel, is drawn as a 2D Gaussian
    of variance eps2d: its neighbour gets exp(-1 / (2 eps2d)) of the centre's alpha."""
    means = torch.tensor([[0.0, 0.0, 4.0]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.full((1, 3), 1e-5)
    opacities = torch.tensor([0.9])
    colors = torch.ones(1, 3)
    Ks = torch.tensor([[[50.0, 0.0, 10.5], [0.0, 50.0, 10.5], [0.0, 0.0, 1.0]]])  # pixel (10, 10) at the centre
    args = (means, quats, scales, opacities, colors, torch.eye(4)[None], Ks, 21, 21)
    if backend == "cpu":
        _, alpha, _ = render(*args, backend="cpu", eps2d=eps2d)
    else:
        _, alpha, _ = render_reference(*args, eps2d=eps2d)
    a = alpha[0, ..., 0]
    assert a[10, 10].item() == pytest.approx(0.9, rel=1e-3)
    assert (a[10, 11] / a[10, 10]).item() == pytest.approx(torch.exp(torch.tensor(-0.5 / eps2d)).item(), rel=1e-2)


def test_cpu_matches_reference_antialiased():
    """The compensated filter: images and every gradient (through the per-camera opacities
    into scales, quats and means) match the reference, and differ from the classic mode."""
    n = 120
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    cpu, ref = run_both(n, seed=33, colors64=colors, n_cams=2, eps2d=0.1, rasterize_mode="antialiased")
    assert (cpu[0] - ref[0]).abs().max().item() < 2e-5
    assert_close_grads(cpu, ref)
    classic, _ = run_both(n, seed=33, colors64=colors, n_cams=2, eps2d=0.1)
    assert (classic[0] - cpu[0]).abs().max().item() > 1e-2


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_antialiased_filter_keeps_a_tiny_gaussians_energy(backend):
    """Classic mode draws a point at full opacity whatever its size, so its summed alpha is
    the same from every distance; antialiased mode scales it with the projected area, as a
    real sub-pixel object covers a pixel (twice the distance, a quarter of the energy)."""
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.full((1, 3), 0.004)  # 0.05 px std at depth 4 with f = 50
    opacities = torch.tensor([0.9])
    colors = torch.ones(1, 3)
    Ks = torch.tensor([[[50.0, 0.0, 10.5], [0.0, 50.0, 10.5], [0.0, 0.0, 1.0]]])

    def energy(depth: float, mode: str) -> float:
        args = (torch.tensor([[0.0, 0.0, depth]]), quats, scales, opacities, colors, torch.eye(4)[None], Ks, 21, 21)
        fn = render if backend == "cpu" else render_reference
        kw = {"backend": "cpu"} if backend == "cpu" else {}
        _, alpha, _ = fn(*args, eps2d=0.1, rasterize_mode=mode, **kw)
        return alpha.sum().item()

    assert energy(8.0, "classic") == pytest.approx(energy(4.0, "classic"), rel=0.02)
    near, far = energy(4.0, "antialiased"), energy(8.0, "antialiased")
    assert far / near == pytest.approx(0.25, rel=0.05)
    # nearly all of it in the centre pixel, at opacity · σ² / (σ² + eps2d) for σ = 0.05 px
    assert near == pytest.approx(0.9 * 0.05**2 / (0.05**2 + 0.1), rel=0.05)


def test_unknown_rasterize_mode_is_refused():
    means, quats, scales, opacities = make_scene(3, 0, dtype=torch.float32)
    viewmats, Ks = cameras(1, dtype=torch.float32)
    with pytest.raises(ValueError, match="rasterize_mode"):
        render(means, quats, scales, opacities, torch.ones(3, 3), viewmats, Ks, W, H, rasterize_mode="mip")


def test_no_background_and_dense_opaque_scene():
    """Many opaque overlapping Gaussians: exercises early termination (T < 1e-4) and the 0.999 clamp."""
    n = 300
    scene = make_scene(n, seed=5, spread=0.25)
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    viewmats, Ks = cameras(1)
    outs = []
    for dtype, fn in ((torch.float32, render), (torch.float64, render_reference)):
        m, q, s, _ = [t.detach().clone().to(dtype) for t in scene]
        o = torch.full((n,), 0.995, dtype=dtype)
        params = [t.requires_grad_() for t in (m, q, s * 2, o, colors.to(dtype))]
        out, alpha, info = fn(*params, viewmats.to(dtype), Ks.to(dtype), W, H)
        (out.square().sum() + alpha.sum()).backward()
        outs.append((out.detach().double(), alpha.detach().double(), [p.grad.double() for p in params]))
    assert (outs[1][1] > 1 - 1e-3).sum() > 100  # saturated pixels exist
    assert (outs[0][0] - outs[1][0]).abs().max() < 2e-5
    for a, b in zip(outs[0][2], outs[1][2]):
        assert (a - b).abs().max() <= 5e-4 * b.abs().max() + 1e-6


def cpu_and_reference(scene64, Ks64, width, height, weights):
    """One camera at the origin: the C++ backend in float32 and the reference in float64 on
    the same Gaussians (means, quats, scales, opacities, colours), the same weighted loss
    of image and alpha backpropagated. Per backend: (image, alpha, gradients of the five
    inputs and of means2d), in float64."""
    outs = []
    for dtype, fn in ((torch.float32, render), (torch.float64, render_reference)):
        params = [t.detach().clone().to(dtype).requires_grad_() for t in scene64]
        kw = {"backend": "cpu"} if fn is render else {}
        out, alpha, info = fn(*params, torch.eye(4, dtype=dtype)[None], Ks64.to(dtype), width, height, **kw)
        info["means2d"].retain_grad()
        ((out * weights.to(dtype)).sum() + alpha.sum()).backward()
        grads = [p.grad.double() for p in params] + [info["means2d"].grad.double()]
        outs.append((out.detach().double(), alpha.detach().double(), grads))
    return outs


def test_thin_slanted_gaussians_that_graze_tile_corners():
    """Wire-like Gaussians (long, thin, slanted, some faint) crossing the 16-pixel tiles at
    every angle: the rasterizer drops the tile rows (and, with kernels narrower than a row,
    the halves of rows) whose slice of the ellipse misses their columns, and one dropped
    wrongly would leave a gap in the line. Image and gradients against the reference, on a
    64x48 image (12 tiles)."""
    n, width, height = 120, 64, 48
    g = torch.Generator().manual_seed(7)
    angle = torch.rand(n, generator=g, dtype=torch.float64) * torch.pi
    means = torch.stack([(torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 3.2,
                         (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2.4,
                         torch.full((n,), 3.0, dtype=torch.float64)], -1)
    quats = torch.stack([torch.cos(angle / 2), torch.zeros(n, dtype=torch.float64),
                         torch.zeros(n, dtype=torch.float64), torch.sin(angle / 2)], -1)  # about the view axis
    scales = torch.stack([torch.rand(n, generator=g, dtype=torch.float64) * 0.6 + 0.2,
                          torch.rand(n, generator=g, dtype=torch.float64) * 0.01 + 0.004,
                          torch.full((n,), 0.01, dtype=torch.float64)], -1)
    opacities = torch.rand(n, generator=g, dtype=torch.float64) * 0.95 + 0.02
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    Ks = torch.tensor([[[60.0, 0.0, width / 2 + 0.37], [0.0, 60.0, height / 2 - 0.21], [0.0, 0.0, 1.0]]],
                      dtype=torch.float64)
    weights = torch.randn(1, height, width, 3, generator=g, dtype=torch.float64)
    (cpu_img, cpu_alpha, cpu_grads), (ref_img, ref_alpha, ref_grads) = cpu_and_reference(
        (means, quats, scales, opacities, colors), Ks, width, height, weights)
    assert ((ref_alpha > 0.02) & (ref_alpha < 0.9)).sum() > 300  # many partly covered pixels along the lines
    # float32 against float64 on conics of thin Gaussians; a wrongly dropped row would miss
    # at least 1/255 of alpha at some pixel
    assert (cpu_img - ref_img).abs().max() < 5e-5
    assert (cpu_alpha - ref_alpha).abs().max() < 5e-5
    for a, b in zip(cpu_grads, ref_grads):  # the conics of thin Gaussians cost float32 a digit
        assert (a - b).abs().max() <= 1e-3 * b.abs().max() + 1e-6


def test_culling_of_tile_row_halves_keeps_small_gaussians_that_cross_the_middle():
    """Small Gaussians (radius 1-3 px) centred just left and right of the middle of a tile
    row and of the tile edges, on every row: with kernels narrower than a tile row each half
    of a row walks only the Gaussians whose ellipse reaches its columns, so a Gaussian whose
    edge reaches one pixel across the middle must still be composited there. Image and
    gradients against the reference, on a 48x32 image."""
    width, height, f = 48, 32, 40.0
    g = torch.Generator().manual_seed(11)
    xs = torch.tensor([7.3, 7.8, 8.0, 8.2, 8.7, 15.6, 16.4, 23.5, 24.5, 39.9, 40.1], dtype=torch.float64)
    ys = torch.arange(1.5, height, 3.0, dtype=torch.float64)
    px, py = torch.meshgrid(xs, ys, indexing="ij")
    px, py = px.flatten() + torch.rand(px.numel(), generator=g, dtype=torch.float64) * 0.1, py.flatten()
    n = px.numel()
    depth = 3.0
    means = torch.stack([(px - width / 2) * depth / f, (py - height / 2) * depth / f, torch.full((n,), depth,
                        dtype=torch.float64)], -1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.5 + 0.25) * depth / f  # 0.25-0.75 px sigma
    opacities = torch.rand(n, generator=g, dtype=torch.float64) * 0.5 + 0.45
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    Ks = torch.tensor([[[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    weights = torch.randn(1, height, width, 3, generator=g, dtype=torch.float64)
    (cpu_img, cpu_alpha, cpu_grads), (ref_img, ref_alpha, ref_grads) = cpu_and_reference(
        (means, quats, scales, opacities, colors), Ks, width, height, weights)
    # the Gaussians reach across the middle of the rows (columns 7 and 8 both covered)
    assert (ref_alpha[0, :, 7:9, 0] > 0.05).all(dim=1).sum() > 5
    assert (cpu_img - ref_img).abs().max() < 5e-5
    assert (cpu_alpha - ref_alpha).abs().max() < 5e-5
    for a, b in zip(cpu_grads, ref_grads):
        assert (a - b).abs().max() <= 1e-3 * b.abs().max() + 1e-6


def test_large_gaussians_gradients_match_the_reference():
    """Gaussians 50-150 pixels across, elongated and overlapping, on a 256x192 image: the
    backward forms a Gaussian's conic and mean gradients from sums over its pixels, where
    large footprints add many terms of both signs, so its float32 error is checked against
    the float64 reference more tightly than the general parity tests do."""
    n, width, height = 40, 256, 192
    g = torch.Generator().manual_seed(3)
    means = torch.stack([(torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2,
                         (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 1.5,
                         torch.rand(n, generator=g, dtype=torch.float64) * 2 + 2], -1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.5 + 0.05
    scales[:, 0] *= 3
    opacities = torch.rand(n, generator=g, dtype=torch.float64) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    Ks = torch.tensor([[[200.0, 0.0, width / 2], [0.0, 200.0, height / 2], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    weights = torch.randn(1, height, width, 3, generator=g, dtype=torch.float64)
    (_, _, cpu_grads), (_, _, ref_grads) = cpu_and_reference(
        (means, quats, scales, opacities, colors), Ks, width, height, weights)
    for name, a, b, rtol in zip(GRAD_NAMES, cpu_grads, ref_grads, (2e-5, 2e-5, 2e-5, 2e-5, 1e-3, 2e-5)):
        assert (a - b).abs().max() <= rtol * b.abs().max(), f"{name}: {(a - b).abs().max():.3g} of {b.abs().max():.3g}"


def test_backward_is_bit_reproducible():
    """Tiles go to the threads in a fixed order, so the same inputs give the same gradients to
    the last bit (with a dynamic schedule, per-thread sums came out in a different order)."""
    from promptgs_engine.render.cpu import _ext

    if _ext().num_threads() < 2:
        pytest.skip("one OpenMP thread: the summation order cannot vary")
    n, width, height = 20000, 320, 240
    m, q, s, o = make_scene(n, seed=11, spread=1.0, dtype=torch.float32)
    s = s * 0.2  # a few pixels each, many per tile
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(1))
    Ks = torch.tensor([[[300.0, 0.0, width / 2], [0.0, 300.0, height / 2], [0.0, 0.0, 1.0]]])

    def grads():
        params = [t.clone().requires_grad_() for t in (m, q, s, o, colors)]
        out, alpha, _ = render(*params, torch.eye(4)[None], Ks, width, height, backend="cpu")
        (out.square().sum() + alpha.sum()).backward()
        return [p.grad for p in params]

    first = grads()
    for _ in range(3):
        for a, b in zip(first, grads()):
            assert torch.equal(a, b)


@pytest.mark.parametrize("used", ["colors", "alphas"])
def test_an_output_no_loss_reaches_counts_as_zero_gradient(used):
    """The rasterizer's backward gets no image of zeros for an output the loss does not use
    (the alphas, in training); its gradients are those of an explicit zero gradient, bit for bit."""
    m, q, s, o = make_scene(300, seed=4, dtype=torch.float32)
    colors = torch.rand(300, 3, generator=torch.Generator().manual_seed(2))
    viewmats, Ks = cameras(1, dtype=torch.float32)
    w = torch.Generator().manual_seed(3)
    w_out, w_alpha = torch.randn(1, H, W, 3, generator=w), torch.randn(1, H, W, 1, generator=w)

    def grads(explicit_zero: bool):
        params = [t.clone().requires_grad_() for t in (m, q, s, o, colors)]
        out, alpha, _ = render(*params, viewmats, Ks, W, H, backend="cpu")
        loss = (out * w_out).sum() if used == "colors" else (alpha * w_alpha).sum()
        if explicit_zero:
            loss = loss + ((alpha * 0.0).sum() if used == "colors" else (out * 0.0).sum())
        loss.backward()
        return [p.grad for p in params]

    implicit, explicit = grads(False), grads(True)
    assert any(g.abs().max() > 0 for g in implicit)
    for a, b in zip(implicit, explicit):
        assert torch.equal(a, b)


def test_rasterizer_finite_differences_float32():
    """Central differences of the C++ forward against its backward, on an 8×8 image where no
    pixel crosses the 1/255 cut-off or the termination threshold (so the loss is smooth)."""
    g = torch.Generator().manual_seed(0)
    n, D, S = 4, 3, 8
    means2d = (torch.rand(1, n, 2, generator=g) * 4 + 2).double()
    conics = torch.tensor([[0.02, 0.005, 0.03]]).repeat(n, 1)[None].double() * (1 + torch.rand(1, n, 1, generator=g).double())
    colors = torch.rand(1, n, D, generator=g).double()
    opac = (torch.rand(n, generator=g) * 0.5 + 0.2).double()
    depths = torch.arange(n, dtype=torch.float32)[None] + 1
    radii = torch.full((1, n, 2), 40, dtype=torch.int32)
    bg = torch.rand(1, D, generator=g)
    w_img = torch.randn(1, S, S, D, generator=g).double()
    w_a = torch.randn(1, S, S, 1, generator=g).double()

    def loss(m, c, col, o):
        img, a = rasterize_cpu(m.float(), c.float(), col.float(), o.float(), depths, radii, S, S, bg)
        return (img.double() * w_img).sum() + (a.double() * w_a).sum()

    inputs = [t.clone().requires_grad_() for t in (means2d, conics, colors, opac)]
    loss(*inputs).backward()
    eps = [1e-2, 1e-4, 1e-2, 1e-2]
    for k, (x, h) in enumerate(zip(inputs, eps)):
        fd = torch.zeros_like(x)
        flat = fd.view(-1)
        for j in range(x.numel()):
            plus = [t.detach().clone() for t in inputs]
            minus = [t.detach().clone() for t in inputs]
            plus[k].view(-1)[j] += h
            minus[k].view(-1)[j] -= h
            flat[j] = (loss(*plus) - loss(*minus)) / (2 * h)
        err = (fd - x.grad).abs().max().item()
        assert err <= 2e-2 * x.grad.abs().max().item() + 1e-3, f"input {k}: fd vs analytic max err {err:.3g}"


def test_reference_gradcheck_float64():
    """The reference's autograd gradients (ground truth for the parity tests) pass gradcheck."""
    scene = make_scene(6, seed=1, spread=0.3)
    colors = torch.rand(6, 2, dtype=torch.float64)
    viewmats, Ks = cameras(1)
    S = 12
    Ks = Ks.clone()
    Ks[0, 0, 2], Ks[0, 1, 2], Ks[0, 0, 0], Ks[0, 1, 1] = S / 2, S / 2, 10.0, 10.0
    params = [t.clone().requires_grad_() for t in (*scene, colors)]

    def f(*p):
        out, alpha, _ = render_reference(*p, viewmats, Ks, S, S)
        return out.sum() + 0.3 * alpha.square().sum()

    assert torch.autograd.gradcheck(f, params, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_absgrad_bounds_and_single_pixel():
    scene = [t.float() for t in make_scene(120, seed=7)]
    colors = torch.rand(120, 3)
    viewmats, Ks = cameras(1, torch.float32)
    params = [t.clone().requires_grad_() for t in (*scene, colors)]
    out, alpha, info = render(*params, viewmats, Ks, W, H, absgrad=True, backend="cpu")
    info["means2d"].retain_grad()
    (out * torch.randn_like(out)).sum().backward()
    m2 = info["means2d"]
    assert m2.absgrad.shape == m2.shape
    assert (m2.absgrad >= m2.grad.abs() - 1e-6).all()
    assert (m2.absgrad > m2.grad.abs() + 1e-4).any()  # sums of |.| over pixels differ from |sum|

    # one pixel: the absolute gradient is exactly |grad|
    Ks1 = torch.tensor([[[20.0, 0.0, 0.5], [0.0, 20.0, 0.5], [0.0, 0.0, 1.0]]])
    p1 = [t.clone().requires_grad_() for t in (*scene, colors)]
    out1, _, info1 = render(*p1, viewmats, Ks1, 1, 1, absgrad=True, backend="cpu")
    info1["means2d"].retain_grad()
    out1.sum().backward()
    g1 = info1["means2d"]
    assert (g1.grad.abs() > 0).any()
    torch.testing.assert_close(g1.absgrad, g1.grad.abs(), rtol=0, atol=1e-7)


def test_culling_behind_outside_and_transparent():
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0], [50.0, 0.0, 2.0], [0.1, 0.1, 2.5], [0.0, 0.0, 0.005]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(5, 1)
    scales = torch.full((5, 3), 0.1)
    opac = torch.tensor([0.8, 0.8, 0.8, 0.001, 0.8])
    colors = torch.rand(5, 3)
    viewmats, Ks = cameras(1, torch.float32)
    params = [t.clone().requires_grad_() for t in (means, quats, scales, opac, colors)]
    out, alpha, info = render(*params, viewmats, Ks, W, H, backend="cpu")
    radii = info["radii"][0]
    assert radii.dtype == torch.int32 and radii.shape == (5, 2)
    assert (radii[0] > 0).all()
    for i in (1, 2, 3, 4):  # behind, outside the frustum, below 1/255 opacity, before the near plane
        assert (radii[i] == 0).all(), i
    info["means2d"].retain_grad()
    out.sum().backward()
    for p in params:
        assert torch.isfinite(p.grad).all()
    assert (params[0].grad[1:] == 0).all() and (params[4].grad[1:] == 0).all()
    assert (params[0].grad[0] != 0).any()
    assert info["depths"][0, 1].item() == pytest.approx(-2.0)


def test_projection_matches_gsplat_torch_implementation():
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    means, quats, scales, opac = make_scene(200, seed=3)
    viewmats, Ks = cameras(2)
    m2, conics, depths, radii = project_gaussians(means, quats, scales, opac, viewmats, Ks, W, H)
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False, triu=False)
    g_radii, g_m2, g_depths, g_conics, _ = _fully_fused_projection(means, covars, viewmats, Ks, W, H)
    torch.testing.assert_close(m2, g_m2)
    torch.testing.assert_close(conics, g_conics)
    torch.testing.assert_close(depths, g_depths)
    # our boxes are the opacity-aware ones (never larger than gsplat's 3.33 sigma)
    vis = (radii > 0).all(-1)
    assert vis.sum() > 100
    assert (radii[vis] <= g_radii[vis]).all()


def test_sh_matches_gsplat_torch_implementation():
    from gsplat.cuda._torch_impl import _spherical_harmonics

    from promptgs_engine.render.sh import eval_sh

    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(100, 3, generator=g, dtype=torch.float64)
    coeffs = torch.randn(100, 16, 3, generator=g, dtype=torch.float64)
    for d in range(4):
        torch.testing.assert_close(eval_sh(d, dirs, coeffs), _spherical_harmonics(d, dirs, coeffs))


def test_info_drives_gsplat_default_strategy():
    from gsplat.strategy import DefaultStrategy

    n = 80
    means, quats, scales, opac = [t.float() for t in make_scene(n, seed=9)]
    params = torch.nn.ParameterDict(
        {
            "means": means,
            "quats": quats,
            "scales": scales.log(),
            "opacities": torch.logit(opac),
            "sh0": torch.rand(n, 1, 3),
            "shN": torch.zeros(n, 15, 3),
        }
    )
    optimizers = {k: torch.optim.Adam([v], lr=1e-3) for k, v in params.items()}
    viewmats, Ks = cameras(2, torch.float32)
    for absgrad in (False, True):
        strategy = DefaultStrategy(absgrad=absgrad, refine_start_iter=10_000)
        strategy.check_sanity(params, optimizers)
        state = strategy.initialize_state()
        for step in range(2):
            colors = torch.cat([params["sh0"], params["shN"]], dim=1)
            out, alpha, info = render(
                params["means"], params["quats"], params["scales"].exp(), params["opacities"].sigmoid(),
                colors, viewmats, Ks, W, H, sh_degree=3, absgrad=absgrad, backend="cpu",
            )
            assert set(["means2d", "radii", "depths", "width", "height", "n_cameras", "gaussian_ids", "backend"]) <= set(info)
            assert info["means2d"].shape == (2, n, 2) and info["radii"].shape == (2, n, 2)
            assert info["radii"].dtype == torch.int32 and info["gaussian_ids"] is None
            assert info["n_cameras"] == 2 and info["backend"] == "cpu"
            strategy.step_pre_backward(params, optimizers, state, step, info)
            out.mean().backward()
            strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        visible = (info["radii"] > 0).all(-1).sum(0)
        assert torch.equal(state["count"], 2 * visible.float())
        assert (state["grad2d"][visible > 0] > 0).all()


def test_empty_and_fully_culled_scenes():
    viewmats, Ks = cameras(1, torch.float32)
    bg = torch.tensor([[0.2, 0.4, 0.6]])
    for n in (0, 3):
        means = torch.zeros(n, 3) - torch.tensor([0.0, 0.0, 5.0])  # all behind the camera
        params = [t.requires_grad_() for t in (means, torch.randn(n, 4), torch.ones(n, 3) * 0.1, torch.ones(n) * 0.5, torch.rand(n, 3))]
        out, alpha, info = render(*params, viewmats, Ks, W, H, backgrounds=bg, backend="cpu")
        assert torch.allclose(out, bg.view(1, 1, 1, 3).expand_as(out))
        assert (alpha == 0).all()
        out.sum().backward()


def test_backend_selection_errors():
    assert resolve_backend("auto", torch.device("cpu")) == "cpu"
    with pytest.raises(ValueError):
        resolve_backend("opengl", torch.device("cpu"))
    if not torch.cuda.is_available():
        with pytest.raises(RenderBackendError, match="CUDA"):
            resolve_backend("cuda", torch.device("cpu"))
    with pytest.raises(ValueError, match="render_mode"):
        render(*[torch.zeros(1, k) for k in (3, 4, 3)], torch.zeros(1), torch.zeros(1, 3), *cameras(1, torch.float32), W, H, render_mode="D")


@pytest.mark.parametrize("sh_degree", [None, 2])
def test_several_cameras_sum_the_projection_gradients_of_each_in_camera_order(sh_degree):
    """One render of three cameras gives the projection's gradients of three one-camera
    renders, summed camera by camera, bit for bit (enough Gaussians for every thread to
    hold a range of them, so each thread's sum of its own range is checked)."""
    n, views = 3000, cameras(3, dtype=torch.float32)
    geometry = [t.float() for t in make_scene(n, seed=11, spread=1.5)]
    colors = (torch.randn(n, 9, 3, generator=torch.Generator().manual_seed(6)) * 0.3 if sh_degree is not None
              else torch.rand(n, 3, generator=torch.Generator().manual_seed(6)))
    weights = torch.rand(3, H, W, 3, generator=torch.Generator().manual_seed(8))

    def grads(cams: list[int]) -> list[torch.Tensor]:
        leaves = [t.clone().requires_grad_(True) for t in (*geometry, colors)]
        img, alpha, _ = render(*leaves, views[0][cams], views[1][cams], W, H, sh_degree=sh_degree, backend="cpu")
        ((img * weights[cams]).sum() + alpha.sum()).backward()
        return [leaves[i].grad for i in (0, 1, 2)] + ([leaves[4].grad] if sh_degree is not None else [])

    together = grads([0, 1, 2])
    apart = [grads([c]) for c in range(3)]
    summed = [a.clone().add_(b).add_(c) for a, b, c in zip(*apart)]
    for name, t, s in zip(["means", "quats", "scales", "sh"], together, summed):
        assert t.abs().max() > 0, f"{name}: no gradient, the scene tests nothing"
        assert torch.equal(t, s), f"{name}: max difference {(t - s).abs().max().item():.3g}"
