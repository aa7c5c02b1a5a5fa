"""Checks of the installed extension with recorded/fake trainers (see test_blender_addon.py)."""

import json
import os
import shutil
import sys
import time
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, os.path.dirname(__file__))
from harness import (addon, blocked_attempts, bpy, cancel_and_wait, check, config, delete_selected_points,  # noqa: E402
                     drain_until, finish, forbidden_modules, install, process_gone, run_until_idle)

import numpy as np  # noqa: E402
from bpy_extras.object_utils import world_to_camera_view  # noqa: E402
from mathutils import Euler, Matrix, Vector  # noqa: E402

TMP = Path(config["tmp"])
SH_C0 = 0.28209479177387814


def srgb_to_linear(c):
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
scene = lambda: bpy.context.scene  # noqa: E731
jobs = lambda: bpy.context.window_manager.promptgs_run  # noqa: E731  (the other background jobs)


def state():
    """The record of the run the scene shows."""
    return addon("training").shown_record(scene())


class StubLayout:
    """Records what a panel draws; checks property names and operator ids as it goes."""

    def __init__(self, log):
        self.log = log

    def __getattr__(self, name):
        def call(*args, **kwargs):
            if name == "prop":
                data, prop = args[0], args[1]
                assert prop in data.bl_rna.properties, f"{type(data).__name__} has no property {prop}"
            elif name == "operator":
                module, op = args[0].split(".")
                assert hasattr(getattr(bpy.ops, module), op), f"no operator {args[0]}"
                self.log.append(f"[{args[0]}]")
            elif name == "label":
                self.log.append(kwargs.get("text", ""))
            return StubLayout(self.log)
        return call

    def __setattr__(self, name, value):
        object.__setattr__(self, name, value)


def panel_lines(*panels) -> list[str]:
    """The labels (and, as [id], the operator buttons) the panels draw now."""
    log = []
    for cls in panels or addon("ui").CLASSES:
        cls.draw(SimpleNamespace(layout=StubLayout(log)), bpy.context)
    return log


class PrefsView:
    """The add-on preferences with a recording layout, to draw them outside a window."""

    def __init__(self, log):
        object.__setattr__(self, "layout", StubLayout(log))

    def __getattr__(self, name):
        return getattr(prefs(), name)


def prefs_lines() -> list[str]:
    log = []
    type(prefs()).draw(PrefsView(log), bpy.context)
    return log


def live_run():
    return addon("training").live_of(state())


def shown_gaussians() -> tuple[str, int]:
    """(the file the shown Gaussians hold, their count)."""
    obj = bpy.data.objects[addon("results").GAUSSIANS]
    return obj.get("promptgs_shows", ""), addon("display").point_count(obj)


def npz_count(path: str, key: str = "means") -> int:
    with np.load(path) as npz:
        return len(npz[key])


@check
def installed_and_enabled():
    info = install()
    assert hasattr(bpy.types.Scene, "promptgs") and hasattr(bpy.ops.promptgs, "train")
    return info


def prefs():
    return bpy.context.preferences.addons["bl_ext.user_default.promptgs"].preferences


prefs().output_dir = str(TMP / "runs")


SCENE, DISTORTED = config["scene"], config["distorted"]  # made by tests/scenes.py


def points_of(facts: dict):
    return bpy.data.objects[f"PromptGS Sparse Points {facts['name']}"]


def root_of(facts: dict):
    return bpy.data.objects[f"PromptGS Root {facts['name']}"]


def import_scene(facts: dict):
    bpy.ops.promptgs.import_colmap(directory=facts["path"], images=facts["small"])
    root = scene().promptgs.root
    assert root == root_of(facts)
    cams = [o for o in root.children if o.type == "CAMERA"]
    points = points_of(facts)
    assert len(cams) == facts["n_images"], len(cams)
    assert len(points.data.vertices) == facts["n_points"] and points.type == "MESH"  # editable: a mesh on every line
    assert {"color", "error"} <= set(points.data.attributes.keys())
    assert scene().promptgs.distortion == ""
    return {"cameras": len(cams)}


def projection_matches_colmap(facts: dict):
    root = root_of(facts)
    errors = []
    for item in facts["projections"]:
        cam = bpy.data.objects[item["image"]]
        assert cam.parent == root
        bpy.ops.promptgs.use_camera(name=cam.name)
        width, height = scene().render.resolution_x, scene().render.resolution_y
        assert (width, height) == (cam.data["promptgs_width"], cam.data["promptgs_height"]) == tuple(facts["size"])
        ndc = world_to_camera_view(scene(), cam, root.matrix_world @ Vector(item["point"]))
        uv = np.array([ndc.x * width, (1.0 - ndc.y) * height])
        errors.append(float(np.abs(uv - np.array(item["uv"])).max()))
    assert max(errors) < 0.5, max(errors)
    return {"max_error_px": max(errors), "n": len(errors)}


def root_puts_capture_upright(facts: dict):
    ups = []
    for cam in [o for o in root_of(facts).children if o.type == "CAMERA"]:
        ups.append(tuple(cam.matrix_world.to_3x3() @ Vector((0, 1, 0))))  # Blender camera up
    mean_up = np.mean(ups, axis=0)
    assert mean_up[2] > 0.5, mean_up
    return {"mean_camera_up": mean_up.tolist()}


def import_distorted_reports_distortion(facts: dict):
    before = set(bpy.data.objects.keys())
    bpy.ops.promptgs.import_colmap(directory=facts["path"], backgrounds=True)
    note = scene().promptgs.distortion
    cam = bpy.data.objects[facts["background"]]
    assert cam.data.show_background_images and cam.data.background_images[0].image.name == facts["background"]
    assert (cam.data["promptgs_width"], cam.data["promptgs_height"]) == tuple(facts["size"])
    for word in facts["distortion_words"]:
        assert word in note, (word, note)
    new = set(bpy.data.objects.keys()) - before
    assert len([n for n in new if bpy.data.objects[n].type == "CAMERA"]) == facts["n_images"]
    return {"note": note}


def back_to_the_scene() -> None:
    """The made pinhole scene's import is the one the later checks work on."""
    scene().promptgs.root = root_of(SCENE)
    scene().promptgs.images = SCENE["small"]


check(import_scene, SCENE)
check(projection_matches_colmap, SCENE)
check(root_puts_capture_upright, SCENE)


@check
def non_square_pixels_project_exactly():
    bpy.ops.promptgs.import_colmap(directory=config["pinhole"], up="+Z")
    root = scene().promptgs.root
    errors = []
    for item in config["pinhole_projections"]:
        cam = bpy.data.objects[item["image"]]
        bpy.ops.promptgs.use_camera(name=cam.name)
        width, height = scene().render.resolution_x, scene().render.resolution_y
        ndc = world_to_camera_view(scene(), cam, root.matrix_world @ Vector(item["point"]))
        uv = np.array([ndc.x * width, (1.0 - ndc.y) * height])
        errors.append(float(np.abs(uv - np.array(item["uv"])).max()))
    aspect = (scene().render.pixel_aspect_x, scene().render.pixel_aspect_y)
    back_to_the_scene()
    assert max(errors) < 0.5, max(errors)
    return {"max_error_px": max(errors), "last_pixel_aspect": aspect}


check(import_distorted_reports_distortion, DISTORTED)
back_to_the_scene()


def pytest_approx(values, tol=1e-6):
    class Approx:
        def __eq__(self, other):
            return all(abs(a - b) <= tol for a, b in zip(other, values)) and len(other) == len(values)
    return Approx()


def fake_trainer(mode: str) -> None:
    os.environ["FAKE_TRAINER_MODE"] = mode
    prefs().python = config["fake_python"]


@check
def prompt_cube_box_in_job_file():
    root = scene().promptgs.root
    scene().cursor.location = (0.1, 0.2, 0.3)
    bpy.ops.promptgs.add_prompt()
    cube = bpy.context.active_object
    assert cube.empty_display_type == "CUBE" and cube.users_collection[0].name == "PromptGS Prompts"
    assert tuple(cube.location) == pytest_approx((0.1, 0.2, 0.3))
    # move, rotate, scale it, change its size and weight
    cube.location = (0.3, -0.2, 0.5)
    cube.rotation_euler = Euler((0.3, -0.5, 1.1))
    cube.scale = (0.2, 0.3, 0.4)
    cube.empty_display_size = 0.5
    cube.promptgs_weight = 2.5
    bpy.ops.promptgs.add_prompt()
    off = bpy.context.active_object
    off.promptgs_enabled = False
    bpy.context.view_layer.update()
    fake_trainer("ok")
    os.environ["FAKE_TRAINER_MODE"] = "crash"  # only the job file matters here
    bpy.ops.promptgs.train()
    run_until_idle(60)
    job = json.loads(Path(state().job_path).read_text())
    assert len(job["prompts"]["prompts"]) == 1
    box = job["prompts"]["prompts"][0]
    assert box["weight"] == 2.5
    # the box's corners, taken back to Blender with the root, are the cube's drawn corners
    rot = Matrix(np.array(addon("coords").quat_to_rotmat(box["rotation_wxyz"])).tolist()).to_4x4()
    box_matrix = Matrix.Translation(box["center"]) @ rot
    worst = 0.0
    for corner in [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]:
        drawn = cube.matrix_world @ (Vector(corner) * cube.empty_display_size)
        local = Vector([c * s / 2.0 for c, s in zip(corner, box["size"])])
        sent = root.matrix_world @ box_matrix @ local
        worst = max(worst, (drawn - sent).length)
    assert worst < 1e-5, worst
    assert box["size"] == pytest_approx([0.2, 0.3, 0.4])  # 2 × display size 0.5 × scale
    for key in ("dataset", "out", "images", "iterations", "strategy", "backend", "snapshot_every", "seed"):
        assert key in job, key
    assert job["images"] == SCENE["small"] and Path(job["dataset"]).resolve() == Path(SCENE["path"]).resolve()
    assert not {"budget", "auto_prompts", "propose_prompts", "compact", "nproc"} & set(job)  # off / one process
    scene().promptgs.compact, scene().promptgs.nproc, scene().promptgs.propose_prompts = True, 2, True
    job_with = addon("training").build_job(bpy.context, TMP / "job_check")
    scene().promptgs.strategy = "3dgs"  # proposing needs the PromptGS strategy: not asked for
    job_3dgs = addon("training").build_job(bpy.context, TMP / "job_check")
    scene().promptgs.compact, scene().promptgs.nproc, scene().promptgs.propose_prompts = False, 1, False
    scene().promptgs.strategy = "promptgs"
    assert job_with["compact"] is True and job_with["nproc"] == 2 and job_with["propose_prompts"] is True, job_with
    assert not {"prompts", "auto_prompts", "propose_prompts"} & set(job_3dgs), job_3dgs  # the engine refuses them
    # a flat cube is a clear error in the panel, not a traceback
    off.promptgs_enabled = True
    off.scale = (1.0, 0.0, 1.0)
    try:
        bpy.ops.promptgs.train()
    except RuntimeError:
        pass
    assert f"prompt '{off.name}'" in scene().promptgs.start_error, scene().promptgs.start_error
    bpy.data.objects.remove(off)
    return {"box": box, "corner_error": worst, "flat_message": scene().promptgs.start_error}


