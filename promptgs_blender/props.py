"""Preferences, per-scene settings with the scene's training runs, and the (unsaved)
state of the other background jobs."""

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty,
                       PointerProperty, StringProperty)

from . import results
from .trainer import CPU_INDEX

ADDON_ID = __package__

COLOR_ATTRIBUTES = [
    ("error", "Error", "Accumulated pixel error per Gaussian"),
    ("score", "Score", "Prompt relevance score per Gaussian"),
    ("opacity", "Opacity", ""),
    ("scale", "Scale", "Mean of the three axis scales"),
    ("color", "Colour", "The trained colour (degree-0 SH; Material Preview / Rendered shading)"),
]
PRESETS = {"QUICK": 2000, "STANDARD": 7000, "FULL": 30000}


def prefs(context=None) -> "PromptGSPreferences":
    context = context or bpy.context
    return context.preferences.addons[ADDON_ID].preferences


class PromptGSPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    python: StringProperty(
        name="Trainer Python", subtype="FILE_PATH",
        description="A Python interpreter that has promptgs_engine installed (runs `python -m promptgs_engine`)")
    device: EnumProperty(
        name="Default Device", default="auto",
        items=[("auto", "Auto", "CUDA when the trainer sees a GPU, else CPU"),
               ("cpu", "CPU", "The C++ CPU rasterizer"), ("cuda", "CUDA", "gsplat on an NVIDIA GPU")])
    output_dir: StringProperty(
        name="Output Folder", subtype="DIR_PATH",
        description="Where runs are written (empty: next to the .blend file, or the temporary folder)")
    probe_result: StringProperty(name="Trainer check", default="")
    setup_folder: StringProperty(
        name="Environment Folder", subtype="DIR_PATH", default="",
        description="Where Set Up Trainer makes the Python environment (empty: trainer-env in this extension's "
                    "user folder)")
    setup_base: StringProperty(
        name="Base Python", subtype="FILE_PATH", default="",
        description="The Python 3.10+ (with its C headers) the environment is made from (empty: python3 on PATH, "
                    "else Blender's own)")
    setup_source: StringProperty(
        name="Engine Source", subtype="FILE_PATH", default="",
        description="A PromptGS checkout (the folder with pyproject.toml; built here, needs a C++ compiler) "
                    "or a promptgs wheel")
    setup_torch: EnumProperty(
        name="Torch", default="CPU", update=lambda self, context: self.set_torch_index(),
        items=[("CPU", "CPU", f"torch 2.13.0, CPU build (from {CPU_INDEX})"),
               ("CUDA", "CUDA", "torch 2.13.0 from PyPI (CUDA builds on Linux; several GB)")])
    torch_index: StringProperty(
        name="Torch Index", default=CPU_INDEX,
        description="Extra package index pip looks in for torch (empty: only pip's own configuration)")

    def set_torch_index(self) -> None:
        self.torch_index = CPU_INDEX if self.setup_torch == "CPU" else ""

    def draw(self, context):
        layout = self.layout
        jobs = context.window_manager.promptgs_run
        row = layout.row(align=True)
        row.prop(self, "python")
        row.operator("promptgs.find_trainer", text="", icon="VIEWZOOM")
        row.operator("promptgs.test_trainer", text="Test")
        for status, message in ((jobs.find_status, jobs.find_message), (jobs.probe_status, self.probe_result)):
            if status != "IDLE" and message:
                layout.label(text=message, icon=_STATUS_ICONS.get(status, "INFO"))
        layout.prop(self, "device")
        layout.prop(self, "output_dir")
        box = layout.box()
        box.label(text="Set Up Trainer: a Python environment with torch and the engine", icon="CONSOLE")
        col = box.column()
        col.prop(self, "setup_folder")
        col.prop(self, "setup_base")
        col.prop(self, "setup_source")
        col.row().prop(self, "setup_torch", expand=True)
        col.prop(self, "torch_index")
        if jobs.setup_status == "RUNNING":
            box.progress(factor=jobs.setup_progress, type="BAR", text=jobs.setup_stage)
            box.label(text=jobs.setup_message)
        else:
            box.operator("promptgs.setup_trainer", icon="IMPORT")
            if jobs.setup_status != "IDLE":
                box.label(text=jobs.setup_message, icon=_STATUS_ICONS.get(jobs.setup_status, "INFO"))
        if jobs.setup_log:
            box.label(text=f"Log: {jobs.setup_log}")


_STATUS_ICONS = {"ERROR": "ERROR", "DONE": "CHECKMARK", "CANCELLED": "CANCEL", "INTERRUPTED": "PAUSE",
                 "MISSING": "ERROR"}


def _apply_preset(self, context):
    if self.preset in PRESETS:
        self.iterations = PRESETS[self.preset]


def _recolor(self, context):
    results.recolor(context)


def _restyle(self, context):
    results.restyle(context)


