"""Reading images from disk: header sizes, area downscaling, and a byte-bounded LRU cache.

Pixel convention (the one COLMAP and gsplat use): pixel (i, j) covers the square
[j, j+1) x [i, i+1) in image coordinates, so its centre is at (j + 0.5, i + 0.5).
Downscaling by an integer factor f averages f x f blocks (box filter); the block
starting at (f*j, f*i) becomes pixel (j, i), so a point at x in the full image is at
x / f in the small one, and intrinsics scale by exactly 1/f. When the size is not a
multiple of f, the last partial row/column of blocks is cropped (right and bottom
edges), which keeps the 1/f scaling exact.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from ..errors import DatasetError

DEFAULT_CACHE_BYTES = 2 * 1024**3


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, read from its header without decoding pixels."""
    try:
        with Image.open(path) as im:
            return int(im.width), int(im.height)
    except FileNotFoundError:
        raise DatasetError(f"{path}: image file not found") from None
    except UnidentifiedImageError:
        raise DatasetError(f"{path}: unreadable image file (not an image format PIL can open)") from None
    except OSError as e:
        raise DatasetError(f"{path}: unreadable image file ({e})") from None


def read_image_uint8(path: Path, downscale: int = 1) -> np.ndarray:
    """Decode an image as RGB uint8 [H, W, 3], box-downscaled by an integer factor.

    The result has size (W // downscale, H // downscale); see the module docstring for
    the cropping convention.
    """
    if downscale < 1:
        raise ValueError(f"downscale must be >= 1, got {downscale}")
    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            if downscale > 1:
                w, h = im.width // downscale, im.height // downscale
                if w == 0 or h == 0:
                    raise DatasetError(f"{path}: image of {im.width}x{im.height} is too small to downscale by {downscale}")
                im = im.reduce(downscale, box=(0, 0, w * downscale, h * downscale))
            return np.asarray(im, dtype=np.uint8).copy()
    except FileNotFoundError:
        raise DatasetError(f"{path}: image file not found") from None
    except UnidentifiedImageError:
        raise DatasetError(f"{path}: unreadable image file (not an image format PIL can open)") from None
    except OSError as e:
        raise DatasetError(f"{path}: unreadable image file ({e})") from None


