"""One ``render()`` for all backends: the C++ CPU rasterizer and gsplat on CUDA.

The signature and outputs mirror ``gsplat.rasterization(..., packed=False)`` so the same
training and densification code (gsplat's ``DefaultStrategy`` included) drives both
backends; see docs/interfaces.md, section "Rendering".
"""

from __future__ import annotations

from typing import Any, Callable

import torch
from torch import Tensor

from ..errors import PromptGSError
from .projection import EPS2D, camera_centers, filter_compensation, project_gaussians
from .sh import sh_to_color

RENDER_MODES = ("RGB", "RGB+ED")
RASTERIZE_MODES = ("classic", "antialiased")
BACKENDS = ("auto", "cpu", "cuda")


class RenderBackendError(PromptGSError, RuntimeError):
    """The requested rendering backend cannot run here (no CUDA, tensors on the wrong device)."""


def resolve_backend(backend: str, device: torch.device | None = None) -> str:
    """The backend (``"cpu"`` or ``"cuda"``) that ``backend`` names here: the one place
    the engine decides it.

    With ``device``, the backend that renders tensors on that device (``auto`` follows the
    device). Without, the backend a run or a command asks for: ``auto`` is CUDA where
    torch sees a GPU, else the CPU.
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if backend == "auto":
        on_gpu = device.type == "cuda" if device is not None else True
        return "cuda" if on_gpu and torch.cuda.is_available() else "cpu"
    if backend == "cuda" and not torch.cuda.is_available():
        raise RenderBackendError("backend 'cuda' needs a CUDA GPU, but torch sees none (use --backend cpu)")
    if device is not None and backend == "cuda" and device.type != "cuda":
        raise RenderBackendError("backend 'cuda' needs the Gaussians and cameras on a CUDA device")
    if device is not None and backend == "cpu" and device.type != "cpu":
        raise RenderBackendError("backend 'cpu' needs the Gaussians and cameras on the CPU")
    return backend


def backend_device(backend: str) -> torch.device:
    """The device a run asking for ``backend`` keeps its Gaussians on (`resolve_backend`)."""
    return torch.device(resolve_backend(backend))


def on_backend_device(tensors: dict[str, Tensor], backend: str) -> dict[str, Tensor]:
    """``tensors`` (a model's Gaussians), detached, on the device ``backend`` renders on."""
    device = backend_device(backend)
    return {name: value.detach().to(device) for name, value in tensors.items()}


def render(
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
    absgrad: bool = False,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backend: str = "auto",
    eps2d: float = EPS2D,
    rasterize_mode: str = "classic",
    sh_rest: Tensor | None = None,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Render N Gaussians into C pinhole cameras.

    Args:
        means [N,3], quats [N,4] wxyz (any norm), scales [N,3] and opacities [N] activated;
        colors [N,K,3] SH coefficients when ``sh_degree`` is given, else [N,D] features;
        viewmats [C,4,4] world-to-camera; Ks [C,3,3]; backgrounds [C,D] or None.
        render_mode "RGB" or "RGB+ED" (expected depth appended as the last channel).
        eps2d: the screen-space filter, a variance in pixels² added to every projected
        covariance (gsplat's ``eps2d``; 3DGS uses 0.3).
        sh_rest: with ``sh_degree``, the SH coefficients after the first [N,K-1,3], ``colors``
        then holding the first [N,1,3]: the same as ``colors=torch.cat([colors, sh_rest], 1)``,
        which the CPU backend reads in place (no copy of the coefficients and of their
        gradients each step).
        rasterize_mode: "classic" (3DGS) or "antialiased": opacities are scaled by
        ``filter_compensation`` so the filter keeps each Gaussian's energy (gsplat's mode
        of the same name).

    Returns:
        colors [C,H,W,D(+1)], alphas [C,H,W,1], and ``info`` with ``means2d`` [C,N,2]
        (a non-leaf tensor: call ``retain_grad()`` before backward; ``.absgrad`` is set in
        backward when ``absgrad=True``), ``radii`` [C,N,2] int32 (0 = not visible),
        ``depths`` [C,N], ``conics``, ``width``, ``height``, ``n_cameras``,
        ``gaussian_ids`` (None) and ``backend``.
    """
    if render_mode not in RENDER_MODES:
        raise ValueError(f"unknown render_mode {render_mode!r}; choose one of {', '.join(RENDER_MODES)}")
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"unknown rasterize_mode {rasterize_mode!r}; choose one of {', '.join(RASTERIZE_MODES)}")
    name = resolve_backend(backend, means.device)
    if name == "cuda":
        from .cuda import render_cuda

        if sh_rest is not None:  # gsplat reads the coefficients as one tensor
            colors = torch.cat([colors, sh_rest], dim=1)
        return render_cuda(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height,
            sh_degree, backgrounds, render_mode, absgrad, near_plane, far_plane, eps2d, rasterize_mode,
        )
    from .cpu import rasterize_cpu

    return render_with(
        rasterize_cpu, means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        sh_degree, backgrounds, render_mode, absgrad, near_plane, far_plane, backend_name="cpu", eps2d=eps2d,
        rasterize_mode=rasterize_mode, sh_rest=sh_rest,
    )


def render_with(
    rasterize: Callable[..., tuple[Tensor, Tensor]],
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
    backend_name: str,
    eps2d: float = EPS2D,
    rasterize_mode: str = "classic",
    sh_rest: Tensor | None = None,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Projection + colour evaluation (C++ for the cpu backend, torch otherwise), then ``rasterize``.
    ``sh_rest`` as in ``render`` (cpu backend only; others get the coefficients concatenated)."""
    C = viewmats.shape[0]
    N = means.shape[0]
    if sh_rest is not None and (backend_name != "cpu" or sh_degree is None):
        colors, sh_rest = torch.cat([colors, sh_rest], dim=1), None
    if sh_degree is not None:
        if colors.dim() != 3 or colors.shape[0] != N or colors.shape[-1] != 3:
            raise ValueError(f"with sh_degree, colors must be [N, K, 3]; got {list(colors.shape)}")
        if sh_rest is not None and (colors.shape[1] != 1 or sh_rest.dim() != 3 or sh_rest.shape[0] != N
                                    or sh_rest.shape[-1] != 3):
            raise ValueError(f"with sh_rest, colors must be [N, 1, 3] and sh_rest [N, K-1, 3]; got "
                             f"{list(colors.shape)} and {list(sh_rest.shape)}")
        n_coefs = colors.shape[1] + (sh_rest.shape[1] if sh_rest is not None else 0)
        if not 0 <= sh_degree <= 3 or n_coefs < (sh_degree + 1) ** 2:
            raise ValueError(f"sh_degree {sh_degree} needs 0..3 and {(sh_degree + 1) ** 2} coefficients, got {n_coefs}")
    elif colors.dim() != 2 or colors.shape[0] != N:
        raise ValueError(f"without sh_degree, colors must be [N, D]; got {list(colors.shape)}")
    if backend_name == "cpu":
        # projection and SH in C++ (forward and backward)
        from .cpu import project_cpu

        means2d, conics, depths, radii, sh_colors = project_cpu(
            means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane,
            sh=colors if sh_degree is not None else None, sh_degree=sh_degree or 0, eps2d=eps2d, sh_rest=sh_rest,
        )
    else:
        means2d, conics, depths, radii = project_gaussians(
            means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d=eps2d
        )
        sh_colors = sh_to_color(sh_degree, means, colors, camera_centers(viewmats)) if sh_degree is not None else None
    if sh_colors is not None:
        feats = sh_colors  # [C, N, 3]
    else:
        feats = colors[None].expand(C, *colors.shape)
    if render_mode == "RGB+ED":
        feats = torch.cat([feats, depths[..., None]], dim=-1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, torch.zeros_like(backgrounds[:, :1])], dim=-1)
    if rasterize_mode == "antialiased":
        opacities = opacities[None] * filter_compensation(conics, eps2d)  # [C, N]
    out_colors, out_alphas = rasterize(
        means2d, conics, feats, opacities, depths, radii, width, height, backgrounds, absgrad
    )
    if render_mode == "RGB+ED":
        out_colors = torch.cat(
            [out_colors[..., :-1], out_colors[..., -1:] / out_alphas.clamp(min=1e-10)], dim=-1
        )
    info: dict[str, Any] = {
        "means2d": means2d,
        "radii": radii,
        "depths": depths,
        "conics": conics,
        "opacities": opacities,
        "width": width,
        "height": height,
        "n_cameras": C,
        "gaussian_ids": None,
        "camera_ids": None,
        "batch_ids": None,
        "backend": backend_name,
    }
    return out_colors, out_alphas, info


__all__ = ["render", "render_with", "resolve_backend", "backend_device", "on_backend_device", "RenderBackendError", "RENDER_MODES", "RASTERIZE_MODES", "BACKENDS"]
