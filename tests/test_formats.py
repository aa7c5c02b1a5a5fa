"""SPZ and glTF (KHR_gaussian_splatting) in and out: frames, round trips, an independent SPZ
reader and writer (Niantic's C++ library inside the ``gaussforge`` wheel), bad input, and
the CLI (``promptgs export``, ``train --init/--export``, ``eval`` of a file)."""

from __future__ import annotations

import gzip
import json
import struct

import numpy as np
import pytest
import torch

from promptgs_engine.cli import main
from promptgs_engine.errors import PromptGSError
from promptgs_engine.formats import load_gaussians, read_splats, save_gaussians
from promptgs_engine.formats.frames import (
    Y_UP_TO_Z_UP, Z_UP_TO_Y_UP, permute_axes, rotate_points, rotate_quats, rotate_sh, rotation_to_quat,
)
from promptgs_engine.formats.spz import COLOR_SCALE
from promptgs_engine.formats.splats import Splats, sigmoid
from promptgs_engine.render.sh import eval_sh


def gaussians(n: int = 500, seed: int = 0, degree: int = 3) -> Splats:
    """Gaussians inside every SPZ code's range (the SH stay within ±1 in any frame)."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return Splats(
        means=(rng.normal(size=(n, 3)) * 4).astype(np.float32),
        scales=rng.uniform(-7, -1, size=(n, 3)).astype(np.float32),
        quats=(rng.normal(size=(n, 4)) * rng.uniform(0.5, 2, size=(n, 1))).astype(np.float32),
        opacities=(rng.normal(size=n) * 2).astype(np.float32),
        sh0=(rng.normal(size=(n, 3)) * 0.6).astype(np.float32),
        sh_rest=np.clip(rng.normal(size=(n, k, 3)) * 0.12, -0.3, 0.3).astype(np.float32),
    )


def unit(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def covariances(quats: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    w, x, y, z = unit(quats).T
    r = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    s = np.exp(2 * np.asarray(log_scales, dtype=np.float64))
    return np.einsum("nij,nj,nkj->nik", r, s, r)


def assert_within_spz_codes(
    original: Splats, decoded: Splats, sh_bits: tuple[int, int] = (8, 8), rounded_twice: bool = False
) -> None:
    """Every attribute within half a step of SPZ's code for it (in its own frame: the SH
    error's norm per band is kept by the rotation between frames). ``rounded_twice``: SH
    codes rounded to 1/128 before their multiple, as Niantic's library does (half a code more)."""
    reach = float(np.abs(original.means).max())
    bits = 12
    while reach * (1 << bits) > (1 << 23) - 1:
        bits -= 1
    assert np.abs(decoded.means - original.means).max() <= 0.5 ** (bits + 1) + 1e-6 * reach
    assert np.abs(decoded.sh0 - original.sh0).max() <= 0.5 / (COLOR_SCALE * 255) + 1e-5
    assert np.abs(sigmoid(decoded.opacities) - sigmoid(original.opacities)).max() <= 0.5 / 255 + 1e-6
    assert np.abs(decoded.scales - original.scales).max() <= 0.5 / 16 + 1e-5
    assert np.abs(unit(decoded.quats) - unit(original.quats)).max() <= 2.1 * (0.5**0.5 / 511)
    for band in range(1, original.sh_degree + 1):
        rows = slice(band * band - 1, (band + 1) ** 2 - 1)
        bucket = 2 ** (8 - sh_bits[0 if band == 1 else 1])  # codes of 1/128 on multiples of this
        half_step = (bucket / 2 + (0.5 if rounded_twice and bucket > 1 else 0.0)) / 128
        error = np.linalg.norm(decoded.sh_rest[:, rows] - original.sh_rest[:, rows], axis=1)
        assert error.max() <= np.sqrt(2 * band + 1) * half_step + 1e-5, f"SH degree {band}"


# -- frames ---------------------------------------------------------------------------


@pytest.mark.parametrize("rotation", ["z_up_to_y_up", "random"])
def test_rotated_sh_give_each_gaussian_its_colour_along_the_rotated_direction(rotation):
    rng = np.random.default_rng(1)
    if rotation == "random":
        q = rng.normal(size=4)
        w, x, y, z = q / np.linalg.norm(q)
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    else:
        r = Z_UP_TO_Y_UP
    coeffs = rng.normal(size=(50, 16, 3)).astype(np.float32)
    turned = coeffs.copy()
    turned[:, 1:] = rotate_sh(r, coeffs[:, 1:])
    dirs = rng.normal(size=(50, 3))
    before = eval_sh(3, torch.from_numpy(dirs), torch.from_numpy(coeffs.astype(np.float64)))
    after = eval_sh(3, torch.from_numpy(dirs @ r.T), torch.from_numpy(turned.astype(np.float64)))
    torch.testing.assert_close(after, before, rtol=0, atol=1e-5)
    back = rotate_sh(r.T, turned[:, 1:])
    np.testing.assert_allclose(back, coeffs[:, 1:], rtol=0, atol=1e-5)


