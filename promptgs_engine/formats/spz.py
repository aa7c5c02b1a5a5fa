"""SPZ, Niantic's compressed Gaussian splat format: versions 2 to 4 read, 3 or 4 written.

Written from the format description in Niantic's repository (nianticlabs/spz, README.md
and extensions/README.md at commit 21715c3). A file is a 16-byte header and six packed
arrays in one gzip stream (versions 1-3), or a 32-byte plain header, a table of contents
and one zstd stream per array (version 4). Per Gaussian:

| array     | bytes | encoding                                                        |
|-----------|-------|-----------------------------------------------------------------|
| positions | 9     | x, y, z as 24-bit signed fixed point, ``fractionalBits`` bits   |
| alphas    | 1     | ``sigmoid(logit) * 255``                                        |
| colors    | 3     | SH DC ``sh0 * 0.15 * 255 + 127.5``                              |
| scales    | 3     | log scale ``(s + 10) * 16``                                     |
| rotations | 4     | v3+: index of the largest quaternion component (2 bits) and the |
|           |       | other three, sign and 9 bits each; v2: x, y, z in 3 bytes        |
| sh        | 3K    | ``sh * 128 + 128``, coefficient-major, RGB innermost            |

Coordinates are RUB (right, up, back), unless a version-4 file names another frame in the
``SPZ_ADOBE_coordinate_system`` extension (read here; right-handed frames only). Writing
turns the engine's Z-up world into RUB as Blender's SPZ importer expects it back
(frames.py): ``(x, y, z) -> (x, z, -y)``, orientations turned by the same rotation, SH
rotated band by band.

SH quantisation: each coefficient's code is the nearest multiple of ``2**(8 - bits)``
(``sh_bits``, the library's ``sh1Bits``/``shRestBits``; Niantic's defaults are 5 and 4).
Readers read all 8 bits, so the bits are the writer's choice: coarser codes compress
better. The rounding is done once: Niantic's library rounds to a code first and then to
the multiple with ties always up, a bias shared by every Gaussian (at 7 bits it costs
about as much test-view PSNR as 6 bits without it; benchmarks/formats.py).
"""

from __future__ import annotations

import gzip
import logging
import math
import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import PromptGSError
from .frames import Y_UP_TO_Z_UP, Z_UP_TO_Y_UP, rotate_points, rotate_quats, rotate_sh
from .splats import Splats, logit, sigmoid

log = logging.getLogger(__name__)

MAGIC = 0x5053474E  # "NGSP"
COLOR_SCALE = 0.15
LEGACY_HEADER = struct.Struct("<IIIBBBB")  # magic, version, points, SH degree, fractional bits, flags, reserved
NGSP_HEADER = struct.Struct("<IIIBBBBI12x")  # ... numStreams, tocByteOffset, reserved
FLAG_ANTIALIASED = 0x1
FLAG_EXTENSIONS = 0x2
COORDINATE_SYSTEM_EXTENSION = 0xADBE0003
# SPZ's CoordinateSystem values 1..16; each letter is where that stored axis points.
COORDINATE_SYSTEMS = ("LDB", "RDB", "LUB", "RUB", "LDF", "RDF", "LUF", "RUF",
                      "LFD", "RFD", "LFU", "RFU", "LBD", "RBD", "LBU", "RBU")
_AXIS = {"R": (1, 0, 0), "L": (-1, 0, 0), "U": (0, 1, 0), "D": (0, -1, 0), "B": (0, 0, 1), "F": (0, 0, -1)}
MAX_POSITION_FIXED = (1 << 23) - 1
DEFAULT_FRACTIONAL_BITS = 12  # Niantic's choice: 1/4096 of a unit
SQRT1_2 = math.sqrt(0.5)
ZSTD_LEVEL = 12
GZIP_LEVEL = 6


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _quantize_sh(sh: np.ndarray, bits: int) -> np.ndarray:
    """Codes ``sh * 128 + 128`` on multiples of ``2**(8 - bits)``, in one rounding."""
    bucket = 1 << (8 - bits)
    q = np.rint(np.asarray(sh, dtype=np.float64) * (128.0 / bucket)).astype(np.int64) * bucket + 128
    return np.clip(q, 0, 255).astype(np.uint8)


