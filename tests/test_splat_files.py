"""The add-on's 3DGS PLY reader and writer and its splat arithmetic (no bpy): files of
other trainers' layouts read as plyfile reads them, written back bit for bit, and the
transform that takes an edited object back to dataset coordinates."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from promptgs_blender import plyio, splats

plyfile = pytest.importorskip("plyfile")


def write_with_plyfile(path: Path, columns: dict[str, np.ndarray], text: bool = False, byte_order: str = "<",
                       dtype: str = "f4", faces: bool = False) -> None:
    table = np.empty(len(next(iter(columns.values()))), [(name, dtype) for name in columns])
    for name, values in columns.items():
        table[name] = values
    elements = [plyfile.PlyElement.describe(table, "vertex")]
    if faces:
        face = np.empty(2, [("vertex_indices", "i4", (3,))])
        face["vertex_indices"] = [[0, 1, 2], [1, 2, 3]]
        elements.append(plyfile.PlyElement.describe(face, "face"))
    plyfile.PlyData(elements, text=text, byte_order=byte_order).write(str(path))


def inria_columns(n: int, rng, degree: int, normals: bool = True, extra: tuple[str, ...] = ()) -> dict:
    """A vertex table in the layout of the Inria code / gsplat (normals as zeros or not)."""
    cols = {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.normal(size=n)}
    if normals:
        cols.update({"nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n)})
    cols.update({f"f_dc_{i}": rng.normal(size=n) for i in range(3)})
    cols.update({f"f_rest_{i}": 0.1 * rng.normal(size=n) for i in range(3 * splats.SH_COUNTS[degree])})
    cols["opacity"] = 4 * rng.normal(size=n)
    cols.update({f"scale_{i}": rng.normal(size=n) - 4 for i in range(3)})
    cols.update({f"rot_{i}": rng.normal(size=n) for i in range(4)})
    cols.update({name: rng.normal(size=n) for name in extra})
    return {name: values.astype(np.float32) for name, values in cols.items()}


@pytest.mark.parametrize("degree,normals,extra", [(0, True, ()), (3, True, ()), (1, False, ("filter_3D",)), (2, True, ())])
def test_other_trainers_ply_written_back_bit_for_bit(tmp_path, degree, normals, extra):
    cols = inria_columns(300, np.random.default_rng(degree), degree, normals, extra)
    write_with_plyfile(tmp_path / "in.ply", cols)
    g = plyio.read_splats(tmp_path / "in.ply")
    assert g.sh_degree == degree and len(g) == 300
    plyio.write_splats(tmp_path / "out.ply", g)
    back = plyfile.PlyData.read(str(tmp_path / "out.ply"))["vertex"].data
    assert list(back.dtype.names) == list(cols)  # every property, in the file's order
    for name, values in cols.items():
        assert back[name].dtype == np.float32
        np.testing.assert_array_equal(back[name].view(np.uint32), values.view(np.uint32), err_msg=name)


def test_conventions_of_blenders_importer(tmp_path):
    """Blender 5.3's ply_import_gsplat.cc: f_dc as stored, sigmoid opacity, exp scale,
    normalised wxyz rotation, radiance:sh_k = (f_rest_k, f_rest_{K+k}, f_rest_{2K+k})."""
    cols = inria_columns(200, np.random.default_rng(5), 3)
    write_with_plyfile(tmp_path / "in.ply", cols)
    g = plyio.read_splats(tmp_path / "in.ply")
    col = lambda *names: np.stack([cols[n].astype(np.float64) for n in names], 1)  # noqa: E731
    np.testing.assert_array_equal(g.f_dc, col("f_dc_0", "f_dc_1", "f_dc_2"))
    np.testing.assert_allclose(g.opacity, 1 / (1 + np.exp(-cols["opacity"].astype(np.float64))), rtol=1e-6)
    np.testing.assert_allclose(g.scale, np.exp(col("scale_0", "scale_1", "scale_2")), rtol=1e-6)
    rot = col("rot_0", "rot_1", "rot_2", "rot_3")
    np.testing.assert_allclose(g.rotation, rot / np.linalg.norm(rot, axis=1, keepdims=True), atol=1e-6)
    for k in (0, 7, 14):
        np.testing.assert_array_equal(g.f_rest[:, k], col(f"f_rest_{k}", f"f_rest_{15 + k}", f"f_rest_{30 + k}"))


def test_changed_values_written_from_the_activated_ones(tmp_path):
    cols = inria_columns(100, np.random.default_rng(1), 0)
    write_with_plyfile(tmp_path / "in.ply", cols)
    g = plyio.read_splats(tmp_path / "in.ply")
    g.opacity[:10] = 0.25
    g.scale[10:20] *= 2.0
    plyio.write_splats(tmp_path / "out.ply", g)
    back = plyio.read_vertices(tmp_path / "out.ply")
    np.testing.assert_allclose(back["opacity"][:10], np.log(0.25 / 0.75), atol=1e-6)
    np.testing.assert_array_equal(back["opacity"][10:], cols["opacity"][10:])
    np.testing.assert_allclose(back["scale_1"][10:20], cols["scale_1"][10:20] + np.log(2.0), atol=1e-5)
    np.testing.assert_array_equal(back["scale_1"][20:], cols["scale_1"][20:])


@pytest.mark.parametrize("form", ["ascii", "double", "big_endian", "with_faces"])
def test_other_ply_encodings_read_like_plyfile(tmp_path, form):
    cols = inria_columns(50, np.random.default_rng(2), 1)
    write_with_plyfile(tmp_path / "a.ply", cols, text=form == "ascii", byte_order=">" if form == "big_endian" else "<",
                       dtype="f8" if form == "double" else "f4", faces=form == "with_faces")
    g = plyio.read_splats(tmp_path / "a.ply")
    expected = plyfile.PlyData.read(str(tmp_path / "a.ply"))["vertex"].data
    np.testing.assert_array_equal(g.means, np.stack([expected[c] for c in "xyz"], 1).astype(np.float32))
    np.testing.assert_array_equal(g.f_rest[:, 2], np.stack([expected[f"f_rest_{2 + 3 * c}"] for c in range(3)], 1).astype(np.float32))
    np.testing.assert_array_equal(g.raw["opacity"], expected["opacity"].astype(np.float32))


def test_incomplete_sh_band_kept_as_properties(tmp_path):
    cols = inria_columns(20, np.random.default_rng(3), 0)
    cols.update({f"f_rest_{i}": np.full(20, i, np.float32) for i in range(5)})
    write_with_plyfile(tmp_path / "a.ply", cols)
    g = plyio.read_splats(tmp_path / "a.ply")
    assert g.sh_degree == 0 and {f"f_rest_{i}" for i in range(5)} <= set(g.extra)
    plyio.write_splats(tmp_path / "b.ply", g)
    np.testing.assert_array_equal(plyio.read_vertices(tmp_path / "b.ply")["f_rest_4"], 4)


def test_written_file_is_read_by_the_engine(tmp_path):
    gaussians = pytest.importorskip("promptgs_engine.gaussians")
    cols = inria_columns(64, np.random.default_rng(4), 3, normals=False)
    write_with_plyfile(tmp_path / "in.ply", cols)
    g = plyio.read_splats(tmp_path / "in.ply")
    plyio.write_splats(tmp_path / "out.ply", splats.subset(g, np.arange(64) % 2 == 0))
    params = gaussians.load_ply(tmp_path / "out.ply")
    assert params["means"].shape == (32, 3) and gaussians.sh_degree_of(params) == 3
    np.testing.assert_array_equal(params["opacities"].detach().numpy(), cols["opacity"][::2])
    np.testing.assert_array_equal(params["shN"].detach().numpy()[:, 4, 1], cols["f_rest_19"][::2])


def _rotation(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _covariances(g: splats.Splats) -> np.ndarray:
    w, x, y, z = g.rotation.astype(np.float64).T
    r = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)
    s = g.scale.astype(np.float64)
    return np.einsum("nij,nj,nkj->nik", r, s * s, r)


def test_transform_moves_shapes_and_turns_view_dependent_colour(tmp_path):
    cols = inria_columns(40, np.random.default_rng(6), 3)
    write_with_plyfile(tmp_path / "a.ply", cols)
    g = plyio.read_splats(tmp_path / "a.ply")
    assert splats.transformed(g, np.eye(4)) is g
    rot = _rotation([1.0, 2.0, -0.5], 0.7)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = 1.5 * rot, [0.3, -2.0, 1.0]
    t = splats.transformed(g, m)
    np.testing.assert_allclose(t.means, g.means @ (1.5 * rot).T + m[:3, 3], atol=1e-5)
    np.testing.assert_allclose(_covariances(t), 2.25 * np.einsum("ij,njk,lk->nil", rot, _covariances(g), rot), atol=1e-6)
    dirs = np.random.default_rng(7).normal(size=(30, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    before = np.einsum("mk,nkc->nmc", splats.sh_basis(dirs, 3), g.f_rest)
    after = np.einsum("mk,nkc->nmc", splats.sh_basis(dirs @ rot.T, 3), t.f_rest)  # seen along R d
    np.testing.assert_allclose(after, before, atol=1e-5)
    np.testing.assert_array_equal(t.raw["opacity"], g.raw["opacity"])
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="not a rotation"):
        splats.transformed(g, mirror)


def test_snapshot_form_becomes_blender_form():
    rng = np.random.default_rng(8)
    n = 30
    data = {"means": rng.normal(size=(n, 3)).astype(np.float32), "opacity": rng.uniform(size=n).astype(np.float32),
            "scale": rng.uniform(size=(n, 3)).astype(np.float32), "rotation": np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
            "color": rng.uniform(size=(n, 3)).astype(np.float32)}
    g = splats.from_snapshot(data)
    np.testing.assert_allclose(splats.rgb(g), data["color"], atol=1e-6)
    assert g.sh_degree == 0 and g.opacity is not data["opacity"]
    np.testing.assert_allclose(splats.logit(g.opacity), np.log(data["opacity"] / (1 - data["opacity"])), atol=1e-4)


@pytest.mark.parametrize("degree", [0, 3])
def test_gsplat_export_written_back_byte_for_byte(tmp_path, degree):
    """A PLY written by gsplat's own exporter (no normals, f_rest only when degree > 0)
    comes back out of the add-on's reader and writer with the same vertex bytes."""
    torch = pytest.importorskip("torch")
    exporter = pytest.importorskip("gsplat.exporter")
    g = torch.Generator().manual_seed(degree)
    n = 500
    k = splats.SH_COUNTS[degree]
    exporter.export_splats(means=torch.randn(n, 3, generator=g), scales=torch.randn(n, 3, generator=g) - 4,
                           quats=torch.randn(n, 4, generator=g), opacities=3 * torch.randn(n, generator=g),
                           sh0=torch.randn(n, 1, 3, generator=g), shN=0.1 * torch.randn(n, k, 3, generator=g),
                           format="ply", save_to=str(tmp_path / "gsplat.ply"))
    loaded = plyio.read_splats(tmp_path / "gsplat.ply")
    assert loaded.sh_degree == degree and not loaded.extra
    plyio.write_splats(tmp_path / "out.ply", loaded)
    source, written = (path.read_bytes() for path in (tmp_path / "gsplat.ply", tmp_path / "out.ply"))
    props = lambda data: [line for line in data.split(b"end_header\n")[0].splitlines() if line.startswith(b"property")]  # noqa: E731
    assert props(written) == props(source)
    assert written.split(b"end_header\n", 1)[1] == source.split(b"end_header\n", 1)[1]
