"""COLMAP scene loading: pinhole and distorted scenes (made by tests/scenes.py, and the real
ones of ../shared/data when present), undistortion cache, image pyramid, bad input."""

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
from scenes import SceneFacts


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


# ---------------------------------------------------------------- pinhole (binary): made, tumbler


@pytest.fixture(scope="module")
def full(pinhole_scene: SceneFacts) -> Scene:
    return load_colmap_scene(pinhole_scene.path)


@pytest.fixture(scope="module")
def small(pinhole_scene: SceneFacts) -> Scene:
    return load_colmap_scene(pinhole_scene.path, images=pinhole_scene.small)


def test_counts_and_split(full: Scene, pinhole_scene: SceneFacts) -> None:
    facts = pinhole_scene
    assert len(full.train_cameras) + len(full.test_cameras) == facts.n_images
    assert [c.name for c in full.test_cameras] == list(facts.names[::8])  # indices 0, 8, 16, ...
    assert sorted(c.name for c in full.cameras) == list(facts.names)
    assert full.points.shape == (facts.n_points, 3) and full.points.dtype == torch.float32
    assert full.point_colors.shape == (facts.n_points, 3)
    assert 0.0 <= float(full.point_colors.min()) and float(full.point_colors.max()) <= 1.0
    assert full.source == facts.path
    cam = full.train_cameras[0]
    assert (cam.width, cam.height) == facts.size
    assert cam.K.dtype == torch.float32 and cam.K.shape == (3, 3)
    assert cam.world_to_camera.dtype == torch.float32 and cam.world_to_camera.shape == (4, 4)
    assert torch.equal(cam.world_to_camera[3], torch.tensor([0.0, 0.0, 0.0, 1.0]))
    centers = torch.stack([c.center for c in full.train_cameras]).double()
    radius = (centers - centers.mean(0)).norm(dim=1).max().item() * 1.1
    assert full.extent == pytest.approx(radius, rel=1e-5)
    for c in full.cameras if facts.poses else ():  # a made scene: the poses and intrinsics it was made with
        np.testing.assert_allclose(c.world_to_camera.double().numpy(), facts.poses[c.name], atol=1e-6)
        np.testing.assert_allclose(c.K.double().numpy(), facts.intrinsics[c.name], rtol=1e-6)


def test_split_options(pinhole_scene: SceneFacts) -> None:
    n = pinhole_scene.n_images
    s = load_colmap_scene(pinhole_scene.path, test_every=0)
    assert len(s.train_cameras) == n and s.test_cameras == []
    s = load_colmap_scene(pinhole_scene.path, test_every=4)
    assert len(s.test_cameras) == len(range(0, n, 4)) and len(s.train_cameras) == n - len(range(0, n, 4))


def test_points_project_onto_observations(full: Scene, small: Scene, pinhole_scene: SceneFacts) -> None:
    median, p90 = pinhole_scene.observation_px
    scale = pinhole_scene.small_size[0] / pinhole_scene.size[0]
    errs = observation_errors(full, pinhole_scene.model_dir, 1.0)
    assert len(errs) > 500
    assert np.median(errs) < median and np.percentile(errs, 90) < p90
    errs4 = observation_errors(small, pinhole_scene.model_dir, scale)
    assert np.median(errs4) < median * scale and np.percentile(errs4, 90) < p90 * scale


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


def test_images_4_scales_intrinsics(full: Scene, small: Scene, pinhole_scene: SceneFacts) -> None:
    assert len(small.cameras) == pinhole_scene.n_images
    for big, little in zip(full.cameras, small.cameras):
        assert big.name == little.name
        assert (little.width, little.height) == pinhole_scene.small_size
        assert torch.allclose(little.K[:2], big.K[:2] / 4, rtol=1e-6)
        assert torch.equal(little.world_to_camera, big.world_to_camera)
        assert little.image_path.parent.name == "images_4"


def test_images_load_at_camera_size(full: Scene, small: Scene) -> None:
    for cam in (full.test_cameras[0], small.train_cameras[3]):
        img = cam.load_image()
        assert img.shape == (cam.height, cam.width, 3) and img.dtype == torch.float32
        assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0 and float(img.std()) > 0.01


