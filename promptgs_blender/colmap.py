"""Read COLMAP sparse models (text and binary) without pycolmap.

Only the standard library and numpy: this runs inside Blender. The formats are COLMAP's
documented ``cameras``, ``images`` and ``points3D`` files; 2D keypoints and tracks are
skipped because the add-on does not need them.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# model id -> (name, parameter names), as in COLMAP's camera model list
CAMERA_MODELS: dict[int, tuple[str, tuple[str, ...]]] = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    6: ("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    7: ("FOV", ("fx", "fy", "cx", "cy", "omega")),
    8: ("SIMPLE_RADIAL_FISHEYE", ("f", "cx", "cy", "k")),
    9: ("RADIAL_FISHEYE", ("f", "cx", "cy", "k1", "k2")),
    10: ("THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5",
                                        "p0", "p1", "s0", "s1", "s2", "s3")),
}
MODEL_IDS = {name: model_id for model_id, (name, _) in CAMERA_MODELS.items()}
PINHOLE_MODELS = {"SIMPLE_PINHOLE", "PINHOLE"}


class ColmapError(ValueError):
    """A COLMAP model that cannot be read; the message names the file and the problem."""


@dataclass
class Camera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # float64, in the model's parameter order

    @property
    def param_names(self) -> tuple[str, ...]:
        return CAMERA_MODELS[MODEL_IDS[self.model]][1]

    def pinhole(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of the model's pinhole part."""
        p = dict(zip(self.param_names, self.params.tolist()))
        fx = p.get("fx", p.get("f"))
        fy = p.get("fy", p.get("f"))
        return float(fx), float(fy), float(p["cx"]), float(p["cy"])

    def distortion(self) -> dict[str, float]:
        """The non-pinhole parameters (empty for SIMPLE_PINHOLE and PINHOLE)."""
        return {n: float(v) for n, v in zip(self.param_names, self.params)
                if n not in ("f", "fx", "fy", "cx", "cy")}

    def distortion_note(self) -> str:
        """One line for the UI; empty when the camera is an exact pinhole."""
        if self.model in PINHOLE_MODELS:
            return ""
        values = ", ".join(f"{n}={v:.4g}" for n, v in self.distortion().items())
        return (f"{self.model} ({values}): Blender cameras are pinhole, "
                f"the distortion is not shown in the viewport (the trainer undistorts)")


@dataclass
class Image:
    id: int
    qvec: np.ndarray  # (w, x, y, z), world-to-camera rotation
    tvec: np.ndarray  # world-to-camera translation
    camera_id: int
    name: str


@dataclass
class Model:
    path: Path
    cameras: dict[int, Camera]
    images: dict[int, Image]
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))        # [M, 3] float64
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))  # [M, 3] uint8
    errors: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def sorted_images(self) -> list[Image]:
        return sorted(self.images.values(), key=lambda im: im.name)


def find_model_dir(dataset: Path) -> Path:
    """The folder holding the model: ``sparse/0``, ``sparse`` or the folder itself."""
    dataset = Path(dataset)
    for candidate in (dataset / "sparse" / "0", dataset / "sparse", dataset):
        for ext in (".bin", ".txt"):
            if (candidate / f"cameras{ext}").is_file():
                return candidate
    raise ColmapError(f"{dataset}: no COLMAP model (cameras.bin or cameras.txt) in sparse/0, sparse or the folder")


def read_model(path: Path, read_points: bool = True) -> Model:
    """Read a model folder (binary preferred when both forms are present)."""
    path = Path(path)
    if (path / "cameras.bin").is_file():
        ext, cams, imgs, pts = ".bin", _read_cameras_bin, _read_images_bin, _read_points_bin
    elif (path / "cameras.txt").is_file():
        ext, cams, imgs, pts = ".txt", _read_cameras_txt, _read_images_txt, _read_points_txt
    else:
        raise ColmapError(f"{path}: no cameras.bin or cameras.txt")
    files = {name: path / f"{name}{ext}" for name in ("cameras", "images", "points3D")}
    for name in ("cameras", "images"):
        if not files[name].is_file():
            raise ColmapError(f"{files[name]}: missing")
    model = Model(path=path, cameras=_guard(cams, files["cameras"]), images=_guard(imgs, files["images"]))
    if read_points and files["points3D"].is_file():
        model.point_ids, model.points, model.colors, model.errors = _guard(pts, files["points3D"])
    for image in model.images.values():
        if image.camera_id not in model.cameras:
            raise ColmapError(f"{files['images']}: image {image.name} uses camera {image.camera_id}, "
                              f"which {files['cameras'].name} does not define")
    return model


