"""CUDA backend: gsplat's rasterizer, called unpacked so ``info`` has the [C, N, ...] layout."""

from __future__ import annotations

from typing import Any

from torch import Tensor

from .projection import EPS2D


def render_cuda(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    sh_degree: int | None,
    backgrounds: Tensor | None,
    render_mode: str,
    absgrad: bool,
    near_plane: float,
    far_plane: float,
    eps2d: float = EPS2D,
    rasterize_mode: str = "classic",
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """gsplat.rasterization with the arguments the CPU backend mirrors."""
    from gsplat import rasterization

    out_colors, out_alphas, meta = rasterization(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        sh_degree=sh_degree,
        packed=False,
        backgrounds=backgrounds,
        render_mode=render_mode,
        absgrad=absgrad,
        rasterize_mode=rasterize_mode,
    )
    info = dict(meta)
    info["backend"] = "cuda"
    info.setdefault("n_cameras", viewmats.shape[0])
    return out_colors, out_alphas, info
