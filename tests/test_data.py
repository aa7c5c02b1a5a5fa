"""COLMAP scene loading: both shared scenes, undistortion cache, image pyramid, bad input."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from promptgs_engine.data import Camera, Scene, load_colmap_scene
from promptgs_engine.data.images import DeviceImageCache, ImageCache, preload_images
from promptgs_engine.errors import DatasetError


def project(cam: Camera, X: np.ndarray) -> np.ndarray:
    """Pixel coordinates of world points [N, 3] with our K and world_to_camera."""
    W = cam.world_to_camera.double().numpy()
    K = cam.K.double().numpy()
    Xc = X @ W[:3, :3].T + W[:3, 3]
    p = Xc @ K.T
    return p[:, :2] / p[:, 2:3]


def copy_scene(src: Path, dst: Path, images: tuple[str, ...] = ("images",)) -> Path:
    """A temp copy of a scene: model files copied, image folders symlinked."""
    dst.mkdir(parents=True)
    shutil.copytree(src / "sparse", dst / "sparse")
    for name in images:
        (dst / name).symlink_to(src / name)
    return dst


def observation_errors(scene: Scene, model_dir: Path, scale: float, n_points: int = 300) -> np.ndarray:
    """Distances (px) between our projection of SfM points and their recorded 2D observations."""
    rec = pycolmap.Reconstruction(str(model_dir))
    by_name = {c.name: c for c in scene.cameras}
    errs = []
    for pid in sorted(rec.points3D)[:n_points]:
        pt = rec.points3D[pid]
        for el in pt.track.elements:
            im = rec.images[el.image_id]
            obs = np.asarray(im.points2D[el.point2D_idx].xy) * scale
            errs.append(np.linalg.norm(project(by_name[im.name], pt.xyz[None])[0] - obs))
    return np.asarray(errs)


# ---------------------------------------------------------------- tumbler (binary, SIMPLE_PINHOLE)


@pytest.fixture(scope="module")
def tumbler(shared_data: Path) -> Scene:
    return load_colmap_scene(shared_data / "tumbler")


@pytest.fixture(scope="module")
def tumbler4(shared_data: Path) -> Scene:
    return load_colmap_scene(shared_data / "tumbler", images="images_4")


def test_tumbler_counts_and_split(tumbler: Scene, shared_data: Path) -> None:
    assert len(tumbler.train_cameras) + len(tumbler.test_cameras) == 77
    assert len(tumbler.test_cameras) == 10  # indices 0, 8, ..., 72
    names = sorted(c.name for c in tumbler.cameras)
    assert [c.name for c in tumbler.test_cameras] == names[::8]
    assert tumbler.points.shape == (9262, 3) and tumbler.points.dtype == torch.float32
    assert tumbler.point_colors.shape == (9262, 3)
    assert 0.0 <= float(tumbler.point_colors.min()) and float(tumbler.point_colors.max()) <= 1.0
    assert tumbler.source == shared_data / "tumbler"
    cam = tumbler.train_cameras[0]
    assert (cam.width, cam.height) == (800, 600)
    assert cam.K.dtype == torch.float32 and cam.K.shape == (3, 3)
    assert cam.world_to_camera.dtype == torch.float32 and cam.world_to_camera.shape == (4, 4)
    assert torch.equal(cam.world_to_camera[3], torch.tensor([0.0, 0.0, 0.0, 1.0]))
    centers = torch.stack([c.center for c in tumbler.train_cameras]).double()
    radius = (centers - centers.mean(0)).norm(dim=1).max().item() * 1.1
    assert tumbler.extent == pytest.approx(radius, rel=1e-5)


def test_tumbler_split_options(shared_data: Path) -> None:
    s = load_colmap_scene(shared_data / "tumbler", test_every=0)
    assert len(s.train_cameras) == 77 and s.test_cameras == []
    s = load_colmap_scene(shared_data / "tumbler", test_every=4)
    assert len(s.test_cameras) == 20 and len(s.train_cameras) == 57


def test_tumbler_points_project_onto_observations(tumbler: Scene, tumbler4: Scene, shared_data: Path) -> None:
    model = shared_data / "tumbler" / "sparse" / "0"
    errs = observation_errors(tumbler, model, 1.0)
    assert len(errs) > 500
    assert np.median(errs) < 1.0 and np.percentile(errs, 90) < 2.0
    errs4 = observation_errors(tumbler4, model, 0.25)
    assert np.median(errs4) < 0.25 and np.percentile(errs4, 90) < 0.5


def test_camera_projects_world_points_to_pixels_and_depth() -> None:
    # Camera at the origin looking down +z; a point 2 m ahead and 0.5 m right lands
    # 0.25 focal lengths right of the principal point.
    K = torch.tensor([[100.0, 0, 32.0], [0, 100.0, 24.0], [0, 0, 1]])
    cam = Camera("c", 64, 48, K, torch.eye(4), Path("none"))
    u, v, z = cam.project(torch.tensor([[0.5, 0.0, 2.0], [0.0, -0.24, 1.0]]))
    assert torch.allclose(u, torch.tensor([57.0, 32.0])) and torch.allclose(v, torch.tensor([24.0, 0.0]))
    assert torch.allclose(z, torch.tensor([2.0, 1.0]))
    # The same through a translated camera: world moves, pixels do not.
    moved = Camera("m", 64, 48, K, torch.tensor([[1.0, 0, 0, -1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), Path("none"))
    u2, v2, z2 = moved.project(torch.tensor([[1.5, 0.0, 2.0]]))
    assert torch.allclose(u2, torch.tensor([57.0])) and torch.allclose(z2, torch.tensor([2.0]))


def test_tumbler_images_4_scales_intrinsics(tumbler: Scene, tumbler4: Scene) -> None:
    for full, small in zip(tumbler.cameras, tumbler4.cameras):
        assert full.name == small.name
        assert (small.width, small.height) == (200, 150)
        assert torch.allclose(small.K[:2], full.K[:2] / 4, rtol=1e-6)
        assert torch.equal(small.world_to_camera, full.world_to_camera)
        assert small.image_path.parent.name == "images_4"


def test_images_load_at_camera_size(tumbler: Scene, tumbler4: Scene) -> None:
    for cam in (tumbler.test_cameras[0], tumbler4.train_cameras[3]):
        img = cam.load_image()
        assert img.shape == (cam.height, cam.width, 3) and img.dtype == torch.float32
        assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0 and float(img.std()) > 0.01


def test_downscaled_camera_matches_downscaled_image(tumbler4: Scene) -> None:
    cam = tumbler4.train_cameras[0]
    small = cam.downscaled(4)  # 150 is not a multiple of 4: 37 rows, bottom 2 rows cropped
    assert (small.width, small.height) == (50, 37)
    assert torch.allclose(small.K[:2], cam.K[:2] / 4) and small.K[2, 2] == 1
    img = small.load_image()
    assert img.shape == (37, 50, 3)
    assert torch.equal(img, cam.load_image(4))
    full = cam.load_image()[: 37 * 4, : 50 * 4]
    box = full.reshape(37, 4, 50, 4, 3).mean(dim=(1, 3))
    assert (img - box).abs().max() <= 1.0 / 255 + 1e-6
    # a point projects to x/4 in the downscaled camera, and chained downscaling composes
    X = tumbler4.points[:50].double().numpy()
    np.testing.assert_allclose(project(small, X), project(cam, X) / 4, rtol=1e-5)
    assert torch.equal(cam.downscaled(2).downscaled(2).load_image(), img)


def test_a_window_of_an_image_is_the_crop_of_the_whole(tumbler4: Scene) -> None:
    cam = tumbler4.train_cameras[0]
    full = cam.load_image()
    assert torch.equal(cam.load_image(window=(10, 7, 40, 30)), full[7:37, 10:50])
    assert torch.equal(cam.load_image(2, window=(1, 2, 5, 4)), cam.load_image(2)[2:6, 1:6])
    with pytest.raises(ValueError, match="window"):
        cam.load_image(window=(cam.width - 5, 0, 10, 10))


def test_image_cache_is_bounded(tumbler4: Scene) -> None:
    cams = tumbler4.train_cameras[:6]
    one = 150 * 200 * 3
    cache = ImageCache(max_bytes=int(2.5 * one))
    for c in cams:
        cache.get(c.image_path, 1)
        assert cache.nbytes <= cache.max_bytes
    assert len(cache) == 2
    again = cache.get(cams[-1].image_path, 1)  # most recent one is still held
    assert again is cache.get(cams[-1].image_path, 1)


def test_the_device_table_converts_every_8_bit_value_as_the_cpu_does() -> None:
    values = np.arange(256, dtype=np.uint8).reshape(16, 16)
    cache = DeviceImageCache()
    table = cache.to_unit_float(torch.from_numpy(values))
    assert table.dtype == torch.float32
    assert torch.equal(table, torch.from_numpy(values.astype(np.float32)).div_(255.0))


def test_the_device_cache_is_bounded_and_keeps_the_most_recent(tumbler4: Scene) -> None:
    cams = tumbler4.train_cameras[:5]
    one = 150 * 200 * 3
    cache = DeviceImageCache(max_bytes=int(2.5 * one))
    for c in cams:
        host = c.load_image()  # float; the cache holds what it is given, here the 8-bit copy
        held = cache.get(c.image_path, 1, torch.device("cpu"), (host * 255).round().to(torch.uint8).numpy())
        assert held.dtype == torch.uint8 and cache.nbytes <= cache.max_bytes
        assert torch.equal(cache.to_unit_float(held), host)
    assert len(cache) == 2
    assert cache.get(cams[-1].image_path, 1, torch.device("cpu"), None) is held  # served, not re-copied


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_an_image_loaded_onto_the_gpu_equals_the_cpu_one_bit_for_bit(tumbler4: Scene) -> None:
    cam = tumbler4.train_cameras[0]
    for kwargs in ({}, {"window": (10, 7, 40, 30)}, {"downscale": 2}):
        cpu = cam.load_image(**kwargs)
        gpu = cam.load_image(device="cuda", **kwargs)
        assert gpu.device.type == "cuda"
        assert torch.equal(gpu.cpu(), cpu), kwargs


def test_preload_decodes_every_image_once_when_all_fit(tumbler4: Scene, tmp_path: Path) -> None:
    cams = tumbler4.train_cameras[:5]
    items = [(c.image_path, 1, c.width * c.height * 3) for c in cams]
    small = ImageCache(max_bytes=4 * items[0][2])
    assert not preload_images(items, threads=2, cache=small) and len(small) == 0  # would not all fit
    missing = items + [(tmp_path / "gone.jpg", 1, 10)]
    cache = ImageCache()
    assert not preload_images(missing, threads=2, cache=cache) and len(cache) == 0  # reported when needed
    assert preload_images(items, threads=2, cache=cache) and len(cache) == 5
    held = cache.get(cams[3].image_path, 1)
    assert held is cache.get(cams[3].image_path, 1)  # served from the cache, not decoded again
    assert np.array_equal(held, np.asarray(Image.open(cams[3].image_path).convert("RGB")))


# ---------------------------------------------------------------- fern (text, SIMPLE_RADIAL)


@pytest.fixture(scope="module")
def fern_copy(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return copy_scene(shared_data / "fern", tmp_path_factory.mktemp("fern") / "fern")


def test_fern_is_undistorted_and_cached(fern_copy: Path) -> None:
    scene = load_colmap_scene(fern_copy)
    cache = fern_copy / ".promptgs_cache" / "undistorted_images"
    assert len(scene.cameras) == 20 and len(scene.test_cameras) == 3
    assert scene.points.shape == (10091, 3)
    cam = scene.cameras[0]
    assert cam.image_path.parent == cache / "images"
    assert cam.K[0, 1] == 0 and cam.K[0, 0] == pytest.approx(407.5658, rel=1e-4)
    assert cam.load_image().shape == (cam.height, cam.width, 3)
    with Image.open(cam.image_path) as im:
        assert im.size == (cam.width, cam.height)

    stamp = cache / "stamp.json"
    stamp_mtime = stamp.stat().st_mtime_ns
    img_mtime = cam.image_path.stat().st_mtime_ns
    again = load_colmap_scene(fern_copy)
    assert stamp.stat().st_mtime_ns == stamp_mtime and cam.image_path.stat().st_mtime_ns == img_mtime
    assert torch.equal(again.cameras[0].K, cam.K)

    # a changed source model invalidates the cache
    txt = fern_copy / "sparse" / "0" / "cameras.txt"
    txt.write_text(txt.read_text().replace("0.019750463822896944", "0.03"))
    changed = load_colmap_scene(fern_copy)
    assert stamp.stat().st_mtime_ns != stamp_mtime
    assert not torch.equal(changed.cameras[0].K, cam.K)


def test_fern_undistorted_images_agree_with_distorted_model(shared_data: Path, fern_copy: Path) -> None:
    """A point's colour where the distorted model sees it in the original image equals its
    colour where our pinhole camera sees it in the undistorted image."""
    src = shared_data / "fern"
    scene = load_colmap_scene(src, cache_dir=fern_copy.parent / "cache_b")
    rec = pycolmap.Reconstruction(str(src / "sparse" / "0"))
    X = np.stack([p.xyz for p in rec.points3D.values()])
    for cam in scene.cameras[:2]:
        im = rec.find_image_with_name(cam.name)
        cfw = im.cam_from_world().matrix()
        Xc = X @ cfw[:, :3].T + cfw[:, 3]
        keep = Xc[:, 2] > 0.1
        model_cam = rec.cameras[im.camera_id]
        pd = np.asarray(model_cam.img_from_cam(Xc[keep]))
        pu = project(cam, X[keep])
        m = np.all((pd > 5) & (pd < [model_cam.width - 5, model_cam.height - 5]), 1)
        m &= np.all((pu > 5) & (pu < [cam.width - 5, cam.height - 5]), 1)
        assert m.sum() > 1000
        with Image.open(src / "images" / cam.name) as f:
            orig = np.asarray(f.convert("RGB"), dtype=np.float32) / 255
        und = cam.load_image().numpy()

        def at(img: np.ndarray, p: np.ndarray) -> np.ndarray:
            return img[p[:, 1].astype(int), p[:, 0].astype(int)]

        diff = np.abs(at(orig, pd[m]) - at(und, pu[m])).mean()
        shifted = np.abs(at(orig, pd[m]) - at(und, pu[m] + [3, 0])).mean()
        assert diff < 0.06 and diff < 0.5 * shifted


def test_fern_smaller_images_are_rescaled_then_undistorted(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "fern", tmp_path / "fern")
    (ds / "images_2").mkdir()
    for p in sorted((shared_data / "fern" / "images").iterdir()):
        with Image.open(p) as im:
            im.convert("RGB").reduce(2).save(ds / "images_2" / p.name)
    full = load_colmap_scene(ds)
    half = load_colmap_scene(ds, images="images_2")
    assert half.cameras[0].image_path.parent == ds / ".promptgs_cache" / "undistorted_images_2" / "images"
    for a, b in zip(full.cameras, half.cameras):
        assert abs(b.width - a.width / 2) <= 2 and abs(b.height - a.height / 2) <= 2
        assert float(b.K[0, 0]) == pytest.approx(float(a.K[0, 0]) / 2, rel=1e-3)
        assert b.load_image().shape == (b.height, b.width, 3)


# ---------------------------------------------------------------- bad input


def expect_error(path: Path, *words: str, **kwargs) -> None:
    with pytest.raises(DatasetError) as info:
        load_colmap_scene(path, **kwargs)
    msg = str(info.value)
    assert "\n" not in msg
    for w in words:
        assert w.lower() in msg.lower(), f"{w!r} not in {msg!r}"


def test_missing_dataset_folder(tmp_path: Path) -> None:
    expect_error(tmp_path / "nope", "nope", "not found")


def test_no_model(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "tumbler", tmp_path / "t")
    shutil.rmtree(ds / "sparse")
    expect_error(ds, "no COLMAP model")


def test_model_directly_in_sparse_is_accepted(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "tumbler", tmp_path / "t")
    for f in (ds / "sparse" / "0").iterdir():
        f.rename(ds / "sparse" / f.name)
    (ds / "sparse" / "0").rmdir()
    assert len(load_colmap_scene(ds).cameras) == 77


def test_images_folder_missing(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "tumbler", tmp_path / "t")
    expect_error(ds, "images_4", "images folder not found", images="images_4")


def test_image_missing_on_disk(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "tumbler", tmp_path / "t", images=())
    (ds / "images").mkdir()
    for p in (shared_data / "tumbler" / "images").iterdir():
        if p.name != "12.jpg":
            (ds / "images" / p.name).symlink_to(p)
    expect_error(ds, "12.jpg", "missing")


def test_unreadable_image(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "tumbler", tmp_path / "t", images=())
    (ds / "images").mkdir()
    for p in (shared_data / "tumbler" / "images").iterdir():
        (ds / "images" / p.name).symlink_to(p)
    (ds / "images" / "3.jpg").unlink()
    (ds / "images" / "3.jpg").write_bytes(b"not a jpeg at all")
    expect_error(ds, "3.jpg", "unreadable")


def test_model_without_images(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "fern", tmp_path / "f")
    lines = (ds / "sparse" / "0" / "images.txt").read_text().splitlines()
    (ds / "sparse" / "0" / "images.txt").write_text("\n".join(l for l in lines if l.startswith("#")) + "\n")
    expect_error(ds, "no registered images")


def test_zero_points(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "fern", tmp_path / "f")
    (ds / "sparse" / "0" / "points3D.txt").write_text("# no points\n")
    expect_error(ds, "no SfM points")


def test_unknown_camera_model_text(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "fern", tmp_path / "f")
    txt = ds / "sparse" / "0" / "cameras.txt"
    txt.write_text(txt.read_text().replace("SIMPLE_RADIAL", "WOBBLY_LENS"))
    expect_error(ds, "camera 1", "WOBBLY_LENS")


def test_unknown_camera_model_binary(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "tumbler", tmp_path / "t")
    path = ds / "sparse" / "0" / "cameras.bin"
    data = bytearray(path.read_bytes())
    cam_id = struct.unpack_from("<I", data, 8)[0]
    struct.pack_into("<i", data, 12, 99)  # first camera's model id
    path.write_bytes(bytes(data))
    expect_error(ds, f"camera {cam_id}", "99")


def test_unsupported_camera_model(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "fern", tmp_path / "f")
    model = ds / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    cam = pycolmap.Camera.create_from_model_name(1, "EQUIRECTANGULAR", 1.0, 504, 378)
    rec.cameras[1].model = cam.model
    rec.cameras[1].params = cam.params
    for f in model.iterdir():
        f.unlink()
    rec.write_text(str(model))
    expect_error(ds, "camera 1", "EQUIRECTANGULAR")


def test_image_with_other_aspect_ratio(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "tumbler", tmp_path / "t", images=())
    (ds / "images").mkdir()
    for p in (shared_data / "tumbler" / "images_4").iterdir():
        (ds / "images" / p.name).symlink_to(p)
    (ds / "images" / "5.jpg").unlink()
    Image.new("RGB", (150, 200)).save(ds / "images" / "5.jpg")
    expect_error(ds, "5.jpg", "aspect ratio")


def test_truncated_image_fails_when_loaded(shared_data: Path, tmp_path: Path) -> None:
    ds = copy_scene(shared_data / "tumbler", tmp_path / "t", images=())
    (ds / "images").mkdir()
    for p in (shared_data / "tumbler" / "images_4").iterdir():
        (ds / "images" / p.name).symlink_to(p)
    (ds / "images" / "1.jpg").unlink()
    data = (shared_data / "tumbler" / "images_4" / "1.jpg").read_bytes()
    (ds / "images" / "1.jpg").write_bytes(data[: len(data) // 2])  # header intact, pixels cut
    scene = load_colmap_scene(ds)
    cam = next(c for c in scene.cameras if c.name == "1.jpg")
    with pytest.raises(DatasetError, match="1.jpg: unreadable image"):
        cam.load_image()


def test_cache_dir_from_environment(shared_data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ds = copy_scene(shared_data / "fern", tmp_path / "fern")
    monkeypatch.setenv("PROMPTGS_CACHE_DIR", str(tmp_path / "cache"))
    scene = load_colmap_scene(ds)
    assert (tmp_path / "cache") in scene.cameras[0].image_path.parents
    assert not (ds / ".promptgs_cache").exists()