def test_both_ways_of_turning_orientations_give_the_turned_covariance():
    g = gaussians(200)
    expected = np.einsum("ij,njk,lk->nil", Z_UP_TO_Y_UP, covariances(g.quats, g.scales), Z_UP_TO_Y_UP)
    size = np.abs(expected).max(axis=(1, 2))[:, None, None]  # float32 quaternions: relative to each Gaussian
    turned = rotate_quats(Z_UP_TO_Y_UP, g.quats)
    assert (np.abs(covariances(turned, g.scales) - expected) <= 1e-6 * size).all()
    quats, scales = permute_axes(Z_UP_TO_Y_UP, g.quats, g.scales)
    assert (np.abs(covariances(quats, scales) - expected) <= 1e-6 * size).all()
    np.testing.assert_allclose(rotation_to_quat(Z_UP_TO_Y_UP), [0.5**0.5, -(0.5**0.5), 0, 0], atol=1e-15)
    np.testing.assert_array_equal(rotate_points(Y_UP_TO_Z_UP, rotate_points(Z_UP_TO_Y_UP, g.means)), g.means)


# -- round trips ----------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_gltf_round_trip_keeps_the_floats(tmp_path, suffix):
    g = gaussians()
    path = save_gaussians(tmp_path / f"m{suffix}", g)
    back = read_splats(path)
    # Moves and negations only: bit for bit.
    np.testing.assert_array_equal(back.means, g.means)
    np.testing.assert_array_equal(back.sh0, g.sh0)
    np.testing.assert_array_equal(back.sh_rest[:, :3], g.sh_rest[:, :3])
    # The specification's forms (unit quaternion, linear scale, activated opacity) and the
    # rotation of degrees 2 and 3 to +Y up and back: float32 rounding.
    np.testing.assert_allclose(unit(back.quats), unit(g.quats), rtol=0, atol=2e-7)
    np.testing.assert_allclose(back.scales, g.scales, rtol=2e-7, atol=0)
    np.testing.assert_allclose(sigmoid(back.opacities), sigmoid(g.opacities), rtol=0, atol=6e-8)
    np.testing.assert_allclose(back.sh_rest[:, 3:], g.sh_rest[:, 3:], rtol=0, atol=2e-7)


