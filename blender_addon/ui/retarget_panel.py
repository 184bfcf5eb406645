"""The Retarget sub-panel: the target armature's bone map and how keys are written (bpy).

The per-armature bone map is stored on the armature **Object** as ``obj.mld_retarget`` (saved in the .blend):
``rows``, one ``(joint, bone)`` row per canonical joint in skeleton order (bone '' = unmapped; ``required``
marks the joints Generate cannot do without), and ``extras``, a JSON string with the map's source (preset name,
"auto", "file" ...), parent overrides and pose properties (Rigify's IK/FK switches). With no row filled in the
armature uses the detected map (cached per set of bone names). ``key_takes.bone_map_of(obj)`` reads it.

Operators are adapters over plain functions: ``do_detect(obj)``, ``do_save_map(obj, path)``,
``do_load_map(obj, path)``, ``do_clear_map(obj)``, ``do_export_actions(obj, folder)``, each returning
``(level, message)``.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, CollectionProperty, IntProperty, PointerProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from mld_core.rig import bone_maps
from mld_core.rig.bone_map_rows import map_extras, map_to_rows
from mld_core.rig.keying import detections, map_problem

from ..scene import canonical_armature, key_takes


# -- data -------------------------------------------------------------------------------------------------------
class MLD_BoneMapRow(bpy.types.PropertyGroup):
    joint: StringProperty(name="Joint", description="Joint of the model's skeleton")
    bone: StringProperty(name="Bone", description="The armature's bone whose head sits on this joint (empty: none)")
    required: BoolProperty(name="Required", description="Generate needs a bone for this joint")


class MLD_RetargetMap(bpy.types.PropertyGroup):
    rows: CollectionProperty(type=MLD_BoneMapRow)
    index: IntProperty(name="Active Row", default=0)
    extras: StringProperty(name="Map Extras", description="Source, parent overrides and pose properties (JSON)")


# -- plain functions --------------------------------------------------------------------------------------------
def store_map(obj, bone_map: bone_maps.BoneMap) -> None:
    """Write ``bone_map`` onto ``obj.mld_retarget`` (all 22 rows)."""
    data = obj.mld_retarget
    data.rows.clear()
    for row in map_to_rows(bone_map):
        item = data.rows.add()
        item.joint, item.bone, item.required = row.joint, row.bone, row.required
    data.extras = map_extras(bone_map)
    data.index = min(data.index, len(data.rows) - 1) if len(data.rows) else 0


def do_clear_map(obj) -> tuple[str, str]:
    obj.mld_retarget.rows.clear()
    obj.mld_retarget.extras = ""
    return "INFO", f"{obj.name}: bone map cleared (the detected map is used)"


def do_detect(obj) -> tuple[str, str]:
    """Fill the armature's map from detection; the message names the preset found and what is missing."""
    if obj is None or obj.type != "ARMATURE":
        return "ERROR", "Pick an armature first"
    detection = detections.get(obj.data.bones.keys(), key_takes.rig_parents(obj))
    store_map(obj, detection.bone_map)
    mapped = len(detection.bone_map.joints)
    text = f"{obj.name}: detected '{detection.source}', {mapped} of 22 joints mapped"
    if detection.missing:
        return "WARNING", f"{text}; no bone for the required joints {', '.join(detection.missing)}: pick them in the list"
    return "INFO", text


def do_save_map(obj, path: str) -> tuple[str, str]:
    """Save the armature's map (stored, else detected) as JSON (temporary file, then renamed)."""
    if obj is None or obj.type != "ARMATURE":
        return "ERROR", "Pick an armature first"
    bone_map = key_takes.bone_map_of(obj)
    try:
        bone_map.save(path)
    except OSError as exc:
        return "ERROR", f"Could not write {path}: {exc.strerror or exc}"
    return "INFO", f"Saved the bone map of {obj.name} ({len(bone_map.joints)} joints) to {path}"


