"""Pure-torch reference rasterizer, for tests only.

Dense: every pixel looks at every visible Gaussian, sorted by depth, with the same
compositing rules as the C++ and gsplat rasterizers (alpha = min(0.999, o·exp(-σ)),
contributions with σ < 0 or alpha < 1/255 skipped, a pixel stops before the Gaussian that
would bring its transmittance to ≤ 1e-4). Gradients come from autograd, so it works in
float64 and serves as ground truth for the C++ backward. Memory is O(H·W·N): keep scenes
small (e.g. 64×48 pixels, a few hundred Gaussians).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .projection import ALPHA_THRESHOLD, EPS2D

MAX_ALPHA = 0.999
T_EPS = 1e-4


def rasterize_reference(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Composite one camera. Shapes: means2d [N,2], conics [N,3], colors [N,D], opacities [N],
    depths [N], radii [N,2], background [D]. Returns colours [H,W,D] and alphas [H,W,1]."""
    D = colors.shape[-1]
    visible = (radii > 0).all(dim=-1)
    idx = torch.nonzero(visible).squeeze(-1)
    idx = idx[torch.argsort(depths.detach()[idx], stable=True)]
    m, q, c, o = means2d[idx], conics[idx], colors[idx], opacities[idx]

    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means2d.dtype, device=means2d.device) + 0.5,
        torch.arange(width, dtype=means2d.dtype, device=means2d.device) + 0.5,
        indexing="ij",
    )
    px = xs.reshape(-1, 1)
    py = ys.reshape(-1, 1)
    dx = m[None, :, 0] - px  # [P, M]
    dy = m[None, :, 1] - py
    sigma = 0.5 * (q[None, :, 0] * dx * dx + q[None, :, 2] * dy * dy) + q[None, :, 1] * dx * dy
    alpha = torch.clamp(o[None, :] * torch.exp(-sigma), max=MAX_ALPHA)
    with torch.no_grad():
        keep = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        t_incl = torch.cumprod(1.0 - alpha, dim=-1)
        alive = t_incl > T_EPS  # a Gaussian is composited only if the pixel stays above 1e-4
    alpha = torch.where(alive, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    t_excl = torch.cumprod(torch.cat([torch.ones_like(one_minus[:, :1]), one_minus[:, :-1]], dim=-1), dim=-1)
    weights = alpha * t_excl  # [P, M]
    out = weights @ c  # [P, D]
    t_final = torch.prod(one_minus, dim=-1, keepdim=True)  # [P, 1]
    if background is not None:
        out = out + t_final * background[None, :]
    return out.reshape(height, width, D), (1.0 - t_final).reshape(height, width, 1)


def rasterize_reference_batch(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    backgrounds: Tensor | None = None,
    absgrad: bool = False,
) -> tuple[Tensor, Tensor]:
    """Same call as the C++ backend's ``rasterize_cpu`` (C cameras); ``absgrad`` is not supported."""
    if absgrad:
        raise NotImplementedError("the reference rasterizer does not compute absgrad")
    outs = [
        rasterize_reference(
            means2d[c], conics[c], colors[c], opacities[c] if opacities.dim() == 2 else opacities, depths[c], radii[c],
            width, height,
            None if backgrounds is None else backgrounds[c],
        )
        for c in range(means2d.shape[0])
    ]
    return torch.stack([o[0] for o in outs]), torch.stack([o[1] for o in outs])


def render_reference(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    sh_degree: int | None = None,
    backgrounds: Tensor | None = None,
    render_mode: str = "RGB",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = EPS2D,
    rasterize_mode: str = "classic",
) -> tuple[Tensor, Tensor, dict]:
    """``render()`` with the dense torch rasterizer (any dtype, autograd gradients)."""
    from . import render_with

    return render_with(
        rasterize_reference_batch, means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        sh_degree, backgrounds, render_mode, False, near_plane, far_plane, backend_name="reference", eps2d=eps2d,
        rasterize_mode=rasterize_mode,
    )
