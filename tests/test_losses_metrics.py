import math
from types import SimpleNamespace

import pytest
import torch

from promptgs_engine import losses, metrics


def test_ssim_is_one_for_identical_and_drops_with_noise():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(1, 32, 40, 3, generator=g)
    assert abs(float(losses.ssim(img, img)) - 1.0) < 1e-5
    noisy = (img + 0.2 * torch.randn(img.shape, generator=g)).clamp(0, 1)
    assert float(losses.ssim(noisy, img)) < 0.9
    assert float(losses.d_ssim(noisy, img)) > 0.1


def test_photometric_loss_gradient_flows():
    img = torch.full((1, 16, 16, 3), 0.5, requires_grad=True)
    ref = torch.zeros(1, 16, 16, 3)
    loss = losses.photometric_loss(img, ref)
    loss.backward()
    assert img.grad is not None and float(img.grad.abs().sum()) > 0


def test_edge_loss_sees_a_missing_edge_but_not_a_flat_offset():
    ref = torch.zeros(1, 16, 16, 1)
    ref[:, :, 8:] = 1.0
    flat = torch.full_like(ref, 0.5)
    shifted = ref * 0.5 + 0.25  # same edge position, lower contrast
    assert float(losses.edge_loss(ref + 0.1, ref)) < 1e-5  # a constant offset has the same edges
    assert float(losses.edge_loss(flat, ref)) > float(losses.edge_loss(shifted, ref)) > 0


def test_edge_losses_are_each_images_edge_loss():
    g = torch.Generator().manual_seed(0)
    img, ref = torch.rand(3, 20, 17, 3, generator=g), torch.rand(3, 20, 17, 3, generator=g)
    batch = losses.edge_losses(img, ref)
    assert batch.shape == (3,)
    for i in range(3):
        assert torch.allclose(batch[i], losses.edge_loss(img[i : i + 1], ref[i : i + 1]), rtol=1e-6, atol=0)


def test_psnr_and_masked_psnr_hand_computed():
    ref = torch.zeros(4, 4, 3)
    img = ref.clone()
    img[0, 0] = 0.1  # one pixel wrong by 0.1 in all channels
    assert math.isclose(metrics.psnr(img, ref), -10 * math.log10(0.01 / 16), rel_tol=1e-5)
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[0, :2] = True  # the wrong pixel and a right one
    assert math.isclose(metrics.masked_psnr(img, ref, mask), -10 * math.log10(0.01 / 2), rel_tol=1e-5)
    assert metrics.masked_psnr(img, ref, torch.zeros_like(mask)) is None


def test_object_region_is_the_dilated_box_of_each_object():
    ids = torch.zeros(20, 20, dtype=torch.int64)
    ids[5, 5] = 1
    ids[15, 16:18] = 2
    boxes = metrics.object_boxes(ids, dilate=4)
    assert sorted(boxes) == [(1, 10, 1, 10), (11, 20, 12, 20)]
    ref = torch.zeros(20, 20, 3)
    img = torch.zeros(20, 20, 3)
    img[0, 0] = 1.0  # outside both boxes: does not count
    assert metrics.object_region_psnr(img, ref, ids) == float("inf")
    img[1, 1] = 1.0  # inside the first box's dilation
    assert math.isfinite(metrics.object_region_psnr(img, ref, ids))


def test_resize_mask_keeps_a_one_pixel_object_when_downscaling():
    ids = torch.zeros(16, 16, dtype=torch.int64)
    ids[5, 6] = 3
    small = metrics.resize_mask(ids, 4, 4)
    assert small.shape == (4, 4)
    assert int(small[1, 1]) == 3 and int((small > 0).sum()) == 1


