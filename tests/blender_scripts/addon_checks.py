"""Checks of the installed extension with recorded/fake trainers (see test_blender_addon.py)."""

import json
import os
import shutil
import sys
import time
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, os.path.dirname(__file__))
from harness import addon, bpy, check, finish, config, forbidden_modules, blocked_attempts, install, run_until_idle  # noqa: E402

import numpy as np  # noqa: E402
from bpy_extras.object_utils import world_to_camera_view  # noqa: E402
from mathutils import Euler, Matrix, Vector  # noqa: E402

TMP = Path(config["tmp"])
scene = lambda: bpy.context.scene  # noqa: E731
state = lambda: bpy.context.window_manager.promptgs_run  # noqa: E731


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
    assert state().status == "ERROR" and f"prompt '{off.name}'" in state().message, state().message
    bpy.data.objects.remove(off)
    return {"box": box, "corner_error": worst, "flat_message": state().message}


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
    for key in ("opacity", "scale", "rotation", "score", "error"):
        np.testing.assert_allclose(display.get_attribute(obj, key), data[key], atol=1e-6, err_msg=key)
    np.testing.assert_allclose(display.get_attribute(obj, "color")[:, :3], data["color"], atol=1e-6)
    assert obj.parent == scene().promptgs.root
    field = bpy.data.objects["PromptGS Loss Field"]
    assert display.point_count(field) == 64
    np.testing.assert_allclose(display.get_attribute(field, "loss"), data["field_loss"], atol=1e-6)
    np.testing.assert_allclose(display.get_attribute(field, "attention"), data["field_attention"], atol=1e-6)
    bins = display.get_attribute(obj, "display_bin")
    assert bins.min() >= 0 and bins.max() == display.N_BINS - 1  # coloured by error
    # a point cloud where Blender can resize one from Python (5.1+), a points-only mesh before
    kind = "POINTCLOUD" if bpy.app.version >= (5, 1, 0) else "MESH"
    assert obj.type == field.type == kind, (obj.type, field.type, bpy.app.version_string)
    # what the object carries, for the comparison across lines (test_blender_addon.py)
    np.savez(TMP / "gaussians_object.npz", snapshot=np.array(Path(st.last_snapshot).name),
             **{f"gaussians_{key}": display.get_attribute(obj, key)
                for key in ("position", "opacity", "scale", "rotation", "color", "score", "error")},
             **{f"field_{key}": display.get_attribute(field, key) for key in ("position", "loss", "attention")})
    return {"first_snapshot_count": seen["count"], "final_count": n, "object_type": obj.type,
            "blender": bpy.app.version_string}


@check
def cancel_keeps_last_snapshot():
    fake_trainer("slow")
    bpy.ops.promptgs.train()
    out = Path(state().out_dir)
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
    st = state()
    assert st.status == "ERROR" and "Trainer command not found: /no/such/python" in st.message, st.message
    return {"message": st.message, "reported": reported.strip()}


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
    st = state()
    assert st.status == "ERROR" and "no such image folder" in st.message and "no_images" in st.message, st.message
    back_to_the_scene()
    return {"message": st.message}


@check
def dataset_generation_runs_in_background():
    training = addon("training")
    fake_trainer("ok")
    scene().promptgs.dataset_out = str(TMP / "generated")
    scene().promptgs.dataset_preset = "tiny"
    bpy.ops.promptgs.generate_dataset()
    assert state().dataset_status == "RUNNING"
    run_until_idle(60)
    assert state().dataset_status == "DONE", state().dataset_message
    argv = (TMP / "generated" / "done").read_text().split()
    assert argv[argv.index("dataset"):][:4] == ["dataset", "mountain", "--preset", "tiny"], argv
    fake_trainer("crash")
    bpy.ops.promptgs.generate_dataset()
    run_until_idle(60)
    assert state().dataset_status == "ERROR"
    assert state().dataset_message == "promptgs: error: --preset tiny: cannot find a blender binary"
    return {"argv": argv}