RUN_STATES = [
    ("STARTING", "Starting", ""), ("RUNNING", "Running", ""), ("CANCELLING", "Cancelling", ""),
    ("CANCELLED", "Cancelled", "Stopped by the user; resumable from its last checkpoint"),
    ("INTERRUPTED", "Interrupted", "Stopped before its end (Blender quit or crashed); resumable"),
    ("DONE", "Done", ""), ("ERROR", "Error", ""), ("MISSING", "Missing", "Its run folder is gone")]
ACTIVE_STATES = ("STARTING", "RUNNING", "CANCELLING")


class PromptGSRun(bpy.types.PropertyGroup):
    """One training run of the scene: its folder, settings and last known state (saved in
    the .blend; ``name`` is its label, e.g. "Run 2")."""

    folder: StringProperty(name="Run Folder", subtype="DIR_PATH")
    job_path: StringProperty()
    log_path: StringProperty()
    summary: StringProperty(description="The settings it was started with")
    started: StringProperty()
    blend: StringProperty(description="The .blend file the run was started from")
    status: EnumProperty(name="Status", default="STARTING", items=RUN_STATES)
    message: StringProperty()
    error_lines: StringProperty()
    warning: StringProperty(description="A problem that did not stop the run (an unreadable snapshot)")
    last_output: StringProperty()
    last_snapshot: StringProperty()
    result_ply: StringProperty()
    shown: StringProperty(description="The snapshot or result its objects show")
    backend: StringProperty()
    snapshot_step: IntProperty()
    step: IntProperty()
    iterations: IntProperty()
    checkpoint_every: IntProperty()
    n_gaussians: IntProperty()
    loss: FloatProperty()
    psnr: FloatProperty()
    elapsed_s: FloatProperty()
    eta_s: FloatProperty()
    progress: FloatProperty(min=0.0, max=1.0, subtype="FACTOR")
    cancel_requested: BoolProperty()


class PromptGSSettings(bpy.types.PropertyGroup):
    dataset: StringProperty(name="Dataset", subtype="DIR_PATH",
                            description="Folder with images/ and sparse/0 (a COLMAP model)")
    images: StringProperty(name="Images", default="images",
                           description="Image folder inside the dataset (e.g. images_4 for quarter size)")
    root: PointerProperty(name="Root", type=bpy.types.Object,
                          description="The empty holding the imported dataset (dataset → Blender transform)")
    distortion: StringProperty(name="Distortion", default="")
    strategy: EnumProperty(name="Strategy", default="promptgs", items=[
        ("promptgs", "PromptGS", "Spend densification where the prompts are"),
        ("3dgs", "3DGS", "The original densification"), ("absgs", "AbsGS", "Absolute-gradient densification")])
    preset: EnumProperty(name="Preset", default="STANDARD", update=_apply_preset, items=[
        ("QUICK", "Quick", "2,000 steps"), ("STANDARD", "Standard", "7,000 steps"),
        ("FULL", "Full", "30,000 steps"), ("CUSTOM", "Custom", "Set the steps yourself")])
    iterations: IntProperty(
        name="Steps", default=7000, min=1,
        description="Steps that train whole views; PromptGS with prompts adds its focused crop steps on top (a quarter more)")
    budget: IntProperty(name="Budget", default=0, min=0, description="Maximum number of Gaussians (0: no limit)")
    auto_prompts: IntProperty(name="Auto Prompts", default=0, min=0,
                              description="Also add the error field's top N proposals as prompts (0: off)")
    propose_prompts: BoolProperty(
        name="Propose While Training", default=False,
        description="Part-way through densification, box what several views show and the render still misses "
                    "(small objects) and train them as prompts too (PromptGS strategy)")
    compact: BoolProperty(
        name="Compact", default=False,
        description="When growth ends, remove the Gaussians that carry the least of the training views "
                    "and fine-tune the rest (prompted objects are kept)")
    nproc: IntProperty(
        name="Processes", default=1, min=1, soft_max=8,
        description="Training processes on this machine (data-parallel, torchrun): each trains its share of "
                    "every step's views")
    backend: EnumProperty(name="Device", default="PREFS", items=[
        ("PREFS", "Default", "The default device of the preferences"), ("auto", "Auto", ""),
        ("cpu", "CPU", ""), ("cuda", "CUDA", "")])
    snapshot_every: IntProperty(name="Snapshot Every", default=500, min=1,
                                description="Steps between viewport updates")
    seed: IntProperty(name="Seed", default=0, min=0)
    color_by: EnumProperty(name="Colour By", items=COLOR_ATTRIBUTES, default="color",
                           update=_recolor)
    point_radius: FloatProperty(name="Point Size", default=0.01, min=0.0, precision=4,
                                update=_restyle)
    field_cutoff: FloatProperty(name="Field Cutoff", default=0.5, min=0.0, max=1.0, subtype="FACTOR",
                                update=_restyle,
                                description="Draw only loss-field voxels above this fraction of the loss range")
    display_style: EnumProperty(name="Draw As", default="AUTO", update=_restyle, items=[
        ("AUTO", "Auto", "Gaussians: Blender's own splats (5.3+), else splats up to 500,000 and points above; "
                         "the loss field: spheres up to 50,000 points, points above"),
        ("SPLATS", "Splats", "Each Gaussian with its scale, rotation and opacity: Blender's own splats (5.3+), "
                             "else instanced ellipsoids (Material Preview / Rendered shading)"),
        ("SPHERES", "Spheres", "Small spheres coloured in every shading mode (slow for many points)"),
        ("POINTS", "Points", "Point-cloud points, fast; colours in Material Preview and Rendered")])
    dataset_preset: EnumProperty(name="Preset", default="small", items=[
        ("tiny", "Tiny", "A few low-resolution views, for a quick look"),
        ("small", "Small", "A small dataset (minutes to render on a CPU)"),
        ("paper", "Paper", "The full-size dataset (long)")])
    dataset_out: StringProperty(name="Output", subtype="DIR_PATH", default="")
    init_ply: StringProperty(
        name="Start From", subtype="FILE_PATH", default="",
        description="A 3DGS PLY to start training from instead of the sparse points (e.g. the Gaussians "
                    "exported after cleaning them); empty: the sparse points")
    preview_run: StringProperty(
        name="Run", subtype="DIR_PATH", default="",
        description="Run folder to preview (empty: the shown training run)")
    checkpoint_every: IntProperty(
        name="Checkpoint Every", default=1000, min=1,
        description="Steps between checkpoints: a cancelled or interrupted run resumes from the last one")
    replace_shown: BoolProperty(
        name="Replace Shown Run", default=False,
        description="The new run's Gaussians replace the shown run's objects (its folder stays on disk); "
                    "off: the shown run's objects are kept, hidden, under Runs")
    start_error: StringProperty(description="Why the last Train Focused could not start")
    key: StringProperty(description="Which training runs belong to this scene (made with its first run)")
    runs: CollectionProperty(type=PromptGSRun)
    shown_run: StringProperty(name="Shown Run", default="",
                              description="The run whose objects the scene shows (the others are hidden)")


