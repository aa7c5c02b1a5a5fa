"""A training step's small CPU bookkeeping, on the calling thread alone.

The engine sets ``OMP_WAIT_POLICY=PASSIVE`` (see ``__init__``): idle OpenMP threads sleep
instead of spinning, so that runs sharing a small machine do not starve each other. Every
parallel region of torch's CPU kernels then wakes a sleeping thread, which costs more than
it saves on tensors of 10⁴–10⁵ elements. A step's bookkeeping (the growth statistics,
PromptGS's scores and per-view losses, the error field) is dozens of such operations.

`one_thread` runs a block with torch's intra-op threads set to one (element-wise kernels
then run inline, without waking anyone) and puts the count back afterwards, also on an
error. The block's results are the same bits: the operations it is used around are
element-wise, gathers and scatters whose sums do not depend on how the work is split
(`tests/test_threads.py`, and whole runs compared to the last bit). Used around the
strategies' statistics, `PromptFocus.observe` and the trainer's finiteness check (a sum
per parameter, whose finiteness is the same however it is split).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Run the block with one intra-op thread, then restore the count the caller had."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
