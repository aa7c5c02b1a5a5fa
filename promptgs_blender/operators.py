"""Operators: import, prompts, train/cancel, load result, export Gaussians, trainer check, dataset generation."""

import time
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper
from mathutils import Vector

from . import colmap, display, importer, plyio, prompts, proposals, reconstruct, results, training
from .props import prefs
from .trainer import find_python, probe


class PROMPTGS_OT_import_colmap(bpy.types.Operator):
    """Import a COLMAP dataset folder (cameras with exact intrinsics, sparse points)"""

    bl_idname = "promptgs.import_colmap"
    bl_label = "Import COLMAP Dataset"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(subtype="DIR_PATH")
    images: StringProperty(name="Images", default="images", description="Image folder inside the dataset")
    backgrounds: BoolProperty(name="Images as Camera Backgrounds", default=False)
    up: EnumProperty(name="Up", default="AUTO", items=[
        ("AUTO", "From Cameras", "Average 'up' of the cameras becomes +Z"),
        ("-Y", "-Y", "COLMAP's usual up"), ("+Y", "+Y", ""), ("+Z", "+Z", "")])

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        try:
            root, warnings = importer.import_colmap(context, self.directory, self.images, self.backgrounds, self.up)
        except (colmap.ColmapError, OSError) as exc:
            context.window_manager.promptgs_run.message = str(exc)
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for warning in warnings:
            self.report({"WARNING"}, warning)
        n = len([c for c in root.children if c.type == "CAMERA"])
        self.report({"INFO"}, f"Imported {n} cameras from {root['promptgs_dataset']}")
        return {"FINISHED"}


class PROMPTGS_OT_use_camera(bpy.types.Operator):
    """Look through this camera with its image's resolution"""

    bl_idname = "promptgs.use_camera"
    bl_label = "Use Camera"
    bl_options = {"REGISTER", "UNDO"}

    name: StringProperty()

    def execute(self, context):
        obj = bpy.data.objects.get(self.name) or context.active_object
        if obj is None or obj.type != "CAMERA":
            self.report({"ERROR"}, "Select an imported camera")
            return {"CANCELLED"}
        importer.use_camera(context.scene, obj)
        return {"FINISHED"}


class PROMPTGS_OT_add_prompt(bpy.types.Operator):
    """Add a prompt cube at the 3D cursor, or around the selected points in Edit Mode"""

    bl_idname = "promptgs.add_prompt"
    bl_label = "Add Prompt"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        bounds = prompts.selected_points_bounds(context)
        if bounds is not None:
            center, half = bounds
            bpy.ops.object.mode_set(mode="OBJECT")
        else:
            center = context.scene.cursor.location.copy()
            size = context.scene.promptgs.point_radius * 25.0
            half = Vector((size, size, size))
        _make_only_selected(context, prompts.add_prompt(context, center, half))
        return {"FINISHED"}


def _make_only_selected(context, obj) -> None:
    """Select ``obj`` alone and make it the active object."""
    for other in context.selected_objects:
        other.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj


class PROMPTGS_OT_select_prompt(bpy.types.Operator):
    """Select this prompt"""

    bl_idname = "promptgs.select_prompt"
    bl_label = "Select Prompt"
    bl_options = {"REGISTER", "UNDO"}

    name: StringProperty()

    def execute(self, context):
        obj = bpy.data.objects.get(self.name)
        if obj is None:
            return {"CANCELLED"}
        _make_only_selected(context, obj)
        return {"FINISHED"}


class PROMPTGS_OT_remove_prompt(bpy.types.Operator):
    """Delete this prompt"""

    bl_idname = "promptgs.remove_prompt"
    bl_label = "Remove Prompt"
    bl_options = {"REGISTER", "UNDO"}

    name: StringProperty()

    def execute(self, context):
        obj = bpy.data.objects.get(self.name)
        if obj is not None:
            proposed = obj.get("promptgs_proposed") is not None
            bpy.data.objects.remove(obj)
            if proposed:
                proposals.update_markers(context)
        return {"FINISHED"}


