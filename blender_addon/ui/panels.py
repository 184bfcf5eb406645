"""The sidebar panel: View3D > Sidebar > MLD (bpy)."""

from __future__ import annotations

from pathlib import Path

import bpy

from .. import env
from . import quality_panel, sequence_panel
from . import runtime
from .operators import resolve_target


def _draw_model(layout, settings, context) -> None:
    """The Model choice (or the Preferences' folder that overrides it), and why Draft is off for a model without one."""
    from ..worker.model_choice import folder_override_for, folder_weights_line, has_draft, model_dir_for
    from .preferences import get_prefs

    prefs = get_prefs(context)
    override = folder_override_for(prefs)
    if override is not None:
        layout.label(text=f"Model: {Path(override).name or override} (set in Preferences)", icon="FILE_FOLDER")
        line = folder_weights_line(override)
        if line:
            layout.label(text=line)
    else:
        layout.prop(settings, "model")
    if settings.mode == "DRAFT" or settings.live_preview:
        if not has_draft(model_dir_for(settings, prefs)):
            layout.label(text="This model has no Draft: use Final (Live Preview needs a Draft)", icon="ERROR")


class MLD_PT_generate(bpy.types.Panel):
    bl_label = "Text to Motion"
    bl_idname = "MLD_PT_generate"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "MLD"

    def draw(self, context):
        layout = self.layout
        settings = getattr(context.scene, "mld_motion", None)
        if settings is None:
            layout.label(text="Not registered for this scene", icon="ERROR")
            return

        missing = env.missing_modules()
        if missing:
            box = layout.box()
            box.alert = True
            box.label(text="PyTorch is needed: " + ", ".join(missing) + " missing", icon="ERROR")
            col = box.column(align=True)
            col.label(text="Install it for Blender's Python:")
            col.operator("mld.install_dependencies", icon="IMPORT")
            col.label(text="(or Preferences > Add-ons > MLD Text to Motion)")

        layout.prop(settings, "prompt", text="")
        quality_panel.draw_coverage(layout, settings, context)
        col = layout.column(align=True)
        row = col.row(align=True)
        row.prop(settings, "seconds")
        row.prop(settings, "variants")
        row = col.row(align=True)
        row.prop(settings, "seed")
        row.operator("mld.randomize_seed", text="", icon="FILE_REFRESH")
        _draw_model(col, settings, context)
        row = col.row(align=True)
        row.prop(settings, "mode", expand=True)
        row = col.row(align=True)
        steps = row.row(align=True)
        steps.enabled = settings.mode == "FINAL"  # a Draft runs its own few steps
        steps.prop(settings, "steps")
        row.prop(settings, "guidance")
        row = layout.row(align=True)
        row.prop(settings, "live_preview", toggle=True, icon="PLAY")
        if settings.live_preview:
            row.operator("mld.keep_live", icon="CHECKMARK")
        row = layout.row(align=True)
        row.prop(settings, "loop", toggle=True)
        row.prop(settings, "follow_curve", text="", icon="CURVE_DATA")
        sequence_panel.draw(layout, settings)
        row = layout.row(align=True)
        row.prop(settings, "use_armature_keys")
        row.prop(settings, "keys_selected_only", text="Selected")
        row = layout.row(align=True)
        row.prop(settings, "preview", toggle=True)
        row.operator("mld.accept_take", icon="CHECKMARK")
        row.operator("mld.reject_take", icon="X")

        target = resolve_target(context)
        layout.prop(settings, "target", icon="ARMATURE_DATA")
        if settings.target is None:
            if target is not None:
                layout.label(text=f"Using the active armature {target.name}", icon="INFO")
            else:
                box = layout.box()
                box.label(text="No armature selected", icon="INFO")
                box.operator("mld.create_armature", icon="OUTLINER_OB_ARMATURE")
        row = layout.row(align=True)
        row.prop(settings, "exact", toggle=True)
        row.prop(settings, "set_frame_range", toggle=True)

        job = runtime.current_job()
        if settings.live_preview:
            layout.label(text="Live Preview: edits regenerate a Draft take", icon="INFO")
        elif job is not None:
            row = layout.row(align=True)
            label = f"{job.stage.capitalize()} {job.step_done}/{job.step_total}" if job.step_total else job.stage.capitalize()
            if hasattr(row, "progress"):
                row.progress(factor=job.progress, type="BAR", text=label)
            else:  # before Blender 4.0
                row.label(text=f"{label} ({job.progress:.0%})")
            row.operator("mld.cancel", text="", icon="CANCEL")
        else:
            layout.operator("mld.generate", icon="PLAY")

        if settings.last_error:
            box = layout.box()
            box.alert = True
            for index, line in enumerate(_wrap(settings.last_error, 48)):
                box.label(text=line, icon="ERROR" if index == 0 else "BLANK1")
        elif settings.last_message:
            box = layout.box()
            if settings.last_frames:
                box.label(text=f"{settings.last_frames} frames in {settings.last_seconds:.2f} s", icon="CHECKMARK")
                for name in settings.last_actions.split(", "):
                    box.label(text=name, icon="ACTION")
                quality_panel.draw_badges(layout, settings)
            else:
                box.label(text=settings.last_message, icon="INFO")


def _wrap(text: str, width: int) -> list[str]:
    words, lines, line = text.split(), [], ""
    for word in words:
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    if line:
        lines.append(line)
    return lines[:6] or [""]


classes = (MLD_PT_generate,)


def register():
    from . import export_panel, retarget_panel

    for cls in classes:
        bpy.utils.register_class(cls)
    retarget_panel.register()  # the Retarget sub-panel (after its parent), its operators and Object.mld_retarget
    quality_panel.register()  # the "What This Model Knows" sub-panel
    sequence_panel.register()  # the prompt sequence's list and its buttons
    export_panel.register()  # Game Engine Export: Actions into FBX / GLB / BVH files


def unregister():
    from . import export_panel, retarget_panel

    export_panel.unregister()
    sequence_panel.unregister()
    quality_panel.unregister()
    retarget_panel.unregister()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