class BoundedCache:
    """Least-recently-used cache of items that have ``nbytes`` (arrays, tensors), bounded in
    bytes. Thread-safe. Subclasses say what the keys are and how a missing item is made."""

    def __init__(self, max_bytes: int = DEFAULT_CACHE_BYTES) -> None:
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[tuple, Any] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        """Bytes currently held."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0

    def set_max_bytes(self, max_bytes: int) -> None:
        with self._lock:
            self.max_bytes = int(max_bytes)
            self._evict()

    def _held(self, key: tuple):
        """The item under ``key``, now the most recently used, or None."""
        with self._lock:
            item = self._items.get(key)
            if item is not None:
                self._items.move_to_end(key)
            return item

    def _hold(self, key: tuple, item) -> None:
        """Keep ``item`` (anything with ``nbytes``) if it fits, evicting the oldest."""
        with self._lock:
            if key not in self._items and item.nbytes <= self.max_bytes:
                self._items[key] = item
                self._bytes += item.nbytes
                self._evict()

    def _evict(self) -> None:
        while self._bytes > self.max_bytes and self._items:
            _, old = self._items.popitem(last=False)
            self._bytes -= old.nbytes


class ImageCache(BoundedCache):
    """Least-recently-used cache of decoded images (uint8), bounded in bytes.

    Keys are (path, downscale). Thread-safe. Holding uint8 rather than float32 keeps
    four times as many images for the same memory.
    """

    def get(self, path: Path, downscale: int) -> np.ndarray:
        """The decoded image, from the cache or from disk (then cached if it fits)."""
        key = (str(path), int(downscale))
        arr = self._held(key)
        if arr is None:
            arr = read_image_uint8(path, downscale)
            arr.setflags(write=False)
            self._hold(key, arr)
        return arr


IMAGE_CACHE = ImageCache()


def set_image_cache_bytes(max_bytes: int) -> None:
    """Bound the process-wide decoded-image cache (default 2 GiB; 0 disables caching)."""
    IMAGE_CACHE.set_max_bytes(max_bytes)


def preload_images(items: list[tuple[Path, int, int]], threads: int = 1, cache: ImageCache | None = None) -> bool:
    """Decode images into the cache before they are needed, ``threads`` at a time.

    ``items`` are (path, downscale, decoded bytes). Nothing is read when they would not all
    fit in the cache's free room, or when a file is missing (they then load as needed, and a
    missing one is reported when a step needs it); returns whether they were read.
    """
    cache = IMAGE_CACHE if cache is None else cache
    if sum(nbytes for _, _, nbytes in items) > cache.max_bytes - cache.nbytes:
        return False
    if not all(Path(path).is_file() for path, _, _ in items):
        return False
    from concurrent.futures import ThreadPoolExecutor  # PIL decodes without the GIL

    with ThreadPoolExecutor(max(1, int(threads))) as pool:
        list(pool.map(lambda item: cache.get(item[0], item[1]), items))
    return True


# float32(i) / 255 for every 8-bit value, computed as the CPU path computes it: indexing
# this table converts an image on any device to the same floats, bit for bit (a CUDA
# division by a scalar multiplies by its reciprocal, which can differ in the last bit).
_UNIT_TABLE = np.arange(256, dtype=np.float32) / np.float32(255.0)


class DeviceImageCache(ImageCache):
    """Decoded 8-bit images kept on an accelerator, least recently used first out, bounded
    in bytes over all devices. A training step then converts its image to float where it
    renders, instead of converting on the CPU and copying four times the bytes each step."""

    def __init__(self, max_bytes: int = DEFAULT_CACHE_BYTES) -> None:
        super().__init__(max_bytes)
        self._tables: dict[str, torch.Tensor] = {}

    def clear(self) -> None:
        super().clear()
        self._tables.clear()

    def get(self, path: Path, downscale: int, device: torch.device, host: np.ndarray | None) -> torch.Tensor:  # type: ignore[override]
        """The uint8 image on ``device``: cached, or copied from ``host`` (then cached if it fits)."""
        key = (str(path), int(downscale), str(device))
        image = self._held(key)
        if image is None:
            image = torch.from_numpy(host.copy()).to(device)  # the host array is read-only
            self._hold(key, image)
        return image

    def to_unit_float(self, image: torch.Tensor) -> torch.Tensor:
        """uint8 [..] to float32 in [0, 1] on the image's device, equal to the CPU's conversion."""
        key = str(image.device)
        table = self._tables.get(key)
        if table is None:
            table = self._tables[key] = torch.from_numpy(_UNIT_TABLE).to(image.device)
        return table[image.long()]


DEVICE_IMAGE_CACHE = DeviceImageCache()


def load_image_tensor(
    path: Path,
    downscale: int,
    expected_size: tuple[int, int],
    window: tuple[int, int, int, int] | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """[H, W, 3] float32 in [0, 1]; checks the decoded size is `expected_size` (W, H).

    ``window`` (x0, y0, width, height) cuts a crop out of the 8-bit image before it
    becomes float, so that a crop costs its own pixels, not the whole image's.
    ``device`` other than the CPU returns the tensor there, the same values: the 8-bit
    image is kept on that device (`DEVICE_IMAGE_CACHE`) and converted there."""
    arr = IMAGE_CACHE.get(path, downscale)
    h, w = arr.shape[:2]
    if (w, h) != tuple(expected_size):
        raise DatasetError(
            f"{path}: image is {w}x{h} at downscale {downscale}, expected {expected_size[0]}x{expected_size[1]}"
        )
    if window is not None:
        x0, y0, cw, ch = window
        if x0 < 0 or y0 < 0 or x0 + cw > w or y0 + ch > h:
            raise ValueError(f"{path}: window {window} is not inside the {w}x{h} image")
    on_cpu = device is None or torch.device(device).type == "cpu"
    image = arr if on_cpu else DEVICE_IMAGE_CACHE.get(path, downscale, torch.device(device), arr)
    if window is not None:
        image = image[y0 : y0 + ch, x0 : x0 + cw]
    return torch.from_numpy(image.astype(np.float32)).div_(255.0) if on_cpu else DEVICE_IMAGE_CACHE.to_unit_float(image)
