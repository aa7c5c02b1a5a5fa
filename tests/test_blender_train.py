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
              "strategy": strategy, "timeout": 240, "resume_iterations": 60, "image": str(image),
              "render_camera": facts.render_camera, "prompt_rect": list(facts.prompt_rect),  # the scene's object in that view
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
    # Blender 5.3's Gaussian-splat layout (ply_import_gsplat.cc), on every line
    base = obj["radiance:base"]
    np.testing.assert_array_equal(base[:, :3], col("f_dc_0", "f_dc_1", "f_dc_2"))
    np.testing.assert_allclose(base[:, 3], 1 / (1 + np.exp(-v["opacity"].astype(np.float64))), atol=1e-6)
    np.testing.assert_allclose(obj["scale"], np.exp(col("scale_0", "scale_1", "scale_2")), rtol=1e-5, atol=1e-8)
    rot = col("rot_0", "rot_1", "rot_2", "rot_3")
    np.testing.assert_allclose(obj["rotation"], rot / np.linalg.norm(rot, axis=1, keepdims=True), atol=1e-5)
    k = sum(1 for name in v.dtype.names if name.startswith("f_rest_")) // 3
    assert k == 15 and [f"radiance:sh_{j}" in obj for j in range(k + 1)] == [True] * k + [False]
    for j in (0, 7, 14):
        np.testing.assert_array_equal(obj[f"radiance:sh_{j}"], col(f"f_rest_{j}", f"f_rest_{k + j}", f"f_rest_{2 * k + j}"))
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


def test_exported_gaussians_evaluate(run):
    """*Export Gaussians* of the finished run, unchanged and with the prompt box's splats
    deleted in Edit Mode: ``promptgs eval`` reads both; the unchanged one scores exactly
    what the run scored (it is the run's own PLY, bit for bit)."""
    from promptgs_engine.evaluation import evaluate_run

    tmp, results = run
    info = _ok(results, "export_for_eval")
    out = Path(_ok(results, "train_real_trainer")["out"])
    trained = json.loads((out / "metrics.json").read_text())
    unchanged = evaluate_run(Path(info["unchanged"]), quiet=True)
    assert unchanged["n_gaussians"] == trained["n_gaussians"]
    assert unchanged["psnr"] == pytest.approx(trained["psnr"], abs=1e-6)
    assert (Path(info["unchanged"]) / "point_cloud.ply").read_bytes().split(b"end_header")[1] == \
        (out / "point_cloud.ply").read_bytes().split(b"end_header")[1]
    cropped = evaluate_run(Path(info["cropped"]), quiet=True)
    assert cropped["n_gaussians"] == info["n_left"] == trained["n_gaussians"] - info["deleted"]
    assert np.isfinite(cropped["psnr"]) and cropped["psnr"] != trained["psnr"]


def test_a_run_trains_from_the_cleaned_export(run):
    """*Train From It*: the run after the export starts from the exported file's Gaussians
    (as many as the first run's, less those deleted in the prompt box) and finishes with a
    PLY that ``promptgs eval`` scores."""
    from promptgs_engine.evaluation import evaluate_run

    tmp, results = run
    exported = _ok(results, "export_for_eval")
    info = _ok(results, "train_from_the_cleaned_export")
    trained = json.loads((Path(_ok(results, "train_real_trainer")["out"]) / "metrics.json").read_text())
    assert info["init"] == str(Path(exported["cropped"]) / "point_cloud.ply")
    assert info["initial_gaussians"] == exported["n_left"] == trained["n_gaussians"] - exported["deleted"]
    again = evaluate_run(Path(info["out"]), quiet=True)
    assert again["n_gaussians"] == info["n_final"] and np.isfinite(again["psnr"])


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a.astype(np.float64) - b) ** 2)))


def test_cycles_renders_the_run_like_promptgs_render(run, tmp_path):
    """5.3+: Cycles' render of Blender's own splats from a dataset camera against the photo
    and against ``promptgs render`` of that camera (PSNR). Before 5.3 the add-on finds no
    splats of Blender's own (and there is nothing to render)."""
    from PIL import Image

    from promptgs_engine.evaluation import render_run

    tmp, results = run
    info = _ok(results, "cycles_render_of_native_splats")
    assert info["native"] == (tuple(info["blender"][:2]) >= (5, 3)), info
    if not info["native"]:
        return
    out = Path(_ok(results, "train_real_trainer")["out"])
    camera = json.loads((tmp / "config.json").read_text())["render_camera"]
    [path] = render_run(out, tmp_path, [camera], quiet=True)
    ours = np.asarray(Image.open(path).convert("RGB"), np.float32) / 255.0
    cycles = np.asarray(Image.open(info["image"]).convert("RGB"), np.float32) / 255.0
    photo = np.asarray(Image.open(run_photo(out, camera)).convert("RGB"), np.float32) / 255.0
    assert cycles.shape == ours.shape == photo.shape, (cycles.shape, ours.shape)
    against_ours, against_photo = _psnr(cycles, ours), _psnr(cycles, photo)
    # the same scene in the same place and colours: the match peaks where the pictures line
    # up (shifted by 3 pixels or by a tenth of the width, either way along either axis, it
    # loses more than 1 dB; measured on the made scene at 84x63: 1.4 dB at 3 pixels)
    tenth = cycles.shape[1] // 10
    shifted = max(_psnr(np.roll(cycles, d, axis=axis), ours) for axis in (0, 1) for d in (-3, 3, -tenth, tenth))
    assert against_ours > 20.0 and against_ours > shifted + 1.0, (against_ours, shifted)
    assert against_photo > 12.0, against_photo
    print(f"Cycles vs promptgs render {against_ours:.2f} dB, vs photo {against_photo:.2f} dB, "
          f"promptgs render vs photo {_psnr(ours, photo):.2f} dB, {info['seconds']} s")


