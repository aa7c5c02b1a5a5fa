"""The installed extension driving the real trainer (see test_blender_train.py).

Imports a pinhole scene (tests/scenes.py's, or tumbler), adds a prompt around its
object, runs a short CPU training through ``python -m promptgs_engine train`` (a separate
process: this one blocks torch imports), renders the scene with Workbench while training
goes on, previews it, exports its Gaussians (and trains again from them after deleting
those in the prompt box), cancels a run mid-way, resumes a reopened one and cancels a
two-process one.
"""

import json
import os
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
from harness import (addon, bpy, cancel_and_wait, check, config, delete_selected_points, drain_until,  # noqa: E402
                     finish, forbidden_modules, install, process_tree, run_until_idle)

import bmesh  # noqa: E402
import numpy as np  # noqa: E402
from mathutils import Vector  # noqa: E402

TMP = Path(config["tmp"])
scene = lambda: bpy.context.scene  # noqa: E731
jobs = lambda: bpy.context.window_manager.promptgs_run  # noqa: E731


def state():
    """The record of the run the scene shows."""
    return addon("training").shown_record(scene())


def prefs():
    return bpy.context.preferences.addons["bl_ext.user_default.promptgs"].preferences


def select_object_points(camera: str, rect: list) -> None:
    """Select (in Edit Mode) the sparse points seen inside a pixel rectangle of a camera,
    the middle 60 % of them in depth: the object the photos are about."""
    from bpy_extras.object_utils import world_to_camera_view

    sc = scene()
    cam = bpy.data.objects[camera]
    addon("importer").use_camera(sc, cam)
    points = next(o for o in bpy.data.objects if o.name.startswith("PromptGS Sparse Points"))
    width, height = sc.render.resolution_x, sc.render.resolution_y
    mesh = points.data
    chosen, depths = [], []
    for i, vertex in enumerate(mesh.vertices):
        ndc = world_to_camera_view(sc, cam, points.matrix_world @ vertex.co)
        u, v = ndc.x * width, (1.0 - ndc.y) * height
        if ndc.z > 0 and rect[0] <= u <= rect[2] and rect[1] <= v <= rect[3]:
            chosen.append(i)
            depths.append(ndc.z)
    lo, hi = np.percentile(depths, [20, 80])
    select = np.zeros(len(mesh.vertices), bool)
    select[[i for i, d in zip(chosen, depths) if lo <= d <= hi]] = True
    mesh.vertices.foreach_set("select", select)
    for obj in bpy.context.selected_objects:
        obj.select_set(False)
    points.select_set(True)
    bpy.context.view_layer.objects.active = points
    bpy.ops.object.mode_set(mode="EDIT")


@check
def setup():
    install()
    for name in ("Cube", "Light", "Camera"):  # the startup file's objects
        if name in bpy.data.objects:
            bpy.data.objects.remove(bpy.data.objects[name])
    prefs().python = config["python"]
    prefs().output_dir = str(TMP / "runs")
    bpy.ops.promptgs.test_trainer()  # in the background: the follower brings its answer
    run_until_idle(120)
    probe = prefs().probe_result
    bpy.ops.promptgs.import_colmap(directory=config["dataset"], images=config["images"])
    settings = scene().promptgs
    root = settings.root
    select_object_points(config["render_camera"], config["prompt_rect"])
    bpy.ops.promptgs.add_prompt()  # around the selected points
    settings.preset = "CUSTOM"
    settings.strategy = config["strategy"]
    settings.backend = "cpu"
    settings.color_by = "error"
    settings.display_style = "SPHERES"  # the Workbench image: spheres in colour-map materials
    settings.point_radius = settings.point_radius * 1.5
    return {"probe": probe}


