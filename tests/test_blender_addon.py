"""The installed extension inside every supported Blender line, with fake/recorded trainers.

For each line of tests/blender_lines.py one bpy subprocess (that line's bpy, in its own
Python) installs the extension zip built from this checkout and runs
tests/blender_scripts/addon_checks.py; each test here reads one of its checks. HOME points
at a temporary folder, so a fresh user profile is used.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from blender_lines import LINES, BlenderLine, LineUnavailable
from scenes import FERN, TUMBLER, SceneFacts, real_scene

pytest.importorskip("bpy", reason="needs the bpy module")
pytestmark = pytest.mark.blender

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = REPO / "tests" / "blender_scripts"


def projections(model_dir: Path, n_cameras: int = 6, n_points: int = 5) -> list[dict]:
    """Pixels of a few points in a few images (spread over the sorted names), projected by pycolmap."""
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction(str(model_dir))
    out = []
    images = sorted(rec.images.values(), key=lambda im: im.name)
    for index in np.linspace(0, len(images) - 1, n_cameras).astype(int):
        image = images[index]
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


def scene_config(facts: SceneFacts) -> dict:
    """What the Blender checks know of a scene (tests/scenes.py), as JSON."""
    config = {"name": facts.name, "path": str(facts.path), "n_images": facts.n_images, "n_points": facts.n_points,
              "size": list(facts.size), "small": facts.small, "distortion_words": list(facts.distortion_words),
              "background": facts.names[3]}
    if not facts.distortion_words:
        config["projections"] = projections(facts.model_dir)
    return config


def real_scenes() -> list[tuple[str, SceneFacts]]:
    """The real scenes beside the repository that the import checks also run on: (kind, facts)."""
    return [(kind, facts) for kind, facts in (("scene", TUMBLER), ("distorted", FERN)) if real_scene(facts)]


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


def prepare(tmp: Path, made: dict[str, SceneFacts], zip_path: Path) -> Path:
    """Write the fake trainer wrapper and the config; returns the config path. The checks
    run on the made scenes; the real ones add their import checks (``NAME@SCENE``)."""
    fake = tmp / "fake_python"
    fake.write_text(f"#!/bin/sh\nexec {sys.executable} {SCRIPTS / 'fake_trainer.py'} \"$@\"\n")
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    slow = tmp / "slow_python"  # this interpreter (it has the engine), after a 2 s pause
    slow.write_text(f"#!/bin/sh\nsleep 2\nexec {sys.executable} \"$@\"\n")
    slow.chmod(slow.stat().st_mode | stat.S_IEXEC)
    config = {"zip": str(zip_path), "tmp": str(tmp), "scene": scene_config(made["pinhole"]),
              "distorted": scene_config(made["distorted"]), "fake_python": str(fake), "slow_python": str(slow),
              "repo": str(REPO), "home": str(tmp / "home"),
              "real": [dict(scene_config(facts), kind=kind) for kind, facts in real_scenes()],
              "pinhole": str(tmp / "pinhole"), "pinhole_projections": pinhole_dataset(tmp / "pinhole")}
    (tmp / "config.json").write_text(json.dumps(config))
    (tmp / "home").mkdir()
    return tmp / "config.json"


@pytest.fixture(scope="session")
def line_results(tmp_path_factory, made_scenes, blender_envs, extension_zip):
    """``line_results(line)``: (folder, check outcomes) of the add-on checks run in that
    Blender line's bpy, once per line (a fresh user profile each)."""
    done: dict = {}

    def results(line: BlenderLine) -> tuple[Path, dict]:
        if line not in done:
            try:
                python = blender_envs.python(line)
            except LineUnavailable as exc:
                done[line] = exc
                return results(line)
            tmp = tmp_path_factory.mktemp(f"addon-{line.id}")
            config = prepare(tmp, made_scenes, extension_zip)
            env = dict(os.environ, HOME=str(tmp / "home"))
            start = time.time()
            proc = subprocess.run([python, str(SCRIPTS / "addon_checks.py"), str(config), str(tmp / "results.json")],
                                  env=env, capture_output=True, text=True, timeout=600)
            (tmp / "seconds").write_text(f"{time.time() - start:.1f}\n")
            if (tmp / "results.json").is_file():
                done[line] = (tmp, json.loads((tmp / "results.json").read_text()))
            else:
                done[line] = f"Blender {line.name}: the script failed before any check:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
        outcome = done[line]
        if isinstance(outcome, LineUnavailable):
            pytest.skip(str(outcome))
        if isinstance(outcome, str):
            pytest.fail(outcome)
        return outcome

    return results


