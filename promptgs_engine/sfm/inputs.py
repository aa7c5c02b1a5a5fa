"""What `promptgs sfm` is given: a folder of photos or a video file, checked up front."""

from __future__ import annotations

import re
from pathlib import Path

from PIL import Image, UnidentifiedImageError

from ..errors import DatasetError
from .video import VIDEO_SUFFIXES, is_video_file

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")


def natural_key(name: str) -> list:
    """Sort key that orders numbers by value: ``2.jpg`` before ``10.jpg``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def input_kind(path: Path) -> str:
    """"images" for a folder, "video" for a video file; DatasetError otherwise."""
    if not path.exists():
        raise DatasetError(f"{path}: not found (give a folder of images or a video file)")
    if path.is_dir():
        return "images"
    if is_video_file(path):
        return "video"
    raise DatasetError(
        f"{path}: neither a folder of images nor a video file (video suffixes: {', '.join(VIDEO_SUFFIXES)})"
    )


def list_images(folder: Path) -> list[str]:
    """Names of the image files directly in `folder`, in natural order, each checked.

    Every file is opened and its header read, so an unreadable file is named before
    any work starts. Raises DatasetError when the folder holds no image or one of them
    cannot be read.
    """
    names = sorted(
        (p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")),
        key=natural_key,
    )
    if not names:
        raise DatasetError(f"{folder}: no images found (looked for {', '.join(IMAGE_SUFFIXES)} files)")
    for name in names:
        check_image(folder / name)
    return names


def check_image(path: Path) -> tuple[int, int]:
    """(width, height) of an image whose pixels decode; DatasetError naming it otherwise."""
    try:
        with Image.open(path) as im:
            size = int(im.width), int(im.height)
            im.draft("RGB", (max(1, size[0] // 8), max(1, size[1] // 8)))  # JPEG: decode at 1/8 scale, quick
            im.load()
            return size
    except UnidentifiedImageError:
        raise DatasetError(f"{path}: unreadable image file (not an image format that can be opened)") from None
    except (OSError, ValueError, SyntaxError) as e:
        raise DatasetError(f"{path}: unreadable image file ({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None
