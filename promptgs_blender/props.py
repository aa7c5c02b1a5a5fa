"""Preferences, per-scene settings and the (unsaved) state of the running job."""

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)

from . import results

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

    def draw(self, context):
        layout = self.layout
        row = layout.row(align=True)
        row.prop(self, "python")
        row.operator("promptgs.find_trainer", text="", icon="VIEWZOOM")
        row.operator("promptgs.test_trainer", text="Test")
        if self.probe_result:
            layout.label(text=self.probe_result, icon="INFO")
        layout.prop(self, "device")
        layout.prop(self, "output_dir")


def _apply_preset(self, context):
    if self.preset in PRESETS:
        self.iterations = PRESETS[self.preset]


def _recolor(self, context):
    results.recolor(context)


def _restyle(self, context):
    results.restyle(context)


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
        description="Run folder to preview (empty: the current or last training run)")


class PromptGSRunState(bpy.types.PropertyGroup):
    """What the panel shows about the running (or last) job; lives on the window manager."""

    status: EnumProperty(name="Status", default="IDLE", items=[
        (s, s.title(), "") for s in ("IDLE", "STARTING", "RUNNING", "CANCELLING", "CANCELLED", "DONE", "ERROR")])
    message: StringProperty()
    error_lines: StringProperty()
    last_output: StringProperty()
    out_dir: StringProperty()
    job_path: StringProperty()
    log_path: StringProperty()
    last_snapshot: StringProperty()
    result_ply: StringProperty()
    backend: StringProperty()
    snapshot_step: IntProperty()
    step: IntProperty()
    iterations: IntProperty()
    n_gaussians: IntProperty()
    loss: FloatProperty()
    psnr: FloatProperty()
    elapsed_s: FloatProperty()
    eta_s: FloatProperty()
    progress: FloatProperty(min=0.0, max=1.0, subtype="FACTOR")
    cancel_requested: BoolProperty()
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


CLASSES = (PromptGSPreferences, PromptGSSettings, PromptGSRunState)


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
