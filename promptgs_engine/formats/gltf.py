"""glTF 2.0 with ``KHR_gaussian_splatting``: a ``.glb`` (binary) or a ``.gltf`` (JSON with
its buffer embedded as a data URI), through pygltflib.

Written against the extension's specification in KhronosGroup/glTF
(extensions/2.0/Khronos/KHR_gaussian_splatting/README.md, "Release Candidate", commit
63770cc of 2026-04-15). One point primitive (``mode`` 0) with the ``ellipse`` kernel and
the ``srgb_rec709_display`` colour space (the photos are trained on as they are):

| attribute                                     | type          | value                        |
|-----------------------------------------------|---------------|------------------------------|
| ``POSITION``                                  | VEC3 float    | mean                         |
| ``KHR_gaussian_splatting:ROTATION``           | VEC4 float    | unit quaternion x, y, z, w   |
| ``KHR_gaussian_splatting:SCALE``              | VEC3 float    | linear std-devs, ``exp(s)``  |
| ``KHR_gaussian_splatting:OPACITY``            | SCALAR float  | ``sigmoid(logit)``           |
| ``KHR_gaussian_splatting:SH_DEGREE_0_COEF_0`` | VEC3 float    | SH DC, as in the PLY         |
| ``KHR_gaussian_splatting:SH_DEGREE_l_COEF_n`` | VEC3 float    | degree l, order m = n - l    |

glTF is +Y up: the engine's Z-up world is turned by ``(x, y, z) -> (x, z, -y)``; as
Blender's glTF importer undoes it, the quaternion's axis and the scales are permuted
(exact) rather than the orientation turned, and the SH are rotated band by band
(frames.py). The SH basis and its order are the 3DGS ones (the specification's, with the
Condon-Shortley phase), so coefficients are not reordered.

Reading takes every primitive with the extension in the default scene, through its
node's transform (rotation, translation and uniform scale), float or normalised-integer
accessors as the specification allows.
"""

from __future__ import annotations

import base64
from pathlib import Path

import numpy as np

from ..errors import PromptGSError
from .frames import (
    Y_UP_TO_Z_UP, Z_UP_TO_Y_UP, permute_axes, quat_multiply, rotate_points, rotate_sh, rotation_to_quat,
)
from .splats import Splats, logit, sigmoid

EXTENSION = "KHR_gaussian_splatting"
PREFIX = EXTENSION + ":"
KERNEL = "ellipse"
COLOR_SPACE = "srgb_rec709_display"
FLOAT = 5126
ARRAY_BUFFER = 34962
_COMPONENTS = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
# componentType: (numpy dtype, divisor of a normalised integer)
_COMPONENT_TYPES = {5120: ("<i1", 127.0), 5121: ("<u1", 255.0), 5122: ("<i2", 32767.0),
                    5123: ("<u2", 65535.0), 5125: ("<u4", None), 5126: ("<f4", None)}
_MIN_SCALE = 1e-30  # a zero scale (a flat Gaussian) reads as a log scale of -69


def _sh_names(degree: int) -> list[str]:
    """Attribute names of the coefficients after the DC one, in the 3DGS order."""
    return [f"{PREFIX}SH_DEGREE_{l}_COEF_{n}" for l in range(1, degree + 1) for n in range(2 * l + 1)]


