"""EWA projection of 3D Gaussians to image-space ellipses (pure torch, differentiable).

Conventions follow 3DGS / gsplat (pinhole, unpacked):

- camera space is x right, y down, z forward; ``viewmats`` are world-to-camera;
- the 2D covariance is ``J W Σ Wᵀ Jᵀ + eps2d·I`` (the 0.3 low-pass dilation), where the
  Jacobian ``J`` is evaluated at the mean clamped to 1.3× the field of view;
- ``conics`` hold the inverse 2D covariance as ``(a, b, c)`` with
  ``Σ⁻¹ = [[a, b], [b, c]]``;
- the screen-space extent is the opacity-aware bounding box: the ellipse where
  ``opacity·exp(-½ dᵀΣ⁻¹d) = 1/255`` (at most 3.33 sigma), rounded up to whole pixels,
  so no pixel outside it can receive a visible contribution;
- ``radii`` are 0 for Gaussians that are culled: depth outside (near, far), a singular
  2D covariance, opacity below 1/255, or a bounding box outside the image.
"""

from __future__ import annotations

import torch
from torch import Tensor

ALPHA_THRESHOLD = 1.0 / 255.0
EPS2D = 0.3
MAX_EXTEND = 3.33


def quat_scale_to_covar(quats: Tensor, scales: Tensor) -> Tensor:
    """World-space covariances ``R S Sᵀ Rᵀ`` [N, 3, 3] from wxyz quaternions (any norm) and scales."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))
    M = R * scales[..., None, :]
    return M @ M.transpose(-1, -2)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = EPS2D,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Project N Gaussians into C pinhole cameras.

    Args:
        means [N, 3], quats [N, 4] (wxyz), scales [N, 3] (activated), opacities [N]
        (activated), viewmats [C, 4, 4] world-to-camera, Ks [C, 3, 3].

    Returns:
        means2d [C, N, 2] pixel coordinates (pixel centres at +0.5), conics [C, N, 3],
        depths [C, N] camera-space z, radii [C, N, 2] int32 (0 = culled).
        All but radii are differentiable with respect to the inputs.
    """
    covars = quat_scale_to_covar(quats, scales)  # [N, 3, 3]
    R = viewmats[:, :3, :3]  # [C, 3, 3]
    t = viewmats[:, :3, 3]  # [C, 3]
    means_c = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C, N, 3]
    covars_c = torch.einsum("cij,njk,clk->cnil", R, covars, R)  # [C, N, 3, 3]

    x, y, z = means_c.unbind(-1)
    depth_ok = (z > near_plane) & (z < far_plane)
    # Culled Gaussians get a harmless denominator so no inf/NaN reaches the gradients.
    zs = torch.where(depth_ok, z, torch.ones_like(z))

    fx = Ks[:, 0, 0, None]
    fy = Ks[:, 1, 1, None]
    cx = Ks[:, 0, 2, None]
    cy = Ks[:, 1, 2, None]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    tx = zs * torch.minimum(torch.maximum(x / zs, -lim_x_neg), lim_x_pos)
    ty = zs * torch.minimum(torch.maximum(y / zs, -lim_y_neg), lim_y_pos)

    zero = torch.zeros_like(zs)
    J = torch.stack(
        [fx / zs, zero, -fx * tx / (zs * zs), zero, fy / zs, -fy * ty / (zs * zs)], dim=-1
    ).reshape(zs.shape + (2, 3))
    cov2d = J @ covars_c @ J.transpose(-1, -2)  # [C, N, 2, 2]
    c00 = cov2d[..., 0, 0] + eps2d
    c01 = 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0])
    c11 = cov2d[..., 1, 1] + eps2d
    det = c00 * c11 - c01 * c01
    det_ok = det > 0
    det_safe = torch.where(det_ok, det, torch.ones_like(det))
    conics = torch.stack([c11 / det_safe, -c01 / det_safe, c00 / det_safe], dim=-1)

    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)

    with torch.no_grad():
        opac = opacities.detach().expand_as(z)
        opac_ok = opac >= ALPHA_THRESHOLD
        extend = torch.sqrt(2.0 * torch.log(opac.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
        extend = extend.clamp(max=MAX_EXTEND)
        rx = torch.ceil(extend * torch.sqrt(c00.detach().clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(c11.detach().clamp_min(0)))
        m = means2d.detach()
        inside = (
            (m[..., 0] + rx > 0)
            & (m[..., 0] - rx < width)
            & (m[..., 1] + ry > 0)
            & (m[..., 1] - ry < height)
        )
        valid = depth_ok & det_ok & opac_ok & inside & torch.isfinite(rx) & torch.isfinite(ry)
        radii = torch.stack([rx, ry], dim=-1)
        radii = torch.where(valid[..., None], radii, torch.zeros_like(radii)).to(torch.int32)

    return means2d, conics, z, radii


def filter_compensation(conics: Tensor, eps2d: float) -> Tensor:
    """Opacity factor that keeps a Gaussian's screen-space energy through the filter.

    ``sqrt(det Σ / det(Σ + eps2d·I))`` from the filtered ``conics`` [..., 3] (Mip-Splatting's
    2D filter, gsplat's ``rasterize_mode="antialiased"``): a Gaussian smaller than a pixel
    then covers the image in proportion to its projected area, as a real object does,
    instead of drawing a blob of the filter's size at full opacity from every distance.
    Differentiable; 0 where the unfiltered covariance is degenerate.
    """
    a, b, c = conics.unbind(-1)
    det_inv = a * c - b * b  # 1 / det(Σ + eps2d·I)
    det_inv_safe = torch.where(det_inv > 0, det_inv, torch.ones_like(det_inv))
    c00 = c / det_inv_safe - eps2d
    c11 = a / det_inv_safe - eps2d
    c01 = -b / det_inv_safe
    ratio = (c00 * c11 - c01 * c01) * det_inv_safe
    ok = (det_inv > 0) & (ratio > 1e-12)
    return torch.where(ok, torch.sqrt(torch.where(ok, ratio, torch.ones_like(ratio))), torch.zeros_like(ratio))


def camera_centers(viewmats: Tensor) -> Tensor:
    """Camera centres in world space [C, 3] from world-to-camera matrices [C, 4, 4]."""
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    return -(R.transpose(-1, -2) @ t[..., None])[..., 0]


__all__ = ["project_gaussians", "quat_scale_to_covar", "camera_centers", "filter_compensation", "ALPHA_THRESHOLD", "EPS2D"]