def _guard(reader, file: Path):
    try:
        return reader(file)
    except ColmapError:
        raise
    except (struct.error, ValueError, IndexError, KeyError, UnicodeDecodeError) as exc:
        raise ColmapError(f"{file}: not a valid COLMAP file ({exc})") from None


# --- binary -----------------------------------------------------------------------------

def _read_cameras_bin(file: Path) -> dict[int, Camera]:
    data = file.read_bytes()
    (count,), offset = struct.unpack_from("<Q", data, 0), 8
    cameras = {}
    for _ in range(count):
        cam_id, model_id, width, height = struct.unpack_from("<iiQQ", data, offset)
        offset += 24
        if model_id not in CAMERA_MODELS:
            raise ColmapError(f"{file}: unknown camera model id {model_id}")
        name, names = CAMERA_MODELS[model_id]
        params = np.frombuffer(data, "<f8", len(names), offset).astype(np.float64)
        offset += 8 * len(names)
        cameras[cam_id] = Camera(cam_id, name, int(width), int(height), params)
    return cameras


def _read_images_bin(file: Path) -> dict[int, Image]:
    data = file.read_bytes()
    (count,), offset = struct.unpack_from("<Q", data, 0), 8
    images = {}
    for _ in range(count):
        values = struct.unpack_from("<I7di", data, offset)
        offset += 64
        end = data.index(b"\0", offset)
        name = data[offset:end].decode("utf-8")
        offset = end + 1
        (n_points2d,) = struct.unpack_from("<Q", data, offset)
        offset += 8 + 24 * n_points2d
        images[values[0]] = Image(values[0], np.array(values[1:5]), np.array(values[5:8]), values[8], name)
    return images


def _read_points_bin(file: Path):
    data = file.read_bytes()
    (count,), offset = struct.unpack_from("<Q", data, 0), 8
    ids = np.empty(count, np.int64)
    xyz = np.empty((count, 3), np.float64)
    rgb = np.empty((count, 3), np.uint8)
    err = np.empty(count, np.float64)
    record = struct.Struct("<Q3d3BdQ")
    for i in range(count):
        values = record.unpack_from(data, offset)
        ids[i] = values[0]
        xyz[i] = values[1:4]
        rgb[i] = values[4:7]
        err[i] = values[7]
        offset += record.size + 8 * values[8]
    return ids, xyz, rgb, err


# --- text -------------------------------------------------------------------------------

def _data_lines(file: Path):
    with open(file, encoding="utf-8") as handle:
        for line in handle:
            yield line.rstrip("\r\n")


def _read_cameras_txt(file: Path) -> dict[int, Camera]:
    cameras = {}
    for line in _data_lines(file):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if parts[1] not in MODEL_IDS:
            raise ColmapError(f"{file}: unknown camera model {parts[1]}")
        names = CAMERA_MODELS[MODEL_IDS[parts[1]]][1]
        params = np.array([float(v) for v in parts[4:]], np.float64)
        if len(params) != len(names):
            raise ColmapError(f"{file}: camera {parts[0]} ({parts[1]}) has {len(params)} parameters, expected {len(names)}")
        cameras[int(parts[0])] = Camera(int(parts[0]), parts[1], int(parts[2]), int(parts[3]), params)
    return cameras


def _read_images_txt(file: Path) -> dict[int, Image]:
    images = {}
    lines = _data_lines(file)
    for line in lines:
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split(maxsplit=9)
        if len(parts) < 10:
            raise ColmapError(f"{file}: image line has {len(parts)} fields, expected 10: {line[:60]!r}")
        image_id = int(parts[0])
        images[image_id] = Image(image_id, np.array([float(v) for v in parts[1:5]]),
                                 np.array([float(v) for v in parts[5:8]]), int(parts[8]), parts[9].strip())
        next(lines, None)  # the 2D points line (may be empty)
    return images


def _read_points_txt(file: Path):
    ids, xyz, rgb, err = [], [], [], []
    for line in _data_lines(file):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split(maxsplit=8)
        ids.append(int(parts[0]))
        xyz.append([float(v) for v in parts[1:4]])
        rgb.append([int(v) for v in parts[4:7]])
        err.append(float(parts[7]))
    return (np.array(ids, np.int64), np.array(xyz, np.float64).reshape(-1, 3),
            np.array(rgb, np.uint8).reshape(-1, 3), np.array(err, np.float64))