def _start(operator, context, start, message: str) -> set[str]:
    """Run a ``training.start_*`` function: its problem is reported as an error, else the
    panel's ``message`` field as information."""
    try:
        start(context)
    except training.UserError as exc:
        operator.report({"ERROR"}, str(exc))
        return {"CANCELLED"}
    operator.report({"INFO"}, getattr(context.window_manager.promptgs_run, message))
    return {"FINISHED"}


class PROMPTGS_OT_propose(bpy.types.Operator):
    """Box the small objects the run still misses (several views show them, its render does not): promptgs propose in the background"""

    bl_idname = "promptgs.propose"
    bl_label = "Propose Prompts"

    def execute(self, context):
        return _start(self, context, training.start_propose, "propose_message")


class PROMPTGS_OT_accept_proposal(bpy.types.Operator):
    """Make this proposed cube a prompt (empty name: every proposed cube)"""

    bl_idname = "promptgs.accept_proposal"
    bl_label = "Accept Proposal"
    bl_options = {"REGISTER", "UNDO"}

    name: StringProperty()

    def execute(self, context):
        cubes = [bpy.data.objects.get(self.name)] if self.name else proposals.proposed_objects(context.scene)
        if not cubes or cubes[0] is None:
            self.report({"ERROR"}, f"No proposed prompt '{self.name}'")
            return {"CANCELLED"}
        try:
            for obj in cubes:
                proposals.accept(context, obj)
        except proposals.ProposeError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class PROMPTGS_OT_train(bpy.types.Operator):
    """Train with the prompts in a separate trainer process (Esc cancels)"""

    bl_idname = "promptgs.train"
    bl_label = "Train Focused"

    _timer = None

    def execute(self, context):
        try:
            training.start_training(context)
        except training.UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Training into {context.window_manager.promptgs_run.out_dir}")
        return {"FINISHED"}

    def invoke(self, context, event):
        if self.execute(context) != {"FINISHED"}:
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.25, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            training.cancel_training(context)
        elif event.type == "TIMER":
            if not training.drain_and_apply(context):
                context.window_manager.event_timer_remove(self._timer)
                return {"FINISHED"}
        return {"PASS_THROUGH"}


class PROMPTGS_OT_cancel(bpy.types.Operator):
    """Stop the trainer; its last snapshot stays in the scene"""

    bl_idname = "promptgs.cancel"
    bl_label = "Cancel Training"

    def execute(self, context):
        training.cancel_training(context)
        return {"FINISHED"}


class PROMPTGS_OT_load_result(bpy.types.Operator, ImportHelper):
    """Load a 3D Gaussian Splatting PLY as the PromptGS Gaussians object"""

    bl_idname = "promptgs.load_result"
    bl_label = "Load Result"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})

    def invoke(self, context, event):
        result = context.window_manager.promptgs_run.result_ply
        if result and not self.filepath:
            self.filepath = result
        return ImportHelper.invoke(self, context, event)

    def execute(self, context):
        try:
            obj = results.load_result(context, Path(bpy.path.abspath(self.filepath)))
        except plyio.PlyError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Loaded {display.point_count(obj)} Gaussians")
        return {"FINISHED"}


