"""`promptgs train` on photos or a video: structure from motion first, into the run folder."""

from __future__ import annotations

from pathlib import Path

from ..events import EventWriter
from .inputs import IMAGE_SUFFIXES
from .pipeline import SfmOptions, finished_summary, run_sfm
from .video import is_video_file

SFM_FOLDER = "sfm"


def _has_model(folder: Path) -> bool:
    from ..data.colmap import find_model_dir
    from ..errors import DatasetError

    try:
        find_model_dir(folder)
        return True
    except DatasetError:
        return False


def needs_sfm(dataset: Path) -> bool:
    """True for a video file, or a folder of images with no COLMAP model (no sparse/)."""
    if is_video_file(dataset):
        return True
    if not dataset.is_dir() or _has_model(dataset):
        return False
    return any(p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES for p in dataset.iterdir())


def sfm_dataset_for_run(
    dataset: Path,
    run_dir: Path,
    options: SfmOptions | None = None,
    events: EventWriter | None = None,
    quiet: bool = False,
) -> Path:
    """Run SfM on `dataset` into ``run_dir/sfm`` and return that dataset folder.

    A finished reconstruction already there (a resumed or repeated run) is used as it is,
    so the cameras a checkpoint was trained with never change under it.
    """
    target = run_dir / SFM_FOLDER
    if finished_summary(target) is None:
        run_sfm(dataset, target, options, events=events, quiet=quiet)
    return target
