"""Frames from a video file: a chosen rate, the sharpest frame of each time window kept.

Decoding uses PyAV (the ``av`` package), whose wheels ship FFmpeg's libraries and codecs:
no system ffmpeg is needed. Each window of ``1 / fps`` seconds yields one frame, the one
with the highest sharpness (variance of the Laplacian of its grey levels), so motion-
blurred frames are dropped. Frames are written as numbered JPEGs (``frame_000001.jpg``,
…) in time order, which is the order sequential matching follows.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

from ..errors import DatasetError

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".mts", ".m2ts", ".mpg", ".mpeg", ".wmv", ".flv", ".3gp")
FRAME_PATTERN = "frame_{:06d}.jpg"
FRAMES_RECORD = "frames.json"


def is_video_file(path: Path) -> bool:
    """True for a file whose suffix is a common video container."""
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def sharpness(gray: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of a grey image (higher: sharper)."""
    g = gray.astype(np.float32)
    lap = 4.0 * g[1:-1, 1:-1] - g[:-2, 1:-1] - g[2:, 1:-1] - g[1:-1, :-2] - g[1:-1, 2:]
    return float(lap.var())


def _resized(image: Image.Image, max_size: int | None) -> Image.Image:
    if max_size is None or max(image.size) <= max_size:
        return image
    s = max_size / max(image.size)
    return image.resize((max(1, round(image.width * s)), max(1, round(image.height * s))), Image.LANCZOS)


@dataclass
class FrameStats:
    """What `extract_frames` did: frames decoded and written, the video's own rate, and
    the time (seconds into the video) of each written frame."""

    decoded: int
    written: int
    video_fps: float | None
    duration_s: float | None
    times_s: list[float]

    def to_json(self) -> dict:
        """The counts (not the per-frame times) for a summary."""
        return {"decoded": self.decoded, "written": self.written, "video_fps": self.video_fps, "duration_s": self.duration_s}


def _record(video: Path, fps: float, max_frames: int | None, max_size: int | None) -> dict:
    st = video.stat()
    return {
        "video": str(video.resolve()),
        "size": st.st_size,
        "mtime": st.st_mtime,
        "fps": fps,
        "max_frames": max_frames,
        "max_image_size": max_size,
    }


def probe_video(video: Path) -> None:
    """Open `video` and decode its first frame; DatasetError (one line, naming it) if that fails."""
    import av

    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                raise DatasetError(f"{video}: holds no video stream")
            for _ in container.decode(container.streams.video[0]):
                return
    except DatasetError:
        raise
    except av.FFmpegError as e:
        raise DatasetError(f"{video}: cannot open the video ({_first_line(e)})") from None
    except (OSError, ValueError) as e:
        raise DatasetError(f"{video}: cannot open the video ({_first_line(e)})") from None
    raise DatasetError(f"{video}: no frame could be decoded")


def extract_frames(
    video: Path,
    out_dir: Path,
    fps: float = 2.0,
    max_frames: int | None = None,
    max_size: int | None = None,
    progress: Callable[[int, int | None], None] | None = None,
) -> FrameStats:
    """Write the sharpest frame of every ``1 / fps`` seconds of `video` into `out_dir`.

    `max_size` caps the longer side of the written frames (pixels). `progress(done,
    total)` is called as frames are decoded (`total` None when the video does not say).
    When `out_dir` already holds the frames of this very video and these settings (see
    ``frames.json``), nothing is decoded again. Raises DatasetError (one line, naming the
    video) when it cannot be opened or decoded, or yields no frame.
    """
    import av  # PyAV: imported here so the engine loads without it until a video is given

    if fps <= 0:
        raise DatasetError(f"frame rate must be > 0 frames per second, got {fps}")
    record = _record(video, fps, max_frames, max_size)
    record_path = out_dir / FRAMES_RECORD
    if record_path.is_file():
        try:
            saved = json.loads(record_path.read_text())
        except (OSError, json.JSONDecodeError):
            saved = None
        if saved and saved.get("settings") == record and saved.get("complete"):
            return FrameStats(**saved["stats"])
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("frame_*.jpg"):
        old.unlink()
    record_path.unlink(missing_ok=True)

    try:
        container = av.open(str(video))
    except (av.FFmpegError, OSError, ValueError) as e:
        raise DatasetError(f"{video}: cannot open the video ({_first_line(e)})") from None
    try:
        if not container.streams.video:
            raise DatasetError(f"{video}: holds no video stream")
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        rate = float(stream.average_rate) if stream.average_rate else None
        total = int(stream.frames) if stream.frames else None
        duration = float(stream.duration * stream.time_base) if stream.duration and stream.time_base else None
        if total is None and duration and rate:
            total = int(round(duration * rate))
        window = 1.0 / fps
        decoded = 0
        times: list[float] = []
        best: tuple[float, Image.Image, float] | None = None
        current = None
        try:
            for frame in container.decode(stream):
                t = frame.time if frame.time is not None else decoded / (rate or 30.0)
                decoded += 1
                k = int(np.floor(t / window + 1e-9))
                if current is not None and k != current and best is not None:
                    _write(best, times, out_dir, max_size)
                    best = None
                    if max_frames is not None and len(times) >= max_frames:
                        break
                current = k
                image = frame.to_image()
                small = image.convert("L")
                if max(small.size) > 480:  # judge sharpness at a fixed scale: cheaper, and comparable across videos
                    small = _resized(small, 480)
                score = sharpness(np.asarray(small))
                if best is None or score > best[0]:
                    best = (score, image, float(t))
                if progress is not None:
                    progress(decoded, total)
        except av.FFmpegError as e:
            if decoded == 0:
                raise DatasetError(f"{video}: cannot decode the video ({_first_line(e)})") from None
            # A truncated file: keep the frames decoded so far.
        if best is not None and (max_frames is None or len(times) < max_frames):
            _write(best, times, out_dir, max_size)
    finally:
        container.close()
    if not times:
        raise DatasetError(f"{video}: no frame could be decoded")
    stats = FrameStats(decoded=decoded, written=len(times), video_fps=rate, duration_s=duration, times_s=times)
    tmp = record_path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"settings": record, "complete": True, "stats": asdict(stats)}, indent=2))
    os.replace(tmp, record_path)
    return stats


def _write(best: tuple[float, Image.Image, float], times: list[float], out_dir: Path, max_size: int | None) -> None:
    times.append(round(best[2], 6))
    _resized(best[1], max_size).save(out_dir / FRAME_PATTERN.format(len(times)), quality=95)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
