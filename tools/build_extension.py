"""Build and validate the PromptGS Blender extension zip, and the extension repository
index beside it.

Stages ``promptgs_blender/`` (without ``dataset/``, which the engine's CLI runs) together
with ``blender_manifest.toml`` and runs Blender's own extension builder, which ships in
the bpy wheel (``bpy/<version>/scripts/addons_core/bl_pkg/cli/blender_ext.py``) and in
every Blender: ``build`` and ``validate`` make the zip, ``server-generate`` writes
``index.json`` (and ``index.html``) for every zip in the output folder. That folder is then
an extension repository: Blender's *Get Extensions > Repositories > + > Add Remote
Repository* takes its ``index.json`` by URL (a static web server, or ``file://`` for a
local folder) and installs and updates from it. Usage::

    python tools/build_extension.py [--out dist] [--blender-ext PATH/blender_ext.py]

Prints the path of the zip and of the index. Exit code 1 when a step fails.
"""

from __future__ import annotations

import argparse
import importlib.util
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def find_blender_ext() -> Path:
    """blender_ext.py from the installed bpy module (found without importing bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("bpy is not installed: pass --blender-ext PATH to Blender's blender_ext.py")
    base = Path(next(iter(spec.submodule_search_locations)))
    found = sorted(base.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        raise SystemExit(f"{base}: no */scripts/addons_core/bl_pkg/cli/blender_ext.py")
    return found[-1]


def stage(dest: Path) -> None:
    shutil.copytree(REPO / "promptgs_blender", dest,
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "dataset"))
    shutil.copy2(REPO / "blender_manifest.toml", dest / "blender_manifest.toml")


def _run(blender_ext: Path, *command: str) -> None:
    done = subprocess.run([sys.executable, str(blender_ext), *command], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"blender_ext {command[0]} failed:\n{done.stdout}{done.stderr}")


def write_index(repo_dir: Path, blender_ext: Path | None = None) -> Path:
    """Write the repository index (``index.json``, ``index.html``) of the zips in ``repo_dir``."""
    _run(blender_ext or find_blender_ext(), "server-generate", "--repo-dir", str(repo_dir), "--html")
    return repo_dir / "index.json"


def build(out_dir: Path, blender_ext: Path | None = None) -> Path:
    """Build the zip into ``out_dir`` and validate it; returns its path."""
    blender_ext = blender_ext or find_blender_ext()
    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    out_dir.mkdir(parents=True, exist_ok=True)
    zip_path = out_dir / f"{manifest['id']}-{manifest['version']}.zip"
    with tempfile.TemporaryDirectory() as tmp:
        source = Path(tmp) / manifest["id"]
        stage(source)
        _run(blender_ext, "build", "--source-dir", str(source), "--output-filepath", str(zip_path))
        _run(blender_ext, "validate", str(zip_path))
    return zip_path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "dist", help="output folder (default: dist/)")
    parser.add_argument("--blender-ext", type=Path, default=None, help="path of Blender's blender_ext.py")
    args = parser.parse_args(argv)
    print(build(args.out, args.blender_ext))
    print(write_index(args.out, args.blender_ext))


if __name__ == "__main__":
    main()