@check
def reconstruct_from_photos_imports_the_result():
    """sfm runs in the background, its stage line shows, and its dataset is imported."""
    fake_trainer("stepwise")  # the fake holds at its mapping stage until sfm_go exists
    photos = Path(SCENE["path"]) / "images"
    n = SCENE["n_images"]
    bpy.ops.promptgs.reconstruct(directory=str(photos))
    assert state().sfm_status == "RUNNING", (state().sfm_status, state().sfm_message)
    go = Path(state().sfm_out).parent / "sfm_go"
    lines = []
    training = addon("training")
    deadline = time.time() + 60
    while training.drain_and_apply(bpy.context) and time.time() < deadline:
        lines.append(state().sfm_message)
        if state().sfm_message.startswith("mapping"):
            go.touch()
        time.sleep(0.01)
    assert state().sfm_status == "DONE", (state().sfm_status, state().sfm_message)
    assert any(line.startswith(("features", "matching", "mapping")) for line in lines), lines
    assert f"{n - 1} of {n} images registered" in state().sfm_message, state().sfm_message
    root = scene().promptgs.root
    assert Path(root["promptgs_dataset"]) == Path(state().sfm_out).resolve()
    assert len([o for o in root.children if o.type == "CAMERA"]) == n
    back_to_the_scene()
    return {"message": state().sfm_message, "stage_lines": sorted(set(lines))[:6]}


@check
def reconstruct_errors_and_cancel():
    fake_trainer("crash")
    photos = Path(SCENE["path"]) / "images"
    bpy.ops.promptgs.reconstruct(directory=str(photos))
    run_until_idle(60)
    only = f"only 6 of {SCENE['n_images']} images registered"
    assert state().sfm_status == "ERROR" and only in state().sfm_message, state().sfm_message
    fake_trainer("slow")
    bpy.ops.promptgs.reconstruct(directory=str(photos))
    out = Path(state().sfm_out)
    training = addon("training")
    deadline = time.time() + 60
    while not state().sfm_message.startswith("mapping") and time.time() < deadline:
        training.drain_and_apply(bpy.context)
        time.sleep(0.05)
    bpy.ops.promptgs.cancel_reconstruct()
    run_until_idle(60)
    assert state().sfm_status == "CANCELLED", (state().sfm_status, state().sfm_message)
    assert (out.parent / "sfm_cancelled").is_file(), "the reconstruction was not interrupted cleanly"
    try:
        bpy.ops.promptgs.reconstruct(directory=str(TMP / "no_such_photos"))
        raise AssertionError("reconstruct did not fail")
    except RuntimeError:
        pass
    assert state().sfm_status == "ERROR" and "no_such_photos: not found" in state().sfm_message, state().sfm_message
    return {"message": state().sfm_message}