def test_cancel_keeps_last_snapshot(run):
    info = _ok(run[1], "cancel_real_trainer")
    assert info["snapshot_step"] > 0


def test_an_interrupted_run_resumes_to_the_uninterrupted_result(run):
    info = _ok(run[1], "resume_reaches_the_uninterrupted_result")
    assert info["resumed_at"] >= 10


def test_a_two_process_cancel_leaves_no_process(run):
    info = _ok(run[1], "multi_rank_cancel_leaves_no_process")
    assert info["processes"] >= 4


def test_trainer_never_imported_in_blender(run):
    _ok(run[1], "never_imports_torch_or_engine")


@pytest.mark.skipif(os.environ.get("PROMPTGS_TEST_SETUP") != "1",
                    reason="installs torch and compiles the engine into a new environment (minutes, about 1 GB): "
                           "PROMPTGS_TEST_SETUP=1 runs it")
def test_set_up_trainer_makes_an_environment_that_trains(tmp_path, toy, extension_zip):
    """*Set Up Trainer* in this interpreter's bpy (the project's own line), for real: a
    fresh environment made from this interpreter, torch 2.13.0 CPU and the engine built
    from a copy of this checkout's files; then it trains the toy scene from the panel."""
    source = tmp_path / "checkout"
    files = subprocess.run(["git", "-C", str(REPO), "ls-files"], capture_output=True, text=True, check=True).stdout
    for name in files.splitlines():
        if (REPO / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            (source / name).write_bytes((REPO / name).read_bytes())
    config = {"zip": str(extension_zip), "tmp": str(tmp_path), "base_python": sys.executable, "source": str(source),
              "torch_index": os.environ.get("PROMPTGS_TORCH_INDEX", ""), "toy": str(toy), "timeout": 3000}
    (tmp_path / "config.json").write_text(json.dumps(config))
    (tmp_path / "home").mkdir()
    env = dict(os.environ, HOME=str(tmp_path / "home"))
    env.pop("PYTHONPATH", None)  # the new environment must import its own engine
    done = subprocess.run([sys.executable, str(SCRIPTS / "setup_checks.py"), str(tmp_path / "config.json"),
                           str(tmp_path / "results.json")], env=env, capture_output=True, text=True, timeout=3600)
    (tmp_path / "stdout.log").write_text(done.stdout + done.stderr)
    if not (tmp_path / "results.json").is_file():
        pytest.fail(f"the script failed before any check:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    results = json.loads((tmp_path / "results.json").read_text())
    for name in ("set_up_trainer_makes_the_environment", "the_environment_trains_the_toy_scene",
                 "never_imports_torch_or_engine"):
        _ok(results, name)
    assert results["set_up_trainer_makes_the_environment"]["python"].startswith(str(tmp_path))


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process tree from /proc")
@pytest.mark.parametrize("line", LINES, ids=str)
def test_a_killed_blender_leaves_no_trainer_running(line, tmp_path, made_scenes, blender_envs, extension_zip):
    """Blender (this line's bpy) starts a two-process training and is killed (SIGKILL: no
    handler of its runs): every process of the trainer is gone within seconds (the
    lifeline: the pipe on their stdin closes with Blender)."""
    from promptgs_engine.lifeline import GRACE_S

    try:
        python = blender_envs.python(line)
    except LineUnavailable as exc:
        pytest.skip(str(exc))
    config = {"zip": str(extension_zip), "tmp": str(tmp_path), "python": sys.executable, "nproc": 2,
              "dataset": str(made_scenes["pinhole"].path), "images": made_scenes["pinhole"].small, "timeout": 300}
    (tmp_path / "config.json").write_text(json.dumps(config))
    (tmp_path / "home").mkdir()
    env = dict(os.environ, HOME=str(tmp_path / "home"), OMP_NUM_THREADS="1")
    blender = subprocess.Popen([python, str(SCRIPTS / "orphan_checks.py"), str(tmp_path / "config.json"),
                                str(tmp_path / "results.json")], env=env, stdout=subprocess.DEVNULL,
                               stderr=open(tmp_path / "blender.log", "w"))
    pids_file = tmp_path / "trainer_pids.json"
    deadline = time.time() + 400
    while not pids_file.is_file() and blender.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    if not pids_file.is_file():
        blender.kill()
        results = (tmp_path / "results.json").read_text() if (tmp_path / "results.json").is_file() else ""
        pytest.fail(f"Blender {line.name}: no training started: {results}\n{(tmp_path / 'blender.log').read_text()[-3000:]}")
    pids = json.loads(pids_file.read_text())
    assert len(pids) >= 4, pids  # launcher, torchrun, two ranks
    start = time.time()
    blender.kill()
    blender.wait()
    while any(_running(pid) for pid in pids) and time.time() - start < 60:
        time.sleep(0.1)
    seconds = time.time() - start
    (tmp_path / "seconds").write_text(f"{seconds:.2f}\n")
    left = [pid for pid in pids if _running(pid)]
    for pid in left:
        os.kill(pid, 9)
    assert not left, f"still running {seconds:.0f} s after Blender was killed: {left}"
    assert seconds < GRACE_S + 5, seconds


def _running(pid: int) -> bool:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return text[text.rindex(")") + 2:].split()[0] != "Z"
