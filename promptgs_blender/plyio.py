"""Read standard 3D Gaussian Splatting PLY files (and plain coloured point clouds).

Only numpy: this runs inside Blender. The 3DGS layout is a ``vertex`` element with
``x y z``, ``f_dc_0..2`` (degree-0 SH), ``f_rest_*``, ``opacity`` (logit), ``scale_0..2``
(log) and ``rot_0..3`` (w, x, y, z, unnormalised). The result uses the activated form of
the trainer's snapshot ``.npz`` files so both feed the same display code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

SH_C0 = 0.28209479177387814
_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


class PlyError(ValueError):
    """A PLY file that cannot be read; the message names the file and the problem."""


def read_vertices(path: Path) -> np.ndarray:
    """The ``vertex`` element of a binary or ASCII PLY as a numpy structured array."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PlyError(f"{path}: cannot read ({exc.strerror})") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    header = data[:end].decode("ascii", "replace").splitlines()
    body = end + len(b"end_header")
    body += 2 if data[body:body + 2] == b"\r\n" else 1
    fmt, elements = None, []  # [name, count, [(prop, dtype)]]
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property":
            if not elements:
                raise PlyError(f"{path}: property before any element")
            if words[1] == "list":
                raise PlyError(f"{path}: list property '{words[-1]}' in element '{elements[-1][0]}' is not supported")
            if words[1] not in _TYPES:
                raise PlyError(f"{path}: unknown property type '{words[1]}'")
            elements[-1][2].append((words[2], _TYPES[words[1]]))
    if not elements or elements[0][0] != "vertex":
        raise PlyError(f"{path}: the first element is not 'vertex'")
    _, count, props = elements[0]
    if fmt == "ascii":
        table = np.loadtxt(data[body:].decode("ascii").splitlines()[:count], ndmin=2)
        out = np.empty(count, [(name, t) for name, t in props])
        for i, (name, _) in enumerate(props):
            out[name] = table[:, i]
        return out
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise PlyError(f"{path}: unknown PLY format '{fmt}'")
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(name, order + t) for name, t in props])
    if len(data) - body < dtype.itemsize * count:
        raise PlyError(f"{path}: truncated ({count} vertices announced, {(len(data) - body) // dtype.itemsize} present)")
    return np.frombuffer(data, dtype, count, body)


def read_gaussians(path: Path) -> dict[str, np.ndarray]:
    """Gaussians of a 3DGS PLY in snapshot form (float32, activated).

    Keys: ``means`` [N, 3], ``opacity`` [N], ``scale`` [N, 3], ``rotation`` [N, 4] wxyz
    normalised, ``color`` [N, 3] RGB of the DC term. A PLY without Gaussian properties
    (a plain point cloud) gets its ``red green blue`` colours, opacity 1 and zero scale.
    """
    v = read_vertices(path)
    names = set(v.dtype.names)
    if not {"x", "y", "z"} <= names:
        raise PlyError(f"{path}: vertices have no x, y, z")
    n = len(v)

    def stack(keys):
        return np.stack([v[k].astype(np.float64) for k in keys], axis=1)

    out = {"means": stack(["x", "y", "z"])}
    if {"f_dc_0", "f_dc_1", "f_dc_2"} <= names:
        out["color"] = np.clip(0.5 + SH_C0 * stack(["f_dc_0", "f_dc_1", "f_dc_2"]), 0.0, 1.0)
    elif {"red", "green", "blue"} <= names:
        rgb = stack(["red", "green", "blue"])
        out["color"] = rgb / (255.0 if v["red"].dtype.kind in "iu" else 1.0)
    else:
        out["color"] = np.full((n, 3), 0.5)
    out["opacity"] = 1.0 / (1.0 + np.exp(-v["opacity"].astype(np.float64))) if "opacity" in names else np.ones(n)
    if {"scale_0", "scale_1", "scale_2"} <= names:
        out["scale"] = np.exp(stack(["scale_0", "scale_1", "scale_2"]))
    else:
        out["scale"] = np.zeros((n, 3))
    if {"rot_0", "rot_1", "rot_2", "rot_3"} <= names:
        rot = stack(["rot_0", "rot_1", "rot_2", "rot_3"])
        norm = np.linalg.norm(rot, axis=1, keepdims=True)
        out["rotation"] = np.where(norm > 0, rot / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    else:
        out["rotation"] = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return {k: np.ascontiguousarray(a, np.float32) for k, a in out.items()}
