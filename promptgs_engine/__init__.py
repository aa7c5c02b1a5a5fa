"""PromptGS engine: 3D Gaussian Splatting training with visual prompts for tiny objects."""

import os

# The C++ rasterizer's OpenMP threads must not spin while waiting: on a small shared
# machine spinning threads starve each other (measured: the 2-thread training step
# collapses under load without this). Must be set before torch loads the OpenMP runtime.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# A training step's image-sized buffers from memory the process holds, not fresh pages
# each step (allocator.py says why and what it measured).
from .allocator import keep_large_buffers

keep_large_buffers()

__version__ = "0.1.0"