def _fractional_bits(means_rub: np.ndarray, path: Path) -> int:
    reach = float(np.abs(means_rub).max()) if means_rub.size else 0.0
    if not math.isfinite(reach):
        raise PromptGSError(f"{path}: cannot write SPZ: a Gaussian position is not finite")
    bits = DEFAULT_FRACTIONAL_BITS
    while bits > 0 and reach * (1 << bits) > MAX_POSITION_FIXED:
        bits -= 1
    if reach * (1 << bits) > MAX_POSITION_FIXED:
        raise PromptGSError(f"{path}: cannot write SPZ: a Gaussian lies {reach:.3g} units from the origin, "
                            f"beyond SPZ's 24-bit positions ({MAX_POSITION_FIXED} units)")
    return bits


def _pack_positions(means: np.ndarray, bits: int) -> np.ndarray:
    fixed = np.rint(means.astype(np.float64) * (1 << bits)).astype(np.int32).reshape(-1)
    raw = fixed.astype("<i4").view(np.uint8).reshape(-1, 4)[:, :3]  # little-endian, low 3 bytes
    return np.ascontiguousarray(raw).reshape(-1)


def _unpack_positions(raw: np.ndarray, bits: int) -> np.ndarray:
    b = raw.reshape(-1, 3).astype(np.int32)
    fixed = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    return (fixed.astype(np.float64) / (1 << bits)).astype(np.float32).reshape(-1, 3)


def _pack_quats(quats_wxyz: np.ndarray) -> np.ndarray:
    """Smallest-three packing of unit quaternions (SPZ order x, y, z, w)."""
    q = np.asarray(quats_wxyz, dtype=np.float64)[:, [1, 2, 3, 0]]
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 0.0, 1.0]))
    largest = np.abs(q).argmax(axis=1)
    q = np.where(q[np.arange(len(q)), largest][:, None] < 0, -q, q)
    comp = largest.astype(np.uint32)
    for i in range(4):
        mag = np.floor(511.0 * np.abs(q[:, i]) / SQRT1_2 + 0.5).astype(np.uint32)
        bits = (np.uint32(q[:, i] < 0) << np.uint32(9)) | np.minimum(mag, 511)
        comp = np.where(largest == i, comp, (comp << np.uint32(10)) | bits)
    return comp.astype("<u4").view(np.uint8)


def _unpack_quats(raw: np.ndarray, version: int) -> np.ndarray:
    """Quaternions (w, x, y, z) from version 2 (first three) or 3+ (smallest three)."""
    if version == 2:
        xyz = raw.reshape(-1, 3).astype(np.float64) / 127.5 - 1.0
        w = np.sqrt(np.clip(1.0 - (xyz**2).sum(axis=1), 0.0, None))
        return np.column_stack([w, xyz]).astype(np.float32)
    packed = raw.reshape(-1, 4).copy().view("<u4").reshape(-1).astype(np.uint64)
    largest = (packed >> np.uint64(30)).astype(np.int64)
    q = np.zeros((len(packed), 4))
    rest = packed.copy()
    for i in range(3, -1, -1):
        mag = (rest & np.uint64(511)).astype(np.float64)
        sign = np.where((rest >> np.uint64(9)) & np.uint64(1), -1.0, 1.0)
        value = SQRT1_2 * mag / 511.0 * sign
        here = largest != i
        q[here, i] = value[here]
        rest = np.where(here, rest >> np.uint64(10), rest)
    rows = np.arange(len(q))
    q[rows, largest] = np.sqrt(np.clip(1.0 - (q**2).sum(axis=1), 0.0, None))
    return q[:, [3, 0, 1, 2]].astype(np.float32)