def test_downscaled_camera_matches_downscaled_image(small: Scene) -> None:
    cam = small.train_cameras[0]
    w, h = cam.width // 4, cam.height // 4
    assert cam.height % 4 != 0  # both scenes: the last rows are cropped (tumbler 150 -> 37 rows)
    tiny = cam.downscaled(4)
    assert (tiny.width, tiny.height) == (w, h)
    assert torch.allclose(tiny.K[:2], cam.K[:2] / 4) and tiny.K[2, 2] == 1
    img = tiny.load_image()
    assert img.shape == (h, w, 3)
    assert torch.equal(img, cam.load_image(4))
    whole = cam.load_image()[: h * 4, : w * 4]
    box = whole.reshape(h, 4, w, 4, 3).mean(dim=(1, 3))
    assert (img - box).abs().max() <= 1.0 / 255 + 1e-6
    # a point projects to x/4 in the downscaled camera, and chained downscaling composes
    X = small.points[:50].double().numpy()
    np.testing.assert_allclose(project(tiny, X), project(cam, X) / 4, rtol=1e-5)
    assert torch.equal(cam.downscaled(2).downscaled(2).load_image(), img)


def test_a_window_of_an_image_is_the_crop_of_the_whole(small: Scene) -> None:
    cam = small.train_cameras[0]
    full = cam.load_image()
    assert torch.equal(cam.load_image(window=(10, 7, 40, 30)), full[7:37, 10:50])
    assert torch.equal(cam.load_image(2, window=(1, 2, 5, 4)), cam.load_image(2)[2:6, 1:6])
    with pytest.raises(ValueError, match="window"):
        cam.load_image(window=(cam.width - 5, 0, 10, 10))


def test_image_cache_is_bounded(small: Scene) -> None:
    cams = small.train_cameras[:6]
    one = cams[0].width * cams[0].height * 3
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


def test_the_device_cache_is_bounded_and_keeps_the_most_recent(small: Scene) -> None:
    cams = small.train_cameras[:5]
    one = cams[0].width * cams[0].height * 3
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
def test_an_image_loaded_onto_the_gpu_equals_the_cpu_one_bit_for_bit(small: Scene) -> None:
    cam = small.train_cameras[0]
    for kwargs in ({}, {"window": (10, 7, 40, 30)}, {"downscale": 2}):
        cpu = cam.load_image(**kwargs)
        gpu = cam.load_image(device="cuda", **kwargs)
        assert gpu.device.type == "cuda"
        assert torch.equal(gpu.cpu(), cpu), kwargs


def test_preload_decodes_every_image_once_when_all_fit(small: Scene, tmp_path: Path) -> None:
    cams = small.train_cameras[:5]
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


# ---------------------------------------------------------------- distorted (text): made, fern


@pytest.fixture(scope="module")
def distorted_copy(distorted_scene: SceneFacts, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return copy_scene(distorted_scene.path, tmp_path_factory.mktemp("distorted") / distorted_scene.name)


def change_first_distortion(model_dir: Path) -> None:
    """Add 0.03 to the last distortion parameter of the first camera in cameras.txt."""
    txt = model_dir / "cameras.txt"
    lines = txt.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.strip() and not line.startswith("#"))
    words = lines[first].split()
    words[-1] = repr(float(words[-1]) + 0.03)
    lines[first] = " ".join(words)
    txt.write_text("\n".join(lines) + "\n")


def test_distorted_scene_is_undistorted_and_cached(distorted_scene: SceneFacts, distorted_copy: Path) -> None:
    facts = distorted_scene
    scene = load_colmap_scene(distorted_copy)
    cache = distorted_copy / ".promptgs_cache" / "undistorted_images"
    assert len(scene.cameras) == facts.n_images and len(scene.test_cameras) == len(facts.names[::8])
    assert scene.points.shape == (facts.n_points, 3)
    cam = scene.cameras[0]
    assert cam.image_path.parent == cache / "images"
    assert cam.K[0, 1] == 0 and cam.K[0, 0] == pytest.approx(facts.focal, rel=1e-4)
    assert cam.load_image().shape == (cam.height, cam.width, 3)
    with Image.open(cam.image_path) as im:
        assert im.size == (cam.width, cam.height)

    stamp = cache / "stamp.json"
    stamp_mtime = stamp.stat().st_mtime_ns
    img_mtime = cam.image_path.stat().st_mtime_ns
    again = load_colmap_scene(distorted_copy)
    assert stamp.stat().st_mtime_ns == stamp_mtime and cam.image_path.stat().st_mtime_ns == img_mtime
    assert torch.equal(again.cameras[0].K, cam.K)

    # a changed source model invalidates the cache
    change_first_distortion(distorted_copy / "sparse" / "0")
    changed = load_colmap_scene(distorted_copy)
    assert stamp.stat().st_mtime_ns != stamp_mtime
    assert not torch.equal(changed.cameras[0].K, cam.K)


