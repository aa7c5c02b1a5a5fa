"""The PromptGS sidebar panel (View3D > Sidebar > PromptGS)."""

from __future__ import annotations

import bpy

from . import prompts, proposals, results, training


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
        sub = row.row(align=True)
        sub.enabled = state.propose_status != "RUNNING"
        sub.operator("promptgs.propose", icon="VIEWZOOM")
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


class PROMPTGS_PT_train(PromptGSPanel, bpy.types.Panel):
    bl_label = "Train Focused"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.promptgs
        state = context.window_manager.promptgs_run
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
        col.prop(settings, "init_ply")
        running = training.current_run() is not None and state.status in ("STARTING", "RUNNING", "CANCELLING")
        if running:
            layout.operator("promptgs.cancel", icon="CANCEL")
        else:
            layout.operator("promptgs.train", icon="PLAY")
        if state.status == "IDLE":
            return
        if state.status in ("STARTING", "RUNNING", "CANCELLING"):
            layout.progress(factor=state.progress, type="BAR",
                            text=f"{state.step} / {state.iterations}  ETA {_duration(state.eta_s)}")
        grid = layout.grid_flow(columns=2, align=True)
        grid.label(text=f"Loss {state.loss:.4f}")
        grid.label(text=f"PSNR {state.psnr:.2f} dB")
        grid.label(text=f"{state.n_gaussians:,} Gaussians")
        grid.label(text=f"{_duration(state.elapsed_s)} elapsed")
        if state.snapshot_step:
            layout.label(text=f"Viewport shows step {state.snapshot_step}", icon="POINTCLOUD_DATA")
        icon = {"ERROR": "ERROR", "DONE": "CHECKMARK", "CANCELLED": "CANCEL"}.get(state.status, "INFO")
        layout.label(text=state.message or state.status.title(), icon=icon)
        if state.out_dir:
            layout.label(text=f"Run: {state.out_dir}", icon="FILE_FOLDER")
        if state.status == "ERROR":
            box = layout.box()
            for line in state.error_lines.splitlines():
                box.label(text=line)
            if state.log_path:
                box.label(text=f"Log: {state.log_path}")
        if state.result_ply:
            layout.operator("promptgs.load_result", icon="IMPORT")


class PROMPTGS_PT_preview(PromptGSPanel, bpy.types.Panel):
    bl_label = "Preview"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.promptgs
        state = context.window_manager.promptgs_run
        layout.prop(context.scene, "camera")
        layout.prop(settings, "preview_run")
        if not settings.preview_run and state.out_dir:
            layout.label(text=f"Run: {state.out_dir}", icon="FILE_FOLDER")
        row = layout.row()
        row.enabled = state.preview_status != "RUNNING"
        row.operator("promptgs.render_preview", icon="RENDER_STILL")
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


CLASSES = (PROMPTGS_PT_dataset, PROMPTGS_PT_prompts, PROMPTGS_PT_train, PROMPTGS_PT_preview, PROMPTGS_PT_display)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
