"""Run the Blender-side generator (``promptgs_blender/dataset``) in its own process.

Either the ``bpy`` module of this Python (``python -c ...``) or a Blender binary
(``blender -b --python-expr ... -- ARGS``). The dataset package is loaded from its folder
under a private name, so the add-on's own ``__init__`` (UI registration) never runs.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from typing import Callable

from ..errors import DatasetError

DATASET_PACKAGE = Path(__file__).resolve().parents[2] / "promptgs_blender" / "dataset"

_BOOTSTRAP = """\
import importlib.util, sys
root = {root!r}
spec = importlib.util.spec_from_file_location(
    "promptgs_dataset", root + "/__init__.py", submodule_search_locations=[root])
module = importlib.util.module_from_spec(spec)
sys.modules["promptgs_dataset"] = module
spec.loader.exec_module(module)
from promptgs_dataset.generate import main
argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
code = main(argv)
sys.stdout.flush()
if code:
    sys.exit(code)
"""

Progress = Callable[[str, int, int], None]


class BlenderFailed(DatasetError):
    """Blender stopped with an error other than a parameter problem; its log is kept."""


def bpy_available() -> bool:
    """Whether this Python can import ``bpy`` (checked without importing it)."""
    return importlib.util.find_spec("bpy") is not None


def command(args: list[str], blender: str | None) -> list[str]:
    """The command line that runs ``generate.main(args)`` in Blender."""
    code = _BOOTSTRAP.format(root=str(DATASET_PACKAGE))
    if blender:
        return [blender, "-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", code, "--", *args]
    return [sys.executable, "-c", code, *args]


def run_generator(
    args: list[str], blender: str | None, log_path: Path, progress: Progress | None = None, need_bpy: bool = True
) -> None:
    """Run the generator; progress lines go to ``progress``, everything else to ``log_path``.

    Raises :class:`DatasetError` with the generator's own one-line message for a parameter
    problem, or a pointer to the log when Blender fails.
    """
    if blender is None and need_bpy and not bpy_available():
        raise DatasetError(
            "the bpy module is not installed in this Python (pip install bpy==5.0.1) and no --blender binary was given"
        )
    if blender is not None and not Path(blender).exists() and "/" in blender:
        raise DatasetError(f"{blender}: Blender binary not found")
    error: str | None = None
    log_path.parent.mkdir(parents=True, exist_ok=True)
    try:
        proc = subprocess.Popen(
            command(args, blender), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
        )
    except OSError as exc:
        raise DatasetError(f"cannot start Blender ({blender or sys.executable}): {exc}") from exc
    try:
        with open(log_path, "w") as log:
            assert proc.stdout is not None
            for line in proc.stdout:
                if line.startswith("PROMPTGS_PROGRESS "):
                    if progress is not None:
                        msg = json.loads(line.split(" ", 1)[1])
                        progress(msg["stage"], int(msg["done"]), int(msg["total"]))
                elif line.startswith("PROMPTGS_ERROR "):
                    error = line.split(" ", 1)[1].strip()
                else:
                    log.write(line)
        code = proc.wait()
    finally:
        if proc.poll() is None:  # interrupted (Ctrl-C) or failed while reading: stop Blender too
            proc.kill()
            proc.wait()
    if error is not None:
        raise DatasetError(error)
    if code != 0:
        raise BlenderFailed(f"Blender exited with status {code}; see {log_path}")
