"""Changes of coordinate frame for Gaussians: positions, orientations and SH coefficients.

The engine's Gaussians live in the dataset's world coordinates, which the files read as
Blender's frame: right-handed, +Z up (the frame Blender's own PLY importer puts a 3DGS PLY
in, and the frame of the generated datasets). SPZ stores RUB (right, up, back) and glTF is
right-handed +Y up; both are this frame turned by -90° about X::

    (x, y, z)  ->  (x, z, -y)          (Z_UP_TO_Y_UP)

A rotation ``R`` of the frame maps each Gaussian's mean ``p`` to ``R p``, its covariance
``Σ`` to ``R Σ Rᵀ`` and its colour along a direction ``d`` to the colour along ``R d``.
For the covariance there are two equally valid ways, and each reader expects one:

- ``rotate_quats``: the orientation is turned (``q -> q_R ⊗ q``), the scales stay. This is
  what Niantic's SPZ library and Blender's SPZ importer do.
- ``permute_axes``: for a signed permutation ``R`` only, the quaternion's axis is mapped by
  ``R`` and the scales are permuted with it, which is exact in floating point. This is what
  Blender's glTF importer does.

SH coefficients of degree ``l`` mix only among themselves: ``rotate_sh`` applies, band by
band, the matrix that turns the 3DGS real SH basis (render/sh.py) by ``R``, fitted once in
float64 on sample directions; entries within 1e-9 of an integer are that integer, so a
signed permutation of degree-1 coefficients stays exact.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch

from ..render.sh import sh_bases

Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
Y_UP_TO_Z_UP = Z_UP_TO_Y_UP.T


def rotation_to_quat(rotation: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z), w ≥ 0, of a 3×3 rotation matrix."""
    m = np.asarray(rotation, dtype=np.float64)
    w = np.sqrt(max(0.0, 1.0 + m[0, 0] + m[1, 1] + m[2, 2])) / 2.0
    x = np.copysign(np.sqrt(max(0.0, 1.0 + m[0, 0] - m[1, 1] - m[2, 2])) / 2.0, m[2, 1] - m[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1.0 - m[0, 0] + m[1, 1] - m[2, 2])) / 2.0, m[0, 2] - m[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1.0 - m[0, 0] - m[1, 1] + m[2, 2])) / 2.0, m[1, 0] - m[0, 1])
    return np.array([w, x, y, z])


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` of quaternions (w, x, y, z), broadcast over leading axes."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def rotate_points(rotation: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points [N, 3] in the rotated frame (float32; exact for a signed permutation)."""
    return (np.asarray(points, dtype=np.float64) @ np.asarray(rotation, dtype=np.float64).T).astype(np.float32)


def rotate_quats(rotation: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """Orientations (w, x, y, z) [N, 4] turned by ``rotation`` (``q_R ⊗ q``), float32."""
    return quat_multiply(rotation_to_quat(rotation), quats).astype(np.float32)


def _signed_permutation(rotation: np.ndarray) -> np.ndarray:
    r = np.asarray(rotation, dtype=np.float64)
    if not (np.all(np.isin(r, (-1.0, 0.0, 1.0))) and np.all(np.abs(r).sum(axis=0) == 1) and np.linalg.det(r) > 0):
        raise ValueError("permute_axes needs a rotation that is a signed permutation")
    return r


def permute_axes(rotation: np.ndarray, quats: np.ndarray, scales: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quaternions (w, x, y, z) [N, 4] and per-axis scales [N, 3] of the same Gaussians in
    a frame turned by ``rotation``, a signed permutation: the quaternion's axis is mapped,
    the scales follow their axes. Exact in floating point (only moves and negations)."""
    r = _signed_permutation(rotation)
    quats = np.asarray(quats)
    out_q = np.empty_like(quats)
    out_q[:, 0] = quats[:, 0]
    out_q[:, 1:] = quats[:, 1:] @ r.T.astype(quats.dtype)
    out_s = np.asarray(scales) @ np.abs(r).T.astype(np.asarray(scales).dtype)
    return out_q, out_s


@lru_cache(maxsize=16)
def _band_matrices(rotation_key: tuple[float, ...], degree: int) -> tuple[np.ndarray, ...]:
    """For each band l = 1..degree, the matrix A with c' = A c for that band's coefficients."""
    rotation = np.array(rotation_key).reshape(3, 3)
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(256, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # colour'(d) = colour(Rᵀ d): Y(Rᵀ d) = B Y(d) band by band, and c' = Bᵀ c.
    y = sh_bases(degree, torch.from_numpy(dirs)).numpy()
    y_back = sh_bases(degree, torch.from_numpy(dirs @ rotation)).numpy()  # rows: Rᵀ d
    out = []
    for band in range(1, degree + 1):
        cols = slice(band * band, (band + 1) * (band + 1))
        a, *_ = np.linalg.lstsq(y[:, cols], y_back[:, cols], rcond=None)  # y @ Bᵀ = y_back: a = Bᵀ
        nearest = np.round(a) + 0.0  # no negative zeros
        out.append(np.where(np.abs(a - nearest) < 1e-9, nearest, a))
    return tuple(out)


def rotate_sh(rotation: np.ndarray, sh_rest: np.ndarray) -> np.ndarray:
    """Higher SH coefficients [N, K-1, 3] (degree 1 onwards, 3DGS order) in a frame turned
    by ``rotation``, so that every Gaussian's colour along ``R d`` is its old colour along
    ``d``. float32 out; computed in float64."""
    sh_rest = np.asarray(sh_rest)
    k = sh_rest.shape[1] + 1
    degree = int(round(np.sqrt(k))) - 1
    if (degree + 1) ** 2 != k or degree > 3:
        raise ValueError(f"{k} SH coefficients per channel is not a degree 0..3")
    key = tuple(float(v) for v in np.asarray(rotation, dtype=np.float64).ravel())
    out = np.empty(sh_rest.shape, dtype=np.float64)
    coeffs = sh_rest.astype(np.float64)
    for band, a in enumerate(_band_matrices(key, degree), start=1):
        lo, hi = band * band - 1, (band + 1) * (band + 1) - 1  # shN has no DC row
        out[:, lo:hi, :] = np.einsum("ij,njc->nic", a, coeffs[:, lo:hi, :])
    return out.astype(np.float32)
