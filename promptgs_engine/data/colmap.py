"""Loading a COLMAP dataset folder (model read by pycolmap) into a `Scene`."""

from __future__ import annotations

import hashlib
import os
import re
import struct
from pathlib import Path

import numpy as np
import pycolmap
import torch

from ..errors import DatasetError
from .images import image_size
from .scene import Camera, Scene, nerf_normalization_radius
from .undistort import camera_model_name, check_undistortable, needs_undistortion, undistorted_model

MODEL_FILES = ("cameras", "images", "points3D")
CACHE_FOLDER = ".promptgs_cache"


def find_model_dir(dataset: Path) -> Path:
    """`DATASET/sparse/0`, or `DATASET/sparse` when the model files lie there directly."""

    def has_model(d: Path) -> bool:
        return all((d / f"{n}.bin").is_file() or (d / f"{n}.txt").is_file() for n in MODEL_FILES)

    for d in (dataset / "sparse" / "0", dataset / "sparse"):
        if has_model(d):
            return d
    raise DatasetError(
        f"{dataset}: no COLMAP model found (expected cameras, images and points3D .bin or .txt in sparse/0 or sparse)"
    )


def default_cache_root(dataset: Path) -> Path:
    """Where undistorted copies go when no `cache_dir` is given.

    `$PROMPTGS_CACHE_DIR/<name>-<hash>` when that variable is set, else
    `DATASET/.promptgs_cache` when the dataset folder is writable, else
    `~/.cache/promptgs/<name>-<hash>` (hash of the dataset's absolute path).
    """
    tag = f"{dataset.resolve().name}-{hashlib.sha1(str(dataset.resolve()).encode()).hexdigest()[:10]}"
    env = os.environ.get("PROMPTGS_CACHE_DIR")
    if env:
        return Path(env).expanduser() / tag
    local = dataset / CACHE_FOLDER
    if local.is_dir() or os.access(dataset, os.W_OK):
        return local
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "promptgs" / tag


def _unknown_camera_model(model_dir: Path) -> str | None:
    """A message naming the first camera whose model pycolmap does not know, if any."""
    known_names = set(pycolmap.CameraModelId.__members__) - {"INVALID"}
    txt, bin_ = model_dir / "cameras.txt", model_dir / "cameras.bin"
    if bin_.is_file():
        # Layout: uint64 count, then per camera uint32 id, int32 model id, uint64 w, uint64 h, float64 params.
        data = bin_.read_bytes()
        n_params = {}
        for name in known_names:
            cam = pycolmap.Camera.create_from_model_name(1, name, 1.0, 1, 1)
            n_params[int(cam.model.value)] = len(cam.params)
        (count,), off = struct.unpack_from("<Q", data, 0), 8
        for _ in range(count):
            cam_id, model_id = struct.unpack_from("<Ii", data, off)
            if model_id not in n_params:
                return f"{bin_}: camera {cam_id} has unknown camera model id {model_id}"
            off += 24 + 8 * n_params[model_id]
    elif txt.is_file():
        for line in txt.read_text(errors="replace").splitlines():
            parts = line.split()
            if len(parts) >= 2 and not line.lstrip().startswith("#") and parts[1] not in known_names:
                return f"{txt}: camera {parts[0]} has unknown camera model {parts[1]}"
    return None


def _first_line(e: Exception) -> str:
    """pycolmap's message of `e`, its first line without the source location prefix."""
    text = str(e).strip()
    return re.sub(r"^\[[^\]]*\]\s*", "", text.splitlines()[0]) if text else type(e).__name__


def read_model(model_dir: Path) -> "pycolmap.Reconstruction":
    """Read a COLMAP model (binary preferred, else text); DatasetError on failure."""
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except IndexError as e:  # a point's track, an image or a frame names an id the model lacks
        raise DatasetError(f"{model_dir}: cannot read the COLMAP model (it names what it does not hold: "
                           f"{_first_line(e)})") from None
    except (ValueError, RuntimeError) as e:
        try:
            unknown = _unknown_camera_model(model_dir)
        except (OSError, struct.error, ValueError):
            unknown = None
        if unknown:
            raise DatasetError(unknown) from None
        raise DatasetError(f"{model_dir}: cannot read the COLMAP model ({_first_line(e)})") from None


def _cam_from_world_matrix(image: "pycolmap.Image") -> np.ndarray:
    """[4, 4] float64 world-to-camera; `cam_from_world` is a method in pycolmap 4, a property before."""
    cfw = image.cam_from_world
    if callable(cfw):
        cfw = cfw()
    m = np.eye(4)
    m[:3, :4] = cfw.matrix()
    return m


def _reg_image_ids(rec: "pycolmap.Reconstruction") -> list[int]:
    ids = rec.reg_image_ids() if callable(rec.reg_image_ids) else rec.reg_image_ids
    return sorted(int(i) for i in ids)


