"""Prompt boxes: oriented boxes in dataset (COLMAP world) coordinates that mark where
training effort should go.

File format (also accepted inline in a job file)::

    {"prompts": [{"center": [x, y, z], "size": [sx, sy, sz],
                  "rotation_wxyz": [w, x, y, z], "weight": 1.0}]}

``size`` is the full edge length along the box's own axes, ``rotation_wxyz`` the
box-to-world rotation as a quaternion (need not be normalised, must not be zero),
``weight`` (optional, default 1, >= 0) how strongly the box is favoured.

Image-plane convention (shared with the rasterizer and ``errorfield``): continuous pixel
coordinates where pixel column ``i`` / row ``j`` covers ``[i, i+1) x [j, j+1)`` and its
centre is ``(i + 0.5, j + 0.5)``; a camera-space point ``X`` projects to ``K @ X / z``.
The image is the rectangle ``[0, W] x [0, H]``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Protocol, Sequence

import numpy as np
import torch

from .errors import PromptError

__all__ = [
    "CameraLike",
    "PromptBox",
    "BoxProjection",
    "prompts_from_json",
    "prompts_to_json",
    "load_prompts",
    "save_prompts",
    "boxes_contain",
    "contains_any",
    "max_weight",
    "project_box",
    "check_visible",
    "center_prompt",
    "scene_center_prompt",
    "scene_look_point",
    "placement_warnings",
    "camera_center",
]

_KEYS = ("center", "size", "rotation_wxyz", "weight")
# Keys a proposal file (`proposals`) adds to an entry; training reads the box and ignores them.
_PROPOSAL_KEYS = ("confidence", "evidence")


class CameraLike(Protocol):
    """What this module needs of a camera (see the Camera contract in docs/interfaces.md)."""

    width: int
    height: int
    K: Any  # [3, 3] tensor or array
    world_to_camera: Any  # [4, 4], COLMAP: x right, y down, z forward


def _quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _matrix_to_quat(r: np.ndarray) -> tuple[float, float, float, float]:
    # Shepperd's method: pick the largest diagonal combination for stability.
    t = float(np.trace(r))
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = (0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = ((r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s)
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = ((r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s)
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = ((r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s)
    if q[0] < 0:
        q = tuple(-v for v in q)
    return tuple(float(v) for v in q)  # type: ignore[return-value]


@dataclass(frozen=True)
class PromptBox:
    """An oriented box: ``center`` [3], full edge lengths ``size`` [3], box-to-world
    rotation ``rotation_wxyz`` and a non-negative ``weight``."""

    center: tuple[float, float, float]
    size: tuple[float, float, float]
    rotation_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    weight: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", tuple(float(v) for v in self.center))
        object.__setattr__(self, "size", tuple(float(v) for v in self.size))
        object.__setattr__(self, "rotation_wxyz", tuple(float(v) for v in self.rotation_wxyz))
        object.__setattr__(self, "weight", float(self.weight))
        problem = _box_problem(self.center, self.size, self.rotation_wxyz, self.weight)
        if problem:
            raise PromptError(f"invalid prompt box: {problem}")

    # -- geometry -------------------------------------------------------------------
    def rotation_matrix(self) -> np.ndarray:
        """[3, 3] float64 box-to-world rotation (columns are the box axes in world)."""
        return _quat_to_matrix(self.rotation_wxyz)

    def box_to_world(self) -> np.ndarray:
        """[4, 4] float64 matrix mapping the unit cube [-0.5, 0.5]^3 onto the box."""
        m = np.eye(4)
        m[:3, :3] = self.rotation_matrix() * np.asarray(self.size)[None, :]
        m[:3, 3] = self.center
        return m

    @classmethod
    def from_matrix(cls, matrix: Any, base_edge: float = 1.0, weight: float = 1.0) -> "PromptBox":
        """Box from a 4×4 affine box-to-world matrix (rotation × scale + translation) that
        maps a cube of edge ``base_edge`` centred at the origin (a Blender CUBE empty of
        display size 1 has ``base_edge=2``) onto the box."""
        m = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
        cols = m[:3, :3]
        scale = np.linalg.norm(cols, axis=0)
        if not np.all(np.isfinite(m)) or np.any(scale <= 0):
            raise PromptError("prompt matrix is degenerate (zero scale or non-finite entries)")
        rot = cols / scale[None, :]
        if np.linalg.det(rot) < 0:  # mirrored: flip one axis, sizes stay positive
            rot[:, 0] = -rot[:, 0]
        return cls(tuple(m[:3, 3]), tuple(scale * base_edge), _matrix_to_quat(rot), weight)

    def corners(self) -> torch.Tensor:
        """[8, 3] float64 world corners; corner ``i`` has local sign bits (i&1, i&2, i&4)."""
        signs = np.array([[(i >> b & 1) * 2 - 1 for b in range(3)] for i in range(8)], dtype=np.float64)
        local = signs * (np.asarray(self.size) / 2)[None, :]
        world = local @ self.rotation_matrix().T + np.asarray(self.center)[None, :]
        return torch.from_numpy(world)

    def volume(self) -> float:
        return float(np.prod(self.size))

    def contains(self, points: torch.Tensor) -> torch.Tensor:
        """bool [N]: whether each point [N, 3] lies inside the box (faces included)."""
        return boxes_contain([self], points)[0]

    def project(self, camera: CameraLike, near: float = 0.01) -> "BoxProjection":
        return project_box(self, camera, near)

    # -- serialisation ----------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "center": list(self.center),
            "size": list(self.size),
            "rotation_wxyz": list(self.rotation_wxyz),
            "weight": self.weight,
        }


def center_prompt(weight: float = 1.0) -> PromptBox:
    """The paper's "Ours*" prompt taken literally: an axis-aligned unit box (1 × 1 × 1) at
    the origin. It means what the paper means only in a normalised scene; the trainer's
    ``--center-prompt`` uses `scene_center_prompt`."""
    return PromptBox((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (1.0, 0.0, 0.0, 0.0), weight)


# Edge of the centre box as a fraction of the median camera-to-centre distance: at a 60°
# field of view such a box spans about a quarter of the image width from a typical view.
CENTER_BOX_FRACTION = 0.25


# Weight of each camera's SfM depth along its axis in `scene_look_point`, against 1 for the
# distance across its axis: it only decides where the axes alone do not (parallel axes).
DEPTH_PULL = 0.02


def scene_look_point(cameras: Sequence[CameraLike], points: Any) -> tuple[np.ndarray, float]:
    """Where the cameras look, in the scene's own frame, and how far they are from it.

    The point closest to all optical axes in least squares (where the views converge),
    with a weak pull (`DEPTH_PULL`) towards each camera's median SfM-point depth along its
    axis (of the points in its image), which settles the depth where the axes are nearly
    parallel (a forward-facing capture such as fern). Returns the point and the median
    distance of the camera centres from it."""
    pts = _as_np(points)
    lhs = np.zeros((3, 3))
    rhs = np.zeros(3)
    centres = []
    for cam in cameras:
        w2c = _as_np(cam.world_to_camera)
        k = _as_np(cam.K)
        centre = camera_center(cam)
        axis = w2c[2, :3]  # the optical axis in world: third row of R
        centres.append(centre)
        across = np.eye(3) - np.outer(axis, axis)
        lhs += across
        rhs += across @ centre
        z = pts @ w2c[2, :3] + w2c[2, 3]
        front = z > 1e-6
        if front.any():
            uvw = pts[front] @ w2c[:3, :3].T + w2c[:3, 3]
            uv = (uvw @ k.T)[:, :2] / z[front, None]
            in_image = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            if in_image.any():
                depth = float(np.median(z[front][in_image]))
                lhs += DEPTH_PULL * np.outer(axis, axis)
                rhs += DEPTH_PULL * axis * (axis @ centre + depth)
    try:
        look = np.linalg.solve(lhs, rhs)
    except np.linalg.LinAlgError:  # one camera, or every axis parallel with no points seen
        look = np.median(pts, axis=0) if len(pts) else np.mean(centres, axis=0)
    distance = float(np.median(np.linalg.norm(np.stack(centres) - look, axis=1)))
    return look, distance


def scene_center_prompt(
    cameras: Sequence[CameraLike], points: Any, weight: float = 1.0, fraction: float = CENTER_BOX_FRACTION
) -> PromptBox:
    """The centre prompt ("Ours*") in the scene's own frame: an axis-aligned cube at the
    point the cameras look at (`scene_look_point`), its edge ``fraction`` of the median
    camera distance from that point. A COLMAP model's origin and scale are arbitrary, so
    the paper's unit box at the origin lands anywhere (among the cameras of tumbler and
    fern); this box covers the same share of a typical view in every capture."""
    look, distance = scene_look_point(cameras, points)
    edge = max(fraction * distance, 1e-6)
    return PromptBox(tuple(float(v) for v in look), (edge, edge, edge), (1.0, 0.0, 0.0, 0.0), weight)


# A box whose centre is nearer to a camera than this fraction of the cameras' median
# distance from where they look lies among the cameras (`placement_warnings`).
AMONG_CAMERAS_FRACTION = 0.25


def placement_warnings(
    boxes: Sequence[PromptBox], cameras: Sequence[CameraLike], points: Any, names: Sequence[str] | None = None
) -> list[str]:
    """One line per box that lies among the cameras rather than in the scene they look at:
    its centre is within a camera's half-diagonal of the box, or nearer to some camera
    than `AMONG_CAMERAS_FRACTION` of the cameras' median distance from their look point
    (`scene_look_point`). Such a box is seen from very close or from inside, by few views
    (the paper's unit box at a COLMAP origin often lands there). A box that no camera
    sees at all is an error instead (`check_visible`)."""
    out: list[str] = []
    if not cameras or not boxes:
        return out
    centres = np.stack([camera_center(c) for c in cameras])
    _, distance = scene_look_point(cameras, points)
    for i, box in enumerate(boxes):
        reach = max(0.5 * float(np.linalg.norm(box.size)), AMONG_CAMERAS_FRACTION * distance)
        dist = np.linalg.norm(centres - np.asarray(box.center), axis=1)
        j = int(np.argmin(dist))
        if dist[j] <= reach:
            who = names[j] if names is not None else f"camera {j}"
            out.append(
                f"prompt {i} (center {[round(float(v), 3) for v in box.center]}, size {[round(float(v), 3) for v in box.size]}) "
                f"lies among the cameras: {who} is {dist[j]:.3g} units from its centre, while the cameras are a median "
                f"{distance:.3g} units from where they look; check where the box is"
            )
    return out


# -------------------------------------------------------------------------------------
# validation and the JSON form
# -------------------------------------------------------------------------------------


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _box_problem(center: Any, size: Any, rot: Any, weight: Any) -> str | None:
    for name, value, n in (("center", center, 3), ("size", size, 3), ("rotation_wxyz", rot, 4)):
        if not isinstance(value, (list, tuple)) or len(value) != n or not all(_is_number(v) for v in value):
            return f"'{name}' must be a list of {n} numbers, got {json.dumps(value, default=str)}"
        if not all(math.isfinite(v) for v in value):
            return f"'{name}' has a non-finite number: {list(value)}"
    if not all(v > 0 for v in size):
        return f"'size' must be positive edge lengths, got {list(size)}"
    if math.sqrt(sum(v * v for v in rot)) < 1e-12:
        return "'rotation_wxyz' is the zero quaternion"
    if not _is_number(weight) or not math.isfinite(weight) or weight < 0:
        return f"'weight' must be a finite number >= 0, got {json.dumps(weight, default=str)}"
    return None


def prompts_from_json(obj: Any, source: str = "prompts") -> list[PromptBox]:
    """Boxes from the parsed JSON object ``{"prompts": [...]}``; ``source`` (a file name or
    "job file") names where it came from in errors. Raises :class:`PromptError`."""
    if not isinstance(obj, dict) or "prompts" not in obj:
        raise PromptError(f'{source}: expected an object {{"prompts": [...]}}')
    entries = obj["prompts"]
    if not isinstance(entries, list):
        raise PromptError(f"{source}: 'prompts' must be a list, got {type(entries).__name__}")
    boxes = []
    for i, entry in enumerate(entries):
        where = f"{source}: prompt {i}"
        if not isinstance(entry, dict):
            raise PromptError(f"{where}: expected an object, got {type(entry).__name__}")
        missing = [k for k in ("center", "size", "rotation_wxyz") if k not in entry]
        if missing:
            raise PromptError(f"{where}: missing key(s) {', '.join(repr(k) for k in missing)}")
        unknown = sorted(set(entry) - set(_KEYS) - set(_PROPOSAL_KEYS))
        if unknown:
            raise PromptError(f"{where}: unknown key(s) {', '.join(repr(k) for k in unknown)}")
        conf = entry.get("confidence", 1.0)
        if not _is_number(conf) or not 0.0 <= conf <= 1.0:
            raise PromptError(f"{where}: 'confidence' must be a number in [0, 1], got {json.dumps(conf, default=str)}")
        if not isinstance(entry.get("evidence", {}), dict):
            raise PromptError(f"{where}: 'evidence' must be an object")
        weight = entry.get("weight", 1.0)
        problem = _box_problem(entry["center"], entry["size"], entry["rotation_wxyz"], weight)
        if problem:
            raise PromptError(f"{where}: {problem}")
        boxes.append(PromptBox(entry["center"], entry["size"], entry["rotation_wxyz"], weight))
    return boxes


def prompts_to_json(boxes: Iterable[PromptBox]) -> dict[str, Any]:
    return {"prompts": [b.to_dict() for b in boxes]}


def load_prompts(path: str | Path) -> list[PromptBox]:
    """Read a prompt file. Raises :class:`PromptError` with a one-line message naming the
    file and the bad entry."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise PromptError(f"{path}: prompt file not found") from None
    except OSError as e:
        raise PromptError(f"{path}: cannot read prompt file ({e.strerror})") from None
    try:
        # Python's json accepts NaN/Infinity; they are caught by validation below.
        obj = json.loads(text)
    except json.JSONDecodeError as e:
        raise PromptError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
    return prompts_from_json(obj, str(path))


def save_prompts(path: str | Path, boxes: Iterable[PromptBox]) -> None:
    Path(path).write_text(json.dumps(prompts_to_json(boxes), indent=2) + "\n", encoding="utf-8")


# -------------------------------------------------------------------------------------
# containment
# -------------------------------------------------------------------------------------


def boxes_contain(boxes: Sequence[PromptBox], points: torch.Tensor) -> torch.Tensor:
    """bool [B, N]: entry (b, n) says whether point n (of ``points`` [N, 3]) is inside box b
    (faces included)."""
    n = points.shape[0]
    if len(boxes) == 0:
        return torch.zeros((0, n), dtype=torch.bool, device=points.device)
    dtype = points.dtype if points.dtype.is_floating_point else torch.float32
    p = points.to(dtype)
    centers = torch.tensor([b.center for b in boxes], dtype=dtype, device=p.device)  # [B, 3]
    rots = torch.tensor(np.stack([b.rotation_matrix() for b in boxes]), dtype=dtype, device=p.device)
    half = torch.tensor([b.size for b in boxes], dtype=dtype, device=p.device) / 2  # [B, 3]
    # local = R^T (p - c), computed as (p - c) @ R per box
    local = torch.einsum("bnj,bji->bni", p[None, :, :] - centers[:, None, :], rots)
    return (local.abs() <= half[:, None, :]).all(dim=-1)


def contains_any(boxes: Sequence[PromptBox], points: torch.Tensor) -> torch.Tensor:
    """bool [N]: inside at least one box (the union)."""
    inside = boxes_contain(boxes, points)
    if inside.shape[0] == 0:
        return torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    return inside.any(dim=0)


def max_weight(boxes: Sequence[PromptBox], points: torch.Tensor) -> torch.Tensor:
    """float [N]: the largest weight among the boxes containing each point, 0 outside all."""
    dtype = points.dtype if points.dtype.is_floating_point else torch.float32
    inside = boxes_contain(boxes, points)
    if inside.shape[0] == 0:
        return torch.zeros(points.shape[0], dtype=dtype, device=points.device)
    w = torch.tensor([b.weight for b in boxes], dtype=dtype, device=points.device)
    return torch.where(inside, w[:, None], torch.zeros((), dtype=dtype, device=points.device)).amax(dim=0)


# -------------------------------------------------------------------------------------
# projection into a camera
# -------------------------------------------------------------------------------------


def _as_np(t: Any) -> np.ndarray:
    if isinstance(t, torch.Tensor):
        t = t.detach().cpu().double().numpy()
    return np.asarray(t, dtype=np.float64)


def camera_center(camera: CameraLike) -> np.ndarray:
    """[3] float64 camera centre in world: C = -R^T t."""
    w2c = _as_np(camera.world_to_camera)
    return -w2c[:3, :3].T @ w2c[:3, 3]


@dataclass
class BoxProjection:
    """How one box appears in one camera. Areas are in pixels of that camera's size;
    ``bbox`` is ``(x0, y0, x1, y1)`` in continuous pixel coordinates, clipped to
    ``[0, W] x [0, H]`` (None when nothing is inside the image)."""

    in_front: bool  # some part of the box lies beyond the near plane
    bbox: tuple[float, float, float, float] | None
    visible_area: float  # silhouette area inside the image
    projected_area: float  # whole silhouette area (of the part in front of the near plane)
    in_image_fraction: float  # visible_area / projected_area (0 when nothing projects)
    distance: float  # camera centre to box centre
    depth: float  # camera-space z of the box centre
    view_cos: float  # cosine between the optical axis and the direction to the box centre
    polygon: list[tuple[float, float]] = field(default_factory=list, repr=False)  # clipped silhouette

    @property
    def visible(self) -> bool:
        return self.visible_area > 0.0

    def pixel_bbox(self) -> tuple[int, int, int, int] | None:
        """Integer pixel index range ``(i0, j0, i1, j1)`` (ends exclusive) covering ``bbox``."""
        if self.bbox is None:
            return None
        x0, y0, x1, y1 = self.bbox
        return int(math.floor(x0)), int(math.floor(y0)), int(math.ceil(x1)), int(math.ceil(y1))


# 12 edges of the corner numbering used by PromptBox.corners (pairs differing in one bit).
_EDGES = [(i, i | (1 << b)) for i in range(8) for b in range(3) if not i & (1 << b)]


def _hull(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Convex hull, counter-clockwise (monotone chain)."""
    pts = sorted(set(points))
    if len(pts) <= 2:
        return pts

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, float]] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[tuple[float, float]] = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def _area(poly: list[tuple[float, float]]) -> float:
    s = 0.0
    for k in range(len(poly)):
        x0, y0 = poly[k]
        x1, y1 = poly[(k + 1) % len(poly)]
        s += x0 * y1 - x1 * y0
    return abs(s) / 2


def _clip_rect(poly: list[tuple[float, float]], w: float, h: float) -> list[tuple[float, float]]:
    """Clip a convex polygon to [0, w] x [0, h] (Sutherland–Hodgman)."""
    for axis, bound, keep_below in ((0, 0.0, False), (0, w, True), (1, 0.0, False), (1, h, True)):
        if not poly:
            break
        out: list[tuple[float, float]] = []
        for k in range(len(poly)):
            a, b = poly[k - 1], poly[k]
            a_in = a[axis] <= bound if keep_below else a[axis] >= bound
            b_in = b[axis] <= bound if keep_below else b[axis] >= bound
            if b_in != a_in:
                t = (bound - a[axis]) / (b[axis] - a[axis])
                out.append((a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])))
            if b_in:
                out.append(b)
        poly = out
    return poly


def project_box(box: PromptBox, camera: CameraLike, near: float = 0.01) -> BoxProjection:
    """Project ``box`` into ``camera``. The silhouette is the convex hull of the projected
    vertices of the box clipped by the near plane ``z = near`` (exact for a convex box
    under a pinhole camera); it is then clipped to the image rectangle. Occlusion by the
    scene is not considered."""
    k = _as_np(camera.K)
    w2c = _as_np(camera.world_to_camera)
    cam_pts = box.corners().numpy() @ w2c[:3, :3].T + w2c[:3, 3]  # [8, 3]
    center_cam = w2c[:3, :3] @ np.asarray(box.center) + w2c[:3, 3]
    distance = float(np.linalg.norm(center_cam))
    view_cos = float(center_cam[2] / distance) if distance > 0 else 1.0

    z = cam_pts[:, 2]
    verts = [cam_pts[i] for i in range(8) if z[i] >= near]
    for a, b in _EDGES:
        if (z[a] - near) * (z[b] - near) < 0:
            t = (near - z[a]) / (z[b] - z[a])
            verts.append(cam_pts[a] + t * (cam_pts[b] - cam_pts[a]))
    in_front = bool(np.any(z > near))
    if not in_front or not verts:
        return BoxProjection(False, None, 0.0, 0.0, 0.0, distance, float(center_cam[2]), view_cos)
    v = np.stack(verts)
    uvw = v @ k.T
    uv = uvw[:, :2] / uvw[:, 2:3]
    hull = _hull([(float(a), float(b)) for a, b in uv])
    total = _area(hull) if len(hull) >= 3 else 0.0
    clipped = _clip_rect(hull, float(camera.width), float(camera.height)) if len(hull) >= 3 else []
    visible = _area(clipped) if len(clipped) >= 3 else 0.0
    bbox = None
    if visible > 0:
        xs = [p[0] for p in clipped]
        ys = [p[1] for p in clipped]
        bbox = (min(xs), min(ys), max(xs), max(ys))
    frac = visible / total if total > 0 else 0.0
    return BoxProjection(
        True, bbox, visible, total, min(frac, 1.0), distance, float(center_cam[2]), view_cos, clipped
    )


def check_visible(
    boxes: Sequence[PromptBox],
    cameras: Sequence[CameraLike],
    min_pixels: float = 0.0,
    source: str | None = None,
) -> list[list[int]]:
    """For each box, the indices of the cameras whose image shows more than ``min_pixels``
    of its silhouette. Raises :class:`PromptError` naming the first box that no camera
    sees (``source`` — the prompt file — is named too when given)."""
    seen: list[list[int]] = []
    for i, box in enumerate(boxes):
        idx = [c for c, cam in enumerate(cameras) if project_box(box, cam).visible_area > min_pixels]
        if not idx:
            prefix = f"{source}: " if source else ""
            raise PromptError(
                f"{prefix}prompt {i} (center {list(box.center)}, size {list(box.size)}) "
                f"is seen by none of the {len(cameras)} training cameras"
            )
        seen.append(idx)
    return seen
