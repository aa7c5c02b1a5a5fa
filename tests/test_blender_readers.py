"""The add-on's bpy-free parts: COLMAP reader (against pycolmap), coordinates, PLY
reader (against plyfile), the trainer process reader. Runs in the test process."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from promptgs_blender import colmap, coords, plyio, trainer

REPO = Path(__file__).resolve().parents[1]
FAKE_TRAINER = REPO / "tests" / "blender_scripts" / "fake_trainer.py"


def _pycolmap_quat_wxyz(image) -> np.ndarray:
    x, y, z, w = np.asarray(image.cam_from_world().rotation.quat)
    return np.array([w, x, y, z])


def _same_rotation(q1, q2) -> bool:
    return np.allclose(coords.quat_to_rotmat(q1), coords.quat_to_rotmat(q2), atol=1e-9)


def _compare_with_pycolmap(model: colmap.Model, path: Path) -> None:
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction(str(path))
    assert set(model.cameras) == set(rec.cameras)
    for cam_id, cam in rec.cameras.items():
        ours = model.cameras[cam_id]
        assert ours.model == cam.model.name
        assert (ours.width, ours.height) == (cam.width, cam.height)
        np.testing.assert_allclose(ours.params, cam.params, rtol=0, atol=1e-12)
    assert set(model.images) == set(rec.images)
    for image_id, image in rec.images.items():
        ours = model.images[image_id]
        assert ours.name == image.name and ours.camera_id == image.camera_id
        assert _same_rotation(ours.qvec, _pycolmap_quat_wxyz(image))
        np.testing.assert_allclose(ours.tvec, image.cam_from_world().translation, atol=1e-9)
        matrix = coords.colmap_camera_to_blender(ours.qvec, ours.tvec)
        np.testing.assert_allclose(matrix[:3, 3], image.projection_center(), atol=1e-9)
    ids = sorted(rec.points3D)
    assert sorted(model.point_ids.tolist()) == ids
    order = np.argsort(model.point_ids)
    np.testing.assert_allclose(model.points[order], [rec.points3D[i].xyz for i in ids], atol=1e-12)
    np.testing.assert_array_equal(model.colors[order], [rec.points3D[i].color for i in ids])


def test_binary_model_matches_pycolmap(pinhole_scene):
    path = colmap.find_model_dir(pinhole_scene.path)
    assert sorted(path.glob("*.bin")) and not sorted(path.glob("*.txt"))
    model = colmap.read_model(path)
    assert len(model.images) == pinhole_scene.n_images and len(model.points) == pinhole_scene.n_points
    assert {i: c.model for i, c in model.cameras.items()} == pinhole_scene.models
    _compare_with_pycolmap(model, path)


def test_text_model_matches_pycolmap(distorted_scene):
    path = colmap.find_model_dir(distorted_scene.path)
    assert sorted(path.glob("*.txt")) and not sorted(path.glob("*.bin"))
    model = colmap.read_model(path)
    assert len(model.images) == distorted_scene.n_images and len(model.points) == distorted_scene.n_points
    assert {i: c.model for i, c in model.cameras.items()} == distorted_scene.models
    _compare_with_pycolmap(model, path)


def test_text_and_binary_forms_agree(pinhole_scene, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction(str(pinhole_scene.model_dir))
    rec.write_text(str(tmp_path))
    text, binary = colmap.read_model(tmp_path), colmap.read_model(pinhole_scene.model_dir)
    assert [im.name for im in text.sorted_images()] == [im.name for im in binary.sorted_images()]
    np.testing.assert_allclose(text.points, binary.points, atol=1e-9)
    _compare_with_pycolmap(text, tmp_path)


def test_distortion_is_reported(distorted_scene, pinhole_scene):
    model = colmap.read_model(colmap.find_model_dir(distorted_scene.path))
    note = "; ".join(c.distortion_note() for c in model.cameras.values())
    for word in distorted_scene.distortion_words:
        assert word in note, (word, note)
    pinhole = colmap.read_model(colmap.find_model_dir(pinhole_scene.path))
    assert all(c.distortion_note() == "" for c in pinhole.cameras.values())


def test_bad_models_name_the_file(tmp_path):
    with pytest.raises(colmap.ColmapError, match=str(tmp_path)):
        colmap.find_model_dir(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 100 100 50 50\n")
    (tmp_path / "images.txt").write_text("")
    with pytest.raises(colmap.ColmapError, match="cameras.txt.*expected 4"):
        colmap.read_model(tmp_path)
    (tmp_path / "cameras.txt").unlink()
    (tmp_path / "cameras.bin").write_bytes(b"\x05\x00")
    (tmp_path / "images.bin").write_bytes(b"\0" * 8)
    with pytest.raises(colmap.ColmapError, match="cameras.bin: not a valid COLMAP file"):
        colmap.read_model(tmp_path)


def test_projection_through_blender_camera_settings(pinhole_scene):
    """Blender's view frame from the camera settings reproduces COLMAP's pixel (in the made
    scene for both of its cameras, one with non-square pixels)."""
    model = colmap.read_model(colmap.find_model_dir(pinhole_scene.path))
    images = model.sorted_images()[:5]
    assert len({image.camera_id for image in images}) >= min(2, len(model.cameras))
    for image in images:
        cam = model.cameras[image.camera_id]
        fx, fy, cx, cy = cam.pinhole()
        s = coords.blender_camera_settings(cam.width, cam.height, fx, fy, cx, cy)
        cam_matrix = coords.colmap_camera_to_blender(image.qvec, image.tvec)
        for point in model.points[:50]:
            local = np.linalg.inv(cam_matrix) @ np.append(point, 1.0)
            uv = _blender_pixel(local, s, cam.width, cam.height)
            expected = coords.project_colmap(point, image.qvec, image.tvec, fx, fy, cx, cy)
            np.testing.assert_allclose(uv, expected, atol=1e-6)


def _blender_pixel(local, s: dict, width: int, height: int) -> np.ndarray:
    """Pixel of a camera-local point the way Blender's view plane maps it (horizontal fit):
    view-plane units are image widths; rows are stretched by ycor = aspect_y / aspect_x."""
    x, y, depth = local[0], local[1], -local[2]
    ycor = s["pixel_aspect"][1] / s["pixel_aspect"][0]
    scale = s["lens"] / s["sensor_width"] * width
    column = x / depth * scale + 0.5 * width - s["shift_x"] * width
    row_up = (y / depth * scale + 0.5 * ycor * height - s["shift_y"] * width) / ycor
    return np.array([column, height - row_up])


@pytest.mark.parametrize("fy", [500.0, 520.0, 470.0])
def test_non_square_pixels(fy):
    s = coords.blender_camera_settings(640, 480, 500.0, fy, 330.5, 250.25)
    assert min(s["pixel_aspect"]) == 1.0
    rng = np.random.default_rng(0)
    q = coords.rotmat_to_quat(coords.quat_to_rotmat(rng.normal(size=4)))
    t = np.array([0.1, -0.2, 4.0])
    cam_matrix = coords.colmap_camera_to_blender(q, t)
    for point in rng.normal(size=(20, 3)):
        local = np.linalg.inv(cam_matrix) @ np.append(point, 1.0)
        expected = coords.project_colmap(point, q, t, 500.0, fy, 330.5, 250.25)
        np.testing.assert_allclose(_blender_pixel(local, s, 640, 480), expected, atol=1e-6)


@pytest.mark.parametrize("fy", [500.0, 520.0, 470.0])
def test_blender_camera_intrinsics_invert_the_settings(fy):
    """A dataset camera made into Blender settings reads back as the same pinhole."""
    s = coords.blender_camera_settings(640, 480, 500.0, fy, 330.5, 250.25)
    back = coords.blender_camera_intrinsics(640, 480, s["lens"], s["sensor_width"], 24.0, s["sensor_fit"],
                                            s["shift_x"], s["shift_y"], s["pixel_aspect"])
    np.testing.assert_allclose(back, (500.0, fy, 330.5, 250.25), rtol=1e-12)


def test_blender_camera_intrinsics_follow_the_sensor_fit():
    # 36 mm sensor width, 50 mm lens: AUTO fits the longer side of the frame with the width
    assert coords.blender_camera_intrinsics(800, 600, 50.0, 36.0, 24.0)[0] == pytest.approx(50 / 36 * 800)
    assert coords.blender_camera_intrinsics(600, 800, 50.0, 36.0, 24.0)[0] == pytest.approx(50 / 36 * 800)
    assert coords.blender_camera_intrinsics(600, 800, 50.0, 36.0, 24.0, "HORIZONTAL")[0] == pytest.approx(50 / 36 * 600)
    assert coords.blender_camera_intrinsics(800, 600, 50.0, 36.0, 24.0, "VERTICAL")[0] == pytest.approx(50 / 24 * 600)
    # a shift moves the principal point by that fraction of the fitted side
    fx, fy, cx, cy = coords.blender_camera_intrinsics(600, 800, 50.0, 36.0, 24.0, "AUTO", 0.1, -0.05)
    assert (cx, cy) == (pytest.approx(300 - 0.1 * 800), pytest.approx(400 - 0.05 * 800))


def test_blender_camera_pose_round_trip():
    rng = np.random.default_rng(4)
    for _ in range(5):
        q = coords.rotmat_to_quat(coords.quat_to_rotmat(rng.normal(size=4)))
        t = rng.normal(size=3)
        matrix = coords.colmap_camera_to_blender(q, t)
        matrix[:3, :3] *= 2.5  # a scaled camera object is the same camera
        world_to_camera = coords.blender_camera_to_colmap(matrix)
        np.testing.assert_allclose(world_to_camera[:3, :3], coords.quat_to_rotmat(q), atol=1e-12)
        np.testing.assert_allclose(world_to_camera[:3, 3], t, atol=1e-12)


def test_dataset_to_blender_puts_up_on_z():
    rng = np.random.default_rng(1)
    for up in [(0, -1, 0), (0, 0, -1), (0, 0, 1), *rng.normal(size=(5, 3))]:
        m = coords.dataset_to_blender(up, center=(1, 2, 3))
        rot = m[:3, :3]
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0)
        np.testing.assert_allclose(rot @ (np.asarray(up) / np.linalg.norm(up)), [0, 0, 1], atol=1e-12)
        np.testing.assert_allclose(m @ [1, 2, 3, 1], [0, 0, 0, 1], atol=1e-12)


def test_estimate_up_of_upright_cameras():
    # cameras whose COLMAP y (down) is world −Z: up must be +Z
    q = coords.rotmat_to_quat(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]))
    np.testing.assert_allclose(coords.estimate_up([q, q]), [0, 0, 1], atol=1e-12)


def test_prompt_box_from_cube_matrix():
    rot = coords.quat_to_rotmat([0.9, 0.1, -0.3, 0.2])
    m = np.eye(4)
    m[:3, :3] = rot @ np.diag([0.5, 1.0, 2.0])
    m[:3, 3] = [1.0, -2.0, 3.0]
    box = coords.prompt_box(m, display_size=1.0)
    np.testing.assert_allclose(box["center"], [1, -2, 3])
    np.testing.assert_allclose(box["size"], [1.0, 2.0, 4.0])  # display size 1 = half edge 1
    assert _same_rotation(box["rotation_wxyz"], coords.rotmat_to_quat(rot))
    np.testing.assert_allclose(coords.prompt_box(m, display_size=0.25)["size"], [0.25, 0.5, 1.0])
    mirrored = m.copy()
    mirrored[:3, 2] *= -1
    assert coords.prompt_box(mirrored)["size"] == pytest.approx([1.0, 2.0, 4.0])



def test_proposed_box_becomes_a_cube_that_gives_the_box_back():
    box = {"center": [0.5, -1.0, 2.0], "size": [0.1, 0.3, 0.2],
           "rotation_wxyz": coords.rotmat_to_quat(coords.quat_to_rotmat([0.8, -0.2, 0.4, 0.1])).tolist()}
    m = coords.prompt_box_matrix(box)
    back = coords.prompt_box(m)  # what the job file sends for that cube
    np.testing.assert_allclose(back["center"], box["center"], atol=1e-12)
    np.testing.assert_allclose(back["size"], box["size"], atol=1e-12)
    assert _same_rotation(back["rotation_wxyz"], box["rotation_wxyz"])
    # the cube's corners (display size 1: ±1 on each local axis) are the box's corners
    corner = m @ np.array([1.0, -1.0, 1.0, 1.0])
    rot = coords.quat_to_rotmat(box["rotation_wxyz"])
    np.testing.assert_allclose(corner[:3], np.array(box["center"]) + rot @ (np.array([1, -1, 1]) * np.array(box["size"]) / 2))
    with pytest.raises(ValueError, match="three positive lengths"):
        coords.prompt_box_matrix({**box, "size": [0.1, 0.0, 0.2]})

def _write_3dgs_ply(path: Path, n: int, rng) -> dict:
    plyfile = pytest.importorskip("plyfile")
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(45)] + ["opacity", "scale_0", "scale_1", "scale_2",
                                                     "rot_0", "rot_1", "rot_2", "rot_3"])
    values = {name: rng.normal(size=n).astype(np.float32) for name in names}
    table = np.empty(n, [(name, "f4") for name in names])
    for name in names:
        table[name] = values[name]
    plyfile.PlyData([plyfile.PlyElement.describe(table, "vertex")]).write(str(path))
    return values


def test_ply_reader_matches_3dgs_layout(tmp_path):
    rng = np.random.default_rng(0)
    v = _write_3dgs_ply(tmp_path / "point_cloud.ply", 1000, rng)
    g = plyio.read_gaussians(tmp_path / "point_cloud.ply")
    np.testing.assert_allclose(g["means"], np.stack([v["x"], v["y"], v["z"]], 1))
    np.testing.assert_allclose(g["opacity"], 1 / (1 + np.exp(-v["opacity"])), rtol=1e-6)
    np.testing.assert_allclose(g["scale"], np.exp(np.stack([v[f"scale_{i}"] for i in range(3)], 1)), rtol=1e-6)
    rot = np.stack([v[f"rot_{i}"] for i in range(4)], 1)
    np.testing.assert_allclose(g["rotation"], rot / np.linalg.norm(rot, axis=1, keepdims=True), rtol=1e-5)
    dc = np.stack([v[f"f_dc_{i}"] for i in range(3)], 1)
    np.testing.assert_allclose(g["color"], np.clip(0.5 + plyio.SH_C0 * dc, 0, 1), atol=1e-6)


def test_ply_reader_plain_point_cloud_and_errors(tmp_path):
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                                    "property float y\nproperty float z\nproperty uchar red\n"
                                    "property uchar green\nproperty uchar blue\nend_header\n"
                                    "0 0 0 255 0 0\n1 2 3 0 255 0\n")
    g = plyio.read_gaussians(tmp_path / "a.ply")
    np.testing.assert_allclose(g["means"][1], [1, 2, 3])
    np.testing.assert_allclose(g["color"], [[1, 0, 0], [0, 1, 0]])
    (tmp_path / "b.ply").write_bytes(b"not a ply")
    with pytest.raises(plyio.PlyError, match="b.ply: not a PLY"):
        plyio.read_gaussians(tmp_path / "b.ply")
    header = b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    (tmp_path / "c.ply").write_bytes(header + b"\0" * 20)
    with pytest.raises(plyio.PlyError, match="c.ply: truncated"):
        plyio.read_gaussians(tmp_path / "c.ply")


# --- trainer process -------------------------------------------------------------------

def _state():
    return SimpleNamespace(status="STARTING", message="", error_lines="", last_output="", log_path="",
                           last_snapshot="", result_ply="", backend="", snapshot_step=0, step=0,
                           iterations=0, n_gaussians=0, loss=0.0, psnr=0.0, elapsed_s=0.0, eta_s=0.0,
                           progress=0.0, cancel_requested=False)


def _fake_argv(tmp_path: Path, iterations: int = 30) -> list[str]:
    job = tmp_path / "job.json"
    job.write_text(json.dumps({"iterations": iterations, "strategy": "promptgs"}))
    return [sys.executable, str(FAKE_TRAINER), "train", "DATASET", "--out", str(tmp_path), "--events",
            "--job", str(job)]


def _run_to_end(run: trainer.TrainerRun, state, timeout: float = 30.0) -> list[dict]:
    events, deadline = [], time.time() + timeout
    while time.time() < deadline:
        batch = run.drain()
        for event in batch:
            trainer.reduce_event(state, event)
        events += batch
        if run.done:
            return events
        time.sleep(0.02)
    raise AssertionError("the trainer did not finish")


def test_reader_thread_follows_recorded_events(tmp_path, monkeypatch):
    monkeypatch.setenv("FAKE_TRAINER_MODE", "ok")
    run = trainer.TrainerRun(_fake_argv(tmp_path), tmp_path / "stderr.log")
    run.start()
    state = _state()
    events = _run_to_end(run, state)
    kinds = [e["event"] for e in events]
    assert kinds[0] == "output" and kinds[1] == "start" and kinds[-2:] == ["done", "exit"]
    assert kinds.count("progress") == 30 and kinds.count("snapshot") == 3
    assert state.status == "DONE" and state.step == 30 and state.progress == 1.0
    assert state.n_gaussians == 400 and state.psnr == 40.0 and state.snapshot_step == 30
    assert Path(state.last_snapshot).is_file()
    assert state.last_output == "fake trainer: not an event line"
    assert state.message == "Done: PSNR 20.00 dB"
    assert trainer.metrics_summary({"psnr": 24.1, "ssim": 0.8123, "n_gaussians": 1234.0, "train_seconds": 95.2,
                                    "resolution": [1, 2]}) == "PSNR 24.10 dB, SSIM 0.812, 1,234 Gaussians, 95 s"


def test_crashed_trainer_shows_its_last_lines(tmp_path, monkeypatch):
    monkeypatch.setenv("FAKE_TRAINER_MODE", "crash")
    run = trainer.TrainerRun(_fake_argv(tmp_path), tmp_path / "stderr.log")
    run.start()
    state = _state()
    _run_to_end(run, state)
    assert state.status == "ERROR"
    assert state.message == "RuntimeError: the fake trainer crashed"
    assert "Traceback" in state.error_lines


def test_cancel_stops_the_process_and_keeps_snapshots(tmp_path, monkeypatch):
    monkeypatch.setenv("FAKE_TRAINER_MODE", "slow")
    run = trainer.TrainerRun(_fake_argv(tmp_path), tmp_path / "stderr.log")
    run.start()
    state = _state()
    deadline = time.time() + 30
    while not state.last_snapshot and time.time() < deadline:
        for event in run.drain():
            trainer.reduce_event(state, event)
        time.sleep(0.02)
    assert state.last_snapshot
    state.cancel_requested = True
    state.status = "CANCELLING"
    run.cancel(timeout=10)
    _run_to_end(run, state)
    assert state.status == "CANCELLED" and "kept the snapshot" in state.message
    assert (tmp_path / "cancelled").is_file()  # stopped by SIGINT, not killed
    assert Path(state.last_snapshot).is_file() and not run.running


def test_wrong_trainer_path_is_a_clear_error(tmp_path):
    run = trainer.TrainerRun(["/no/such/python", "-m", "promptgs_engine", "train"], tmp_path / "log")
    with pytest.raises(trainer.TrainerError, match="Trainer command not found: /no/such/python"):
        run.start()
    assert "not an executable" in trainer.check_python(str(tmp_path))
    assert "error" in trainer.probe("/no/such/python")


def test_background_job_start_and_end(tmp_path, monkeypatch):
    """start_run: a job's start problem comes as the job's own error class; ``done`` only
    once the exit event was taken."""
    class JobError(Exception):
        pass

    with pytest.raises(JobError, match="Trainer command not found: /no/such/python"):
        trainer.start_run(["/no/such/python", "-m", "promptgs_engine", "propose"], tmp_path / "log", tmp_path, JobError)
    monkeypatch.setenv("FAKE_TRAINER_MODE", "ok")
    run = trainer.start_run(_fake_argv(tmp_path, iterations=3), tmp_path / "stderr.log", tmp_path, JobError)
    assert run.wait(30) and not run.done  # ended, its events not taken yet
    assert run.exit_event()["returncode"] == 0 and run.done


def test_pure_modules_never_import_torch_or_the_engine():
    code = textwrap.dedent(f"""
        import sys
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("torch", "promptgs_engine", "pycolmap", "plyfile"):
                    raise ImportError("blocked: " + name)
        sys.meta_path.insert(0, Block())
        sys.path.insert(0, {str(REPO)!r})
        import promptgs_blender, promptgs_blender.colmap, promptgs_blender.coords
        import promptgs_blender.plyio, promptgs_blender.splats, promptgs_blender.trainer
        assert "bpy" not in sys.modules
        print("ok")
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.stdout.strip() == "ok", done.stderr