SCENE_CHECKS = ["import_scene", "projection_matches_colmap", "root_puts_capture_upright"]
DISTORTED_CHECKS = ["import_distorted_reports_distortion"]
CHECKS = ["installed_and_enabled", *SCENE_CHECKS, "non_square_pixels_project_exactly",
          *DISTORTED_CHECKS, "prompt_cube_box_in_job_file", "prompt_around_selected_points",
          "train_with_recorded_events_updates_objects", "cancel_keeps_last_snapshot",
          "crashed_trainer_shows_error_lines", "wrong_trainer_path_is_a_clear_error",
          "dataset_without_images_is_a_clear_error", "dataset_generation_runs_in_background",
          "reconstruct_from_photos_imports_the_result", "reconstruct_errors_and_cancel", "load_result_reads_3dgs_ply",
          "blender_import_agrees_with_ours", "splats_drawn_with_scale_rotation_opacity", "million_points_update",
          "display_settings_apply", "export_round_trip_bit_for_bit", "export_after_deleting_in_box", "propose_accept_and_reject",
          "proposed_cubes_drawn_in_their_colour", "training_proposals_become_proposed_cubes",
          "panels_draw_in_every_state", "runs_need_no_modal_operator", "second_run_keeps_the_first_and_runs_switch",
          "undo_after_a_snapshot_leaves_a_consistent_scene", "the_panel_tells_what_went_wrong",
          "buttons_grey_out_when_they_cannot_run", "a_picked_photo_means_its_folder",
          "find_and_test_run_in_the_background", "set_up_trainer_says_what_it_needs",
          "cancel_ends_every_process_of_the_trainer", "overlay_handler_follows_register",
          "proposed_cubes_draw_orange_pixels", "loading_a_file_detaches_the_run",
          "reopened_file_shows_result_or_resume", "never_imports_torch_or_engine"]
REAL_CHECKS = [f"{name}@{facts.name}" for kind, facts in real_scenes()
               for name in (SCENE_CHECKS if kind == "scene" else DISTORTED_CHECKS)]


@pytest.mark.parametrize("line", LINES, ids=str)
@pytest.mark.parametrize("name", CHECKS + REAL_CHECKS)
def test_blender(line_results, line, name):
    _, results = line_results(line)
    assert name in results, f"check {name} did not run in Blender {line.name}"
    outcome = results[name]
    assert outcome["ok"], f"Blender {line.name}: {outcome['error']}\n{outcome.get('traceback', '')}"


@pytest.mark.parametrize("line", [line for line in LINES if line.bpy >= "5.1"], ids=str)
def test_point_clouds_carry_what_the_mesh_carries(line_results, line):
    """The same snapshot shown as a point cloud (5.1+) and as a points-only mesh (5.0)."""
    mesh_line = next(candidate for candidate in LINES if candidate.bpy.startswith("5.0"))
    (cloud_dir, cloud), (mesh_dir, mesh) = line_results(line), line_results(mesh_line)
    for results in (cloud, mesh):
        assert results["train_with_recorded_events_updates_objects"]["ok"]
    assert cloud["train_with_recorded_events_updates_objects"]["object_type"] == "POINTCLOUD"
    assert mesh["train_with_recorded_events_updates_objects"]["object_type"] == "MESH"
    with np.load(cloud_dir / "gaussians_object.npz") as a, np.load(mesh_dir / "gaussians_object.npz") as b:
        assert str(a["snapshot"]) == str(b["snapshot"])
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


@pytest.mark.parametrize("line", [line for line in LINES if line.bpy >= "5.3"], ids=str)
def test_blenders_own_import_is_what_the_addon_shows(line_results, line):
    """5.3+: the check compared Blender's import of a 3DGS PLY with the Gaussians object."""
    _, results = line_results(line)
    outcome = results["blender_import_agrees_with_ours"]
    assert outcome["ok"] and outcome["native"], outcome
    assert "radiance:base" in outcome["compared"] and outcome["snapshot_compared"] > 100


