"""CPU backend: the C++ tile rasterizer (csrc/) wrapped in a torch.autograd.Function."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from .projection import EPS2D


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


def _stack(tensors: list[Tensor]) -> Tensor:
    """``torch.stack``, without its copy for the one camera of a training step."""
    return tensors[0].unsqueeze(0) if len(tensors) == 1 else torch.stack(tensors)


class RasterizeCPU(torch.autograd.Function):
    """Composite C images from projected Gaussians.

    Inputs: means2d [C,N,2], conics [C,N,3], colors [C,N,D], opacities [N] or [C,N], depths [C,N]
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
        per_camera_opacity = opacities.dim() == 2
        shared_opac = None if per_camera_opacity else _f32(opacities)
        out_colors, out_alphas, saved = [], [], []
        for c in range(C):
            bg = _f32(backgrounds[c]) if backgrounds is not None else torch.empty(0)
            opac = _f32(opacities[c]) if per_camera_opacity else shared_opac
            img, alpha, *bins = _C.rasterize_forward(
                _f32(means2d[c]), _f32(conics[c]), _f32(colors[c]), opac, _f32(depths[c]), radii[c].contiguous(), bg,
                width, height,
            )
            out_colors.append(img)
            out_alphas.append(alpha)
            saved.append((bg, alpha, bins))
        ctx.saved_per_camera = saved
        ctx.width, ctx.height, ctx.absgrad = width, height, absgrad
        ctx.channels = colors.shape[-1]
        ctx.has_bg = backgrounds is not None
        ctx.per_camera_opacity = per_camera_opacity
        ctx.save_for_backward(means2d)
        # An output that no loss reaches (most often the alphas) gets None, not a zero image.
        ctx.set_materialize_grads(False)
        return _stack(out_colors), _stack(out_alphas)

    @staticmethod
    def backward(ctx: Any, grad_colors: Tensor | None, grad_alphas: Tensor | None):  # type: ignore[override]
        (means2d,) = ctx.saved_tensors
        _C = _ext()
        if grad_colors is None:
            grad_colors = means2d.new_zeros(len(ctx.saved_per_camera), ctx.height, ctx.width, ctx.channels)
        no_alpha_grad = torch.empty(0)  # the extension reads an empty tensor as zeros
        g_m, g_cn, g_col, g_op, g_abs, g_bg = [], [], [], [], [], []
        n = means2d.shape[-2]
        for c, (bg, alpha, bins) in enumerate(ctx.saved_per_camera):
            last_ids, *tiles = bins  # tile_offsets, tile_ids, tile_order, tile_rows, splats, sorted_colors
            gm, gcn, gcol, gop, gab = _C.rasterize_backward(
                n, bg, ctx.width, ctx.height, *tiles, alpha, last_ids,
                _f32(grad_colors[c]), no_alpha_grad if grad_alphas is None else _f32(grad_alphas[c]), ctx.absgrad,
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
            means2d.absgrad = _stack(g_abs).to(means2d.dtype)
        grad_bg = torch.stack(g_bg) if g_bg else None
        dtype = means2d.dtype
        return (
            _stack(g_m).to(dtype),
            _stack(g_cn).to(dtype),
            _stack(g_col).to(dtype),
            (torch.stack(g_op) if ctx.per_camera_opacity else torch.stack(g_op).sum(0)).to(dtype),
            None,
            None,
            grad_bg,
            None,
            None,
            None,
        )


class ProjectCPU(torch.autograd.Function):
    """EWA projection (and SH colours) in C++ for C cameras.

    Inputs: means [N,3], quats [N,4], scales [N,3], opacities [N], sh [N,K,3] or None (or
    [N,1,3] with ``sh_rest`` [N,K-1,3], the other coefficients, read where they are instead of
    concatenated), viewmats [C,4,4], Ks [C,3,3]. Outputs: means2d [C,N,2], conics [C,N,3],
    depths [C,N], radii [C,N,2] int32 (no gradient), colors [C,N,3] (an empty tensor without
    SH). Gradients flow to means, quats, scales, sh and sh_rest; opacities only set the radii.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        sh: Tensor | None,
        sh_rest: Tensor | None,
        viewmats: Tensor,
        Ks: Tensor,
        width: int,
        height: int,
        sh_degree: int,
        near_plane: float,
        far_plane: float,
        eps2d: float,
    ):
        _C = _ext()
        inputs = (_f32(means), _f32(quats), _f32(scales), _f32(opacities), _f32(sh) if sh is not None else torch.empty(0))
        cams = (_f32(viewmats), _f32(Ks))
        rest = _f32(sh_rest) if sh is not None and sh_rest is not None and sh_rest.numel() else torch.empty(0)
        means2d, conics, depths, radii, colors = _C.project_forward(
            *inputs, sh_degree, *cams, width, height, near_plane, far_plane, eps2d, rest
        )
        ctx.inputs, ctx.cams, ctx.has_sh, ctx.rest = inputs, cams, sh is not None, rest
        ctx.rest_shape = None if sh_rest is None else sh_rest.shape
        ctx.args = (sh_degree, width, height, near_plane, far_plane, eps2d)
        ctx.save_for_backward(radii)
        ctx.mark_non_differentiable(radii)
        ctx.dtype = means.dtype
        return means2d, conics, depths, radii, colors

    @staticmethod
    def backward(ctx: Any, v_means2d, v_conics, v_depths, _v_radii, v_colors):  # type: ignore[override]
        (radii,) = ctx.saved_tensors
        _C = _ext()
        sh_degree, width, height, near_plane, far_plane, eps2d = ctx.args
        vc = _f32(v_colors) if ctx.has_sh and v_colors is not None and v_colors.numel() else torch.empty(0)
        # The C++ pass sums the cameras' gradients, camera by camera.
        totals = _C.project_backward(
            *ctx.inputs, sh_degree, *ctx.cams, width, height, near_plane, far_plane, eps2d, radii,
            _f32(v_means2d), _f32(v_conics), _f32(v_depths), vc, ctx.rest,
        )
        v_means, v_quats, v_scales, v_sh, v_rest = (t.to(ctx.dtype) for t in totals)
        if ctx.rest_shape is not None and not ctx.rest.numel():  # no coefficients past the first
            v_rest = torch.zeros(ctx.rest_shape, dtype=ctx.dtype)
        ctx.inputs = ctx.cams = ctx.rest = None
        return (v_means, v_quats, v_scales, None, v_sh if ctx.has_sh else None,
                v_rest if ctx.has_sh and ctx.rest_shape is not None else None,
                None, None, None, None, None, None, None, None)


def project_cpu(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    sh: Tensor | None = None,
    sh_degree: int = 0,
    eps2d: float = EPS2D,
    sh_rest: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """C++ projection; returns means2d, conics, depths, radii and SH colours [C,N,3] (None without sh).
    With ``sh_rest``, ``sh`` is the first SH coefficient [N,1,3] and ``sh_rest`` the others."""
    means2d, conics, depths, radii, colors = ProjectCPU.apply(
        means, quats, scales, opacities, sh, sh_rest, viewmats, Ks, width, height, sh_degree, near_plane, far_plane,
        eps2d,
    )
    return means2d, conics, depths, radii, (colors if sh is not None else None)


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