def _pinhole_K(camera: "pycolmap.Camera") -> np.ndarray:
    name = camera_model_name(camera)
    p = np.asarray(camera.params, dtype=np.float64)
    if name == "SIMPLE_PINHOLE":
        f, cx, cy = p
        fx = fy = f
    elif name == "PINHOLE":
        fx, fy, cx, cy = p
    else:
        raise AssertionError(f"not a pinhole model: {name}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def load_colmap_scene(
    path: str | Path,
    images: str = "images",
    test_every: int = 8,
    cache_dir: str | Path | None = None,
) -> Scene:
    """Load a COLMAP dataset folder into a `Scene`.

    - The model is read from `path/sparse/0` (or `path/sparse`), binary or text.
    - `images` names the image folder under `path`. When its images differ in size from
      the model's cameras (the `images_4` convention), intrinsics are scaled by the
      actual width and height ratios.
    - PINHOLE and SIMPLE_PINHOLE cameras are used as they are; other perspective models
      are undistorted by pycolmap into a cached pinhole copy under `cache_dir` (default:
      see `default_cache_root`, normally `path/.promptgs_cache`), reused while the
      source model and images are unchanged.
    - Test split: images sorted by name, index % test_every == 0 go to test
      (3DGS convention); `test_every=0` puts every image in train.
    - `extent` is 1.1 x the largest distance of a train camera centre from their mean.

    Raises DatasetError with a one-line message for any unusable input.
    """
    dataset = Path(path).expanduser()
    if not dataset.is_dir():
        raise DatasetError(f"{dataset}: dataset folder not found")
    if test_every < 0:
        raise DatasetError(f"test_every must be >= 0, got {test_every}")
    model_dir = find_model_dir(dataset)
    rec = read_model(model_dir)

    image_ids = [i for i in _reg_image_ids(rec) if rec.images[i].has_pose]
    if not image_ids:
        raise DatasetError(f"{model_dir}: the COLMAP model has no registered images")
    if rec.num_points3D() == 0:
        raise DatasetError(f"{model_dir}: the scene has no SfM points (points3D is empty); 3DGS needs them to start")

    images_dir = dataset / images
    if not images_dir.is_dir():
        raise DatasetError(f"{images_dir}: images folder not found")
    names = [rec.images[i].name for i in image_ids]
    missing = [n for n in names if not (images_dir / n).is_file()]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise DatasetError(f"{images_dir / missing[0]}: image listed in the COLMAP model is missing on disk{more}")

    if needs_undistortion(rec):
        check_undistortable(rec, model_dir)

    sizes = {i: image_size(images_dir / rec.images[i].name) for i in image_ids}

    if needs_undistortion(rec):
        camera_sizes: dict[int, tuple[int, int]] = {}
        for i in image_ids:
            cam_id = rec.images[i].camera_id
            prev = camera_sizes.setdefault(cam_id, sizes[i])
            if prev != sizes[i]:
                raise DatasetError(
                    f"{images_dir / rec.images[i].name}: image is {sizes[i][0]}x{sizes[i][1]} but other images "
                    f"of camera {cam_id} are {prev[0]}x{prev[1]}"
                )
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", images)
        cache_root = Path(cache_dir) if cache_dir is not None else default_cache_root(dataset)
        rec, images_dir = undistorted_model(rec, model_dir, images_dir, names, camera_sizes, cache_root / f"undistorted_{safe}")
        by_name = {im.name: int(im_id) for im_id, im in rec.images.items()}
        image_ids = [by_name[n] for n in names]
        sizes = {i: image_size(images_dir / rec.images[i].name) for i in image_ids}

    cameras: list[Camera] = []
    for i in image_ids:
        im = rec.images[i]
        cam = rec.cameras[im.camera_id]
        w, h = sizes[i]
        K = _pinhole_K(cam)
        if (w, h) != (cam.width, cam.height):
            sx, sy = w / cam.width, h / cam.height
            if abs(sx - sy) > 0.02 * max(sx, sy):
                raise DatasetError(
                    f"{images_dir / im.name}: image is {w}x{h} but its camera {im.camera_id} is "
                    f"{cam.width}x{cam.height} (a different aspect ratio; rotated image?)"
                )
            K[0, :] *= w / cam.width
            K[1, :] *= h / cam.height
        cameras.append(
            Camera(
                name=im.name,
                width=w,
                height=h,
                K=torch.from_numpy(K).float(),
                world_to_camera=torch.from_numpy(_cam_from_world_matrix(im)).float(),
                image_path=images_dir / im.name,
            )
        )
    cameras.sort(key=lambda c: c.name)
    if test_every > 0:
        test = [c for k, c in enumerate(cameras) if k % test_every == 0]
        train = [c for k, c in enumerate(cameras) if k % test_every != 0]
    else:
        test, train = [], list(cameras)

    pts = rec.points3D
    xyz = np.stack([p.xyz for p in pts.values()]).astype(np.float32)
    rgb = np.stack([p.color for p in pts.values()]).astype(np.float32) / 255.0
    return Scene(
        train_cameras=train,
        test_cameras=test,
        points=torch.from_numpy(xyz),
        point_colors=torch.from_numpy(rgb),
        extent=nerf_normalization_radius(train if train else cameras),
        source=dataset,
    )
