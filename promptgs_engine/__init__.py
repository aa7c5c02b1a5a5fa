"""PromptGS engine: 3D Gaussian Splatting training with visual prompts for tiny objects."""

import os

# The C++ rasterizer's OpenMP threads must not spin while waiting: on a small shared
# machine spinning threads starve each other (measured: the 2-thread training step
# collapses under load without this). Must be set before torch loads the OpenMP runtime.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
