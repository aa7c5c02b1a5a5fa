"""Structure from motion inside the product: photos or a video in, a dataset to train on out.

`run_sfm` (pipeline.py) runs pycolmap's SIFT extraction, matching, incremental mapping
and undistortion; video.py takes frames from a video with PyAV; chain.py lets
`promptgs train` start from photos or a video. See docs/sfm.md.
"""

from .chain import needs_sfm, sfm_dataset_for_run
from .pipeline import SfmOptions, run_sfm

__all__ = ["SfmOptions", "needs_sfm", "run_sfm", "sfm_dataset_for_run"]
