"""How close a reconstruction's cameras are to a reference model's (tests, benchmarks).

Two SfM models of one scene differ by a similarity (scale, rotation, translation). The
camera centres of the images both registered are aligned with Umeyama's closed-form
least-squares similarity, and each centre's remaining distance is measured against the
scene's extent (the largest distance of a reference centre from their mean).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R [3, 3], translation t [3] minimising sum |s R src_i + t - dst_i|²."""
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(f"need matching [N >= 3, 3] point sets, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    rot = u @ sign @ vt
    var_s = (xs**2).sum() / len(src)
    scale = float(np.trace(np.diag(d) @ sign) / var_s)
    return scale, rot, mu_d - scale * rot @ mu_s


def camera_centres(model) -> dict[str, np.ndarray]:
    """Image name -> camera centre in world coordinates, for the registered images of a
    pycolmap Reconstruction (or a model folder)."""
    import pycolmap

    rec = model if isinstance(model, pycolmap.Reconstruction) else pycolmap.Reconstruction(str(Path(model)))
    out = {}
    for image_id in rec.reg_image_ids():
        image = rec.images[image_id]
        out[image.name] = np.asarray(image.projection_center(), dtype=np.float64)
    return out


def compare_centres(estimate: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> dict:
    """Align `estimate`'s centres onto `reference`'s (common names) and report the errors.

    Returns ``common`` (images in both), ``extent`` (reference), ``max_error`` and
    ``median_error`` as fractions of the extent, ``scale``, and ``per_image`` errors.
    """
    names = sorted(set(estimate) & set(reference))
    if len(names) < 3:
        raise ValueError(f"only {len(names)} images in common; at least 3 are needed to align")
    src = np.stack([estimate[n] for n in names])
    dst = np.stack([reference[n] for n in names])
    s, rot, t = umeyama(src, dst)
    aligned = (s * (rot @ src.T)).T + t
    extent = float(np.linalg.norm(dst - dst.mean(0), axis=1).max())
    err = np.linalg.norm(aligned - dst, axis=1) / extent
    return {
        "common": len(names),
        "extent": extent,
        "scale": s,
        "max_error": float(err.max()),
        "median_error": float(np.median(err)),
        "per_image": dict(zip(names, err.round(5).tolist())),
    }