def encode_gltf(splats: Splats, binary: bool) -> bytes:
    """The bytes of a ``.glb`` (``binary``) or a self-contained ``.gltf`` of ``splats``."""
    from pygltflib import GLTF2, Accessor, Asset, Attributes, Buffer, BufferView, Mesh, Node, Primitive, Scene

    n = splats.n
    if n == 0:
        raise PromptGSError("cannot write glTF: no Gaussians")
    means = rotate_points(Z_UP_TO_Y_UP, splats.means)
    q = splats.quats.astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True).clip(min=1e-30)
    quats, scales = permute_axes(Z_UP_TO_Y_UP, q, np.exp(splats.scales.astype(np.float64)))
    sh_rest = rotate_sh(Z_UP_TO_Y_UP, splats.sh_rest) if splats.sh_degree else splats.sh_rest
    columns = {
        "POSITION": means,
        PREFIX + "ROTATION": quats[:, [1, 2, 3, 0]],
        PREFIX + "SCALE": scales,
        PREFIX + "OPACITY": sigmoid(splats.opacities),
        PREFIX + "SH_DEGREE_0_COEF_0": splats.sh0,
    }
    for i, name in enumerate(_sh_names(splats.sh_degree)):
        columns[name] = sh_rest[:, i]
    blob, views, accessors, attributes = bytearray(), [], [], {}
    for name, values in columns.items():
        values = np.ascontiguousarray(values, dtype="<f4")
        kind = {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[1 if values.ndim == 1 else values.shape[1]]
        views.append(BufferView(buffer=0, byteOffset=len(blob), byteLength=values.nbytes, target=ARRAY_BUFFER))
        extra = {}
        if name == "POSITION":  # glTF requires the bounds of positions
            extra = dict(min=values.min(axis=0).tolist(), max=values.max(axis=0).tolist())
        accessors.append(Accessor(bufferView=len(views) - 1, componentType=FLOAT, count=n, type=kind, **extra))
        attributes[name] = len(accessors) - 1
        blob += values.tobytes()
    primitive = Primitive(attributes=Attributes(**attributes), mode=0,
                          extensions={EXTENSION: {"kernel": KERNEL, "colorSpace": COLOR_SPACE}})
    doc = GLTF2(
        asset=Asset(version="2.0", generator="PromptGS"), extensionsUsed=[EXTENSION], scene=0,
        scenes=[Scene(nodes=[0])], nodes=[Node(mesh=0, name="gaussians")],
        meshes=[Mesh(name="gaussians", primitives=[primitive])],
        accessors=accessors, bufferViews=views, buffers=[Buffer(byteLength=len(blob))],
    )
    if binary:
        doc.set_binary_blob(bytes(blob))
        return b"".join(doc.save_to_bytes())
    doc.buffers[0].uri = "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode("ascii")
    return doc.to_json(indent=None).encode("utf-8")


def _load(path: Path):
    from pygltflib import GLTF2

    data = path.read_bytes()
    try:
        if data[:4] == b"glTF":
            declared = int.from_bytes(data[8:12], "little") if len(data) >= 12 else -1
            if declared != len(data):
                raise PromptGSError(f"{path}: truncated or padded GLB ({len(data)} bytes, its header says {declared})")
            doc = GLTF2.load_from_bytes(data)
        else:
            doc = GLTF2.gltf_from_json(data.decode("utf-8"))
    except PromptGSError:
        raise
    except Exception as exc:  # pygltflib and json raise many kinds for malformed files
        raise PromptGSError(f"{path}: not a readable glTF file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from exc
    if doc is None:
        raise PromptGSError(f"{path}: not a readable glTF file (no JSON chunk)")
    doc._path = path.parent
    return doc


def _buffers(doc, path: Path) -> list[bytes]:
    out = []
    for i, buffer in enumerate(doc.buffers):
        if buffer.uri is None:
            data = doc.binary_blob()
        elif buffer.uri.startswith("data:"):
            data = base64.b64decode(buffer.uri.split(",", 1)[1])
        else:
            file = path.parent / buffer.uri
            if not file.is_file():
                raise PromptGSError(f"{path}: its buffer {buffer.uri} is missing")
            data = file.read_bytes()
        if data is None or len(data) < buffer.byteLength:
            raise PromptGSError(f"{path}: truncated glTF (buffer {i} has {0 if data is None else len(data)} "
                                f"of its {buffer.byteLength} bytes)")
        out.append(data)
    return out


def _accessor(doc, buffers: list[bytes], index: int, path: Path, name: str) -> np.ndarray:
    acc = doc.accessors[index]
    if acc.sparse is not None or acc.bufferView is None:
        raise PromptGSError(f"{path}: attribute {name} uses a sparse or empty accessor, which is not supported")
    if acc.componentType not in _COMPONENT_TYPES or acc.type not in _COMPONENTS:
        raise PromptGSError(f"{path}: attribute {name} has an unsupported accessor ({acc.type}, component type {acc.componentType})")
    dtype, divisor = _COMPONENT_TYPES[acc.componentType]
    width = _COMPONENTS[acc.type]
    view = doc.bufferViews[acc.bufferView]
    item = np.dtype(dtype).itemsize * width
    stride = view.byteStride or item
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    end = start + stride * (acc.count - 1) + item if acc.count else start
    data = buffers[view.buffer]
    if end > len(data) or (acc.byteOffset or 0) + stride * max(acc.count - 1, 0) + item > view.byteLength:
        raise PromptGSError(f"{path}: truncated glTF (attribute {name} runs past its buffer)")
    raw = np.lib.stride_tricks.as_strided(
        np.frombuffer(data, dtype=np.uint8, count=end - start, offset=start),
        shape=(acc.count, item), strides=(stride, 1)).copy()
    values = raw.view(dtype).reshape(acc.count, width).astype(np.float64)
    if acc.normalized and divisor is not None:
        values = np.maximum(values / divisor, -1.0)
    return values


def _node_transforms(doc) -> list[tuple[int, np.ndarray]]:
    """(mesh, 4×4 global matrix) for every mesh node in the default scene."""
    def local(node) -> np.ndarray:
        if node.matrix:
            return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T  # column-major
        m = np.eye(4)
        x, y, z, w = node.rotation or (0.0, 0.0, 0.0, 1.0)
        qm = _quat_matrix(np.array([w, x, y, z]))
        m[:3, :3] = qm * np.array(node.scale or (1.0, 1.0, 1.0))[None, :]
        m[:3, 3] = node.translation or (0.0, 0.0, 0.0)
        return m

    out: list[tuple[int, np.ndarray]] = []
    scene = doc.scenes[doc.scene or 0] if doc.scenes else None
    roots = scene.nodes if scene is not None else list(range(len(doc.nodes)))
    stack = [(i, np.eye(4)) for i in roots]
    while stack:
        i, parent = stack.pop()
        node = doc.nodes[i]
        m = parent @ local(node)
        if node.mesh is not None:
            out.append((node.mesh, m))
        stack.extend((c, m) for c in node.children or [])
    return out


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def read_gltf(path: str | Path) -> Splats:
    """Gaussians from a ``.gltf`` or ``.glb`` with ``KHR_gaussian_splatting``, in the engine's frame."""
    path = Path(path)
    if not path.is_file():
        raise PromptGSError(f"{path}: no such glTF file")
    doc = _load(path)
    unknown = [e for e in (doc.extensionsRequired or []) if e != EXTENSION]
    if unknown:
        raise PromptGSError(f"{path}: needs the glTF extensions {', '.join(unknown)}, which are not supported")
    if EXTENSION not in (doc.extensionsUsed or []):
        raise PromptGSError(f"{path}: a glTF file without Gaussians (no {EXTENSION} extension)")
    buffers = _buffers(doc, path)
    parts: list[Splats] = []
    for mesh, matrix in _node_transforms(doc):
        for primitive in doc.meshes[mesh].primitives:
            if EXTENSION in (primitive.extensions or {}):
                parts.append(_read_primitive(doc, buffers, primitive, matrix, path))
    if not parts:
        raise PromptGSError(f"{path}: a glTF file without Gaussians (no primitive of its scene uses {EXTENSION})")
    degree = min(p.sh_degree for p in parts)
    parts = [p.with_sh_degree(degree) for p in parts]
    return Splats(**{key: np.concatenate([getattr(p, key) for p in parts]) for key in
                     ("means", "scales", "quats", "opacities", "sh0", "sh_rest")})


def _read_primitive(doc, buffers, primitive, matrix: np.ndarray, path: Path) -> Splats:
    settings = primitive.extensions[EXTENSION] or {}
    kernel = settings.get("kernel", KERNEL)
    if kernel != KERNEL:
        raise PromptGSError(f"{path}: Gaussian kernel {kernel!r} is not supported (only {KERNEL!r})")
    if primitive.mode != 0:
        raise PromptGSError(f"{path}: a {EXTENSION} primitive must be of points (mode 0), it has mode {primitive.mode}")
    attrs = {k: v for k, v in vars(primitive.attributes).items() if v is not None}
    required = ["POSITION", PREFIX + "ROTATION", PREFIX + "SCALE", PREFIX + "OPACITY", PREFIX + "SH_DEGREE_0_COEF_0"]
    missing = [a for a in required if a not in attrs]
    if missing:
        raise PromptGSError(f"{path}: {EXTENSION} primitive without {', '.join(missing)}")

    def get(name: str) -> np.ndarray:
        return _accessor(doc, buffers, attrs[name], path, name)

    degree = 0
    while degree < 3 and all(name in attrs for name in _sh_names(degree + 1)[degree * (degree + 2):]):
        degree += 1
    means = get("POSITION")
    n = len(means)
    quats_xyzw = get(PREFIX + "ROTATION")
    quats = quats_xyzw[:, [3, 0, 1, 2]]
    scales = get(PREFIX + "SCALE")
    opacity = get(PREFIX + "OPACITY").reshape(n)
    sh_rest = np.stack([get(name) for name in _sh_names(degree)], axis=1) if degree else np.zeros((n, 0, 3))
    # The node's transform: rotation, translation and one scale factor.
    linear, offset = matrix[:3, :3], matrix[:3, 3]
    factor = float(np.cbrt(np.linalg.det(linear)))
    rotation = linear / factor if factor > 0 else linear
    if factor <= 0 or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5):
        raise PromptGSError(f"{path}: a node transform with non-uniform or negative scale is not supported")
    if not np.allclose(linear, np.eye(3), atol=0):
        means = means @ linear.T
        quats = quat_multiply(rotation_to_quat(rotation), quats)
        scales = scales * factor
        sh_rest = rotate_sh(rotation, sh_rest).astype(np.float64) if degree else sh_rest
    means = means + offset
    # glTF's +Y up to the engine's +Z up: a signed permutation, exact.
    quats, scales = permute_axes(Y_UP_TO_Z_UP, quats, scales)
    return Splats(
        means=rotate_points(Y_UP_TO_Z_UP, means),
        scales=np.log(np.maximum(scales, _MIN_SCALE)).astype(np.float32),
        quats=quats.astype(np.float32),
        opacities=logit(opacity),
        sh0=get(PREFIX + "SH_DEGREE_0_COEF_0").astype(np.float32),
        sh_rest=rotate_sh(Y_UP_TO_Z_UP, sh_rest) if degree else sh_rest.astype(np.float32),
    )
