"""Read and write standard 3D Gaussian Splatting PLY files (and read plain coloured point clouds).

Only numpy: this runs inside Blender. The 3DGS layout is a ``vertex`` element with
``x y z``, ``f_dc_0..2`` (degree-0 SH), ``f_rest_*`` (higher SH, channel-major: all the
red coefficients, then green, then blue), ``opacity`` (logit), ``scale_0..2`` (log) and
``rot_0..3`` (w, x, y, z, unnormalised), often with ``nx ny nz`` and other properties
(the Inria code, gsplat, OpenSplat and Brush write this layout with SH degree 0 to 3).
Any SH degree, any extra scalar properties, any scalar type, ASCII or binary of either
byte order are read; other elements (faces, lists) after the vertices are skipped.
Written files are binary little-endian float32, the layout every 3DGS reader takes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .splats import SH_C0, SH_COUNTS, Splats, file_values, normalized, sigmoid, exp_scale

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
GAUSSIAN_PROPERTIES = (["f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)]
                       + [f"rot_{i}" for i in range(4)])


class PlyError(ValueError):
    """A PLY file that cannot be read or written; the message names the file and the problem."""


def _header(data: bytes, path: Path) -> tuple[str, list, int]:
    """Format, elements ``[name, count, [(property, dtype or None for a list)]]`` and where the body starts."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    body = end + len(b"end_header")
    body += 2 if data[body:body + 2] == b"\r\n" else 1
    fmt, elements = None, []
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
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
                elements[-1][2].append((words[-1], None))
            elif words[1] not in _TYPES:
                raise PlyError(f"{path}: unknown property type '{words[1]}'")
            else:
                elements[-1][2].append((words[2], _TYPES[words[1]]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PlyError(f"{path}: unknown PLY format '{fmt}'")
    return fmt, elements, body


def read_vertices(path: Path) -> np.ndarray:
    """The ``vertex`` element of a binary or ASCII PLY as a numpy structured array."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PlyError(f"{path}: cannot read ({exc.strerror})") from None
    fmt, elements, body = _header(data, path)
    names = [element[0] for element in elements]
    if "vertex" not in names:
        raise PlyError(f"{path}: no 'vertex' element")
    before, (_, count, props) = elements[:names.index("vertex")], elements[names.index("vertex")]
    if any(t is None for _, t in props):
        raise PlyError(f"{path}: list property in element 'vertex' is not supported")
    if fmt == "ascii":
        lines = data[body:].decode("ascii").splitlines()
        skip = sum(element[1] for element in before)
        rows = lines[skip:skip + count]
        if len(rows) < count:
            raise PlyError(f"{path}: truncated ({count} vertices announced, {len(rows)} present)")
        table = np.loadtxt(rows, ndmin=2) if count else np.zeros((0, len(props)))
        out = np.empty(count, [(name, t) for name, t in props])
        for i, (name, _) in enumerate(props):
            out[name] = table[:, i]
        return out
    order = "<" if fmt == "binary_little_endian" else ">"
    for name, n, element_props in before:
        if any(t is None for _, t in element_props):
            raise PlyError(f"{path}: element '{name}' with a list property comes before 'vertex'")
        body += n * np.dtype([(p, order + t) for p, t in element_props]).itemsize
    dtype = np.dtype([(name, order + t) for name, t in props])
    if len(data) - body < dtype.itemsize * count:
        raise PlyError(f"{path}: truncated ({count} vertices announced, {max(0, len(data) - body) // dtype.itemsize} present)")
    return np.frombuffer(data, dtype, count, body)


def read_splats(path: Path) -> Splats:
    """The Gaussians of a 3DGS PLY (see :mod:`splats` for the conventions).

    Every vertex property that is not a Gaussian parameter is kept in ``extra`` (as float32),
    and the file's own opacity, scale and rotation values in ``raw``, so that
    :func:`write_splats` writes unchanged Gaussians back as they were. ``f_rest_*`` that do
    not make whole SH bands are kept as extra properties, not as SH. A PLY without Gaussian
    properties (a plain point cloud) gets its ``red green blue`` colours, opacity 1 and
    zero scale.
    """
    path = Path(path)
    v = read_vertices(path)
    names = list(v.dtype.names)
    if not {"x", "y", "z"} <= set(names):
        raise PlyError(f"{path}: vertices have no x, y, z")
    n = len(v)

    def stack(keys) -> np.ndarray:
        return np.ascontiguousarray(np.stack([v[k].astype(np.float32) for k in keys], axis=1))

    used = {"x", "y", "z"}
    rest = []
    while f"f_rest_{len(rest)}" in names:
        rest.append(f"f_rest_{len(rest)}")
    if len(rest) % 3 == 0 and len(rest) // 3 in SH_COUNTS:
        k = len(rest) // 3
        f_rest = stack(rest).reshape(n, 3, k).transpose(0, 2, 1).copy() if k else np.zeros((n, 0, 3), np.float32)
        used.update(rest)
    else:
        f_rest = np.zeros((n, 0, 3), np.float32)
    raw = {}
    if set(GAUSSIAN_PROPERTIES) <= set(names):
        f_dc = stack(["f_dc_0", "f_dc_1", "f_dc_2"])
        raw = {"opacity": v["opacity"].astype(np.float32), "scale": stack(["scale_0", "scale_1", "scale_2"]),
               "rotation": stack(["rot_0", "rot_1", "rot_2", "rot_3"])}
        opacity, scale, rotation = sigmoid(raw["opacity"]), exp_scale(raw["scale"]), normalized(raw["rotation"])
        used.update(GAUSSIAN_PROPERTIES)
    else:
        if {"red", "green", "blue"} <= set(names):
            rgb = stack(["red", "green", "blue"]).astype(np.float64)
            rgb /= 255.0 if v["red"].dtype.kind in "iu" else 1.0
            used.update(["red", "green", "blue"])
        else:
            rgb = np.full((n, 3), 0.5)
        f_dc = np.ascontiguousarray((rgb - 0.5) / SH_C0, np.float32)
        opacity, scale = np.ones(n, np.float32), np.zeros((n, 3), np.float32)
        rotation = np.tile(np.float32([1.0, 0.0, 0.0, 0.0]), (n, 1))
    extra = {name: np.ascontiguousarray(v[name], np.float32) for name in names if name not in used}
    return Splats(means=stack(["x", "y", "z"]), f_dc=f_dc, f_rest=f_rest, opacity=opacity, scale=scale,
                  rotation=rotation, extra=extra, raw=raw, order=names)


def columns(splats: Splats) -> dict[str, np.ndarray]:
    """The PLY properties (float32 columns) of the Gaussians, in the order to write them:
    the file's order when they came from one, else the Inria code's (``x y z``, ``nx ny nz``
    when present, ``f_dc``, ``f_rest``, ``opacity``, ``scale``, ``rot``, then the rest)."""
    k = splats.f_rest.shape[1]
    cols = {"x": splats.means[:, 0], "y": splats.means[:, 1], "z": splats.means[:, 2]}
    cols.update({name: splats.extra[name] for name in ("nx", "ny", "nz") if name in splats.extra})
    cols.update({f"f_dc_{c}": splats.f_dc[:, c] for c in range(3)})
    cols.update({f"f_rest_{c * k + j}": splats.f_rest[:, j, c] for c in range(3) for j in range(k)})
    cols["opacity"] = file_values(splats, "opacity")
    scale, rotation = file_values(splats, "scale"), file_values(splats, "rotation")
    cols.update({f"scale_{i}": scale[:, i] for i in range(3)})
    cols.update({f"rot_{i}": rotation[:, i] for i in range(4)})
    cols.update({name: values for name, values in splats.extra.items() if name not in cols})
    ordered = {name: cols[name] for name in splats.order if name in cols}
    ordered.update({name: values for name, values in cols.items() if name not in ordered})
    return ordered


def write_splats(path: Path, splats: Splats) -> None:
    """Write a standard 3DGS PLY (binary little-endian float32), atomically."""
    path = Path(path)
    cols = columns(splats)
    n = len(splats)
    table = np.empty(n, [(name, "<f4") for name in cols])
    for name, values in cols.items():
        table[name] = values
    header = ("ply\nformat binary_little_endian 1.0\ncomment PromptGS Blender add-on\n"
              f"element vertex {n}\n" + "".join(f"property float {name}\n" for name in cols) + "end_header\n")
    tmp = path.with_name(path.name + ".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as handle:
            handle.write(header.encode("ascii"))
            handle.write(table.tobytes())
        os.replace(tmp, path)
    except OSError as exc:
        raise PlyError(f"{path}: cannot write ({exc.strerror})") from None


def read_gaussians(path: Path) -> dict[str, np.ndarray]:
    """Gaussians of a 3DGS PLY in snapshot form (float32, activated).

    Keys: ``means`` [N, 3], ``opacity`` [N], ``scale`` [N, 3], ``rotation`` [N, 4] wxyz
    normalised, ``color`` [N, 3] RGB of the DC term (clipped to 0..1).
    """
    splats = read_splats(path)
    color = np.clip(0.5 + SH_C0 * splats.f_dc.astype(np.float64), 0.0, 1.0).astype(np.float32)
    return {"means": splats.means, "opacity": splats.opacity, "scale": splats.scale,
            "rotation": splats.rotation, "color": color}
