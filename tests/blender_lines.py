"""The Blender lines the add-on supports, and a Python with each line's ``bpy`` module.

Every line runs the same checks (tests/test_blender_addon.py, tests/test_blender_train.py)
in its own interpreter. The ``bpy`` wheel of a line needs one Python minor version (4.2 to
5.0: 3.11; 5.1 to 5.3: 3.13). For each line a virtual environment with that wheel is made
once in a cache folder outside the repository (``$PROMPTGS_BLENDER_LINES_CACHE``, default
``~/.cache/promptgs/blender-lines``) and reused; the interpreter that runs the tests is
used directly when it already has the line's ``bpy``.

The versions are the newest patch release of each line on PyPI when they were last
updated (November 2026).
"""

from __future__ import annotations

import fcntl
import glob
import importlib.metadata
import os
import shutil
import subprocess
import sys
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class BlenderLine:
    name: str  # as Blender names the release, e.g. "5.2 LTS"
    bpy: str  # the bpy wheel's version
    python: str  # the Python minor version that wheel is built for

    @property
    def id(self) -> str:
        return "blender-" + self.bpy.rsplit(".", 1)[0]

    def __str__(self) -> str:
        return self.id


LINES = (
    BlenderLine("4.2 LTS", "4.2.23", "3.11"),
    BlenderLine("4.5 LTS", "4.5.15", "3.11"),
    BlenderLine("5.0", "5.0.1", "3.11"),
    BlenderLine("5.1", "5.1.2", "3.13"),
    BlenderLine("5.2 LTS", "5.2.3", "3.13"),
    BlenderLine("5.3", "5.3.0", "3.13"),
)


class LineUnavailable(Exception):
    """This machine cannot run a line (no interpreter of the needed version)."""


def cache_dir() -> Path:
    folder = os.environ.get("PROMPTGS_BLENDER_LINES_CACHE")
    return Path(folder) if folder else Path.home() / ".cache" / "promptgs" / "blender-lines"


def _version_of(python: str) -> str | None:
    try:
        done = subprocess.run([python, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"],
                              capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def interpreter_candidates(version: str) -> list[str]:
    """Where a ``pythonX.Y`` may be: ``$PROMPTGS_PYTHON_X_Y``, PATH, pyenv, the usual prefixes."""
    name = f"python{version}"
    found = [os.environ.get("PROMPTGS_PYTHON_" + version.replace(".", "_"), ""), shutil.which(name) or ""]
    pyenv_root = os.environ.get("PYENV_ROOT") or str(Path.home() / ".pyenv")
    found += sorted(glob.glob(os.path.join(pyenv_root, "versions", f"{version}.*", "bin", name)), reverse=True)
    found += [f"/usr/bin/{name}", f"/usr/local/bin/{name}", f"/opt/homebrew/bin/{name}"]
    return [path for path in dict.fromkeys(found) if path]


def find_interpreter(version: str) -> str | None:
    """A working interpreter of ``version`` ("3.13"), checked by running it: a pyenv shim
    or a stale link of that name that runs another version (or nothing) does not count."""
    for path in interpreter_candidates(version):
        if os.access(path, os.X_OK) and _version_of(path) == version:
            return path
    return None


def _has_bpy(python_version: str, bpy_version: str) -> bool:
    """Whether the interpreter running the tests is of the line's Python and has its bpy."""
    if "%d.%d" % sys.version_info[:2] != python_version:
        return False
    try:
        return importlib.metadata.version("bpy") == bpy_version
    except importlib.metadata.PackageNotFoundError:
        return False


def own_line() -> BlenderLine | None:
    """The line whose bpy the interpreter running the tests has, if any."""
    return next((line for line in LINES if _has_bpy(line.python, line.bpy)), None)


def line_python(line: BlenderLine, cache: Path | None = None) -> str:
    """A Python with the line's bpy: this interpreter, or the line's cached virtual environment,
    made now if missing (under a lock, so concurrent test runs share one). Raises
    :class:`LineUnavailable` when no interpreter of the line's Python version exists."""
    if _has_bpy(line.python, line.bpy):
        return sys.executable
    cache = cache or cache_dir()
    venv = cache / f"bpy-{line.bpy}-py{line.python}"
    python = venv / "bin" / "python"
    ready = venv / "promptgs-ready"
    if ready.is_file():
        return str(python)
    base = find_interpreter(line.python)
    if base is None:
        looked = ", ".join(interpreter_candidates(line.python))
        raise LineUnavailable(f"Blender {line.name} (bpy {line.bpy}) needs Python {line.python}: "
                              f"no working python{line.python} found (looked at {looked})")
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / f"{venv.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if ready.is_file():
            return str(python)
        shutil.rmtree(venv, ignore_errors=True)
        for argv in ([base, "-m", "venv", str(venv)],
                     [str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                      f"bpy=={line.bpy}"]):
            done = subprocess.run(argv, capture_output=True, text=True, stdin=subprocess.DEVNULL)
            if done.returncode != 0:
                tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
                raise RuntimeError(f"Blender {line.name}: {' '.join(argv[:4])} failed: {tail}")
        ready.write_text(line.bpy + "\n")
    return str(python)


class LineEnvironments:
    """Makes every line's environment in the background, so downloads overlap each other
    and the checks of the lines that are ready."""

    def __init__(self, lines: tuple[BlenderLine, ...] = LINES, cache: Path | None = None):
        self._pool = ThreadPoolExecutor(max_workers=len(lines), thread_name_prefix="blender-line")
        self._futures: dict[BlenderLine, Future] = {line: self._pool.submit(line_python, line, cache)
                                                    for line in lines}

    def python(self, line: BlenderLine) -> str:
        """The line's interpreter (waits for it); raises what making it raised."""
        return self._futures[line].result()

    def close(self) -> None:
        self._pool.shutdown(wait=True)
