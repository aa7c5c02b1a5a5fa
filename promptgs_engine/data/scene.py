"""`Camera` and `Scene`: the engine's view of a dataset (see docs/interfaces.md)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import torch

from .images import load_image_tensor


@dataclass(eq=False)
class Camera:
    """One posed pinhole view.

    `K` is for `width` x `height` with COLMAP's pixel convention (pixel centres at
    integer + 0.5); `world_to_camera` maps dataset world to camera coordinates
    (x right, y down, z forward). Images are read lazily through a shared LRU cache.
    """

    name: str
    width: int
    height: int
    K: torch.Tensor
    world_to_camera: torch.Tensor
    image_path: Path
    downscale: int = 1  # factor this camera already is below the image file's resolution

    def load_image(
        self,
        downscale: int = 1,
        window: tuple[int, int, int, int] | None = None,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """[height // downscale, width // downscale, 3] float32 in [0, 1] (box-filtered);
        ``window`` (x0, y0, width, height) takes a crop of it, ``device`` puts it on an
        accelerator with the same values (`images.load_image_tensor`)."""
        factor = self.downscale * int(downscale)
        size = (self.width // int(downscale), self.height // int(downscale))
        return load_image_tensor(self.image_path, factor, size, window=window, device=device)

    def downscaled(self, factor: int) -> "Camera":
        """The same view at size (width // factor, height // factor) with K divided by factor.

        `downscaled(f).load_image()` equals `load_image(f)`.
        """
        factor = int(factor)
        if factor < 1:
            raise ValueError(f"downscale factor must be >= 1, got {factor}")
        if factor == 1:
            return self
        K = self.K.clone()
        K[:2, :] /= factor
        return dataclasses.replace(
            self,
            width=self.width // factor,
            height=self.height // factor,
            K=K,
            downscale=self.downscale * factor,
        )

    @property
    def camera_to_world(self) -> torch.Tensor:
        """[4, 4] float32 inverse of `world_to_camera`."""
        return torch.linalg.inv(self.world_to_camera.double()).float()

    @property
    def center(self) -> torch.Tensor:
        """[3] camera centre in dataset world coordinates."""
        R = self.world_to_camera[:3, :3].double()
        t = self.world_to_camera[:3, 3].double()
        return (-R.T @ t).float()

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Pinhole projection of world ``points`` [N, 3]: ``(u, v, z)``, each [N]. ``u, v``
        are continuous pixel coordinates (pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)``),
        ``z`` the camera-space depth; points at ``z <= 0`` get meaningless ``u, v``."""
        w2c = self.world_to_camera.to(points.dtype)
        k = self.K.to(points.dtype)
        p = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        u = p[:, 0] / z.clamp_min(1e-6) * k[0, 0] + k[0, 2]
        v = p[:, 1] / z.clamp_min(1e-6) * k[1, 1] + k[1, 2]
        return u, v, z


@dataclass(eq=False)
class Scene:
    """A loaded dataset: cameras split into train/test, SfM points, scene radius."""

    train_cameras: list[Camera]
    test_cameras: list[Camera]
    points: torch.Tensor
    point_colors: torch.Tensor
    extent: float
    source: Path

    @property
    def cameras(self) -> list[Camera]:
        """All cameras, sorted by image name."""
        return sorted(self.train_cameras + self.test_cameras, key=lambda c: c.name)


def nerf_normalization_radius(cameras: list[Camera]) -> float:
    """1.1 x the largest distance of a camera centre from the mean centre (3DGS convention).

    Falls back to 1.0 when all centres coincide (a single camera).
    """
    if not cameras:
        return 1.0
    centers = torch.stack([c.center.double() for c in cameras])
    radius = float((centers - centers.mean(0)).norm(dim=1).max()) * 1.1
    return radius if radius > 1e-9 else 1.0
