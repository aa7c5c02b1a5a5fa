"""Large CPU buffers reused from the heap instead of fresh pages at every training step.

glibc serves an allocation above its mmap threshold with new pages from the kernel and
returns them when it is freed, and it gives back the top of the heap once more than the
trim threshold lies free there. A CPU training step allocates and frees image-sized
buffers (renders, the loss maps, the SSIM partials the backward needs: 17 MB at
800×600), so by default each step page-faults and zeroes them again; whether glibc's
sliding threshold catches up differs from process to process, and on a 2-core Xeon a
tumbler step at 800×600 took about 50 ms in most processes and 40 ms in the others
(`benchmarks/train_profile.py`: the loss forward 8.8 against 4.3 ms). With the mmap
threshold at glibc's 64-bit maximum (32 MiB) and the trim threshold at 1 GiB, such
buffers come from memory the process already holds, in every process. What is computed
does not change; freed memory up to the trim threshold stays with the process.

Set at import of the engine (``__init__``), unless ``MALLOC_MMAP_THRESHOLD_`` or
``MALLOC_TRIM_THRESHOLD_`` is in the environment (glibc then uses what they say), and only
where the C library has glibc's ``mallopt``.
"""

from __future__ import annotations

import ctypes
import os
import sys

# glibc's <malloc.h>
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD = 32 * 2**20  # the largest glibc accepts on 64-bit systems
TRIM_THRESHOLD = 2**30


def keep_large_buffers() -> bool:
    """Raise glibc's mmap and trim thresholds (see the module docstring); whether both
    were set. Does nothing where the environment sets either, or off glibc."""
    if not sys.platform.startswith("linux"):
        return False
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1 and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