def prompt_wire_meshes() -> list:
    """Render-visible stand-ins for the prompt empties (empties are not rendered)."""
    made = []
    mat = bpy.data.materials.new("Prompt Wire")
    mat.diffuse_color = (0.9, 0.9, 0.95, 1.0)
    for obj in addon("prompts").prompt_objects(scene()):
        mesh = bpy.data.meshes.new(obj.name + " wire")
        bm = bmesh.new()
        bmesh.ops.create_cube(bm, size=2.0 * obj.empty_display_size)
        bm.to_mesh(mesh)
        bm.free()
        mesh.materials.append(mat)
        wire = bpy.data.objects.new(mesh.name, mesh)
        wire.matrix_world = obj.matrix_world
        mod = wire.modifiers.new("wire", "WIREFRAME")
        mod.thickness = 0.012
        mod.use_relative_offset = False
        scene().collection.objects.link(wire)
        made.append(wire)
    return made


def render(path: str) -> float:
    sc = scene()
    importer = addon("importer")
    cam = bpy.data.objects[config["render_camera"]]
    importer.use_camera(sc, cam)
    sc.render.resolution_percentage = 100
    sc.render.engine = "BLENDER_WORKBENCH"
    sc.display.shading.light = "STUDIO"
    sc.display.shading.color_type = "MATERIAL"
    sc.display.shading.show_cavity = False
    if sc.world is None:
        sc.world = bpy.data.worlds.new("World")
    sc.world.color = (0.02, 0.02, 0.025)
    for obj in bpy.data.objects:
        if obj.name.startswith("PromptGS Sparse Points"):
            obj.hide_render = True
    wires = prompt_wire_meshes()
    sc.render.filepath = path
    start = time.time()
    bpy.ops.render.render(write_still=True)
    for wire in wires:
        bpy.data.objects.remove(wire)
    return time.time() - start


@check
def train_real_trainer():
    settings = scene().promptgs
    settings.iterations = config["iterations"]
    settings.snapshot_every = config["snapshot_every"]
    bpy.ops.promptgs.train()
    info = {"out": state().folder}

    def first_snapshot_render():
        if "render_s" not in info and "PromptGS Gaussians" in bpy.data.objects:
            info["render_s"] = render(config["image"])
            info["render_step"] = state().snapshot_step
        return False

    run_until_idle(config["timeout"], on_events=first_snapshot_render)
    st = state()
    assert st.status == "DONE", (st.status, st.message, st.error_lines)
    assert st.result_ply and Path(st.result_ply).is_file()
    obj = bpy.data.objects["PromptGS Gaussians"]
    display = addon("display")
    names = ["position", "radiance:base", "scale", "rotation", "score", "error"]
    names += sorted((a.name for a in obj.data.attributes if a.name.startswith("radiance:sh_")), key=lambda n: int(n[12:]))
    arrays = {key: display.get_attribute(obj, key) for key in names}
    np.savez(TMP / "object_attributes.npz", **arrays)
    info.update({"ply": st.result_ply, "n": display.point_count(obj), "status_message": st.message,
                 "psnr": st.psnr, "step": st.step, "loss_field": "PromptGS Loss Field" in bpy.data.objects})
    return info


def preview_now() -> dict:
    """Render Preview of the active camera, driven to its end; the outcome and the pixels."""
    bpy.ops.promptgs.render_preview()
    run_until_idle(config["timeout"])
    st = jobs()
    assert st.preview_status == "DONE", (st.preview_status, st.preview_message)
    image = bpy.data.images["PromptGS Preview"]
    return {"message": st.preview_message, "size": list(image.size)}