# --- the processes of a run ------------------------------------------------------------

def _sleeper(new_session: bool = False, ignore: str = "") -> subprocess.Popen:
    code = f"import signal, time\nfor s in ({ignore}): signal.signal(s, signal.SIG_IGN)\nwhile True: time.sleep(0.05)\n"
    return subprocess.Popen([sys.executable, "-c", code], start_new_session=new_session, stdin=subprocess.DEVNULL)


@pytest.mark.skipif(os.name != "posix", reason="process groups and /proc or ps: POSIX")
def test_descendants_and_alive_follow_the_process_tree(tmp_path):
    parent = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import subprocess, sys, time
        kids = [subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True)
                for _ in range(2)]
        open({str(tmp_path / 'kids')!r}, "w").write(" ".join(str(k.pid) for k in kids))
        time.sleep(60)
    """)])
    try:
        deadline = time.time() + 30
        while not (tmp_path / "kids").is_file() and time.time() < deadline:
            time.sleep(0.05)
        kids = {int(pid) for pid in (tmp_path / "kids").read_text().split()}
        found = dict(trainer.descendants(parent.pid))
        assert kids <= set(found), (kids, found)  # in their own sessions, still below it
        assert all(trainer.alive(pid, start) for pid, start in found.items())
        pid = next(iter(kids))
        if found[pid]:  # /proc: a start time tells a reused pid apart
            assert not trainer.alive(pid, str(int(found[pid]) + 1))
    finally:
        for pid in trainer.descendants(parent.pid):
            os.kill(pid[0], 9)
        parent.kill()
        parent.wait()
    assert not trainer.alive(parent.pid)


def test_a_trainer_run_gets_the_lifeline_and_releases_it_when_it_ends(tmp_path, monkeypatch):
    monkeypatch.setenv("FAKE_TRAINER_MODE", "ok")
    script = tmp_path / "env.py"
    script.write_text("import os, stat\n"
                      "print(os.environ.get('PROMPTGS_LIFELINE'), stat.S_ISFIFO(os.fstat(0).st_mode), flush=True)\n")
    run = trainer.TrainerRun([sys.executable, str(script)], tmp_path / "log")
    run.start()
    assert run.wait(30)
    lines = [e["line"] for e in run.drain() if e["event"] == "output"]
    assert lines == ["stdin True"]  # asked for, and its stdin is a pipe
    assert run.process.stdin.closed  # our end, closed once the run ended


# --- folder state and set-up -----------------------------------------------------------

def test_a_run_folder_says_what_its_run_is(tmp_path):
    run = tmp_path / "run"
    assert trainer.folder_state(run)["status"] == "MISSING"
    (run / "snapshots").mkdir(parents=True)
    (run / "cfg.json").write_text("{}")
    assert trainer.folder_state(run)["status"] == "ERROR"  # before its first checkpoint: no resume
    for step in (500, 1000):
        (run / "snapshots" / f"step_{step:06d}.npz").write_bytes(b"")
    (run / "ckpt.pt").write_bytes(b"")
    state = trainer.folder_state(run)
    assert state["status"] == "INTERRUPTED" and state["snapshot_step"] == 1000
    assert state["last_snapshot"].endswith("step_001000.npz")
    (run / "point_cloud.ply").write_bytes(b"")
    (run / "metrics.json").write_text(json.dumps({"psnr": 24.1, "n_gaussians": 1234}))
    state = trainer.folder_state(run)
    assert state["status"] == "DONE" and state["result_ply"] == str(run / "point_cloud.ply")
    assert state["message"] == "Done: PSNR 24.10 dB, 1,234 Gaussians"


def _setup_events(capsys) -> list[dict]:
    return [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]


def test_set_up_refuses_what_cannot_work_in_one_line(tmp_path, capsys):
    assert trainer.run_setup(tmp_path / "env", "") == 2
    assert _setup_events(capsys)[-1]["message"].startswith("Choose the engine source")
    assert trainer.run_setup(tmp_path / "env", str(tmp_path)) == 2
    assert _setup_events(capsys)[-1]["message"] == f"{tmp_path}: no pyproject.toml (not a PromptGS checkout)"
    (tmp_path / "promptgs-0.1.0-py3-none-any.whl").write_bytes(b"")
    (tmp_path / "other.whl").write_bytes(b"")
    assert trainer.check_source(str(tmp_path / "promptgs-0.1.0-py3-none-any.whl")) == ""
    assert "not a promptgs wheel" in trainer.check_source(str(tmp_path / "other.whl"))
    no_compiler = {"PATH": str(tmp_path / "empty"), "CXX": ""}
    assert trainer.find_compiler(no_compiler) is None
    assert trainer.run_setup(tmp_path / "env", str(REPO), environ=no_compiler) == 2
    message = _setup_events(capsys)[-1]["message"]
    assert message.startswith("No C++ compiler found") and "build-essential" in message, message
    assert not (tmp_path / "env").exists()


def test_set_up_runs_its_stages_and_stops_at_a_failing_one(tmp_path, capsys, monkeypatch):
    """Each stage is announced, its output passed on line by line; a failing stage ends it
    with its last line; a made environment is checked with the probe."""
    stages = [("one", [sys.executable, "-c", "print('first line'); print('second line')"]),
              ("two", [sys.executable, "-c", "import sys; print('it broke'); sys.exit(4)"]),
              ("three", [sys.executable, "-c", "print('never')"])]
    monkeypatch.setattr(trainer, "setup_stages", lambda venv, source, index: stages)
    monkeypatch.setattr(trainer, "find_compiler", lambda environ=None: "/usr/bin/c++")
    assert trainer.run_setup(tmp_path / "env", str(REPO)) == 2
    out = capsys.readouterr().out.splitlines()
    assert [json.loads(x)["stage"] for x in out if '"setup_stage"' in x] == ["one", "two"]
    assert "first line" in out and "second line" in out and "never" not in out
    assert json.loads(out[-1]) | {"time": 0} == {"event": "error", "time": 0,
                                                 "message": "two failed (exit code 4): it broke"}
    monkeypatch.setattr(trainer, "setup_stages", lambda venv, source, index: stages[:1])
    monkeypatch.setattr(trainer, "probe", lambda python: {"version": "0.1.0", "torch": "2.13.0+cpu", "backends": ["cpu"]})
    assert trainer.run_setup(tmp_path / "env", str(REPO)) == 0
    done = _setup_events(capsys)[-1]
    assert done["event"] == "setup_done" and done["python"] == str(trainer.venv_python(tmp_path / "env"))


def test_set_up_stages_install_torch_then_the_engine_without_build_isolation(tmp_path):
    stages = dict(trainer.setup_stages(tmp_path / "env", str(REPO), trainer.CPU_INDEX))
    python = str(trainer.venv_python(tmp_path / "env"))
    assert stages["virtual environment"] == [sys.executable, "-m", "venv", str(tmp_path / "env")]
    assert stages["torch"][:4] == [python, "-m", "pip", "install"] and "torch==2.13.0" in stages["torch"]
    assert stages["torch"][-2:] == ["--extra-index-url", trainer.CPU_INDEX]
    assert "--extra-index-url" not in dict(trainer.setup_stages(tmp_path / "env", str(REPO), ""))["torch"]
    engine = stages["PromptGS engine (compiles the CPU rasterizer)"]
    assert engine[-2:] == ["--no-build-isolation", str(REPO)]
    assert list(stages) == ["virtual environment", "build tools", "torch", "PromptGS engine (compiles the CPU rasterizer)"]
