"""Residual evidence: where a render misses something small and high-contrast that the
image has.

A tiny object (a drone of one or two pixels) that 3DGS lost is a small error in a big
image, so the summed loss does not find it. Its residual ``image − render`` is a compact
blob, though, while a badly fitted terrain leaves residual texture over a whole area. Per
view (all maps at one resolution):

* **Blob response** ``R``: the residual is filtered per channel with a difference of
  Gaussians (centre ``σ``, surround ``3σ``) and ``R`` is the norm over the channels,
  divided by the filter's response to a one-pixel impulse, so a one-pixel object of
  contrast ``c`` gives ``R ≈ c``. Two scales (``σ = 0.7`` and ``1.6`` px by default)
  cover objects of 1 to about 10 pixels.
* **Normalised strength** ``S = R / max(local mean of R, floor)``: the local mean over a
  ``window`` × ``window`` neighbourhood is the reconstruction error around the pixel;
  where the render misses the texture of a whole area, every pixel there has a large
  ``R`` and none stands out. ``floor`` (the image's median ``R``, at least
  ``abs_floor``) keeps a perfectly fitted area from turning noise into strength.
  ``S`` is the larger over the scales.
* **Candidates**: local maxima of ``S`` (5 × 5) with ``S ≥ support_threshold`` and
  ``R ≥ min_contrast``, where the *image* has the blob (its own difference-of-Gaussians
  magnitude at the pixel is at least the render's): a floater that the render draws and
  the image lacks is not a missing object. Those of ``S ≥ threshold`` must also be
  *compact* (`_shape`: ``roundness ≥ min_roundness`` and ``extent ≤ max_extent``): a
  line the render misses (a seam, a cable) is a ridge, fires all along its length, and
  its points triangulate across views like an object's. Positions are refined to sub-pixel by the
  ``R``-weighted centroid of the 3 × 3 neighbourhood. The strongest ``max_candidates``
  are kept. Candidates of ``S ≥ threshold`` seed proposals; the weaker ones can only
  support a proposal that strong candidates of other views seeded.

Pixel convention as everywhere (docs/promptgs.md): pixel ``(i, j)`` has its centre at
``(i + 0.5, j + 0.5)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["ResidualSettings", "ViewEvidence", "residual_strength", "view_evidence"]

# Below this rendered opacity a pixel shows nothing (its depth is taken as infinite). The
# expected depth is divided by the opacity, so a faint surface early in training still
# tells where the render puts it.
MIN_DEPTH_ALPHA = 0.05


@dataclass(frozen=True)
class ResidualSettings:
    """Parameters of the per-view detector (see the module docstring)."""

    sigmas: tuple[float, ...] = (0.7, 1.6)  # centre widths of the difference of Gaussians, px
    surround: float = 3.0  # surround width = surround × centre width
    window: int = 31  # px: neighbourhood of the local reconstruction error
    abs_floor: float = 0.005  # lowest noise level (in units of R)
    threshold: float = 5.0  # strength of a candidate that seeds proposals (local-noise units)
    support_threshold: float = 3.0  # strength of a candidate that supports one
    min_contrast: float = 0.03  # R of a candidate (a one-pixel object of this contrast)
    min_roundness: float = 0.1  # smaller / larger principal curvature of a seeding blob
    max_extent: float = 0.3  # response 3σ + 1 px away along the blob's long axis / at its peak
    max_candidates: int = 512  # per view, strongest first


@dataclass
class ViewEvidence:
    """One view's residual evidence. ``uv`` are continuous pixel positions; ``strength``
    and ``contrast`` the candidates' ``S`` and ``R``; ``scale`` their DoG centre width
    (px); ``colour`` the image's colour at the candidate pixel. ``strength_map`` [H, W],
    ``image_blob`` [H, W] (the image's own blob response), ``depth`` [H, W] (the render's
    expected depth, inf where it shows nothing) and ``residual_map`` [H, W, 3] (the
    residual's response per channel at the scale of ``S``, whose norm is ``R``) are kept,
    in float16 (12 bytes a pixel), for the multi-view check."""

    uv: np.ndarray  # [K, 2] float64
    strength: np.ndarray  # [K]
    contrast: np.ndarray  # [K]
    scale: np.ndarray  # [K]
    colour: np.ndarray  # [K, 3]
    strength_map: np.ndarray = field(repr=False)  # [H, W] float16
    image_blob: np.ndarray = field(repr=False)  # [H, W] float16: the image's own blob response R
    depth: np.ndarray | None = field(default=None, repr=False)  # [H, W] float16 or None
    residual_map: np.ndarray | None = field(default=None, repr=False)  # [H, W, 3] float16: R's vector

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    def strength_at(self, uv: np.ndarray, radius: int = 1) -> np.ndarray:
        """The largest ``S`` within ``radius`` pixels of each position [N, 2] (0 outside the image)."""
        return _max_near(self.strength_map, uv, radius)

    def image_blob_at(self, uv: np.ndarray, radius: int = 1) -> np.ndarray:
        """The largest image blob response within ``radius`` pixels of each position [N, 2]."""
        return _max_near(self.image_blob, uv, radius)

    def residual_direction(self, k: int) -> np.ndarray:
        """[3] unit colour direction of the residual's response at candidate ``k``'s pixel
        (zeros without the map)."""
        if self.residual_map is None:
            return np.zeros(3)
        px, py = np.floor(self.uv[k]).astype(np.int64)
        vec = self.residual_map[py, px].astype(np.float64)
        return vec / max(float(np.linalg.norm(vec)), 1e-12)

    def response_along(self, uv: np.ndarray, direction: np.ndarray, min_contrast: float) -> np.ndarray:
        """The residual's strength along the colour ``direction`` [3] at the pixel of each
        position [N, 2]: the component of its response on that direction, in local-noise
        units as ``S`` (``S`` times the component over the response's norm), where that
        component is at least ``min_contrast``; 0 elsewhere, outside the image or without
        the map."""
        out = np.zeros(len(uv))
        if self.residual_map is None:
            return out
        px, py, ok = _pixels(uv, self.strength_map.shape)
        vec = self.residual_map[py[ok], px[ok]].astype(np.float64)
        along = vec @ np.asarray(direction, np.float64)
        norm = np.maximum(np.linalg.norm(vec, axis=1), 1e-12)
        strength = along / norm * self.strength_map[py[ok], px[ok]].astype(np.float64)
        out[ok] = np.where(along >= min_contrast, strength, 0.0)
        return out

    def depth_at(self, uv: np.ndarray) -> np.ndarray:
        """The render's depth at each position [N, 2] (inf outside the image or without depth)."""
        out = np.full(len(uv), np.inf)
        if self.depth is None:
            return out
        px, py, ok = _pixels(uv, self.depth.shape)
        out[ok] = self.depth[py[ok], px[ok]].astype(np.float64)
        return out


def _pixels(uv: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column, row and inside-the-image flag [N] of the pixel holding each position [N, 2]
    in an image of ``shape`` (H, W, ...)."""
    h, w = shape[:2]
    px = np.floor(uv[:, 0]).astype(np.int64)
    py = np.floor(uv[:, 1]).astype(np.int64)
    return px, py, (px >= 0) & (px < w) & (py >= 0) & (py < h)


def _max_near(image: np.ndarray, uv: np.ndarray, radius: int) -> np.ndarray:
    """The largest value of ``image`` [H, W] within ``radius`` pixels of each position
    [N, 2] (0 where the neighbourhood is outside the image)."""
    h, w = image.shape
    px = np.floor(uv[:, 0]).astype(np.int64)
    py = np.floor(uv[:, 1]).astype(np.int64)
    best = np.zeros(len(uv))
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            x, y = px + dx, py + dy
            ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
            best[ok] = np.maximum(best[ok], image[y[ok], x[ok]].astype(np.float64))
    return best


def _gaussian_kernel(sigma: float) -> torch.Tensor:
    radius = max(1, int(math.ceil(3.0 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of [C, H, W] (edges replicated): one depthwise convolution
    along the rows, one along the columns. (A matrix product over ``unfold`` windows did
    the same sums but ran one small parallel region per row; with the engine's passive
    OpenMP threads a 480×270 view's four blurs took about 0.5 s, against 20 ms now.)"""
    k = _gaussian_kernel(sigma).to(img.dtype)
    r = (k.numel() - 1) // 2
    c = img.shape[0]
    x = F.pad(img[None], (r, r, r, r), mode="replicate")
    x = F.conv2d(x, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(x, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)[0]


def _dog(img: torch.Tensor, sigma: float, surround: float) -> torch.Tensor:
    """Difference of Gaussians of [C, H, W], scaled so a one-pixel impulse gives 1 at its pixel."""
    gain = _centre_weight(sigma) - _centre_weight(sigma * surround)
    return (_blur(img, sigma) - _blur(img, sigma * surround)) / gain


def _centre_weight(sigma: float) -> float:
    """The centre value of the discrete 2D Gaussian kernel of width ``sigma``."""
    return float(_gaussian_kernel(sigma).max() ** 2)


def _norm(x: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the channels of [C, H, W]."""
    return (x * x).sum(dim=0).sqrt()


def _local_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean of [H, W] over a window × window neighbourhood (clipped at the edges), from
    running sums."""

    def box_rows(a: torch.Tensor) -> torch.Tensor:
        r = window // 2
        n = a.shape[-1]
        c = F.pad(a.double().cumsum(-1), (1, 0))
        hi = torch.clamp(torch.arange(n) + r + 1, max=n)
        lo = torch.clamp(torch.arange(n) - r, min=0)
        return (c[..., hi] - c[..., lo]) / (hi - lo).double()

    return box_rows(box_rows(x).transpose(0, 1)).transpose(0, 1).float()


def _shape(dog: torch.Tensor, sigma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pixel of a response [C, H, W] at DoG width ``sigma``: ``roundness``, the smaller
    over the larger absolute principal curvature of the response along its own colour
    direction at the pixel (3 × 3 finite differences; 0 where the curvatures differ in
    sign), and ``extent``, the larger response (along the same colour direction) at the two
    points ``3 sigma + 1`` pixels away along the direction of least curvature, over the
    response at the pixel. A compact object peaks like a dome, or an elongated dome (an
    oblique drone: roundness 0.1-0.5), and its response has faded at that distance; a
    line or an edge is a ridge, whose response runs on along it (extent near 1)."""
    d = F.pad(dog[None], (1, 1, 1, 1), mode="replicate")[0]
    c = d[:, 1:-1, 1:-1]
    h, w = c.shape[1:]
    n = c / _norm(c).clamp_min(1e-12)[None]

    def at(dy: int, dx: int) -> torch.Tensor:
        return (d[:, 1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] * n).sum(dim=0)

    f0 = (c * n).sum(dim=0)
    fxx = at(0, 1) - 2 * f0 + at(0, -1)
    fyy = at(1, 0) - 2 * f0 + at(-1, 0)
    fxy = (at(1, 1) - at(-1, 1) - at(1, -1) + at(-1, -1)) / 4
    half_tr = (fxx + fyy) / 2
    root = torch.sqrt(((fxx - fyy) / 2) ** 2 + fxy**2)
    big, small = half_tr.abs() + root, half_tr.abs() - root
    det = fxx * fyy - fxy**2
    roundness = torch.where(det > 0, small / big.clamp_min(1e-12), torch.zeros_like(det))
    # Direction of least curvature: the eigenvector of the eigenvalue nearer zero.
    lam = torch.where(half_tr >= 0, half_tr - root, half_tr + root)
    ex, ey = fxy, lam - fxx
    alt = (fxy.abs() < 1e-12) & ((lam - fxx).abs() < 1e-12)
    ex, ey = torch.where(alt, lam - fyy, ex), torch.where(alt, fxy, ey)
    norm = torch.sqrt(ex * ex + ey * ey).clamp_min(1e-12)
    ex, ey = ex / norm, ey / norm
    ex = torch.where(norm > 1e-12, ex, torch.ones_like(ex))
    reach = 3.0 * sigma + 1.0
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    far = torch.zeros_like(f0)
    for sign in (1.0, -1.0):
        gx = (xs + sign * reach * ex + 0.5) / w * 2 - 1
        gy = (ys + sign * reach * ey + 0.5) / h * 2 - 1
        grid = torch.stack([gx, gy], dim=-1)[None]
        sampled = F.grid_sample(dog[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
        far = torch.maximum(far, (sampled * n).sum(dim=0))
    return roundness, far / f0.clamp_min(1e-12)


def _as_chw(img: torch.Tensor) -> torch.Tensor:
    t = torch.as_tensor(img).detach().cpu().float()
    if t.dim() != 3 or t.shape[-1] not in (1, 3):
        raise ValueError(f"expected an image [H, W, 3], got shape {tuple(t.shape)}")
    return t.permute(2, 0, 1)


def residual_strength(image: torch.Tensor, render: torch.Tensor, settings: ResidualSettings = ResidualSettings()) -> dict[str, torch.Tensor]:
    """Per-pixel maps [H, W] of one view (``image`` and ``render`` [H, W, 3] in [0, 1]):
    ``strength`` (S), ``contrast`` (R of the residual), ``scale`` (the DoG centre width
    that gave S), ``residual`` [3, H, W] (the residual's response per channel at that
    scale; its norm is ``contrast``), ``image_blob`` (R of the image itself, at that scale), ``roundness``
    and ``extent`` (of the residual's response at that scale, `_shape`) and ``image_has_it``
    (the image's blob response at the pixel is at least the render's)."""
    gt, ren = _as_chw(image), _as_chw(render)
    if gt.shape != ren.shape:
        raise ValueError(f"image {tuple(gt.shape)} and render {tuple(ren.shape)} differ in size")
    both = torch.cat([gt, ren])  # [6, H, W]: one blur per width for image and render
    best: dict[str, torch.Tensor] = {}
    for sigma in settings.sigmas:
        dog = _dog(both, sigma, settings.surround)
        dog_gt, dog_ren = dog[:3], dog[3:]
        r = _norm(dog_gt - dog_ren)  # the residual's response (the filter is linear)
        floor = max(settings.abs_floor, float(r.median()))
        s = r / _local_mean(r, settings.window).clamp_min(floor)
        own = _norm(dog_gt)
        maps = {
            "strength": s, "contrast": r, "scale": torch.full_like(s, sigma), "image_blob": own,
            "residual": dog_gt - dog_ren,
            **dict(zip(("roundness", "extent"), _shape(dog_gt - dog_ren, sigma))),
            "image_has_it": (own >= _norm(dog_ren)).float(),
        }
        if not best:
            best = maps
        else:
            better = s > best["strength"]
            best = {k: torch.where(better, maps[k], best[k]) for k in best}
    best["image_has_it"] = best["image_has_it"] > 0.5
    return best


def view_evidence(
    image: torch.Tensor,
    render: torch.Tensor,
    depth: torch.Tensor | None = None,
    alpha: torch.Tensor | None = None,
    settings: ResidualSettings = ResidualSettings(),
) -> ViewEvidence:
    """Candidates of one view (see the module docstring). ``image`` and ``render`` are
    [H, W, 3]; ``depth`` [H, W] is the render's expected depth and ``alpha`` [H, W] its
    opacity (depth counts only where alpha ≥ MIN_DEPTH_ALPHA), both optional."""
    maps = residual_strength(image, render, settings)
    s, r, scale, has_it = maps["strength"], maps["contrast"], maps["scale"], maps["image_has_it"]
    h, w = s.shape
    peak = F.max_pool2d(s[None, None], 5, stride=1, padding=2)[0, 0]
    keep = (s >= peak) & (s >= settings.support_threshold) & (r >= settings.min_contrast) & has_it
    compact = (maps["roundness"] >= settings.min_roundness) & (maps["extent"] <= settings.max_extent)
    keep &= compact | (s < settings.threshold)  # only compact blobs seed
    ys, xs = torch.nonzero(keep, as_tuple=True)
    order = torch.argsort(s[ys, xs], descending=True)[: settings.max_candidates]
    ys, xs = ys[order], xs[order]
    # Sub-pixel position: R-weighted centroid of the 3 × 3 neighbourhood.
    rp = F.pad(r[None, None], (1, 1, 1, 1))[0, 0]
    offs = torch.tensor([-1.0, 0.0, 1.0])
    patch = torch.stack([rp[ys + 1 + dy, xs + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], dim=1).view(-1, 3, 3)
    total = patch.sum(dim=(1, 2)).clamp_min(1e-12)
    du = (patch.sum(dim=1) * offs).sum(dim=1) / total
    dv = (patch.sum(dim=2) * offs).sum(dim=1) / total
    uv = torch.stack([xs.float() + 0.5 + du, ys.float() + 0.5 + dv], dim=1)
    gt = torch.as_tensor(image).detach().cpu().float()
    depth_map = None
    if depth is not None:
        d = torch.as_tensor(depth).detach().cpu().float().reshape(h, w)
        bad = ~torch.isfinite(d) | (d <= 0)
        if alpha is not None:
            bad |= torch.as_tensor(alpha).detach().cpu().float().reshape(h, w) < MIN_DEPTH_ALPHA
        depth_map = torch.where(bad, torch.full_like(d, float("inf")), d).numpy().astype(np.float16)
    return ViewEvidence(
        uv=uv.double().numpy(),
        strength=s[ys, xs].double().numpy(),
        contrast=r[ys, xs].double().numpy(),
        scale=scale[ys, xs].double().numpy(),
        colour=gt[ys, xs].double().numpy().reshape(-1, 3),
        strength_map=s.clamp(max=60000).numpy().astype(np.float16),
        image_blob=maps["image_blob"].clamp(max=60000).numpy().astype(np.float16),
        depth=depth_map,
        residual_map=maps["residual"].clamp(-60000, 60000).permute(1, 2, 0).numpy().astype(np.float16),
    )


def evidence_counts(evidence: Sequence[ViewEvidence]) -> list[int]:
    """Number of candidates per view (for logs and reports)."""
    return [len(e) for e in evidence]