def do_load_map(obj, path: str) -> tuple[str, str]:
    """Load a JSON map onto the armature; a bad file changes nothing and says why."""
    if obj is None or obj.type != "ARMATURE":
        return "ERROR", "Pick an armature first"
    try:
        bone_map = bone_maps.BoneMap.load(path)
    except FileNotFoundError:
        return "ERROR", f"No such file: {path}; the bone map is unchanged"
    except (bone_maps.BoneMapError, OSError, UnicodeDecodeError, TypeError, ValueError, AttributeError) as exc:
        return "ERROR", f"Not a bone map: {path}: {exc}; the bone map is unchanged"
    names = set(obj.data.bones.keys())
    if bone_map.joints and not any(b in names for b in bone_map.joints.values()):
        return "ERROR", f"None of the bones in {path} are in {obj.name}; the bone map is unchanged"
    present = bone_maps.BoneMap(
        {j: b for j, b in bone_map.joints.items() if b in names}, source="file",
        parent_overrides=bone_map.parent_overrides, pose_properties=bone_map.pose_properties,
        ik_controls=[c for c in bone_map.ik_controls if all(b in names for b in bone_maps.chain_bones(c))],
    )
    absent = sorted(j for j, b in bone_map.joints.items() if b not in names)
    store_map(obj, present)
    problem = map_problem(present, names, obj.name)
    if absent or problem:
        extra = f" (bones not in the armature were left empty: {', '.join(absent)})" if absent else ""
        return "WARNING", f"Loaded {path}{extra}. {problem}".strip()
    return "INFO", f"Loaded the bone map {path} onto {obj.name}"


def _target(context):
    from .operators import resolve_target

    return resolve_target(context)


def _poll_armature(cls, context) -> bool:
    if getattr(context.scene, "mld_motion", None) is None:
        cls.poll_message_set("The add-on is not registered for this scene")
        return False
    if _target(context) is None:
        cls.poll_message_set("Pick an armature first")
        return False
    return True


# -- operators ----------------------------------------------------------------------------------------------------
class MLD_OT_detect_bone_map(bpy.types.Operator):
    """Fill the armature's bone map from its bone names and hierarchy (presets: Rigify, Mixamo, BVH ...)"""

    bl_idname = "mld.detect_bone_map"
    bl_label = "Detect"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _poll_armature(cls, context)

    def execute(self, context):
        level, message = do_detect(_target(context))
        self.report({level}, message)
        return {"FINISHED"} if level != "ERROR" else {"CANCELLED"}


class MLD_OT_clear_bone_map(bpy.types.Operator):
    """Forget the stored bone map (Generate then uses the detected one)"""

    bl_idname = "mld.clear_bone_map"
    bl_label = "Clear"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _poll_armature(cls, context)

    def execute(self, context):
        level, message = do_clear_map(_target(context))
        self.report({level}, message)
        return {"FINISHED"}


class MLD_OT_save_bone_map(bpy.types.Operator, ExportHelper):
    """Save the armature's bone map as a JSON file"""

    bl_idname = "mld.save_bone_map"
    bl_label = "Save Map..."
    bl_options = {"REGISTER"}

    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return _poll_armature(cls, context)

    def execute(self, context):
        level, message = do_save_map(_target(context), self.filepath)
        self.report({level}, message)
        return {"FINISHED"} if level != "ERROR" else {"CANCELLED"}


class MLD_OT_load_bone_map(bpy.types.Operator, ImportHelper):
    """Load a bone map (JSON, from Save Map... or a preset) onto the armature"""

    bl_idname = "mld.load_bone_map"
    bl_label = "Load Map..."
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return _poll_armature(cls, context)

    def execute(self, context):
        level, message = do_load_map(_target(context), self.filepath)
        self.report({level}, message)
        return {"FINISHED"} if level != "ERROR" else {"CANCELLED"}


def do_export_actions(obj, folder: str, name_filter: str = "") -> tuple[str, str]:
    """Every Action that keys ``obj``'s mapped bones (whose name contains ``name_filter``), through the bone map, as
    BVH files + captions.csv in ``folder`` for ``data prepare bvh``. Captions: the Action's 'mld_caption' property
    (one per line), else its name in words."""
    from mld_core.data.action_export import CAPTION_PROPERTY, Take, export_takes
    from mld_core.inputs import InputError

    from ..scene.action_joints import action_joints, animates

    if not folder:
        return "ERROR", "Choose a folder to export to"
    scene = bpy.context.scene
    bone_map = key_takes.bone_map_of(obj).joints
    fps = scene.render.fps / (scene.render.fps_base or 1.0)
    actions = [a for a in bpy.data.actions if name_filter.lower() in a.name.lower() and animates(a, obj, bone_map)]
    if not actions:
        return "ERROR", f"No Action keys the mapped bones of {obj.name}" + (f" with '{name_filter}' in its name"
                                                                            if name_filter else "")
    takes = [Take(a.name, action_joints(obj, a, scene, bone_map), fps,
                  str(a.get(CAPTION_PROPERTY, "")).splitlines()) for a in actions]
    try:
        result = export_takes(takes, bpy.path.abspath(folder))
    except InputError as exc:
        return "ERROR", str(exc)
    skipped = "; ".join(f"{k}: {v}" for k, v in result["skipped"].items())
    message = f"Exported {len(result['written'])} Actions to {folder} (captions.csv beside them)"
    return ("WARNING", f"{message}; skipped {skipped}") if skipped else ("INFO", message)


