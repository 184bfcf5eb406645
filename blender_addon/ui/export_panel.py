"""The Game Engine Export sub-panel (bpy): the target armature's Actions, ticked in a list, written as FBX, GLB and
BVH files for Unity, Unreal or Godot (docs/game_engines.md).

Settings live on the scene (``scene.mld_export``), the tick on each Action (``action.mld_export``, saved with the
file). The operator is an adapter over ``do_export_takes(obj, actions, folder, settings)``, which returns
``(level, message)``; :func:`export_problem` is the button's poll message.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, PointerProperty, StringProperty

from mld_core.rig import engine_export as ee

from ..scene import key_takes

ROOT_MOTION_ITEMS = (
    ("object", "On the Hips", "The hips carry the travel, as the take plays in Blender"),
    ("in-place", "In Place", "The travel is taken off the body and kept nowhere: the engine moves the character"),
    ("root-bone", "Root Bone", "A root bone on the ground carries the travel; the body hangs from it (root motion)"),
)


def _naming_items(self, context):
    return _NAMING_ITEMS


_NAMING_ITEMS = [(n.name, n.label, n.description) for n in ee.load_namings().values()]


class MLD_ExportSettings(bpy.types.PropertyGroup):
    folder: StringProperty(name="Folder", subtype="DIR_PATH", default="//engine/",
                           description="Where the files go (// is the .blend's folder)")
    fbx: BoolProperty(name="FBX", default=True, description="Unity, Unreal and Godot: armature, body and takes")
    glb: BoolProperty(name="GLB", default=False, description="glTF binary (Godot, Unity with glTFast, web)")
    bvh: BoolProperty(name="BVH", default=False, description="Motion only, Y up, centimetres (one file per take)")
    one_file: BoolProperty(name="One File", default=False,
                           description="One FBX / GLB holding every ticked take as its own animation (named after "
                                       "the armature); off: one file per take")
    root_motion: EnumProperty(name="Travel", items=ROOT_MOTION_ITEMS, default="object",
                              description="Where the take's travel over the ground goes")
    yaw: BoolProperty(name="Turning Too", default=False,
                      description="In Place / Root Bone: the take's turning goes with its travel")
    bone_names: EnumProperty(name="Bone Names", items=_naming_items,
                             description="Bone names in the files, so the engine's humanoid mapping finds them")
    overwrite: BoolProperty(name="Replace Files", default=False, description="Replace files that exist")
    index: IntProperty(name="Active Action", default=0)

    def formats(self) -> list[str]:
        return [fmt for fmt in ee.FORMATS if getattr(self, fmt)]


# -- plain functions --------------------------------------------------------------------------------------------
def ticked_actions(obj) -> list:
    """The Actions ticked for export that animate ``obj`` (key one of its bones), by name."""
    if obj is None:
        return []
    from ..scene.action_joints import animates

    bones = {b.name: b.name for b in obj.data.bones}
    return sorted((a for a in bpy.data.actions if getattr(a, "mld_export", False) and animates(a, obj, bones)),
                  key=lambda a: a.name)


def export_problem(context) -> str:
    """'' when Export Takes can run, else why not (the button's tooltip)."""
    from .operators import resolve_target

    settings = getattr(context.scene, "mld_export", None)
    if settings is None:
        return "The add-on is not registered for this scene"
    obj = resolve_target(context)
    if obj is None:
        return "Pick an armature first"
    if not settings.formats():
        return "Tick a format: FBX, GLB or BVH"
    if not ticked_actions(obj):
        return f"Tick the Actions of {obj.name} to export in the list"
    if not settings.folder.strip():
        return "Choose a folder for the files"
    if settings.folder.startswith("//") and not bpy.data.filepath:
        return "Save the .blend first (the folder is relative to it), or choose an absolute folder"
    return ""


def do_export_takes(obj, actions, folder: str, settings) -> tuple[str, str]:
    """Write ``actions`` of ``obj`` into ``folder`` as ``settings`` (``scene.mld_export``) say, all files or none."""
    from mld_core.fileio import OutputSet
    from mld_core.inputs import InputError

    from ..scene import export_takes

    try:
        chosen = ee.ExportSettings.parse(settings.formats(), settings.root_motion, settings.yaw and
                                         settings.root_motion != "object", settings.bone_names, settings.one_file)
        target = bpy.path.abspath(folder)
        files = ee.export_files(target, ee.file_stem(obj.name), [a.name for a in actions], chosen)
        ee.check_export_files(files, {}, {}, overwrite=settings.overwrite)
        with OutputSet(overwrite=settings.overwrite) as outputs:
            export_takes.export_takes(obj, actions, files, chosen, outputs, bone_map=key_takes.bone_map_of(obj))
    except (InputError, FileExistsError) as exc:
        return "ERROR", str(exc).replace("pass --overwrite to replace it", "tick Replace Files to replace it")
    except OSError as exc:
        return "ERROR", f"Could not write into {folder}: {exc.strerror or exc}"
    except RuntimeError as exc:  # an exporter that did not finish: nothing was put in place
        return "ERROR", str(exc).strip().splitlines()[-1]
    takes = f"{len(actions)} take{'s' if len(actions) != 1 else ''}"
    return "INFO", f"Exported {takes} to {len(files)} file{'s' if len(files) != 1 else ''} in {target}"


# -- operator and panel -----------------------------------------------------------------------------------------
class MLD_OT_export_takes(bpy.types.Operator):
    """Write the ticked Actions as FBX / GLB / BVH files for a game engine, with the travel and bone names chosen
    below (every file written, or none)"""

    bl_idname = "mld.export_takes"
    bl_label = "Export Takes"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        problem = export_problem(context)
        if problem:
            cls.poll_message_set(problem)
        return not problem

    def execute(self, context):
        from .operators import resolve_target

        obj = resolve_target(context)
        level, message = do_export_takes(obj, ticked_actions(obj), context.scene.mld_export.folder,
                                         context.scene.mld_export)
        self.report({level}, message)
        return {"FINISHED"} if level != "ERROR" else {"CANCELLED"}


class MLD_UL_export_actions(bpy.types.UIList):
    """The Actions that animate the target armature, each with its Export tick."""

    bl_idname = "MLD_UL_export_actions"

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        row = layout.row(align=True)
        row.prop(item, "mld_export", text="")
        row.label(text=item.name, icon="ACTION")

    def filter_items(self, context, data, propname):
        from ..scene.action_joints import animates
        from .operators import resolve_target

        obj = resolve_target(context)
        actions = getattr(data, propname)
        bones = {b.name: b.name for b in obj.data.bones} if obj is not None else {}
        flags = [self.bitflag_filter_item if obj is not None and animates(a, obj, bones) else 0 for a in actions]
        return flags, []


class MLD_PT_export(bpy.types.Panel):
    bl_label = "Game Engine Export"
    bl_idname = "MLD_PT_export"
    bl_parent_id = "MLD_PT_generate"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "MLD"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        settings = getattr(context.scene, "mld_export", None)
        if settings is None:
            return
        layout.template_list("MLD_UL_export_actions", "", bpy.data, "actions", settings, "index", rows=4)
        row = layout.row(align=True)
        for fmt in ee.FORMATS:
            row.prop(settings, fmt, toggle=True)
        layout.prop(settings, "one_file")
        layout.prop(settings, "root_motion")
        sub = layout.row()
        sub.enabled = settings.root_motion != "object"
        sub.prop(settings, "yaw")
        layout.prop(settings, "bone_names")
        layout.prop(settings, "folder")
        layout.prop(settings, "overwrite")
        layout.operator("mld.export_takes", icon="EXPORT")


classes = (MLD_ExportSettings, MLD_OT_export_takes, MLD_UL_export_actions, MLD_PT_export)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.mld_export = PointerProperty(type=MLD_ExportSettings)
    bpy.types.Action.mld_export = BoolProperty(name="Export", default=False,
                                               description="Export this take (Game Engine Export)")


def unregister():
    del bpy.types.Action.mld_export
    del bpy.types.Scene.mld_export
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
