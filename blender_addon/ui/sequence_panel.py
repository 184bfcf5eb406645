"""The prompt sequence in the panel (bpy): a list of (prompt, seconds) rows made as one take, each segment
continuing the previous one (``MLDPipeline.sequence``); add, remove and reorder rows."""

from __future__ import annotations

import bpy
from bpy.props import StringProperty


class MLD_UL_sequence(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        row = layout.row(align=True)
        row.prop(item, "prompt", text="", emboss=False)
        row.prop(item, "seconds", text="")


class MLD_OT_sequence_edit(bpy.types.Operator):
    """Add, remove or move a segment of the prompt sequence"""

    bl_idname = "mld.sequence_edit"
    bl_label = "Edit Sequence"
    bl_options = {"REGISTER", "UNDO"}

    action: StringProperty(default="ADD")  # ADD (a copy of the prompt above), REMOVE, UP, DOWN

    def execute(self, context):
        s = context.scene.mld_motion
        rows, i = s.sequence, s.sequence_index
        if self.action == "ADD":
            row = rows.add()
            row.prompt, row.seconds = s.prompt, min(s.seconds, row.bl_rna.properties["seconds"].hard_max)
            s.sequence_index = len(rows) - 1
        elif not len(rows):
            return {"CANCELLED"}
        elif self.action == "REMOVE":
            rows.remove(i)
            s.sequence_index = max(0, min(i, len(rows) - 1))
        elif self.action in ("UP", "DOWN"):
            j = i - 1 if self.action == "UP" else i + 1
            if 0 <= j < len(rows):
                rows.move(i, j)
                s.sequence_index = j
        return {"FINISHED"}


def draw(layout, settings) -> None:
    """The list and its buttons; with rows, Generate makes them as one take (with Push to NLA: one strip a segment)."""
    box = layout.box()
    box.label(text="Sequence (one take from these, in order)" if len(settings.sequence) else "Sequence",
              icon="SEQ_STRIP_DUPLICATE")
    row = box.row()
    row.template_list("MLD_UL_sequence", "", settings, "sequence", settings, "sequence_index", rows=3)
    col = row.column(align=True)
    for action, icon in (("ADD", "ADD"), ("REMOVE", "REMOVE"), ("UP", "TRIA_UP"), ("DOWN", "TRIA_DOWN")):
        col.operator("mld.sequence_edit", text="", icon=icon).action = action
    if len(settings.sequence):
        box.prop(settings, "push_nla", text="One NLA Strip per Segment")


classes = (MLD_UL_sequence, MLD_OT_sequence_edit)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