class MLD_OT_export_actions(bpy.types.Operator):
    """Write the armature's Actions, through its bone map, as BVH files with a captions.csv, ready for
    'python -m mld_core data prepare bvh FOLDER --captions FOLDER/captions.csv'"""

    bl_idname = "mld.export_actions"
    bl_label = "Export Actions as Training Data..."
    bl_options = {"REGISTER"}

    directory: StringProperty(subtype="DIR_PATH")
    name_filter: StringProperty(name="Name Contains", description="Only Actions whose name contains this text")

    @classmethod
    def poll(cls, context):
        return _poll_armature(cls, context)

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        level, message = do_export_actions(_target(context), self.directory, self.name_filter)
        self.report({level}, message)
        return {"FINISHED"} if level != "ERROR" else {"CANCELLED"}


# -- UI ------------------------------------------------------------------------------------------------------------
class MLD_UL_bone_map(bpy.types.UIList):
    """Canonical joint -> bone (required joints marked *), the bone picked from the armature's bones."""

    bl_idname = "MLD_UL_bone_map"

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        obj = data.id_data
        split = layout.split(factor=0.45)
        missing = item.required and not item.bone
        split.label(text=item.joint + (" *" if item.required else ""), icon="ERROR" if missing else "BLANK1")
        if obj is not None and obj.type == "ARMATURE":
            split.prop_search(item, "bone", obj.data, "bones", text="")
        else:
            split.label(text=item.bone)


class MLD_PT_retarget(bpy.types.Panel):
    bl_label = "Retarget"
    bl_idname = "MLD_PT_retarget"
    bl_parent_id = "MLD_PT_generate"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "MLD"

    def draw(self, context):
        from .panels import _wrap

        layout = self.layout
        settings = getattr(context.scene, "mld_motion", None)
        if settings is None:
            return
        obj = _target(context)
        if obj is None:
            layout.label(text="Pick an armature to see its bone map", icon="INFO")
        elif canonical_armature.is_canonical(obj):
            layout.label(text="Canonical armature: no map needed", icon="CHECKMARK")
        else:
            data = obj.mld_retarget
            stored = any(row.bone for row in data.rows)
            bone_map = key_takes.bone_map_of(obj)
            source = bone_map.source if stored else f"detected: {bone_map.source}"
            layout.label(text=f"Bone map ({source})", icon="GROUP_BONE")
            problem = map_problem(bone_map, obj.data.bones.keys(), "")
            if problem:
                box = layout.box()
                box.alert = True
                for index, line in enumerate(_wrap(problem, 48)):
                    box.label(text=line, icon="ERROR" if index == 0 else "BLANK1")
            row = layout.row(align=True)
            row.operator("mld.detect_bone_map", icon="VIEWZOOM")
            row.operator("mld.clear_bone_map", icon="X")
            if len(data.rows):
                layout.template_list("MLD_UL_bone_map", "", data, "rows", data, "index", rows=6)
                layout.label(text="* required joint", icon="BLANK1")
            else:
                layout.label(text="Press Detect to edit the map", icon="INFO")
            row = layout.row(align=True)
            row.operator("mld.save_bone_map", icon="EXPORT")
            row.operator("mld.load_bone_map", icon="IMPORT")
        if obj is not None:
            layout.operator("mld.export_actions", icon="EXPORT")

        col = layout.column(align=True)
        row = col.row(align=True)
        row.prop(settings, "reduce_keys", toggle=True)
        sub = row.row(align=True)
        sub.enabled = settings.reduce_keys
        sub.prop(settings, "reduce_tolerance", text="Tol.")
        col.prop(settings, "rotation_mode")
        col.prop(settings, "match")
        row = col.row(align=True)
        row.prop(settings, "foot_lock", toggle=True)
        row.prop(settings, "push_nla", toggle=True)
        if settings.last_reduction < 1.0 and settings.last_frames:
            layout.label(text=f"Last take: {settings.last_reduction:.0%} of the keys kept", icon="KEYFRAME")


classes = (
    MLD_BoneMapRow,
    MLD_RetargetMap,
    MLD_OT_detect_bone_map,
    MLD_OT_clear_bone_map,
    MLD_OT_save_bone_map,
    MLD_OT_load_bone_map,
    MLD_OT_export_actions,
    MLD_UL_bone_map,
    MLD_PT_retarget,
)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Object.mld_retarget = PointerProperty(type=MLD_RetargetMap)


def unregister():
    del bpy.types.Object.mld_retarget
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
