"""The COLMAP scenes the tests run on: two that the tests make, the real ones when present.

The made scenes are ray-cast with numpy from known geometry (a room with a textured
floor and walls, two textured boxes on the floor), so what a test asserts about them is
known apart from the code under test:

- ``pinhole``: 24 views, a binary model with a SIMPLE_PINHOLE and a PINHOLE camera, JPEG
  photos in ``images/`` (336×252) and ``images_4/`` (84×63); each SfM point's track lists
  the views that see it (nothing in between), at its exact projection.
- ``distorted``: 16 views, a text model with a SIMPLE_RADIAL and an OPENCV camera, PNG
  photos rendered through the distortion (each pixel's ray is pycolmap's own
  ``cam_from_img`` of that pixel), tracks at the exact distorted projections.

Each builds in about 5 s of one core. ``../shared/data/tumbler`` (binary, SIMPLE_PINHOLE)
and ``../shared/data/fern`` (text, SIMPLE_RADIAL) are described by the same
:class:`SceneFacts` and join the made scenes wherever they are present
(:func:`pinhole_scene_names`, :func:`distorted_scene_names`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from promptgs_engine.bench.toy_scene import look_at

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@dataclass(frozen=True)
class SceneFacts:
    """What is known about a scene; tests assert these values."""

    name: str  # the dataset folder's name (the add-on names its objects after it)
    path: Path
    form: str  # "binary" or "text" model files
    n_images: int
    names: tuple[str, ...]  # image names, sorted (a real scene's: its photos folder's)
    n_points: int
    size: tuple[int, int]  # (width, height) of every camera of the model
    models: dict[int, str]  # camera id -> COLMAP camera model
    small: str = ""  # a folder of smaller photos ("images_4"), if any
    small_size: tuple[int, int] = (0, 0)
    observation_px: tuple[float, float] = (0.0, 0.0)  # bounds on the median and 90th percentile of reprojection
    distortion_words: tuple[str, ...] = ()  # in the add-on's distortion note
    focal: float = 0.0  # fx of the first image's camera (the undistorted camera keeps it)
    render_camera: str = ""  # a view that sees the scene's object well...
    prompt_rect: tuple[int, int, int, int] = (0, 0, 0, 0)  # ...and its pixel rectangle there (full size)
    poses: dict[str, np.ndarray] = field(default_factory=dict, compare=False)  # name -> world-to-camera [4, 4], made scenes
    intrinsics: dict[str, np.ndarray] = field(default_factory=dict, compare=False)  # name -> K [3, 3], made pinhole scene

    @property
    def model_dir(self) -> Path:
        return self.path / "sparse" / "0"

    def __str__(self) -> str:
        return self.name


# --- the real scenes beside the repository ----------------------------------------------

def _photos(folder: Path) -> tuple[str, ...]:
    return tuple(sorted(p.name for p in folder.iterdir())) if folder.is_dir() else ()


TUMBLER = SceneFacts(
    name="tumbler", path=SHARED_DATA / "tumbler", form="binary", n_images=77,
    names=_photos(SHARED_DATA / "tumbler" / "images"), n_points=9262, size=(800, 600),
    models={i: "SIMPLE_PINHOLE" for i in range(1, 78)}, small="images_4", small_size=(200, 150),
    observation_px=(1.0, 2.0), render_camera="12.jpg", prompt_rect=(210, 160, 560, 380))  # the cup in 12.jpg
FERN = SceneFacts(
    name="fern", path=SHARED_DATA / "fern", form="text", n_images=20,
    names=_photos(SHARED_DATA / "fern" / "images"), n_points=10091, size=(504, 378),
    models={1: "SIMPLE_RADIAL"}, distortion_words=("SIMPLE_RADIAL", "k=0.01975"), focal=407.5658)


def real_scene(facts: SceneFacts) -> bool:
    """Whether a real scene is on this machine (its model folder and photos)."""
    return (facts.model_dir).is_dir() and (facts.path / "images").is_dir()


def pinhole_scene_names() -> list[str]:
    """The pinhole scenes a test runs on here: the made one, tumbler when present."""
    return ["pinhole"] + (["tumbler"] if real_scene(TUMBLER) else [])


def distorted_scene_names() -> list[str]:
    """The distorted scenes a test runs on here: the made one, fern when present."""
    return ["distorted"] + (["fern"] if real_scene(FERN) else [])


def subset_of_model(model_dir: Path, images: Path, names: set[str], folder: Path) -> Path:
    """A dataset in `folder`: the model in `model_dir` restricted to the images `names`, and
    `images` (linked) as its photos."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    for image_id in list(rec.reg_image_ids()):
        image = rec.images[image_id]
        if image.name not in names:
            rec.deregister_frame(image.frame_id)
    (folder / "sparse" / "0").mkdir(parents=True)
    rec.write(str(folder / "sparse" / "0"))
    (folder / "images").symlink_to(images)
    return folder