@check
def preview_dataset_camera():
    """The finished run from a dataset camera: the datablock holds the trainer's render."""
    sc = scene()
    addon("importer").use_camera(sc, bpy.data.objects[config["render_camera"]])
    sc.render.resolution_percentage = 25  # the run trained on images_4, a quarter of the model's size
    assert config["images"] == "images_4"
    info = preview_now()
    preview = addon("preview")
    image = bpy.data.images["PromptGS Preview"]
    assert tuple(image.size) == (sc.render.resolution_x // 4, sc.render.resolution_y // 4), tuple(image.size)
    np.save(TMP / "preview_dataset_camera.npy", preview.pixels(image)[..., :3])
    both = bpy.data.images["PromptGS Preview | Image"]
    assert tuple(both.size) == (2 * image.size[0], image.size[1]), tuple(both.size)
    np.save(TMP / "preview_side_by_side.npy", preview.pixels(both)[..., :3])
    info["camera_file"] = str(Path(state().folder) / "preview" / "camera.json")
    return info


@check
def preview_user_camera():
    """A camera placed by a script (portrait, AUTO sensor fit, shifted): the camera file it
    sends projects the sparse points where Blender's own camera does."""
    from bpy_extras.object_utils import world_to_camera_view

    sc = scene()
    reference = bpy.data.objects[config["render_camera"]]
    data = bpy.data.cameras.new("Placed")
    data.lens, data.sensor_width, data.sensor_fit = 30.0, 36.0, "AUTO"
    data.shift_x, data.shift_y = 0.05, -0.03
    cam = bpy.data.objects.new("Placed Camera", data)
    sc.collection.objects.link(cam)
    # a step back from a dataset camera and a turn, so the view differs but sees the object
    back = reference.matrix_world.to_3x3() @ Vector((0.0, 0.0, 1.0))
    cam.matrix_world = reference.matrix_world.copy()
    cam.location = reference.matrix_world.translation + 0.6 * back
    cam.rotation_euler.z += 0.15
    sc.camera = cam
    sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = 240, 320, 100
    sc.render.pixel_aspect_x = sc.render.pixel_aspect_y = 1.0
    bpy.context.view_layer.update()
    info = preview_now()
    image = bpy.data.images["PromptGS Preview"]
    assert tuple(image.size) == (240, 320), tuple(image.size)
    sent = json.loads((Path(state().folder) / "preview" / "camera.json").read_text())
    K, w2c = np.array(sent["K"]), np.array(sent["world_to_camera"])
    points = next(o for o in bpy.data.objects if o.name.startswith("PromptGS Sparse Points"))
    co = addon("display").get_attribute(points, "position")[::50]
    errors = []
    for p in co:
        local = w2c[:3, :3] @ p + w2c[:3, 3]
        if local[2] <= 0.1:
            continue
        uv = (K @ (local / local[2]))[:2]
        ndc = world_to_camera_view(sc, cam, points.matrix_world @ Vector(p.tolist()))  # points hold dataset coordinates
        errors.append(float(np.abs(uv - [ndc.x * 240, (1.0 - ndc.y) * 320]).max()))
    assert len(errors) > 20 and max(errors) < 0.05, (len(errors), max(errors) if errors else None)
    np.save(TMP / "preview_user_camera.npy", addon("preview").pixels(image)[..., :3])
    info.update({"max_error_px": max(errors), "n_points": len(errors)})
    return info


@check
def cycles_render_of_native_splats():
    """5.3+: Cycles renders the finished run's splats (Blender's own) from a dataset camera,
    at the run's image size, Standard view transform, for the PSNR comparison of the test."""
    if not addon("display").native_splats_supported():
        return {"native": False, "blender": list(bpy.app.version)}
    sc = scene()
    sc.promptgs.display_style = "AUTO"  # Blender's own splats (setup chose spheres for Workbench)
    assert bpy.data.objects["PromptGS Gaussians"].data.type == "GAUSSIAN_SPLAT"
    addon("importer").use_camera(sc, bpy.data.objects[config["render_camera"]])
    sc.render.resolution_percentage = 25  # the run trained on images_4
    sc.render.engine = "CYCLES"
    sc.cycles.device, sc.cycles.samples = "CPU", config.get("cycles_samples", 16)
    sc.view_settings.view_transform, sc.view_settings.look = "Standard", "None"
    sc.render.film_transparent = False
    if sc.world is None:
        sc.world = bpy.data.worlds.new("World")
    sc.world.use_nodes = False
    sc.world.color = (0.0, 0.0, 0.0)
    shown = [o for o in bpy.data.objects if o.type in ("MESH", "POINTCLOUD") and not o.hide_render]
    for o in shown:
        o.hide_render = o.name != "PromptGS Gaussians"
    sc.render.filepath = str(TMP / "cycles_native.png")
    start = time.time()
    bpy.ops.render.render(write_still=True)
    for o in shown:
        o.hide_render = False
    return {"native": True, "blender": list(bpy.app.version), "image": sc.render.filepath, "seconds": round(time.time() - start, 1),
            "size": [sc.render.resolution_x // 4, sc.render.resolution_y // 4]}


@check
def export_for_eval():
    """The finished run's Gaussians exported as they are, and with the splats inside the
    prompt box deleted, each into a copy of the run folder (for ``promptgs eval``)."""
    obj = bpy.data.objects["PromptGS Gaussians"]
    run = Path(state().folder)
    display = addon("display")
    out = {}
    for name in ("unchanged", "cropped"):
        copy = TMP / f"run_{name}"
        copy.mkdir()
        shutil.copy(run / "cfg.json", copy / "cfg.json")
        if name == "cropped":  # delete in Edit Mode what lies in the prompt cube, as a user would
            cube = addon("prompts").prompt_objects(scene())[0]
            local = np.array(cube.matrix_world.inverted() @ obj.matrix_world)
            co = display.get_attribute(obj, "position").astype(np.float64)
            inside = (np.abs(co @ local[:3, :3].T + local[:3, 3]) <= cube.empty_display_size).all(axis=1)
            assert 0 < inside.sum() < len(co), inside.sum()
            delete_selected_points(obj, inside)
            out["deleted"] = int(inside.sum())
        path = copy / "point_cloud.ply"
        assert bpy.ops.promptgs.export_gaussians(filepath=str(path), start_from=name == "cropped") == {"FINISHED"}
        out[name] = str(copy)
    out["n_left"] = display.point_count(obj)
    assert scene().promptgs.init_ply == str(TMP / "run_cropped" / "point_cloud.ply")  # Train From It
    return out


@check
def train_from_the_cleaned_export():
    """The next run starts from what *Export Gaussians* wrote with Train From It (the
    Gaussians left after deleting those in the prompt box): the job file and the run's
    cfg.json name the file, the run starts from exactly its Gaussians (train.json, and the
    first snapshot, taken before the first refinement), and it finishes."""
    settings = scene().promptgs
    path = TMP / "run_cropped" / "point_cloud.ply"
    assert settings.init_ply == str(path), settings.init_ply
    exported = len(addon("plyio").read_vertices(path))
    settings.iterations, settings.snapshot_every = config["iterations"], 5  # refinement starts at step 10
    try:
        bpy.ops.promptgs.train()
        run_until_idle(config["timeout"])
    finally:
        settings.init_ply, settings.snapshot_every = "", config["snapshot_every"]
    st = state()
    assert st.status == "DONE", (st.status, st.message, st.error_lines)
    folder = Path(st.folder)
    assert json.loads(Path(st.job_path).read_text())["init"] == str(path)
    assert json.loads((folder / "cfg.json").read_text())["init"] == str(path)
    started = json.loads((folder / "train.json").read_text())["initial_gaussians"]
    first = min((folder / "snapshots").glob("step_*.npz"))
    with np.load(first) as npz:
        in_first = len(npz["means"])
    assert started == exported == in_first and first.name == "step_000005.npz", (started, exported, in_first, first.name)
    assert Path(st.result_ply).is_file() and st.step == st.iterations, (st.result_ply, st.step, st.iterations)
    return {"out": str(folder), "init": str(path), "exported": exported, "initial_gaussians": started,
            "first_snapshot": first.name, "n_final": st.n_gaussians, "psnr": st.psnr}


@check
def cancel_real_trainer():
    settings = scene().promptgs
    settings.iterations = 5000
    settings.snapshot_every = 5
    bpy.ops.promptgs.train()
    training = addon("training")
    run = training.current_run()
    deadline = time.time() + config["timeout"]
    while state().snapshot_step == 0 and time.time() < deadline:
        training.drain_and_apply(bpy.context)
        time.sleep(0.1)
    assert state().snapshot_step > 0, (state().status, state().message)
    bpy.ops.promptgs.cancel()
    run_until_idle(60)
    st = state()
    assert st.status == "CANCELLED", (st.status, st.message, st.error_lines)
    assert not run.running and run.process.returncode != 0
    with np.load(st.last_snapshot) as npz:
        n = len(npz["means"])
        means = npz["means"]
    obj = bpy.data.objects["PromptGS Gaussians"]
    assert addon("display").point_count(obj) == n
    np.testing.assert_allclose(addon("display").get_attribute(obj, "position"), means, atol=1e-6)
    return {"message": st.message, "returncode": run.process.returncode, "snapshot_step": st.snapshot_step,
            "last_output": st.last_output}


@check
def resume_reaches_the_uninterrupted_result():
    """A run saved while it trains and reopened after Blender quit shows Resume; resumed,
    it ends with the very PLY of the same run trained without a stop (the CPU backend
    adds in a fixed order)."""
    training = addon("training")
    settings = scene().promptgs
    settings.iterations, settings.snapshot_every, settings.checkpoint_every = config["resume_iterations"], 10, 10
    bpy.ops.promptgs.train()
    straight = state().name
    run_until_idle(config["timeout"])
    assert state().status == "DONE", (state().status, state().message, state().error_lines)
    straight_ply, straight_psnr = Path(state().result_ply), state().psnr
    bpy.ops.promptgs.train()
    stopped = state().name
    drain_until(lambda: state().snapshot_step >= 20, config["timeout"], "the snapshot after a checkpoint")
    saved = TMP / "resume.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(saved))
    training.stop_all()  # Blender quits: the trainer stops, its checkpoint stays
    training._ended.clear()  # a new Blender knows nothing of the old one's runs
    bpy.ops.wm.open_mainfile(filepath=str(saved))
    record = scene().promptgs.runs[stopped]
    assert record.status == "INTERRUPTED" and training.resumable(record), (record.status, record.message)
    folder = Path(record.folder)
    assert not (folder / "point_cloud.ply").exists()
    bpy.ops.promptgs.resume(name=stopped)
    run_until_idle(config["timeout"])
    record = scene().promptgs.runs[stopped]
    assert record.status == "DONE", (record.status, record.message, record.error_lines)
    log = (folder / "train.log").read_text()
    resumed_at = int(log.split("resumed at step ")[1].split()[0])
    assert resumed_at >= 10 and resumed_at % 10 == 0, resumed_at
    assert Path(record.result_ply).read_bytes() == straight_ply.read_bytes(), "the resumed run ended elsewhere"
    assert record.psnr == straight_psnr
    assert addon("training").shown_path() == record.result_ply
    return {"resumed_at": resumed_at, "psnr": record.psnr, "straight": straight, "resumed": stopped}


@check
def multi_rank_cancel_leaves_no_process():
    """Cancel of a two-process run (launcher, torchrun, two ranks in their own sessions)
    leaves none of them running."""
    training = addon("training")
    settings = scene().promptgs
    settings.iterations, settings.snapshot_every, settings.nproc = 5000, 5, 2
    try:
        bpy.ops.promptgs.train()
        drain_until(lambda: state().step > 0, config["timeout"], "the first step of both ranks")
        tree = process_tree(training.current_run().pid)
        assert len(tree) >= 4, tree  # launcher, torchrun, two ranks
        seconds, left = cancel_and_wait(tree, 30)
    finally:
        settings.nproc = 1
    assert not left, left
    assert state().status == "CANCELLED", (state().status, state().message)
    return {"processes": len(tree), "cancel_seconds": round(seconds, 2), "message": state().message}


@check
def never_imports_torch_or_engine():
    assert not forbidden_modules(), forbidden_modules()


finish()
