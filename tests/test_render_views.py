"""``promptgs render`` of any camera (a camera file) and of a snapshot of a running training."""

import json

import numpy as np
import pytest
from PIL import Image

from promptgs_engine.cli import main
from promptgs_engine.data import load_colmap_scene
from promptgs_engine.data.camera_file import camera_file_entry, load_camera_file


@pytest.fixture(scope="module")
def run(toy, tmp_path_factory):
    out = tmp_path_factory.mktemp("render_views") / "run"
    assert main(["train", str(toy), "--out", str(out), "--iterations", "30", "--snapshot-every", "15", "--quiet"]) == 0
    return out


def _png(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), np.int16)


def test_a_camera_file_of_a_dataset_camera_renders_the_same_image(run, toy, tmp_path):
    camera = load_colmap_scene(toy).train_cameras[3]
    (tmp_path / "cam.json").write_text(json.dumps({"cameras": [camera_file_entry(camera)]}))
    assert main(["render", str(run), "--camera", camera.name, "--out", str(tmp_path / "named"), "--quiet"]) == 0
    assert main(["render", str(run), "--camera-file", str(tmp_path / "cam.json"), "--out", str(tmp_path / "file"), "--quiet"]) == 0
    stem = camera.name.rsplit(".", 1)[0]
    named, from_file = _png(tmp_path / "named" / f"{stem}.png"), _png(tmp_path / "file" / f"{stem}.png")
    assert named.std() > 5  # the scene, not an empty frame
    np.testing.assert_array_equal(from_file, named)


def test_a_camera_file_places_the_view_anywhere(run, toy, tmp_path):
    """A camera moved sideways sees the scene shifted the other way; half the size halves the image."""
    scene = load_colmap_scene(toy)
    camera = scene.train_cameras[0]
    entry = camera_file_entry(camera)
    moved = json.loads(json.dumps(entry))
    moved["name"] = "moved"
    # the camera goes +x by what moves the scene's median depth 4 px left in the image
    depth = float((scene.points @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3])[:, 2].median())
    moved["world_to_camera"][0][3] -= 4.0 * depth / float(camera.K[0, 0])
    small = dict(entry, name="small", width=camera.width // 2, height=camera.height // 2,
                 K=(np.array(entry["K"]) * [[0.5], [0.5], [1]]).tolist())
    (tmp_path / "cams.json").write_text(json.dumps({"cameras": [entry, moved, small]}))
    assert main(["render", str(run), "--camera-file", str(tmp_path / "cams.json"), "--out", str(tmp_path), "--quiet"]) == 0
    base = _png(tmp_path / f"{camera.name.rsplit('.', 1)[0]}.png").mean(axis=2)
    shifted = _png(tmp_path / "moved.png").mean(axis=2)
    assert _png(tmp_path / "small.png").shape == (camera.height // 2, camera.width // 2, 3)
    # the shift that best aligns the two images is to the left
    errors = {dx: np.abs(shifted[:, 10:-10] - base[:, 10 + dx:base.shape[1] - 10 + dx]).mean() for dx in range(-8, 9)}
    assert 2 <= min(errors, key=errors.get) <= 6, errors


def test_a_snapshot_renders_before_the_run_ends(run, toy, tmp_path):
    snapshot = sorted((run / "snapshots").glob("step_*.npz"))[-1]
    camera = load_colmap_scene(toy).train_cameras[2]
    assert main(["render", str(run), "--camera", camera.name, "--snapshot", str(snapshot), "--out", str(tmp_path / "s"), "--quiet"]) == 0
    assert main(["render", str(run), "--camera", camera.name, "--out", str(tmp_path / "f"), "--quiet"]) == 0
    stem = camera.name.rsplit(".", 1)[0]
    from_snapshot, final = _png(tmp_path / "s" / f"{stem}.png"), _png(tmp_path / "f" / f"{stem}.png")
    # the last snapshot holds the final Gaussians; it renders with the DC colour only
    assert np.abs(from_snapshot - final).mean() < 8.0
    assert from_snapshot.std() > 5


@pytest.mark.parametrize("content, expected", [
    ("{", "cannot read camera file"),
    ('{"width": 10, "height": 10, "K": [[1, 0, 0], [0, 1, 0]], "world_to_camera": []}', "'K' must be 3x3"),
    ('{"width": 0, "height": 10, "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "world_to_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}', "'width' must be a positive"),
    ('{"width": 10, "height": 10, "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}', "has no 'world_to_camera'"),
    ('{"width": 10, "height": 10, "K": [[NaN, 0, 0], [0, 1, 0], [0, 0, 1]], "world_to_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}', "NaN or inf"),
])
def test_bad_camera_files_are_one_line_errors(tmp_path, content, expected):
    path = tmp_path / "cam.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=expected) as info:
        load_camera_file(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_render_of_an_unfinished_run_without_a_snapshot_is_a_clear_error(run, tmp_path, capsys):
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    (unfinished / "cfg.json").write_text((run / "cfg.json").read_text())
    assert main(["render", str(unfinished), "--all", "--out", str(tmp_path / "x")]) == 2
    assert "no point_cloud.ply yet" in capsys.readouterr().err
    assert main(["render", str(run), "--all", "--snapshot", str(tmp_path / "none.npz"), "--out", str(tmp_path / "x")]) == 2
    assert "no such snapshot file" in capsys.readouterr().err