@check
def load_result_reads_3dgs_ply():
    rng = np.random.default_rng(3)
    n = 500
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    table = rng.normal(size=(n, len(names))).astype("<f4")
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    path = TMP / "result.ply"
    path.write_bytes(header.encode() + table.tobytes())
    bpy.ops.promptgs.load_result(filepath=str(path))
    obj = bpy.data.objects["PromptGS Gaussians"]
    display = addon("display")
    col = {name: table[:, i] for i, name in enumerate(names)}
    assert display.point_count(obj) == n
    np.testing.assert_allclose(display.get_attribute(obj, "position")[:, 0], col["x"], atol=1e-6)
    np.testing.assert_allclose(display.get_attribute(obj, "opacity"), 1 / (1 + np.exp(-col["opacity"])), atol=1e-6)
    return {"n": n}


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
    addon("training").show_gaussians(bpy.context, data)
    seconds = time.time() - start
    assert display.point_count(obj) == n
    start = time.time()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    depsgraph.update()
    evaluated = obj.evaluated_get(depsgraph)
    draw_seconds = time.time() - start
    assert evaluated.data is not None
    assert draw_seconds < 5.0, f"evaluating the display of 1M points took {draw_seconds:.1f} s (spheres?)"
    # points are drawn as plain points now; a small set goes back to spheres
    small = {k: v[:1000] for k, v in data.items()}
    addon("training").show_gaussians(bpy.context, small)
    return {"update_seconds_1M": round(seconds, 2), "evaluate_seconds_1M": round(draw_seconds, 2)}


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
            elif name == "label":
                self.log.append(kwargs.get("text", ""))
            return StubLayout(self.log)
        return call

    def __setattr__(self, name, value):
        object.__setattr__(self, name, value)


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
    opacity = display.get_attribute(obj, "opacity")
    bins = display.get_attribute(obj, "display_bin")
    assert bins[np.argmax(opacity)] == display.N_BINS - 1 and bins[np.argmin(opacity)] == 0
    settings.color_by = "color"
    rgb = display.get_attribute(obj, "display_color")[:, :3]
    np.testing.assert_allclose(rgb, display.get_attribute(obj, "color")[:, :3], atol=1e-6)
    settings.display_style = "AUTO"
    settings.color_by = "error"
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
    assert state().propose_status == "RUNNING", (state().propose_status, state().propose_message)
    run_until_idle(60)
    assert state().propose_status == "DONE", state().propose_message
    assert state().propose_message.startswith("2 proposals from snapshot step_000010, 1 of confidence"), state().propose_message
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
    assert state().propose_status == "ERROR", state().propose_message
    assert state().propose_message == f"promptgs: error: {run}: the run has no point_cloud.ply yet", state().propose_message
    scene().promptgs.preview_run = str(TMP)
    try:
        bpy.ops.promptgs.propose()
        raise AssertionError("propose did not fail")
    except RuntimeError:
        pass
    assert "not a PromptGS run folder" in state().propose_message, state().propose_message
    scene().promptgs.preview_run = ""
    return {"message": state().propose_message}


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
    out = Path(state().out_dir)
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
    assert state().propose_status == "DONE"
    assert state().propose_message == ("2 proposals from training step 15, 1 of confidence ≥ 0.3 "
                                       "(the run trains 1 box around them)"), state().propose_message
    names_after_first = proposed_names()
    training.drain_and_apply(bpy.context)
    assert proposed_names() == names_after_first
    # accept the first, train again: the same proposals come back, the accepted one not twice
    accepted = proposals.accept(bpy.context, cubes[0])
    bpy.ops.promptgs.train()
    second = Path(state().out_dir)
    run_until_idle(60)
    assert second != out and state().status == "DONE", (state().status, state().message)
    job = json.loads(Path(state().job_path).read_text())
    assert len(job["prompts"]["prompts"]) == len(first_job["prompts"]["prompts"]) + 1  # the accepted cube is trained
    cubes = proposals.proposed_objects(scene())
    assert len(cubes) == 1 and abs(cubes[0]["promptgs_confidence"] - 0.21) < 1e-6, [c.name for c in cubes]
    assert state().propose_message.startswith("1 proposals from training step 15, 0 of confidence ≥ 0.3, "
                                              "1 already inside prompts"), state().propose_message
    assert len(addon("overlay").proposed_edges(bpy.context)[0]) + len(addon("overlay").proposed_edges(bpy.context)[1]) == 24
    # a run without proposing leaves the proposed cubes as they are
    settings.propose_prompts = False
    bpy.ops.promptgs.train()
    run_until_idle(60)
    assert not (Path(state().out_dir) / "proposals.json").exists()
    assert len(proposals.proposed_objects(scene())) == 1
    for obj in proposals.proposed_objects(scene()) + [accepted]:
        bpy.data.objects.remove(obj)
    proposals.update_markers(bpy.context)
    settings.preset = "STANDARD"
    return {"message": state().propose_message}


@check
def panels_draw_in_every_state():
    ui = addon("ui")
    labels = {}
    for status in ("IDLE", "RUNNING", "ERROR", "DONE"):
        state().status = state().sfm_status = state().preview_status = state().propose_status = status
        state().error_lines = "line one\nline two"
        log = []
        for cls in ui.CLASSES:
            cls.draw(SimpleNamespace(layout=StubLayout(log)), bpy.context)
        labels[status] = log
    assert "line two" in labels["ERROR"]
    return {"labels": labels["ERROR"][:12]}


@check
def loading_a_file_stops_the_trainer():
    fake_trainer("slow")
    bpy.ops.promptgs.train()
    run = addon("training").current_run()
    time.sleep(0.3)
    assert run.running
    bpy.ops.wm.read_homefile(use_empty=True)
    assert not run.running and run.process.returncode is not None
    assert addon("training").current_run() is None
    return {"returncode": run.process.returncode}


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
def never_imports_torch_or_engine():
    assert not blocked_attempts, blocked_attempts
    assert not forbidden_modules(), forbidden_modules()
    return {}


finish()
