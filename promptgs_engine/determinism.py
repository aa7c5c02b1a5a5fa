"""What a CPU run needs, beyond its seed, to give the same bits every time.

torch computes ``sqrt``, ``exp`` and other element-wise functions of large CPU tensors
through MKL's vector math, split over its OpenMP threads (chunks of 2,048 elements). On
the first such call in a process, when two threads enter MKL at once, one thread's chunk
is sometimes computed by another code path: in about one process in ten (2 threads, an
Intel Xeon with AVX-512, torch 2.13) ``torch.sqrt`` of 20,000 doubles differed in the last
bit from every later call. The sky shell's directions (`sky.fibonacci_directions`) were
such a first call, so a few of its points moved by one unit in the last place, and the
whole run parted from its seed's other runs. With ``MKL_NUM_THREADS=1`` it did not happen; neither ``MKL_CBWR=AUTO`` nor
``MKL_DYNAMIC=FALSE`` helped.

`settle_mkl` makes that first call on one thread, with a tensor too small to be split,
before any real work: later calls then agree in every process.
"""

from __future__ import annotations

import functools

import torch


@functools.cache
def settle_mkl() -> None:
    """Make MKL's first vector-math call of this process on the calling thread alone (once)."""
    for dtype in (torch.float32, torch.float64):
        x = torch.ones(8, dtype=dtype)  # under the 2,048-element chunk: one thread
        torch.sqrt(x)
        torch.exp(x)
