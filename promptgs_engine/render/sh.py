"""Real spherical harmonics up to degree 3 with the 3DGS constants and sign conventions.

``sh_to_color`` matches what gsplat does before rasterizing: evaluate the SH for the
direction from the camera centre to each mean, add 0.5 and clamp at 0.
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_bases(degree: int, dirs: Tensor) -> Tensor:
    """SH basis values [..., (degree+1)²] at unit directions [..., 3]."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    out = [torch.full_like(dirs[..., 0], C0)]
    if degree >= 1:
        x, y, z = dirs.unbind(-1)
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Evaluate SH coefficients [..., K, 3] (K ≥ (degree+1)²) along directions [..., 3] (any norm)."""
    n = (degree + 1) ** 2
    if coeffs.shape[-2] < n:
        raise ValueError(f"sh_degree {degree} needs {n} coefficients per Gaussian, got {coeffs.shape[-2]}")
    d = torch.nn.functional.normalize(dirs, dim=-1)
    bases = sh_bases(degree, d)  # [..., n]
    return (bases[..., None] * coeffs[..., :n, :]).sum(dim=-2)


def sh_to_color(degree: int, means: Tensor, coeffs: Tensor, campos: Tensor) -> Tensor:
    """View-dependent colours [C, N, 3] for means [N, 3], coefficients [N, K, 3], camera centres [C, 3]."""
    dirs = means[None, :, :] - campos[:, None, :]
    rgb = eval_sh(degree, dirs, coeffs[None].expand(campos.shape[0], *coeffs.shape))
    return torch.clamp_min(rgb + 0.5, 0.0)