def test_fused_cpu_ssim_matches_torch_ssim_and_its_gradient():
    """The C++ SSIM (float32 on the CPU) against the torch version: values and gradients,
    on sizes that are not multiples of anything and with more than one image and channel."""
    from promptgs_engine.losses import _fused_ssim_applies, ssim_map_torch

    g = torch.Generator().manual_seed(0)
    for shape in ((2, 23, 37, 3), (1, 9, 5, 4)):
        img = torch.rand(*shape, generator=g)
        ref = (img + 0.2 * torch.randn(*shape, generator=g)).clamp(0, 1)
        assert _fused_ssim_applies(img, ref)
        weights = torch.randn(*shape, generator=g)
        a = img.clone().requires_grad_()
        b = img.double().clone().requires_grad_()
        fused = losses.ssim_map(a, ref)
        torch_ssim = ssim_map_torch(b, ref.double())
        assert (fused.double() - torch_ssim).abs().max() < 2e-5
        (fused * weights).sum().backward()
        (torch_ssim * weights.double()).sum().backward()
        scale = b.grad.abs().max()
        assert scale > 0
        assert (a.grad.double() - b.grad).abs().max() < 2e-4 * scale


@pytest.mark.parametrize("shape", [(2, 23, 37, 3), (1, 16, 32, 3)])
def test_fused_photometric_loss_equals_the_torch_expression_bit_for_bit(shape):
    """The one-node loss gives the loss, both maps and the image gradient of the torch
    expression to the last bit (so training results do not change), including pixels
    where the render equals the reference (sgn 0); rows whose window is cut by the image's
    edge and rows of whole vectors (32 x 3 floats) or not (37 x 3)."""
    g = torch.Generator().manual_seed(5)
    img = torch.rand(*shape, generator=g)
    ref = torch.rand(*shape, generator=g)
    ref[0, :5] = img[0, :5]
    for lam in (0.2, 0.37):
        results = []
        for fn in (losses.photometric_maps, losses.photometric_maps_torch):
            x = img.clone().requires_grad_(True)
            loss, l1_map, dssim_map = fn(x, ref, lam)
            (loss * 1.7).backward()
            results.append((loss.detach(), l1_map.detach(), dssim_map.detach(), x.grad))
            if fn is losses.photometric_maps:  # the fused node, not the torch expression again
                assert type(loss.grad_fn).__name__ == "_FusedPhotometricBackward"
        fused, plain = results
        for a, b in zip(fused, plain):
            assert a.shape == b.shape and torch.equal(a, b)
    x = img.clone().requires_grad_(True)
    _, l1_map, dssim_map = losses.photometric_maps(x, ref)
    assert not l1_map.requires_grad and not dssim_map.requires_grad


def test_reference_edges_are_kept_per_view_and_per_crop_window():
    """The per-view loss's ground-truth edges, kept between steps, are those `edge_losses`
    computes; two crops of one view at the same size but different windows each get
    their own, and a new reference is computed, not the old one returned."""
    from promptgs_engine.focus import ReferenceEdges
    from promptgs_engine.views import TrainView
    from promptgs_engine.losses import edge_losses, edge_losses_to

    g = torch.Generator().manual_seed(0)
    image = torch.rand(40, 50, 3, generator=g)
    camera = SimpleNamespace(width=20, height=16)
    crops = [TrainView(camera, image[y:y + 16, x:x + 20], source=3, crop=True, window=(x, y, 20, 16))
             for x, y in ((0, 0), (25, 20))]
    cache = ReferenceEdges()
    render = torch.rand(2, 16, 20, 3, generator=g)
    for _ in range(2):  # computed, then kept
        kept = torch.stack([cache.of(v) for v in crops])
        assert torch.equal(edge_losses_to(render, kept), edge_losses(render, torch.stack([v.gt for v in crops])))
    assert len(cache) == 2


def test_loss_and_mse_reads_the_image_s_mse_without_touching_it():
    """The step's MSE is the plain expression's to the bit, and neither image changes."""
    g = torch.Generator().manual_seed(2)
    img = torch.rand(1, 9, 13, 3, generator=g).requires_grad_(True)
    ref = torch.rand(1, 9, 13, 3, generator=g)
    before = img.detach().clone(), ref.clone()
    loss = (img * 2.0).sum()
    loss_value, mse_value = metrics.loss_and_mse(loss, img, ref)
    assert mse_value == float(((img.detach() - ref) ** 2).mean())
    assert loss_value == float(loss.detach())
    assert torch.equal(img.detach(), before[0]) and torch.equal(ref, before[1])