def test_undistorted_images_agree_with_distorted_model(distorted_scene: SceneFacts, distorted_copy: Path) -> None:
    """A point's colour where the distorted model sees it in the original image equals its
    colour where our pinhole camera sees it in the undistorted image (the first two
    images: in the made scene one of each of its two distorted cameras)."""
    src = distorted_scene.path
    scene = load_colmap_scene(src, cache_dir=distorted_copy.parent / "cache_b")
    rec = pycolmap.Reconstruction(str(distorted_scene.model_dir))
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


def test_smaller_images_are_rescaled_then_undistorted(distorted_scene: SceneFacts, tmp_path: Path) -> None:
    src = distorted_scene.path
    ds = copy_scene(src, tmp_path / distorted_scene.name)
    (ds / "images_2").mkdir()
    for p in sorted((src / "images").iterdir()):
        with Image.open(p) as im:
            im.convert("RGB").reduce(2).save(ds / "images_2" / p.name)
    full = load_colmap_scene(ds)
    half = load_colmap_scene(ds, images="images_2")
    assert half.cameras[0].image_path.parent == ds / ".promptgs_cache" / "undistorted_images_2" / "images"
    assert len(half.cameras) == distorted_scene.n_images
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


def test_no_model(pinhole_scene: SceneFacts, tmp_path: Path) -> None:
    ds = copy_scene(pinhole_scene.path, tmp_path / "t")
    shutil.rmtree(ds / "sparse")
    expect_error(ds, "no COLMAP model")


def test_model_directly_in_sparse_is_accepted(pinhole_scene: SceneFacts, tmp_path: Path) -> None:
    ds = copy_scene(pinhole_scene.path, tmp_path / "t")
    for f in (ds / "sparse" / "0").iterdir():
        f.rename(ds / "sparse" / f.name)
    (ds / "sparse" / "0").rmdir()
    assert len(load_colmap_scene(ds).cameras) == pinhole_scene.n_images


def test_images_folder_missing(pinhole_scene: SceneFacts, tmp_path: Path) -> None:
    ds = copy_scene(pinhole_scene.path, tmp_path / "t")
    expect_error(ds, "images_4", "images folder not found", images="images_4")


def test_image_missing_on_disk(pinhole_scene: SceneFacts, tmp_path: Path) -> None:
    gone = pinhole_scene.names[3]
    ds = copy_scene(pinhole_scene.path, tmp_path / "t", images=())
    (ds / "images").mkdir()
    for p in (pinhole_scene.path / "images").iterdir():
        if p.name != gone:
            (ds / "images" / p.name).symlink_to(p)
    expect_error(ds, gone, "missing")


def test_unreadable_image(pinhole_scene: SceneFacts, tmp_path: Path) -> None:
    bad = pinhole_scene.names[1]
    ds = copy_scene(pinhole_scene.path, tmp_path / "t", images=())
    (ds / "images").mkdir()
    for p in (pinhole_scene.path / "images").iterdir():
        (ds / "images" / p.name).symlink_to(p)
    (ds / "images" / bad).unlink()
    (ds / "images" / bad).write_bytes(b"not a jpeg at all")
    expect_error(ds, bad, "unreadable")


def test_model_without_images(distorted_scene: SceneFacts, tmp_path: Path) -> None:
    ds = copy_scene(distorted_scene.path, tmp_path / "f")
    model = ds / "sparse" / "0"
    lines = (model / "images.txt").read_text().splitlines()
    (model / "images.txt").write_text("\n".join(l for l in lines if l.startswith("#")) + "\n")
    # the points' tracks and the frames name the images: they go too (fern's model has neither)
    points = [l.split()[:8] for l in (model / "points3D.txt").read_text().splitlines() if not l.startswith("#")]
    (model / "points3D.txt").write_text("".join(" ".join(p) + " \n" for p in points))
    for name in ("frames.txt", "rigs.txt"):
        (model / name).unlink(missing_ok=True)
    expect_error(ds, "no registered images")


def _drop_first_image_text(model: Path) -> int:
    """Remove the first image of a text model from images.txt; returns its id."""
    lines = (model / "images.txt").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    image_id = int(lines[first].split()[0])
    (model / "images.txt").write_text("\n".join(lines[:first] + lines[first + 2:]) + "\n")
    return image_id


def _drop_first_image_binary(model: Path) -> int:
    """Remove the first image record of images.bin (COLMAP's layout); returns its id."""
    data = (model / "images.bin").read_bytes()
    count, image_id = struct.unpack_from("<QI", data, 0)
    name_end = data.index(b"\0", 8 + 4 + 7 * 8 + 4) + 1  # id, qvec and tvec, camera id, then the name
    n_points2d = struct.unpack_from("<Q", data, name_end)[0]
    (model / "images.bin").write_bytes(struct.pack("<Q", count - 1) + data[name_end + 8 + 24 * n_points2d:])
    return image_id


