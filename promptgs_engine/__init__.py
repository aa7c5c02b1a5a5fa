"""PromptGS engine: 3D Gaussian Splatting training with visual prompts for tiny objects."""

__version__ = "0.1.0"