def test_gltf_holds_the_extension_attributes_the_specification_names(tmp_path):
    g = gaussians(50, degree=2)
    doc = json.loads(save_gaussians(tmp_path / "m.gltf", g).read_text())
    assert doc["extensionsUsed"] == ["KHR_gaussian_splatting"]
    primitive = doc["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 0
    assert primitive["extensions"]["KHR_gaussian_splatting"] == {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}
    names = set(primitive["attributes"])
    expected = {"POSITION"} | {f"KHR_gaussian_splatting:{a}" for a in ("ROTATION", "SCALE", "OPACITY", "SH_DEGREE_0_COEF_0")}
    expected |= {f"KHR_gaussian_splatting:SH_DEGREE_{l}_COEF_{m}" for l in (1, 2) for m in range(2 * l + 1)}
    assert names == expected
    position = doc["accessors"][primitive["attributes"]["POSITION"]]
    assert position["componentType"] == 5126 and len(position["min"]) == 3  # glTF requires the bounds
    opacity = doc["accessors"][primitive["attributes"]["KHR_gaussian_splatting:OPACITY"]]
    assert opacity["type"] == "SCALAR"


@pytest.mark.parametrize("version", [3, 4])
@pytest.mark.parametrize("sh_bits", [(8, 8), (5, 4)])
def test_spz_round_trip_is_within_its_codes(tmp_path, version, sh_bits):
    g = gaussians()
    g.antialiased = True
    path = save_gaussians(tmp_path / "m.spz", g, spz_version=version, spz_sh_bits=sh_bits)
    assert path.read_bytes()[:2] == (b"\x1f\x8b" if version == 3 else b"NG")
    back = read_splats(path)
    assert back.antialiased and back.n == g.n and back.sh_degree == 3
    assert_within_spz_codes(g, back, sh_bits)


def test_spz_sh_codes_have_no_bias(tmp_path):
    """Coarser SH codes stay centred: rounding to 1/128 first and then to the multiple with
    ties up (Niantic's library) shifts every coefficient by half a code at 7 bits (+1/256)."""
    g = gaussians(2000)
    back = read_splats(save_gaussians(tmp_path / "m.spz", g, spz_sh_bits=(7, 7)))
    error = rotate_sh(Z_UP_TO_Y_UP, back.sh_rest).astype(np.float64) - rotate_sh(Z_UP_TO_Y_UP, g.sh_rest)
    assert abs(error.mean()) < 1e-4, error.mean()  # its spread: 1/128 / sqrt(3) over 90,000 values
    assert np.abs(error).max() <= 1 / 128 + 1e-6


def test_spz_far_gaussians_get_fewer_fractional_bits(tmp_path):
    g = gaussians(100)
    g.means[0] = [5000.0, -3000.0, 20.0]  # past 12 fractional bits' ±2048
    back = read_splats(save_gaussians(tmp_path / "far.spz", g))
    assert_within_spz_codes(g, back)
    assert np.abs(back.means[0] - g.means[0]).max() <= 2.0**-11


def test_sh_degree_is_cut_or_padded_and_ply_round_trip_is_exact(tmp_path):
    g = gaussians(100)
    for degree in (0, 1, 2):
        back = read_splats(save_gaussians(tmp_path / f"d{degree}.spz", g, sh_degree=degree))
        assert back.sh_degree == degree
    params = load_gaussians(save_gaussians(tmp_path / "d1.ply", g, sh_degree=1), sh_degree=3)
    assert params["shN"].shape == (100, 15, 3)
    np.testing.assert_array_equal(params["shN"][:, :3].detach().numpy(), g.sh_rest[:, :3])
    assert not params["shN"][:, 3:].any()
    exact = read_splats(save_gaussians(tmp_path / "all.ply", g))
    for key in ("means", "scales", "quats", "opacities", "sh0", "sh_rest"):
        np.testing.assert_array_equal(getattr(exact, key), getattr(g, key))


# -- Niantic's SPZ library (inside gaussforge), a reader and writer we did not write -----


def _gaussforge_arrays(data: bytes) -> dict[str, np.ndarray]:
    gaussforge = pytest.importorskip("gaussforge", reason="the independent SPZ reader: pip install gaussforge")
    result = gaussforge.GaussForge().read(data, "spz")
    assert "error" not in result, result
    ir = result["data"]
    n = ir["numPoints"]
    return {key: np.frombuffer(ir[key], dtype=np.float32).reshape(n, -1)
            for key in ("positions", "scales", "rotations", "alphas", "colors", "sh")}


@pytest.mark.parametrize("version", [3, 4])
def test_niantics_reader_decodes_our_spz_to_our_gaussians(tmp_path, version):
    g = gaussians()
    got = _gaussforge_arrays(save_gaussians(tmp_path / "m.spz", g, spz_version=version).read_bytes())
    # Its values are in SPZ's own frame (RUB); ours turned there by the rotation we write with.
    decoded = Splats(
        means=rotate_points(Y_UP_TO_Z_UP, got["positions"]), scales=got["scales"],
        quats=rotate_quats(Y_UP_TO_Z_UP, got["rotations"]),  # w, x, y, z (as in a PLY)
        opacities=got["alphas"].reshape(-1), sh0=got["colors"],
        sh_rest=rotate_sh(Y_UP_TO_Z_UP, got["sh"].reshape(g.n, -1, 3)),
    )
    assert_within_spz_codes(g, decoded)


@pytest.mark.parametrize("version", [3, 4])
def test_our_reader_decodes_niantics_spz(tmp_path, version):
    gaussforge = pytest.importorskip("gaussforge", reason="the independent SPZ writer: pip install gaussforge")
    g = gaussians()
    ply = tmp_path / "m.ply"
    save_gaussians(ply, g)
    result = gaussforge.GaussForge().convert(ply.read_bytes(), "ply", "spz", spz_version=version)
    assert "error" not in result, result
    spz = tmp_path / "theirs.spz"
    spz.write_bytes(result["data"])
    back = read_splats(spz)
    # gaussforge stores the PLY's values as they are, so they are SPZ-frame values; its SH
    # codes have Niantic's default precision (5 bits for degree 1, 4 above).
    in_spz_frame = Splats(
        means=rotate_points(Z_UP_TO_Y_UP, back.means), scales=back.scales,
        quats=rotate_quats(Z_UP_TO_Y_UP, back.quats), opacities=back.opacities, sh0=back.sh0,
        sh_rest=rotate_sh(Z_UP_TO_Y_UP, back.sh_rest),
    )
    assert_within_spz_codes(g, in_spz_frame, sh_bits=(5, 4), rounded_twice=True)


# -- bad input ------------------------------------------------------------------------


def _one_line_error(capsys, argv: list[str], *fragments: str) -> None:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("promptgs: error:") and "\n" not in err, err
    for fragment in fragments:
        assert fragment in err, err


@pytest.mark.parametrize("version", [3, 4])
def test_truncated_spz_is_one_line_naming_the_file(tmp_path, capsys, version):
    data = save_gaussians(tmp_path / "m.spz", gaussians(), spz_version=version).read_bytes()
    for cut in (len(data) // 2, 20, 3):
        bad = tmp_path / f"cut{cut}.spz"
        bad.write_bytes(data[:cut])
        with pytest.raises(PromptGSError, match="cut"):
            read_splats(bad)
        _one_line_error(capsys, ["export", str(bad), "--format", "ply"], str(bad))
    if version == 3:  # a whole gzip stream that holds too little
        raw = gzip.decompress(data)
        short = tmp_path / "short.spz"
        short.write_bytes(gzip.compress(raw[: len(raw) - 100]))
        with pytest.raises(PromptGSError, match="truncated SPZ: 500 Gaussians need"):
            read_splats(short)


def test_gltf_without_the_extension_is_one_line_naming_the_file(tmp_path, capsys):
    from pygltflib import GLTF2, Accessor, Attributes, Buffer, BufferView, Mesh, Node, Primitive, Scene

    points = np.zeros((4, 3), dtype="<f4")
    doc = GLTF2(scene=0, scenes=[Scene(nodes=[0])], nodes=[Node(mesh=0)],
                meshes=[Mesh(primitives=[Primitive(attributes=Attributes(POSITION=0), mode=0)])],
                accessors=[Accessor(bufferView=0, componentType=5126, count=4, type="VEC3", min=[0, 0, 0], max=[0, 0, 0])],
                bufferViews=[BufferView(buffer=0, byteLength=points.nbytes)], buffers=[Buffer(byteLength=points.nbytes)])
    doc.set_binary_blob(points.tobytes())
    plain = tmp_path / "points.glb"
    plain.write_bytes(b"".join(doc.save_to_bytes()))
    with pytest.raises(PromptGSError, match="without Gaussians"):
        read_splats(plain)
    _one_line_error(capsys, ["export", str(plain), "--format", "spz"], str(plain), "KHR_gaussian_splatting")
    good = save_gaussians(tmp_path / "m.glb", gaussians()).read_bytes()
    cut = tmp_path / "cut.glb"
    cut.write_bytes(good[: len(good) - 1000])
    _one_line_error(capsys, ["export", str(cut), "--format", "spz"], str(cut), "truncated")


def test_ply_without_3dgs_properties_is_one_line_naming_the_file(tmp_path, capsys):
    from plyfile import PlyData, PlyElement

    vertex = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1")])
    plain = tmp_path / "cloud.ply"
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(plain))
    _one_line_error(capsys, ["export", str(plain), "--format", "spz"], str(plain), "not a 3DGS PLY")
    _one_line_error(capsys, ["export", str(tmp_path / "model.obj"), "--format", "spz"], "no such run folder or file")
    (tmp_path / "model.obj").write_text("v 0 0 0\n")
    _one_line_error(capsys, ["export", str(tmp_path / "model.obj"), "--format", "spz"], "unknown Gaussian file type")


def test_spz_version_1_is_refused(tmp_path):
    data = gzip.decompress(save_gaussians(tmp_path / "m.spz", gaussians(10)).read_bytes())
    v1 = tmp_path / "v1.spz"
    v1.write_bytes(gzip.compress(data[:4] + struct.pack("<I", 1) + data[8:]))
    with pytest.raises(PromptGSError, match="version 1 is not supported"):
        read_splats(v1)


def _with_coordinate_system(data: bytes, value: int) -> bytes:
    """A version-4 file with an SPZ_ADOBE_coordinate_system record naming ``value``."""
    v4 = bytearray(data)
    record = struct.pack("<III", 0xADBE0003, 4, value)
    v4[14] |= 0x2  # flags: extensions
    struct.pack_into("<I", v4, 16, 32 + len(record))  # the TOC moves past the record
    return bytes(v4[:32]) + record + bytes(v4[32:])


def test_spz_coordinate_system_extension_names_the_stored_frame(tmp_path):
    """Values stored in RFU (Blender's frame, value 12) are the engine's own: a file that
    says so reads as those Gaussians; the same bytes without the record read as RUB."""
    g = gaussians(200)
    # Gaussians whose RUB form (what the writer stores) is g's values as they are.
    shifted = Splats(means=rotate_points(Y_UP_TO_Z_UP, g.means), scales=g.scales,
                     quats=rotate_quats(Y_UP_TO_Z_UP, g.quats), opacities=g.opacities, sh0=g.sh0,
                     sh_rest=rotate_sh(Y_UP_TO_Z_UP, g.sh_rest))
    data = save_gaussians(tmp_path / "plain.spz", shifted, spz_version=4).read_bytes()
    rfu = tmp_path / "rfu.spz"
    rfu.write_bytes(_with_coordinate_system(data, 12))
    assert_within_spz_codes(g, read_splats(rfu))
    assert_within_spz_codes(shifted, read_splats(tmp_path / "plain.spz"))
    lub = tmp_path / "lub.spz"
    lub.write_bytes(_with_coordinate_system(data, 3))
    with pytest.raises(PromptGSError, match="left-handed frame LUB"):
        read_splats(lub)


# -- the CLI and the trainer ----------------------------------------------------------


def test_export_eval_and_init_from_a_run(toy, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", str(toy), "--out", str(out), "--iterations", "30", "--quiet",
                 "--export", "spz,gltf"]) == 0
    assert (out / "point_cloud.spz").is_file() and (out / "point_cloud.glb").is_file()
    ply_metrics = json.loads((out / "metrics.json").read_text())

    capsys.readouterr()
    assert main(["export", str(out), "--format", "spz", "--sh-degree", "1", "--out", str(tmp_path / "d1.spz")]) == 0
    assert "Gaussians" in capsys.readouterr().out
    assert read_splats(tmp_path / "d1.spz").sh_degree == 1
    assert main(["export", str(out / "point_cloud.spz"), "--format", "ply", "--out", str(tmp_path / "back.ply")]) == 0
    _one_line_error(capsys, ["export", str(out), "--format", "ply"], "already ply")
    _one_line_error(capsys, ["export", str(out), "--format", "spz", "--out", str(tmp_path / "x.glb")], "does not fit")

    # eval of a file inside a run, and of any file with --gaussians: metrics.json untouched.
    capsys.readouterr()
    assert main(["eval", str(out / "point_cloud.glb"), "--quiet"]) == 0
    glb = json.loads(capsys.readouterr().out)
    assert glb["gaussians"].endswith("point_cloud.glb")
    assert abs(glb["psnr"] - ply_metrics["psnr"]) < 1e-4
    assert main(["eval", str(out), "--gaussians", str(out / "point_cloud.spz"), "--quiet"]) == 0
    spz = json.loads(capsys.readouterr().out)
    assert abs(spz["psnr"] - ply_metrics["psnr"]) < 0.2
    assert json.loads((out / "metrics.json").read_text()) == ply_metrics

    # Training from an SPZ starts with its Gaussians (and no sky shell).
    from promptgs_engine.config import TrainConfig
    from promptgs_engine.train import Trainer

    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "again"), init=str(out / "point_cloud.spz"), backend="cpu")
    trainer = Trainer(cfg, quiet=True)
    start = load_gaussians(out / "point_cloud.spz")
    assert trainer.n_sky_points == 0
    for key in start:
        torch.testing.assert_close(trainer.params[key].detach(), start[key].detach(), rtol=0, atol=0)
    assert main(["train", str(toy), "--out", str(tmp_path / "from_glb"), "--iterations", "10", "--quiet",
                 "--init", str(out / "point_cloud.glb")]) == 0
    from_glb = json.loads((tmp_path / "from_glb" / "train.json").read_text())
    assert from_glb["initial_gaussians"] == read_splats(out / "point_cloud.glb").n == ply_metrics["n_gaussians"]
    _one_line_error(capsys, ["train", str(toy), "--out", str(tmp_path / "x"), "--init", str(tmp_path / "none.spz")],
                    "none.spz", "not found")
    _one_line_error(capsys, ["train", str(toy), "--out", str(tmp_path / "x"), "--export", "spz,obj"], "'obj'")
    # A run trained again in the same folder without --export leaves no stale exports.
    assert main(["train", str(toy), "--out", str(out), "--iterations", "10", "--overwrite", "--quiet"]) == 0
    assert not (out / "point_cloud.spz").exists() and not (out / "point_cloud.glb").exists()