# --- the made scenes: geometry ------------------------------------------------------------

ROOM = (np.array([-6.0, -6.0, 0.0]), np.array([6.0, 6.0, 5.0]))  # seen from inside
BOXES = (  # (centre, half size): the "object" and a smaller one beside it, on the floor
    (np.array([0.0, 0.0, 0.45]), np.array([0.6, 0.4, 0.45])),
    (np.array([1.4, -1.1, 0.3]), np.array([0.3, 0.3, 0.3])),
)
CELL = {"room": 0.25, "floor": 0.12, "box": 0.07}  # texture cell sizes (metres)
TARGET = np.array([0.0, 0.0, 0.4])
_PALETTE = np.random.default_rng(11).uniform(0.05, 0.95, size=(4096, 3))
_TINT = np.random.default_rng(12).uniform(0.2, 0.8, size=(18, 3))


def _slabs(origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(dirs) < 1e-15, 1e-15, dirs)
    t1, t2 = (lo - origin) * inv, (hi - origin) * inv
    return np.minimum(t1, t2), np.maximum(t1, t2)


def cast(origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance along each ray [N, 3] (unit or not: in units of the ray) to the first
    surface, and that surface's id (0-5 the room's faces, 6+ the boxes' faces)."""
    _, t_out = _slabs(origin, dirs, *ROOM)
    axis = t_out.argmin(1)
    t = t_out[np.arange(len(dirs)), axis]
    face = 2 * axis + (dirs[np.arange(len(dirs)), axis] > 0)
    for b, (centre, half) in enumerate(BOXES):
        t_in, t_far = _slabs(origin, dirs, centre - half, centre + half)
        axis_in = t_in.argmax(1)
        near, far = t_in.max(1), t_far.min(1)
        hit = (near <= far) & (near > 1e-9) & (near < t)
        t = np.where(hit, near, t)
        entered = 2 * axis_in + (dirs[np.arange(len(dirs)), axis_in] < 0)  # through its low or high side
        face = np.where(hit, 6 + 6 * b + entered, face)
    return t, face


def colour(points: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Texture of each surface point [N, 3] in 0..1: a tint per face, cells of random colours
    four cells wide over it, and fine cells of random colours (a few pixels in a photo)."""
    axis = (face % 6) // 2
    u = np.where(axis == 0, points[:, 1], points[:, 0])
    v = np.where(axis == 2, points[:, 1], points[:, 2])
    size = np.where(face >= 6, CELL["box"], np.where(face == 4, CELL["floor"], CELL["room"]))
    rgb = 0.35 * _TINT[face]
    for scale, weight in ((4.0, 0.4), (1.0, 0.25)):
        i = np.floor(u / (scale * size)).astype(np.int64)
        j = np.floor(v / (scale * size)).astype(np.int64)
        cell = (i * 73856093) ^ (j * 19349663) ^ (face.astype(np.int64) * 83492791 + int(scale))
        rgb = rgb + weight * _PALETTE[cell % len(_PALETTE)]
    return rgb


def ring_poses(n: int, radius: float, height: float) -> list[np.ndarray]:
    poses = []
    for i in range(n):
        a = 2 * math.pi * i / n + 0.1
        centre = np.array([radius * math.cos(a), radius * math.sin(a), height + 0.35 * math.sin(3 * a)])
        poses.append(look_at(centre, TARGET + [0.1 * math.sin(5 * a), 0.1 * math.cos(2 * a), 0.0]))
    return poses


def sample_surface_points(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points on the floor near the boxes (half), on the boxes (a third), on the walls, and
    the id of the surface each lies on (as :func:`cast` numbers them)."""
    n_floor, n_box = n // 2, n // 3
    r, a = 3.2 * np.sqrt(rng.uniform(size=n_floor)), rng.uniform(0, 2 * math.pi, size=n_floor)
    points = [np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n_floor)], 1)]
    faces = [np.full(n_floor, 4)]  # the room's low z side
    for k in range(n_box):
        b = k % 2
        centre, half = BOXES[b]
        axis = int(rng.integers(0, 3))
        high = axis == 2 or rng.uniform() < 0.5  # no points under a box
        p = centre + half * rng.uniform(-1, 1, size=3)
        p[axis] = centre[axis] + (half[axis] if high else -half[axis])
        points.append(p[None])
        faces.append(np.array([6 + 6 * b + 2 * axis + int(high)]))
    n_wall = n - n_floor - n_box
    a = rng.uniform(0, 2 * math.pi, size=n_wall)
    d = np.stack([np.cos(a), np.sin(a), np.zeros(n_wall)], 1)
    axis = np.abs(d[:, :2]).argmax(1)
    wall = d * (6.0 / np.abs(d[:, :2]).max(1))[:, None]
    wall[:, 2] = rng.uniform(0.2, 3.5, size=n_wall)
    points.append(wall)
    faces.append(2 * axis + (d[np.arange(n_wall), axis] > 0))
    points, faces = np.concatenate(points), np.concatenate(faces)
    on_floor_under_a_box = np.zeros(len(points), bool)
    for centre, half in BOXES:
        on_floor_under_a_box |= (faces == 4) & np.all(np.abs(points[:, :2] - centre[:2]) < half[:2], axis=1)
    return points[~on_floor_under_a_box], faces[~on_floor_under_a_box]


