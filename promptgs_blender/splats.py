"""Gaussians as arrays, in the conventions Blender 5.3 stores Gaussian splats with.

Only numpy: this runs inside Blender and in tests without it. Blender's PLY importer
(``source/blender/io/ply/importer/ply_import_gsplat.cc``, Blender 5.3) keeps the degree-0
spherical-harmonic coefficients as they are in the file (``f_dc``, not an RGB colour),
applies the sigmoid to the opacity and the exponential to the scales, normalises the
rotation (w, x, y, z), and keeps the higher coefficients per coefficient: its
``radiance:sh_k`` is ``(f_rest_k, f_rest_{K+k}, f_rest_{2K+k})`` for a file with ``K``
coefficients per channel (channel-major ``f_rest``). :class:`Splats` holds exactly those
values. Cycles adds 0.5 to the evaluated harmonics and reads the sum as an sRGB colour
(``intern/cycles/kernel/geom/gsplat.h``, ``gsplat_radiance``).

A file's own opacity logits, log scales and unnormalised rotations are kept beside the
activated values (``raw``) so that Gaussians written back unchanged are the file's
values bit for bit; what was changed is written from the activated values.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

SH_C0 = 0.28209479177387814
SH_COUNTS = (0, 3, 8, 15, 24)  # higher coefficients per channel for SH degree 0..4
# the real SH basis of the 3DGS reference code (degree 1..3), as gsplat evaluates it
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


@dataclass
class Splats:
    """N Gaussians. ``f_rest`` is [N, K, 3] (K of :data:`SH_COUNTS`, coefficient-major);
    ``extra`` the file's other per-vertex properties (float32, by name); ``raw`` the file's
    ``opacity`` [N], ``scale`` [N, 3] and ``rotation`` [N, 4] before activation; ``order``
    the file's property names in order (empty when not from a file)."""

    means: np.ndarray
    f_dc: np.ndarray
    f_rest: np.ndarray
    opacity: np.ndarray
    scale: np.ndarray
    rotation: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    raw: dict[str, np.ndarray] = field(default_factory=dict)
    order: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.means)

    @property
    def sh_degree(self) -> int:
        return SH_COUNTS.index(self.f_rest.shape[1])


def _f32(array) -> np.ndarray:
    return np.ascontiguousarray(array, np.float32)


def sigmoid(logit: np.ndarray) -> np.ndarray:
    return _f32(1.0 / (1.0 + np.exp(-np.asarray(logit, np.float64))))


def logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, np.float64), 2.0 ** -24, 1.0 - 2.0 ** -24)
    return _f32(np.log(p) - np.log1p(-p))


def exp_scale(log_scale: np.ndarray) -> np.ndarray:
    return _f32(np.exp(np.asarray(log_scale, np.float64)))


def log_scale(scale: np.ndarray) -> np.ndarray:
    return _f32(np.log(np.maximum(np.asarray(scale, np.float64), 1e-30)))


def normalized(quats: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z), float32 (norms taken in float64); a zero one becomes the identity."""
    q = np.asarray(quats)
    norm = np.sqrt(np.einsum("ij,ij->i", q, q, dtype=np.float64))
    zero = norm == 0
    out = _f32(q / np.where(zero, 1.0, norm)[:, None])
    if zero.any():
        out[zero] = [1.0, 0.0, 0.0, 0.0]
    return out


ACTIVATIONS = {"opacity": (sigmoid, logit), "scale": (exp_scale, log_scale), "rotation": (normalized, None)}


def file_values(splats: Splats, name: str) -> np.ndarray:
    """The values to write for ``opacity``, ``scale`` or ``rotation``: the file's own
    (``raw``) for every Gaussian whose activated value is still what they activate to,
    the inverse of the activated value for the others."""
    activate, inverse = ACTIVATIONS[name]
    current = getattr(splats, name)
    out = current.copy() if inverse is None else inverse(current)
    raw = splats.raw.get(name)
    if raw is not None and raw.shape == current.shape:
        same = activate(raw) == current
        same = same if same.ndim == 1 else same.all(axis=1)
        out[same] = raw[same]
    return out


def from_snapshot(data: dict[str, np.ndarray]) -> Splats:
    """A trainer snapshot (activated opacity and scale, RGB of the DC term, no higher SH)."""
    n = len(data["means"])
    color = _f32(data["color"])[:, :3] if "color" in data else np.full((n, 3), 0.5, np.float32)
    return Splats(means=_f32(data["means"]).reshape(n, 3), f_dc=(color - np.float32(0.5)) * np.float32(1.0 / SH_C0),
                  f_rest=np.zeros((n, 0, 3), np.float32),
                  opacity=_f32(data.get("opacity", np.ones(n))).reshape(n),
                  scale=_f32(data.get("scale", np.zeros((n, 3)))).reshape(n, 3),
                  rotation=normalized(data.get("rotation", np.tile([1.0, 0, 0, 0], (n, 1)))))


def rgb(splats: Splats) -> np.ndarray:
    """The degree-0 colour (sRGB, 0..1) as 3DGS renderers and Cycles show it."""
    return _f32(np.clip(0.5 + SH_C0 * splats.f_dc.astype(np.float64), 0.0, 1.0))


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function undone (float32), as Cycles reads a splat's colour."""
    c = _f32(c)
    out = np.power((c + np.float32(0.055)) * np.float32(1 / 1.055), np.float32(2.4))
    low = c <= 0.04045
    out[low] = c[low] * np.float32(1 / 12.92)
    return out


