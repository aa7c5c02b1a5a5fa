"""Readers we did not write: Blender 5.3's own importers on our SPZ and glTF files.

The same Gaussians are written as our PLY, SPZ (versions 3 and 4) and glTF (.glb and
.gltf); Blender 5.3 (the bpy 5.3.0 module, Python 3.13, in a subprocess:
tests/blender_scripts/splat_import.py) imports each with its own importer —
``wm.ply_import``, ``wm.spz_import``, the bundled glTF importer — and every attribute of
the SPZ and glTF imports must match the PLY import's within the format's quantisation:
glTF to float32 rounding, SPZ to half a step of each of its codes.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from blender_lines import LINES, BlenderLine, LineUnavailable, line_python

from promptgs_engine.formats import save_gaussians
from promptgs_engine.formats.spz import COLOR_SCALE
from promptgs_engine.gaussians import make_params, save_ply

pytestmark = [pytest.mark.blender, pytest.mark.slow]

SCRIPT = Path(__file__).resolve().parent / "blender_scripts" / "splat_import.py"
# The first Blender with Gaussian splat point clouds and SPZ and KHR_gaussian_splatting importers.
SPLAT_LINE = next((line for line in LINES if line.bpy.startswith("5.3.")), BlenderLine("5.3", "5.3.0", "3.13"))
N = 2000


def gaussians(seed: int = 0) -> torch.nn.ParameterDict:
    """Gaussians of SH degree 3 inside every SPZ code's range (no clamping): the check is of
    the readers' conventions, not of the format's range."""
    g = torch.Generator().manual_seed(seed)
    n = N
    means = torch.randn(n, 3, generator=g) * 3.0
    means[:10] *= 100.0  # some far away
    scales = torch.rand(n, 3, generator=g) * 6.0 - 7.0
    quats = torch.randn(n, 4, generator=g) * (torch.rand(n, 1, generator=g) + 0.5)  # not unit
    opacities = torch.randn(n, generator=g) * 2.0
    sh0 = torch.randn(n, 1, 3, generator=g) * 0.6
    shN = (torch.randn(n, 15, 3, generator=g) * 0.12).clamp(-0.3, 0.3)
    return make_params(means, scales, quats, opacities, sh0, shN)


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    try:
        python = line_python(SPLAT_LINE)
    except LineUnavailable as exc:
        pytest.skip(str(exc))
    except RuntimeError as exc:  # the wheel could not be installed (offline, no such version)
        pytest.skip(f"no bpy {SPLAT_LINE.bpy}: {exc}")
    tmp = tmp_path_factory.mktemp("splat-import")
    params = gaussians()
    files = {"ply": tmp / "model.ply", "spz3": tmp / "model3.spz", "spz4": tmp / "model4.spz",
             "glb": tmp / "model.glb", "gltf": tmp / "model.gltf"}
    save_ply(params, files["ply"])
    save_gaussians(files["spz3"], params, spz_version=3)
    save_gaussians(files["spz4"], params, spz_version=4)
    save_gaussians(files["glb"], params)
    save_gaussians(files["gltf"], params)
    config = {"files": [[name, str(path)] for name, path in files.items()], "out": str(tmp)}
    (tmp / "config.json").write_text(json.dumps(config))
    (tmp / "home").mkdir()
    done = subprocess.run([python, str(SCRIPT), str(tmp / "config.json"), str(tmp / "results.json")],
                          env=dict(os.environ, HOME=str(tmp / "home")), capture_output=True, text=True,
                          timeout=600, stdin=subprocess.DEVNULL)
    if not (tmp / "results.json").is_file():
        pytest.fail(f"Blender {SPLAT_LINE.name}: the script failed before any check:\n"
                    f"{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    results = json.loads((tmp / "results.json").read_text())
    for name, outcome in results.items():
        assert outcome["ok"], f"{name}: {outcome['error']}\n{outcome.get('traceback', '')}"
    return {name: dict(np.load(tmp / f"{name}.npz"), **results[name]) for name in files}


def sh_bands(values: dict) -> np.ndarray:
    return np.stack([values[f"radiance:sh_{i}"] for i in range(15)], axis=1).astype(np.float64)  # [N, 15, 3]


def unit(q: np.ndarray) -> np.ndarray:
    q = q.astype(np.float64) / np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)  # q and -q are one rotation


@pytest.mark.parametrize("name", ["ply", "spz3", "spz4", "glb", "gltf"])
def test_blender_imports_a_gaussian_splat_cloud(imported, name):
    info = imported[name]
    assert info["object_type"] == "POINTCLOUD" and info["cloud_type"] == "GAUSSIAN_SPLAT"
    assert info["n"] == N
    np.testing.assert_array_equal(info["matrix_world"], np.eye(4))
    assert {"position", "radiance:base", "scale", "rotation", "radiance:sh_14"} <= set(info["attributes"])


@pytest.mark.parametrize("name", ["glb", "gltf"])
def test_gltf_import_matches_the_ply_import(imported, name):
    ply, ours = imported["ply"], imported[name]
    np.testing.assert_array_equal(ours["position"], ply["position"])
    np.testing.assert_array_equal(ours["radiance:base"][:, :3], ply["radiance:base"][:, :3])  # SH DC
    np.testing.assert_allclose(ours["radiance:base"][:, 3], ply["radiance:base"][:, 3], rtol=0, atol=2e-7)  # opacity
    np.testing.assert_allclose(ours["scale"], ply["scale"], rtol=3e-7, atol=0)
    np.testing.assert_allclose(unit(ours["rotation"]), unit(ply["rotation"]), rtol=0, atol=3e-7)
    sh, sh_ply = sh_bands(ours), sh_bands(ply)
    np.testing.assert_array_equal(sh[:, :3], sh_ply[:, :3])  # degree 1: a signed permutation each way
    np.testing.assert_allclose(sh[:, 3:], sh_ply[:, 3:], rtol=0, atol=2e-7)  # degrees 2, 3: rotated there and back


@pytest.mark.parametrize("name", ["spz3", "spz4"])
def test_spz_import_matches_the_ply_import_within_its_codes(imported, name):
    ply, ours = imported["ply"], imported[name]
    far = np.abs(ply["position"]).max()
    step = 2.0 ** -int(np.clip(np.floor(23 - np.log2(far)), 0, 12))  # the file's fractional bits
    assert np.abs(ours["position"] - ply["position"]).max() <= step / 2 + 1e-6 * far
    assert np.abs(ours["radiance:base"][:, :3] - ply["radiance:base"][:, :3]).max() <= 0.5 / (COLOR_SCALE * 255) + 1e-5
    assert np.abs(ours["radiance:base"][:, 3] - ply["radiance:base"][:, 3]).max() <= 0.5 / 255 + 1e-6
    assert np.abs(np.log(ours["scale"] / ply["scale"])).max() <= 0.5 / 16 + 1e-5
    # Smallest-three quaternions: 9 bits of magnitude over [0, 1/√2] per component.
    assert np.abs(unit(ours["rotation"]) - unit(ply["rotation"])).max() <= 2.1 * (0.5**0.5 / 511)
    # SH: each code is within 1/256 in SPZ's frame; the rotation back keeps each band's norm.
    error = sh_bands(ours) - sh_bands(ply)
    for band in (1, 2, 3):
        rows = slice(band * band - 1, (band + 1) ** 2 - 1)
        norm = np.linalg.norm(error[:, rows, :], axis=1)
        assert norm.max() <= np.sqrt(2 * band + 1) / 256 + 1e-5, f"degree {band}"