# --- the made scenes: cameras, photos, model ---------------------------------------------


@dataclass(frozen=True)
class _Camera:
    camera_id: int
    model: str
    params: tuple[float, ...]
    width: int
    height: int

    def pycolmap(self):
        import pycolmap

        return pycolmap.Camera(model=self.model, width=self.width, height=self.height,
                               params=list(self.params), camera_id=self.camera_id)

    def K(self) -> np.ndarray:
        """The pinhole intrinsics [3, 3] of a SIMPLE_PINHOLE or PINHOLE camera."""
        fx, fy = (self.params[0],) * 2 if self.model == "SIMPLE_PINHOLE" else self.params[:2]
        cx, cy = self.params[-2:]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
PINHOLE_CAMERAS = (_Camera(1, "SIMPLE_PINHOLE", (262.0, 168.0, 126.0), 336, 252),
                   _Camera(2, "PINHOLE", (251.0, 255.5, 171.25, 123.5), 336, 252))
DISTORTED_CAMERAS = (_Camera(1, "SIMPLE_RADIAL", (270.0, 168.0, 126.0, 0.05), 336, 252),
                     _Camera(2, "OPENCV", (265.0, 268.0, 166.0, 128.0, -0.06, 0.01, 0.001, -0.0015), 336, 252))
DISTORTED_WORDS = ("SIMPLE_RADIAL", "k=0.05", "OPENCV", "k1=-0.06", "k2=0.01", "p1=0.001", "p2=-0.0015")


def _render(camera: _Camera, world_to_camera: np.ndarray, supersample: int = 2) -> np.ndarray:
    """uint8 [H, W, 3]: each pixel the mean of supersample² rays through the camera model."""
    s = supersample
    offsets = (np.arange(s) + 0.5) / s
    xs = (np.arange(camera.width)[:, None] + offsets).ravel()
    ys = (np.arange(camera.height)[:, None] + offsets).ravel()
    px = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    normalized = camera.pycolmap().cam_from_img(px)
    rays_cam = np.concatenate([normalized, np.ones((len(px), 1))], 1)
    rot, centre = world_to_camera[:3, :3], -world_to_camera[:3, :3].T @ world_to_camera[:3, 3]
    rays = (rays_cam @ rot).astype(np.float32)  # camera to world: R^T d
    t, face = cast(centre.astype(np.float32), rays)
    rgb = colour(centre + t[:, None] * rays, face).reshape(camera.height * s, camera.width * s, 3)
    rgb = rgb.reshape(camera.height, s, camera.width, s, 3).mean((1, 3))
    return (rgb * 255).round().clip(0, 255).astype(np.uint8)


def _observations(points: np.ndarray, camera: _Camera, world_to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which points the view sees (in the frame, nothing in between) and their pixels."""
    cam = camera.pycolmap()
    local = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    front = local[:, 2] > 0.1
    corners = cam.cam_from_img(np.array([[0.0, 0.0], [camera.width, 0.0], [0.0, camera.height],
                                         [camera.width, camera.height]]))
    reach = np.abs(corners).max(0) * 1.05  # the distortion polynomial folds back far outside
    normalized = local[:, :2] / np.where(front, local[:, 2], 1.0)[:, None]
    near = front & np.all(np.abs(normalized) <= reach, axis=1)
    uv = np.full((len(points), 2), -1.0)
    uv[near] = cam.img_from_cam(local[near])
    inside = near & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    centre = -world_to_camera[:3, :3].T @ world_to_camera[:3, 3]
    t, _ = cast(centre, points - centre)  # the point itself is at t = 1
    return inside & (np.abs(t - 1.0) < 1e-6), uv


def _write_model(model_dir: Path, form: str, cameras: tuple[_Camera, ...], names: list[str],
                 poses: list[np.ndarray], points: np.ndarray, colours: np.ndarray, seen: np.ndarray,
                 pixels: list[np.ndarray]) -> None:
    """The COLMAP model: the cameras, the images with their keypoints (the points each
    sees), the points with their tracks; binary or text."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    for camera in cameras:
        rec.add_camera_with_trivial_rig(camera.pycolmap())
    index = np.full(seen.shape, -1)
    for i, (name, pose) in enumerate(zip(names, poses)):
        idx = np.flatnonzero(seen[i])
        index[i, idx] = np.arange(len(idx))
        image = pycolmap.Image(name=name, keypoints=pixels[i][idx], camera_id=cameras[i % len(cameras)].camera_id,
                               image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:3, :3]), pose[:3, 3]))
    for j, (xyz, rgb) in enumerate(zip(points, colours)):
        track = pycolmap.Track()
        for i in np.flatnonzero(seen[:, j]):
            track.add_element(int(i + 1), int(index[i, j]))
        rec.add_point3D(xyz, track, rgb)
    (rec.write_binary if form == "binary" else rec.write_text)(str(model_dir))


