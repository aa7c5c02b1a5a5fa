"""Gaussian parameters, their initialisation from SfM points, and PLY files.

Parameters live in a ``torch.nn.ParameterDict`` with gsplat's names and activations so
that gsplat's strategies (``DefaultStrategy`` and ``gsplat.strategy.ops``) can edit them:

| key         | shape        | stored as                | activation          |
|-------------|--------------|--------------------------|---------------------|
| `means`     | [N, 3]       | dataset (COLMAP) world   | none                |
| `scales`    | [N, 3]       | log of the std-devs      | `exp`               |
| `quats`     | [N, 4]       | wxyz, unnormalised       | normalised in render|
| `opacities` | [N]          | logit                    | `sigmoid`           |
| `sh0`       | [N, 1, 3]    | SH DC coefficient        | see `sh_to_rgb`     |
| `shN`       | [N, K-1, 3]  | higher SH coefficients   |                     |

PLY files use the layout of the original 3DGS code (``x y z nx ny nz f_dc_0..2
f_rest_* opacity scale_0..2 rot_0..3``, f_rest channel-major), which every common 3DGS
viewer reads.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from .errors import PromptGSError

SH_C0 = 0.28209479177387814
PARAM_KEYS = ("means", "scales", "quats", "opacities", "sh0", "shN")


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    return sh0 * SH_C0 + 0.5


def nearest_neighbor_distance(points: torch.Tensor, k: int = 3, chunk: int = 4096, rms: bool = False) -> torch.Tensor:
    """Mean distance of each point to its ``k`` nearest other points, [N]; with ``rms``
    the root mean square of those distances (gsplat's simple_trainer initialisation)."""
    n = points.shape[0]
    k = min(k, max(n - 1, 1))
    out = torch.empty(n, dtype=points.dtype)
    for start in range(0, n, chunk):
        d = torch.cdist(points[start : start + chunk], points)
        # The smallest distance is the point itself (0); take the next k.
        nearest = d.topk(k + 1, dim=1, largest=False).values[:, 1:]
        out[start : start + chunk] = (nearest**2).mean(dim=1).sqrt() if rms else nearest.mean(dim=1)
    return out


def init_from_points(
    points: torch.Tensor,
    colors: torch.Tensor,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    init_scale: float = 1.0,
) -> torch.nn.ParameterDict:
    """Isotropic Gaussians at SfM points, sized by the distance to their neighbours."""
    if points.shape[0] == 0:
        raise PromptGSError("cannot initialise Gaussians: the point cloud is empty")
    points = points.float()
    n = points.shape[0]
    dist = nearest_neighbor_distance(points).clamp_min(1e-7) if n > 1 else torch.ones(1)
    scales = torch.log(dist * init_scale).unsqueeze(-1).repeat(1, 3)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    opacities = torch.logit(torch.full((n,), init_opacity))
    sh0 = rgb_to_sh(colors.float().clamp(0, 1)).unsqueeze(1)
    shN = torch.zeros(n, num_sh_bases(sh_degree) - 1, 3)
    return make_params(points, scales, quats, opacities, sh0, shN)


def make_params(means, scales, quats, opacities, sh0, shN) -> torch.nn.ParameterDict:
    tensors = dict(means=means, scales=scales, quats=quats, opacities=opacities, sh0=sh0, shN=shN)
    return torch.nn.ParameterDict(
        {k: torch.nn.Parameter(v.detach().float().contiguous()) for k, v in tensors.items()}
    )


def sh_degree_of(params: torch.nn.ParameterDict) -> int:
    return int(round(math.sqrt(params["shN"].shape[1] + 1))) - 1


def save_ply(params: torch.nn.ParameterDict, path: str | Path) -> None:
    """Write the Gaussians in the standard 3DGS PLY layout (atomically)."""
    path = Path(path)
    with torch.no_grad():
        means = params["means"].detach().cpu().numpy()
        n = means.shape[0]
        f_dc = params["sh0"].detach().cpu().reshape(n, 3).numpy()
        # 3DGS stores f_rest channel-major: all R coefficients, then G, then B.
        f_rest = params["shN"].detach().cpu().transpose(1, 2).reshape(n, -1).numpy()
        columns = {
            "x": means[:, 0], "y": means[:, 1], "z": means[:, 2],
            "nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n),
        }
        for i in range(3):
            columns[f"f_dc_{i}"] = f_dc[:, i]
        for i in range(f_rest.shape[1]):
            columns[f"f_rest_{i}"] = f_rest[:, i]
        columns["opacity"] = params["opacities"].detach().cpu().numpy()
        scales = params["scales"].detach().cpu().numpy()
        quats = params["quats"].detach().cpu().numpy()
        for i in range(3):
            columns[f"scale_{i}"] = scales[:, i]
        for i in range(4):
            columns[f"rot_{i}"] = quats[:, i]
    vertex = np.empty(n, dtype=[(name, "f4") for name in columns])
    for name, values in columns.items():
        vertex[name] = values
    tmp = path.with_suffix(path.suffix + ".tmp")
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(tmp))
    tmp.replace(path)


def load_ply(path: str | Path) -> torch.nn.ParameterDict:
    """Read Gaussians from a standard 3DGS PLY file."""
    path = Path(path)
    if not path.is_file():
        raise PromptGSError(f"{path}: no such PLY file")
    try:
        vertex = PlyData.read(str(path))["vertex"]
    except Exception as exc:  # plyfile raises several types for malformed files
        raise PromptGSError(f"{path}: not a readable PLY file ({exc})") from exc
    names = vertex.data.dtype.names
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    required += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    missing = [r for r in required if r not in names]
    if missing:
        raise PromptGSError(f"{path}: not a 3DGS PLY (missing properties {', '.join(missing)})")

    def cols(keys):
        return torch.from_numpy(np.stack([np.asarray(vertex[k], dtype=np.float32) for k in keys], 1))

    n = len(vertex.data)
    rest = sorted((k for k in names if k.startswith("f_rest_")), key=lambda k: int(k[7:]))
    if len(rest) % 3 != 0:
        raise PromptGSError(f"{path}: {len(rest)} f_rest properties is not a multiple of 3")
    k_rest = len(rest) // 3
    shN = cols(rest).reshape(n, 3, k_rest).transpose(1, 2) if rest else torch.zeros(n, 0, 3)
    return make_params(
        means=cols(["x", "y", "z"]),
        scales=cols([f"scale_{i}" for i in range(3)]),
        quats=cols([f"rot_{i}" for i in range(4)]),
        opacities=cols(["opacity"]).reshape(n),
        sh0=cols(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(n, 1, 3),
        shN=shN,
    )
