"""The installed extension with the real trainer, in every supported Blender line.

For each line of tests/blender_lines.py, tests/blender_scripts/train_checks.py runs in one
bpy subprocess of that line (HOME in a temporary folder): a short CPU run and a cancel, on
the pinhole scene of tests/scenes.py; with ../shared/data beside the repository, also on
tumbler in the project's own line (the one whose bpy runs the tests). The trainer is
``python -m promptgs_engine train`` with this interpreter. The tumbler run in the
project's own line also renders docs/images/blender_training.png (Workbench, from a
dataset camera) when PROMPTGS_UPDATE_DOCS_IMAGE=1, else into the test's temporary folder.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from blender_lines import LINES, LineUnavailable, own_line
from scenes import TUMBLER, real_scene

pytest.importorskip("bpy", reason="needs the bpy module")
pytestmark = [pytest.mark.blender, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = REPO / "tests" / "blender_scripts"
RUNS = [(line, "pinhole") for line in LINES] + ([(own_line() or LINES[-1], "tumbler")] if real_scene(TUMBLER) else [])


@pytest.fixture(scope="module", params=RUNS, ids=lambda run: f"{run[0].id}-{run[1]}")
def run(request, tmp_path_factory, made_scenes, blender_envs, extension_zip):
    pytest.importorskip("promptgs_engine.train", reason="needs the trainer")
    line, scene_name = request.param
    facts = made_scenes[scene_name] if scene_name in made_scenes else TUMBLER
    try:
        python = blender_envs.python(line)
    except LineUnavailable as exc:
        pytest.skip(str(exc))
    tmp = tmp_path_factory.mktemp(f"train-{line.id}-{scene_name}")
    update_docs = bool(os.environ.get("PROMPTGS_UPDATE_DOCS_IMAGE")) and python == sys.executable and facts is TUMBLER
    image = REPO / "docs" / "images" / "blender_training.png" if update_docs else tmp / "blender_training.png"
    image.parent.mkdir(parents=True, exist_ok=True)
    strategy = "promptgs" if (REPO / "promptgs_engine" / "strategies" / "promptgs.py").is_file() else "3dgs"
    config = {"zip": str(extension_zip), "tmp": str(tmp), "python": sys.executable,
              "dataset": str(facts.path), "images": facts.small, "iterations": 20, "snapshot_every": 10,
              "strategy": strategy, "timeout": 240, "image": str(image), "render_camera": facts.render_camera,
              "prompt_rect": list(facts.prompt_rect),  # the scene's object in that view
              "update_docs": update_docs}
    (tmp / "config.json").write_text(json.dumps(config))
    (tmp / "home").mkdir()
    env = dict(os.environ, HOME=str(tmp / "home"), OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "2"))
    start = time.time()
    done = subprocess.run([python, str(SCRIPTS / "train_checks.py"), str(tmp / "config.json"),
                           str(tmp / "results.json")], env=env, capture_output=True, text=True, timeout=900)
    (tmp / "seconds").write_text(f"{time.time() - start:.1f}\n")
    if not (tmp / "results.json").is_file():
        pytest.fail(f"Blender {line.name}: the script failed before any check:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return tmp, json.loads((tmp / "results.json").read_text())


def _ok(results, name):
    assert name in results, f"check {name} did not run"
    assert results[name]["ok"], f"{results[name]['error']}\n{results[name].get('traceback', '')}"
    return results[name]


def test_setup_and_trainer_probe(run):
    info = _ok(run[1], "setup")
    assert "promptgs_engine" in info["probe"] and "cpu" in info["probe"], info["probe"]


def test_gaussians_object_matches_trainer_ply(run):
    tmp, results = run
    info = _ok(results, "train_real_trainer")
    plyfile = pytest.importorskip("plyfile")
    v = plyfile.PlyData.read(info["ply"])["vertex"].data
    obj = np.load(tmp / "object_attributes.npz")
    assert len(v) == info["n"] == len(obj["position"])
    col = lambda *names: np.stack([v[n] for n in names], axis=1).astype(np.float64)  # noqa: E731
    np.testing.assert_allclose(obj["position"], col("x", "y", "z"), atol=1e-5)
    np.testing.assert_allclose(obj["opacity"], 1 / (1 + np.exp(-v["opacity"].astype(np.float64))), atol=1e-5)
    np.testing.assert_allclose(obj["scale"], np.exp(col("scale_0", "scale_1", "scale_2")), rtol=1e-5, atol=1e-8)
    rot = col("rot_0", "rot_1", "rot_2", "rot_3")
    np.testing.assert_allclose(obj["rotation"], rot / np.linalg.norm(rot, axis=1, keepdims=True), atol=1e-5)
    dc = col("f_dc_0", "f_dc_1", "f_dc_2")
    np.testing.assert_allclose(obj["color"][:, :3], np.clip(0.5 + 0.28209479177387814 * dc, 0, 1), atol=1e-5)
    assert obj["score"].shape == obj["error"].shape == (len(v),)


def test_rendered_training_image(run):
    info = _ok(run[1], "train_real_trainer")
    assert "render_s" in info, "no snapshot arrived to render"
    assert Path(run[0] / "config.json").is_file()
    image = json.loads((run[0] / "config.json").read_text())["image"]
    assert Path(image).is_file() and Path(image).stat().st_size > 10_000


def test_preview_of_a_dataset_camera_is_promptgs_render(run, tmp_path):
    """*Render Preview* from a dataset camera shows what ``promptgs render RUN --camera NAME``
    writes, to within 1/255 per pixel, beside the dataset's photo."""
    from PIL import Image

    from promptgs_engine.evaluation import render_run

    tmp, results = run
    _ok(results, "preview_dataset_camera")
    out = Path(_ok(results, "train_real_trainer")["out"])
    camera = json.loads((tmp / "config.json").read_text())["render_camera"]
    [path] = render_run(out, tmp_path, [camera], quiet=True)
    expected = np.asarray(Image.open(path).convert("RGB"), np.float32) / 255.0
    shown = np.load(tmp / "preview_dataset_camera.npy")
    assert shown.shape == expected.shape
    assert expected.std() > 0.05  # a picture of the scene, not an empty frame
    assert np.abs(shown - expected).max() <= 1.0 / 255.0 + 1e-6
    both = np.load(tmp / "preview_side_by_side.npy")
    width = expected.shape[1]
    np.testing.assert_array_equal(both[:, :width], shown)
    photo = np.asarray(Image.open(run_photo(out, camera)).convert("RGB"), np.float32) / 255.0
    assert np.abs(both[:, width:] - photo).max() <= 1.0 / 255.0 + 1e-6
    if _updates_docs(tmp):
        Image.fromarray((both * 255).round().astype(np.uint8)).save(REPO / "docs" / "images" / "preview_dataset_camera.png")


def test_preview_of_a_placed_camera_shows_another_view(run):
    tmp, results = run
    info = _ok(results, "preview_user_camera")
    assert info["size"] == [240, 320] and info["max_error_px"] < 0.05
    shown = np.load(tmp / "preview_user_camera.npy")
    assert shown.shape == (320, 240, 3) and shown.std() > 0.05
    if _updates_docs(tmp):
        from PIL import Image

        Image.fromarray((shown * 255).round().astype(np.uint8)).save(REPO / "docs" / "images" / "preview_placed_camera.png")


def run_photo(run_dir: Path, camera: str) -> Path:
    cfg = json.loads((run_dir / "cfg.json").read_text())
    return Path(cfg["dataset"]) / cfg["images"] / camera


def _updates_docs(tmp: Path) -> bool:
    """Whether this line's run writes the docs images (PROMPTGS_UPDATE_DOCS_IMAGE=1, the project's own bpy)."""
    return json.loads((tmp / "config.json").read_text())["update_docs"]


def test_cancel_keeps_last_snapshot(run):
    info = _ok(run[1], "cancel_real_trainer")
    assert info["snapshot_step"] > 0


def test_trainer_never_imported_in_blender(run):
    _ok(run[1], "never_imports_torch_or_engine")
