"""Write single-channel 16-bit PNG files with numpy and zlib only (no bpy)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def write_png16(path: Path, image: np.ndarray) -> None:
    """Write a [H, W] array of integers 0..65535 as a 16-bit greyscale PNG."""
    img = np.asarray(image)
    if img.ndim != 2 or img.min(initial=0) < 0 or img.max(initial=0) > 65535:
        raise ValueError(f"{path}: expected a [H, W] array of values 0..65535")
    h, w = img.shape
    rows = np.ascontiguousarray(img.astype(">u2")).view(np.uint8).reshape(h, w * 2)
    raw = np.concatenate([np.zeros((h, 1), dtype=np.uint8), rows], axis=1).tobytes()
    header = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)
    data = b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(raw, 6)) + _chunk(b"IEND", b"")
    Path(path).write_bytes(data)