@pytest.mark.parametrize("kind", ["distorted", "pinhole"])  # text, binary
def test_tracks_naming_a_missing_image_name_the_model(made_scenes: dict, kind: str, tmp_path: Path) -> None:
    """A model whose points' tracks name an image it does not list (an image removed by
    hand): one line naming the model folder and the image, not pycolmap's IndexError."""
    facts = made_scenes[kind]
    ds = copy_scene(facts.path, tmp_path / kind)
    model = ds / "sparse" / "0"
    for name in ("frames", "rigs"):  # only the tracks name the image then (a legacy model)
        for f in model.glob(f"{name}.*"):
            f.unlink()
    image_id = (_drop_first_image_text if facts.form == "text" else _drop_first_image_binary)(model)
    expect_error(ds, str(model), "cannot read the COLMAP model", f"Image with ID {image_id} does not exist")


def test_zero_points(distorted_scene: SceneFacts, tmp_path: Path) -> None:
    ds = copy_scene(distorted_scene.path, tmp_path / "f")
    (ds / "sparse" / "0" / "points3D.txt").write_text("# no points\n")
    expect_error(ds, "no SfM points")


def test_unknown_camera_model_text(distorted_scene: SceneFacts, tmp_path: Path) -> None:
    ds = copy_scene(distorted_scene.path, tmp_path / "f")
    txt = ds / "sparse" / "0" / "cameras.txt"
    txt.write_text(txt.read_text().replace(distorted_scene.models[1], "WOBBLY_LENS"))
    expect_error(ds, "camera 1", "WOBBLY_LENS")


def test_unknown_camera_model_binary(pinhole_scene: SceneFacts, tmp_path: Path) -> None:
    ds = copy_scene(pinhole_scene.path, tmp_path / "t")
    path = ds / "sparse" / "0" / "cameras.bin"
    data = bytearray(path.read_bytes())
    cam_id = struct.unpack_from("<I", data, 8)[0]
    struct.pack_into("<i", data, 12, 99)  # first camera's model id
    path.write_bytes(bytes(data))
    expect_error(ds, f"camera {cam_id}", "99")


def test_unsupported_camera_model(distorted_scene: SceneFacts, tmp_path: Path) -> None:
    ds = copy_scene(distorted_scene.path, tmp_path / "f")
    model = ds / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    cam = pycolmap.Camera.create_from_model_name(1, "EQUIRECTANGULAR", 1.0, *distorted_scene.size)
    rec.cameras[1].model = cam.model
    rec.cameras[1].params = cam.params
    for f in model.iterdir():
        f.unlink()
    rec.write_text(str(model))
    expect_error(ds, "camera 1", "EQUIRECTANGULAR")


def test_image_with_other_aspect_ratio(pinhole_scene: SceneFacts, tmp_path: Path) -> None:
    turned = pinhole_scene.names[5]
    ds = copy_scene(pinhole_scene.path, tmp_path / "t", images=())
    (ds / "images").mkdir()
    for p in (pinhole_scene.path / pinhole_scene.small).iterdir():
        (ds / "images" / p.name).symlink_to(p)
    (ds / "images" / turned).unlink()
    Image.new("RGB", pinhole_scene.small_size[::-1]).save(ds / "images" / turned)  # portrait
    expect_error(ds, turned, "aspect ratio")


def test_truncated_image_fails_when_loaded(pinhole_scene: SceneFacts, tmp_path: Path) -> None:
    cut = pinhole_scene.names[0]
    small = pinhole_scene.path / pinhole_scene.small
    ds = copy_scene(pinhole_scene.path, tmp_path / "t", images=())
    (ds / "images").mkdir()
    for p in small.iterdir():
        (ds / "images" / p.name).symlink_to(p)
    (ds / "images" / cut).unlink()
    data = (small / cut).read_bytes()
    (ds / "images" / cut).write_bytes(data[: len(data) // 2])  # header intact, pixels cut
    scene = load_colmap_scene(ds)
    cam = next(c for c in scene.cameras if c.name == cut)
    with pytest.raises(DatasetError, match=f"{cut}: unreadable image"):
        cam.load_image()


def test_cache_dir_from_environment(distorted_scene: SceneFacts, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ds = copy_scene(distorted_scene.path, tmp_path / distorted_scene.name)
    monkeypatch.setenv("PROMPTGS_CACHE_DIR", str(tmp_path / "cache"))
    scene = load_colmap_scene(ds)
    assert (tmp_path / "cache") in scene.cameras[0].image_path.parents
    assert not (ds / ".promptgs_cache").exists()
