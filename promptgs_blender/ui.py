"""The PromptGS sidebar panel (View3D > Sidebar > PromptGS)."""

from __future__ import annotations

from pathlib import Path

import bpy

from . import prompts, proposals, results, training
from .props import ACTIVE_STATES, prefs


def _duration(seconds: float) -> str:
    seconds = int(max(seconds, 0))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}" if seconds >= 3600 \
        else f"{seconds // 60}:{seconds % 60:02d}"


class PromptGSPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "PromptGS"


class PROMPTGS_PT_dataset(PromptGSPanel, bpy.types.Panel):
    bl_label = "Dataset"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.promptgs
        state = context.window_manager.promptgs_run
        layout.operator("promptgs.import_colmap", icon="IMPORT")
        if state.sfm_status == "RUNNING":
            layout.operator("promptgs.cancel_reconstruct", icon="CANCEL")
            layout.progress(factor=state.sfm_progress, type="BAR", text=state.sfm_message)
        else:
            layout.operator("promptgs.reconstruct", icon="OUTLINER_OB_CAMERA")
            if state.sfm_status != "IDLE":
                icon = {"ERROR": "ERROR", "DONE": "CHECKMARK", "CANCELLED": "CANCEL"}.get(state.sfm_status, "INFO")
                layout.label(text=state.sfm_message, icon=icon)
        col = layout.column()
        col.prop(settings, "root")
        col.prop(settings, "images")
        if settings.distortion:
            box = layout.box()
            for note in settings.distortion.split("; "):
                box.label(text=note, icon="ERROR")
        cam = context.active_object
        if cam is not None and cam.type == "CAMERA" and "promptgs_width" in cam.data:
            layout.operator("promptgs.use_camera", icon="CAMERA_DATA").name = cam.name
        row = layout.row(align=True)
        row.prop(settings, "dataset_preset", text="")
        row.operator("promptgs.generate_dataset", text="Test Dataset", icon="RENDER_STILL")
        if state.dataset_status != "IDLE":
            layout.label(text=state.dataset_message, icon="ERROR" if state.dataset_status == "ERROR" else "INFO")
        if state.dataset_status == "DONE" and state.dataset_out:
            op = layout.operator("promptgs.import_colmap", text="Import Generated Dataset", icon="IMPORT")
            op.directory = state.dataset_out


class PROMPTGS_PT_prompts(PromptGSPanel, bpy.types.Panel):
    bl_label = "Prompts"

    def draw(self, context):
        layout = self.layout
        state = context.window_manager.promptgs_run
        row = layout.row(align=True)
        row.operator("promptgs.add_prompt", icon="CUBE")
        row.operator("promptgs.propose", icon="VIEWZOOM")
        if state.propose_status != "IDLE":
            icon = {"ERROR": "ERROR", "DONE": "CHECKMARK"}.get(state.propose_status, "INFO")
            layout.label(text=state.propose_message, icon=icon)
        items = prompts.prompt_objects(context.scene)
        proposed = proposals.proposed_objects(context.scene)
        if not items and not proposed:
            layout.label(text="No prompts: the whole scene counts the same")
        for obj in items:
            row = layout.row(align=True)
            row.prop(obj, "promptgs_enabled", text="")
            sub = row.row(align=True)
            sub.active = obj.promptgs_enabled
            sub.operator("promptgs.select_prompt", text=obj.name, depress=obj.select_get(),
                         emboss=True).name = obj.name
            sub.prop(obj, "promptgs_weight", text="")
            row.operator("promptgs.remove_prompt", text="", icon="X").name = obj.name
        if proposed:
            box = layout.box()
            box.label(text=f"Proposed ({len(proposed)}): accept or delete", icon="QUESTION")
            for obj in proposed:
                row = box.row(align=True)
                row.operator("promptgs.select_prompt", text=obj.name, depress=obj.select_get()).name = obj.name
                row.label(text=f"{obj['promptgs_confidence']:.2f}  {obj.get('promptgs_views', '')}")
                row.operator("promptgs.accept_proposal", text="", icon="CHECKMARK").name = obj.name
                row.operator("promptgs.remove_prompt", text="", icon="X").name = obj.name
            box.operator("promptgs.accept_proposal", text="Accept All", icon="CHECKMARK").name = ""


ICONS = {"ERROR": "ERROR", "DONE": "CHECKMARK", "CANCELLED": "CANCEL", "INTERRUPTED": "PAUSE",
         "MISSING": "ERROR", "RUNNING": "PLAY", "STARTING": "TIME", "CANCELLING": "TIME"}


def draw_run(layout, record) -> None:
    """The shown run: progress while it trains, its last output line, its state, its
    error and warning with the log's path."""
    state = training.view(record)
    live = training.live_of(record) is not None
    box = layout.box()
    box.label(text=f"{record.name}: {record.summary}", icon="POINTCLOUD_DATA")
    if live and state.status in ACTIVE_STATES:
        box.progress(factor=state.progress, type="BAR",
                     text=f"{state.step} / {state.iterations}  ETA {_duration(state.eta_s)}")
    if state.step or state.n_gaussians:
        grid = box.grid_flow(columns=2, align=True)
        grid.label(text=f"Loss {state.loss:.4f}")
        grid.label(text=f"PSNR {state.psnr:.2f} dB")
        grid.label(text=f"{state.n_gaussians:,} Gaussians")
        grid.label(text=f"{_duration(state.elapsed_s)} elapsed")
    if state.snapshot_step:
        box.label(text=f"Viewport shows step {state.snapshot_step}", icon="POINTCLOUD_DATA")
    status = state.status if live or state.status not in ACTIVE_STATES else "INTERRUPTED"
    box.label(text=state.message or status.title(), icon=ICONS.get(status, "INFO"))
    if state.last_output:
        box.label(text=state.last_output, icon="CONSOLE")
    if state.warning:
        box.label(text=state.warning, icon="ERROR")
    if status == "ERROR" and state.error_lines:
        sub = box.box()
        for line in state.error_lines.splitlines():
            sub.label(text=line)
    if status in ("ERROR", "CANCELLED", "INTERRUPTED") or state.warning:
        box.label(text=f"Log: {state.log_path or record.log_path}")
    box.label(text=f"Folder: {record.folder}", icon="FILE_FOLDER")
    if training.resumable(record):
        box.operator("promptgs.resume", icon="PLAY").name = record.name
    if state.result_ply:
        box.operator("promptgs.load_result", icon="IMPORT")


class PROMPTGS_PT_train(PromptGSPanel, bpy.types.Panel):
    bl_label = "Train Focused"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.promptgs
        col = layout.column()
        col.prop(settings, "strategy")
        col.prop(settings, "preset")
        row = col.row()
        row.enabled = settings.preset == "CUSTOM"
        row.prop(settings, "iterations")
        col.prop(settings, "budget")
        col.prop(settings, "auto_prompts")
        sub = col.row()
        sub.enabled = settings.strategy == "promptgs"
        sub.prop(settings, "propose_prompts")
        col.prop(settings, "compact")
        col.prop(settings, "backend")
        col.prop(settings, "nproc")
        col.prop(settings, "snapshot_every")
        col.prop(settings, "checkpoint_every")
        col.prop(settings, "replace_shown")
        col.prop(settings, "init_ply")
        if not prefs(context).python:
            layout.label(text="No trainer: Preferences > Add-ons > PromptGS: Find, or Set Up Trainer", icon="ERROR")
        record = training.shown_record(context.scene)
        live = training.live_of(record)
        if live is not None and live.progress.status in ACTIVE_STATES:
            layout.operator("promptgs.cancel", icon="CANCEL")
        else:
            layout.operator("promptgs.train", icon="PLAY")
        if settings.start_error:
            layout.label(text=settings.start_error, icon="ERROR")
        if record is not None:
            draw_run(layout, record)


class PROMPTGS_PT_runs(PromptGSPanel, bpy.types.Panel):
    """The scene's runs (the eye shows one: compare them) and the runs still training for
    another file."""

    bl_label = "Runs"
    bl_parent_id = "PROMPTGS_PT_train"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.promptgs
        if not settings.runs:
            layout.label(text="No runs yet")
        for record in settings.runs:
            state = training.view(record)
            row = layout.row(align=True)
            shown = record.name == settings.shown_run
            row.operator("promptgs.show_run", text="", icon="HIDE_OFF" if shown else "HIDE_ON",
                         depress=shown).name = record.name
            psnr = f", {state.psnr:.2f} dB" if state.psnr else ""
            row.label(text=f"{record.name}: {state.status.title()}{psnr}", icon=ICONS.get(state.status, "INFO"))
            row.operator("promptgs.remove_run", text="", icon="X").name = record.name
        detached = training.detached_runs()
        if detached:
            box = layout.box()
            box.label(text="Training for a file that is not open:", icon="INFO")
            for live in detached:
                row = box.row(align=True)
                where = Path(live.blend).name if live.blend else "an unsaved file"
                row.label(text=f"{live.name} ({where}): step {live.progress.step} / {live.progress.iterations}")
                row.operator("promptgs.attach_run", text="", icon="LINKED").folder = live.folder
                row.operator("promptgs.cancel_detached", text="", icon="CANCEL").folder = live.folder


class PROMPTGS_PT_preview(PromptGSPanel, bpy.types.Panel):
    bl_label = "Preview"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.promptgs
        state = context.window_manager.promptgs_run
        layout.prop(context.scene, "camera")
        layout.prop(settings, "preview_run")
        record = training.shown_record(context.scene)
        if not settings.preview_run and record is not None:
            layout.label(text=f"{record.name}: {record.folder}", icon="FILE_FOLDER")
        layout.operator("promptgs.render_preview", icon="RENDER_STILL")
        if state.preview_status != "IDLE":
            icon = {"ERROR": "ERROR", "DONE": "CHECKMARK"}.get(state.preview_status, "INFO")
            layout.label(text=state.preview_message, icon=icon)


class PROMPTGS_PT_display(PromptGSPanel, bpy.types.Panel):
    bl_label = "Display"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        settings = context.scene.promptgs
        layout.prop(settings, "color_by")
        obj = bpy.data.objects.get(results.GAUSSIANS)
        if obj is not None and obj.get("promptgs_color_note"):
            layout.label(text=obj["promptgs_color_note"], icon="INFO")
        layout.prop(settings, "display_style")
        layout.prop(settings, "point_radius")
        layout.prop(settings, "field_cutoff")
        layout.operator("promptgs.load_result", text="Load PLY…", icon="FILE")
        layout.operator("promptgs.export_gaussians", text="Export Gaussians…", icon="EXPORT")


CLASSES = (PROMPTGS_PT_dataset, PROMPTGS_PT_prompts, PROMPTGS_PT_train, PROMPTGS_PT_runs, PROMPTGS_PT_preview,
           PROMPTGS_PT_display)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
