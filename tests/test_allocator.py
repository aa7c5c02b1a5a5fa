"""The engine keeps large CPU buffers in the heap (promptgs_engine/allocator.py)."""

import os
import subprocess
import sys
import textwrap

import pytest

# Whether a fresh process's first 17 MB tensor (the SSIM partials at 800×600) lies in the
# heap, which glibc reuses, or in pages mapped for it alone, which it unmaps when freed.
IN_HEAP = textwrap.dedent(
    """
    import torch
    import promptgs_engine
    t = torch.empty(3 * 600 * 800 * 3)
    with open("/proc/self/maps") as f:
        heap = [line.split()[0] for line in f if line.rstrip().endswith("[heap]")]
    lo, hi = (int(v, 16) for v in heap[0].split("-"))
    print(lo <= t.data_ptr() < hi)
    """
)


def _in_heap(**env: str) -> bool:
    environ = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    environ.update(env)
    out = subprocess.run([sys.executable, "-c", IN_HEAP], env=environ, capture_output=True, text=True, check=True)
    return out.stdout.split()[-1] == "True"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt and /proc/self/maps")
def test_an_image_sized_buffer_comes_from_the_heap_unless_the_environment_says_otherwise():
    assert _in_heap()
    # glibc's own setting where the environment gives one: its default threshold maps
    # such a buffer by itself.
    assert not _in_heap(MALLOC_MMAP_THRESHOLD_="131072")