def _frame_from_extensions(records: bytes, path: Path) -> np.ndarray:
    """The stored frame's axes in RUB (a 3×3 matrix: v_rub = M v_stored) from the
    extension records, RUB when none names one."""
    frame = np.eye(3)
    offset = 0
    while offset + 8 <= len(records):
        kind, length = struct.unpack_from("<II", records, offset)
        payload = records[offset + 8 : offset + 8 + length]
        if len(payload) < length:
            raise PromptGSError(f"{path}: truncated SPZ (an extension record runs past its block)")
        if kind == COORDINATE_SYSTEM_EXTENSION and length >= 4:
            value = struct.unpack_from("<I", payload)[0]
            if value:  # 0: unspecified, read as RUB
                if not 1 <= value <= len(COORDINATE_SYSTEMS):
                    raise PromptGSError(f"{path}: SPZ names an unknown coordinate system ({value})")
                name = COORDINATE_SYSTEMS[value - 1]
                frame = np.array([_AXIS[c] for c in name], dtype=np.float64).T
                if np.linalg.det(frame) < 0:
                    raise PromptGSError(f"{path}: SPZ stored in the left-handed frame {name} is not supported")
        offset += 8 + length
    return frame


def _ngsp_streams(data: bytes, path: Path) -> tuple[tuple, list[bytes], bytes]:
    if len(data) < NGSP_HEADER.size:
        raise PromptGSError(f"{path}: truncated SPZ ({len(data)} bytes, shorter than its 32-byte header)")
    header = NGSP_HEADER.unpack_from(data)
    n_streams, toc = header[6], header[7]
    toc_end = toc + 16 * n_streams
    if toc < NGSP_HEADER.size or toc_end > len(data):
        raise PromptGSError(f"{path}: truncated SPZ (its table of contents runs past the end of the file)")
    try:
        import zstandard
    except ImportError as exc:  # declared in pyproject; for a clear message where it is missing
        raise PromptGSError(f"{path}: SPZ version 4 needs the 'zstandard' package") from exc
    offset, streams = toc_end, []
    for i in range(n_streams):
        packed_size, size = struct.unpack_from("<QQ", data, toc + 16 * i)
        chunk = data[offset : offset + packed_size]
        if len(chunk) < packed_size:
            raise PromptGSError(f"{path}: truncated SPZ (stream {i + 1} of {n_streams} runs past the end of the file)")
        try:
            streams.append(zstandard.ZstdDecompressor().decompress(chunk, max_output_size=size))
        except zstandard.ZstdError as exc:
            raise PromptGSError(f"{path}: corrupt SPZ (stream {i + 1}: {exc})") from exc
        offset += packed_size
    records = data[NGSP_HEADER.size : toc] if header[5] & FLAG_EXTENSIONS else b""
    return header, streams, records