@pytest.mark.parametrize("line", LINES, ids=str)
def test_exported_ply_is_the_loaded_one(line_results, line):
    """Another trainer's PLY loaded and exported unchanged: every property bit for bit (read by plyfile)."""
    plyfile = pytest.importorskip("plyfile")
    _, results = line_results(line)
    outcome = results["export_round_trip_bit_for_bit"]
    assert outcome["ok"], outcome.get("error")
    source = plyfile.PlyData.read(outcome["source"])["vertex"].data
    exported = plyfile.PlyData.read(outcome["exported"])["vertex"].data
    assert exported.dtype.names == source.dtype.names and len(exported) == len(source)
    for name in source.dtype.names:
        np.testing.assert_array_equal(exported[name].view(np.uint32), source[name].view(np.uint32), err_msg=name)


@pytest.mark.parametrize("line", [line for line in LINES if line.bpy >= "5.2"], ids=str)
def test_overlay_draws_where_blender_can_draw_without_a_window(line_results, line):
    """5.2+ can start its GPU module in background (gpu.init): the overlay was drawn there."""
    _, results = line_results(line)
    outcome = results["proposed_cubes_draw_orange_pixels"]
    assert outcome["ok"], outcome.get("error")
    if not outcome["drawn"] and outcome["why"].startswith("gpu.init"):
        pytest.skip(outcome["why"])  # no offscreen GPU context on this machine
    assert outcome["drawn"] and outcome["orange_pixels"] > 100, outcome


@pytest.mark.parametrize("line", LINES, ids=str)
def test_installs_from_the_repository_index(line, tmp_path, blender_envs, extension_zip):
    """The folder tools/build_extension.py makes is an extension repository: a fresh
    profile of each line adds its index.json as a remote repository (file:// URL) and
    installs and enables the extension from it."""
    import tomllib

    sys.path.insert(0, str(REPO / "tools"))
    import build_extension

    try:
        python = blender_envs.python(line)
    except LineUnavailable as exc:
        pytest.skip(str(exc))
    repo = tmp_path / "repo"
    repo.mkdir()
    shutil.copy2(extension_zip, repo / extension_zip.name)
    index = build_extension.write_index(repo)
    listed = json.loads(index.read_text())["data"]
    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    assert [(p["id"], p["version"], p["archive_url"]) for p in listed] == \
        [("promptgs", manifest["version"], f"./{extension_zip.name}")]
    assert manifest["website"].startswith("https://") and listed[0]["website"] == manifest["website"]
    config = {"index_url": index.resolve().as_uri(), "version": manifest["version"]}
    (tmp_path / "config.json").write_text(json.dumps(config))
    (tmp_path / "home").mkdir()
    done = subprocess.run([python, str(SCRIPTS / "repo_checks.py"), str(tmp_path / "config.json"),
                           str(tmp_path / "results.json")], env=dict(os.environ, HOME=str(tmp_path / "home")),
                          capture_output=True, text=True, timeout=600)
    if not (tmp_path / "results.json").is_file():
        pytest.fail(f"Blender {line.name}: the script failed before any check:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    outcome = json.loads((tmp_path / "results.json").read_text())["installed_from_the_repository_index"]
    assert outcome["ok"], f"Blender {line.name}: {outcome['error']}\n{outcome.get('traceback', '')}"
    assert outcome["repo_directory"].startswith(str(tmp_path / "home")), outcome  # the fresh profile


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


def test_same_checks_under_blender_binary(tmp_path, made_scenes, extension_zip):
    binary = _blender_binary()
    if binary is None:
        pytest.skip("no Blender ≥ 4.2 binary (set $BLENDER)")
    config = prepare(tmp_path, made_scenes, extension_zip)
    env = dict(os.environ, HOME=str(tmp_path / "home"))
    done = subprocess.run([binary, "-b", "--factory-startup", "--python-exit-code", "1", "--python",
                           str(SCRIPTS / "addon_checks.py"), "--", str(config), str(tmp_path / "results.json")],
                          env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
