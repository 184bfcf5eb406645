"""Add-on preferences: model folder, device, threads, and getting PyTorch into Blender's Python (bpy)."""

from __future__ import annotations

import bpy
from bpy.props import EnumProperty, IntProperty, StringProperty

from .. import env
from . import runtime

ADDON_PACKAGE = __package__.rpartition(".")[0]  # the add-on itself (this module lives in its ui package)


def get_prefs(context=None):
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


def _model_dir_changed(self, context):
    runtime.cache().clear()


class MLD_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    model_dir: StringProperty(
        name="Model folder",
        description="Folder of a trained MLD model (config.json + safetensors); empty uses the model chosen in the "
        "panel (a bundled one)",
        subtype="DIR_PATH",
        default="",
        update=_model_dir_changed,
    )
    device: EnumProperty(
        name="Device",
        description="Where the model runs",
        items=[
            ("cpu", "CPU", "Run on the processor (always available)"),
            ("auto", "Automatic", "A GPU if PyTorch can use one, else the CPU"),
            ("cuda", "CUDA GPU", "An NVIDIA GPU (needs a CUDA build of PyTorch)"),
            ("mps", "Apple GPU", "Metal on Apple silicon"),
        ],
        default="cpu",
        update=_model_dir_changed,
    )
    threads: IntProperty(
        name="CPU threads",
        description="Threads PyTorch may use (0: its default, usually all cores)",
        default=0,
        min=0,
        max=256,
    )

    def draw(self, context):
        layout = self.layout
        col = layout.column()
        col.prop(self, "model_dir")
        row = col.row()
        row.prop(self, "device")
        row.prop(self, "threads")
        col.label(text=f"Model: {runtime.cache().describe()}", icon="INFO")

        box = layout.box()
        missing = env.missing_modules()
        installer = runtime.installer()
        if installer.running:
            box.label(text="Installing dependencies (see the system console) ...", icon="SORTTIME")
            if installer.last_line:
                box.label(text=installer.last_line[:120])
        elif missing:
            box.label(text="Missing: " + ", ".join(missing), icon="ERROR")
            box.label(text="Press the button to pip-install them for Blender's Python (about 200 MB, CPU build).")
            box.operator("mld.install_dependencies", icon="IMPORT")
        else:
            box.label(text="PyTorch and the other dependencies are available.", icon="CHECKMARK")
        if installer.message:
            box.label(text=installer.message, icon="ERROR" if installer.failed else "INFO")
        target = env.user_site_dir()
        if target is not None:
            box.label(text=f"Dependency folder: {target}")


classes = (MLD_AddonPreferences,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