class PromptGSRunState(bpy.types.PropertyGroup):
    """What the panel shows about the other background jobs (dataset, reconstruction,
    preview, proposals, the trainer set-up and check); lives on the window manager."""

    dataset_status: EnumProperty(name="Dataset job", default="IDLE", items=[
        (s, s.title(), "") for s in ("IDLE", "RUNNING", "DONE", "ERROR")])
    dataset_message: StringProperty()
    dataset_out: StringProperty()
    sfm_status: EnumProperty(name="Reconstruction", default="IDLE", items=[
        (s, s.title(), "") for s in ("IDLE", "RUNNING", "DONE", "CANCELLED", "ERROR")])
    sfm_message: StringProperty()
    sfm_out: StringProperty()
    sfm_progress: FloatProperty(min=0.0, max=1.0, subtype="FACTOR")
    preview_status: EnumProperty(name="Preview job", default="IDLE", items=[
        (s, s.title(), "") for s in ("IDLE", "RUNNING", "DONE", "ERROR")])
    preview_message: StringProperty()
    propose_status: EnumProperty(name="Propose job", default="IDLE", items=[
        (s, s.title(), "") for s in ("IDLE", "RUNNING", "DONE", "ERROR")])
    propose_message: StringProperty()
    setup_status: EnumProperty(name="Set-up job", default="IDLE", items=[
        (s, s.title(), "") for s in ("IDLE", "RUNNING", "DONE", "ERROR")])
    setup_stage: StringProperty()
    setup_message: StringProperty()
    setup_progress: FloatProperty(min=0.0, max=1.0, subtype="FACTOR")
    setup_log: StringProperty()
    find_status: EnumProperty(default="IDLE", items=[(s, s.title(), "") for s in ("IDLE", "RUNNING", "DONE", "ERROR")])
    find_message: StringProperty()
    probe_status: EnumProperty(default="IDLE", items=[(s, s.title(), "") for s in ("IDLE", "RUNNING", "DONE", "ERROR")])


CLASSES = (PromptGSPreferences, PromptGSRun, PromptGSSettings, PromptGSRunState)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.promptgs = PointerProperty(type=PromptGSSettings)
    bpy.types.WindowManager.promptgs_run = PointerProperty(type=PromptGSRunState)
    bpy.types.Object.promptgs_weight = FloatProperty(
        name="Weight", default=1.0, min=0.0, description="How much training effort this prompt asks for")
    bpy.types.Object.promptgs_enabled = BoolProperty(
        name="Enabled", default=True, description="Send this prompt to the trainer")


def unregister():
    del bpy.types.Object.promptgs_enabled
    del bpy.types.Object.promptgs_weight
    del bpy.types.WindowManager.promptgs_run
    del bpy.types.Scene.promptgs
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