def _object_rect(camera: _Camera, pose: np.ndarray) -> tuple[int, int, int, int]:
    """The pixel rectangle (x0, y0, x1, y1) around the first box's corners in a view."""
    centre, half = BOXES[0]
    corners = np.array([centre + half * np.array([x, y, z]) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    uv = np.asarray(camera.pycolmap().img_from_cam(corners @ pose[:3, :3].T + pose[:3, 3]))
    return int(uv[:, 0].min()), int(uv[:, 1].min()), int(math.ceil(uv[:, 0].max())), int(math.ceil(uv[:, 1].max()))


def _make(out: Path, cameras: tuple[_Camera, ...], n_views: int, n_points: int, ext: str, form: str,
          prefix: str, small: int, seed: int) -> SceneFacts:
    from PIL import Image

    rng = np.random.default_rng(seed)
    folders = [out / "images"] + ([out / f"images_{small}"] if small else [])
    for folder in folders + [out / "sparse" / "0"]:
        folder.mkdir(parents=True)
    save = {"quality": 95} if ext == "jpg" else {}
    poses = ring_poses(n_views, radius=3.6, height=1.7)
    points, faces = sample_surface_points(n_points, rng)
    names = [f"{prefix}_{i:02d}.{ext}" for i in range(n_views)]
    camera_of = [cameras[i % len(cameras)] for i in range(n_views)]
    seen, pixels = [], []
    for name, camera, pose in zip(names, camera_of, poses):
        photo = Image.fromarray(_render(camera, pose))
        photo.save(out / "images" / name, **save)
        if small:
            photo.reduce(small).save(out / f"images_{small}" / name, **save)
        visible, uv = _observations(points, camera, pose)
        seen.append(visible)
        pixels.append(uv)
    seen = np.array(seen)
    keep = seen.sum(0) >= 2  # as SfM would: a point seen by two views at least
    points, seen, pixels = points[keep], seen[:, keep], [uv[keep] for uv in pixels]
    colours = (colour(points, faces[keep]) * 255).round().astype(np.uint8)
    _write_model(out / "sparse" / "0", form, cameras, names, poses, points, colours, seen, pixels)

    view = n_views // 8 + 3  # a view of the object whose name sorts into the training split
    first = cameras[0]
    return SceneFacts(
        name=out.name, path=out, form=form, n_images=n_views, names=tuple(sorted(names)), n_points=len(points),
        size=(first.width, first.height), models={c.camera_id: c.model for c in cameras},
        small=f"images_{small}" if small else "",
        small_size=(first.width // small, first.height // small) if small else (0, 0),
        observation_px=(0.01, 0.02),  # the observations are exact projections: float32 rounding is left
        distortion_words=DISTORTED_WORDS if form == "text" else (),
        focal=first.params[0], render_camera=names[view], prompt_rect=_object_rect(camera_of[view], poses[view]),
        poses=dict(zip(names, poses)),
        intrinsics={name: camera.K() for name, camera in zip(names, camera_of) if camera.model in PINHOLE_MODELS})


def make_pinhole_scene(out: Path) -> SceneFacts:
    """The binary pinhole scene (24 views, images and images_4) in ``out``."""
    return _make(Path(out), PINHOLE_CAMERAS, n_views=24, n_points=2400, ext="jpg", form="binary",
                 prefix="view", small=4, seed=1)


def make_distorted_scene(out: Path) -> SceneFacts:
    """The text scene with distorted cameras (16 views) in ``out``."""
    return _make(Path(out), DISTORTED_CAMERAS, n_views=16, n_points=3000, ext="png", form="text",
                 prefix="image", small=0, seed=2)