class PROMPTGS_OT_export_gaussians(bpy.types.Operator, ExportHelper):
    """Write the Gaussians, as you edited them (deleted, cropped), to a standard 3DGS PLY in dataset coordinates"""

    bl_idname = "promptgs.export_gaussians"
    bl_label = "Export Gaussians"

    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})
    start_from: BoolProperty(name="Train From It", default=True,
                             description="Make it the Start From file of the next training")

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath))
        try:
            n = results.export_gaussians(context, path)
        except (ValueError, plyio.PlyError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if self.start_from:
            context.scene.promptgs.init_ply = str(path)
        self.report({"INFO"}, f"Wrote {n} Gaussians to {path}")
        return {"FINISHED"}


class PROMPTGS_OT_find_trainer(bpy.types.Operator):
    """Look for a Python that has promptgs_engine installed"""

    bl_idname = "promptgs.find_trainer"
    bl_label = "Find Trainer"

    def execute(self, context):
        found = find_python()
        if not found:
            self.report({"WARNING"}, "No Python with promptgs_engine found: set the path yourself")
            return {"CANCELLED"}
        prefs(context).python = found
        return {"FINISHED"}


class PROMPTGS_OT_test_trainer(bpy.types.Operator):
    """Check the trainer command: engine version and the backends it can use"""

    bl_idname = "promptgs.test_trainer"
    bl_label = "Test Trainer"

    def execute(self, context):
        p = prefs(context)
        info = probe(bpy.path.abspath(p.python) if p.python else "")
        if "error" in info:
            p.probe_result = info["error"]
            self.report({"ERROR"}, info["error"])
            return {"CANCELLED"}
        backends = ", ".join(info.get("backends") or []) or "none"
        p.probe_result = (f"promptgs_engine {info.get('version')} (torch {info.get('torch', '?')}), "
                          f"backends: {backends}" + (f" ({info['gpu']})" if info.get("gpu") else ""))
        self.report({"INFO"}, p.probe_result)
        return {"FINISHED"}


class PROMPTGS_OT_generate_dataset(bpy.types.Operator):
    """Render the synthetic mountain dataset in the background (promptgs dataset mountain)"""

    bl_idname = "promptgs.generate_dataset"
    bl_label = "Generate Test Dataset"

    def execute(self, context):
        settings = context.scene.promptgs
        out = (Path(bpy.path.abspath(settings.dataset_out)) if settings.dataset_out
               else training.output_root(context) / f"mountain-{time.strftime('%Y%m%d-%H%M%S')}")
        try:
            training.start_dataset_job(context, out, settings.dataset_preset, settings.seed)
        except training.UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class PROMPTGS_OT_reconstruct(bpy.types.Operator):
    """Make a dataset from a folder of photos or a video (structure from motion in the trainer's environment), then import it"""

    bl_idname = "promptgs.reconstruct"
    bl_label = "Reconstruct from Photos"

    filepath: StringProperty(subtype="FILE_PATH", description="A video file, or empty to use the folder")
    directory: StringProperty(subtype="DIR_PATH", description="A folder of photos")
    filter_folder: BoolProperty(default=True, options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath)) if self.filepath else None
        source = path if path is not None and path.is_file() else Path(bpy.path.abspath(self.directory))
        try:
            training.start_reconstruction(context, source)
        except training.UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, context.window_manager.promptgs_run.sfm_message)
        return {"FINISHED"}


class PROMPTGS_OT_cancel_reconstruct(bpy.types.Operator):
    """Stop structure from motion (a new run on the same photos resumes what was extracted and matched)"""

    bl_idname = "promptgs.cancel_reconstruct"
    bl_label = "Cancel Reconstruction"

    def execute(self, context):
        reconstruct.cancel()
        return {"FINISHED"}


class PROMPTGS_OT_render_preview(bpy.types.Operator):
    """Render the trained Gaussians from the active camera with the trainer's rasterizer (in the background)"""

    bl_idname = "promptgs.render_preview"
    bl_label = "Render Preview"

    def execute(self, context):
        return _start(self, context, training.start_preview, "preview_message")


def menu_import(self, context):
    self.layout.operator(PROMPTGS_OT_import_colmap.bl_idname, text="PromptGS COLMAP Dataset")


CLASSES = (
    PROMPTGS_OT_import_colmap, PROMPTGS_OT_use_camera, PROMPTGS_OT_add_prompt, PROMPTGS_OT_select_prompt,
    PROMPTGS_OT_remove_prompt, PROMPTGS_OT_propose, PROMPTGS_OT_accept_proposal, PROMPTGS_OT_train, PROMPTGS_OT_cancel, PROMPTGS_OT_load_result,
    PROMPTGS_OT_export_gaussians,
    PROMPTGS_OT_find_trainer, PROMPTGS_OT_test_trainer, PROMPTGS_OT_generate_dataset,
    PROMPTGS_OT_render_preview, PROMPTGS_OT_reconstruct, PROMPTGS_OT_cancel_reconstruct,
)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister():
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
