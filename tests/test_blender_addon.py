"""The installed extension inside Blender (bpy module), with fake/recorded trainers.

One bpy subprocess runs tests/blender_scripts/addon_checks.py; each test here reads one
of its checks. HOME points at a temporary folder, so a fresh user profile is used.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("bpy", reason="needs the bpy module")  # find_spec only; no import here
pytestmark = pytest.mark.blender

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = REPO / "tests" / "blender_scripts"
sys.path.insert(0, str(REPO / "tools"))


def projections(tumbler: Path, n_cameras: int = 6, n_points: int = 5) -> list[dict]:
    """Pixels of a few points in a few images, projected by pycolmap."""
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction(str(tumbler / "sparse" / "0"))
    out = []
    images = sorted(rec.images.values(), key=lambda im: im.name)
    for image in images[:: max(1, len(images) // n_cameras)][:n_cameras]:
        count = 0
        for point in rec.points3D.values():
            uv = image.project_point(point.xyz)
            if uv is None:
                continue
            uv = np.asarray(uv)
            cam = rec.cameras[image.camera_id]
            if 0 <= uv[0] < cam.width and 0 <= uv[1] < cam.height:
                out.append({"image": image.name, "point": point.xyz.tolist(), "uv": uv.tolist()})
                count += 1
            if count == n_points:
                break
    return out


def pinhole_dataset(folder: Path) -> list[dict]:
    """A small text model with PINHOLE cameras whose fy ≠ fx; returns pycolmap's projections."""
    pycolmap = pytest.importorskip("pycolmap")
    from promptgs_blender import coords

    sparse = folder / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("1 PINHOLE 640 480 500 520 330.5 250.25\n2 PINHOLE 640 480 520 480 300 260\n")
    rng = np.random.default_rng(7)
    lines = []
    for i in range(4):
        q = coords.rotmat_to_quat(coords.quat_to_rotmat(rng.normal(size=4)))
        lines += [f"{i + 1} {' '.join(map(str, q))} 0.1 -0.2 5.0 {i % 2 + 1} pin_{i}.png", ""]
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    points = rng.normal(scale=0.7, size=(40, 3))
    (sparse / "points3D.txt").write_text("".join(f"{j + 1} {p[0]} {p[1]} {p[2]} 200 100 50 0.5\n"
                                                 for j, p in enumerate(points)))
    rec = pycolmap.Reconstruction(str(sparse))
    out = []
    for image in rec.images.values():
        for point in points[:8]:
            out.append({"image": image.name, "point": point.tolist(), "uv": np.asarray(image.project_point(point)).tolist()})
    return out


def prepare(tmp: Path, shared_data: Path) -> Path:
    """Build the zip, write the fake trainer wrapper and the config; returns the config path."""
    import build_extension

    zip_path = build_extension.build(tmp / "dist")
    fake = tmp / "fake_python"
    fake.write_text(f"#!/bin/sh\nexec {sys.executable} {SCRIPTS / 'fake_trainer.py'} \"$@\"\n")
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    config = {"zip": str(zip_path), "tmp": str(tmp), "tumbler": str(shared_data / "tumbler"),
              "fern": str(shared_data / "fern"), "fake_python": str(fake),
              "projections": projections(shared_data / "tumbler"),
              "pinhole": str(tmp / "pinhole"), "pinhole_projections": pinhole_dataset(tmp / "pinhole")}
    (tmp / "config.json").write_text(json.dumps(config))
    (tmp / "home").mkdir()
    return tmp / "config.json"


@pytest.fixture(scope="module")
def results(tmp_path_factory, shared_data):
    tmp = tmp_path_factory.mktemp("blender_addon")
    config = prepare(tmp, shared_data)
    env = dict(os.environ, HOME=str(tmp / "home"))
    done = subprocess.run([sys.executable, str(SCRIPTS / "addon_checks.py"), str(config),
                           str(tmp / "results.json")], env=env, capture_output=True, text=True, timeout=600)
    if not (tmp / "results.json").is_file():
        pytest.fail(f"the Blender script failed before any check:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return json.loads((tmp / "results.json").read_text())


CHECKS = ["installed_and_enabled", "import_tumbler", "projection_matches_colmap", "root_puts_capture_upright", "non_square_pixels_project_exactly",
          "import_fern_reports_distortion", "prompt_cube_box_in_job_file", "prompt_around_selected_points",
          "train_with_recorded_events_updates_objects", "cancel_keeps_last_snapshot",
          "crashed_trainer_shows_error_lines", "wrong_trainer_path_is_a_clear_error",
          "dataset_without_images_is_a_clear_error", "dataset_generation_runs_in_background", "load_result_reads_3dgs_ply", "million_points_update", "display_settings_apply", "panels_draw_in_every_state", "loading_a_file_stops_the_trainer",
          "never_imports_torch_or_engine"]


@pytest.mark.parametrize("name", CHECKS)
def test_blender(results, name):
    assert name in results, f"check {name} did not run"
    outcome = results[name]
    assert outcome["ok"], f"{outcome['error']}\n{outcome.get('traceback', '')}"


def _blender_binary() -> str | None:
    """A ``blender`` (≥ 4.2, extensions) on PATH or in $BLENDER, else None."""
    binary = os.environ.get("BLENDER") or shutil.which("blender")
    if not binary:
        return None
    try:
        out = subprocess.run([binary, "--version"], capture_output=True, text=True, timeout=60).stdout
        major, minor = (int(x) for x in out.split()[1].split(".")[:2])
    except (OSError, ValueError, IndexError, subprocess.TimeoutExpired):
        return None
    return binary if (major, minor) >= (4, 2) else None


def test_same_checks_under_blender_binary(tmp_path, shared_data):
    binary = _blender_binary()
    if binary is None:
        pytest.skip("no Blender ≥ 4.2 binary (set $BLENDER)")
    config = prepare(tmp_path, shared_data)
    env = dict(os.environ, HOME=str(tmp_path / "home"))
    done = subprocess.run([binary, "-b", "--factory-startup", "--python-exit-code", "1", "--python",
                           str(SCRIPTS / "addon_checks.py"), "--", str(config), str(tmp_path / "results.json")],
                          env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
