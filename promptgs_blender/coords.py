"""Coordinate conventions between COLMAP (the dataset, the truth) and Blender.

Pure numpy so it is testable without Blender. Matrices are 4×4 float64 arrays; the
operators turn them into ``mathutils.Matrix``.

- COLMAP camera: x right, y down, z forward; images store world-to-camera ``R, t``.
- Blender camera: x right, y up, looks along −z.
- Everything imported lives under one root empty whose matrix is the dataset-to-Blender
  transform (:func:`dataset_to_blender`); children keep dataset coordinates locally.
"""

from __future__ import annotations

import numpy as np

# COLMAP camera axes expressed in Blender camera axes (and back: it is its own inverse).
COLMAP_TO_BLENDER_CAMERA = np.diag([1.0, -1.0, -1.0])


def quat_to_rotmat(q) -> np.ndarray:
    """Rotation matrix of a (w, x, y, z) quaternion (normalised here)."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) with w ≥ 0 of a proper rotation matrix."""
    r = np.asarray(r, np.float64)
    trace = np.trace(r)
    if trace > 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def colmap_camera_to_blender(qvec, tvec) -> np.ndarray:
    """The matrix of a Blender camera object, in dataset coordinates, for a COLMAP image.

    COLMAP maps world to camera with ``x_cam = R x_world + t``; the camera sits at
    ``-Rᵀ t`` and its axes in the world are the columns of ``Rᵀ``. Blender's camera axes
    are COLMAP's with y and z negated.
    """
    rot = quat_to_rotmat(qvec)
    matrix = np.eye(4)
    matrix[:3, :3] = rot.T @ COLMAP_TO_BLENDER_CAMERA
    matrix[:3, 3] = -rot.T @ np.asarray(tvec, np.float64)
    return matrix


