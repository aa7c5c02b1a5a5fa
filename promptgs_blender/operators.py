"""Operators: import, prompts, train / cancel / resume and the runs list, load result, export Gaussians, the
trainer's check and set-up, dataset generation, reconstruction, previews.

None of them is modal: a job is followed by a timer (training.drain_and_apply), so Esc
means nothing to it and Blender autosaves while it goes. The exception is
``promptgs.notify``, which lives for one timer event to put a message in the status bar.
Each has a ``poll`` where it cannot always run, so its button is greyed out then.
"""

import time
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper
from mathutils import Vector

from . import colmap, display, importer, plyio, preview, prompts, proposals, reconstruct, results, training
from .props import prefs


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

    @classmethod
    def poll(cls, context):
        return any(obj.type == "CAMERA" for obj in context.scene.objects)

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

    @classmethod
    def poll(cls, context):
        return context.mode in ("OBJECT", "EDIT_MESH")

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
    job panel's ``message`` field as information."""
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

    @classmethod
    def poll(cls, context):
        return proposals.current_job() is None and _has_chosen_run(context)

    def execute(self, context):
        return _start(self, context, training.start_propose, "propose_message")


class PROMPTGS_OT_accept_proposal(bpy.types.Operator):
    """Make this proposed cube a prompt (empty name: every proposed cube)"""

    bl_idname = "promptgs.accept_proposal"
    bl_label = "Accept Proposal"
    bl_options = {"REGISTER", "UNDO"}

    name: StringProperty()

    @classmethod
    def poll(cls, context):
        return bool(proposals.proposed_objects(context.scene))

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


def _has_chosen_run(context) -> bool:
    return bool(context.scene.promptgs.preview_run) or training.shown_record(context.scene) is not None


def _shown_live(context):
    return training.live_of(training.shown_record(context.scene))


class PROMPTGS_OT_train(bpy.types.Operator):
    """Train with the prompts as a new run of this scene, in a separate trainer process (the shown run's objects are kept, unless Replace Shown Run)"""

    bl_idname = "promptgs.train"
    bl_label = "Train Focused"

    @classmethod
    def poll(cls, context):
        return training.has_dataset(context) and training.any_live() is None

    def execute(self, context):
        try:
            training.start_training(context)
        except training.UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        record = training.shown_record(context.scene)
        self.report({"INFO"}, f"{record.name}: training into {record.folder}")
        return {"FINISHED"}


class PROMPTGS_OT_cancel(bpy.types.Operator):
    """Stop the shown run's trainer (every process of it); its last snapshot stays shown and Resume continues from its last checkpoint"""

    bl_idname = "promptgs.cancel"
    bl_label = "Cancel Training"

    @classmethod
    def poll(cls, context):
        live = _shown_live(context)
        return live is not None and live.progress.status in ("STARTING", "RUNNING")

    def invoke(self, context, event):
        record = training.shown_record(context.scene)
        redo = training.unsaved_seconds(record)
        if redo < training.CONFIRM_AFTER_S:
            return self.execute(context)
        return context.window_manager.invoke_confirm(
            self, event, title="Cancel Training?", confirm_text="Cancel Training", icon="WARNING",
            message=f"{record.name}: Resume continues from its last checkpoint; the "
                    f"{training.unsaved_seconds(record) / 60:.0f} min trained since then are trained again")

    def execute(self, context):
        training.cancel_training(context)
        return {"FINISHED"}


class PROMPTGS_OT_resume(bpy.types.Operator):
    """Continue this stopped run from its last checkpoint (promptgs train --resume)"""

    bl_idname = "promptgs.resume"
    bl_label = "Resume"

    name: StringProperty(description="The run (empty: the shown run)")

    @classmethod
    def poll(cls, context):
        return training.any_live() is None and any(training.resumable(r) for r in context.scene.promptgs.runs)

    def execute(self, context):
        try:
            training.resume_training(context, self.name)
        except training.UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class PROMPTGS_OT_show_run(bpy.types.Operator):
    """Show this run's Gaussians (the shown run's are kept, hidden)"""

    bl_idname = "promptgs.show_run"
    bl_label = "Show Run"
    bl_options = {"UNDO"}

    name: StringProperty()

    def execute(self, context):
        try:
            training.show_run(context, self.name)
        except training.UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class PROMPTGS_OT_remove_run(bpy.types.Operator):
    """Forget this run and delete its objects (its folder stays on disk)"""

    bl_idname = "promptgs.remove_run"
    bl_label = "Remove Run"
    bl_options = {"UNDO"}

    name: StringProperty()

    def invoke(self, context, event):
        return context.window_manager.invoke_confirm(self, event)

    def execute(self, context):
        try:
            training.remove_run(context, self.name)
        except training.UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class PROMPTGS_OT_attach_run(bpy.types.Operator):
    """Make this run, still training for a file that is not open, a run of this scene"""

    bl_idname = "promptgs.attach_run"
    bl_label = "Attach Here"

    folder: StringProperty()

    def execute(self, context):
        try:
            training.attach_here(context, self.folder)
        except training.UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class PROMPTGS_OT_cancel_detached(bpy.types.Operator):
    """Stop this run, still training for a file that is not open"""

    bl_idname = "promptgs.cancel_detached"
    bl_label = "Cancel"

    folder: StringProperty()

    def execute(self, context):
        training.cancel_detached(self.folder)
        return {"FINISHED"}