@check
def prompt_around_selected_points():
    points = points_of(SCENE)
    mesh = points.data
    n = len(mesh.vertices)
    co = np.empty(n * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    co = co.reshape(n, 3)
    chosen = np.zeros(n, bool)
    chosen[np.argsort(np.linalg.norm(co - np.median(co, axis=0), axis=1))[:200]] = True
    mesh.vertices.foreach_set("select", chosen)
    for obj in bpy.context.selected_objects:
        obj.select_set(False)
    points.select_set(True)
    bpy.context.view_layer.objects.active = points
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.promptgs.add_prompt()
    cube = bpy.context.active_object
    assert bpy.context.mode == "OBJECT" and cube.empty_display_type == "CUBE"
    inside = cube.matrix_world.inverted() @ points.matrix_world
    local = np.array([tuple(inside @ Vector(p.tolist())) for p in co[chosen]])
    assert np.abs(local).max() <= 1.0 + 1e-6, np.abs(local).max()  # every chosen point in the cube
    assert np.abs(local).max(axis=0).min() > 0.8  # and the cube is tight around them
    bpy.data.objects.remove(cube)
    return {}


@check
def train_with_recorded_events_updates_objects():
    fake_trainer("ok")
    scene().promptgs.preset = "CUSTOM"
    scene().promptgs.iterations = 30
    bpy.ops.promptgs.train()
    training = addon("training")
    seen = {}

    def first_snapshot():
        obj = bpy.data.objects.get("PromptGS Gaussians")
        if obj is not None and "pointer" not in seen:
            seen["pointer"] = obj.as_pointer()
            seen["data"] = obj.data.as_pointer()
            seen["count"] = addon("display").point_count(obj)
        return False

    # drain one batch at a time so the snapshots arrive separately
    deadline = time.time() + 60
    while training.drain_and_apply(bpy.context) and time.time() < deadline:
        first_snapshot()
        time.sleep(0.001)
    st = state()
    assert st.status == "DONE", (st.status, st.message)
    obj = bpy.data.objects["PromptGS Gaussians"]
    assert obj.as_pointer() == seen["pointer"], "the object was re-created"
    if obj.type == "MESH":  # a point cloud gets a new datablock when its count changes (display._resize)
        assert obj.data.as_pointer() == seen["data"], "the mesh was re-created"
    with np.load(st.last_snapshot) as npz:
        data = dict(npz)
    display = addon("display")
    n = len(data["means"])
    assert display.point_count(obj) == n == st.n_gaussians == 400
    np.testing.assert_allclose(display.get_attribute(obj, "position"), data["means"], atol=1e-6)
    for key in ("scale", "rotation", "score", "error"):
        np.testing.assert_allclose(display.get_attribute(obj, key), data[key], atol=1e-6, err_msg=key)
    base = display.get_attribute(obj, "radiance:base")  # Blender 5.3's layout: f_dc, opacity
    np.testing.assert_allclose(base[:, 3], data["opacity"], atol=1e-6)
    np.testing.assert_allclose(0.5 + SH_C0 * base[:, :3], data["color"], atol=1e-6)
    assert obj.parent == scene().promptgs.root
    field = bpy.data.objects["PromptGS Loss Field"]
    assert display.point_count(field) == 64
    np.testing.assert_allclose(display.get_attribute(field, "loss"), data["field_loss"], atol=1e-6)
    np.testing.assert_allclose(display.get_attribute(field, "attention"), data["field_attention"], atol=1e-6)
    # the default look: splats in their trained colours (Blender's own from 5.3 on)
    native = bpy.app.version >= (5, 3, 0)
    assert obj["promptgs_mode"] == ("NATIVE" if native else "SPLATS"), obj["promptgs_mode"]
    if native:
        assert obj.data.type == "GAUSSIAN_SPLAT" and not obj.modifiers["PromptGS Display"].show_viewport
    else:
        shown = display.get_attribute(obj, "display_color")
        np.testing.assert_allclose(shown[:, :3], srgb_to_linear(data["color"]), atol=1e-5)
        np.testing.assert_allclose(shown[:, 3], data["opacity"], atol=1e-6)
    # a point cloud where Blender can resize one from Python (5.1+), a points-only mesh before
    kind = "POINTCLOUD" if bpy.app.version >= (5, 1, 0) else "MESH"
    assert obj.type == field.type == kind, (obj.type, field.type, bpy.app.version_string)
    # what the object carries, for the comparison across lines (test_blender_addon.py)
    np.savez(TMP / "gaussians_object.npz", snapshot=np.array(Path(st.last_snapshot).name),
             **{f"gaussians_{key}": display.get_attribute(obj, key)
                for key in ("position", "radiance:base", "scale", "rotation", "score", "error")},
             **{f"field_{key}": display.get_attribute(field, key) for key in ("position", "loss", "attention")})
    return {"first_snapshot_count": seen["count"], "final_count": n, "object_type": obj.type,
            "blender": bpy.app.version_string}


@check
def cancel_keeps_last_snapshot():
    fake_trainer("slow")
    bpy.ops.promptgs.train()
    out = Path(state().folder)
    training = addon("training")
    deadline = time.time() + 60
    while not state().last_snapshot and time.time() < deadline:
        training.drain_and_apply(bpy.context)
        time.sleep(0.05)
    assert state().last_snapshot
    bpy.ops.promptgs.cancel()
    run_until_idle(60)
    st = state()
    assert st.status == "CANCELLED", (st.status, st.message)
    assert (out / "cancelled").is_file(), "the trainer was not interrupted cleanly"
    with np.load(st.last_snapshot) as npz:
        n = len(npz["means"])
    assert addon("display").point_count(bpy.data.objects["PromptGS Gaussians"]) == n
    assert training.current_run() is None
    return {"message": st.message}


@check
def crashed_trainer_shows_error_lines():
    fake_trainer("crash")
    bpy.ops.promptgs.train()
    run_until_idle(60)
    st = state()
    assert st.status == "ERROR" and st.message == "RuntimeError: the fake trainer crashed", st.message
    assert "Traceback" in st.error_lines and Path(st.log_path).is_file()
    return {"message": st.message, "log": st.log_path}


@check
def wrong_trainer_path_is_a_clear_error():
    prefs().python = "/no/such/python"
    try:
        bpy.ops.promptgs.train()
        raise AssertionError("train did not fail")
    except RuntimeError as exc:
        reported = str(exc)
    message = scene().promptgs.start_error
    assert "Trainer command not found: /no/such/python" in message and message in reported, (message, reported)
    log = []
    addon("ui").PROMPTGS_PT_train.draw(SimpleNamespace(layout=StubLayout(log)), bpy.context)
    assert message in log, log  # the panel says it
    return {"message": message, "reported": reported.strip()}


@check
def dataset_without_images_is_a_clear_error():
    bare = TMP / "no_images"
    shutil.copytree(Path(SCENE["path"]) / "sparse", bare / "sparse")
    bpy.ops.promptgs.import_colmap(directory=str(bare))
    fake_trainer("ok")
    try:
        bpy.ops.promptgs.train()
        raise AssertionError("train did not fail")
    except RuntimeError:
        pass
    message = scene().promptgs.start_error
    assert "no such image folder" in message and "no_images" in message, message
    back_to_the_scene()
    return {"message": message}


@check
def dataset_generation_runs_in_background():
    training = addon("training")
    fake_trainer("ok")
    scene().promptgs.dataset_out = str(TMP / "generated")
    scene().promptgs.dataset_preset = "tiny"
    bpy.ops.promptgs.generate_dataset()
    assert jobs().dataset_status == "RUNNING"
    run_until_idle(60)
    assert jobs().dataset_status == "DONE", jobs().dataset_message
    argv = (TMP / "generated" / "done").read_text().split()
    assert argv[argv.index("dataset"):][:4] == ["dataset", "mountain", "--preset", "tiny"], argv
    fake_trainer("crash")
    bpy.ops.promptgs.generate_dataset()
    run_until_idle(60)
    assert jobs().dataset_status == "ERROR"
    assert jobs().dataset_message == "promptgs: error: --preset tiny: cannot find a blender binary"
    return {"argv": argv}


@check
def reconstruct_from_photos_imports_the_result():
    """sfm runs in the background, its stage line shows, and its dataset is imported."""
    fake_trainer("stepwise")  # the fake holds at its mapping stage until sfm_go exists
    photos = Path(SCENE["path"]) / "images"
    n = SCENE["n_images"]
    bpy.ops.promptgs.reconstruct(directory=str(photos))
    assert jobs().sfm_status == "RUNNING", (jobs().sfm_status, jobs().sfm_message)
    go = Path(jobs().sfm_out).parent / "sfm_go"
    lines = []
    training = addon("training")
    deadline = time.time() + 60
    while training.drain_and_apply(bpy.context) and time.time() < deadline:
        lines.append(jobs().sfm_message)
        if jobs().sfm_message.startswith("mapping"):
            go.touch()
        time.sleep(0.01)
    assert jobs().sfm_status == "DONE", (jobs().sfm_status, jobs().sfm_message)
    assert any(line.startswith(("features", "matching", "mapping")) for line in lines), lines
    assert f"{n - 1} of {n} images registered" in jobs().sfm_message, jobs().sfm_message
    root = scene().promptgs.root
    assert Path(root["promptgs_dataset"]) == Path(jobs().sfm_out).resolve()
    assert len([o for o in root.children if o.type == "CAMERA"]) == n
    back_to_the_scene()
    return {"message": jobs().sfm_message, "stage_lines": sorted(set(lines))[:6]}


@check
def reconstruct_errors_and_cancel():
    fake_trainer("crash")
    photos = Path(SCENE["path"]) / "images"
    bpy.ops.promptgs.reconstruct(directory=str(photos))
    run_until_idle(60)
    only = f"only 6 of {SCENE['n_images']} images registered"
    assert jobs().sfm_status == "ERROR" and only in jobs().sfm_message, jobs().sfm_message
    fake_trainer("slow")
    bpy.ops.promptgs.reconstruct(directory=str(photos))
    out = Path(jobs().sfm_out)
    training = addon("training")
    deadline = time.time() + 60
    while not jobs().sfm_message.startswith("mapping") and time.time() < deadline:
        training.drain_and_apply(bpy.context)
        time.sleep(0.05)
    bpy.ops.promptgs.cancel_reconstruct()
    run_until_idle(60)
    assert jobs().sfm_status == "CANCELLED", (jobs().sfm_status, jobs().sfm_message)
    assert (out.parent / "sfm_cancelled").is_file(), "the reconstruction was not interrupted cleanly"
    try:
        bpy.ops.promptgs.reconstruct(directory=str(TMP / "no_such_photos"))
        raise AssertionError("reconstruct did not fail")
    except RuntimeError:
        pass
    assert jobs().sfm_status == "ERROR" and "no_such_photos: not found" in jobs().sfm_message, jobs().sfm_message
    return {"message": jobs().sfm_message}


INRIA_NAMES = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
               + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def write_ply(path: Path, names: list, table: np.ndarray) -> Path:
    """A binary little-endian float32 PLY of one vertex table (numpy only: no plyfile here)."""
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % len(table)
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    path.write_bytes(header.encode() + np.ascontiguousarray(table, "<f4").tobytes())
    return path


def load_random_ply(name: str, seed: int, n: int) -> tuple[np.ndarray, Path, object]:
    """A random Inria-layout PLY (SH degree 3, normals) loaded with Load Result: its table,
    its path and the Gaussians object."""
    table = np.random.default_rng(seed).normal(size=(n, len(INRIA_NAMES))).astype("<f4")
    path = write_ply(TMP / name, INRIA_NAMES, table)
    bpy.ops.promptgs.load_result(filepath=str(path))
    return table, path, bpy.data.objects["PromptGS Gaussians"]


def expected_layout(col: dict) -> dict:
    """Blender 5.3's Gaussian-splat attributes of a 3DGS vertex table (ply_import_gsplat.cc)."""
    stack = lambda *names: np.stack([col[n].astype(np.float64) for n in names], 1)  # noqa: E731
    rot = stack("rot_0", "rot_1", "rot_2", "rot_3")
    out = {"position": stack("x", "y", "z"),
           "radiance:base": np.concatenate([stack("f_dc_0", "f_dc_1", "f_dc_2"),
                                            1 / (1 + np.exp(-stack("opacity")))], 1),
           "scale": np.exp(stack("scale_0", "scale_1", "scale_2")),
           "rotation": rot / np.linalg.norm(rot, axis=1, keepdims=True)}
    k = sum(1 for name in col if name.startswith("f_rest_")) // 3
    out.update({f"radiance:sh_{j}": stack(f"f_rest_{j}", f"f_rest_{k + j}", f"f_rest_{2 * k + j}") for j in range(k)})
    return out


@check
def load_result_reads_3dgs_ply():
    """A 3DGS PLY (degree 3, normals) becomes Blender 5.3's splat attributes, on every line."""
    n = 500
    run = next(r for r in reversed(scene().promptgs.runs) if r.last_snapshot)  # a run with Gaussians
    bpy.ops.promptgs.show_run(name=run.name)
    table, _, obj = load_random_ply("result.ply", 3, n)
    assert scene().promptgs.shown_run == "" and obj.get("promptgs_run") is None  # shows no run now
    kept = bpy.data.objects[addon("training").parked_name("PromptGS Gaussians", run.name)]  # the run's are kept
    assert addon("display").point_count(kept) == npz_count(run.last_snapshot)
    display = addon("display")
    col = {name: table[:, i] for i, name in enumerate(INRIA_NAMES)}
    assert display.point_count(obj) == n
    for name, values in expected_layout(col).items():
        np.testing.assert_allclose(display.get_attribute(obj, name), values, rtol=1e-6, atol=1e-7, err_msg=name)
    assert "radiance:sh_15" not in obj.data.attributes
    np.testing.assert_array_equal(display.get_attribute(obj, "nx"), col["nx"])  # other properties kept
    result = {"n": n, "radiance_base_type": obj.data.attributes["radiance:base"].data_type}
    bpy.ops.promptgs.show_run(name=run.name)  # back to the run (the loaded PLY is kept, as "Loaded")
    assert bpy.data.objects.get(addon("training").parked_name("PromptGS Gaussians", "Loaded")) is not None
    assert display.point_count(bpy.data.objects["PromptGS Gaussians"]) == npz_count(run.last_snapshot)
    return result


@check
def blender_import_agrees_with_ours():
    """5.3+: Blender's own import (wm.ply_import) of a 3DGS PLY and our Gaussians object of
    the same file, and of a snapshot of the same Gaussians, agree attribute by attribute."""
    if not addon("display").native_splats_supported():
        return {"native": False}
    display, results = addon("display"), addon("results")
    run = next(r for r in reversed(scene().promptgs.runs) if r.last_snapshot)  # shown again at the end
    rng = np.random.default_rng(4)
    n = 400
    table = rng.normal(size=(n, len(INRIA_NAMES))).astype("<f4")
    table[:, INRIA_NAMES.index("opacity")] *= 4  # logits far from 0: a logit taken for an opacity shows
    path = write_ply(TMP / "agree.ply", INRIA_NAMES, table)
    bpy.ops.promptgs.load_result(filepath=str(path))
    ours = bpy.data.objects["PromptGS Gaussians"]
    before = set(bpy.data.objects)
    bpy.ops.wm.ply_import(filepath=str(path))
    [theirs] = set(bpy.data.objects) - before
    assert theirs.type == "POINTCLOUD" and theirs.data.type == ours.data.type == "GAUSSIAN_SPLAT"
    compared = []
    for attr in theirs.data.attributes:
        mine = ours.data.attributes.get(attr.name)
        assert mine is not None and mine.data_type == attr.data_type, (attr.name, attr.data_type, mine and mine.data_type)
        np.testing.assert_allclose(display.get_attribute(ours, attr.name), display.get_attribute(theirs, attr.name),
                                   rtol=1e-6, atol=1e-7, err_msg=attr.name)
        compared.append(attr.name)
    assert {"radiance:base", "scale", "rotation", "radiance:sh_14"} <= set(compared), compared
    # a live snapshot of the same Gaussians (activated values, the DC term's RGB, no higher SH)
    col = {name: table[:, i] for i, name in enumerate(INRIA_NAMES)}
    layout = expected_layout(col)
    rgb = 0.5 + SH_C0 * layout["radiance:base"][:, :3]
    results.show_gaussians(bpy.context, {"means": layout["position"].astype(np.float32),
                                         "opacity": layout["radiance:base"][:, 3].astype(np.float32),
                                         "scale": layout["scale"].astype(np.float32),
                                         "rotation": table[:, -4:], "color": np.clip(rgb, 0, 1).astype(np.float32)})
    inside = ((rgb > 0) & (rgb < 1)).all(axis=1)
    for name in ("position", "radiance:base", "scale", "rotation"):
        np.testing.assert_allclose(display.get_attribute(ours, name)[inside], display.get_attribute(theirs, name)[inside],
                                   rtol=1e-5, atol=2e-6, err_msg=f"snapshot {name}")
    assert ours.data.type == "GAUSSIAN_SPLAT" and "radiance:sh_0" not in ours.data.attributes
    bpy.data.objects.remove(theirs)
    bpy.ops.promptgs.show_run(name=run.name)  # the later checks work on the run's objects, as on the other lines
    assert results.LOSS_FIELD in bpy.data.objects
    return {"native": True, "compared": compared, "snapshot_compared": int(inside.sum())}


def check_splats_drawn() -> dict:
    display, results = addon("display"), addon("results")
    rng = np.random.default_rng(5)
    n = 300
    q = rng.normal(size=(n, 4)).astype(np.float32)
    data = {"means": rng.normal(size=(n, 3)).astype(np.float32), "opacity": rng.uniform(size=n).astype(np.float32),
            "scale": rng.uniform(0.01, 0.1, size=(n, 3)).astype(np.float32),
            "rotation": q / np.linalg.norm(q, axis=1, keepdims=True), "color": rng.uniform(size=(n, 3)).astype(np.float32)}
    obj = results.show_gaussians(bpy.context, data)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    if display.native_splats_supported():
        evaluated = obj.evaluated_get(depsgraph)
        assert obj["promptgs_mode"] == "NATIVE" and evaluated.data.type == "GAUSSIAN_SPLAT"
        assert len(evaluated.data.points) == n and not obj.modifiers["PromptGS Display"].show_viewport
        return {"mode": "NATIVE"}
    assert obj["promptgs_mode"] == "SPLATS"
    root = np.array(scene().promptgs.root.matrix_world)
    found = {}
    for inst in depsgraph.object_instances:
        if inst.is_instance and inst.parent is not None and inst.parent.original == obj:
            found[inst.persistent_id[1]] = (np.array(inst.matrix_world),
                                            [m.name for m in inst.object.data.materials if m is not None])
    assert sorted(found) == list(range(n)), len(found)
    worst = 0.0
    for i in range(0, n, 7):
        w, x, y, z = data["rotation"][i].astype(np.float64)
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        local = np.eye(4)
        local[:3, :3] = rot * (display.SPLAT_SIGMAS * data["scale"][i])
        local[:3, 3] = data["means"][i]
        worst = max(worst, float(np.abs(found[i][0] - root @ local).max()))
        assert found[i][1] == [display.SPLAT_MATERIAL], found[i][1]
    assert worst < 1e-5, worst
    shown = display.get_attribute(obj, "display_color")
    evaluated = obj.evaluated_get(depsgraph)
    if hasattr(evaluated, "evaluated_geometry"):  # 4.3+: what the splat material reads per instance
        geometry = evaluated.evaluated_geometry()
        shown = display.get_attribute(geometry.instances_pointcloud(), "display_color")
    np.testing.assert_allclose(shown[:, :3], srgb_to_linear(data["color"]), atol=1e-5)
    np.testing.assert_allclose(shown[:, 3], data["opacity"], atol=1e-6)
    return {"mode": "SPLATS", "instances": len(found), "max_matrix_error": worst}


@check
def splats_drawn_with_scale_rotation_opacity():
    """Each Gaussian drawn as itself: Blender's splats (5.3+), else an instance per Gaussian
    at its centre, turned by its rotation, 3 sigmas along its scales, in its colour and opacity."""
    settings = scene().promptgs
    settings.display_style, settings.color_by = "SPLATS", "color"
    try:
        return check_splats_drawn()
    finally:
        settings.display_style = "AUTO"


@check
def million_points_update():
    display = addon("display")
    obj = bpy.data.objects["PromptGS Gaussians"]
    n = 1_000_000
    rng = np.random.default_rng(0)
    data = {"means": rng.normal(size=(n, 3)).astype(np.float32),
            "opacity": rng.uniform(size=n).astype(np.float32),
            "scale": rng.uniform(size=(n, 3)).astype(np.float32),
            "rotation": np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
            "color": rng.uniform(size=(n, 3)).astype(np.float32),
            "score": rng.uniform(size=n).astype(np.float32), "error": rng.uniform(size=n).astype(np.float32)}
    start = time.time()
    addon("results").show_gaussians(bpy.context, data)
    seconds = time.time() - start
    assert display.point_count(obj) == n
    # above SPLATS_UP_TO the fallback draws points (4.2–5.2); Blender's own splats from 5.3 on
    assert obj["promptgs_mode"] == ("NATIVE" if display.native_splats_supported() else "POINTS"), obj["promptgs_mode"]
    start = time.time()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    depsgraph.update()
    evaluated = obj.evaluated_get(depsgraph)
    draw_seconds = time.time() - start
    assert evaluated.data is not None
    assert draw_seconds < 5.0, f"evaluating the display of 1M points took {draw_seconds:.1f} s (spheres?)"
    # points are drawn as plain points now; a small set goes back to spheres
    small = {k: v[:1000] for k, v in data.items()}
    addon("results").show_gaussians(bpy.context, small)
    return {"update_seconds_1M": round(seconds, 2), "evaluate_seconds_1M": round(draw_seconds, 2)}


def shown_vertices(obj) -> int:
    """Vertices of what the display modifier makes of a points object (spheres are a mesh)."""
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    if hasattr(evaluated, "evaluated_geometry"):  # 4.3+: any object type
        geometry = evaluated.evaluated_geometry()  # the mesh lives as long as this set
        return len(geometry.mesh.vertices) if geometry.mesh is not None else 0
    return len(evaluated.data.vertices)  # 4.2: the points are a mesh there


@check
def display_settings_apply():
    obj = bpy.data.objects["PromptGS Gaussians"]
    display = addon("display")
    mod = obj.modifiers["PromptGS Display"]
    settings = scene().promptgs
    settings.display_style = "POINTS"
    assert not display.modifier_input(mod, "Spheres")
    settings.display_style = "SPHERES"
    assert display.modifier_input(mod, "Spheres")
    settings.point_radius = 0.0123
    assert abs(display.modifier_input(mod, "Radius") - 0.0123) < 1e-6
    settings.color_by = "opacity"
    assert obj["promptgs_color_by"] == "opacity"
    opacity = display.get_attribute(obj, "radiance:base")[:, 3]
    bins = display.get_attribute(obj, "display_bin")
    assert bins[np.argmax(opacity)] == display.N_BINS - 1 and bins[np.argmin(opacity)] == 0
    settings.color_by = "color"
    rgb = display.get_attribute(obj, "display_color")[:, :3]
    dc = display.get_attribute(obj, "radiance:base")[:, :3]
    np.testing.assert_allclose(rgb, srgb_to_linear(np.clip(0.5 + SH_C0 * dc, 0, 1)), atol=1e-5)
    settings.display_style = "AUTO"  # back to splats, in the trained colours
    # the loss field: a quarter-voxel radius and only the voxels above the cutoff
    field = bpy.data.objects["PromptGS Loss Field"]
    fmod = field.modifiers["PromptGS Display"]
    settings.field_cutoff = 0.75
    assert abs(display.modifier_input(fmod, "Min Value") - 0.75) < 1e-6
    value = display.get_attribute(field, "display_value")
    bins = display.get_attribute(field, "display_bin")
    assert bins.min() >= display.N_BINS  # the loss field's own palette
    n_vertices_per_sphere = 12  # ico sphere, 1 subdivision
    assert shown_vertices(field) == n_vertices_per_sphere * int((value >= 0.75).sum()) > 0
    settings.field_cutoff = 0.5
    return {"field_shown": int((value >= 0.75).sum()), "field_total": len(value)}


def ply_body(path: Path) -> tuple[list, bytes]:
    """The property lines and the bytes after the header of a PLY."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return [line for line in data[:end].decode().splitlines() if line.startswith(("property", "element"))], data[end:]


@check
def export_round_trip_bit_for_bit():
    """A PLY of another trainer's layout (gsplat/Inria: degree 0, zero normals), loaded and
    exported unchanged, is the same file: every property bit for bit, in the same order."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    rng = np.random.default_rng(6)
    table = rng.normal(size=(700, len(names))).astype("<f4")
    table[:, 3:6] = 0.0
    table[:, names.index("opacity")] *= 6.0
    table[:, 10:13] -= 4.0
    source = write_ply(TMP / "gsplat_like.ply", names, table)
    root = scene().promptgs.root
    root_before = root.matrix_world.copy()
    root.matrix_world = Matrix.Translation((0.3, -1.0, 2.0)) @ Euler((0.2, 0.5, -0.3)).to_matrix().to_4x4() @ root.matrix_world
    bpy.ops.promptgs.load_result(filepath=str(source))
    out = TMP / "gsplat_like_exported.ply"
    assert bpy.ops.promptgs.export_gaussians(filepath=str(out), start_from=False) == {"FINISHED"}
    assert ply_body(out) == ply_body(source), "the exported PLY differs from the one loaded"
    # the Gaussians object itself turned: written turned, in dataset coordinates
    obj = bpy.data.objects["PromptGS Gaussians"]
    obj.matrix_basis = Matrix.Rotation(0.4, 4, "Z")
    bpy.context.view_layer.update()
    turned = TMP / "gsplat_like_turned.ply"
    bpy.ops.promptgs.export_gaussians(filepath=str(turned), start_from=False)
    moved = addon("plyio").read_vertices(turned)
    expected = table[:, :3].astype(np.float64) @ np.array(Matrix.Rotation(0.4, 3, "Z")).T
    np.testing.assert_allclose(np.stack([moved["x"], moved["y"], moved["z"]], 1), expected, atol=1e-5)
    obj.matrix_basis.identity()
    root.matrix_world = root_before
    return {"source": str(source), "exported": str(out)}


@check
def export_after_deleting_in_box():
    """Splats deleted in a box are gone from the export, the others are written as loaded;
    the file becomes the next training's start (job key "init"); Blender 5.3 reads it back."""
    display, plyio = addon("display"), addon("plyio")
    n = 600
    table, _, obj = load_random_ply("to_crop.ply", 7, n)
    inside = (np.abs(table[:, :3]) < 0.6).all(axis=1)
    delete_selected_points(obj, inside)
    assert display.point_count(obj) == n - inside.sum()
    out = TMP / "cropped.ply"
    assert bpy.ops.promptgs.export_gaussians(filepath=str(out)) == {"FINISHED"}
    kept = plyio.read_vertices(out)
    assert len(kept) == n - inside.sum() and list(kept.dtype.names) == INRIA_NAMES
    for i, name in enumerate(INRIA_NAMES):
        np.testing.assert_array_equal(kept[name], table[~inside, i], err_msg=name)
    assert scene().promptgs.init_ply == str(out)
    job = addon("training").build_job(bpy.context, TMP / "job_init")
    assert job["init"] == str(out), job.get("init")
    info = {"deleted": int(inside.sum()), "kept": len(kept)}
    if display.native_splats_supported():  # Blender's own importer reads what we wrote
        before = set(bpy.data.objects)
        bpy.ops.wm.ply_import(filepath=str(out))
        [theirs] = set(bpy.data.objects) - before
        assert len(theirs.data.points) == len(kept) and theirs.data.type == "GAUSSIAN_SPLAT"
        for name in ("position", "radiance:base", "scale", "rotation", "radiance:sh_14"):
            np.testing.assert_allclose(display.get_attribute(theirs, name), display.get_attribute(obj, name),
                                       rtol=1e-6, atol=1e-7, err_msg=name)
        # and exporting Blender's own object works too (its ply_export writes no vertices)
        again = TMP / "blender_object.ply"
        addon("results").export_gaussians(bpy.context, again, theirs)
        assert len(plyio.read_vertices(again)) == len(kept)
        bpy.data.objects.remove(theirs)
        info["blender_reads_it"] = True
    # a crop by a modifier of the user's own applies too (the display modifier does not)
    group = bpy.data.node_groups.new("Crop x>0", "GeometryNodeTree")
    group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    g_in, g_out = group.nodes.new("NodeGroupInput"), group.nodes.new("NodeGroupOutput")
    position, xyz = group.nodes.new("GeometryNodeInputPosition"), group.nodes.new("ShaderNodeSeparateXYZ")
    compare, delete = group.nodes.new("FunctionNodeCompare"), group.nodes.new("GeometryNodeDeleteGeometry")
    compare.data_type, compare.operation, delete.domain = "FLOAT", "GREATER_THAN", "POINT"
    group.links.new(position.outputs[0], xyz.inputs[0])
    group.links.new(xyz.outputs["X"], display.socket(compare.inputs, "A"))
    group.links.new(g_in.outputs[0], display.socket(delete.inputs, "Geometry"))
    group.links.new(compare.outputs[0], display.socket(delete.inputs, "Selection"))
    group.links.new(delete.outputs[0], g_out.inputs[0])
    crop = obj.modifiers.new("Crop", "NODES")
    crop.node_group = group
    cropped = TMP / "cropped_by_modifier.ply"
    bpy.ops.promptgs.export_gaussians(filepath=str(cropped), start_from=False)
    obj.modifiers.remove(crop)
    left = plyio.read_vertices(cropped)
    assert len(left) == int(((table[:, 0] <= 0) & ~inside).sum()) and left["x"].max() <= 0, len(left)
    info["cropped_by_modifier"] = len(left)
    return info


def box_of(obj, root) -> dict:
    """The prompt-file box the add-on sends for a cube (the job file's conversion)."""
    return addon("coords").prompt_box(np.array(root.matrix_world.inverted() @ obj.matrix_world), obj.empty_display_size)


@check
def propose_accept_and_reject():
    """Propose Prompts on a run: cubes in the Proposed state (not trained), one accepted
    becomes the proposed box in the job file, one deleted is gone; errors are one line."""
    proposals, prompts_module, display = addon("proposals"), addon("prompts"), addon("display")
    root = scene().promptgs.root
    run = TMP / "propose_run"
    (run / "snapshots").mkdir(parents=True)
    (run / "cfg.json").write_text("{}")
    np.savez(run / "snapshots" / "step_000010.npz", means=np.zeros((1, 3), np.float32))
    scene().promptgs.preview_run = str(run)
    trained_before = addon("training").build_job(bpy.context, TMP / "job_propose")["prompts"]["prompts"]
    fake_trainer("ok")
    bpy.ops.promptgs.propose()
    assert jobs().propose_status == "RUNNING", (jobs().propose_status, jobs().propose_message)
    run_until_idle(60)
    assert jobs().propose_status == "DONE", jobs().propose_message
    assert jobs().propose_message.startswith("2 proposals from snapshot step_000010, 1 of confidence"), jobs().propose_message
    argv = json.loads((run / "propose" / "argv.json").read_text())
    argv = argv[argv.index("propose"):]
    assert argv[:4] == ["propose", str(run), "--out", str(run / "propose" / "proposals.json")], argv
    assert argv[argv.index("--snapshot") + 1] == str(run / "snapshots" / "step_000010.npz"), argv
    written = json.loads((run / "propose" / "proposals.json").read_text())["prompts"]
    cubes = proposals.proposed_objects(scene())
    assert [c["promptgs_confidence"] for c in cubes] == pytest_approx([0.82, 0.21])
    assert cubes[0]["promptgs_views"] == "24/31 views"
    assert cubes[0].users_collection[0].name == "PromptGS Proposed" and cubes[0].empty_display_type == "CUBE"
    for cube, entry in zip(cubes, written):  # placed through the dataset root, exactly
        box = box_of(cube, root)
        np.testing.assert_allclose(box["center"], entry["center"], atol=1e-5)
        np.testing.assert_allclose(box["size"], entry["size"], atol=1e-5)
        assert abs(abs(np.dot(box["rotation_wxyz"], entry["rotation_wxyz"])) - 1.0) < 1e-6
    # proposed cubes are not trained until accepted
    assert addon("training").build_job(bpy.context, TMP / "job_propose")["prompts"]["prompts"] == trained_before
    markers = bpy.data.objects["PromptGS Proposal Points"]
    np.testing.assert_allclose(display.get_attribute(markers, "confidence"), [0.82, 0.21], atol=1e-6)
    np.testing.assert_allclose(display.get_attribute(markers, "position"), [e["center"] for e in written], atol=1e-5)
    log = []
    addon("ui").PROMPTGS_PT_prompts.draw(SimpleNamespace(layout=StubLayout(log)), bpy.context)
    assert any(line.startswith("0.82  24/31 views") for line in log), log
    # accept the first (the user made it a little larger first), delete the second
    accepted, rejected = cubes
    accepted.scale = accepted.scale * 1.5
    bpy.context.view_layer.update()
    expected = box_of(accepted, root)
    bpy.ops.promptgs.accept_proposal(name=accepted.name)
    rejected_name = rejected.name
    bpy.ops.promptgs.remove_prompt(name=rejected_name)
    assert proposals.proposed_objects(scene()) == [] and bpy.data.objects.get(rejected_name) is None
    assert accepted in prompts_module.prompt_objects(scene()) and accepted.get("promptgs_proposed") is None
    assert bpy.data.objects.get("PromptGS Proposal Points") is None  # no proposal left to mark
    trained = addon("training").build_job(bpy.context, TMP / "job_propose")["prompts"]["prompts"]
    assert len(trained) == len(trained_before) + 1
    new = next(b for b in trained if b not in trained_before)
    np.testing.assert_allclose(new["center"], written[0]["center"], atol=1e-5)
    np.testing.assert_allclose(new["size"], np.array(written[0]["size"]) * 1.5, atol=1e-5)
    np.testing.assert_allclose(new["size"], expected["size"], atol=1e-6)
    assert new["weight"] == 1.0
    bpy.data.objects.remove(accepted)
    # a trainer error is one line in the panel; a folder that is not a run is refused
    fake_trainer("crash")
    bpy.ops.promptgs.propose()
    run_until_idle(60)
    assert jobs().propose_status == "ERROR", jobs().propose_message
    assert jobs().propose_message == f"promptgs: error: {run}: the run has no point_cloud.ply yet", jobs().propose_message
    scene().promptgs.preview_run = str(TMP)
    try:
        bpy.ops.promptgs.propose()
        raise AssertionError("propose did not fail")
    except RuntimeError:
        pass
    assert "not a PromptGS run folder" in jobs().propose_message, jobs().propose_message
    scene().promptgs.preview_run = ""
    return {"message": jobs().propose_message}


def edges_in_box_frame(edges: np.ndarray, box: dict, root) -> np.ndarray:
    """Edge points (Blender world) in the frame of a prompt-file box (dataset coordinates)."""
    to_dataset = np.array(root.matrix_world.inverted()) if root is not None else np.eye(4)
    points = edges @ to_dataset[:3, :3].T + to_dataset[:3, 3]
    rotation = np.array(addon("coords").quat_to_rotmat(box["rotation_wxyz"]))
    return (points - np.array(box["center"])) @ rotation


def assert_cube_edges(edges: np.ndarray, box: dict, root) -> None:
    """12 distinct edges of the box: every end at a corner, each edge along one box axis."""
    assert edges.shape == (24, 3), edges.shape
    local = edges_in_box_frame(edges.astype(np.float64), box, root)
    half = np.array(box["size"]) / 2.0
    np.testing.assert_allclose(np.abs(local), np.broadcast_to(half, local.shape), rtol=1e-4, atol=1e-5)
    signs = np.sign(local).reshape(12, 2, 3)
    assert all((a != b).sum() == 1 for a, b in signs), signs  # one axis per edge
    assert len({tuple(sorted(map(tuple, pair))) for pair in signs}) == 12  # all 12 edges
    lengths = np.sort(np.linalg.norm(local[1::2] - local[0::2], axis=1))
    np.testing.assert_allclose(lengths, np.sort(np.repeat(box["size"], 4)), rtol=1e-4)


def proposal_entries() -> list[dict]:
    from fake_trainer import proposal_file
    return json.loads(proposal_file())["prompts"]


@check
def proposed_cubes_drawn_in_their_colour():
    """The viewport overlay's lines: each proposed cube's 12 edges (rotated, scaled), none
    for an accepted prompt or a hidden cube; accepting a cube takes it off the overlay."""
    proposals, overlay = addon("proposals"), addon("overlay")
    root = scene().promptgs.root
    assert overlay.handler() is not None, "no draw handler after the add-on was enabled"
    cubes = proposals.show(bpy.context, proposal_entries())
    cubes[0].scale = (1.0, 2.0, 0.5)  # the user stretched it: a rotated, non-uniform box
    cubes[1].empty_display_size = 1.3
    bpy.ops.promptgs.add_prompt()
    prompt = bpy.context.active_object
    prompt.location, prompt.scale = (0.4, 0.1, -0.2), (0.1, 0.1, 0.1)
    for obj in bpy.context.selected_objects:
        obj.select_set(False)
    bpy.context.view_layer.update()
    plain, selected = overlay.proposed_edges(bpy.context)
    assert plain.shape == (48, 3) and selected.shape == (0, 3), (plain.shape, selected.shape)
    for cube, edges in zip(cubes, (plain[:24], plain[24:])):
        assert_cube_edges(edges, box_of(cube, root), root)
    prompt_corners = overlay.cube_edges(prompt.matrix_world, prompt.empty_display_size)
    assert not np.isin(prompt_corners.round(5), plain.round(5)).all(axis=1).any()  # the prompt is not drawn
    cubes[1].select_set(True)
    plain, selected = overlay.proposed_edges(bpy.context)
    assert plain.shape == selected.shape == (24, 3)
    assert_cube_edges(selected, box_of(cubes[1], root), root)
    cubes[1].hide_set(True)
    plain, selected = overlay.proposed_edges(bpy.context)
    assert plain.shape == (24, 3) and selected.shape == (0, 3)
    cubes[1].hide_set(False)
    cubes[1].select_set(True)  # hiding deselected it
    proposals.accept(bpy.context, cubes[0])
    plain, selected = overlay.proposed_edges(bpy.context)
    assert plain.shape == (0, 3) and selected.shape == (24, 3), "the accepted cube is still drawn"
    assert_cube_edges(selected, box_of(cubes[1], root), root)
    for obj in (cubes[0], cubes[1], prompt):
        bpy.data.objects.remove(obj)
    proposals.update_markers(bpy.context)
    assert overlay.proposed_edges(bpy.context)[0].shape == (0, 3)
    return {"edges_per_cube": 12}


def proposed_names() -> list[str]:
    return sorted(o.name for o in addon("proposals").proposed_objects(scene()))


@check
def training_proposals_become_proposed_cubes():
    """A run started with Propose While Training: its RUN/proposals.json becomes proposed
    cubes while it trains (once, though the file is written three times); a second run
    replaces them and leaves out the one the user accepted."""
    proposals, training = addon("proposals"), addon("training")
    root = scene().promptgs.root
    fake_trainer("ok")
    settings = scene().promptgs
    settings.preset, settings.iterations, settings.propose_prompts = "CUSTOM", 30, True
    bpy.ops.promptgs.train()
    out = Path(state().folder)
    first_job = json.loads(Path(state().job_path).read_text())
    assert first_job["propose_prompts"] is True
    counts, seen_running = set(), False
    deadline = time.time() + 60
    while training.drain_and_apply(bpy.context) and time.time() < deadline:
        counts.add(len(proposals.proposed_objects(scene())))
        seen_running |= bool(proposals.proposed_objects(scene())) and state().status == "RUNNING"
        time.sleep(0.02)
    assert state().status == "DONE", (state().status, state().message)
    assert seen_running, "the proposals appeared only after the run"
    assert counts <= {0, 2}, counts  # never twice the cubes
    cubes = proposals.proposed_objects(scene())
    written = json.loads((out / "proposals.json").read_text())
    assert len(cubes) == 2 and written["trained_as"], (len(cubes), written.keys())
    assert [c["promptgs_confidence"] for c in cubes] == pytest_approx([0.82, 0.21])
    for cube, entry in zip(cubes, written["prompts"]):
        box = box_of(cube, root)
        np.testing.assert_allclose(box["center"], entry["center"], atol=1e-5)
        np.testing.assert_allclose(box["size"], entry["size"], atol=1e-5)
    assert jobs().propose_status == "DONE"
    assert jobs().propose_message == ("2 proposals from training step 15, 1 of confidence ≥ 0.3 "
                                       "(the run trains 1 box around them)"), jobs().propose_message
    names_after_first = proposed_names()
    training.drain_and_apply(bpy.context)
    assert proposed_names() == names_after_first
    # accept the first, train again: the same proposals come back, the accepted one not twice
    accepted = proposals.accept(bpy.context, cubes[0])
    bpy.ops.promptgs.train()
    second = Path(state().folder)
    run_until_idle(60)
    assert second != out and state().status == "DONE", (state().status, state().message)
    job = json.loads(Path(state().job_path).read_text())
    assert len(job["prompts"]["prompts"]) == len(first_job["prompts"]["prompts"]) + 1  # the accepted cube is trained
    cubes = proposals.proposed_objects(scene())
    assert len(cubes) == 1 and abs(cubes[0]["promptgs_confidence"] - 0.21) < 1e-6, [c.name for c in cubes]
    assert jobs().propose_message.startswith("1 proposals from training step 15, 0 of confidence ≥ 0.3, "
                                              "1 already inside prompts"), jobs().propose_message
    assert len(addon("overlay").proposed_edges(bpy.context)[0]) + len(addon("overlay").proposed_edges(bpy.context)[1]) == 24
    # a run without proposing leaves the proposed cubes as they are
    settings.propose_prompts = False
    bpy.ops.promptgs.train()
    run_until_idle(60)
    assert not (Path(state().folder) / "proposals.json").exists()
    assert len(proposals.proposed_objects(scene())) == 1
    for obj in proposals.proposed_objects(scene()) + [accepted]:
        bpy.data.objects.remove(obj)
    proposals.update_markers(bpy.context)
    settings.preset = "STANDARD"
    return {"message": jobs().propose_message}


@check
def panels_draw_in_every_state():
    labels = {}
    record = state()
    for status in ("IDLE", "RUNNING", "ERROR", "DONE", "INTERRUPTED"):
        jobs().sfm_status = jobs().preview_status = jobs().propose_status = jobs().setup_status = \
            status if status in ("IDLE", "RUNNING", "ERROR", "DONE") else "IDLE"
        if status != "IDLE":
            record.status = status
        record.error_lines = "line one\nline two"
        labels[status] = panel_lines() + prefs_lines()  # the panels, and the preferences with Set Up
    assert "line two" in labels["ERROR"]
    return {"labels": labels["ERROR"][:12]}


@check
def runs_need_no_modal_operator():
    """Training is followed by a timer: no operator of the add-on is modal (notify aside,
    which lives for one timer event after a job), no window has a modal handler while a
    run goes (Blender's autosave waits while one has: wm_files.cc, wm_autosave_timer), an
    Esc changes nothing, and the file saves while it trains."""
    training, operators = addon("training"), addon("operators")
    fake_trainer("slow")
    window = bpy.context.window_manager.windows[0]
    with bpy.context.temp_override(window=window):
        assert bpy.ops.promptgs.train("INVOKE_DEFAULT") == {"FINISHED"}
    modal = [cls.bl_idname for cls in operators.CLASSES if hasattr(cls, "modal") and cls.bl_idname != "promptgs.notify"]
    assert not modal, modal
    drain_until(lambda: state().snapshot_step > 0, what="a snapshot")
    assert bpy.app.timers.is_registered(training._timer), "the run is not followed by a timer"
    handlers = {w.as_pointer(): [op.bl_idname for op in w.modal_operators] for w in bpy.context.window_manager.windows}
    assert not any(handlers.values()), handlers
    # Esc: nothing of the add-on listens to keys (no modal operator, no key map item)
    keymaps = bpy.context.window_manager.keyconfigs.addon
    bound = [item.idname for km in (keymaps.keymaps if keymaps else []) for item in km.keymap_items
             if item.idname.startswith("promptgs.")]
    assert not bound, bound
    esc = "simulated" if bpy.app.use_event_simulate else "no event simulation in background"
    if bpy.app.use_event_simulate:  # a Blender binary started with --enable-event-simulate
        window.event_simulate("ESC", "PRESS")
        window.event_simulate("ESC", "RELEASE")
    step = state().snapshot_step
    drain_until(lambda: state().snapshot_step > step, what="the next snapshot after Esc")
    assert state().status == "RUNNING" and not live_run().progress.cancel_requested, (state().status, state().message)
    # the file saves while the run goes; it records the run
    saved = TMP / "during_run.blend"
    assert bpy.ops.wm.save_as_mainfile(filepath=str(saved), copy=True) == {"FINISHED"}
    assert saved.is_file() and saved.stat().st_size > 10_000
    name = state().name
    bpy.ops.promptgs.cancel()
    run_until_idle(60)
    assert state().status == "CANCELLED", (state().status, state().message)
    return {"esc": esc, "saved_bytes": saved.stat().st_size, "run": name}


@check
def second_run_keeps_the_first_and_runs_switch():
    """A new run keeps the shown run's objects (hidden, under its name) unless Replace
    Shown Run; the eye in the runs list shows one run or the other."""
    training, settings = addon("training"), scene().promptgs
    fake_trainer("ok")
    settings.preset, settings.replace_shown = "CUSTOM", False
    settings.iterations = 30
    bpy.ops.promptgs.train()
    run_until_idle(60)
    first = state().name
    first_obj = bpy.data.objects[addon("results").GAUSSIANS]
    assert shown_gaussians()[1] == 400
    settings.iterations = 20
    bpy.ops.promptgs.train()
    run_until_idle(60)
    second = state().name
    assert second != first and settings.shown_run == second
    kept = bpy.data.objects[training.parked_name(addon("results").GAUSSIANS, first)]
    assert kept == first_obj and addon("display").point_count(kept) == 400  # untouched by the second run
    assert kept.users_collection[0].hide_viewport and kept.users_collection[0].name == f"PromptGS {first}"
    assert shown_gaussians()[1] == 300 and bpy.data.objects[addon("results").GAUSSIANS] != first_obj
    bpy.ops.promptgs.show_run(name=first)
    assert settings.shown_run == first and shown_gaussians()[1] == 400
    assert addon("display").point_count(bpy.data.objects[training.parked_name(addon("results").GAUSSIANS, second)]) == 300
    assert f"[promptgs.show_run]" in panel_lines(addon("ui").PROMPTGS_PT_runs)
    # Replace Shown Run: the third run takes the first run's objects over
    settings.replace_shown, settings.iterations = True, 10
    bpy.ops.promptgs.train()
    run_until_idle(60)
    third = state().name
    assert bpy.data.objects[addon("results").GAUSSIANS] == first_obj and shown_gaussians()[1] == 200
    assert bpy.data.objects.get(training.parked_name(addon("results").GAUSSIANS, first)) is None
    bpy.ops.promptgs.show_run(name=first)  # its objects were replaced: loaded again from its folder
    assert shown_gaussians() == (settings.runs[first].last_snapshot, 400)
    for name in (second, third):
        bpy.ops.promptgs.remove_run(name=name)
    assert [r.name for r in settings.runs if r.name in (second, third)] == []
    assert bpy.data.objects.get(training.parked_name(addon("results").GAUSSIANS, second)) is None
    settings.replace_shown = False
    return {"runs": [r.name for r in settings.runs]}


@check
def undo_after_a_snapshot_leaves_a_consistent_scene():
    """Runs are outside undo: Ctrl+Z takes back the user's edit, and the run's record and
    the shown objects are what the run is now, while it trains, after it ended, and when
    the undo goes back to before the run started."""
    training, results = addon("training"), addon("results")
    fake_trainer("slow")
    bpy.ops.promptgs.add_prompt()
    cube = bpy.context.active_object.name
    bpy.data.objects[cube].location = (0.0, 0.0, 0.0)
    bpy.ops.ed.undo_push(message="before training")
    bpy.ops.promptgs.train()
    name = state().name
    drain_until(lambda: state().snapshot_step >= 10, what="a first snapshot")
    bpy.ops.ed.undo_push(message="before the edit")
    bpy.data.objects[cube].location = (0.5, 0.0, 0.0)
    bpy.ops.ed.undo_push(message="moved the cube")
    at_edit = state().snapshot_step
    drain_until(lambda: state().snapshot_step >= at_edit + 20, what="newer snapshots")

    def consistent(expect_status: str) -> dict:
        record = scene().promptgs.runs[name]
        entry = training._live.get(record.folder) or training._ended[record.folder]
        progress = entry.progress
        assert record.status == expect_status == progress.status, (record.status, progress.status)
        assert record.snapshot_step == progress.snapshot_step and record.last_snapshot == progress.last_snapshot
        shown = training.shown_record(scene())
        path, n = shown_gaussians()
        assert path == training.target_of(shown)[0] and n == npz_count(path), (path, n, shown.name)
        field = bpy.data.objects[results.LOSS_FIELD]
        assert addon("display").point_count(field) == npz_count(path, "field_centers")
        assert bpy.data.objects[results.GAUSSIANS].get("promptgs_run") == shown.name
        return {"step": record.snapshot_step, "shown": shown.name}

    bpy.ops.ed.undo()  # back to before the edit: the cube where it was, the run as it is now
    assert tuple(bpy.data.objects[cube].location) == pytest_approx((0.0, 0.0, 0.0))
    during = consistent("RUNNING")
    assert during["shown"] == name and during["step"] >= at_edit + 20
    bpy.ops.ed.redo()
    assert tuple(bpy.data.objects[cube].location) == pytest_approx((0.5, 0.0, 0.0))
    consistent("RUNNING")
    bpy.ops.promptgs.cancel()
    run_until_idle(60)
    bpy.ops.ed.undo_push(message="after the run")
    bpy.ops.ed.undo()
    bpy.ops.ed.undo()  # the record of that step said RUNNING, at an older snapshot
    after = consistent("CANCELLED")
    bpy.ops.ed.undo()  # before the run started: its record comes back
    assert scene().promptgs.runs.get(name) is not None, [r.name for r in scene().promptgs.runs]
    before = consistent("CANCELLED")
    bpy.data.objects.remove(bpy.data.objects[cube])
    bpy.ops.promptgs.show_run(name=name)
    return {"during": during, "after": after, "before_start": before}


@check
def the_panel_tells_what_went_wrong():
    """The panel shows the trainer's last output line; every failure is one line with the
    log's path (a crash at start-up, an unreadable snapshot); the end of a run is a
    report in the status bar whether or not the panel is open."""
    training = addon("training")
    settings = scene().promptgs
    settings.preset, settings.iterations = "CUSTOM", 30
    fake_trainer("badsnapshot")
    bpy.ops.promptgs.train()
    run_until_idle(60)
    record = state()
    assert record.status == "DONE", (record.status, record.message)
    assert record.warning.startswith("step_000030.npz: cannot read the snapshot") and record.log_path in record.warning, record.warning
    assert shown_gaussians()[0] == str(Path(record.folder) / "snapshots" / "step_000020.npz")  # the last good one
    lines = panel_lines(addon("ui").PROMPTGS_PT_train)
    assert record.warning in lines and f"Log: {record.log_path}" in lines, lines
    assert record.last_output.startswith("fake trainer: "), record.last_output  # its newest output line
    assert record.last_output in lines, lines
    assert training.notices[-1] == ("INFO", f"PromptGS {record.name}: Done: PSNR 20.00 dB"), training.notices[-1]
    fake_trainer("crash")
    bpy.ops.promptgs.train()
    run_until_idle(60)
    record = state()
    assert record.status == "ERROR" and record.message == "RuntimeError: the fake trainer crashed", record.message
    lines = panel_lines(addon("ui").PROMPTGS_PT_train)
    assert record.message in lines and f"Log: {record.log_path}" in lines and Path(record.log_path).is_file(), lines
    assert training.notices[-1] == ("ERROR", f"PromptGS {record.name}: RuntimeError: the fake trainer crashed")
    return {"warning": state().warning, "notice": list(training.notices[-1])}


@check
def buttons_grey_out_when_they_cannot_run():
    """poll(): what cannot run now is greyed out (and refused from a script)."""
    ops = bpy.ops.promptgs
    settings = scene().promptgs
    fake_trainer("slow")
    idle = {"train": ops.train.poll(), "cancel": ops.cancel.poll(), "cancel_reconstruct": ops.cancel_reconstruct.poll()}
    assert idle == {"train": True, "cancel": False, "cancel_reconstruct": False}, idle
    bpy.ops.promptgs.train()
    drain_until(lambda: state().status == "RUNNING", what="the run to start")
    busy = {"train": ops.train.poll(), "cancel": ops.cancel.poll(), "resume": ops.resume.poll()}
    assert busy == {"train": False, "cancel": True, "resume": False}, busy
    bpy.ops.promptgs.cancel()
    run_until_idle(60)
    assert ops.train.poll() and not ops.cancel.poll()
    root, dataset, camera = settings.root, settings.dataset, scene().camera
    settings.root, settings.dataset, scene().camera = None, "", None
    try:
        no_dataset = ops.train.poll()
        no_camera = ops.render_preview.poll()
    finally:
        settings.root, settings.dataset, scene().camera = root, dataset, camera
    assert not no_dataset and not no_camera, (no_dataset, no_camera)
    assert not ops.accept_proposal.poll()  # no proposed cube
    # Cancel asks first when more than a minute since the last checkpoint would be trained
    # again (its dialog is Blender's invoke_confirm, with an icon it offers)
    record = SimpleNamespace(step=1500, elapsed_s=300.0, checkpoint_every=1000, folder="")
    assert addon("training").unsaved_seconds(record) == 100.0 > addon("training").CONFIRM_AFTER_S
    record.step = 2100
    assert addon("training").unsaved_seconds(record) < addon("training").CONFIRM_AFTER_S
    icons = bpy.types.WindowManager.bl_rna.functions["invoke_confirm"].parameters["icon"].enum_items.keys()
    assert {"WARNING", "QUESTION"} <= set(icons), icons
    return {"idle": idle, "busy": busy}


@check
def a_picked_photo_means_its_folder():
    reconstruct = addon("reconstruct")
    photos = Path(SCENE["path"]) / "images"
    photo = sorted(photos.iterdir())[0]
    video = TMP / "clip.MP4"
    video.write_bytes(b"\0" * 16)
    assert reconstruct.source_of(photo, photos.parent) == photos
    assert reconstruct.source_of(video, TMP) == video
    assert reconstruct.source_of(None, photos) == photos
    fake_trainer("crash")  # only what it is given matters here
    bpy.ops.promptgs.reconstruct(filepath=str(photo), directory=str(photos))
    assert Path(jobs().sfm_out).name.startswith("images-sfm-"), jobs().sfm_out
    run_until_idle(60)
    return {"sfm_out": jobs().sfm_out}


@check
def find_and_test_run_in_the_background():
    """Find and Test return at once (the UI does not wait for the interpreters they run)
    and the answer arrives through the follower."""
    training = addon("training")
    slow = config["slow_python"]  # the test's Python, after a 2 s sleep
    prefs().python = slow
    start = time.time()
    bpy.ops.promptgs.test_trainer()
    test_seconds = time.time() - start
    assert jobs().probe_status == "RUNNING" and test_seconds < 1.0, (jobs().probe_status, test_seconds)
    run_until_idle(120)
    assert jobs().probe_status == "DONE" and prefs().probe_result.startswith("promptgs_engine "), prefs().probe_result
    assert "backends: cpu" in prefs().probe_result, prefs().probe_result
    prefs().python = ""
    os.environ["PROMPTGS_PYTHON"] = slow
    start = time.time()
    bpy.ops.promptgs.find_trainer()
    find_seconds = time.time() - start
    assert jobs().find_status == "RUNNING" and find_seconds < 1.0, (jobs().find_status, find_seconds)
    run_until_idle(120)
    del os.environ["PROMPTGS_PYTHON"]
    assert jobs().find_status == "DONE" and prefs().python == slow, (jobs().find_message, prefs().python)
    return {"test_seconds": round(test_seconds, 3), "find_seconds": round(find_seconds, 3), "probe": prefs().probe_result}


@check
def set_up_trainer_says_what_it_needs():
    """Set Up Trainer refuses what cannot work, in one line: no engine source, a folder
    that is not a checkout, no C++ compiler to build it (PATH without one). Its default
    folder is in the extension's user folder."""
    training, trainer = addon("training"), addon("trainer")
    p = prefs()
    p.setup_folder, p.setup_base, p.setup_source = "", sys.executable, ""
    try:
        bpy.ops.promptgs.setup_trainer()
        raise AssertionError("set-up did not fail")
    except RuntimeError:
        pass
    assert jobs().setup_status == "ERROR" and jobs().setup_message.startswith("Choose the engine source"), jobs().setup_message
    p.setup_source = str(TMP)
    try:
        bpy.ops.promptgs.setup_trainer()
    except RuntimeError:
        pass
    assert jobs().setup_message == f"{TMP}: no pyproject.toml (not a PromptGS checkout)", jobs().setup_message
    default = training.setup_folder(bpy.context)
    assert default == Path(bpy.utils.extension_path_user(addon("training").__package__, path="trainer-env"))
    assert str(default).startswith(str(Path(config["home"]))), default  # the user's profile
    empty_path = TMP / "path_without_compilers"
    empty_path.mkdir(exist_ok=True)
    p.setup_source, p.setup_folder = config["repo"], str(TMP / "trainer-env")
    saved = {key: os.environ.get(key) for key in ("PATH", "CXX")}
    os.environ["PATH"], os.environ["CXX"] = str(empty_path), ""
    try:
        bpy.ops.promptgs.setup_trainer()
        assert jobs().setup_status == "RUNNING"
        run_until_idle(60)
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
    assert jobs().setup_status == "ERROR", (jobs().setup_status, jobs().setup_message)
    assert jobs().setup_message.startswith("No C++ compiler found"), jobs().setup_message
    assert not (TMP / "trainer-env" / "pyvenv.cfg").exists()  # nothing made
    assert training.notices[-1][0] == "ERROR" and "No C++ compiler found" in training.notices[-1][1]
    assert trainer.venv_python(TMP / "v") == TMP / "v" / "bin" / "python"
    return {"message": jobs().setup_message, "default_folder": str(default)}


@check
def cancel_ends_every_process_of_the_trainer():
    """Cancel ends the trainer and the processes below it, also those in their own
    sessions that ignore SIGINT (and SIGTERM), as torchrun's ranks are, within the cancel's
    bounded wait."""
    training = addon("training")
    fake_trainer("tree")
    bpy.ops.promptgs.train()
    folder = Path(state().folder)
    drain_until(lambda: (folder / "tree.json").is_file() and state().status == "RUNNING", what="the ranks")
    pids = [training.current_run().pid] + json.loads((folder / "tree.json").read_text())
    assert not any(process_gone(pid) for pid in pids)
    training.CANCEL_TIMEOUT_S = 1.0
    try:
        seconds, left = cancel_and_wait(pids, 15)
    finally:
        training.CANCEL_TIMEOUT_S = 20.0
    assert not left, left
    assert state().status == "CANCELLED", (state().status, state().message)
    assert seconds < 1.0 + 5.0 + 5.0 + 2.0, seconds  # the wait, SIGTERM's 5 s, SIGKILL
    return {"processes": len(pids), "cancel_seconds": round(seconds, 2)}


@check
def overlay_handler_follows_register():
    """Disabling the add-on removes its draw handler (removing it again fails: gone);
    enabling adds one again; twice over."""
    import addon_utils
    from harness import ADDON
    handles = []
    for _ in range(2):
        handle = addon("overlay").handler()
        assert handle is not None
        handles.append(handle)
        addon_utils.disable(ADDON, default_set=True)
        assert ADDON not in bpy.context.preferences.addons
        try:
            bpy.types.SpaceView3D.draw_handler_remove(handle, "WINDOW")
            raise AssertionError("the draw handler was still there after the add-on was disabled")
        except ValueError:
            pass
        assert addon("overlay").handler() is None
        addon_utils.enable(ADDON, default_set=True)
        assert ADDON in bpy.context.preferences.addons and addon("overlay").handler() is not None
    assert addon("overlay").handler() not in handles
    return {"cycles": 2}


@check
def proposed_cubes_draw_orange_pixels():
    """Where Blender can draw without a window (5.2+: gpu.init), the overlay's draw
    callback in an offscreen buffer: orange on a proposed cube's edges, nothing inside it
    or for an accepted prompt."""
    import gpu
    if not hasattr(gpu, "init"):
        return {"drawn": False, "why": f"no gpu.init in Blender {bpy.app.version_string}"}
    try:
        gpu.init()
    except SystemError as exc:
        return {"drawn": False, "why": f"gpu.init: {exc}"}
    proposals, overlay = addon("proposals"), addon("overlay")
    width, height = 160, 120
    view = Matrix.Translation((0.0, 0.0, -4.0))  # camera at z = 4 looking down -z
    projection = Matrix(((1.5, 0, 0, 0), (0, 2.0, 0, 0), (0, 0, -1.0002, -0.2), (0, 0, -1, 0)))

    def render() -> np.ndarray:
        offscreen = gpu.types.GPUOffScreen(width, height)
        try:
            with offscreen.bind():
                framebuffer = gpu.state.active_framebuffer_get()
                framebuffer.clear(color=(0.0, 0.0, 0.0, 0.0))
                with gpu.matrix.push_pop():
                    gpu.matrix.load_matrix(view)
                    gpu.matrix.load_projection_matrix(projection)
                    overlay.draw(SimpleNamespace(scene=scene(), view_layer=bpy.context.view_layer, space_data=None))
                pixels = np.array(framebuffer.read_color(0, 0, width, height, 4, 0, "FLOAT").to_list(), np.float32)
        finally:
            offscreen.free()
        return pixels.reshape(height, width, 4)

    def pixel_of(point) -> tuple[int, int]:
        clip = projection @ view @ Vector((*point, 1.0))
        return int((clip.x / clip.w + 1) / 2 * width), int((clip.y / clip.w + 1) / 2 * height)

    def orange(rgba) -> np.ndarray:
        return (rgba[..., 0] > 0.8) & (rgba[..., 1] > 0.3) & (rgba[..., 1] < 0.6) & (rgba[..., 2] < 0.2)

    scene().promptgs.root = None
    entry = {"center": [0.0, 0.0, 0.0], "size": [1.0, 1.0, 1.0], "rotation_wxyz": [1.0, 0.0, 0.0, 0.0], "confidence": 0.9}
    cube = proposals.show(bpy.context, [entry])[0]
    cube.select_set(False)
    image = render()
    corners = [pixel_of((x * 0.5, y * 0.5, 0.5)) for x, y in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    hits = []
    for (x0, y0), (x1, y1) in zip(corners, corners[1:] + corners[:1]):  # the front face's edge midpoints
        x, y = (x0 + x1) // 2, (y0 + y1) // 2
        hits.append(bool(orange(image[max(0, y - 2):y + 3, max(0, x - 2):x + 3]).any()))
    cx, cy = pixel_of((0.0, 0.0, 0.0))
    inside = bool(orange(image[cy - 3:cy + 4, cx - 3:cx + 4]).any())
    n_orange = int(orange(image).sum())
    proposals.accept(bpy.context, cube)  # an accepted prompt: the overlay draws nothing
    after = int(orange(render()).sum())
    bpy.data.objects.remove(cube)
    assert all(hits) and not inside and n_orange > 100, (hits, inside, n_orange)
    assert after == 0, after
    return {"drawn": True, "orange_pixels": n_orange, "renderer": gpu.platform.renderer_get()}


# The real scenes beside the repository, when present: their imports too.
for real in config["real"]:
    if real["kind"] == "scene":
        for fn in (import_scene, projection_matches_colmap, root_puts_capture_upright):
            check(fn, real, name=f"{fn.__name__}@{real['name']}")
    else:
        check(import_distorted_reports_distortion, real, name=f"import_distorted_reports_distortion@{real['name']}")


@check
def loading_a_file_detaches_the_run():
    """Opening another file while a run trains lets it go on, detached (every file's
    panel lists it); opening the file whose scene records it attaches it again, with
    the progress it made meanwhile."""
    training = addon("training")
    scene().promptgs.root = root_of(SCENE)
    fake_trainer("slow")
    bpy.ops.promptgs.train()
    name, folder = state().name, state().folder
    run = training.current_run()
    drain_until(lambda: state().snapshot_step >= 10, what="a snapshot")
    saved = TMP / "with_a_run.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(saved))
    saved_step = state().step
    bpy.ops.wm.read_homefile(use_empty=True)
    assert run.running and training.current_run() is None and not scene().promptgs.runs
    assert [live.folder for live in training.detached_runs()] == [folder]
    detached = training._live[folder]
    step = detached.progress.snapshot_step
    drain_until(lambda: detached.progress.snapshot_step >= step + 20, what="progress while detached")
    lines = panel_lines(addon("ui").PROMPTGS_PT_runs)
    assert "[promptgs.attach_run]" in lines and "[promptgs.cancel_detached]" in lines, lines
    bpy.ops.wm.open_mainfile(filepath=str(saved))
    assert state().name == name and training.current_run() is run and not training.detached_runs()
    assert state().step > saved_step and state().snapshot_step >= step + 20, (state().step, saved_step)
    assert shown_gaussians()[0] == detached.progress.last_snapshot  # the newest, shown at once
    bpy.ops.promptgs.cancel()
    run_until_idle(60)
    assert state().status == "CANCELLED" and not run.running
    return {"saved_step": saved_step, "attached_step": state().step}


def settings_shown() -> str:
    return scene().promptgs.shown_run


@check
def reopened_file_shows_result_or_resume():
    """A saved file opened after Blender quit: a finished run shows its result, a run that
    was training shows Resume, which continues it from its last checkpoint to its end."""
    training = addon("training")
    settings = scene().promptgs
    settings.preset, settings.iterations, settings.checkpoint_every = "CUSTOM", 60, 10
    fake_trainer("ply")
    bpy.ops.promptgs.train()
    run_until_idle(60)
    finished = state().name
    assert state().status == "DONE" and state().result_ply and shown_gaussians()[0] == state().result_ply
    fake_trainer("slow")
    bpy.ops.promptgs.train()
    stopped = state().name
    drain_until(lambda: state().snapshot_step >= 20, what="a checkpoint and a snapshot")
    saved = TMP / "reopen.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(saved))
    training.stop_all()  # what quitting Blender does: the trainer stops, its checkpoint stays
    training._ended.clear()  # and a new Blender knows nothing of this one's runs
    bpy.ops.wm.open_mainfile(filepath=str(saved))
    runs = scene().promptgs.runs
    assert runs[finished].status == "DONE" and runs[stopped].status == "INTERRUPTED", \
        (runs[finished].status, runs[stopped].status)
    assert settings_shown() == stopped and training.resumable(runs[stopped])
    lines = panel_lines(addon("ui").PROMPTGS_PT_train)
    assert "[promptgs.resume]" in lines and runs[stopped].message in lines, lines
    checkpoint = int((Path(runs[stopped].folder) / "ckpt.pt").read_text())
    bpy.ops.promptgs.show_run(name=finished)
    assert shown_gaussians()[0] == runs[finished].result_ply
    fake_trainer("ply")
    bpy.ops.promptgs.resume(name=stopped)
    assert settings_shown() == stopped and state().status == "STARTING"
    run_until_idle(60)
    record = state()
    assert record.status == "DONE" and record.step == 60, (record.status, record.message, record.step)
    assert int((Path(record.folder) / "resumed_at").read_text()) == checkpoint >= 10
    assert shown_gaussians()[0] == record.result_ply
    log = Path(record.log_path).read_text()
    assert "slow run into" in log and f"resumed at step {checkpoint}" in log  # one log, both parts
    scene().promptgs.checkpoint_every = 1000
    return {"checkpoint": checkpoint, "finished": finished, "resumed": stopped}


@check
def never_imports_torch_or_engine():
    assert not blocked_attempts, blocked_attempts
    assert not forbidden_modules(), forbidden_modules()
    return {}


finish()