def estimate_up(qvecs) -> np.ndarray:
    """World 'up' of a capture: minus the mean of the cameras' down (COLMAP +y) axes."""
    downs = np.array([quat_to_rotmat(q)[1] for q in qvecs])  # row 1 of R = camera y in world
    up = -downs.sum(axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-9 else np.array([0.0, -1.0, 0.0])


def dataset_to_blender(up=(0.0, -1.0, 0.0), center=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The root empty's matrix: dataset world → Blender world.

    A rotation taking the dataset's ``up`` direction to Blender's +Z (the smallest such
    rotation), after moving ``center`` (dataset coordinates) to the origin. No scaling, so
    lengths in Blender are dataset units.
    """
    a = np.asarray(up, np.float64)
    a = a / np.linalg.norm(a)
    b = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(a, b), float(a @ b)
    if c < -1.0 + 1e-12:  # up is −Z: half turn about X
        rot = np.diag([1.0, -1.0, -1.0])
    else:
        vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        rot = np.eye(3) + vx + vx @ vx / (1.0 + c)
    matrix = np.eye(4)
    matrix[:3, :3] = rot
    matrix[:3, 3] = -rot @ np.asarray(center, np.float64)
    return matrix


def blender_camera_settings(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                            sensor_width: float = 36.0) -> dict:
    """Blender settings reproducing a pinhole camera exactly.

    Camera data: with ``sensor_fit='HORIZONTAL'`` the sensor width spans the image width
    and Blender's shift is measured in image widths. COLMAP's pixel coordinates have the
    origin at the top-left corner of the image (pixel centres at +0.5); Blender's shift
    moves the optical axis from the image centre. fy ≠ fx needs non-square pixels:
    ``pixel_aspect`` is the scene's (x, y) pixel aspect (both ≥ 1, as Blender requires),
    whose ratio y/x stretches rows by fx/fy; vertical shift is in those stretched units.
    """
    ycor = fx / fy
    aspect = (1.0, ycor) if ycor >= 1.0 else (1.0 / ycor, 1.0)
    return {
        "type": "PERSP",
        "sensor_fit": "HORIZONTAL",
        "sensor_width": sensor_width,
        "lens": fx * sensor_width / width,
        "shift_x": (width / 2.0 - cx) / width,
        "shift_y": (cy - height / 2.0) * ycor / width,
        "pixel_aspect": aspect,
    }


def blender_camera_intrinsics(width: int, height: int, lens: float, sensor_width: float, sensor_height: float,
                              sensor_fit: str = "AUTO", shift_x: float = 0.0, shift_y: float = 0.0,
                              pixel_aspect: tuple[float, float] = (1.0, 1.0)) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in COLMAP's pixel convention of a Blender perspective camera
    rendering ``width`` × ``height`` pixels: the inverse of :func:`blender_camera_settings`
    for any sensor fit, as Blender computes its view plane.

    The sensor size along the fitted axis is ``sensor_height`` only for a VERTICAL fit;
    AUTO fits the longer side of the frame (in pixel-aspect units) but measures it with
    ``sensor_width``. Shifts are in units of that side.
    """
    xasp, yasp = pixel_aspect
    ycor = yasp / xasp
    fit = sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if xasp * width >= yasp * height else "VERTICAL"
    sensor = sensor_height if sensor_fit == "VERTICAL" else sensor_width
    side = width if fit == "HORIZONTAL" else ycor * height  # the fitted side, in x-pixel units
    fx = lens * side / sensor
    fy = fx / ycor
    cx = width / 2.0 - shift_x * side
    cy = height / 2.0 + shift_y * side / ycor
    return fx, fy, cx, cy


def blender_camera_to_colmap(camera_to_dataset) -> np.ndarray:
    """COLMAP's world-to-camera matrix of a Blender camera whose matrix in dataset
    coordinates is ``camera_to_dataset`` (the inverse of :func:`colmap_camera_to_blender`).
    Scale in the matrix (a scaled camera object) is removed."""
    m = np.asarray(camera_to_dataset, np.float64)
    axes = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)
    rot = (axes @ COLMAP_TO_BLENDER_CAMERA).T  # COLMAP's R: rows are the camera axes in the world
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ m[:3, 3]
    return out


def prompt_box(box_to_dataset, display_size: float = 1.0) -> dict:
    """The prompt-file box of a CUBE empty, from its matrix in dataset coordinates.

    A CUBE empty of display size 1 spans −1..1 on each local axis, so the full edge is
    ``2 × display_size × scale``. Shear (from non-uniformly scaled parents) is dropped.
    """
    m = np.asarray(box_to_dataset, np.float64)
    linear = m[:3, :3]
    scale = np.linalg.norm(linear, axis=0)
    if np.any(scale < 1e-12):
        raise ValueError("prompt box has zero size along an axis")
    rot = linear / scale
    if np.linalg.det(rot) < 0:  # a mirrored box is the same box with one axis flipped
        rot[:, 2] *= -1
    u, _, vt = np.linalg.svd(rot)  # nearest rotation (removes shear)
    rot = u @ vt
    return {
        "center": m[:3, 3].tolist(),
        "size": (2.0 * display_size * scale).tolist(),
        "rotation_wxyz": rotmat_to_quat(rot).tolist(),
    }


def prompt_box_matrix(box: dict) -> np.ndarray:
    """The matrix, in dataset coordinates, of a CUBE empty of display size 1 drawing the
    prompt-file ``box`` (``center``, ``size``, ``rotation_wxyz``): the inverse of
    :func:`prompt_box`, so ``prompt_box(prompt_box_matrix(b))`` gives ``b`` back."""
    size = np.asarray(box["size"], np.float64)
    if size.shape != (3,) or np.any(size <= 0):
        raise ValueError(f"box size {box['size']} is not three positive lengths")
    matrix = np.eye(4)
    matrix[:3, :3] = quat_to_rotmat(box.get("rotation_wxyz", (1.0, 0.0, 0.0, 0.0))) * (size / 2.0)
    matrix[:3, 3] = np.asarray(box["center"], np.float64)
    return matrix


def project_colmap(point, qvec, tvec, fx, fy, cx, cy) -> np.ndarray:
    """Pixel (u, v) of a dataset-world point with a pinhole COLMAP camera (for checks)."""
    x = quat_to_rotmat(qvec) @ np.asarray(point, np.float64) + np.asarray(tvec, np.float64)
    return np.array([fx * x[0] / x[2] + cx, fy * x[1] / x[2] + cy])
