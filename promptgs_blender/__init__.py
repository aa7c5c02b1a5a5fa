"""PromptGS for Blender: import COLMAP scenes, draw prompt cubes, train focused 3D Gaussian
Splatting in a separate trainer process and watch the Gaussians and the error field grow.

The add-on uses only bpy, mathutils, numpy and the standard library; the trainer
(``promptgs_engine``, PyTorch) runs as another process. Importing this package does not
import bpy, so the ``dataset`` subpackage can be used from the engine's command line.
"""

_MODULES = ("props", "operators", "ui", "training", "overlay")


def _modules():
    import importlib
    return [importlib.import_module(f".{name}", __package__) for name in _MODULES]


def register():
    for module in _modules():
        module.register()


def unregister():
    for module in reversed(_modules()):
        module.unregister()