def read_spz(path: str | Path) -> Splats:
    """Gaussians from an SPZ file (versions 2-4), in the engine's frame; SH of degree 4
    is cut to 3 (the engine renders up to 3)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PromptGSError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if data[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(data)
        except (EOFError, OSError, zlib.error) as exc:
            raise PromptGSError(f"{path}: truncated or corrupt SPZ (gzip: {exc})") from exc
        if len(raw) < LEGACY_HEADER.size:
            raise PromptGSError(f"{path}: truncated SPZ (no complete header)")
        magic, version, n, degree, bits, flags, _ = LEGACY_HEADER.unpack_from(raw)
        body = memoryview(raw)[LEGACY_HEADER.size :]
        streams = None
    elif len(data) >= 4 and struct.unpack_from("<I", data)[0] == MAGIC:
        header, streams, records = _ngsp_streams(data, path)
        magic, version, n, degree, bits, flags = header[:6]
    else:
        raise PromptGSError(f"{path}: not an SPZ file (neither a gzip stream nor the NGSP header)")
    if magic != MAGIC:
        raise PromptGSError(f"{path}: not an SPZ file (wrong magic number)")
    if not 2 <= version <= 4:
        raise PromptGSError(f"{path}: SPZ version {version} is not supported (2 to 4 are)")
    if (version == 4) != (streams is not None):
        raise PromptGSError(f"{path}: SPZ version {version} in the wrong container")
    if degree > 4:
        raise PromptGSError(f"{path}: SPZ with SH degree {degree} (at most 4)")
    k = (degree + 1) ** 2 - 1
    rot_bytes = 3 if version == 2 else 4
    sizes = [9 * n, n, 3 * n, 3 * n, rot_bytes * n, 3 * k * n]
    if streams is None:
        need = sum(sizes)
        if len(body) < need:
            raise PromptGSError(f"{path}: truncated SPZ: {n} Gaussians need {need} bytes of data, it has {len(body)}")
        arrays, offset = [], 0
        for size in sizes:
            arrays.append(np.frombuffer(body[offset : offset + size], dtype=np.uint8))
            offset += size
        records = bytes(body[offset:]) if flags & FLAG_EXTENSIONS else b""
    else:
        expected = [s for s in sizes if s]
        if [len(s) for s in streams] != expected:
            raise PromptGSError(f"{path}: truncated or corrupt SPZ: stream sizes {[len(s) for s in streams]} "
                                f"do not fit {n} Gaussians of SH degree {degree}")
        arrays = [np.frombuffer(s, dtype=np.uint8) for s in streams] + ([np.zeros(0, np.uint8)] if not k else [])
    positions, alphas, colors, scales, rotations, sh = arrays
    to_world = Y_UP_TO_Z_UP @ _frame_from_extensions(records, path)
    means = _unpack_positions(positions, bits)
    quats = _unpack_quats(rotations, version)
    sh_rest = ((sh.reshape(n, k, 3).astype(np.float32) - 128.0) / 128.0) if k else np.zeros((n, 0, 3), np.float32)
    if degree == 4:
        log.warning("%s: SH degree 4 cut to 3", path)
        sh_rest = sh_rest[:, :15]
    return Splats(
        means=rotate_points(to_world, means),
        scales=(scales.reshape(n, 3).astype(np.float32) / 16.0 - 10.0),
        quats=rotate_quats(to_world, quats),
        opacities=logit(alphas.astype(np.float64) / 255.0),
        sh0=((colors.reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / COLOR_SCALE).astype(np.float32),
        sh_rest=rotate_sh(to_world, sh_rest) if sh_rest.shape[1] else sh_rest,
        antialiased=bool(flags & FLAG_ANTIALIASED),
    )


def encode_spz(splats: Splats, path: Path, version: int = 3, sh_bits: tuple[int, int] = (8, 8)) -> bytes:
    """The bytes of an SPZ file of ``splats``; ``sh_bits``: significant bits of the degree-1
    and of the degree-2/3 SH codes (1..8)."""
    if version not in (3, 4):
        raise PromptGSError(f"SPZ version {version} cannot be written (3 or 4)")
    if not all(1 <= b <= 8 for b in sh_bits):
        raise PromptGSError(f"SPZ SH bits must be 1..8, got {sh_bits}")
    n, degree = splats.n, splats.sh_degree
    means = rotate_points(Z_UP_TO_Y_UP, splats.means)
    bits = _fractional_bits(means, path)
    sh = rotate_sh(Z_UP_TO_Y_UP, splats.sh_rest) if degree else splats.sh_rest
    sh_codes = np.concatenate([_quantize_sh(sh[:, :3], sh_bits[0]), _quantize_sh(sh[:, 3:], sh_bits[1])], axis=1)
    arrays = [
        _pack_positions(means, bits),
        _u8(sigmoid(splats.opacities).astype(np.float64) * 255.0),
        _u8(splats.sh0.astype(np.float64) * (COLOR_SCALE * 255.0) + 127.5).reshape(-1),
        _u8((splats.scales.astype(np.float64) + 10.0) * 16.0).reshape(-1),
        _pack_quats(rotate_quats(Z_UP_TO_Y_UP, splats.quats)),
        sh_codes.reshape(-1),
    ]
    flags = FLAG_ANTIALIASED if splats.antialiased else 0
    if version == 3:
        header = LEGACY_HEADER.pack(MAGIC, 3, n, degree, bits, flags, 0)
        return gzip.compress(header + b"".join(a.tobytes() for a in arrays), compresslevel=GZIP_LEVEL, mtime=0)
    import zstandard

    streams = [a.tobytes() for a in arrays if a.size]
    packed = [zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(s) for s in streams]
    header = NGSP_HEADER.pack(MAGIC, 4, n, degree, bits, flags, len(streams), NGSP_HEADER.size)
    toc = b"".join(struct.pack("<QQ", len(p), len(s)) for p, s in zip(packed, streams))
    return header + toc + b"".join(packed)