def subset(splats: Splats, keep: np.ndarray) -> Splats:
    """The Gaussians where ``keep`` (a boolean mask or indices) selects."""
    return replace(splats, means=splats.means[keep], f_dc=splats.f_dc[keep], f_rest=splats.f_rest[keep],
                   opacity=splats.opacity[keep], scale=splats.scale[keep], rotation=splats.rotation[keep],
                   extra={k: v[keep] for k, v in splats.extra.items()},
                   raw={k: v[keep] for k, v in splats.raw.items()})


def _quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def _matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (Shepperd's method, for one matrix)."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    return np.array(q)


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """The higher real SH basis functions (degree 1..``degree``) of unit directions, [M, K],
    in the order and signs of the 3DGS code's ``f_rest`` coefficients."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = []
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [_C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2 * zz - xx - yy), _C2[3] * x * z, _C2[4] * (xx - yy)]
    if degree >= 3:
        out += [_C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (4 * zz - xx - yy),
                _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, axis=1) if out else np.zeros((len(dirs), 0))


def rotate_sh(f_rest: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Higher SH coefficients [N, K, 3] of Gaussians turned by the 3×3 ``rotation``: the colour
    they show along a direction ``d`` is what the originals showed along ``rotation⁻¹ d``.
    Solved per basis on sample directions (bands do not mix under a rotation)."""
    k = f_rest.shape[1]
    if k == 0:
        return f_rest
    degree = SH_COUNTS.index(k)
    if degree > 3:
        raise ValueError(f"turning SH of degree {degree} is not supported (degree 3 at most)")
    dirs = np.random.default_rng(0).normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    turned = sh_basis(dirs @ np.asarray(rotation, np.float64), degree)  # basis at rotation⁻¹ d, row-wise
    mapping = np.linalg.lstsq(sh_basis(dirs, degree), turned, rcond=None)[0]  # [K, K]
    return _f32(np.einsum("kj,njc->nkc", mapping, f_rest.astype(np.float64)))


def transformed(splats: Splats, matrix: np.ndarray) -> Splats:
    """The Gaussians moved by a 4×4 similarity (rotation, uniform scale, translation), with
    their SH turned along; the identity returns them untouched. An uneven scale or a
    shear cannot keep every Gaussian an axis-aligned ellipsoid and is refused."""
    m = np.asarray(matrix, np.float64)
    if np.array_equal(m, np.eye(4)):
        return splats
    linear = m[:3, :3]
    factor = np.cbrt(np.linalg.det(linear))
    rot = linear / factor if factor != 0 else linear
    if factor <= 0 or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5) or not np.allclose(m[3], [0, 0, 0, 1]):
        raise ValueError("the transform is not a rotation, uniform scale and move (scaled unevenly or mirrored)")
    q = _quat_multiply(_matrix_to_quat(rot)[None, :], splats.rotation.astype(np.float64))
    return replace(splats, means=_f32(splats.means @ linear.T + m[:3, 3]), rotation=normalized(q),
                   scale=_f32(splats.scale * factor), f_rest=rotate_sh(splats.f_rest, rot),
                   raw={k: v for k, v in splats.raw.items() if k == "opacity"})
