"""Image losses. Images are ``[B, H, W, C]`` float tensors in [0, 1] (the render layout)."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

_SSIM_WINDOW = 11
_SSIM_SIGMA = 1.5
_C1 = 0.01**2
_C2 = 0.03**2


def _gaussian_kernel(size: int, sigma: float, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    k = torch.exp(-(x**2) / (2 * sigma**2))
    return k / k.sum()


_WINDOWS: dict[torch.device, torch.Tensor] = {}


def _ssim_window(device: torch.device) -> torch.Tensor:
    """The fused SSIM's float32 window on ``device``, made once (five torch calls a step)."""
    window = _WINDOWS.get(device)
    if window is None:
        window = _WINDOWS[device] = _gaussian_kernel(_SSIM_WINDOW, _SSIM_SIGMA, torch.float32, device)
    return window


def _blur(x: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of [B, C, H, W] with zero padding ("same" size)."""
    c = x.shape[1]
    pad = kernel.numel() // 2
    kx = kernel.view(1, 1, 1, -1).expand(c, 1, 1, -1)
    ky = kernel.view(1, 1, -1, 1).expand(c, 1, -1, 1)
    x = F.conv2d(x, kx, padding=(0, pad), groups=c)
    return F.conv2d(x, ky, padding=(pad, 0), groups=c)


def ssim_map(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM (11×11 Gaussian window, σ = 1.5, as in 3DGS), [B, H, W, C].

    float32 images on the CPU go through the fused C++ version (one pass over memory per
    blurred map instead of torch's depthwise convolutions: about 10x faster at 800×600,
    benchmarks/train_profile.py); anything else, or a ``ref`` that needs a gradient, through
    ``ssim_map_torch``, the reference it is tested against."""
    if _fused_ssim_applies(img, ref):
        return _FusedSSIM.apply(img, ref)
    return ssim_map_torch(img, ref)


def _fused_ssim_applies(img: torch.Tensor, ref: torch.Tensor, kernel: str = "ssim_forward") -> bool:
    """Float32 CPU images of one shape, a reference without gradient, and an extension
    that has ``kernel``."""
    if not (img.device.type == "cpu" and ref.device.type == "cpu" and img.dim() == 4 and img.shape == ref.shape):
        return False
    if img.dtype != torch.float32 or ref.dtype != torch.float32 or ref.requires_grad:
        return False
    try:
        from . import _C
    except ImportError:  # the extension is not built: the torch version still works
        return False
    return hasattr(_C, kernel)


class _FusedSSIM(torch.autograd.Function):
    """``ssim_map`` in C++ (csrc/ssim.cpp); the gradient flows to ``img`` only."""

    @staticmethod
    def forward(ctx, img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        from . import _C

        window = _ssim_window(img.device)
        img_c, ref_c = img.detach().contiguous(), ref.detach().contiguous()
        ssim, partials = _C.ssim_forward(img_c, ref_c, window, img.requires_grad)
        ctx.save_for_backward(img_c, ref_c, partials, window)
        return ssim

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        from . import _C

        img, ref, partials, window = ctx.saved_tensors
        return _C.ssim_backward(grad.contiguous(), partials, img, ref, window), None


def photometric_maps(img: torch.Tensor, ref: torch.Tensor, ssim_lambda: float = 0.2):
    """The 3DGS loss (1 − λ)·L1 + λ·D-SSIM of ``img`` [B, H, W, C] against ``ref``, with its
    per-pixel maps: (loss, L1 map [B, H, W], D-SSIM map [B, H, W]), both maps averaged over
    the channels. The maps carry no gradient.

    For three-channel images where the fused SSIM applies, the loss is one autograd node
    whose forward makes both maps with the SSIM and whose backward is the fused SSIM's plus
    the L1 term, computed with the very operations (and order) that autograd applies to the
    torch expression ``photometric_maps_torch`` (the same values to the last bit), without
    its two dozen separate nodes and image-sized temporaries."""
    if _fused_photometric_applies(img, ref) and img.requires_grad:
        return _FusedPhotometric.apply(img, ref, float(ssim_lambda))
    return photometric_maps_torch(img, ref, ssim_lambda)


def _fused_photometric_applies(img: torch.Tensor, ref: torch.Tensor) -> bool:
    """Three channels (the maps' channel means are summed in torch's order for three) where
    the fused SSIM applies, with an extension that has the fused loss."""
    return img.shape[-1] == 3 and _fused_ssim_applies(img, ref, kernel="photometric_forward")


def photometric_maps_torch(img: torch.Tensor, ref: torch.Tensor, ssim_lambda: float = 0.2):
    """``photometric_maps`` as torch expressions (the maps keep their graph)."""
    l1_map = (img - ref).abs().mean(dim=-1)
    dssim_map = (1.0 - ssim_map(img, ref)).mean(dim=-1)
    loss = (1.0 - ssim_lambda) * l1_map.mean() + ssim_lambda * dssim_map.mean()
    return loss, l1_map, dssim_map


class _FusedPhotometric(torch.autograd.Function):
    """``photometric_maps`` of three-channel images as one node, in C++ (csrc/ssim.cpp): the
    maps come with the SSIM (``_C.photometric_forward``: the channel means of |img − ref| and
    1 − SSIM, summed in channel order and divided by 3, as torch's mean over a last dimension
    of three does), and the backward is the fused SSIM's with the L1 term's sgn added; no
    image-sized temporaries besides the SSIM partials. The gradient flows to ``img`` only."""

    @staticmethod
    def forward(ctx, img: torch.Tensor, ref: torch.Tensor, lam: float):  # type: ignore[override]
        from . import _C

        window = _ssim_window(img.device)
        img_c, ref_c = img.detach().contiguous(), ref.detach().contiguous()
        l1_map, dssim_map, partials = _C.photometric_forward(img_c, ref_c, window)
        loss = (1.0 - lam) * l1_map.mean() + lam * dssim_map.mean()
        ctx.save_for_backward(img_c, ref_c, partials, window)
        ctx.lam = lam
        ctx.mark_non_differentiable(l1_map, dssim_map)
        ctx.set_materialize_grads(False)  # the maps' gradients are never used: no image-sized zeros
        return loss, l1_map, dssim_map

    @staticmethod
    def backward(ctx, grad: torch.Tensor | None, _g_l1: None, _g_dssim: None):  # type: ignore[override]
        from . import _C

        if grad is None:
            return None, None, None
        img, ref, partials, window = ctx.saved_tensors
        lam = ctx.lam
        channels = img.shape[-1]
        n = img.numel() // channels
        # autograd of photometric_maps_torch, node by node: the scalar through MulBackward
        # and the two MeanBackwards, then AbsBackward (sgn) and RSubBackward (negation)
        g_l1 = grad * (1.0 - lam) / n / channels
        g_ssim = -(grad * lam / n / channels)
        return _C.photometric_backward(float(g_ssim), float(g_l1), partials, img, ref, window), None, None


def ssim_map_torch(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """``ssim_map`` with torch operations (any device and dtype, autograd to both inputs)."""
    x = img.permute(0, 3, 1, 2)
    y = ref.permute(0, 3, 1, 2)
    k = _gaussian_kernel(_SSIM_WINDOW, _SSIM_SIGMA, x.dtype, x.device)
    # One blur call over the five stacked statistics is faster than five calls.
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), k)
    mu_x, mu_y, xx, yy, xy = stats.chunk(5, dim=1)
    sigma_x = xx - mu_x**2
    sigma_y = yy - mu_y**2
    sigma_xy = xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + _C1) * (2 * sigma_xy + _C2)
    den = (mu_x**2 + mu_y**2 + _C1) * (sigma_x + sigma_y + _C2)
    return (num / den).permute(0, 2, 3, 1)


def ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    return ssim_map(img, ref).mean()


def l1(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    return (img - ref).abs().mean()


def d_ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Structural dissimilarity (1 − SSIM), the 3DGS convention (not halved)."""
    return 1.0 - ssim(img, ref)


@functools.lru_cache(maxsize=8)
def _sobel_x(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The 3×3 Sobel filter for d/dx, made once per dtype and device (a tensor built from
    Python numbers on a GPU is a copy the host waits for)."""
    return torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=dtype, device=device)


def sobel_magnitude(img: torch.Tensor) -> torch.Tensor:
    """Gradient magnitude of each channel with 3×3 Sobel filters, [B, H, W, C]."""
    x = img.permute(0, 3, 1, 2)
    c = x.shape[1]
    gx = _sobel_x(x.dtype, x.device)
    kx = gx.view(1, 1, 3, 3).expand(c, 1, 3, 3)
    ky = gx.t().reshape(1, 1, 3, 3).expand(c, 1, 3, 3)
    xp = F.pad(x, (1, 1, 1, 1), mode="replicate")
    mag = torch.sqrt(F.conv2d(xp, kx, groups=c) ** 2 + F.conv2d(xp, ky, groups=c) ** 2 + 1e-12)
    return mag.permute(0, 2, 3, 1)


def edge_loss(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """L1 between Sobel gradient magnitudes: penalises missing or blurred edges."""
    return (sobel_magnitude(img) - sobel_magnitude(ref)).abs().mean()


def edge_losses(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """`edge_loss` of each image of a batch, [B], in one pass."""
    return edge_losses_to(img, sobel_magnitude(ref))


def edge_losses_to(img: torch.Tensor, ref_edges: torch.Tensor) -> torch.Tensor:
    """`edge_losses` against references whose `sobel_magnitude` is already known, [B]."""
    return (sobel_magnitude(img) - ref_edges).abs().mean(dim=(1, 2, 3))


def photometric_loss(img: torch.Tensor, ref: torch.Tensor, ssim_lambda: float = 0.2) -> torch.Tensor:
    """The 3DGS training loss: (1 − λ)·L1 + λ·D-SSIM."""
    return (1.0 - ssim_lambda) * l1(img, ref) + ssim_lambda * d_ssim(img, ref)
