"""Gaussians as plain float32 arrays, the common form every file format reads and writes.

The arrays hold what the engine trains (gaussians.py): log scales, opacity logits, the
SH DC coefficient and the higher coefficients in the 3DGS order, in the engine's world
frame. Each format converts its own frame and activations on the way in and out.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from ..gaussians import make_params

# Activated opacities a reader turns back into logits are kept inside this margin of 0 and
# 1, so a fully transparent or opaque Gaussian gets a finite logit (±13.8).
OPACITY_EPS = 1e-6


@dataclass
class Splats:
    means: np.ndarray  # [N, 3] world
    scales: np.ndarray  # [N, 3] log of the standard deviations
    quats: np.ndarray  # [N, 4] w, x, y, z, not necessarily unit
    opacities: np.ndarray  # [N] logits
    sh0: np.ndarray  # [N, 3] SH DC coefficient (colour = 0.2821 sh0 + 0.5)
    sh_rest: np.ndarray  # [N, (degree+1)² - 1, 3] degree 1 onwards
    antialiased: bool = False  # trained with Mip-Splatting's 2D filter (SPZ's flag 0x1)

    @property
    def n(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh_rest.shape[1] + 1))) - 1

    @classmethod
    def from_params(cls, params, antialiased: bool = False) -> "Splats":
        """From the engine's parameters (a ParameterDict or a dict of tensors)."""

        def arr(key: str) -> np.ndarray:
            return np.ascontiguousarray(params[key].detach().cpu().float().numpy())

        n = params["means"].shape[0]
        return cls(
            means=arr("means"), scales=arr("scales"), quats=arr("quats"),
            opacities=arr("opacities").reshape(n), sh0=arr("sh0").reshape(n, 3),
            sh_rest=arr("shN").reshape(n, -1, 3), antialiased=antialiased,
        )

    def to_params(self) -> torch.nn.ParameterDict:
        t = torch.from_numpy
        return make_params(
            means=t(self.means), scales=t(self.scales), quats=t(self.quats), opacities=t(self.opacities),
            sh0=t(self.sh0).reshape(self.n, 1, 3), shN=t(self.sh_rest).reshape(self.n, -1, 3),
        )

    def with_sh_degree(self, degree: int) -> "Splats":
        """The same Gaussians with SH up to ``degree``: higher coefficients dropped, missing
        ones zero (a degree above the file's adds no colour)."""
        if not 0 <= degree <= 3:
            raise ValueError(f"SH degree must be 0..3, got {degree}")
        k = (degree + 1) ** 2 - 1
        rest = self.sh_rest[:, :k]
        if rest.shape[1] < k:
            rest = np.concatenate([rest, np.zeros((self.n, k - rest.shape[1], 3), np.float32)], axis=1)
        return replace(self, sh_rest=np.ascontiguousarray(rest, dtype=np.float32))


def sigmoid(logits: np.ndarray) -> np.ndarray:
    """Opacity from logits, computed in float64, float32 out."""
    return (1.0 / (1.0 + np.exp(-np.asarray(logits, dtype=np.float64)))).astype(np.float32)


def logit(opacity: np.ndarray) -> np.ndarray:
    """Logits from opacities, kept finite (OPACITY_EPS), computed in float64, float32 out."""
    p = np.clip(np.asarray(opacity, dtype=np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    return np.log(p / (1.0 - p)).astype(np.float32)
