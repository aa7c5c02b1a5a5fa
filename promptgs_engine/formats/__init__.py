"""Gaussian splat files in and out: the standard 3DGS PLY, SPZ and glTF (``KHR_gaussian_splatting``).

``load_gaussians(path)`` reads any of ``.ply``, ``.spz``, ``.gltf``, ``.glb`` into the
engine's parameters; ``save_gaussians(path, gaussians, format)`` writes one. Every format
holds the Gaussians in the dataset's world coordinates read as Blender's right-handed
+Z-up frame, where Blender's own PLY importer puts our PLY; SPZ and glTF store them +Y up
as their readers expect (frames.py), so Blender's SPZ and glTF importers show the same
Gaussians as its PLY importer. Conventions and losses per format: spz.py, gltf.py.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from ..errors import PromptGSError
from ..gaussians import load_ply, save_ply
from .splats import Splats

FORMATS = ("ply", "spz", "gltf")
SUFFIXES = {".ply": "ply", ".spz": "spz", ".glb": "gltf", ".gltf": "gltf"}
DEFAULT_SUFFIX = {"ply": ".ply", "spz": ".spz", "gltf": ".glb"}
EXPORT_NAMES = ("point_cloud.spz", "point_cloud.glb")  # what `train --export` writes beside point_cloud.ply
# SPZ's SH codes keep all 8 bits by default (Niantic's library keeps 5 for degree 1 and
# 4 above): the test-view PSNR a model loses stays within 0.2 dB at SH degree 3
# (benchmarks/formats.py). Coarser codes give smaller files.
SPZ_SH_BITS = (8, 8)


def format_of(path: str | Path) -> str:
    """The format a file name asks for: ``ply``, ``spz`` or ``gltf`` (``.gltf``/``.glb``)."""
    suffix = Path(path).suffix.lower()
    if suffix not in SUFFIXES:
        raise PromptGSError(f"{path}: unknown Gaussian file type {suffix or '(no suffix)'!r} (use .ply, .spz, .gltf or .glb)")
    return SUFFIXES[suffix]


def read_splats(path: str | Path) -> Splats:
    """The Gaussians of a PLY, SPZ or glTF file as arrays (formats.splats.Splats)."""
    path = Path(path)
    kind = format_of(path)
    if not path.is_file():
        raise PromptGSError(f"{path}: no such file")
    if kind == "ply":
        return Splats.from_params(load_ply(path))
    if kind == "spz":
        from .spz import read_spz

        return read_spz(path)
    from .gltf import read_gltf

    return read_gltf(path)


def load_gaussians(path: str | Path, sh_degree: int | None = None) -> torch.nn.ParameterDict:
    """The engine's parameters (gaussians.py) from a PLY, SPZ or glTF file; with
    ``sh_degree``, SH cut or zero-padded to that degree."""
    splats = read_splats(path)
    if splats.n == 0:
        raise PromptGSError(f"{path}: the file holds no Gaussians")
    if sh_degree is not None:
        splats = splats.with_sh_degree(sh_degree)
    return splats.to_params()


def save_gaussians(
    path: str | Path,
    gaussians: torch.nn.ParameterDict | dict | Splats,
    format: str | None = None,
    sh_degree: int | None = None,
    antialiased: bool = False,
    spz_version: int = 3,
    spz_sh_bits: tuple[int, int] = SPZ_SH_BITS,
) -> Path:
    """Write Gaussians (the engine's parameters, or Splats) as ``format`` (default: from
    the suffix) to ``path``, atomically; returns the path. ``sh_degree`` cuts (or pads) the
    SH; ``antialiased`` marks a model trained with Mip-Splatting's filter (SPZ's flag)."""
    path = Path(path)
    kind = format or format_of(path)
    if kind not in FORMATS:
        raise PromptGSError(f"unknown format {kind!r} (use {', '.join(FORMATS)})")
    splats = gaussians if isinstance(gaussians, Splats) else Splats.from_params(gaussians, antialiased=antialiased)
    if sh_degree is not None:
        if not 0 <= sh_degree <= 3:
            raise PromptGSError(f"--sh-degree must be 0..3, got {sh_degree}")
        splats = splats.with_sh_degree(sh_degree)
    if kind == "ply":
        save_ply(splats.to_params(), path)  # atomic itself
        return path
    tmp = path.with_name(path.name + ".tmp")
    if kind == "spz":
        from .spz import encode_spz

        tmp.write_bytes(encode_spz(splats, path, version=spz_version, sh_bits=spz_sh_bits))
    else:
        from .gltf import encode_gltf

        tmp.write_bytes(encode_gltf(splats, binary=path.suffix.lower() != ".gltf"))
    os.replace(tmp, path)
    return path


def export_formats(value: str | list | tuple | None) -> list[str]:
    """The formats of ``--export`` ("spz,gltf", or a job file's list), checked."""
    if value is None:
        return []
    names = value.split(",") if isinstance(value, str) else list(value)
    names = [str(name).strip().lower() for name in names if str(name).strip()]
    unknown = [name for name in names if name not in FORMATS]
    if unknown:
        raise PromptGSError(f"--export: unknown format {unknown[0]!r} (use {', '.join(FORMATS)}, comma-separated)")
    return list(dict.fromkeys(names))


def save_exports(params, ply_path: str | Path, formats: list[str], antialiased: bool = False) -> list[Path]:
    """Beside a run's PLY, the same Gaussians in each of ``formats`` (``point_cloud.spz``,
    ``point_cloud.glb``); the PLY itself is not rewritten."""
    ply_path = Path(ply_path)
    return [save_gaussians(ply_path.with_suffix(DEFAULT_SUFFIX[kind]), params, kind, antialiased=antialiased)
            for kind in formats if kind != "ply"]


def check_init(path: str | None) -> None:
    """An ``--init`` file must exist and be of a known type (read when training starts)."""
    if path is None:
        return
    format_of(path)
    if not Path(path).is_file():
        raise PromptGSError(f"{path}: --init file not found")
