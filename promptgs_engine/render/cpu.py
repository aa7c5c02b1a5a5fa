"""CPU backend: the C++ tile rasterizer (csrc/) wrapped in a torch.autograd.Function."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor


def _ext() -> Any:
    try:
        from promptgs_engine import _C
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError(
            "the C++ rasterizer promptgs_engine._C is not built; run "
            "`pip install --no-build-isolation -e .` (needs a C++17 compiler with OpenMP)"
        ) from exc
    return _C


def _f32(t: Tensor) -> Tensor:
    return t.detach().to(torch.float32).contiguous()


class RasterizeCPU(torch.autograd.Function):
    """Composite C images from projected Gaussians.

    Inputs: means2d [C,N,2], conics [C,N,3], colors [C,N,D], opacities [N], depths [C,N]
    (sort keys only, no gradient), radii [C,N,2] int32, backgrounds [C,D] or None.
    Outputs: colors [C,H,W,D], alphas [C,H,W,1].
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means2d: Tensor,
        conics: Tensor,
        colors: Tensor,
        opacities: Tensor,
        depths: Tensor,
        radii: Tensor,
        backgrounds: Tensor | None,
        width: int,
        height: int,
        absgrad: bool,
    ) -> tuple[Tensor, Tensor]:
        C = 1 if means2d.dim() == 2 else means2d.shape[0]
        _C = _ext()
        opac = _f32(opacities)
        out_colors, out_alphas, saved = [], [], []
        for c in range(C):
            bg = _f32(backgrounds[c]) if backgrounds is not None else torch.empty(0)
            args = (_f32(means2d[c]), _f32(conics[c]), _f32(colors[c]), opac, radii[c].contiguous(), bg)
            img, alpha, *bins = _C.rasterize_forward(
                args[0], args[1], args[2], opac, _f32(depths[c]), args[4], bg, width, height
            )
            out_colors.append(img)
            out_alphas.append(alpha)
            saved.append((args, alpha, bins))
        ctx.saved_per_camera = saved
        ctx.width, ctx.height, ctx.absgrad = width, height, absgrad
        ctx.has_bg = backgrounds is not None
        ctx.save_for_backward(means2d)
        return torch.stack(out_colors), torch.stack(out_alphas)

    @staticmethod
    def backward(ctx: Any, grad_colors: Tensor, grad_alphas: Tensor):  # type: ignore[override]
        (means2d,) = ctx.saved_tensors
        _C = _ext()
        g_m, g_cn, g_col, g_op, g_abs, g_bg = [], [], [], [], [], []
        for c, (args, alpha, bins) in enumerate(ctx.saved_per_camera):
            m2, cn, col, opac, radii, bg = args
            last_ids, tile_offsets, tile_ids, tile_order = bins
            gm, gcn, gcol, gop, gab = _C.rasterize_backward(
                m2, cn, col, opac, radii, bg, ctx.width, ctx.height, tile_offsets, tile_ids, tile_order, alpha, last_ids,
                _f32(grad_colors[c]), _f32(grad_alphas[c]), ctx.absgrad,
            )
            g_m.append(gm)
            g_cn.append(gcn)
            g_col.append(gcol)
            g_op.append(gop)
            g_abs.append(gab)
            if ctx.has_bg and ctx.needs_input_grad[6]:
                # d colour / d background = final transmittance = 1 - alpha
                g_bg.append(((1.0 - alpha) * grad_colors[c]).sum(dim=(0, 1)))
        ctx.saved_per_camera = None
        if ctx.absgrad:
            means2d.absgrad = torch.stack(g_abs).to(means2d.dtype)
        grad_bg = torch.stack(g_bg) if g_bg else None
        dtype = means2d.dtype
        return (
            torch.stack(g_m).to(dtype),
            torch.stack(g_cn).to(dtype),
            torch.stack(g_col).to(dtype),
            torch.stack(g_op).sum(0).to(dtype),
            None,
            None,
            grad_bg,
            None,
            None,
            None,
        )


def rasterize_cpu(
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
    """Rasterize C cameras with the C++ backend; see :class:`RasterizeCPU` for shapes."""
    return RasterizeCPU.apply(means2d, conics, colors, opacities, depths, radii, backgrounds, width, height, absgrad)
