"""Far background points: a shell of points around the scene, coloured from the images.

SfM triangulates nothing in the sky (or any background too far for parallax), so 3DGS
must grow Gaussians there from the nearest geometry. Where few training views look, that
growth is uneven, and a novel view shows holes (the black render background) or dark
blotches. Starting a shell of Gaussians far outside the scene, in every direction some
training camera sees, gives the background its own Gaussians from step 0; where the
scene stands in front of the shell they are occluded and stay harmless.

The shell's Gaussians are as wide as its point spacing, which on a wide scene is over
3DGS's world-size pruning limit (a tenth of the scene scale) from the start. The trainer
marks them in the strategy state, and the strategies hold them to that limit as an angle
instead (`strategies.default.too_big`): under 3DGS's rule, every shell Gaussian not yet
split when size pruning began was removed, and the holes were the dark blotches again.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from .data import Camera

EXTRAPOLATE_DEGREES = 15.0  # unseen directions this close to a seen one are kept
SKY_RADIUS_FACTOR = 2.0  # shell radius: this times the distance of the farthest (95th percentile) SfM point


def fibonacci_directions(n: int) -> torch.Tensor:
    """[n, 3] unit vectors spread evenly over the sphere."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt((1.0 - z * z).clamp_min(0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1).float()


def sky_points(
    cameras: Sequence[Camera], scene_points: torch.Tensor, n_directions: int = 20_000, max_image_side: int = 256
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Points on a sphere around the cameras' centre that some training camera sees.

    Returns ``(points [M, 3], colors [M, 3] in [0, 1], radius)``: each point's colour is
    the median, over the cameras that see it, of the pixel it projects to (images read at
    most ``max_image_side`` pixels wide); ``radius`` is the shell's (the strategies' size
    limit for its Gaussians, `strategies.default.too_big`). The radius is
    ``SKY_RADIUS_FACTOR`` times the farther of the scene points' reach (95th percentile)
    and the cameras' from their mean centre.
    """
    centers = torch.stack([c.center.float() for c in cameras])
    origin = centers.mean(dim=0)
    reach = float(torch.quantile((scene_points.float() - origin).norm(dim=1), 0.95)) if scene_points.shape[0] else 0.0
    radius = SKY_RADIUS_FACTOR * max(reach, float((centers - origin).norm(dim=1).max()), 1e-3)
    dirs = fibonacci_directions(n_directions)
    points = origin + radius * dirs
    seen = torch.zeros(n_directions, dtype=torch.long)
    samples = []  # (direction indices, their pixel colours) per camera
    for cam in cameras:
        factor = max(1, math.ceil(max(cam.width, cam.height) / max_image_side))
        small = cam.downscaled(factor)
        img = small.load_image()  # [H, W, 3]
        u, v, z = small.project(points)
        inside = (z > 0) & (u >= 0) & (u < small.width) & (v >= 0) & (v < small.height)
        idx = torch.where(inside)[0]
        seen[idx] += 1
        samples.append((idx, img[v[idx].long(), u[idx].long()]))
    keep = seen > 0
    if not bool(keep.any()):
        return torch.zeros(0, 3), torch.zeros(0, 3), radius
    # Median colour per point over the cameras that see it.
    all_idx = torch.cat([i for i, _ in samples])
    all_col = torch.cat([c for _, c in samples])
    order = torch.argsort(all_idx, stable=True)
    all_idx, all_col = all_idx[order], all_col[order]
    counts = torch.bincount(all_idx, minlength=n_directions)
    starts = torch.cumsum(counts, 0) - counts
    colors = torch.zeros(n_directions, 3)
    for d in torch.where(keep)[0].tolist():
        s, c = int(starts[d]), int(counts[d])
        colors[d] = all_col[s : s + c].median(dim=0).values
    # Directions just beyond what any camera saw (a novel view tilted a little higher
    # than every training view) continue the nearest seen colour, rather than leaving a
    # hole that renders black.
    seen_ids = torch.where(keep)[0]
    unseen_ids = torch.where(~keep)[0]
    limit = math.cos(math.radians(EXTRAPOLATE_DEGREES))
    for start in range(0, unseen_ids.numel(), 1024):  # [1024, S] cosines at a time
        block = unseen_ids[start : start + 1024]
        best, nearest = (dirs[block] @ dirs[seen_ids].T).max(dim=1)
        near = best > limit
        colors[block[near]] = colors[seen_ids[nearest[near]]]
        keep[block[near]] = True
    return points[keep], colors[keep].clamp(0, 1), radius