class PROMPTGS_OT_notify(bpy.types.Operator):
    """Show a message in the status bar"""

    bl_idname = "promptgs.notify"
    bl_label = "PromptGS Message"
    bl_options = {"INTERNAL"}

    level: EnumProperty(items=[(k, k.title(), "") for k in ("INFO", "WARNING", "ERROR")], default="INFO")
    message: StringProperty()

    def execute(self, context):  # called from a script: the report goes to the console
        self.report({self.level}, self.message)
        return {"FINISHED"}

    def invoke(self, context, event):
        # What a script-called operator reports goes to the console only; what a modal
        # operator reports goes to the status bar. So this one waits for one timer event.
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.01, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        self.report({self.level}, self.message)
        return {"FINISHED"}


class PROMPTGS_OT_load_result(bpy.types.Operator, ImportHelper):
    """Load a 3D Gaussian Splatting PLY as the PromptGS Gaussians object (the shown run's objects are kept, hidden)"""

    bl_idname = "promptgs.load_result"
    bl_label = "Load Result"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})

    def invoke(self, context, event):
        record = training.shown_record(context.scene)
        if record is not None and record.result_ply and not self.filepath:
            self.filepath = record.result_ply
        return ImportHelper.invoke(self, context, event)

    def execute(self, context):
        training.park(context)  # a run's objects stay that run's
        context.scene.promptgs.shown_run = ""
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
    """Look for a Python that has promptgs_engine installed (in the background)"""

    bl_idname = "promptgs.find_trainer"
    bl_label = "Find Trainer"

    @classmethod
    def poll(cls, context):
        return not training.checks_running()[0]

    def execute(self, context):
        training.start_find(context)
        return {"FINISHED"}


class PROMPTGS_OT_test_trainer(bpy.types.Operator):
    """Check the trainer command in the background: engine version and the backends it can use"""

    bl_idname = "promptgs.test_trainer"
    bl_label = "Test Trainer"

    @classmethod
    def poll(cls, context):
        return bool(prefs(context).python) and not training.checks_running()[1]

    def execute(self, context):
        training.start_probe(context)
        return {"FINISHED"}


class PROMPTGS_OT_setup_trainer(bpy.types.Operator):
    """Make a Python environment with torch and the engine (from the engine source) and set it as the Trainer Python"""

    bl_idname = "promptgs.setup_trainer"
    bl_label = "Set Up Trainer"

    @classmethod
    def poll(cls, context):
        return not training.setup_running()

    def invoke(self, context, event):
        p = prefs(context)
        return context.window_manager.invoke_confirm(
            self, event, title="Set Up Trainer?", confirm_text="Set Up", icon="QUESTION",
            message=f"Make a Python environment in {training.setup_folder(context)} with torch ({p.setup_torch}) "
                    f"and the engine from {p.setup_source or '(choose the Engine Source first)'}: "
                    "about 1 GB of downloads and a few minutes of compiling")

    def execute(self, context):
        try:
            training.start_setup(context)
        except training.UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class PROMPTGS_OT_generate_dataset(bpy.types.Operator):
    """Render the synthetic mountain dataset in the background (promptgs dataset mountain)"""

    bl_idname = "promptgs.generate_dataset"
    bl_label = "Generate Test Dataset"

    @classmethod
    def poll(cls, context):
        return not training.dataset_running()

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

    filepath: StringProperty(subtype="FILE_PATH", description="A video file; a photo means the folder it is in")
    directory: StringProperty(subtype="DIR_PATH", description="A folder of photos")
    filter_folder: BoolProperty(default=True, options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return not reconstruct.running()

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath)) if self.filepath else None
        source = reconstruct.source_of(path, Path(bpy.path.abspath(self.directory)))
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

    @classmethod
    def poll(cls, context):
        return reconstruct.running()

    def execute(self, context):
        reconstruct.cancel()
        return {"FINISHED"}


class PROMPTGS_OT_render_preview(bpy.types.Operator):
    """Render the trained Gaussians from the active camera with the trainer's rasterizer (in the background)"""

    bl_idname = "promptgs.render_preview"
    bl_label = "Render Preview"

    @classmethod
    def poll(cls, context):
        return preview.current_job() is None and context.scene.camera is not None and _has_chosen_run(context)

    def execute(self, context):
        return _start(self, context, training.start_preview, "preview_message")


def menu_import(self, context):
    self.layout.operator(PROMPTGS_OT_import_colmap.bl_idname, text="PromptGS COLMAP Dataset")


CLASSES = (
    PROMPTGS_OT_import_colmap, PROMPTGS_OT_use_camera, PROMPTGS_OT_add_prompt, PROMPTGS_OT_select_prompt,
    PROMPTGS_OT_remove_prompt, PROMPTGS_OT_propose, PROMPTGS_OT_accept_proposal, PROMPTGS_OT_train,
    PROMPTGS_OT_cancel, PROMPTGS_OT_resume, PROMPTGS_OT_show_run, PROMPTGS_OT_remove_run, PROMPTGS_OT_attach_run,
    PROMPTGS_OT_cancel_detached, PROMPTGS_OT_notify, PROMPTGS_OT_load_result,
    PROMPTGS_OT_export_gaussians,
    PROMPTGS_OT_find_trainer, PROMPTGS_OT_test_trainer, PROMPTGS_OT_setup_trainer, PROMPTGS_OT_generate_dataset,
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
